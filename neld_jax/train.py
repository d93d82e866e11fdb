"""Training: the one parameter pytree, the optimiser, the schedules and the jitted step.

params = {"field": <flax params of DensityField>, "poses": [S, 6] se(3) corrections (rho, omega)}.
The pose of scan s is exp(poses[s]) @ T_init[s] in the normalised frame (neld_jax.lie.apply_correction).

The optimiser is one optax transform over that pytree, partitioned by label: the field gets Adam with its
own exponential decay; the poses get Adam with separate translation / rotation schedules that are exactly
zero until the coarse-to-fine window activates frequency k* (BARF), and gauge-fixed rows are zeroed.
The step is a pure function of (state, rays, T_init, sampler) with no Python branching on traced values
(`make_step_body`); the only static argument is the sampler of the sample-count stage, so it compiles once per
stage. `fit` runs it K = train.log_every steps per device call in a `lax.scan` (`jit_chunk`).
`create_train_state` builds all of it (state, optimiser, schedules, step, chunk, field) from the config.
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

from neld_jax import lie, losses
from neld_jax.config import with_train
from neld_jax.field import DensityField, field_from_config
from neld_jax.model import SamplerSettings, render_rays, scan_poses, world_rays

logger = logging.getLogger(__name__)


class RayData(NamedTuple):
    """All training rays, resident on the device. R rays over S scans, grouped by scan (scan_index sorted)."""

    directions: jax.Array  # [R, 3] unit, sensor frame
    ranges: jax.Array  # [R] normalised measured ranges
    scan_index: jax.Array  # [R] int32
    scan_start: jax.Array | None = None  # [S] int32 first ray of each scan (for per-scan batches)
    scan_count: jax.Array | None = None  # [S] int32 rays of each scan


def device_rays(rayset) -> RayData:
    """A neld_jax.data.rays.RaySet (numpy, rays grouped by scan) on the device, with the dtypes the step expects."""
    scan_index = np.asarray(rayset.scan_index)
    if np.any(np.diff(scan_index) < 0):
        raise ValueError("device_rays: rays must be grouped by scan (scan_index sorted)")
    counts = np.bincount(scan_index, minlength=int(scan_index.max()) + 1 if len(scan_index) else 0)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else counts
    return RayData(jnp.asarray(rayset.directions, jnp.float32), jnp.asarray(rayset.ranges, jnp.float32),
                   jnp.asarray(scan_index, jnp.int32), jnp.asarray(starts, jnp.int32), jnp.asarray(counts, jnp.int32))


def sample_batch(key: jax.Array, rays: RayData, batch_rays: int, scans_per_step: int = 0) -> jax.Array:
    """Ray indices [batch_rays] int32 of one step.

    scans_per_step = 0: uniform over all rays (each of S scans gets batch_rays / S rays on average). Otherwise
    `scans_per_step` scans drawn uniformly, each with batch_rays // scans_per_step of its rays: with hundreds of
    scans a uniform batch gives each pose one or two rays a step, and Adam turns such noisy pose gradients into
    a random walk; a few rays per scan average the noise out (docs/method.md, "Batches").
    """
    if scans_per_step <= 0:
        return jax.random.randint(key, (batch_rays,), 0, rays.ranges.shape[0])
    key_scans, key_rays = jax.random.split(key)
    per_scan = batch_rays // scans_per_step
    scans = jax.random.randint(key_scans, (scans_per_step,), 0, rays.scan_count.shape[0])
    counts = jnp.maximum(rays.scan_count[scans], 1)[:, None]
    offsets = jnp.minimum(jnp.floor(jax.random.uniform(key_rays, (scans_per_step, per_scan)) * counts), counts - 1)
    return (rays.scan_start[scans][:, None] + offsets.astype(jnp.int32)).reshape(-1)


@flax.struct.dataclass
class TrainState:
    step: jax.Array  # scalar int32
    params: Any  # {"field": ..., "poses": [S, 6]}
    opt_state: Any
    key: jax.Array


@dataclasses.dataclass(frozen=True)
class Schedules:
    """Step -> value functions built from the config, shared by the optimiser, the step and the logs."""

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


def make_schedules(config: ml_collections.ConfigDict) -> Schedules:
    t = config.train
    steps = int(t.steps)
    c2f_end = int(round(t.c2f_end_fraction * steps))
    L = int(config.model.pos_freqs)
    # Frequency k is fully on once alpha >= k + 1 and starts at alpha = k; poses start when k* starts.
    # L = 0 (no positional frequencies): nothing to wait for.
    pose_start = int(math.ceil(min(t.pose_start_freq, L) / L * c2f_end)) if L > 0 else 0
    pose_start = max(pose_start, int(t.pose_warmup_steps))
    coarse = tuple(int(n) for n in config.sampling.coarse_stages)
    fine = tuple(int(n) for n in config.sampling.fine_stages)
    if len(coarse) != len(fine) or not coarse:
        raise ValueError("sampling.coarse_stages and sampling.fine_stages must be non-empty and of equal length")
    ramp_end = int(round(config.sampling.sample_ramp_fraction * steps))
    n = len(coarse)
    starts = tuple(0 if n == 1 else int(round(i / (n - 1) * ramp_end)) for i in range(n))

    def decay(init, final, begin, end):
        span = max(end - begin, 1)
        ratio = final / init if init > 0 else 1.0
        return optax.exponential_decay(init, transition_steps=span, decay_rate=ratio, transition_begin=0)

    def delayed(init, final):
        # Exactly zero before pose_start: Adam's update is then exactly zero, so poses stay put.
        return optax.join_schedules(
            [optax.constant_schedule(0.0), decay(init, final, pose_start, steps)], boundaries=[pose_start]
        )

    return Schedules(
        total_steps=steps,
        pos_freqs=L,
        c2f_end_step=c2f_end,
        pose_start_step=pose_start,
        stage_starts=starts,
        coarse_stages=coarse,
        fine_stages=fine,
        field_lr=decay(t.field_lr_init, t.field_lr_final, 0, steps),
        pose_lr_trans=delayed(t.pose_lr_trans_init, t.pose_lr_trans_final),
        pose_lr_rot=delayed(t.pose_lr_rot_init, t.pose_lr_rot_final),
    )


def scale_pose_columns(trans_lr: Callable, rot_lr: Callable) -> optax.GradientTransformation:
    """Descent step for [S, 6] pose updates: columns 0:3 (rho) by -trans_lr(count), 3:6 (omega) by -rot_lr."""

    def init_fn(params):
        del params
        return optax.ScaleByScheduleState(count=jnp.zeros([], jnp.int32))

    def update_fn(updates, state, params=None):
        del params
        lr = jnp.concatenate([jnp.full((3,), trans_lr(state.count)), jnp.full((3,), rot_lr(state.count))])
        # tree.map: inside multi_transform the field's leaves arrive as empty MaskedNodes and are skipped.
        updates = jax.tree.map(lambda u: -u * lr.astype(u.dtype), updates)
        return updates, optax.ScaleByScheduleState(count=optax.safe_increment(state.count))

    return optax.GradientTransformation(init_fn, update_fn)


def pose_prior(trans_weight: float, rot_weight: float) -> optax.GradientTransformation:
    """Add the gradient of a Gaussian prior at the start to [S, 6] pose gradients: w * xi, w = trans_weight on
    columns 0:3 (rho), rot_weight on 3:6 (omega). Stateless (optax.EmptyState, as add_decayed_weights, which it
    equals when the two weights are equal)."""
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


def scale_direction(start_positions: np.ndarray, movable: np.ndarray,
                    start_rotations: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The trajectory's scale mode in the [S, 6] pose corrections: a = (a_rho [S, 3], a_omega [S, 3]) float64 such
    that, to first order, the scale of the positions about their centroid c changes by a . xi (up to a positive
    factor). docs/method.md, "Keeping the start's scale".

    A step moving scan s by d_s scales the trajectory (as a similarity alignment to the start measures it) by
    1 + sum_s (p_s - c) . d_s / sum_s |p_s - c|^2 to first order: the part of d along the positions' own spread,
    to which a translation and a rotation about c are orthogonal.
    start_positions [S, 3]: the start's positions, in the frame that d is measured in; c is their mean over every
    scan (a fixed one's d is 0). movable [S] bool: the rows that may move (a is 0 on the others).

    - start_rotations None: LEFT corrections exp(xi_s) T_s in that frame (the single cube, normalised frame):
      d_s = omega_s x p_s + rho_s, so a_s = [p_s - c, c x p_s].
    - start_rotations [S, 3, 3] (the start's rotations R_s, world): RIGHT corrections T_s Exp(xi_s) in the scan's
      body frame (the submaps' shared rows; rho / s_ref is in metres): d_s = R_s rho_s / s_ref, and omega_s does
      not move the position to first order, so a_s = [R_s^T (p_s - c), 0] (1 / s_ref is a common factor, dropped)."""
    p = np.asarray(start_positions, np.float64)
    c = p.mean(axis=0)
    keep = np.asarray(movable, bool)[:, None]
    if start_rotations is None:
        a_rho, a_omega = p - c, np.cross(c, p)
    else:
        R = np.asarray(start_rotations, np.float64)
        a_rho, a_omega = np.einsum("sji,sj->si", R, p - c), np.zeros_like(p)
    return np.where(keep, a_rho, 0.0), np.where(keep, a_omega, 0.0)


