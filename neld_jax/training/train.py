"""Training: the one parameter pytree, its optimiser and schedules, the jitted step and the loop.

    params = {"fields": <Flax params of DensityField, every leaf stacked [M, ...]>, "poses": [S, 6]}

M cubes ("submaps"; one cube is a plan of M = 1) over S keyframes. Keyframe s has one pose row, shared by every
cube that holds it: in cube m its pose is T_init_m[slot] @ Exp((rho_factor[m] rho_s, omega_s)), a right correction
in the scan's body frame (model.corrected_poses; docs/method.md, "Poses").

The optimiser is one optax transform over that pytree, partitioned by label: the fields get Adam with their own
exponential decay (each cube its own moments, element-wise); the poses get `pose_transform` (a prior toward the
start, Adam, translation / rotation schedules that are exactly zero until the coarse-to-fine window activates
frequency k*, gauge-fixed rows zeroed, the trajectory's scale kept). The step vmaps one cube's loss over the M cubes,
each drawing its batch from its own rays, and sums them: a keyframe in two cubes gets the sum of both gradients and
one update. It is a pure function of (state, rays, frames, sampler) with no Python branching on traced values; the
sampler of the sample-count stage is its one static argument. `fit` runs train.log_every steps per device call in
a `lax.scan`.

Sharding (docs/design.md, "Devices"): a 1-D mesh over the axis "submaps"; the stacked fields, their Adam moments,
the rays and the frames are split along M, the poses replicated; XLA inserts the all-reduce of the pose gradient.
The same code runs on 1 CPU, 1 GPU or several devices.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Callable, NamedTuple

import flax
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from neld_jax.errors import ConfigError
from neld_jax.field import losses
from neld_jax.field.density import DensityField, field_from_config
from neld_jax.field.model import SamplerSettings, body_corrections, corrected_poses, in_units, render_rays, world_rays

logger = logging.getLogger(__name__)

AXIS = "submaps"
MIN_BATCH_RAYS = 8  # rays each cube draws per step, at least
GUIDED_WIDTH_M = 1.0  # range-guided coarse samples lie within this distance of the measured range


# ------------------------------------------------------------------------------------------------ data


class Rays(NamedTuple):
    """Each cube's training rays, stacked and padded to R: directions [M, R, 3] unit, sensor frame; ranges [M, R]
    in the cube's units; scan_index [M, R] the ray's slot (0..W-1) among the cube's keyframes; num_rays [M] (rays
    beyond it are padding and never drawn)."""

    directions: jax.Array
    ranges: jax.Array
    scan_index: jax.Array
    num_rays: jax.Array


class Frames(NamedTuple):
    """Each cube's frame: T_init [M, W, 4, 4] its keyframes' start poses in its normalised frame; scan_global [M, W]
    their rows of the shared poses; scale [M] metres -> cube units; rho_factor [M] scale / the reference scale;
    weight [M] (0: a padding cube that fills the devices)."""

    T_init: jax.Array
    scan_global: jax.Array
    scale: jax.Array
    rho_factor: jax.Array
    weight: jax.Array


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh over the first num_devices devices (all when None), axis "submaps". Several hosts: call
    `jax.distributed.initialize()` first; jax.devices() then lists every host's devices."""
    devices = jax.devices()
    n = len(devices) if num_devices is None else int(num_devices)
    return Mesh(np.asarray(devices[:n]), (AXIS,))


def _spec_of(path, leaf) -> P:
    """P("submaps") for leaves under a "fields" key (params, Adam moments), replicated otherwise."""
    under_fields = any(isinstance(k, jax.tree_util.DictKey) and k.key == "fields" for k in path)
    return P(AXIS) if under_fields and getattr(leaf, "ndim", 0) >= 1 else P()


def state_sharding(state, mesh: Mesh):
    """NamedSharding tree of a TrainState: the fields and their optimiser moments split over M."""
    return jax.tree_util.tree_map_with_path(lambda p, x: NamedSharding(mesh, _spec_of(p, x)), state)


def device_data(arrays, mesh: Mesh) -> tuple[Rays, Frames]:
    """neld_jax.training.submaps.SubmapArrays (numpy) -> (Rays, Frames) on the mesh, split along M."""
    a = arrays
    rays = Rays(jnp.asarray(a.directions), jnp.asarray(a.ranges), jnp.asarray(a.scan_index), jnp.asarray(a.num_rays))
    frames = Frames(
        jnp.asarray(a.T_init),
        jnp.asarray(a.scan_global),
        jnp.asarray(a.scale),
        jnp.asarray(a.rho_factor),
        jnp.asarray(a.weight),
    )
    split = NamedSharding(mesh, P(AXIS))
    return jax.device_put(rays, split), jax.device_put(frames, split)


# ------------------------------------------------------------------------------------------------ schedules


