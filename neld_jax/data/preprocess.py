"""Scan preprocessing as in the paper: keyframes every 3 s, points within 0.5-80 m, 0.05 m voxel grid.

Per-scan fields (scans, poses, timestamps, gt_poses, files) are subset together; a scan that the range
crop empties is a DataError naming its file (and time), e.g. "scans/000002.pcd (t=6.000000)"."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import open3d as o3d

from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)


def select_keyframes(
    timestamps: np.ndarray | None, interval_s: float, num_scans: int | None = None
) -> np.ndarray:
    """Indices [K] int64 of keyframes: the first scan, then each scan at least `interval_s` after the last kept.

    timestamps: [S] seconds, or None. All scans are kept when timestamps is None or interval_s <= 0;
    with timestamps None the scan count must be given as `num_scans`."""
    if timestamps is None:
        if num_scans is None:
            raise ValueError("select_keyframes: pass num_scans when there are no timestamps")
        return np.arange(num_scans, dtype=np.int64)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if interval_s <= 0 or timestamps.size == 0:
        return np.arange(timestamps.size, dtype=np.int64)
    kept = [0]
    for i in range(1, timestamps.size):
        # Small slack so that scans exactly interval_s apart (up to float rounding) are kept.
        if timestamps[i] - timestamps[kept[-1]] >= interval_s - 1e-6:
            kept.append(i)
    return np.asarray(kept, dtype=np.int64)


def crop_range(points: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """points: [N, 3] sensor frame -> the points with min_range <= |p| <= max_range: [N', 3]."""
    distances = np.linalg.norm(points, axis=1)
    return points[(distances >= min_range) & (distances <= max_range)]


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """points: [N, 3] -> one point (the centroid) per occupied voxel: [N', 3]. voxel_size <= 0: unchanged."""
    if voxel_size <= 0 or points.shape[0] == 0:
        return points
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    return np.asarray(cloud.voxel_down_sample(voxel_size).points, dtype=np.float64)


def preprocess(
    seq: Sequence,
    keyframe_interval_s: float = 3.0,
    min_range: float = 0.5,
    max_range: float = 80.0,
    voxel_size: float = 0.05,
    max_scans: int | None = None,
) -> Sequence:
    """Select keyframes, crop each scan by range and voxel-downsample it. Returns a new Sequence.

    max_scans (if set) keeps only the first max_scans keyframes. A scan left empty raises DataError."""
    keep = select_keyframes(seq.timestamps, keyframe_interval_s, num_scans=seq.num_scans)
    if max_scans is not None and max_scans > 0:
        keep = keep[:max_scans]
    logger.info(
        "keyframes: kept %d of %d scans (interval %.3g s, max_scans %s)",
        len(keep), seq.num_scans, keyframe_interval_s, max_scans,
    )

    scans = []
    totals = np.zeros(3, dtype=np.int64)  # raw, after range crop, after voxel grid
    for index in keep:
        raw = seq.scans[index]
        cropped = crop_range(raw, min_range, max_range)
        downsampled = voxel_downsample(cropped, voxel_size)
        logger.debug("%s: %d points -> %d in range -> %d after voxel grid",
                     seq.scan_label(index), len(raw), len(cropped), len(downsampled))
        if downsampled.shape[0] == 0:
            distances = np.linalg.norm(raw, axis=1)
            raise DataError(
                f"{seq.source or seq.name}: {seq.scan_label(index)} has no points left within "
                f"{min_range}-{max_range} m (it had {len(raw)} points, "
                f"{distances.min():.3g}-{distances.max():.3g} m from the sensor; check the units or "
                "data.min_range_m / data.max_range_m)"
            )
        totals += (len(raw), len(cropped), len(downsampled))
        scans.append(downsampled)
    logger.info(
        "points: %d raw -> %d within %.3g-%.3g m -> %d after %.3g m voxel grid (%.0f per scan)",
        totals[0], totals[1], min_range, max_range, totals[2], voxel_size, totals[2] / max(len(keep), 1),
    )
    return dataclasses.replace(
        seq,
        scans=scans,
        poses=seq.poses[keep],
        timestamps=None if seq.timestamps is None else seq.timestamps[keep],
        gt_poses=None if seq.gt_poses is None else seq.gt_poses[keep],
        files=None if seq.files is None else [seq.files[i] for i in keep],
    )


def load_preprocessed(data_cfg) -> Sequence:
    """Load the sequence that `data_cfg` (config.data) names and preprocess it with the config's settings.

    The one place where bin/train.py and bin/baseline.py turn a config into the scans they work on.
    """
    from neld_jax.data.datasets import load_sequence

    return preprocess(load_sequence(data_cfg), keyframe_interval_s=data_cfg.keyframe_interval_s,
                      min_range=data_cfg.min_range_m, max_range=data_cfg.max_range_m,
                      voxel_size=data_cfg.voxel_size_m, max_scans=(data_cfg.max_scans or None))
