"""Training M submaps at once: stacked fields, one shared pose row per keyframe, sharded over a device mesh.

params = {"fields": <Flax params of DensityField, every leaf stacked [M, ...]>, "poses": [S, 6]}.
The pose of keyframe s in submap m is T_init_m[slot] @ Exp((rho_factor[m] rho_s, omega_s)) in submap m's
normalised frame (neld_jax.submaps, docs/method.md "Submaps"). One step vmaps the single-cube step's pieces
(train.sample_batch, model.world_rays / render_rays, train.ray_losses) over the submaps, each drawing its batch
from its own rays, and sums the losses: a keyframe in two submaps gathers its row twice, so its gradient is the
sum of both submaps' contributions and it gets one update.

Sharding (docs/design.md "Submaps and devices"): a 1-D `jax.sharding.Mesh` over the axis "submaps"; the stacked
field params, their optimiser state, the rays and the frames are split along M (NamedSharding P("submaps")),
the poses and everything else replicated. The step is jitted on those shardings and XLA inserts the all-reduce
of the pose gradient (the gather of replicated poses by sharded submaps transposes to a cross-device sum).
The same code runs on 1 CPU, 1 GPU or several devices; only the mesh changes.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from neld_jax import lie, rendering
from neld_jax.errors import ConfigError
from neld_jax.field import DensityField
from neld_jax.model import SamplerSettings, render_rays, world_rays
from neld_jax.train import (FitResult, LossSettings, RayData, Schedules, TrainState, jit_chunk, make_field,
                            make_schedules, pose_transform, range_errors_m, ray_losses, run_chunks, sample_batch,
                            sampler_settings, with_steps)

logger = logging.getLogger(__name__)


AXIS = "submaps"


class SubmapRays(NamedTuple):
    """Each submap's training rays, stacked: directions [M, R, 3], ranges [M, R] (submap-normalised), scan_index
    [M, R] local slot, scan_start / scan_count [M, W], num_rays [M] (rays beyond it are padding)."""

    directions: jax.Array
    ranges: jax.Array
    scan_index: jax.Array
    scan_start: jax.Array
    scan_count: jax.Array
    num_rays: jax.Array


class SubmapFrames(NamedTuple):
    """T_init [M, W, 4, 4] submap-normalised; scan_global [M, W] row of the shared poses; scale [M] metres ->
    submap units; rho_factor [M] = s_m / s_ref; weight [M] (0: a padding submap)."""

    T_init: jax.Array
    scan_global: jax.Array
    scale: jax.Array
    rho_factor: jax.Array
    weight: jax.Array


def from_arrays(arrays) -> tuple[SubmapRays, SubmapFrames]:
    """neld_jax.submaps.SubmapArrays (numpy) -> (SubmapRays, SubmapFrames) of jax arrays (not yet placed)."""
    a = arrays
    rays = SubmapRays(jnp.asarray(a.directions), jnp.asarray(a.ranges), jnp.asarray(a.scan_index),
                      jnp.asarray(a.scan_start), jnp.asarray(a.scan_count), jnp.asarray(a.num_rays))
    frames = SubmapFrames(jnp.asarray(a.T_init), jnp.asarray(a.scan_global), jnp.asarray(a.scale),
                          jnp.asarray(a.rho_factor), jnp.asarray(a.weight))
    return rays, frames


# ------------------------------------------------------------------------------------------------ mesh


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh over the first num_devices devices (all when None), axis "submaps".

    Several hosts: call `jax.distributed.initialize()` in every process before anything else touches jax (see
    README, "Several devices and hosts"); jax.devices() then lists every host's devices and this mesh spans them."""
    devices = jax.devices()
    n = len(devices) if num_devices is None else int(num_devices)
    return Mesh(np.asarray(devices[:n]), (AXIS,))


def _spec_of(path, leaf) -> P:
    """P("submaps") for leaves under a "fields" key (params, Adam moments), replicated otherwise."""
    under_fields = any(isinstance(k, jax.tree_util.DictKey) and k.key == "fields" for k in path)
    return P(AXIS) if under_fields and getattr(leaf, "ndim", 0) >= 1 else P()


def state_sharding(state: TrainState, mesh: Mesh):
    """NamedSharding tree of a submap TrainState: fields and their optimiser moments split over M."""
    return jax.tree_util.tree_map_with_path(lambda p, x: NamedSharding(mesh, _spec_of(p, x)), state)