@flax.struct.dataclass
class TrainState:
    step: jax.Array  # scalar int32
    params: Any  # {"fields": ..., "poses": [S, 6]}
    opt_state: Any
    key: jax.Array


@dataclasses.dataclass(frozen=True)
class Schedules:
    """Step -> value functions of one plan of `total_steps`, shared by the optimiser, the step and the logs."""

    total_steps: int
    pos_freqs: int
    c2f_end_step: int
    pose_start_step: int
    stage_starts: tuple  # first step of each sample-count stage
    coarse_stages: tuple
    fine_stages: tuple
    field_lr: Callable
    pose_lr_trans: Callable
    pose_lr_rot: Callable

    def alpha(self, step):
        """Coarse-to-fine progress in [0, pos_freqs]; works on Python ints and traced scalars."""
        frac = jnp.clip(jnp.asarray(step, jnp.float32) / max(self.c2f_end_step, 1), 0.0, 1.0)
        return frac * self.pos_freqs

    def stage(self, step: int) -> int:
        return max(i for i, start in enumerate(self.stage_starts) if step >= start)

    def samples(self, step: int) -> tuple[int, int]:
        i = self.stage(step)
        return self.coarse_stages[i], self.fine_stages[i]


@dataclasses.dataclass(frozen=True)
class PoseSteps:
    """How the poses move: (init, final) learning rates of the translation and rotation columns, a Gaussian prior
    pulling each correction toward zero (weights on the translation and rotation columns, normalised units and
    radians; 0: none), and whether the trajectory's scale is kept (docs/method.md, "Keeping the start's scale").
    The config's own by default (`from_config`); the start policy (neld_jax.steps.start) sets them for a start from the
    classical baseline."""

    lr_trans: tuple = (5e-5, 2e-5)
    lr_rot: tuple = (5e-5, 2e-5)
    prior_trans: float = 0.0
    prior_rot: float = 0.0
    keep_scale: bool = False

    @classmethod
    def from_config(cls, config: ml_collections.ConfigDict) -> "PoseSteps":
        return cls.from_train(config.train)

    @classmethod
    def from_train(cls, train_cfg: ml_collections.ConfigDict) -> "PoseSteps":
        """The config's own pose steps (train_cfg: config.train, its pose_lr_*), no prior, the scale free."""
        t = train_cfg
        return cls(
            (float(t.pose_lr_trans_init), float(t.pose_lr_trans_final)),
            (float(t.pose_lr_rot_init), float(t.pose_lr_rot_final)),
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def make_schedules(
    config: ml_collections.ConfigDict,
    pose_steps: PoseSteps,
    total_steps: int | None = None,
    field_lr_factor: float = 1.0,
) -> Schedules:
    """The schedules of a plan of total_steps (None: train.steps): coarse-to-fine over train.c2f_end_fraction of
    them, the sample stages spread over the same span, the poses still until frequency k* is active."""
    t = config.train
    steps = int(t.steps if total_steps is None else total_steps)
    c2f_end = int(round(t.c2f_end_fraction * steps))
    L = int(config.model.pos_freqs)
    # Frequency k is fully on once alpha >= k + 1 and starts at alpha = k; the poses start when k* starts.
    pose_start = int(math.ceil(min(t.pose_start_freq, L) / L * c2f_end)) if L > 0 else 0
    coarse = tuple(int(n) for n in config.sampling.coarse_stages)
    fine = tuple(int(n) for n in config.sampling.fine_stages)
    if len(coarse) != len(fine) or not coarse:
        raise ValueError("sampling.coarse_stages and sampling.fine_stages must be non-empty and of equal length")
    n = len(coarse)
    starts = tuple(0 if n == 1 else int(round(i / (n - 1) * c2f_end)) for i in range(n))

    def decay(init, final, span):
        ratio = final / init if init > 0 else 1.0
        return optax.exponential_decay(init, transition_steps=max(span, 1), decay_rate=ratio)

    def delayed(init_final):
        # Exactly zero before pose_start: Adam's update is then exactly zero, so the poses stay put.
        init, final = init_final
        return optax.join_schedules(
            [optax.constant_schedule(0.0), decay(init, final, steps - pose_start)], boundaries=[pose_start]
        )

    field_lr = decay(field_lr_factor * float(t.field_lr_init), field_lr_factor * float(t.field_lr_final), steps)
    return Schedules(
        total_steps=steps,
        pos_freqs=L,
        c2f_end_step=c2f_end,
        pose_start_step=pose_start,
        stage_starts=starts,
        coarse_stages=coarse,
        fine_stages=fine,
        field_lr=field_lr,
        pose_lr_trans=delayed(pose_steps.lr_trans),
        pose_lr_rot=delayed(pose_steps.lr_rot),
    )


# ------------------------------------------------------------------------------------------------ optimiser


def scale_pose_columns(trans_lr: Callable, rot_lr: Callable) -> optax.GradientTransformation:
    """Descent step for [S, 6] pose updates: columns 0:3 (rho) by -trans_lr(count), 3:6 (omega) by -rot_lr."""

    def init_fn(params):
        del params
        return optax.ScaleByScheduleState(count=jnp.zeros([], jnp.int32))

    def update_fn(updates, state, params=None):
        del params
        lr = jnp.concatenate([jnp.full((3,), trans_lr(state.count)), jnp.full((3,), rot_lr(state.count))])
        updates = jax.tree.map(lambda u: -u * lr.astype(u.dtype), updates)
        return updates, optax.ScaleByScheduleState(count=optax.safe_increment(state.count))

    return optax.GradientTransformation(init_fn, update_fn)


def pose_prior(trans_weight: float, rot_weight: float) -> optax.GradientTransformation:
    """Add the gradient of a Gaussian prior at the start, w * xi, to [S, 6] pose gradients (w = trans_weight on
    columns 0:3, rot_weight on 3:6). Stateless."""
    w = jnp.asarray([trans_weight] * 3 + [rot_weight] * 3, jnp.float32)

    def update_fn(updates, state, params=None):
        if params is None:
            raise ValueError("pose_prior needs the poses (params) in update")
        return jax.tree.map(lambda u, p: u + w.astype(u.dtype) * p, updates, params), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update_fn)


