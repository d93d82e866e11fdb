"""Loaders that turn a dataset folder (or the synthetic generator) into a `Sequence`.

Poses are matched to scans by timestamp where the scans carry one (numeric file names), else by
order; a mismatch is a DataError that names the file and both counts.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from neld_jax.data import synthetic
from neld_jax.data.poses import read_newer_college_csv, read_tum
from neld_jax.data.scans import SCAN_EXTENSIONS, read_scan
from neld_jax.data.sequence import Sequence, match_by_timestamp
from neld_jax.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

DEFAULT_TIMESTAMP_TOLERANCE_S = 0.05
FORMATS = ("generic", "fusionportable", "newer_college", "lio_keyframes", "synthetic")


# --------------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------------


def _check_root(root: str | os.PathLike) -> Path:
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"data root {root} does not exist (or is not a folder)")
    return root


def _list_scans(folder: Path) -> list[Path]:
    """Scan files in folder with a known extension (hidden files and others are skipped and counted)."""
    if not folder.is_dir():
        raise DataError(f"scan folder {folder} does not exist")
    files, others = [], []
    for entry in folder.iterdir():
        if entry.name.startswith("."):
            continue
        (files if entry.is_file() and entry.suffix.lower() in SCAN_EXTENSIONS else others).append(entry)
    if others:
        logger.warning("%s: ignored %d entries that are not scan files (%s)", folder, len(others),
                       ", ".join(sorted(p.name for p in others)[:5]))
    if not files:
        raise DataError(f"scan folder {folder} contains no scan files ({', '.join(SCAN_EXTENSIONS)})")
    return files


def _numeric_stem(path: Path) -> float | None:
    """The file name as a number (000012.pcd -> 12.0), else None; used for sorting."""
    try:
        return float(path.stem)
    except ValueError:
        return None


def _timestamp_from_name(path: Path) -> float | None:
    """The time in seconds that a scan file name encodes, else None.

    1650000000.123456.pcd -> seconds with a fraction; an integer name without leading zeros of at least
    10 digits is seconds (10), milliseconds (13), microseconds (16) or nanoseconds (19) since the epoch.
    Zero-padded frame numbers (000012.pcd) are not timestamps."""
    stem = path.stem
    if "." in stem:
        return _numeric_stem(path)
    if not stem.isdigit() or stem.startswith("0") or len(stem) < 10:
        return None
    digits_to_scale = {10: 1.0, 13: 1e-3, 16: 1e-6, 19: 1e-9}
    scale = digits_to_scale.get(len(stem))
    return None if scale is None else int(stem) * scale


def _sorted_by_name(files: list[Path]) -> list[Path]:
    """Sort by numeric value when every name is a number (timestamps of different lengths), else by name."""
    stems = [_numeric_stem(f) for f in files]
    if all(s is not None for s in stems):
        return [f for _, f in sorted(zip(stems, files), key=lambda pair: (pair[0], pair[1].name))]
    return sorted(files, key=lambda f: f.name)


def _read_scans(files: list[Path]) -> list[np.ndarray]:
    scans = [read_scan(f) for f in files]
    logger.info("read %d scans (%d points) from %s", len(scans), sum(len(s) for s in scans), files[0].parent)
    return scans


def _align(
    poses: np.ndarray,
    pose_times: np.ndarray,
    scan_times: np.ndarray | None,
    num_scans: int,
    pose_file: Path,
    tol: float,
    scan_folder: Path,
) -> np.ndarray:
    """Poses [S, 4, 4] for the scans: by timestamp when scan_times is given, else by order (counts must agree)."""
    if scan_times is not None:
        indices = match_by_timestamp(scan_times, pose_times, tol=tol, what=f"{pose_file} ({scan_folder})")
        return poses[indices]
    if poses.shape[0] != num_scans:
        raise DataError(
            f"{pose_file}: {poses.shape[0]} poses but {num_scans} scans in {scan_folder} "
            "(scan file names are not timestamps, so poses must match scans one to one, in order)"
        )
    return poses


def _first_existing(root: Path, candidates: tuple[str, ...]) -> Path | None:
    for name in candidates:
        if (root / name).is_file():
            return root / name
    return None


def _read_gt_map(root: Path) -> np.ndarray | None:
    path = _first_existing(root, ("gt_map.pcd", "gt_map.ply"))
    return None if path is None else read_scan(path)


# --------------------------------------------------------------------------------------------------
# Generic layout
# --------------------------------------------------------------------------------------------------


def load_generic(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S) -> Sequence:
    """Load the generic layout (see DESIGN.md, "Data on disk"):

        ROOT/scans/*.{pcd,ply,bin,npy}   one scan per file, sensor frame, sorted by name
        ROOT/poses.txt                   initial poses, TUM
        ROOT/gt_poses.txt                optional ground-truth poses, TUM
        ROOT/gt_map.pcd | gt_map.ply     optional ground-truth map, world frame

    Poses match scans by order. Only when the counts differ and every scan name is a timestamp
    (1650000000.123456.pcd, or 10/13/16/19-digit integer s/ms/us/ns; zero-padded frame numbers such as
    000012.pcd are not) are they matched by timestamp, nearest within `tol` seconds. Ground-truth poses
    follow the same rule (a different count is matched against the scan timestamps)."""
    root = _check_root(root)
    scan_folder = root / "scans"
    files = _sorted_by_name(_list_scans(scan_folder))
    name_times = [_timestamp_from_name(f) for f in files]
    names_are_times = all(t is not None for t in name_times)

    pose_file = root / "poses.txt"
    pose_times, poses = read_tum(pose_file)
    by_time = names_are_times and poses.shape[0] != len(files)
    scan_times = np.asarray(name_times, dtype=np.float64) if by_time else None
    poses = _align(poses, pose_times, scan_times, len(files), pose_file, tol, scan_folder)
    timestamps = scan_times if by_time else pose_times

    gt_poses = None
    gt_file = root / "gt_poses.txt"
    if gt_file.is_file():
        gt_times, gt_all = read_tum(gt_file)
        gt_by_time = by_time or (gt_all.shape[0] != len(files))
        gt_poses = _align(
            gt_all, gt_times, timestamps if gt_by_time else None, len(files), gt_file, tol, scan_folder
        )

    return Sequence(
        scans=_read_scans(files),
        poses=poses,
        timestamps=timestamps,
        gt_poses=gt_poses,
        gt_map=_read_gt_map(root),
        name=root.name,
        source=str(root),
    )


# --------------------------------------------------------------------------------------------------
# FusionPortable
# --------------------------------------------------------------------------------------------------

FUSIONPORTABLE_POSE_FILES = ("fastlio2_poses.txt", "poses.txt", "odometry.txt")
FUSIONPORTABLE_GT_FILES = ("gt_poses.txt", "traj/gt_poses.txt", "ground_truth.txt", "traj/ground_truth.txt")


def load_fusionportable(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S) -> Sequence:
    """Load a FusionPortable sequence prepared with FAST-LIO2:

        ROOT/scans/<timestamp>.pcd       undistorted scans in the LiDAR frame, named by their time
                                         (1649327985.123456.pcd in seconds, or a 19-digit integer in ns;
                                         .ply/.bin/.npy also read)
        ROOT/fastlio2_poses.txt          initial poses, TUM (FAST-LIO2 output); else ROOT/poses.txt or
                                         ROOT/odometry.txt
        ROOT/gt_poses.txt                optional ground truth, TUM (also ROOT/traj/gt_poses.txt,
                                         ROOT/ground_truth.txt, ROOT/traj/ground_truth.txt)
        ROOT/gt_map.pcd | gt_map.ply     optional ground-truth map (the dataset's TLS map), world frame

    Every scan name must be a timestamp; initial and ground-truth poses are the ones nearest in time,
    within `tol` seconds (else DataError)."""
    root = _check_root(root)
    scan_folder = root / "scans"
    files = _sorted_by_name(_list_scans(scan_folder))
    scan_times = _timestamps_from_names(files, scan_folder, "<timestamp>.pcd")

    return _timestamped_sequence(root, files, scan_times, scan_folder, FUSIONPORTABLE_POSE_FILES,
                                 FUSIONPORTABLE_GT_FILES, read_tum, tol)


def _timestamped_sequence(root: Path, files: list[Path], scan_times: np.ndarray, scan_folder: Path,
                          pose_files: tuple[str, ...], gt_files: tuple[str, ...], read_gt, tol: float) -> Sequence:
    """The part that FusionPortable and Newer College share: scans with timestamps, initial poses (TUM) and
    optional ground truth (read by `read_gt`) matched to them by nearest timestamp, optional GT map."""
    pose_file = _first_existing(root, pose_files)
    if pose_file is None:
        raise DataError(f"{root}: no initial pose file (looked for {', '.join(pose_files)})")
    pose_times, poses = read_tum(pose_file)
    poses = _align(poses, pose_times, scan_times, len(files), pose_file, tol, scan_folder)

    gt_poses = None
    gt_file = _first_existing(root, gt_files)
    if gt_file is not None:
        gt_times, gt_all = read_gt(gt_file)
        gt_poses = _align(gt_all, gt_times, scan_times, len(files), gt_file, tol, scan_folder)

    return Sequence(
        scans=_read_scans(files),
        poses=poses,
        timestamps=scan_times,
        gt_poses=gt_poses,
        gt_map=_read_gt_map(root),
        name=root.name,
        source=str(root),
    )


def _timestamps_from_names(files: list[Path], folder: Path, pattern: str) -> np.ndarray:
    times = [_timestamp_from_name(f) for f in files]
    bad = [f.name for f, t in zip(files, times) if t is None]
    if bad:
        raise DataError(f"{folder}: scan names must be timestamps ({pattern}); not a timestamp: {bad[0]}")
    return np.asarray(times, dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# Newer College
# --------------------------------------------------------------------------------------------------

NEWER_COLLEGE_SCAN_FOLDERS = ("clouds", "raw_format/ouster_scan", "raw_format/clouds")
NEWER_COLLEGE_POSE_FILES = ("odometry.txt", "poses.txt", "fastlio2_poses.txt")
NEWER_COLLEGE_GT_FILES = ("registered_poses.csv", "ground_truth/registered_poses.csv")
_NEWER_COLLEGE_CLOUD_NAME = re.compile(r"^cloud_(\d+)_(\d+)$")


def load_newer_college(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S) -> Sequence:
    """Load a Newer College sequence:

        ROOT/clouds/cloud_<sec>_<nsec>.pcd      Ouster scans in the sensor frame (also read from
                                                ROOT/raw_format/ouster_scan/ or ROOT/raw_format/clouds/)
        ROOT/odometry.txt                       initial poses, TUM (else ROOT/poses.txt or fastlio2_poses.txt)
        ROOT/registered_poses.csv               optional ground truth, '#sec,nsec,x,y,z,qx,qy,qz,qw'
                                                (also ROOT/ground_truth/registered_poses.csv)
        ROOT/gt_map.pcd | gt_map.ply            optional ground-truth map, world frame

    Scan time = sec + nsec * 1e-9 from the file name; poses are matched by nearest timestamp within
    `tol` seconds. Points at the origin (no return in organised Ouster clouds) are left in; the
    preprocessing range crop removes them."""
    root = _check_root(root)
    scan_folder = next((root / f for f in NEWER_COLLEGE_SCAN_FOLDERS if (root / f).is_dir()), None)
    if scan_folder is None:
        raise DataError(f"{root}: no scan folder (looked for {', '.join(NEWER_COLLEGE_SCAN_FOLDERS)})")
    files = _list_scans(scan_folder)
    times = []
    for f in files:
        match = _NEWER_COLLEGE_CLOUD_NAME.match(f.stem)
        if match is None:
            raise DataError(f"{f}: Newer College scan names must be cloud_<sec>_<nsec>{f.suffix}")
        times.append(int(match.group(1)) + int(match.group(2)) * 1e-9)
    order = np.argsort(times, kind="stable")
    files = [files[i] for i in order]
    scan_times = np.asarray(times, dtype=np.float64)[order]

    return _timestamped_sequence(root, files, scan_times, scan_folder, NEWER_COLLEGE_POSE_FILES,
                                 NEWER_COLLEGE_GT_FILES, read_newer_college_csv, tol)


# --------------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------------


def load_sequence(data_cfg) -> Sequence:
    """Load the sequence that data_cfg (ml_collections.ConfigDict) names.

    Reads data_cfg.format (one of FORMATS), data_cfg.root (folder formats) and data_cfg.synthetic (for
    'synthetic'); an optional data_cfg.timestamp_tol_s overrides the 0.05 s matching tolerance.
    Preprocessing is left to the caller (see preprocess.preprocess)."""
    fmt = str(data_cfg.format).lower()
    if fmt not in FORMATS:
        raise ConfigError(f"data.format: unknown format '{data_cfg.format}' (expected one of {', '.join(FORMATS)})")
    if fmt == "synthetic":
        return synthetic.make_sequence(data_cfg.get("synthetic", None))
    root = data_cfg.get("root", None)
    if not root:
        raise ConfigError(f"data.root must be set for format '{fmt}'")
    if fmt == "lio_keyframes":
        from neld_jax.data.lio_keyframes import DEFAULT_POSE_FILE, load_lio_keyframes

        return load_lio_keyframes(root, pose_file=data_cfg.get("pose_file", "") or DEFAULT_POSE_FILE,
                                  drop_unmatched_tail=bool(data_cfg.get("drop_unmatched_tail", False)))
    tol = float(data_cfg.get("timestamp_tol_s", DEFAULT_TIMESTAMP_TOLERANCE_S))
    loader = {"generic": load_generic, "fusionportable": load_fusionportable, "newer_college": load_newer_college}
    return loader[fmt](root, tol=tol)