def keep_off_direction(a_rho: np.ndarray, a_omega: np.ndarray) -> optax.GradientTransformation:
    """Keep the [S, 6] pose updates u off one direction a = (a_rho, a_omega) [S, 3] each: u gets the multiple of
    a_rho on its translation columns that makes a . u = 0 (rotations untouched). Linear, so a constraint a . xi = 0
    met at xi = 0 holds after every step; stateless, so the optimiser state's structure does not depend on a."""
    norm2 = max(float(np.sum(np.asarray(a_rho, np.float64) ** 2)), 1e-30)
    a_rho, a_omega = jnp.asarray(a_rho, jnp.float32), jnp.asarray(a_omega, jnp.float32)

    def project(u):
        change = jnp.sum(u[:, :3] * a_rho.astype(u.dtype)) + jnp.sum(u[:, 3:] * a_omega.astype(u.dtype))
        return u - jnp.pad((change / norm2) * a_rho.astype(u.dtype), ((0, 0), (0, 3)))

    return optax.stateless(lambda updates, params: jax.tree.map(project, updates))


def keep_trajectory_scale(start_positions: np.ndarray, movable: np.ndarray,
                          start_rotations: np.ndarray | None = None) -> optax.GradientTransformation:
    """Keep the [S, 6] pose updates off the trajectory's scale mode (`scale_direction`: left corrections without
    start_rotations, right ones with them), the one motion a rigid alignment cannot take out (docs/method.md,
    "Keeping the start's scale"). Only that mode is removed: every other motion, rotations included, stays free."""
    return keep_off_direction(*scale_direction(start_positions, movable, start_rotations))