def data_sharding(tree, mesh: Mesh):
    """NamedSharding tree for SubmapRays / SubmapFrames: every leaf split along its leading (submap) axis."""
    return jax.tree.map(lambda _: NamedSharding(mesh, P(AXIS)), tree)


def place(tree, sharding):
    return jax.device_put(tree, sharding)


# ------------------------------------------------------------------------------------------------ optimiser


def make_submap_optimizer(config: ml_collections.ConfigDict, schedules: Schedules, num_scans: int,
                          start_poses: np.ndarray | None = None) -> optax.GradientTransformation:
    """train.make_optimizer's transform for {"fields", "poses"}: Adam with the field decay on every stacked field
    leaf (element-wise, so each submap's field has its own moments), the pose chain (Adam, translation / rotation
    schedules, train.fixed_scans rows zeroed) on the one [S, 6] pose array, and with train.keep_start_scale the
    pose steps kept off the trajectory's scale mode, which needs start_poses [S, 4, 4] (the keyframes' start poses,
    world, metres).

    The shared row is a right correction in the world too: submap m's normalisation x -> s_m (x - o_m) keeps
    rotations and scales translations by s_m, so its pose T_init_m[slot] @ Exp((s_m / s_ref rho, omega)) is, back in
    the world, exactly T_s @ Exp((rho / s_ref, omega)) whichever submap holds the scan (neld_jax.submaps;
    test_shared_pose_maps_exactly_into_each_submap_frame). rho has one unit over every submap, and the scan moves
    by R_s rho_s / s_ref to first order: train.scale_direction's right-correction form, a_s = [R_s^T (p_s - c), 0]."""
    positions = rotations = None
    if start_poses is not None:
        T = np.asarray(start_poses, np.float64)
        positions, rotations = T[:, :3, 3], T[:, :3, :3]
    pose_tx = pose_transform(config, schedules, num_scans, positions, rotations)

    def labels(params):
        return {"fields": jax.tree.map(lambda _: "fields", params["fields"]), "poses": "poses"}

    return optax.multi_transform({"fields": optax.adam(schedules.field_lr), "poses": pose_tx},
                                 labels)


# ------------------------------------------------------------------------------------------------ the step


def submap_scan_poses(poses: jax.Array, T_init: jax.Array, scan_global: jax.Array, rho_factor) -> jax.Array:
    """One submap's keyframe poses in its frame: poses [S, 6] shared, T_init [W, 4, 4], scan_global [W],
    rho_factor scalar -> [W, 4, 4] = T_init @ Exp((rho_factor rho, omega))."""
    xi = poses[scan_global]
    xi = jnp.concatenate([xi[:, :3] * rho_factor, xi[:, 3:]], axis=1)
    return lie.compose(T_init, lie.se3_exp(xi))


def scaled_sampler(sampler_m: SamplerSettings, scale) -> SamplerSettings:
    """A sampler in metres (train.sampler_settings with scale 1) in one submap's units; `scale` may be traced."""
    return dataclasses.replace(sampler_m, z_low=sampler_m.z_low * scale, z_up=sampler_m.z_up * scale,
                               guided_width=sampler_m.guided_width * scale)


def _sample_submap(key, rays_m: SubmapRays, batch_rays: int, scans_per_step: int) -> jax.Array:
    """Ray indices [batch_rays] of one submap: train.sample_batch over its W scans, or uniform over its
    num_rays real rays (the padding beyond is never drawn)."""
    if scans_per_step > 0:
        data = RayData(rays_m.directions, rays_m.ranges, rays_m.scan_index, rays_m.scan_start, rays_m.scan_count)
        return sample_batch(key, data, batch_rays, scans_per_step)
    return jax.random.randint(key, (batch_rays,), 0, jnp.maximum(rays_m.num_rays, 1))


