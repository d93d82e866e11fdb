"""Scan timestamps: reading a file of stamps, the nearest time in a list, and matching scans to poses by time.

Pure numpy (no Open3D, no SciPy), so that the evaluation (metrics.associate_timestamps) can share the nearest-time
rule with the loaders without importing the I/O stack.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neld_jax.errors import DataError

# A scan takes the nearest pose within this many seconds (config data.timestamp_tol_s overrides it).
DEFAULT_TIMESTAMP_TOLERANCE_S = 0.05


def nearest_times(query_times: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query time, the index of the nearest of `times` (any order; the earlier one on a tie) and the gap.

    query_times: [Q], times: [P] with P >= 1 -> (indices [Q] int64 into times, |gaps| [Q] seconds)."""
    query_times = np.asarray(query_times, dtype=np.float64).reshape(-1)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    order = np.argsort(times, kind="stable")
    sorted_times = times[order]
    right = np.clip(np.searchsorted(sorted_times, query_times), 1, max(len(sorted_times) - 1, 1))
    left = right - 1
    if len(sorted_times) == 1:
        nearest = np.zeros_like(right)
    else:
        pick_right = np.abs(sorted_times[right] - query_times) < np.abs(sorted_times[left] - query_times)
        nearest = np.where(pick_right, right, left)
    return order[nearest], np.abs(sorted_times[nearest] - query_times)


def match_by_timestamp(
    scan_times: np.ndarray,
    pose_times: np.ndarray,
    tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
    what: str = "poses",
    scan_labels: list[str] | None = None,
) -> np.ndarray:
    """For each scan time, the index of the nearest pose time.

    scan_times: [S], pose_times: [P] (any order) -> indices [S] int64 into pose_times.
    Raises DataError when some scan has no pose within `tol` seconds; `what` names the pose source
    (e.g. a file) in that message and `scan_labels` [S] (e.g. file names) the scans."""
    scan_times = np.asarray(scan_times, dtype=np.float64).reshape(-1)
    pose_times = np.asarray(pose_times, dtype=np.float64).reshape(-1)
    if pose_times.size == 0:
        raise DataError(f"{what}: no pose timestamps to match {scan_times.size} scans against")
    nearest, gaps = nearest_times(scan_times, pose_times)
    unmatched = np.flatnonzero(gaps > tol)
    if unmatched.size:
        i = int(unmatched[0])
        first = f"scan {i}" if scan_labels is None else scan_labels[i]
        raise DataError(
            f"{what}: {unmatched.size} of {scan_times.size} scans have no pose within {tol} s "
            f"(first: {first} at t={scan_times[i]:.6f}, nearest pose {gaps[i]:.6f} s away); "
            f"{pose_times.size} poses for {scan_times.size} scans"
        )
    return nearest


def read_times(path: str | os.PathLike) -> np.ndarray:
    """A file of one timestamp (seconds) per line -> [S] float64; blank lines and '#' comments are skipped.

    Raises DataError naming the file and line for a non-numeric or non-finite value, or for stamps that go
    backwards (scans are matched by order, so a stamp out of order means the files are out of step)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: timestamp file does not exist")
    stamps, lines = [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            value = float(text.split()[0])
        except ValueError:
            raise DataError(f"{path}, line {number}: not a timestamp: {text[:40]!r}") from None
        if not np.isfinite(value):
            raise DataError(f"{path}, line {number}: timestamp is not finite")
        stamps.append(value)
        lines.append(number)
    if not stamps:
        raise DataError(f"{path}: no timestamps")
    stamps = np.asarray(stamps, dtype=np.float64)
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0])
        raise DataError(
            f"{path}, lines {lines[i]} and {lines[i + 1]}: timestamps do not increase "
            f"({stamps[i]:.6f} then {stamps[i + 1]:.6f})"
        )
    return stamps
