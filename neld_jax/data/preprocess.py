"""Scan preprocessing: keyframes at most 3 s apart (and close enough in space to overlap), points within 0.5-80 m,
0.05 m voxel grid.

Per-scan fields (scans, poses, timestamps, gt_poses, files) are subset together; a scan that the range
crop empties is a DataError naming its file (and time), e.g. "scans/000002.pcd (t=6.000000)"."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.geometry import invert_poses, rotation_angles_deg

logger = logging.getLogger(__name__)


KEYFRAME_RANGE_FRACTION = 0.1  # with the time cap on and no distance cap given: a tenth of the sensor's range
KEYFRAME_ANGLE_DEG = 30.0  # with the time cap on and no angle cap given


def select_keyframes(
    timestamps: np.ndarray | None, interval_s: float, num_scans: int | None = None,
    poses: np.ndarray | None = None, distance_m: float = 0.0, angle_deg: float = 0.0,
) -> np.ndarray:
    """Indices [K] int64 of keyframes: neighbouring keyframes lie at most `interval_s` apart in time (needs
    timestamps), `distance_m` apart in space and `angle_deg` apart in rotation (need poses [S, 4, 4]) where they
    can. The first scan is one; a scan after it is one when the next scan would lie beyond any of these caps from
    the last keyframe (whichever first), so each keyframe is the last scan within the caps, and an input sparser
    than the caps keeps every scan: the last scan is one where it lies beyond half a cap from the scan before it.
    A cap is off when it is <= 0 (or its input None); with every cap off all scans are kept. `num_scans` is needed
    only when timestamps and poses are both None."""
    if timestamps is not None:
        timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        num_scans = timestamps.size
    elif poses is not None:
        num_scans = len(poses)
    elif num_scans is None:
        raise ValueError("select_keyframes: pass num_scans when there are no timestamps and no poses")
    use_time = timestamps is not None and interval_s > 0
    use_space = poses is not None and (distance_m > 0 or angle_deg > 0)
    if not (use_time or use_space) or num_scans == 0:
        return np.arange(num_scans, dtype=np.int64)

    def beyond_caps(last: int, scan: int, share: float = 1.0) -> bool:
        # Small slacks so that scans exactly a cap apart (up to float rounding) lie within it.
        if use_time and timestamps[scan] - timestamps[last] > share * interval_s + 1e-6:
            return True
        if not use_space:
            return False
        relative = invert_poses(poses[last]) @ poses[scan]
        return bool((distance_m > 0 and np.linalg.norm(relative[:3, 3]) > share * distance_m + 1e-9)
                    or (angle_deg > 0 and rotation_angles_deg(relative[:3, :3]) > share * angle_deg + 1e-6))

    kept = [0]
    for i in range(1, num_scans - 1):
        if beyond_caps(kept[-1], i + 1):
            kept.append(i)
    if num_scans > 1 and beyond_caps(num_scans - 2, num_scans - 1, share=0.5):  # a sparse input's last scan
        kept.append(num_scans - 1)
    return np.asarray(kept, dtype=np.int64)


def keyframe_caps(interval_s: float, distance_m: float, angle_deg: float, max_range_m: float) -> tuple[float, float]:
    """(distance cap m, angle cap deg) of select_keyframes from the config's: with the time cap on (interval_s > 0),
    a distance cap of 0 is KEYFRAME_RANGE_FRACTION of the sensor's range and an angle cap of 0 KEYFRAME_ANGLE_DEG,
    so that neighbouring keyframes overlap however fast the sensor moves; with it off, as given (0: off)."""
    if interval_s <= 0:
        return distance_m, angle_deg
    return (distance_m if distance_m > 0 else KEYFRAME_RANGE_FRACTION * max_range_m,
            angle_deg if angle_deg > 0 else KEYFRAME_ANGLE_DEG)


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
    """Select keyframes (select_keyframes' caps), crop each scan by range and voxel-downsample it.

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
        "keyframes: kept %d of %d scans (at most %.3g s, %.3g m, %.3g deg apart; max_scans %s)",
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
    distance_m, angle_deg = keyframe_caps(data_cfg.keyframe_interval_s, data_cfg.get("keyframe_distance_m", 0.0),
                                          data_cfg.get("keyframe_angle_deg", 0.0), data_cfg.max_range_m)
    keyframes = preprocess(loaded, keyframe_interval_s=data_cfg.keyframe_interval_s,
                           min_range=data_cfg.min_range_m, max_range=data_cfg.max_range_m,
                           voxel_size=data_cfg.voxel_size_m, max_scans=(data_cfg.max_scans or None),
                           keyframe_distance_m=distance_m, keyframe_angle_deg=angle_deg,
                           first_scan=int(data_cfg.get("first_scan", 0)))
    return loaded, keyframes
