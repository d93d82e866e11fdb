"""Scan preprocessing as in the paper: keyframes every 3 s, points within 0.5-80 m, 0.05 m voxel grid.

Per-scan fields (scans, poses, timestamps, gt_poses, files) are subset together; a scan that the range
crop empties is a DataError naming its file (and time), e.g. "scans/000002.pcd (t=6.000000)"."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.geometry import moved_enough

logger = logging.getLogger(__name__)


def select_keyframes(
    timestamps: np.ndarray | None, interval_s: float, num_scans: int | None = None,
    poses: np.ndarray | None = None, distance_m: float = 0.0, angle_deg: float = 0.0,
) -> np.ndarray:
    """Indices [K] int64 of keyframes: the first scan, then each scan that is far enough from the last kept
    one by ANY enabled rule: at least `interval_s` later (needs timestamps), or at least `distance_m` away or
    `angle_deg` turned (spatial rules, need poses [S, 4, 4]). A rule is off when its threshold is <= 0 (or its
    input is None); with every rule off all scans are kept. `num_scans` is needed only when timestamps and
    poses are both None."""
    if timestamps is not None:
        timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        num_scans = timestamps.size
    elif poses is not None:
        num_scans = len(poses)
    elif num_scans is None:
        raise ValueError("select_keyframes: pass num_scans when there are no timestamps and no poses")
    use_time = timestamps is not None and interval_s > 0
    use_distance = poses is not None and distance_m > 0
    use_angle = poses is not None and angle_deg > 0
    if not (use_time or use_distance or use_angle) or num_scans == 0:
        return np.arange(num_scans, dtype=np.int64)
    kept = [0]
    for i in range(1, num_scans):
        last = kept[-1]
        # Small slack so that scans exactly interval_s apart (up to float rounding) are kept.
        keep = use_time and timestamps[i] - timestamps[last] >= interval_s - 1e-6
        if (use_distance or use_angle) and not keep:
            keep = moved_enough(poses[last], poses[i], distance_m if use_distance else 0.0,
                                angle_deg if use_angle else 0.0)
        if keep:
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
    import open3d as o3d  # here: the training path imports this module on machines without open3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    return np.asarray(cloud.voxel_down_sample(voxel_size).points, dtype=np.float64)


def preprocess(
    seq: Sequence,
    keyframe_interval_s: float = 3.0,
    min_range: float = 0.5,
    max_range: float = 80.0,
    voxel_size: float = 0.05,
    max_scans: int | None = None,
    keyframe_distance_m: float = 0.0,
    keyframe_angle_deg: float = 0.0,
    first_scan: int = 0,
) -> Sequence:
    """Select keyframes (select_keyframes' rules), crop each scan by range and voxel-downsample it.

    Returns a new Sequence whose `source_index` names each kept scan's index in `seq`, so that results can
    be carried back to every input scan. max_scans (if set) keeps only the first max_scans keyframes. A scan
    left empty raises DataError naming its file."""
    keep = select_keyframes(seq.timestamps, keyframe_interval_s, num_scans=seq.num_scans, poses=seq.poses,
                            distance_m=keyframe_distance_m, angle_deg=keyframe_angle_deg)
    keep = keep[keep >= first_scan]
    if max_scans is not None and max_scans > 0:
        keep = keep[:max_scans]
    if len(keep) == 0:
        raise DataError(f"{seq.source or seq.name}: no keyframes from scan {first_scan} on "
                        f"(the sequence has {seq.num_scans} scans)")
    logger.info(
        "keyframes: kept %d of %d scans (interval %.3g s, distance %.3g m, angle %.3g deg, max_scans %s)",
        len(keep), seq.num_scans, keyframe_interval_s, keyframe_distance_m, keyframe_angle_deg, max_scans,
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
        source_index=keep if seq.source_index is None else seq.source_index[keep],
        point_times=None,  # the keyframes are rigid: load_sequence has deskewed or refused raw sweeps
    )


def load_keyframes(data_cfg) -> tuple[Sequence, Sequence]:
    """Load the sequence that `data_cfg` (config.data) names and preprocess it with the config's settings.

    Returns (loaded, keyframes): every input scan as read, and the preprocessed keyframes that training
    uses (`keyframes.source_index` indexes `loaded`). The one place where bin/train.py and bin/baseline.py
    turn a config into the scans they work on.
    """
    from neld_jax.data.formats import load_sequence

    loaded = load_sequence(data_cfg)
    keyframes = preprocess(loaded, keyframe_interval_s=data_cfg.keyframe_interval_s,
                           min_range=data_cfg.min_range_m, max_range=data_cfg.max_range_m,
                           voxel_size=data_cfg.voxel_size_m, max_scans=(data_cfg.max_scans or None),
                           keyframe_distance_m=data_cfg.get("keyframe_distance_m", 0.0),
                           keyframe_angle_deg=data_cfg.get("keyframe_angle_deg", 0.0),
                           first_scan=int(data_cfg.get("first_scan", 0)))
    return loaded, keyframes