def pose_transform(config: ml_collections.ConfigDict, schedules: Schedules, num_scans: int,
                   start_positions: np.ndarray | None = None,
                   start_rotations: np.ndarray | None = None) -> optax.GradientTransformation:
    """The [S, 6] poses' update: train.pose_prior_weight's pull toward the start (docs/method.md, "A prior on the
    pose corrections"), Adam, the translation / rotation learning rate schedules, train.fixed_scans' rows zeroed,
    and with train.keep_start_scale the updates kept off the trajectory's scale mode (`keep_trajectory_scale`),
    which needs start_positions [S, 3] (ignored without the option): the single cube's left corrections pass its
    positions in the normalised frame, the submaps' right (body-frame) corrections their world positions and
    start_rotations [S, 3, 3]. Shared by the single cube and the submaps."""
    fixed = np.zeros(num_scans, bool)
    for s in config.train.fixed_scans:
        if not -num_scans <= int(s) < num_scans:
            raise ValueError(f"train.fixed_scans names scan {s}, but the sequence has {num_scans} scans")
        fixed[int(s)] = True
    prior_weight = float(config.train.get("pose_prior_weight", 0.0))
    rot_factor = float(config.train.get("pose_prior_rot_factor", 1.0))
    # before Adam, so the prior's pull is normalised with the data's gradient (L2, not decoupled decay); left out
    # at 0, so that the default's optimizer state is the one checkpoints written before the prior hold
    prior = [pose_prior(prior_weight, prior_weight * rot_factor)] if prior_weight else []
    keep_scale = bool(config.train.get("keep_start_scale", False))
    if keep_scale and start_positions is None:
        raise ValueError("train.keep_start_scale needs the start's poses (create_train_state's start_positions, "
                         "create_submap_state's start_poses)")
    # last, on the step itself, so the constraint (linear, met at xi = 0) holds exactly after every step
    scale = [keep_trajectory_scale(start_positions, ~fixed, start_rotations)] if keep_scale else []
    return optax.chain(
        *prior,
        optax.scale_by_adam(),
        scale_pose_columns(schedules.pose_lr_trans, schedules.pose_lr_rot),
        zero_rows(fixed),
        *scale,
    )