def zero_rows(row_mask: np.ndarray) -> optax.GradientTransformation:
    """Zero the updates of the rows where row_mask [S] is True (gauge-fixed scans never move)."""
    keep = jnp.asarray(~np.asarray(row_mask, bool), jnp.float32)[:, None]
    return optax.stateless(lambda updates, params: jax.tree.map(lambda u: u * keep.astype(u.dtype), updates))


def scale_direction(start_poses: np.ndarray, movable: np.ndarray) -> np.ndarray:
    """The trajectory's scale mode in the [S, 6] right corrections: a [S, 6] float64 such that, to first order, the
    scale of the positions about their centroid c changes by a . xi (up to a positive factor; docs/method.md,
    "Keeping the start's scale"). A correction xi_s moves scan s by R_s rho_s (omega does not move its position to
    first order), and a similarity alignment measures the scale change sum_s (p_s - c) . d_s / sum |p_s - c|^2:
    a_s = [R_s^T (p_s - c), 0]. start_poses [S, 4, 4] (world); movable [S] bool (a is 0 on the other rows)."""
    T = np.asarray(start_poses, np.float64)
    p = T[:, :3, 3]
    a_rho = np.einsum("sji,sj->si", T[:, :3, :3], p - p.mean(axis=0))
    a = np.concatenate([a_rho, np.zeros_like(a_rho)], axis=1)
    return np.where(np.asarray(movable, bool)[:, None], a, 0.0)


def keep_off_direction(a: np.ndarray) -> optax.GradientTransformation:
    """Keep [S, 6] pose updates u off one direction a [S, 6] (nonzero on the translation columns only): u gets the
    multiple of a that makes a . u = 0. Linear, so a constraint a . xi = 0 met at xi = 0 holds after every step;
    stateless, so the optimiser state's structure does not depend on a."""
    a = np.asarray(a, np.float64)
    norm2 = max(float(np.sum(a**2)), 1e-30)
    a = jnp.asarray(a, jnp.float32)
    return optax.stateless(
        lambda updates, params: jax.tree.map(
            lambda u: u - (jnp.sum(u * a.astype(u.dtype)) / norm2) * a.astype(u.dtype), updates
        )
    )


def pose_transform(
    schedules: Schedules, pose_steps: PoseSteps, fixed: np.ndarray, start_poses: np.ndarray | None = None
) -> optax.GradientTransformation:
    """The [S, 6] poses' update: the prior's pull toward the start (before Adam, so that it is normalised with the
    data's gradient), Adam, the translation / rotation schedules, the fixed rows [S] zeroed, and with
    pose_steps.keep_scale the step kept off the trajectory's scale mode (last, so that it holds exactly), which
    needs start_poses [S, 4, 4] (world)."""
    prior = (
        [pose_prior(pose_steps.prior_trans, pose_steps.prior_rot)]
        if pose_steps.prior_trans or pose_steps.prior_rot
        else []
    )
    scale = []
    if pose_steps.keep_scale:
        if start_poses is None:
            raise ValueError("keeping the start's scale needs the start poses")
        scale = [keep_off_direction(scale_direction(start_poses, ~np.asarray(fixed, bool)))]
    return optax.chain(
        *prior,
        optax.scale_by_adam(),
        scale_pose_columns(schedules.pose_lr_trans, schedules.pose_lr_rot),
        zero_rows(fixed),
        *scale,
    )