def make_submap_loss(field: DensityField, loss: LossSettings, batch_rays: int, scans_per_step: int = 0):
    """loss_fn(params, rays, frames, key, alpha, sampler) -> (total, per-submap metrics {name: [M]}).

    total = sum over submaps of weight[m] * (eq. 13 of submap m's batch of batch_rays rays); each submap draws
    from its own rays with its own key (split from `key`). A keyframe in two submaps is gathered by both, so
    d total / d poses[s] is the sum of their contributions."""

    def submap_loss(field_params, poses, rays_m, frames_m, kb, kr, alpha, sampler):
        idx = _sample_submap(kb, rays_m, batch_rays, scans_per_step)
        d, ranges, slot = rays_m.directions[idx], rays_m.ranges[idx], rays_m.scan_index[idx]
        T = submap_scan_poses(poses, frames_m.T_init, frames_m.scan_global, frames_m.rho_factor)[slot]
        origins, directions = world_rays(T, d)
        out = render_rays(field_params, field, scaled_sampler(sampler, frames_m.scale), origins, directions,
                          alpha, kr, ranges)
        total, metrics = ray_losses(out, ranges, loss)
        metrics.update(range_errors_m(metrics, frames_m.scale))
        return total * frames_m.weight, metrics

    def loss_fn(params, rays: SubmapRays, frames: SubmapFrames, key, alpha, sampler: SamplerSettings):
        m = frames.weight.shape[0]
        key_batch, key_render = jax.random.split(key)
        keys_batch, keys_render = jax.random.split(key_batch, m), jax.random.split(key_render, m)
        totals, metrics = jax.vmap(submap_loss, in_axes=(0, None, 0, 0, 0, 0, None, None))(
            params["fields"], params["poses"], rays, frames, keys_batch, keys_render, alpha, sampler)
        return jnp.sum(totals), metrics

    return loss_fn


def make_submap_step_body(tx: optax.GradientTransformation, schedules: Schedules, field: DensityField,
                          loss: LossSettings, batch_rays: int, scans_per_step: int = 0, state_sharding=None):
    """step(state, rays: SubmapRays, frames: SubmapFrames, sampler) -> (state, metrics), not jitted.

    batch_rays rays per submap per step. sampler: train.sampler_settings(config, 1.0, ...) (metres), converted
    into each submap's units inside. With state_sharding the new state is constrained to it (under jit), so that
    the step's output lives where its input did. Metrics are the weight-averaged per-submap values."""
    loss_fn = make_submap_loss(field, loss, batch_rays, scans_per_step)

    def step(state: TrainState, rays: SubmapRays, frames: SubmapFrames, sampler: SamplerSettings):
        key, key_loss = jax.random.split(state.key)
        alpha = schedules.alpha(state.step)
        (_, per_submap), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, rays, frames, key_loss,
                                                                           alpha, sampler)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        w = frames.weight / jnp.sum(frames.weight)
        metrics = {k: jnp.sum(v * w) for k, v in per_submap.items()}
        metrics.update(alpha=alpha, pose_grad_norm=jnp.linalg.norm(grads["poses"]))
        new_state = TrainState(step=state.step + 1, params=params, opt_state=opt_state, key=key)
        if state_sharding is not None:
            new_state = jax.lax.with_sharding_constraint(new_state, state_sharding)
        return new_state, metrics

    return step


def make_submap_train_step(body: Callable):
    """The jitted step (sampler static, state donated); it follows its inputs' shardings (place() them first)."""
    return jax.jit(body, static_argnames=("sampler",), donate_argnums=(0,))


# ------------------------------------------------------------------------------------------------ setup


class SubmapSetup(NamedTuple):
    state: TrainState
    tx: optax.GradientTransformation
    schedules: Schedules
    step_body: Callable  # unjitted: step_body(state, rays, frames, sampler) -> (state, metrics)
    step_fn: Callable  # jitted step_body
    field: DensityField
    sampler: Callable[[int], SamplerSettings]  # sampler(step), in metres
    mesh: Mesh | None
    sharding: Any  # the state's NamedSharding tree, or None
    chunk_fn: Callable | None = None  # train.jit_chunk(step_body): chunk(state, rays, frames, sampler, num_steps)
    start_poses: np.ndarray | None = None  # [S, 4, 4] world: the start train.keep_start_scale holds the scale of


MIN_SUBMAP_BATCH_RAYS = 8