def make_optimizer(config: ml_collections.ConfigDict, schedules: Schedules, num_scans: int,
                   start_positions: np.ndarray | None = None):
    pose_tx = pose_transform(config, schedules, num_scans, start_positions)
    field_tx = optax.adam(schedules.field_lr)

    def labels(params):
        return {"field": jax.tree.map(lambda _: "field", params["field"]), "poses": "poses"}

    return optax.multi_transform({"field": field_tx, "poses": pose_tx}, labels)


def sampler_settings(config: ml_collections.ConfigDict, scale: float, num_coarse: int,
                     num_fine: int) -> SamplerSettings:
    """The sampler of one stage (config.sampling); metre-valued fields are converted with the normalisation scale."""
    s = config.sampling
    return SamplerSettings(
        num_coarse=int(num_coarse),
        num_fine=int(num_fine),
        z_low=float(s.z_low_m * scale),
        z_up=float(s.z_up_m * scale),
        cube_bound=bool(s.cube_bound),
        hierarchical=str(s.hierarchical),
        guided_samples=int(s.guided_samples),
        guided_width=float(s.guided_width_m * scale),
        range_at_midpoint=bool(s.get("range_at_midpoint", False)),
    )


def make_field(config: ml_collections.ConfigDict) -> DensityField:
    """The density field of config.model (every architecture field, initial_density included)."""
    return field_from_config(config.model)


@dataclasses.dataclass(frozen=True)
class LossSettings:
    """Weights of eq. 13 (config.loss); static under jit."""

    lambda_coarse: float = 0.1
    lambda_range: float = 1.0
    lambda_termination: float = 1.0
    termination: bool = True  # False drops the termination loss (ablation)

    @classmethod
    def from_config(cls, loss_cfg) -> "LossSettings":
        return cls(lambda_coarse=float(loss_cfg.lambda_coarse), lambda_range=float(loss_cfg.lambda_range),
                   lambda_termination=float(loss_cfg.lambda_termination), termination=bool(loss_cfg.termination))


def _pass_losses(rendered, z: jax.Array, ranges: jax.Array, termination: bool) -> tuple[jax.Array, jax.Array]:
    """L1 range loss and termination loss of one pass (coarse or fine)."""
    l_range = losses.range_l1(rendered.depth, ranges)
    l_term = losses.termination_loss(rendered.weights, z, ranges) if termination else jnp.zeros(())
    return l_range, l_term


def ray_losses(out, ranges: jax.Array, loss: LossSettings) -> tuple[jax.Array, dict]:
    """Eq. 13: lambda_coarse (l_d L_range^c + l_h L_term^c) + (l_d L_range^f + l_h L_term^f).

    Returns (total, metrics): each term, the total as "loss", and the median absolute range residual of the
    last pass ("range_residual_median"; not part of the loss)."""
    l_d, l_h = loss.lambda_range, loss.lambda_termination
    lc_range, lc_term = _pass_losses(out.coarse, out.z_coarse, ranges, loss.termination)
    total = loss.lambda_coarse * (l_d * lc_range + l_h * lc_term)
    metrics = {"range_l1_coarse": lc_range, "term_coarse": lc_term}
    if out.fine is not None:
        lf_range, lf_term = _pass_losses(out.fine, out.z_fine, ranges, loss.termination)
        total = total + l_d * lf_range + l_h * lf_term
        metrics.update(range_l1_fine=lf_range, term_fine=lf_term)
    final = out.fine if out.fine is not None else out.coarse
    # The mean L1 hides how well most rays fit: on real scans a tail of badly fitted rays holds it up.
    metrics["range_residual_median"] = jnp.median(jnp.abs(final.depth - ranges))
    metrics["loss"] = total
    return total, metrics


def range_errors_m(metrics: dict, scale) -> dict:
    """The batch's range residuals of `ray_losses`' metrics in metres (scale: metres -> normalised): the mean L1
    of the last pass ("range_err_m") and the median ("range_residual_median_m")."""
    return {"range_err_m": metrics.get("range_l1_fine", metrics["range_l1_coarse"]) / scale,
            "range_residual_median_m": metrics["range_residual_median"] / scale}


