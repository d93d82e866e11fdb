"""The effectful part of a run with submaps (called by neld_jax.run when the sequence outgrows one cube):
rays per submap, the device mesh, resumable training, the optimised poses in the world and the rendered map
stitched from the submaps. The outputs are the single cube's: one pose per keyframe, one rendered map.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time
from typing import NamedTuple

import jax
import numpy as np

from neld_jax import export, mapping, submap_train, submaps, train
from neld_jax.checkpoint import fit_resuming
from neld_jax.data.normalize import Normalization
from neld_jax.data.preprocess import voxel_downsample
from neld_jax.data.rays import build_mapping_rays, build_rays
from neld_jax.mapping import MapRender

logger = logging.getLogger(__name__)

# Parts of the rendered map's rays under a time limit (mapping.max_seconds): the finer, the closer the stop to the
# limit, but each part costs every submap a padded batch of its own.
RENDER_PARTS = 4


def num_devices(config) -> int:
    """submaps.devices, or every visible device (jax.devices(): every host's after jax.distributed.initialize)."""
    requested, available = int(config.submaps.devices), len(jax.devices())
    if requested > available:
        from neld_jax.errors import ConfigError

        raise ConfigError(f"submaps.devices={requested}, but only {available} devices are visible")
    return requested if requested > 0 else available


class SubmapResult(NamedTuple):
    result: train.FitResult
    T_field: np.ndarray  # [S, 4, 4] optimised keyframe poses in the world (metres), before anchoring
    G: np.ndarray  # [4, 4] world-frame anchor transform (train.anchor_scan)
    setup: submap_train.SubmapSetup


def train_submaps(config, seq, norm: Normalization, T_start: np.ndarray, plan: submaps.SubmapPlan, out_dir: str,
                  chash: str, progress: bool, max_seconds: float | None = None) -> SubmapResult:
    """Train the plan's submaps from the keyframe poses T_start [S, 4, 4] (world; also the start whose scale
    train.keep_start_scale keeps); resumes from out_dir/checkpoints. max_seconds: the training guard (None:
    train.max_minutes).

    The rays are the single cube's (same seed and subset), ranges in each submap's units (submaps.submap_arrays)."""
    rays_metres = build_rays(seq, Normalization(1.0), max_rays_per_scan=(config.data.max_rays_per_scan or None),
                             seed=config.seed)
    arrays = submaps.submap_arrays(plan, rays_metres, T_start)
    mesh = submap_train.make_mesh(submaps.mesh_size(plan, num_devices(config)))
    setup = submap_train.create_submap_state(config, seq.num_scans, plan.num_submaps, mesh, T_start)
    field_lr = setup.schedules.field_lr
    logger.info("submaps: %d submaps (%d rays each at most, %d drawn per step, fields %d wide, learning rate %g -> "
                "%g, termination loss weight %g) on a mesh of %d %s device(s)", plan.num_submaps,
                arrays.directions.shape[1], submap_train.submap_batch_rays(config, plan.num_submaps), setup.field.width,
                float(field_lr(0)), float(field_lr(setup.schedules.total_steps)),
                submap_train.submap_loss_settings(config).lambda_termination, mesh.size, jax.devices()[0].platform)
    rays, frames = submap_train.from_arrays(arrays)
    rays = submap_train.place(rays, submap_train.data_sharding(rays, mesh))
    frames = submap_train.place(frames, submap_train.data_sharding(frames, mesh))

    metadata = {"config_hash": chash, "normalization": norm.to_dict(), "num_scans": seq.num_scans,
                "submaps": plan.to_dict()}
    result = fit_resuming(os.path.join(out_dir, "checkpoints"), metadata, lambda: setup.state,
                          functools.partial(submap_train.fit_submaps, config, setup, rays, frames, plan.ref_scale,
                                            progress=progress, max_seconds=max_seconds))
    T_field = submaps.global_poses(T_start, np.asarray(result.state.params["poses"]), plan.ref_scale)
    G = np.eye(4)
    anchor = int(config.train.anchor_scan)
    if anchor >= 0:  # as model.anchor_transform, in the world: the anchor scan keeps its starting pose
        G = T_start[anchor] @ np.linalg.inv(T_field[anchor])
    return SubmapResult(result, T_field, G, setup)


def write_rendered_map(config, trained: SubmapResult, plan: submaps.SubmapPlan, norm: Normalization, seq,
                       out_dir: str, progress: bool, max_seconds: float):
    """The rendered map stitched from the submaps: each ray rendered by every submap holding its scan, kept from
    the one whose cube holds its point most centrally; map_rendered.ply in the world (anchored). max_seconds: the
    render's time limit (0: none; neld_jax.run.rendering_seconds).

    Returns (mapping rays, MapRender) in the whole sequence's normalisation `norm`, as the single cube's map does,
    for the per-scan residuals."""
    from tqdm.auto import tqdm

    m = config.mapping
    mapping_rays = build_mapping_rays(config, seq, norm)
    sampler = dataclasses.replace(train.sampler_settings(config, 1.0, m.num_coarse, m.num_fine), guided_samples=0)
    state, setup = trained.result.state, trained.setup
    # The window the fields were trained with (config's train.steps: the plan that ran, neld_jax.run)
    alpha = float(train.make_schedules(config).alpha(int(state.step)))
    scan_index = np.asarray(mapping_rays.scan_index)
    r = len(scan_index)
    best_r = np.full(r, np.inf)
    points_w, ranges_m, opacity = np.zeros((r, 3)), np.full(r, np.nan), np.full(r, np.nan)
    real = np.flatnonzero(plan.weight > 0)
    # Per submap, once: its keyframes' slot of each scan (-1: not a member), its field, frame and poses in it.
    slots = []
    for sub in real:
        slot_of = np.full(seq.num_scans, -1)
        slot_of[plan.members[sub]] = np.arange(len(plan.members[sub]))
        norm_m = plan.norms[sub]
        slots.append((slot_of, jax.tree.map(lambda x: x[sub], state.params["fields"]), norm_m,
                      norm_m.poses_to_normalized(trained.T_field[plan.members[sub]])))
    # Under a time limit the rays go in RENDER_PARTS parts of a random order, every submap rendering each part's
    # rays, so that the parts rendered before the limit are a uniform sample of the map; as for one cube, no part
    # is started that would end past the limit if it took as long as the one before.
    max_seconds = float(max_seconds)
    order = mapping.render_order(r, max_seconds, config.seed + 1)
    parts = np.array_split(order, RENDER_PARTS if max_seconds > 0 else 1)
    t0 = time.perf_counter()
    with tqdm(total=len(real) * len(parts), disable=not progress, desc="rendered map (submaps)", unit="submap") as bar:
        for part in parts:
            t_part = time.perf_counter()
            for slot_of, fields_m, norm_m, T_n in slots:
                sel = part[slot_of[scan_index[part]] >= 0]
                p_n, op = submap_train.render_submap_rays(fields_m, setup.field, sampler, norm_m.scale, T_n,
                                                          mapping_rays.directions[sel], slot_of[scan_index[sel]],
                                                          alpha, int(m.rays_per_batch))
                centrality = np.abs(p_n).max(axis=1)
                better = centrality < best_r[sel]
                idx = sel[better]
                best_r[idx] = centrality[better]
                points_w[idx] = norm_m.points_to_world(p_n[better])
                origins_n = T_n[slot_of[scan_index[idx]], :3, 3]
                ranges_m[idx] = np.linalg.norm(p_n[better] - origins_n, axis=1) / norm_m.scale
                opacity[idx] = op[better]
                bar.update()
            if mapping.out_of_time(t0, t_part, max_seconds):
                break
    kept = opacity >= float(m.min_opacity)  # NaN (not rendered) is not kept
    points = points_w[kept] @ trained.G[:3, :3].T + trained.G[:3, 3]
    render = MapRender(norm.points_to_normalized(points), ranges_m * norm.scale, opacity)
    logger.info("rendered map stitched from %d submaps", len(real))
    mapping.log_rendered_rays(int(kept.sum()), render.num_rendered, r, max_seconds)
    if kept.any():
        export.write_point_cloud(os.path.join(out_dir, "map_rendered.ply"),
                                 voxel_downsample(points, float(m.voxel_size_m)))
    else:
        logger.warning("rendered map is empty: no ray reached opacity %.2f; map_rendered.ply not written",
                       m.min_opacity)
    return mapping_rays, render