def fixed_rows(train_cfg: ml_collections.ConfigDict, num_scans: int) -> np.ndarray:
    """[S] bool: the rows of train.fixed_scans (train_cfg: config.train); a ConfigError naming the field for a scan
    not among the S."""
    fixed = np.zeros(num_scans, bool)
    for s in train_cfg.fixed_scans:
        if not -num_scans <= int(s) < num_scans:
            raise ConfigError(
                f"train.fixed_scans = {tuple(train_cfg.fixed_scans)!r}: scan {s} is not one of the "
                f"{num_scans} keyframes"
            )
        fixed[int(s)] = True
    return fixed


def make_optimizer(
    config: ml_collections.ConfigDict,
    schedules: Schedules,
    num_scans: int,
    pose_steps: PoseSteps,
    start_poses: np.ndarray | None = None,
) -> optax.GradientTransformation:
    pose_tx = pose_transform(schedules, pose_steps, fixed_rows(config.train, num_scans), start_poses)

    def labels(params):
        return {"fields": jax.tree.map(lambda _: "fields", params["fields"]), "poses": "poses"}

    return optax.multi_transform({"fields": optax.adam(schedules.field_lr), "poses": pose_tx}, labels)


# ------------------------------------------------------------------------------------------------ the step


@dataclasses.dataclass(frozen=True)
class LossSettings:
    """Weights of eq. 13 (config.loss); static under jit."""

    lambda_coarse: float = 0.1
    lambda_range: float = 1.0
    lambda_termination: float = 1.0


def ray_losses(out, ranges: jax.Array, loss: LossSettings) -> tuple[jax.Array, dict]:
    """Eq. 13: lambda_coarse (l_d L_range^c + l_h L_term^c) + (l_d L_range^f + l_h L_term^f).

    Returns (total, metrics): each term, the total as "loss", and the median absolute range residual of the last
    pass ("range_residual_median"; on real scans a tail of badly fitted rays holds the mean up)."""
    l_d, l_h = loss.lambda_range, loss.lambda_termination

    def pass_losses(rendered, z):
        return losses.range_l1(rendered.depth, ranges), losses.termination_loss(rendered.weights, z, ranges)

    lc_range, lc_term = pass_losses(out.coarse, out.z_coarse)
    total = loss.lambda_coarse * (l_d * lc_range + l_h * lc_term)
    metrics = {"range_l1_coarse": lc_range, "term_coarse": lc_term}
    if out.fine is not None:
        lf_range, lf_term = pass_losses(out.fine, out.z_fine)
        total = total + l_d * lf_range + l_h * lf_term
        metrics.update(range_l1_fine=lf_range, term_fine=lf_term)
    final = out.fine if out.fine is not None else out.coarse
    metrics["range_residual_median"] = jnp.median(jnp.abs(final.depth - ranges))
    metrics["loss"] = total
    return total, metrics


def make_loss(field: DensityField, loss: LossSettings, batch_rays: int) -> Callable:
    """loss_fn(params, rays, frames, key, alpha, sampler) -> (total, per-cube metrics {name: [M]}): the sum over
    cubes of weight[m] times eq. 13 on a batch of batch_rays of cube m's rays (its own key). sampler: in metres."""

    def cube_loss(field_params, poses, rays_m, frames_m, key_batch, key_render, alpha, sampler):
        idx = jax.random.randint(key_batch, (batch_rays,), 0, jnp.maximum(rays_m.num_rays, 1))
        directions_local, ranges, slot = rays_m.directions[idx], rays_m.ranges[idx], rays_m.scan_index[idx]
        # the W poses first, then a gather: cheaper than an exp per ray
        T = corrected_poses(poses, frames_m.T_init, frames_m.scan_global, frames_m.rho_factor)[slot]
        origins, directions = world_rays(T, directions_local)
        out = render_rays(
            field_params, field, in_units(sampler, frames_m.scale), origins, directions, alpha, key_render, ranges
        )
        total, metrics = ray_losses(out, ranges, loss)
        metrics["range_err_m"] = metrics.get("range_l1_fine", metrics["range_l1_coarse"]) / frames_m.scale
        metrics["range_residual_median_m"] = metrics["range_residual_median"] / frames_m.scale
        return total * frames_m.weight, metrics

    def loss_fn(params, rays: Rays, frames: Frames, key, alpha, sampler: SamplerSettings):
        m = frames.weight.shape[0]
        key_batch, key_render = jax.random.split(key)
        totals, metrics = jax.vmap(cube_loss, in_axes=(0, None, 0, 0, 0, 0, None, None))(
            params["fields"],
            params["poses"],
            rays,
            frames,
            jax.random.split(key_batch, m),
            jax.random.split(key_render, m),
            alpha,
            sampler,
        )
        return jnp.sum(totals), metrics

    return loss_fn