def make_step_body(tx: optax.GradientTransformation, schedules: Schedules, field: DensityField, loss: LossSettings,
                   batch_rays: int, scans_per_step: int = 0) -> Callable:
    """The pure, unjitted train step: step(state, rays, T_init, sampler) -> (state, metrics).

    One Adam step on one batch of `batch_rays` rays (drawn with the state's key). metrics: a dict of float32
    scalars (the loss terms of eq. 13, alpha, pose_grad_norm, the batch's median absolute range residual).
    `make_train_step` jits it, `make_train_chunk` scans it; a caller that changes the loss (vmapped over submaps,
    say) wraps it and jits with `jit_step` / `jit_chunk`, which keep the same static arguments and donation.
    """

    def step(state: TrainState, rays: RayData, T_init: jax.Array, sampler: SamplerSettings):
        key, key_batch, key_render = jax.random.split(state.key, 3)
        idx = sample_batch(key_batch, rays, batch_rays, scans_per_step)
        directions_local, ranges, scan = rays.directions[idx], rays.ranges[idx], rays.scan_index[idx]
        alpha = schedules.alpha(state.step)

        def loss_fn(params):
            T = scan_poses(params["poses"], T_init)[scan]  # exp of S poses, then a gather: cheaper than exp per ray
            origins, directions = world_rays(T, directions_local)
            out = render_rays(params["field"], field, sampler, origins, directions, alpha, key_render, ranges)
            return ray_losses(out, ranges, loss)

        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, alpha=alpha, pose_grad_norm=jnp.linalg.norm(grads["poses"]))
        new_state = TrainState(step=state.step + 1, params=params, opt_state=opt_state, key=key)
        return new_state, metrics

    return step


def jit_step(step_body: Callable) -> Callable:
    """step_body jitted: the sampler static (one compile per sample-count stage), the state donated."""
    return jax.jit(step_body, static_argnames=("sampler",), donate_argnums=(0,))


def jit_chunk(step_body: Callable) -> Callable:
    """chunk(state, rays, T_init, sampler, num_steps) -> (state, metrics): `num_steps` steps in one device call.

    The steps run in a `jax.lax.scan` over step_body, so the host dispatches once per chunk instead of once per
    step (docs/design.md, "The loop"). The state after the chunk is the state after `num_steps` single steps
    (the key travels in the state, so the batches are the same). metrics: the LAST step's values (the keys of
    step_body's metrics; the others of the chunk are not kept), so a history logged at chunk ends holds
    exactly what a per-step loop logged at those steps. Static: the sampler and num_steps (one compile per
    pair); the state is donated.
    """

    def chunk(state: TrainState, rays: RayData, T_init: jax.Array, sampler: SamplerSettings, num_steps: int):
        def body(s, _):
            return step_body(s, rays, T_init, sampler)

        state, metrics = jax.lax.scan(body, state, None, length=num_steps)  # metrics stacked: [num_steps]
        return state, jax.tree.map(lambda m: m[-1], metrics)

    return jax.jit(chunk, static_argnames=("sampler", "num_steps"), donate_argnums=(0,))


def make_train_step(tx: optax.GradientTransformation, schedules: Schedules, field: DensityField, loss: LossSettings,
                    batch_rays: int, scans_per_step: int = 0):
    """Returns step(state, rays, T_init, sampler) -> (state, metrics), jitted with `sampler` static."""
    return jit_step(make_step_body(tx, schedules, field, loss, batch_rays, scans_per_step))


def make_train_chunk(tx: optax.GradientTransformation, schedules: Schedules, field: DensityField, loss: LossSettings,
                     batch_rays: int, scans_per_step: int = 0):
    """Returns chunk(state, rays, T_init, sampler, num_steps) -> (state, last step's metrics); see `jit_chunk`."""
    return jit_chunk(make_step_body(tx, schedules, field, loss, batch_rays, scans_per_step))


class TrainSetup(NamedTuple):
    """Everything a run trains with, built from the config by `create_train_state`."""

    state: TrainState  # the initial state (seeded by config.seed)
    tx: optax.GradientTransformation
    schedules: Schedules
    step_fn: Callable  # step_fn(state, rays, T_init, sampler) -> (state, metrics); jitted, state donated
    field: DensityField
    sampler: Callable[[int], SamplerSettings]  # sampler(step): the sampler of the step's sample-count stage
    chunk_fn: Callable | None = None  # chunk_fn(state, rays, T_init, sampler, num_steps): the steps fused; donated


