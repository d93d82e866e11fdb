"""The rendered map (eq. 14): cast each scan's own ray directions from its optimised pose and keep, per ray,
the point at argmax_i h_i / delta_i. Works in the normalised frame; the caller maps points back to metres.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax import rendering
from neld_jax.field import DensityField
from neld_jax.model import SamplerSettings, render_rays, world_rays


@functools.partial(jax.jit, static_argnames=("field", "sampler"))
def render_map_points(params_field, field: DensityField, sampler: SamplerSettings, T_rays: jax.Array,
                      directions_local: jax.Array, alpha):
    """T_rays: [R, 4, 4] pose of each ray's scan, directions_local: [R, 3] -> (points [R, 3], opacity [R]).

    Deterministic sampling (no key): bin midpoints for coarse samples, CDF quantiles for fine ones.
    """
    origins, directions = world_rays(T_rays, directions_local)
    out = render_rays(params_field, field, sampler, origins, directions, alpha)
    rendered, z = (out.coarse, out.z_coarse) if out.fine is None else (out.fine, out.z_fine)
    z_map = rendering.map_range(rendered.weights, rendered.deltas, z)
    return origins + z_map[:, None] * directions, rendered.opacity


class MapRender(NamedTuple):
    """points: [N, 3] map points of the rays that end on a surface (normalised frame); ranges, opacity: [R]
    rendered map range (normalised units) and opacity of every ray, for per-ray residuals."""

    points: np.ndarray
    ranges: np.ndarray
    opacity: np.ndarray


def render_map(params_field, field: DensityField, sampler: SamplerSettings, T_scans: np.ndarray,
               directions_local: np.ndarray, scan_index: np.ndarray, alpha: float, rays_per_batch: int = 4096,
               min_opacity: float = 0.5, progress: bool = False) -> MapRender:
    """Rendered map of all rays, in the normalised frame.

    T_scans: [S, 4, 4] optimised poses; directions_local: [R, 3]; scan_index: [R]. Rays whose opacity is below
    `min_opacity` (they pass through empty space and end nowhere) give no map point.
    Batches are padded to one size so that the renderer compiles once.
    """
    from tqdm.auto import tqdm

    origins_of_scan = np.asarray(T_scans, np.float32)[:, :3, 3]  # on the host once, for the ranges
    T_scans = jnp.asarray(T_scans, jnp.float32)
    r = directions_local.shape[0]
    kept, ranges, opacities = [], [], []
    for start in tqdm(range(0, r, rays_per_batch), disable=not progress, desc="rendered map", unit="batch"):
        stop = min(start + rays_per_batch, r)
        pad = rays_per_batch - (stop - start)
        d = np.pad(directions_local[start:stop], ((0, pad), (0, 0)), mode="edge")
        s = np.pad(scan_index[start:stop], (0, pad), mode="edge")
        points, opacity = render_map_points(params_field, field, sampler, T_scans[s], jnp.asarray(d, jnp.float32),
                                            alpha)
        points, opacity = np.asarray(points)[: stop - start], np.asarray(opacity)[: stop - start]
        kept.append(points[opacity >= min_opacity])
        ranges.append(np.linalg.norm(points - origins_of_scan[s[: stop - start]], axis=1))
        opacities.append(opacity)
    if not kept:
        return MapRender(np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    return MapRender(np.concatenate(kept, axis=0), np.concatenate(ranges), np.concatenate(opacities))
