"""The in-memory LiDAR sequence that every loader returns and the trainer consumes, and a plausibility check
on consecutive poses (matching poses to scans by time: timing.py).

Messages about one scan name its file (`Sequence.scan_label`: "scans/000002.pcd (t=1650000006.000000)"),
because after keyframe selection, or with files named by timestamp, an index does not tell the user
which file is meant; only synthetic sequences (no files) fall back to "scan 2".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from neld_jax.data.scan_source import LazyScans, is_lazy
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)


@dataclass
class Sequence:
    """S scans with their initial poses and optional ground truth.

    scans:      S arrays [N_i, 3] float64 (float32 where given so: the keyframes), points in the SENSOR frame: a
                list held in memory, or a LazyScans read from disk when used (data.scan_source: a recording's
                sweeps, which do not fit in memory)
    poses:      [S, 4, 4] float64 initial poses (sensor -> world), e.g. odometry output; None only between a
                loader that found no poses and the front-end, which makes them from the scans (neld_jax.frontend)
    timestamps: [S] float64 seconds, or None
    gt_poses:   [S, 4, 4] float64 ground-truth poses (sensor -> world), or None
    gt_map:     [M, 3] float64 ground-truth map points in the world frame, or None
    name:       short human-readable name (e.g. the folder name)
    source:     where it came from: a path or 'synthetic'
    files:      [S] the file each scan was read from (relative to `source`, or absolute), or None
                (synthetic); carried through keyframe selection so messages can name the file
    source_index: [S] int64 index of each scan in the sequence as loaded (set by keyframe selection), or
                None when these are the loaded scans themselves
    point_times: S arrays [N_i] float64 (a list, or a LazyScans), each point's time in seconds after its scan's
                timestamp (raw full-rate scans: the sweep's motion is still in them), or None (the scans are rigid)
    poses_from: "kiss_icp" when load_sequence made the poses from the scans, else "" (the layout's poses)
    """

    scans: list[np.ndarray] | LazyScans
    poses: np.ndarray | None
    timestamps: np.ndarray | None = None
    gt_poses: np.ndarray | None = None
    gt_map: np.ndarray | None = None
    name: str = "sequence"
    source: str = ""
    files: list[str] | None = None
    source_index: np.ndarray | None = None
    point_times: list[np.ndarray] | LazyScans | None = None
    poses_from: str = ""

    def __post_init__(self) -> None:
        where = f"sequence '{self.name}' ({self.source or 'no source'})"
        if not is_lazy(self.scans):
            self.scans = [_points_array(scan) for scan in self.scans]
        num_scans = len(self.scans)
        if self.files is not None:
            self.files = [str(f) for f in self.files]
            if len(self.files) != num_scans:
                raise DataError(f"{where}: {len(self.files)} file names for {num_scans} scans")
        if not is_lazy(self.scans):  # lazy scans are checked as they are read (scans.read_scan)
            for i, scan in enumerate(self.scans):
                if scan.ndim != 2 or scan.shape[1] != 3:
                    raise DataError(f"{where}: {self.scan_label(i)} must have shape [N, 3], got {scan.shape}")
        if self.poses is not None:
            self.poses = np.asarray(self.poses, dtype=np.float64)
            if self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4):
                raise DataError(f"{where}: poses must have shape [S, 4, 4], got {self.poses.shape}")
            if self.poses.shape[0] != num_scans:
                raise DataError(f"{where}: {self.poses.shape[0]} poses for {num_scans} scans")
        if self.point_times is not None:
            self._check_point_times(where)
        self._check_per_scan_arrays(where)

    def _check_point_times(self, where: str) -> None:
        """point_times: one [N_i] per scan; held in memory, each as long as its scan (lazy: when read)."""
        if not is_lazy(self.point_times):
            self.point_times = [np.asarray(t, dtype=np.float64).reshape(-1) for t in self.point_times]
        if len(self.point_times) != len(self.scans):
            raise DataError(f"{where}: per-point times for {len(self.point_times)} of {len(self.scans)} scans")
        if is_lazy(self.point_times) or is_lazy(self.scans):
            return
        for i, (scan, times) in enumerate(zip(self.scans, self.point_times)):
            if times.shape[0] != scan.shape[0]:
                raise DataError(
                    f"{where}: {self.scan_label(i)} has {scan.shape[0]} points and {times.shape[0]} point times"
                )

    def _check_per_scan_arrays(self, where: str) -> None:
        """timestamps, gt_poses, source_index: one per scan; gt_map [M, 3]."""
        num_scans = len(self.scans)
        if self.timestamps is not None:
            self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
            if self.timestamps.shape[0] != num_scans:
                raise DataError(f"{where}: {self.timestamps.shape[0]} timestamps for {num_scans} scans")
        if self.gt_poses is not None:
            self.gt_poses = np.asarray(self.gt_poses, dtype=np.float64)
            if self.gt_poses.shape != (num_scans, 4, 4):
                raise DataError(
                    f"{where}: {self.gt_poses.shape[0] if self.gt_poses.ndim else 0} ground-truth poses "
                    f"(shape {self.gt_poses.shape}) for {num_scans} scans"
                )
        if self.source_index is not None:
            self.source_index = np.asarray(self.source_index, dtype=np.int64).reshape(-1)
            if self.source_index.shape[0] != num_scans:
                raise DataError(f"{where}: {self.source_index.shape[0]} source indices for {num_scans} scans")
        if self.gt_map is not None:
            self.gt_map = np.asarray(self.gt_map, dtype=np.float64)
            if self.gt_map.ndim != 2 or self.gt_map.shape[1] != 3:
                raise DataError(f"{where}: gt_map must have shape [M, 3], got {self.gt_map.shape}")

    def scan_label(self, i: int) -> str:
        """How messages name scan i: its file and, when known, its time; "scan i" without files."""
        label = f"scan {i}" if self.files is None else self.files[i]
        if self.timestamps is not None and len(self.timestamps) == len(self.scans):
            label += f" (t={self.timestamps[i]:.6f})"
        return label

    @property
    def loaded_index(self) -> np.ndarray:
        """[S] int64 index of each scan in the sequence as loaded: source_index, or 0..S-1 when unset."""
        return self.source_index if self.source_index is not None else np.arange(self.num_scans, dtype=np.int64)

    @property
    def num_scans(self) -> int:
        return len(self.scans)

    @property
    def num_points(self) -> int:
        """Total number of points over all scans (reads every scan of lazy scans once)."""
        return int(sum(scan.shape[0] for scan in self.scans))


def _points_array(scan) -> np.ndarray:
    """A scan held in memory as an array: float32 stays float32 (keyframes: data.preprocess), else float64."""
    scan = np.asarray(scan)
    return scan if scan.dtype in (np.float32, np.float64) else scan.astype(np.float64)


# A step is a jump when it is JUMP_FACTOR times the 90th-percentile step, and at least MIN_JUMP_M.
# Relative, not a fixed distance: steps between consecutive scans range from centimetres (handheld,
# 10 Hz) to tens of metres (a car, keyframes 3 s apart), so any fixed threshold is blind on one and
# noisy on the other. The 90th percentile, not the median: a car that waits at lights for half the
# recording has a median step of ~0, yet its moving steps are normal. The floor keeps a (nearly)
# standing platform from warning about centimetre steps.
JUMP_FACTOR = 5.0
MIN_JUMP_M = 1.0
_MAX_JUMPS_LISTED = 3


def check_pose_jumps(
    poses: np.ndarray,
    labels: list[str] | None = None,
    max_step_m: float | None = None,
    what: str = "poses",
) -> np.ndarray:
    """Warn (logger.warning, naming both scans) about consecutive poses implausibly far apart.

    poses: [S, 4, 4]; labels: [S] how to name each scan (files), else "scan i"; max_step_m: the largest
    plausible distance between consecutive positions, default max(MIN_JUMP_M, JUMP_FACTOR x the 90th
    percentile step); what: names the pose source in the message. Returns the indices i [J] int64 of the
    jumps from scan i to scan i + 1. Only warns: the run goes on (odometry does glitch, and a user may
    mean it), but a jump is the first suspect when the result is bad."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape[0] < 2:
        return np.zeros(0, dtype=np.int64)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    threshold = max_step_m if max_step_m is not None else max(MIN_JUMP_M, JUMP_FACTOR * np.percentile(steps, 90))
    jumps = np.flatnonzero(steps > threshold).astype(np.int64)
    name = (lambda i: f"scan {i}") if labels is None else (lambda i: labels[i])
    for i in jumps[:_MAX_JUMPS_LISTED]:
        logger.warning(
            "%s: the pose jumps %.3g m from %s to %s (more than the %.3g m plausible between consecutive scans)",
            what,
            steps[i],
            name(i),
            name(i + 1),
            threshold,
        )
    if jumps.size > _MAX_JUMPS_LISTED:
        logger.warning(
            "%s: %d more pose jumps over %.3g m (%d in all)",
            what,
            jumps.size - _MAX_JUMPS_LISTED,
            threshold,
            jumps.size,
        )
    return jumps
