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
is short; `drop_unmatched_tail=True` drops up to MAX_UNMATCHED_TAIL trailing scans without a pose instead, with a
warning.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from neld_jax.data.layout import (
    MAX_UNMATCHED_TAIL,
    LoadOptions,
    build_sequence,
    check_root,
    config_root,
    load_options,
    with_explicit_ground_truth,
)
from neld_jax.data.poses import read_kitti
from neld_jax.data.sequence import Sequence
from neld_jax.data.timing import read_times
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

SCAN_FOLDERS = ("Scans", "scans")
TIMES_FILE = "times.txt"
DEFAULT_POSE_FILE = "odom_poses.txt"


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
        logger.warning(
            "%s: ignored %d entries that are not .pcd scans (%s)",
            folder,
            len(others),
            ", ".join(sorted(p.name for p in others)[:5]),
        )
    return folder, files


def load_lio_keyframes(
    root: str | os.PathLike, options: LoadOptions = LoadOptions(), pose_file: str = DEFAULT_POSE_FILE
) -> Sequence:
    """Load the layout of this module's docstring into a Sequence (scans in the sensor frame, initial poses,
    timestamps; the layout has no ground truth). `pose_file` is relative to ROOT. options (layout.LoadOptions):
    drop_unmatched_tail as the module docstring says; gt_poses_file / gt_map_file, when set, give the ground truth
    (matched by time against times.txt when both have stamps: layout.with_explicit_ground_truth); scan_frame is not
    read."""
    root = check_root(root)
    folder, files = _scan_files(root)
    pose_path = root / pose_file
    if not pose_path.is_file():
        present = sorted(p.name for p in root.glob("*poses*.txt"))
        found = f" (found: {', '.join(present)})" if present else ""
        raise DataError(f"{pose_path}: pose file does not exist{found}")
    poses = read_kitti(pose_path)
    times_path = root / TIMES_FILE
    stamps = read_times(times_path) if times_path.is_file() else None
    if stamps is None:
        logger.warning(
            "%s: no %s; scans get the stamps 0, 1, 2, ... (keyframe selection by time is off)", root, TIMES_FILE
        )

    counts = {f"{folder.name}/": len(files), pose_path.name: len(poses)}
    if stamps is not None:
        counts[TIMES_FILE] = len(stamps)
    shortest = min(counts.values())
    if len(set(counts.values())) > 1:
        listing = ", ".join(f"{name} has {n}" for name, n in counts.items())
        short = [name for name, n in counts.items() if n == shortest]
        extra = max(counts.values()) - shortest
        if not options.drop_unmatched_tail or extra > MAX_UNMATCHED_TAIL:
            raise DataError(
                f"{root}: scans, poses and stamps must correspond one to one, but {listing} "
                f"({', '.join(short)} {'is' if len(short) == 1 else 'are'} short by {extra}); if the recording "
                f"was cut short at its end, set data.drop_unmatched_tail=True to drop the last {extra} scan(s)"
                + ("" if extra <= MAX_UNMATCHED_TAIL else f" (only allowed for up to {MAX_UNMATCHED_TAIL})")
            )
        dropped = [p.name for p in files[shortest:]]
        logger.warning(
            "%s: %s; dropping the trailing %d scan(s) without a full record: %s",
            root,
            listing,
            extra,
            ", ".join(dropped) or "(none: only poses or stamps)",
        )
        files, poses = files[:shortest], poses[:shortest]
        stamps = None if stamps is None else stamps[:shortest]

    # Scans read, dropped points counted, files named relative to the root, pose jumps checked: as every loader.
    seq = build_sequence(root, files, poses, stamps, None, pose_path)
    return with_explicit_ground_truth(seq, root, options)


def load(data_cfg) -> Sequence:
    """data.format = 'lio_keyframes': load_lio_keyframes(data.root) with data.initial_poses ('' = DEFAULT_POSE_FILE)
    and data.drop_unmatched_tail; data.gt_poses_path / gt_map_path, when set, give the ground truth (matched by
    time against times.txt when both have stamps; layout.load_options)."""
    pose_file = data_cfg.get("initial_poses", "") or DEFAULT_POSE_FILE
    return load_lio_keyframes(config_root(data_cfg, "lio_keyframes"), load_options(data_cfg), pose_file)
