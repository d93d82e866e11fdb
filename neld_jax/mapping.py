"""The rendered map (eq. 14): cast each scan's own ray directions from its optimised pose and keep, per ray,
the point at argmax_i h_i / delta_i. Works in the normalised frame; the caller maps points back to metres.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax import rendering
from neld_jax.field import DensityField
from neld_jax.model import SamplerSettings, render_rays, world_rays

logger = logging.getLogger(__name__)


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
    rendered map range (normalised units) and opacity of every ray, for per-ray residuals; NaN for the rays a
    time limit left out (`num_rendered` tells how many were rendered)."""

    points: np.ndarray
    ranges: np.ndarray
    opacity: np.ndarray

    @property
    def num_rendered(self) -> int:
        return int(np.isfinite(self.opacity).sum())


def render_order(num_rays: int, max_seconds: float, seed: int) -> np.ndarray:
    """The order rays are rendered in: [num_rays] indices. Under a time limit (max_seconds > 0) a seeded random
    permutation, so that the rays rendered before the limit are a uniform sample of every scan's rays rather
    than the first scans'; otherwise the rays' own order."""
    if max_seconds > 0:
        return np.random.default_rng(seed).permutation(num_rays)
    return np.arange(num_rays)


def out_of_time(started: float, last_started: float, max_seconds: float) -> bool:
    """The render's stop rule under a time limit (max_seconds > 0; 0: never): stop rather than start another piece
    of work (a batch, a part of the rays) that would end past the limit if it took as long as the last one.
    started: time.perf_counter() when the render began; last_started: when the last piece began."""
    now = time.perf_counter()
    return max_seconds > 0 and (now - started) + (now - last_started) > max_seconds


def render_map(params_field, field: DensityField, sampler: SamplerSettings, T_scans: np.ndarray,
               directions_local: np.ndarray, scan_index: np.ndarray, alpha: float, rays_per_batch: int = 4096,
               min_opacity: float = 0.5, progress: bool = False, max_seconds: float = 0.0,
               seed: int = 0) -> MapRender:
    """Rendered map of all rays, in the normalised frame.

    T_scans: [S, 4, 4] optimised poses; directions_local: [R, 3]; scan_index: [R]. Rays whose opacity is below
    `min_opacity` (they pass through empty space and end nowhere) give no map point.
    max_seconds > 0: a time limit. The rays are rendered in a random order (render_order), and no batch is started
    that would end past the limit if it took as long as the one before (the first always runs); the rays left out
    get NaN range and opacity.
    Batches are padded to one size so that the renderer compiles once.
    """
    from tqdm.auto import tqdm

    origins_of_scan = np.asarray(T_scans, np.float32)[:, :3, 3]  # on the host once, for the ranges
    T_scans = jnp.asarray(T_scans, jnp.float32)
    r = directions_local.shape[0]
    order = render_order(r, max_seconds, seed)
    ranges, opacities = np.full(r, np.nan), np.full(r, np.nan)
    kept = [np.zeros((0, 3))]
    t0 = time.perf_counter()
    for start in tqdm(range(0, r, rays_per_batch), disable=not progress, desc="rendered map", unit="batch"):
        t_batch = time.perf_counter()
        idx = order[start:start + rays_per_batch]
        pad = rays_per_batch - len(idx)
        d = np.pad(directions_local[idx], ((0, pad), (0, 0)), mode="edge")
        s = np.pad(scan_index[idx], (0, pad), mode="edge")
        points, opacity = render_map_points(params_field, field, sampler, T_scans[s], jnp.asarray(d, jnp.float32),
                                            alpha)
        points, opacity = np.asarray(points)[: len(idx)], np.asarray(opacity)[: len(idx)]
        kept.append(points[opacity >= min_opacity])
        ranges[idx] = np.linalg.norm(points - origins_of_scan[s[: len(idx)]], axis=1)
        opacities[idx] = opacity
        if out_of_time(t0, t_batch, max_seconds):
            break
    return MapRender(np.concatenate(kept, axis=0), ranges, opacities)


def log_rendered_rays(num_points: int, num_rendered: int, num_rays: int, max_seconds: float) -> None:
    """One log line for the rendered map, and a warning when its time limit left rays out."""
    logger.info("rendered map: %d of %d rendered rays end on a surface", num_points, num_rendered)
    if num_rendered < num_rays:
        logger.warning("rendered map: %d of its %d rays (a uniform sample) were rendered in the %.0f s it may take "
                       "(mapping.max_seconds; 0 renders every ray)", num_rendered, num_rays, max_seconds)
