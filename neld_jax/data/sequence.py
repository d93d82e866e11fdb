"""The in-memory LiDAR sequence that every loader returns and the trainer consumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neld_jax.errors import DataError


@dataclass
class Sequence:
    """S scans with their initial poses and optional ground truth.

    scans:      list of S arrays [N_i, 3] float64, points in the SENSOR frame
    poses:      [S, 4, 4] float64 initial poses (sensor -> world), e.g. odometry output
    timestamps: [S] float64 seconds, or None
    gt_poses:   [S, 4, 4] float64 ground-truth poses (sensor -> world), or None
    gt_map:     [M, 3] float64 ground-truth map points in the world frame, or None
    name:       short human-readable name (e.g. the folder name)
    source:     where it came from: a path or 'synthetic'
    files:      S scan file names relative to `source` (for messages and reports), or None
    source_index: [S] int64 index of each scan in the sequence as loaded (set by keyframe selection), or
                None when these are the loaded scans themselves
    """

    scans: list[np.ndarray]
    poses: np.ndarray
    timestamps: np.ndarray | None = None
    gt_poses: np.ndarray | None = None
    gt_map: np.ndarray | None = None
    name: str = "sequence"
    source: str = ""
    files: list[str] | None = None
    source_index: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = f"sequence '{self.name}' ({self.source or 'no source'})"
        self.scans = [np.asarray(scan, dtype=np.float64) for scan in self.scans]
        for i, scan in enumerate(self.scans):
            if scan.ndim != 2 or scan.shape[1] != 3:
                raise DataError(f"{where}: scan {i} must have shape [N, 3], got {scan.shape}")
        self.poses = np.asarray(self.poses, dtype=np.float64)
        if self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4):
            raise DataError(f"{where}: poses must have shape [S, 4, 4], got {self.poses.shape}")
        num_scans = len(self.scans)
        if self.poses.shape[0] != num_scans:
            raise DataError(f"{where}: {self.poses.shape[0]} poses for {num_scans} scans")
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
        if self.files is not None:
            self.files = [str(f) for f in self.files]
            if len(self.files) != num_scans:
                raise DataError(f"{where}: {len(self.files)} file names for {num_scans} scans")
        if self.source_index is not None:
            self.source_index = np.asarray(self.source_index, dtype=np.int64).reshape(-1)
            if self.source_index.shape[0] != num_scans:
                raise DataError(f"{where}: {self.source_index.shape[0]} source indices for {num_scans} scans")
        if self.gt_map is not None:
            self.gt_map = np.asarray(self.gt_map, dtype=np.float64)
            if self.gt_map.ndim != 2 or self.gt_map.shape[1] != 3:
                raise DataError(f"{where}: gt_map must have shape [M, 3], got {self.gt_map.shape}")

    @property
    def num_scans(self) -> int:
        return len(self.scans)

    def scan_name(self, i: int) -> str:
        """How messages and reports name scan i: its file where known, else 'scan i'."""
        return self.files[i] if self.files is not None else f"scan {i}"

    @property
    def num_points(self) -> int:
        """Total number of points over all scans."""
        return int(sum(scan.shape[0] for scan in self.scans))


def match_by_timestamp(
    scan_times: np.ndarray, pose_times: np.ndarray, tol: float = 0.05, what: str = "poses"
) -> np.ndarray:
    """For each scan time, the index of the nearest pose time.

    scan_times: [S], pose_times: [P] (any order) -> indices [S] int64 into pose_times.
    Raises DataError when some scan has no pose within `tol` seconds; `what` names the pose source
    (e.g. a file) in that message."""
    scan_times = np.asarray(scan_times, dtype=np.float64).reshape(-1)
    pose_times = np.asarray(pose_times, dtype=np.float64).reshape(-1)
    if pose_times.size == 0:
        raise DataError(f"{what}: no pose timestamps to match {scan_times.size} scans against")
    order = np.argsort(pose_times, kind="stable")
    sorted_times = pose_times[order]
    right = np.clip(np.searchsorted(sorted_times, scan_times), 1, max(len(sorted_times) - 1, 1))
    left = right - 1
    if len(sorted_times) == 1:
        nearest = np.zeros_like(right)
    else:
        pick_right = np.abs(sorted_times[right] - scan_times) < np.abs(sorted_times[left] - scan_times)
        nearest = np.where(pick_right, right, left)
    gaps = np.abs(sorted_times[nearest] - scan_times)
    unmatched = np.flatnonzero(gaps > tol)
    if unmatched.size:
        i = int(unmatched[0])
        raise DataError(
            f"{what}: {unmatched.size} of {scan_times.size} scans have no pose within {tol} s "
            f"(first: scan {i} at t={scan_times[i]:.6f}, nearest pose {gaps[i]:.6f} s away); "
            f"{pose_times.size} poses for {scan_times.size} scans"
        )
    return order[nearest]
