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
    timestamps: np.ndarray | None,
    interval_s: float,
    num_scans: int | None = None,
    poses: np.ndarray | None = None,
    distance_m: float = 0.0,
    angle_deg: float = 0.0,
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
        return bool(
            (distance_m > 0 and np.linalg.norm(relative[:3, 3]) > share * distance_m + 1e-9)
            or (angle_deg > 0 and rotation_angles_deg(relative[:3, :3]) > share * angle_deg + 1e-6)
        )

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
    return (
        distance_m if distance_m > 0 else KEYFRAME_RANGE_FRACTION * max_range_m,
        angle_deg if angle_deg > 0 else KEYFRAME_ANGLE_DEG,
    )


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


@dataclasses.dataclass(frozen=True)
class KeyframeSettings:
    """Which scans are keyframes and how their points are prepared (config.data; the caps as select_keyframes'
    takes them: keyframe_caps fills a distance or angle cap left 0 under a time cap).

    keyframe_interval_s, keyframe_distance_m, keyframe_angle_deg: the caps (<= 0: off)
    min_range, max_range: metres, the range crop; voxel_size: metres, the voxel grid (<= 0: none)
    max_scans: keep only the first max_scans keyframes (None or <= 0: all); first_scan: none before this scan
    """

    keyframe_interval_s: float = 3.0
    min_range: float = 0.5
    max_range: float = 80.0
    voxel_size: float = 0.05
    max_scans: int | None = None
    keyframe_distance_m: float = 0.0
    keyframe_angle_deg: float = 0.0
    first_scan: int = 0

    @classmethod
    def from_config(cls, data_cfg) -> "KeyframeSettings":
        """config.data's settings, the caps completed by keyframe_caps."""
        distance_m, angle_deg = keyframe_caps(
            data_cfg.keyframe_interval_s,
            data_cfg.get("keyframe_distance_m", 0.0),
            data_cfg.get("keyframe_angle_deg", 0.0),
            data_cfg.max_range_m,
        )
        return cls(
            keyframe_interval_s=data_cfg.keyframe_interval_s,
            min_range=data_cfg.min_range_m,
            max_range=data_cfg.max_range_m,
            voxel_size=data_cfg.voxel_size_m,
            max_scans=(data_cfg.max_scans or None),
            keyframe_distance_m=distance_m,
            keyframe_angle_deg=angle_deg,
            first_scan=int(data_cfg.get("first_scan", 0)),
        )


def keyframe_indices(seq: Sequence, settings: KeyframeSettings) -> np.ndarray:
    """The keyframes [K] int64 of seq (select_keyframes on its stamps and poses, from first_scan on, at most
    max_scans); a DataError when none is left."""
    keep = select_keyframes(
        seq.timestamps,
        settings.keyframe_interval_s,
        num_scans=seq.num_scans,
        poses=seq.poses,
        distance_m=settings.keyframe_distance_m,
        angle_deg=settings.keyframe_angle_deg,
    )
    keep = keep[keep >= settings.first_scan]
    if settings.max_scans is not None and settings.max_scans > 0:
        keep = keep[: settings.max_scans]
    if len(keep) == 0:
        raise DataError(
            f"{seq.source or seq.name}: no keyframes from scan {settings.first_scan} on "
            f"(the sequence has {seq.num_scans} scans)"
        )
    logger.info(
        "keyframes: kept %d of %d scans (at most %.3g s, %.3g m, %.3g deg apart; max_scans %s)",
        len(keep),
        seq.num_scans,
        settings.keyframe_interval_s,
        settings.keyframe_distance_m,
        settings.keyframe_angle_deg,
        settings.max_scans,
    )
    return keep


def keyframe_points(seq: Sequence, index: int, settings: KeyframeSettings) -> tuple[np.ndarray, tuple[int, int]]:
    """Scan `index` of seq (read now, when seq's scans are read when used) cropped by range and on the voxel grid:
    (points [N', 3] float32, (raw, in-range) point counts). float32: a sensor-frame point within 80 m keeps ~5 um,
    and training casts to float32 anyway. A scan left empty is a DataError naming its file."""
    raw = seq.scans[index]
    cropped = crop_range(raw, settings.min_range, settings.max_range)
    downsampled = voxel_downsample(cropped, settings.voxel_size)
    logger.debug(
        "%s: %d points -> %d in range -> %d after voxel grid",
        seq.scan_label(index),
        len(raw),
        len(cropped),
        len(downsampled),
    )
    if downsampled.shape[0] == 0:
        distances = np.linalg.norm(raw, axis=1)
        raise DataError(
            f"{seq.source or seq.name}: {seq.scan_label(index)} has no points left within "
            f"{settings.min_range}-{settings.max_range} m (it had {len(raw)} points, "
            f"{distances.min():.3g}-{distances.max():.3g} m from the sensor; check the units or "
            "data.min_range_m / data.max_range_m)"
        )
    return np.asarray(downsampled, dtype=np.float32), (len(raw), len(cropped))


def preprocess(seq: Sequence, settings: KeyframeSettings = KeyframeSettings()) -> Sequence:
    """Select keyframes (keyframe_indices), crop each by range and voxel-downsample it (keyframe_points).

    Only the keyframes' points are read (seq's scans may be read from disk when used: data.scan_source) and kept,
    as float32. Returns a new Sequence whose `source_index` names each kept scan's index in `seq`, so that results
    can be carried back to every input scan. A scan left empty raises DataError naming its file."""
    keep = keyframe_indices(seq, settings)
    scans = []
    totals = np.zeros(3, dtype=np.int64)  # raw, after range crop, after voxel grid
    for index in keep:
        points, (num_raw, num_cropped) = keyframe_points(seq, int(index), settings)
        totals += (num_raw, num_cropped, len(points))
        scans.append(points)
    logger.info(
        "points: %d raw -> %d within %.3g-%.3g m -> %d after %.3g m voxel grid (%.0f per scan)",
        totals[0],
        totals[1],
        settings.min_range,
        settings.max_range,
        totals[2],
        settings.voxel_size,
        totals[2] / max(len(keep), 1),
    )
    return dataclasses.replace(
        seq,
        scans=scans,
        poses=seq.poses[keep],
        timestamps=None if seq.timestamps is None else seq.timestamps[keep],
        gt_poses=None if seq.gt_poses is None else seq.gt_poses[keep],
        files=None if seq.files is None else [seq.files[i] for i in keep],
        source_index=keep if seq.source_index is None else seq.source_index[keep],
        point_times=None,  # the keyframes are rigid: the front-end has deskewed or refused raw sweeps
    )