def submap_batch_rays(config: ml_collections.ConfigDict, num_submaps: int) -> int:
    """Rays each of the M submaps (padding ones included: they cost as much) draws per step: submaps.batch_rays,
    or when that is 0 the step's rays (train.batch_rays x submaps.step_rays_factor) shared among them, at least
    MIN_SUBMAP_BATCH_RAYS each. A step then costs about the same however the sequence is split, so a budget's
    steps take about the time they take on one cube (a 600 m route's 13 submaps at the cpu budget's 512 rays each
    were 13x the single cube's rays); the cpu budget's narrower submap fields (submaps.width) draw three times the
    single cube's rays for 1.3-1.4x its step. The floor matters only for hundreds of small submaps, which the cpu
    budget avoids (submaps.max_submaps: Riverside02's 0.25 m rule alone made 340, 8 rays each)."""
    explicit = int(config.submaps.get("batch_rays", 0))
    if explicit > 0:
        return explicit
    step_rays = int(round(int(config.train.batch_rays) * float(config.submaps.get("step_rays_factor", 1.0))))
    return max(step_rays // max(int(num_submaps), 1), MIN_SUBMAP_BATCH_RAYS)


def submap_loss_settings(config: ml_collections.ConfigDict) -> LossSettings:
    """config.loss's weights, with submaps.lambda_termination as the termination loss's weight when that is set
    (0: loss.lambda_termination)."""
    loss = LossSettings.from_config(config.loss)
    weight = float(config.submaps.get("lambda_termination", 0.0))
    return dataclasses.replace(loss, lambda_termination=weight) if weight > 0 else loss


def make_submap_field(config: ml_collections.ConfigDict) -> DensityField:
    """Each submap's field: config.model's, with submaps.width as its width when that is set (0: model.width)."""
    width = int(config.submaps.get("width", 0))
    field = make_field(config)
    return field.clone(width=width) if width > 0 else field


def submap_field_lr_factor(config: ml_collections.ConfigDict) -> float:
    """The factor on train.field_lr_* for the submap fields of a plan of train.steps steps: f from N steps on under
    submaps.field_lr_from_steps = (N, f), else 1 (also when it is ())."""
    rule = tuple(config.submaps.get("field_lr_from_steps", ()))
    if not rule:
        return 1.0
    if len(rule) != 2 or not (rule[0] > 0 and rule[1] > 0):
        raise ConfigError(f"submaps.field_lr_from_steps={rule}: expected () or (N, f), a step count N > 0 and a "
                          "factor f > 0")
    steps, factor = rule
    return float(factor) if int(config.train.steps) >= steps else 1.0


def submap_schedules(config: ml_collections.ConfigDict) -> Schedules:
    """train.make_schedules with the submap fields' learning rate (`submap_field_lr_factor` of the planned steps:
    a schedule compressed to fewer steps takes the rate of those)."""
    schedules = make_schedules(config)
    factor = submap_field_lr_factor(config)
    if factor == 1.0:
        return schedules
    base = schedules.field_lr
    return dataclasses.replace(schedules, field_lr=lambda step: factor * base(step))


def create_submap_state(config: ml_collections.ConfigDict, num_scans: int, num_submaps: int,
                        mesh: Mesh | None = None, start_poses: np.ndarray | None = None) -> SubmapSetup:
    """State, optimiser, schedules and step of M submaps over S keyframes (seeded by config.seed).

    Submap m's field is initialised from key m of config.seed's split. With a mesh, the state is placed on it.
    start_poses: [S, 4, 4] the keyframes' start poses (world, metres), which train.keep_start_scale needs
    (`make_submap_optimizer`); the state's structure does not depend on them."""
    schedules = submap_schedules(config)
    tx = make_submap_optimizer(config, schedules, num_scans, start_poses)
    field = make_submap_field(config)
    key_init, key_state = jax.random.split(jax.random.PRNGKey(int(config.seed)))
    # Jitted: a vmapped init run op by op takes seconds.
    fields = jax.jit(jax.vmap(lambda k: field.init(k, jnp.zeros((1, 3)), jnp.zeros((1, 3)))["params"]))(
        jax.random.split(key_init, num_submaps))
    params = {"fields": fields, "poses": jnp.zeros((num_scans, 6), jnp.float32)}
    state = TrainState(step=jnp.zeros([], jnp.int32), params=params, opt_state=tx.init(params), key=key_state)
    sharding = None
    if mesh is not None:
        sharding = state_sharding(state, mesh)
        state = place(state, sharding)
    batch = submap_batch_rays(config, num_submaps)
    body = make_submap_step_body(tx, schedules, field, submap_loss_settings(config), batch,
                                 int(config.train.get("scans_per_step", 0)), sharding)

    def sampler(step: int) -> SamplerSettings:
        return sampler_settings(config, 1.0, *schedules.samples(step))

    return SubmapSetup(state, tx, schedules, body, make_submap_train_step(body), field, sampler, mesh, sharding,
                       jit_chunk(body), start_poses)


# ------------------------------------------------------------------------------------------------ the loop


def fit_submaps(config: ml_collections.ConfigDict, setup: SubmapSetup, rays: SubmapRays, frames: SubmapFrames,
                ref_scale: float, state: TrainState | None = None,
                checkpoint_fn: Callable[[TrainState, list, float], None] | None = None, progress: bool = True,
                history: list | None = None, elapsed_s: float = 0.0, max_seconds: float | None = None) -> FitResult:
    """train.fit for submaps: the same loop (train.run_chunks: fused chunks, logging, checkpoints,
    train.max_minutes and the schedule compressed to fit it) over the submaps' step.

    rays, frames: placed on setup.mesh (data_sharding) when there is one; ref_scale: s_ref (the logs in metres)."""
    from neld_jax.submaps import body_correction_matrices

    def chunk_of(built: SubmapSetup) -> Callable:  # run_chunks' chunk(state, sampler, num_steps) over this data
        return lambda s, sampler, num_steps: built.chunk_fn(s, rays, frames, sampler, num_steps=num_steps)

    def log(s: TrainState, m: dict) -> dict:
        xi = np.asarray(s.params["poses"])
        C = body_correction_matrices(xi, ref_scale)
        return {"pose_trans_mean_m": float(np.linalg.norm(C[:, :3, 3], axis=1).mean()),
                "pose_rot_mean_deg": float(np.degrees(np.linalg.norm(xi[:, 3:], axis=1)).mean())}

    num_submaps = int(frames.weight.shape[0])  # padding submaps draw rays too
    rays_per_step = submap_batch_rays(config, num_submaps) * num_submaps

    def replan(steps: int):
        planned = create_submap_state(with_steps(config, steps), int(setup.state.params["poses"].shape[0]),
                                      num_submaps, setup.mesh, setup.start_poses)
        if planned.schedules.field_lr(0) != setup.schedules.field_lr(0):  # submaps.field_lr_from_steps
            logger.info("the submap fields' learning rate follows the plan of %d steps: %g -> %g", steps,
                        float(planned.schedules.field_lr(0)), float(planned.schedules.field_lr(steps)))
        return planned.schedules, planned.sampler, chunk_of(planned)

    return run_chunks(config, setup.schedules, setup.sampler, chunk_of(setup), setup.state if state is None else state,
                      log, rays_per_step, checkpoint_fn, progress, history, elapsed_s, max_seconds, replan)


# ------------------------------------------------------------------------------------------------ mapping


def _render_points_impl(params_field, field, sampler_m, scale, T_rays, directions_local, alpha):
    origins, directions = world_rays(T_rays, directions_local)
    out = render_rays(params_field, field, scaled_sampler(sampler_m, scale), origins, directions, alpha)
    rendered, z = (out.coarse, out.z_coarse) if out.fine is None else (out.fine, out.z_fine)
    z_map = rendering.map_range(rendered.weights, rendered.deltas, z)
    return origins + z_map[:, None] * directions, rendered.opacity


_render_points = jax.jit(_render_points_impl, static_argnames=("field", "sampler_m"))


def render_submap_rays(params_field, field: DensityField, sampler_m: SamplerSettings, scale: float,
                       T_scans: np.ndarray, directions_local: np.ndarray, scan_slot: np.ndarray, alpha: float,
                       rays_per_batch: int) -> tuple[np.ndarray, np.ndarray]:
    """Map points of one submap's rays (eq. 14), in its normalised frame: T_scans [W, 4, 4] submap-normalised,
    directions_local [R, 3], scan_slot [R] -> (points [R, 3], opacity [R]) for every ray. The scale is traced,
    so the renderer compiles once for all submaps; batches are padded to one size."""
    T = jnp.asarray(T_scans, jnp.float32)
    r = len(directions_local)
    points, opacity = np.zeros((r, 3)), np.zeros(r)
    for start in range(0, r, rays_per_batch):
        stop = min(start + rays_per_batch, r)
        pad = rays_per_batch - (stop - start)
        d = np.pad(directions_local[start:stop], ((0, pad), (0, 0)), mode="edge")
        s = np.pad(scan_slot[start:stop], (0, pad), mode="edge")
        p, o = _render_points(params_field, field, sampler_m, jnp.float32(scale), T[s], jnp.asarray(d, jnp.float32),
                              jnp.float32(alpha))
        points[start:stop], opacity[start:stop] = np.asarray(p)[: stop - start], np.asarray(o)[: stop - start]
    return points, opacity