def create_train_state(config: ml_collections.ConfigDict, num_scans: int, scale: float,
                       start_positions: np.ndarray | None = None) -> TrainSetup:
    """The one builder of the training state, optimiser, schedules, step and field of a run.

    num_scans: S (the poses' rows); scale: the normalisation scale (metres -> normalised) of the sampler;
    start_positions: [S, 3] the initial poses' positions (normalised frame), which train.keep_start_scale needs
    (`pose_transform`); the state's structure does not depend on them.
    """
    schedules = make_schedules(config)
    tx = make_optimizer(config, schedules, num_scans, start_positions)
    field = make_field(config)
    key_init, key_state = jax.random.split(jax.random.PRNGKey(int(config.seed)))
    field_params = field.init(key_init, jnp.zeros((1, 3)), jnp.zeros((1, 3)))["params"]
    params = {"field": field_params, "poses": jnp.zeros((num_scans, 6), jnp.float32)}
    state = TrainState(step=jnp.zeros([], jnp.int32), params=params, opt_state=tx.init(params), key=key_state)
    body = make_step_body(tx, schedules, field, LossSettings.from_config(config.loss), int(config.train.batch_rays),
                          int(config.train.get("scans_per_step", 0)))

    def sampler(step: int) -> SamplerSettings:
        return sampler_settings(config, scale, *schedules.samples(step))

    return TrainSetup(state, tx, schedules, jit_step(body), field, sampler, jit_chunk(body))


def initial_state(config: ml_collections.ConfigDict, num_scans: int, scale: float) -> TrainState:
    """The state a run starts from (seeded by config.seed); also the template a checkpoint restores into."""
    # train.keep_start_scale's transform is stateless: zeros give the state's structure
    return create_train_state(config, num_scans, scale, np.zeros((num_scans, 3))).state


class FitResult(NamedTuple):
    state: TrainState
    history: list  # one dict of floats per logged step, from step 1 (across resumes)
    stopped_early: bool
    train_seconds: float = 0.0  # wall-clock seconds in fit, summed over resumes
    total_steps: int = 0  # the schedule's steps: train.steps, or fewer when the guard compressed it (run_chunks)


def pose_start_message(config: ml_collections.ConfigDict, schedules: Schedules) -> str:
    """Why the poses start moving at schedules.pose_start_step: frequency k* or train.pose_warmup_steps."""
    step = schedules.pose_start_step
    k_star = min(int(config.train.pose_start_freq), schedules.pos_freqs)
    if step > 0 and step == int(config.train.pose_warmup_steps):
        return f"step {step}: poses start moving (train.pose_warmup_steps; frequency {k_star} is already active)"
    return f"step {step}: frequency {k_star} active, poses start moving"


@jax.jit
def _correction_translations(poses: jax.Array) -> jax.Array:
    """[S, 6] -> [S, 3] translations of exp(xi); one device call (eager, its ops cost ~17 ms a log on a CPU)."""
    return lie.se3_exp(poses)[:, :3, 3]


def pose_correction_stats(poses: np.ndarray, scale: float) -> tuple[float, float]:
    """Mean translation (metres) and rotation (degrees) of the corrections exp(xi), xi = poses [S, 6] (rho, omega).

    The translation of exp(xi) is V(omega) rho, not rho; `scale` converts normalised units to metres.
    """
    translations = np.asarray(_correction_translations(jnp.asarray(poses)), np.float64)
    trans_m = float(np.linalg.norm(translations, axis=1).mean() / scale)
    rot_deg = float(np.degrees(np.linalg.norm(np.asarray(poses)[:, 3:], axis=1)).mean())
    return trans_m, rot_deg


def chunk_bounds(start: int, total: int, log_every: int, checkpoint_every: int, schedules: Schedules) -> list:
    """The (begin, end) step ranges that `fit` runs as one device call each, from `start` to `total`.

    A chunk ends at the next multiple of log_every (K = log_every steps a call) and never straddles a
    sample-count stage start (the sampler is static per chunk), the pose start step (it is logged before its
    chunk), a multiple of checkpoint_every (checkpoints are written between chunks) or `total`. The ends are
    absolute step counts, so a run resumed at a checkpoint cuts the same chunks as an uninterrupted one.
    """
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
    """The total step count of a plan that, `done` steps in, ends within `seconds_left` at `seconds_per_step`
    (10 % kept in hand): `total` when every remaining step fits, else fewer, but at least `min_total`."""
    if seconds_per_step <= 0 or (total - done) * seconds_per_step <= 0.9 * seconds_left:
        return total
    fitting = done + int(0.9 * max(seconds_left, 0.0) / seconds_per_step)
    return int(min(total, max(fitting, min_total)))


def with_steps(config: ml_collections.ConfigDict, steps: int) -> ml_collections.ConfigDict:
    """A copy of config with train.steps = steps (every schedule follows: coarse-to-fine, pose start, decays)."""
    return with_train(config, steps=int(steps))


