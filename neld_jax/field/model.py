"""The NeLD-BA forward model: per-scan poses and the density field to rendered LiDAR ranges.

Everything here works in the normalised frame (the scene inside [-1, 1]^3) and is a pure function of
(params, rays, static settings), so that the trainer and the mapper share one rendering path.

Pose convention (docs/method.md, "Poses"): the pose of keyframe s is `T_init[s] @ Exp(xi_s)`, a RIGHT correction
in the scan's body frame, xi = (rho, omega) with rho in the reference unit of every cube (`corrected_poses`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax import lie
from neld_jax.field import encoding, rendering, sampling
from neld_jax.field.density import DensityField


@dataclasses.dataclass(frozen=True)
class SamplerSettings:
    """Static (hashable) settings of the ray sampler of one stage; a change of any field recompiles.

    The field's architecture is not here: it is the DensityField module itself (neld_jax.field.density), also static.
    """

    num_coarse: int
    num_fine: int
    z_low: float  # normalised units
    z_up: float
    cube_bound: bool = True
    hierarchical: str = "before"  # one of options.HIERARCHICAL: before | nerf | none
    guided_samples: int = 0
    guided_width: float = 0.0  # normalised units


def in_units(sampler_m: SamplerSettings, scale) -> SamplerSettings:
    """A sampler in metres in a cube's units (scale: normalised units per metre; may be traced: one compile for every
    cube)."""
    return dataclasses.replace(
        sampler_m,
        z_low=sampler_m.z_low * scale,
        z_up=sampler_m.z_up * scale,
        guided_width=sampler_m.guided_width * scale,
    )


class RayOutputs(NamedTuple):
    """What one rendering of R rays returns; the fine pass holds coarse and fine samples merged."""

    coarse: rendering.Rendered  # fields [R, Nc'] / [R]
    fine: rendering.Rendered | None  # [R, Nc' + Nf] / [R]; None when hierarchical == "none"
    z_coarse: jax.Array  # [R, Nc']  (Nc' = num_coarse + guided_samples)
    z_fine: jax.Array | None  # [R, Nc' + Nf] sorted
    z_far: jax.Array  # [R]


def corrected_poses(poses: jax.Array, T_init: jax.Array, scan_global: jax.Array, rho_factor) -> jax.Array:
    """One cube's keyframe poses: poses [S, 6] the shared corrections (rho in the reference unit), T_init [W, 4, 4]
    the cube's keyframes' start poses in its normalised frame, scan_global [W] their rows of `poses`, rho_factor:
    the cube's scale over the reference scale -> [W, 4, 4] = T_init @ Exp((rho_factor rho, omega)).

    A normalisation x -> s (x - o) keeps rotations and scales translations, so the same right correction is exact in
    every cube that holds the scan: in the world it is T_world @ Exp((rho / s_ref, omega))."""
    xi = poses[scan_global]
    xi = jnp.concatenate([xi[:, :3] * rho_factor, xi[:, 3:]], axis=1)
    return lie.compose(T_init, lie.se3_exp(xi))


def world_poses(T_start: np.ndarray, poses: np.ndarray, ref_scale: float) -> np.ndarray:
    """The keyframes' corrected poses in the world, float64: T_start [S, 4, 4] (metres), poses [S, 6] (rho in units of
    ref_scale per metre) -> [S, 4, 4] = T_start @ Exp((rho / ref_scale, omega))."""
    return np.asarray(T_start, np.float64) @ body_corrections(poses, ref_scale)


def body_corrections(poses: np.ndarray, ref_scale: float) -> np.ndarray:
    """Exp of the corrections in metres, float64: poses [S, 6] -> [S, 4, 4]."""
    xi = np.asarray(poses, np.float64)
    return lie.se3_exp_float64(np.concatenate([xi[:, :3] / ref_scale, xi[:, 3:]], axis=1))


def world_rays(T_scan: jax.Array, directions_local: jax.Array) -> tuple[jax.Array, jax.Array]:
    """T_scan: [R, 4, 4] pose of each ray's scan, directions_local: [R, 3] unit, sensor frame.

    Returns origins [R, 3] and unit directions [R, 3] in the world frame.
    """
    origins = T_scan[..., :3, 3]
    directions = lie.rotate(T_scan, directions_local)
    return origins, directions


def sample_interval(origins: jax.Array, directions: jax.Array, sampler: SamplerSettings) -> tuple[jax.Array, jax.Array]:
    """[z_near, z_far] per ray: eq. 7 with the cube bound, or the plain [z_low, z_up] (ablation)."""
    if sampler.cube_bound:
        return sampling.cube_interval(origins, directions, sampler.z_low, sampler.z_up)
    r = origins.shape[0]
    return jnp.full((r,), sampler.z_low, origins.dtype), jnp.full((r,), sampler.z_up, origins.dtype)


def _densities(params_field, field: DensityField, origins, directions, z, pos_window):
    """sigma at origins + z * directions; origins, directions: [R, 3], z: [R, N] -> [R, N]."""
    r, n = z.shape
    points = origins[:, None, :] + z[..., None] * directions[:, None, :]
    # The unit direction itself is the view input: smooth everywhere, unlike angles at the poles.
    view = jnp.broadcast_to(directions[:, None, :], (r, n, 3))
    sigma = field.apply({"params": params_field}, points.reshape(-1, 3), view.reshape(-1, 3), pos_window)
    return sigma.reshape(r, n)


def render_rays(
    params_field,
    field: DensityField,
    sampler: SamplerSettings,
    origins: jax.Array,
    directions: jax.Array,
    alpha: jax.Array,
    key: jax.Array | None = None,
    measured_ranges: jax.Array | None = None,
) -> RayOutputs:
    """Render R rays: coarse pass, fine samples from the coarse weights, fine pass over both sets.

    field: the density field module and sampler: the sampler settings (both static under jit);
    origins, directions: [R, 3] world (normalised) frame; alpha: the coarse-to-fine progress (scalar);
    measured_ranges: [R] normalised, only used for range-guided samples (sampler.guided_samples > 0).
    The fine pass reuses the coarse densities (one MLP), so the MLP runs on Nc' + Nf points per ray.
    """
    key_coarse, key_guided, key_fine = (None, None, None) if key is None else tuple(jax.random.split(key, 3))
    # Sample positions are not differentiated (as in NeRF); positions still depend on the pose via o, d.
    z_near, z_far = jax.lax.stop_gradient(sample_interval(origins, directions, sampler))
    z_coarse = sampling.stratified_samples(z_near, z_far, sampler.num_coarse, key_coarse)
    if sampler.guided_samples > 0 and measured_ranges is not None:
        lo = jnp.clip(measured_ranges - sampler.guided_width, z_near, z_far)
        hi = jnp.clip(measured_ranges + sampler.guided_width, z_near, z_far)
        z_guided = sampling.stratified_samples(lo, hi, sampler.guided_samples, key_guided)
        z_coarse, _ = sampling.merge_samples(z_coarse, z_guided)
    z_coarse = jax.lax.stop_gradient(z_coarse)

    pos_window = encoding.barf_window(alpha, field.pos_freqs)
    sigma_coarse = _densities(params_field, field, origins, directions, z_coarse, pos_window)
    coarse = rendering.composite(sigma_coarse, z_coarse, z_far)
    if sampler.hierarchical == "none" or sampler.num_fine == 0:
        return RayOutputs(coarse, None, z_coarse, None, z_far)

    weights = jax.lax.stop_gradient(coarse.weights)
    if sampler.hierarchical == "before":
        z_new = sampling.fine_samples_before(z_coarse, weights, sampler.num_fine, z_near, key_fine)
    elif sampler.hierarchical == "nerf":
        z_new = sampling.nerf_resample(z_coarse, weights, sampler.num_fine, key_fine)
    else:
        raise ValueError(f"unknown hierarchical sampling {sampler.hierarchical!r}")
    sigma_new = _densities(params_field, field, origins, directions, z_new, pos_window)
    z_fine, order = sampling.merge_samples(z_coarse, z_new)
    sigma_fine = jnp.take_along_axis(jnp.concatenate([sigma_coarse, sigma_new], axis=-1), order, axis=-1)
    fine = rendering.composite(sigma_fine, z_fine, z_far)
    return RayOutputs(coarse, fine, z_coarse, z_fine, z_far)