def make_step(
    tx: optax.GradientTransformation,
    schedules: Schedules,
    field: DensityField,
    loss: LossSettings,
    batch_rays: int,
    sharding=None,
) -> Callable:
    """The pure, unjitted train step: step(state, rays, frames, sampler) -> (state, metrics): one Adam step on one
    batch (batch_rays rays per cube, drawn with the state's key). metrics: float32 scalars, the weight-averaged
    per-cube loss terms, alpha and the pose gradient's norm. With `sharding` the new state is constrained to it, so
    that the step's output lives where its input did."""
    loss_fn = make_loss(field, loss, batch_rays)

    def step(state: TrainState, rays: Rays, frames: Frames, sampler: SamplerSettings):
        key, key_loss = jax.random.split(state.key)
        alpha = schedules.alpha(state.step)
        (_, per_cube), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, rays, frames, key_loss, alpha, sampler
        )
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        w = frames.weight / jnp.sum(frames.weight)
        metrics = {k: jnp.sum(v * w) for k, v in per_cube.items()}
        metrics.update(alpha=alpha, pose_grad_norm=jnp.linalg.norm(grads["poses"]))
        new_state = TrainState(step=state.step + 1, params=params, opt_state=opt_state, key=key)
        if sharding is not None:
            new_state = jax.lax.with_sharding_constraint(new_state, sharding)
        return new_state, metrics

    return step


def jit_chunk(step: Callable) -> Callable:
    """chunk(state, rays, frames, sampler, num_steps) -> (state, the last step's metrics): num_steps steps in one
    `lax.scan`, one device call (the key travels in the state, so the batches are those of single steps). Static:
    the sampler and num_steps; the state is donated."""

    def chunk(state: TrainState, rays: Rays, frames: Frames, sampler: SamplerSettings, num_steps: int):
        state, metrics = jax.lax.scan(lambda s, _: step(s, rays, frames, sampler), state, None, length=num_steps)
        return state, jax.tree.map(lambda m: m[-1], metrics)

    return jax.jit(chunk, static_argnames=("sampler", "num_steps"), donate_argnums=(0,))


# ------------------------------------------------------------------------------------------------ setup


class Trainer(NamedTuple):
    """What one plan of `schedules.total_steps` trains with (`make_trainer`)."""

    tx: optax.GradientTransformation
    schedules: Schedules
    field: DensityField
    sampler: Callable[[int], SamplerSettings]  # sampler(step): the stage's sampler, in metres
    step: Callable  # unjitted step(state, rays, frames, sampler)
    chunk: Callable  # jit_chunk(step)
    batch_rays: int  # per cube
    sharding: Any  # the state's NamedSharding tree


def sampler_settings(sampling_cfg: ml_collections.ConfigDict, num_coarse: int, num_fine: int) -> SamplerSettings:
    """The sampler of one stage (sampling_cfg: config.sampling), in metres (model.in_units converts it into a cube's
    units)."""
    s = sampling_cfg
    return SamplerSettings(
        num_coarse=int(num_coarse),
        num_fine=int(num_fine),
        z_low=float(s.z_low_m),
        z_up=float(s.z_up_m),
        cube_bound=bool(s.cube_bound),
        hierarchical=str(s.hierarchical),
        guided_samples=int(s.guided_samples),
        guided_width=GUIDED_WIDTH_M,
    )


def make_field(config: ml_collections.ConfigDict, num_submaps: int = 1) -> DensityField:
    """The density field of config.model; a plan of several cubes at submaps.width when set."""
    field = field_from_config(config.model)
    width = int(config.submaps.width) if num_submaps > 1 else 0
    return field.clone(width=width) if width > 0 else field


