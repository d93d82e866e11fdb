"""The rendered map (eq. 14): cast each keyframe's own ray directions from its optimised pose and keep, per ray, the
point at argmax_i h_i / delta_i. One renderer for one cube and for many: a ray is rendered by every cube that holds
its keyframe and kept from the cube that holds its point most centrally.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax.field import rendering
from neld_jax.field.density import DensityField
from neld_jax.field.model import SamplerSettings, in_units, render_rays, world_rays
from neld_jax.field.normalize import Normalization
from neld_jax.training.rays import RaySet, build_rays, rays_per_scan
from neld_jax.training.train import sampler_settings

logger = logging.getLogger(__name__)

RAYS_PER_BATCH = 4096  # rays a device call renders (padded, so that the renderer compiles once)
# Parts of the rays under a time limit with several cubes: each part costs every cube a padded batch of its own
RENDER_PARTS = 4


@functools.partial(jax.jit, static_argnames=("field", "sampler_m"))
def render_points(
    params_field,
    field: DensityField,
    sampler_m: SamplerSettings,
    scale,
    T_rays: jax.Array,
    directions_local: jax.Array,
    alpha,
):
    """One cube's map points: T_rays [R, 4, 4] the pose of each ray's keyframe in the cube's frame, directions_local
    [R, 3]; sampler_m in metres, scale (traced: one compile for every cube) its units -> (points [R, 3] in the
    cube's frame, opacity [R]). Deterministic sampling (no key): bin midpoints, CDF quantiles."""
    origins, directions = world_rays(T_rays, directions_local)
    out = render_rays(params_field, field, in_units(sampler_m, scale), origins, directions, alpha)
    rendered, z = (out.coarse, out.z_coarse) if out.fine is None else (out.fine, out.z_fine)
    z_map = rendering.map_range(rendered.weights, rendered.deltas, z)
    return origins + z_map[:, None] * directions, rendered.opacity


class MapRender(NamedTuple):
    """rays: the rays cast (ranges in metres); points [N, 3] world: the points of the rays at least min_opacity
    opaque (before the written map's voxel grid); ranges [R] metres and opacity [R] of every ray, NaN for the rays a
    time limit left out."""

    rays: RaySet
    points: np.ndarray
    ranges: np.ndarray
    opacity: np.ndarray

    @property
    def num_rendered(self) -> int:
        return int(np.isfinite(self.opacity).sum())


def mapping_rays(mapping_cfg, keyframes, seed: int) -> RaySet:
    """The rays the rendered map casts (ranges in metres): each keyframe's own directions, mapping.max_rays_per_scan
    of them and mapping.max_rays over the sequence (`rays_per_scan`), drawn with their own seed."""
    per_scan = rays_per_scan(int(mapping_cfg.max_rays_per_scan), int(mapping_cfg.max_rays), keyframes.num_scans)
    return build_rays(keyframes, Normalization(1.0), max_rays_per_scan=per_scan, seed=seed)


def render_order(num_rays: int, max_seconds: float, seed: int) -> np.ndarray:
    """The order rays are rendered in: under a time limit a seeded permutation, so that the rays rendered before the
    limit are a uniform sample of every keyframe's; otherwise their own order."""
    return np.random.default_rng(seed).permutation(num_rays) if max_seconds > 0 else np.arange(num_rays)


def out_of_time(started: float, last_started: float, max_seconds: float) -> bool:
    """Stop rather than start a piece of work that would end past the limit if it took as long as the last one
    (max_seconds <= 0: never)."""
    now = time.perf_counter()
    return max_seconds > 0 and (now - started) + (now - last_started) > max_seconds


class CubeToRender(NamedTuple):
    """One real cube of a plan, as the map renders it: slot_of [K] each keyframe's slot in the cube (-1: not a
    member), params its field's parameters, norm its normalisation, poses [W, 4, 4] its keyframes' refined poses in
    its frame (float32)."""

    slot_of: np.ndarray
    params: object
    norm: Normalization
    poses: jax.Array


def cubes_to_render(refined) -> list[CubeToRender]:
    """The real cubes (weight > 0) of refined.plan with their fields and refined poses (steps.refine.Refined)."""
    plan, fields = refined.plan, refined.result.state.params["fields"]
    cubes = []
    for m in np.flatnonzero(plan.weight > 0):
        slot_of = np.full(len(refined.poses), -1)
        slot_of[plan.members[m]] = np.arange(len(plan.members[m]))
        norm_m = plan.norms[m]
        cubes.append(
            CubeToRender(
                slot_of,
                jax.tree.map(lambda x, m=m: x[m], fields),
                norm_m,
                jnp.asarray(norm_m.poses_to_normalized(refined.poses_in_field[plan.members[m]]), jnp.float32),
            )
        )
    return cubes


def render_parts(order: np.ndarray, max_seconds: float, num_cubes: int) -> list[np.ndarray]:
    """The parts the rays of `order` are rendered in, the clock read between them: all at once without a limit;
    under one each batch with one cube, RENDER_PARTS parts with several (each part costs every cube a batch)."""
    if max_seconds <= 0:
        return [order]
    if num_cubes == 1:
        return [order[i : i + RAYS_PER_BATCH] for i in range(0, len(order), RAYS_PER_BATCH)]
    return np.array_split(order, RENDER_PARTS)


class _MapSoFar(NamedTuple):
    """Per ray [R]: the centrality of the point kept so far (inf: none), the point [R, 3] in the world before the
    anchor, its range in metres and its opacity (NaN: not rendered)."""

    centrality: np.ndarray
    points_w: np.ndarray
    ranges_m: np.ndarray
    opacity: np.ndarray


def _render_batch(
    cube: CubeToRender,
    field: DensityField,
    sampler_m: SamplerSettings,
    alpha,
    rays: RaySet,
    idx: np.ndarray,
    so_far: _MapSoFar,
) -> None:
    """Render rays idx [n <= RAYS_PER_BATCH] (padded to a batch: one compile) in `cube` and keep, in so_far, the
    points more central in it than those kept before."""
    pad = RAYS_PER_BATCH - len(idx)
    slots = np.pad(cube.slot_of[rays.scan_index[idx]], (0, pad), mode="edge")
    directions = np.pad(rays.directions[idx], ((0, pad), (0, 0)), mode="edge")
    p_n, op = render_points(
        cube.params,
        field,
        sampler_m,
        jnp.float32(cube.norm.scale),
        cube.poses[slots],
        jnp.asarray(directions, jnp.float32),
        alpha,
    )
    p_n, op = np.asarray(p_n, np.float64)[: len(idx)], np.asarray(op)[: len(idx)]
    centrality = np.abs(p_n).max(axis=1)
    better = centrality < so_far.centrality[idx]
    kept = idx[better]
    so_far.centrality[kept] = centrality[better]
    so_far.points_w[kept] = cube.norm.points_to_world(p_n[better])
    origins_n = np.asarray(cube.poses)[slots[: len(idx)][better], :3, 3]
    so_far.ranges_m[kept] = np.linalg.norm(p_n[better] - origins_n, axis=1) / cube.norm.scale
    so_far.opacity[kept] = op[better]


def rendered_map(
    mapping_cfg, sampling_cfg, refined, keyframes, seed: int, max_seconds: float = 0.0, progress: bool = False
) -> MapRender | None:
    """Step 4 of a run: the map of `refined` (neld_jax.steps.refine.Refined) rendered along mapping_rays of
    `keyframes` (mapping_cfg: config.mapping) with the sampler of sampling_cfg (config.sampling) at the mapping's
    sample counts; None with mapping.enabled off."""
    if not mapping_cfg.enabled:
        return None
    sampler = sampler_settings(sampling_cfg, mapping_cfg.num_coarse, mapping_cfg.num_fine)
    return render_map(
        refined,
        mapping_rays(mapping_cfg, keyframes, seed),
        sampler,
        float(mapping_cfg.min_opacity),
        max_seconds,
        seed,
        progress,
    )


def render_map(
    refined,
    rays: RaySet,
    sampler_m: SamplerSettings,
    min_opacity: float,
    max_seconds: float = 0.0,
    seed: int = 0,
    progress: bool = False,
) -> MapRender:
    """Render `rays` (ranges in metres, scan_index: keyframes) with the fields and poses of `refined`
    (neld_jax.steps.refine.Refined); points in the world, anchored as refined.poses.

    Each cube renders the rays of its keyframes in its own frame; a ray held by several cubes keeps the point the
    most central in its cube. max_seconds > 0: a time limit; the rays go in parts of a random order, and no part is
    started that would end past the limit if it took as long as the one before; the rays left out get NaN."""
    from tqdm.auto import tqdm

    scan_index = np.asarray(rays.scan_index)
    r = len(scan_index)
    so_far = _MapSoFar(np.full(r, np.inf), np.zeros((r, 3)), np.full(r, np.nan), np.full(r, np.nan))
    cubes = cubes_to_render(refined)
    max_seconds = float(max_seconds)
    alpha = jnp.float32(refined.alpha)
    t0 = time.perf_counter()
    with tqdm(total=r * len(cubes), disable=not progress, desc="rendered map", unit="ray") as bar:
        for part in render_parts(render_order(r, max_seconds, seed), max_seconds, len(cubes)):
            t_part = time.perf_counter()
            for cube in cubes:
                sel = part[cube.slot_of[scan_index[part]] >= 0]
                for start in range(0, len(sel), RAYS_PER_BATCH):
                    idx = sel[start : start + RAYS_PER_BATCH]
                    _render_batch(cube, refined.field, sampler_m, alpha, rays, idx, so_far)
                    bar.update(len(idx))
            if out_of_time(t0, t_part, max_seconds):
                break
    hit = so_far.opacity >= float(min_opacity)  # NaN (not rendered) is not a hit
    points = so_far.points_w[hit] @ refined.anchor[:3, :3].T + refined.anchor[:3, 3]
    render = MapRender(rays, points, so_far.ranges_m, so_far.opacity)
    logger.info(
        "rendered map: %d of %d rendered rays end on a surface%s",
        len(points),
        render.num_rendered,
        "" if len(cubes) == 1 else f" (stitched from {len(cubes)} submaps)",
    )
    if render.num_rendered < r:
        logger.warning(
            "rendered map: %d of its %d rays (a uniform sample) were rendered in the %.0f s it may take "
            "(mapping.max_seconds; 0 renders every ray)",
            render.num_rendered,
            r,
            max_seconds,
        )
    return render
