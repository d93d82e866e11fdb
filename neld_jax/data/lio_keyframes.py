"""Keyframe scans saved by a LiDAR(-inertial) odometry / SLAM front-end, as FAST-LIO2 + Scan Context
(FAST-LIO-SAM, SC-A-LOAM and their forks) write them:

    ROOT/Scans/000000.pcd ...     one keyframe scan per file, SENSOR frame (x y z [intensity])
    ROOT/odom_poses.txt           odometry poses, KITTI (row-major 3x4, sensor -> world), one line per scan
    ROOT/optimized_poses.txt      optional: the same after the front-end's loop-closure pose graph
    ROOT/times.txt                one timestamp (seconds) per scan, in scan order

Scans, poses and stamps correspond by order (line i <-> Scans/%06d.pcd with i). `pose_file` picks which pose
file is the initial trajectory (odom_poses.txt by default; optimized_poses.txt to refine the loop-closed
result). There is no ground truth in this layout; `bin/perturb.py` makes a pseudo ground truth from it.

A count mismatch (a recording cut short: 332 scans and stamps, 331 poses) is an error that says which side
is short; `drop_unmatched_tail=True` drops up to MAX_UNMATCHED_TAIL trailing scans without a pose instead, with a warning.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from neld_jax.data.datasets import MAX_UNMATCHED_TAIL, build_sequence
from neld_jax.data.poses import read_kitti
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

SCAN_FOLDERS = ("Scans", "scans")
TIMES_FILE = "times.txt"
DEFAULT_POSE_FILE = "odom_poses.txt"


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
        raise DataError(f"{path}, lines {lines[i]} and {lines[i + 1]}: timestamps do not increase "
                        f"({stamps[i]:.6f} then {stamps[i + 1]:.6f})")
    return stamps


def _scan_files(root: Path) -> tuple[Path, list[Path]]:
    folder = next((root / name for name in SCAN_FOLDERS if (root / name).is_dir()), None)
    if folder is None:
        raise DataError(f"{root}: no scan folder (looked for {', '.join(SCAN_FOLDERS)}/)")
    files, others = [], []
    for entry in folder.iterdir():
        if not entry.name.startswith("."):
            (files if entry.suffix.lower() == ".pcd" else others).append(entry)
    if not files:
        raise DataError(f"{folder}: no .pcd scans")
    files.sort()
    if others:
        logger.warning("%s: ignored %d entries that are not .pcd scans (%s)", folder, len(others),
                       ", ".join(sorted(p.name for p in others)[:5]))
    return folder, files


def load_lio_keyframes(root: str | os.PathLike, pose_file: str = DEFAULT_POSE_FILE,
                       drop_unmatched_tail: bool = False) -> Sequence:
    """Load the layout of this module's docstring into a Sequence (scans in the sensor frame, initial poses,
    timestamps; no ground truth). `pose_file` is relative to ROOT."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"data root {root} does not exist (or is not a folder)")
    folder, files = _scan_files(root)
    pose_path = root / pose_file
    if not pose_path.is_file():
        present = sorted(p.name for p in root.glob("*poses*.txt"))
        raise DataError(f"{pose_path}: pose file does not exist" + (f" (found: {', '.join(present)})" if present else ""))
    poses = read_kitti(pose_path)
    times_path = root / TIMES_FILE
    stamps = read_times(times_path) if times_path.is_file() else None
    if stamps is None:
        logger.warning("%s: no %s; scans get the stamps 0, 1, 2, ... (keyframe selection by time is off)",
                       root, TIMES_FILE)

    counts = {f"{folder.name}/": len(files), pose_path.name: len(poses)}
    if stamps is not None:
        counts[TIMES_FILE] = len(stamps)
    shortest = min(counts.values())
    if len(set(counts.values())) > 1:
        listing = ", ".join(f"{name} has {n}" for name, n in counts.items())
        short = [name for name, n in counts.items() if n == shortest]
        extra = max(counts.values()) - shortest
        if not drop_unmatched_tail or extra > MAX_UNMATCHED_TAIL:
            raise DataError(
                f"{root}: scans, poses and stamps must correspond one to one, but {listing} "
                f"({', '.join(short)} {'is' if len(short) == 1 else 'are'} short by {extra}); if the recording "
                f"was cut short at its end, set data.drop_unmatched_tail=True to drop the last {extra} scan(s)"
                + ("" if extra <= MAX_UNMATCHED_TAIL else f" (only allowed for up to {MAX_UNMATCHED_TAIL})"))
        dropped = [p.name for p in files[shortest:]]
        logger.warning("%s: %s; dropping the trailing %d scan(s) without a full record: %s", root, listing, extra,
                       ", ".join(dropped) or "(none: only poses or stamps)")
        files, poses = files[:shortest], poses[:shortest]
        stamps = None if stamps is None else stamps[:shortest]

    # Scans read, dropped points counted, files named relative to the root, pose jumps checked: as every loader.
    return build_sequence(root, files, poses, stamps, None, pose_path)