def batch_rays_per_cube(config: ml_collections.ConfigDict, num_submaps: int) -> int:
    """Rays each of the M cubes draws per step: train.batch_rays for one cube; for several,
    train.batch_rays x submaps.step_rays_factor shared among them (padding cubes included: they cost as much), at
    least MIN_BATCH_RAYS each, so that a step costs about the same however the sequence is split."""
    if num_submaps <= 1:
        return int(config.train.batch_rays)
    step_rays = int(round(int(config.train.batch_rays) * float(config.submaps.step_rays_factor)))
    return max(step_rays // num_submaps, MIN_BATCH_RAYS)


def loss_settings(config: ml_collections.ConfigDict, num_submaps: int = 1) -> LossSettings:
    """config.loss's weights; a plan of several cubes at submaps.lambda_termination when set."""
    termination = float(config.loss.lambda_termination)
    if num_submaps > 1 and float(config.submaps.lambda_termination) > 0:
        termination = float(config.submaps.lambda_termination)
    return LossSettings(float(config.loss.lambda_coarse), float(config.loss.lambda_range), termination)


def field_lr_factor(config: ml_collections.ConfigDict, num_submaps: int, total_steps: int) -> float:
    """The factor on train.field_lr_*: f for a plan of several cubes and N steps or more under
    submaps.field_lr_from_steps = (N, f), else 1."""
    rule = tuple(config.submaps.field_lr_from_steps)
    if not rule or num_submaps <= 1:
        return 1.0
    if len(rule) != 2 or not (rule[0] > 0 and rule[1] > 0):
        raise ValueError(f"submaps.field_lr_from_steps: expected (steps, factor) > 0 or (), got {rule!r}")
    return float(rule[1]) if total_steps >= rule[0] else 1.0


def make_trainer(
    config: ml_collections.ConfigDict,
    num_scans: int,
    num_submaps: int,
    pose_steps: PoseSteps,
    start_poses: np.ndarray | None = None,
    total_steps: int | None = None,
    mesh: Mesh | None = None,
) -> Trainer:
    """The optimiser, schedules, field, sampler and step of a plan of total_steps (None: train.steps) over S
    keyframes in M cubes. start_poses [S, 4, 4] (world): what pose_steps.keep_scale keeps the scale of. The step
    keeps the state on the mesh (None: one device), where `init_state` puts it."""
    steps = int(config.train.steps if total_steps is None else total_steps)
    schedules = make_schedules(config, pose_steps, steps, field_lr_factor(config, num_submaps, steps))
    tx = make_optimizer(config, schedules, num_scans, pose_steps, start_poses)
    field = make_field(config, num_submaps)
    batch = batch_rays_per_cube(config, num_submaps)
    shapes = jax.eval_shape(lambda: _initial_state(config, tx, field, num_scans, num_submaps))
    sharding = state_sharding(shapes, make_mesh(1) if mesh is None else mesh)
    step = make_step(tx, schedules, field, loss_settings(config, num_submaps), batch, sharding)

    def sampler(step_index: int) -> SamplerSettings:
        return sampler_settings(config.sampling, *schedules.samples(step_index))

    return Trainer(tx, schedules, field, sampler, step, jit_chunk(step), batch, sharding)


def _initial_state(config, tx, field: DensityField, num_scans: int, num_submaps: int) -> TrainState:
    key_init, key_state = jax.random.split(jax.random.PRNGKey(int(config.seed)))
    fields = jax.vmap(lambda k: field.init(k, jnp.zeros((1, 3)), jnp.zeros((1, 3)))["params"])(
        jax.random.split(key_init, num_submaps)
    )
    params = {"fields": fields, "poses": jnp.zeros((num_scans, 6), jnp.float32)}
    return TrainState(step=jnp.zeros([], jnp.int32), params=params, opt_state=tx.init(params), key=key_state)


def init_state(config: ml_collections.ConfigDict, trainer: Trainer, num_scans: int, num_submaps: int) -> TrainState:
    """The state training starts from (cube m's field from key m of config.seed's split), placed as the trainer
    shards it; also the template a checkpoint restores into."""
    state = jax.jit(lambda: _initial_state(config, trainer.tx, trainer.field, num_scans, num_submaps))()
    return jax.device_put(state, trainer.sharding)


# ------------------------------------------------------------------------------------------------ the loop


class FitResult(NamedTuple):
    state: TrainState
    history: list  # one dict of floats per logged step, from step 1 (across resumes)
    stopped_early: bool
    train_seconds: float = 0.0  # wall-clock seconds in fit, summed over resumes
    schedules: Schedules | None = None  # the plan that ran: train.steps, or fewer when compressed to the time


@dataclasses.dataclass(frozen=True)
class TrainingData:
    """What every step draws its batch from: the M cubes' rays and frames (`device_data`, on the device mesh) and
    ref_scale, the reference cube's units per metre (the pose rows' rho is in those units: the logs give metres)."""

    rays: Rays
    frames: Frames
    ref_scale: float


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """How `fit` runs, besides what it trains: max_seconds > 0 the wall-clock limit of the call (0: none); progress:
    a progress bar; on_log(entry, state) sees each history entry as it is made (a viewer's hook: host code between
    device calls)."""

    max_seconds: float = 0.0
    progress: bool = True
    on_log: Callable[[dict, TrainState], None] | None = None


def pose_correction_stats(poses: np.ndarray, ref_scale: float) -> tuple[float, float]:
    """Mean translation [m] and rotation [deg] of the corrections, poses [S, 6] (rho in units of ref_scale per
    metre)."""
    C = body_corrections(np.asarray(poses), ref_scale)
    rot_deg = np.degrees(np.linalg.norm(np.asarray(poses, np.float64)[:, 3:], axis=1))
    return float(np.linalg.norm(C[:, :3, 3], axis=1).mean()), float(rot_deg.mean())


def chunk_bounds(start: int, total: int, log_every: int, checkpoint_every: int, schedules: Schedules) -> list:
    """The (begin, end) step ranges `fit` runs as one device call each, from `start` to `total`.

    A chunk ends at the next multiple of log_every and never straddles a sample-count stage start (the sampler is
    static per chunk), the pose start step (logged before its chunk), a multiple of checkpoint_every or `total`.
    The ends are absolute, so a run resumed at a checkpoint cuts the same chunks as an uninterrupted one."""
    log_every = max(int(log_every), 1)
    cuts = {*schedules.stage_starts, schedules.pose_start_step, total}
    bounds, begin = [], start
    while begin < total:
        end = (begin // log_every + 1) * log_every
        if checkpoint_every > 0:
            end = min(end, (begin // checkpoint_every + 1) * checkpoint_every)
        end = min([end, *(c for c in cuts if c > begin)])
        bounds.append((begin, end))
        begin = end
    return bounds


def steps_that_fit(done: int, total: int, seconds_left: float, seconds_per_step: float, min_total: int) -> int:
    """The total step count of a plan that, `done` steps in, ends within `seconds_left` at `seconds_per_step` (10 %
    kept in hand): `total` when every remaining step fits, else fewer, but at least `min_total`."""
    if seconds_per_step <= 0 or (total - done) * seconds_per_step <= 0.9 * seconds_left:
        return total
    fitting = done + int(0.9 * max(seconds_left, 0.0) / seconds_per_step)
    return int(min(total, max(fitting, min_total)))


def history_entry(
    metrics: dict, poses: jax.Array, step: int, schedules: Schedules, ref_scale: float, clock: Callable[[], float]
) -> dict:
    """The history's entry of `step`: the metrics of that step (floats), its plan's total_steps, the corrections'
    mean translation [m] and rotation [deg] (poses [S, 6]), training's seconds so far (clock(), read once the
    metrics and poses are on the host: the chunk has run) and the step's learning rates."""
    entry = {k: float(v) for k, v in jax.device_get(metrics).items()}
    trans_m, rot_deg = pose_correction_stats(jax.device_get(poses), ref_scale)
    entry.update(
        step=step,
        total_steps=schedules.total_steps,
        pose_trans_mean_m=trans_m,
        pose_rot_mean_deg=rot_deg,
        elapsed_s=clock(),
        field_lr=float(schedules.field_lr(step - 1)),
        pose_lr_trans=float(schedules.pose_lr_trans(step - 1)),
        pose_lr_rot=float(schedules.pose_lr_rot(step - 1)),
    )
    if not np.isfinite(entry["loss"]):
        raise FloatingPointError(f"loss is {entry['loss']} at step {step}; lower the learning rates")
    return entry


def compressed_plan(
    plan_of: Callable[[int], Trainer], chunk_seconds: list, done: int, total: int, seconds_left: float
) -> Trainer | None:
    """The plan of fewer steps that, `done` steps in, ends within `seconds_left` (`steps_that_fit`, at least a
    quarter of `total`); None when the remaining steps of the plan of `total` fit. chunk_seconds: the first two
    chunks' (steps, seconds); the first one's excess over the second's rate is its compile."""
    (first_steps, first_s), (steps, seconds) = chunk_seconds
    per_step = seconds / max(steps, 1)
    # The new plan compiles its chunk again, and the chunks cut at its pose start have other lengths (up to two
    # more compiles).
    compile_s = max(first_s - first_steps * per_step, 0.0)
    fitting = steps_that_fit(done, total, seconds_left - 3 * compile_s, per_step, min_total=max(done + 1, total // 4))
    if fitting >= total:
        return None
    logger.warning(
        "the remaining %d steps would take %.1f min at %.2f s a step, and %.1f min are left (10%% of them "
        "and %.0f s for three compiles kept in hand): the plan is compressed to %d steps (max_minutes)",
        total - done,
        (total - done) * per_step / 60.0,
        per_step,
        seconds_left / 60.0,
        3 * compile_s,
        fitting,
    )
    return plan_of(fitting)


def _log_stage(step: int, stage: int, sampler: SamplerSettings, rays_per_step: int) -> None:
    logger.info(
        "step %d: stage %d, %d coarse + %d fine (+%d guided) samples per ray, %d rays per step",
        step,
        stage,
        sampler.num_coarse,
        sampler.num_fine,
        sampler.guided_samples,
        rays_per_step,
    )


def _log_pose_start(config: ml_collections.ConfigDict, schedules: Schedules, step: int) -> None:
    if step == schedules.pose_start_step and step > 0:
        logger.info(
            "step %d: frequency %d active, poses start moving",
            step,
            min(int(config.train.pose_start_freq), schedules.pos_freqs),
        )


def _time_is_up(seconds: float, max_seconds: float, done: int, total: int) -> bool:
    """Whether training stops at step `done` of `total`, `seconds` into a limit of max_seconds (0: none); logged."""
    if max_seconds > 0 and seconds > max_seconds and done != total:
        logger.warning(
            "stopping at step %d of %d: the %.1f minutes training may take are over (max_minutes)",
            done,
            total,
            max_seconds / 60.0,
        )
        return True
    return False


def _progress_postfix(entry: dict) -> dict:
    """What the progress bar shows of a history entry."""
    return dict(
        loss=f"{entry['loss']:.4f}",
        range_err=f"{entry['range_err_m']:.3f}m",
        freq=f"{entry['alpha']:.1f}",
        dpose=f"{100 * entry['pose_trans_mean_m']:.1f}cm/{entry['pose_rot_mean_deg']:.2f}deg",
    )


def fit(
    config: ml_collections.ConfigDict,
    plan_of: Callable[[int], Trainer],
    data: TrainingData,
    state: TrainState,
    checkpoint_fn: Callable[[TrainState, list, float], None] | None = None,
    history: list | None = None,
    elapsed_s: float = 0.0,
    settings: FitSettings = FitSettings(),
) -> FitResult:
    """Train from `state` on `data` to the end of the plan: plan_of(total_steps) builds the Trainer of a plan of that
    many steps (`make_trainer`); the first is train.steps, or the plan a resumed run's history records.

    The steps run in chunks (`chunk_bounds`), one device call each. The history gets the last step of each chunk
    that ends on a multiple of train.log_every, and the last step (`history_entry`; settings.on_log sees each);
    checkpoint_fn(state, history, train_seconds) runs every train.checkpoint_every steps and at the end. A resumed
    run passes its restored history and elapsed_s. settings.max_seconds > 0: timed by its second chunk (the first
    compiles), a plan that would overrun goes on as the plan of the steps that fit (`compressed_plan`)."""
    from tqdm.auto import tqdm  # an effect at the edge; the step itself is pure

    start, max_seconds = int(state.step), settings.max_seconds
    log_every, ckpt_every = max(int(config.train.log_every), 1), int(config.train.checkpoint_every)
    history = [h for h in (history or []) if h.get("step", 0) <= start]  # a resumed run's, up to its step
    trainer = plan_of(int(history[-1]["total_steps"] if history else config.train.steps))
    schedules, total, current_stage, stopped_early = trainer.schedules, trainer.schedules.total_steps, None, False
    t0 = time.perf_counter()

    def train_seconds() -> float:
        return elapsed_s + time.perf_counter() - t0

    bar = tqdm(total=total, initial=start, disable=not settings.progress, unit="step", dynamic_ncols=True)
    bounds, chunk_seconds = chunk_bounds(start, total, log_every, ckpt_every, schedules), []
    while bounds:
        begin, done = bounds.pop(0)
        if schedules.stage(begin) != current_stage:
            current_stage, sampler = schedules.stage(begin), trainer.sampler(begin)
            _log_stage(begin, current_stage, sampler, trainer.batch_rays * int(data.frames.weight.shape[0]))
        _log_pose_start(config, schedules, begin)
        t_chunk = time.perf_counter()
        state, metrics = trainer.chunk(state, data.rays, data.frames, sampler, num_steps=done - begin)
        if done % log_every == 0 or done == total:
            m = history_entry(metrics, state.params["poses"], done, schedules, data.ref_scale, train_seconds)
            history.append(m)
            if settings.on_log is not None:
                settings.on_log(m, state)
            bar.set_postfix(**_progress_postfix(m), refresh=False)
        bar.update(done - begin)
        if len(chunk_seconds) < 2:  # the first two chunks time the plan (the first one compiles)
            jax.block_until_ready(state)  # dispatch is asynchronous: wait for the chunk itself
            chunk_seconds.append((done - begin, time.perf_counter() - t_chunk))
            if max_seconds > 0 and len(chunk_seconds) == 2 and done < total:
                left_s = max_seconds - (time.perf_counter() - t0)
                compressed = compressed_plan(plan_of, chunk_seconds, done, total, left_s)
                if compressed is not None:
                    trainer, schedules, current_stage = compressed, compressed.schedules, None
                    total = bar.total = schedules.total_steps
                    bounds = chunk_bounds(done, total, log_every, ckpt_every, schedules)
        if checkpoint_fn is not None and ckpt_every > 0 and done % ckpt_every == 0 and done != total:
            checkpoint_fn(state, history, train_seconds())
        stopped_early = _time_is_up(time.perf_counter() - t0, max_seconds, done, total)
        if stopped_early:
            break
    bar.close()
    seconds = train_seconds()
    if checkpoint_fn is not None:
        checkpoint_fn(state, history, seconds)
    return FitResult(state, history, stopped_early, seconds, schedules)