def run_chunks(config: ml_collections.ConfigDict, schedules: Schedules, sampler_fn: Callable[[int], Any],
               chunk_fn: Callable, state: TrainState, log_fn: Callable[[TrainState, dict], dict],
               rays_per_step: int, checkpoint_fn: Callable[[TrainState, list, float], None] | None = None,
               progress: bool = True, history: list | None = None, elapsed_s: float = 0.0,
               max_seconds: float | None = None, replan: Callable[[int], tuple] | None = None) -> FitResult:
    """The training loop shared by `fit` (one cube) and the submaps' fit: from state.step to config.train.steps.

    chunk_fn(state, sampler, num_steps) -> (state, metrics) runs `num_steps` fused steps (one device call);
    sampler_fn(step) gives the sampler of a step's stage; log_fn(state, metrics) adds the run's own figures
    (metres, pose corrections) to the floats of a logged chunk's metrics, which must then hold "loss",
    "alpha", "range_err_m", "pose_trans_mean_m" and "pose_rot_mean_deg"; rays_per_step is only logged.
    Chunks follow `chunk_bounds`; the history gets the last step of each chunk that ends on a multiple of
    train.log_every (and the last step); the progress bar and the train.max_minutes guard move at chunk ends;
    checkpoint_fn(state, history, train_seconds) runs every train.checkpoint_every steps and at the end. A
    resumed run passes its restored history and elapsed_s (train.max_minutes counts this call only).
    max_seconds: the guard's limit in seconds when the caller narrows it (`neld_jax.run` deducts what the run
    spent before training); None: train.max_minutes; <= 0: none.
    replan(total_steps) -> (schedules, sampler_fn, chunk_fn) of the same run with `total_steps` steps. Given it,
    the loop times its second chunk (the first compiles) and, when the remaining steps would overrun the guard,
    compresses the schedule to the steps that fit (`steps_that_fit`): the coarse-to-fine window, the pose start
    and the learning-rate decays then end within the time instead of being cut off. Each history entry records
    the plan's total_steps, and a resumed run continues the plan its history holds.
    """
    from tqdm.auto import tqdm  # an effect at the edge; the step itself is pure

    start = int(state.step)
    total = schedules.total_steps
    log_every = max(int(config.train.log_every), 1)
    ckpt_every = int(config.train.checkpoint_every)
    if max_seconds is None:
        max_seconds = float(config.train.max_minutes) * 60.0
    history = [h for h in (history or []) if h.get("step", 0) <= start]  # a resumed run's, up to its step
    stopped_early = False
    t0 = time.perf_counter()

    def train_seconds() -> float:
        return elapsed_s + time.perf_counter() - t0

    planned = int(history[-1].get("total_steps", total)) if history else total
    if replan is not None and planned != total:  # a resumed run keeps the plan it was compressed to
        schedules, sampler_fn, chunk_fn = replan(planned)
        total = planned
    current_stage = None
    bar = tqdm(total=total, initial=start, disable=not progress, unit="step", dynamic_ncols=True)
    bounds, chunk_seconds = chunk_bounds(start, total, log_every, ckpt_every, schedules), []
    while bounds:
        begin, done = bounds.pop(0)
        stage = schedules.stage(begin)
        if stage != current_stage:
            current_stage = stage
            sampler = sampler_fn(begin)
            logger.info("step %d: stage %d, %d coarse + %d fine (+%d guided) samples per ray, %d rays per step",
                        begin, stage, sampler.num_coarse, sampler.num_fine, sampler.guided_samples, rays_per_step)
        if begin == schedules.pose_start_step and begin > 0:
            logger.info(pose_start_message(config, schedules))
        t_chunk = time.perf_counter()
        state, metrics = chunk_fn(state, sampler, done - begin)
        if done % log_every == 0 or done == total:
            m = {k: float(v) for k, v in jax.device_get(metrics).items()}
            m["step"], m["total_steps"] = done, total
            m.update(log_fn(state, m))
            m["elapsed_s"] = train_seconds()
            history.append(m)
            if not np.isfinite(m["loss"]):
                raise FloatingPointError(f"loss is {m['loss']} at step {done}; lower the learning rates")
            bar.set_postfix(loss=f"{m['loss']:.4f}", range_err=f"{m['range_err_m']:.3f}m", freq=f"{m['alpha']:.1f}",
                            dpose=f"{100 * m['pose_trans_mean_m']:.1f}cm/{m['pose_rot_mean_deg']:.2f}deg", refresh=False)
        bar.update(done - begin)
        timing = len(chunk_seconds) < 2  # the first two chunks time the plan (the first one compiles)
        if timing:  # dispatch is asynchronous: wait for the chunk itself
            jax.block_until_ready(state)
            chunk_seconds.append((done - begin, time.perf_counter() - t_chunk))
        if replan is not None and max_seconds > 0 and timing and len(chunk_seconds) == 2 and done < total:
            (first_steps, first_s), (steps, seconds) = chunk_seconds
            per_step = seconds / max(steps, 1)
            # The new plan compiles its chunk again, and the chunks cut at its pose start have other lengths (up
            # to two more compiles): HKU main building's first plan overran by 89 of 614 steps without them.
            compile_s = max(first_s - first_steps * per_step, 0.0)
            left_s = max_seconds - (time.perf_counter() - t0)
            fitting = steps_that_fit(done, total, left_s - 3 * compile_s, per_step,
                                     min_total=max(done + 1, total // 4))
            if fitting < total:
                logger.warning("the remaining %d steps would take %.1f min at %.2f s a step, and %.1f min are left "
                               "(10%% of them and %.0f s for three compiles kept in hand): the schedule is compressed "
                               "to %d steps (train.max_minutes)", total - done, (total - done) * per_step / 60.0,
                               per_step, left_s / 60.0, 3 * compile_s, fitting)
                schedules, sampler_fn, chunk_fn = replan(fitting)
                total, current_stage = fitting, None
                bounds = chunk_bounds(done, total, log_every, ckpt_every, schedules)
                bar.total = total
        if checkpoint_fn is not None and ckpt_every > 0 and done % ckpt_every == 0 and done != total:
            checkpoint_fn(state, history, train_seconds())
        if max_seconds > 0 and time.perf_counter() - t0 > max_seconds and done != total:
            logger.warning("stopping at step %d of %d: the %.1f minutes training may take are over "
                           "(train.max_minutes=%g)", done, total, max_seconds / 60.0, config.train.max_minutes)
            stopped_early = True
            break
    bar.close()
    seconds = train_seconds()
    if checkpoint_fn is not None:
        checkpoint_fn(state, history, seconds)
    return FitResult(state, history, stopped_early, seconds, total)


def fit(
    config: ml_collections.ConfigDict,
    rays: RayData,
    T_init: jax.Array,
    scale: float,
    state: TrainState | None = None,
    checkpoint_fn: Callable[[TrainState, list, float], None] | None = None,
    progress: bool = True,
    history: list | None = None,
    elapsed_s: float = 0.0,
    max_seconds: float | None = None,
) -> FitResult:
    """Run the bundle adjustment of one cube from `state` (or a fresh one) up to config.train.steps.

    rays: all training rays on the device; T_init: [S, 4, 4] initial poses, normalised frame; scale: the
    normalisation scale (metres -> normalised), used for the sampler and for the logs in metres.
    The steps run in chunks of up to config.train.log_every steps, one device call each (`run_chunks`,
    `jit_chunk`). checkpoint_fn(state, history, train_seconds) is called every config.train.checkpoint_every
    steps and at the end. A resumed run passes the restored state with the history and elapsed_s saved with it.
    max_seconds: the wall-clock guard (`run_chunks`); None: train.max_minutes.
    """
    start_positions = np.asarray(T_init)[:, :3, 3]
    setup = create_train_state(config, int(T_init.shape[0]), scale, start_positions)

    def chunk_of(built: TrainSetup) -> Callable:  # run_chunks' chunk(state, sampler, num_steps) over this data
        return lambda s, sampler, num_steps: built.chunk_fn(s, rays, T_init, sampler, num_steps=num_steps)

    def log(s: TrainState, m: dict) -> dict:
        trans_m, rot_deg = pose_correction_stats(s.params["poses"], scale)
        return {**range_errors_m(m, scale), "pose_trans_mean_m": trans_m, "pose_rot_mean_deg": rot_deg}

    def replan(steps: int):
        planned = create_train_state(with_steps(config, steps), int(T_init.shape[0]), scale, start_positions)
        return planned.schedules, planned.sampler, chunk_of(planned)

    return run_chunks(config, setup.schedules, setup.sampler, chunk_of(setup), setup.state if state is None else state,
                      log, int(config.train.batch_rays), checkpoint_fn, progress, history, elapsed_s, max_seconds,
                      replan)
