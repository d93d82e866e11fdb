"""Loaders that turn a dataset folder (or the synthetic generator) into a `Sequence`.

Poses are matched to scans by `align_poses` (shared by every loader): by timestamp where the scans carry
one (numeric file names), else by order. What real recordings bring, and what happens:
  - pose and scan counts differ (by order): DataError saying which side is short, by how many, which
    scans (or pose times) are left over and how to fix it; with drop_unmatched_tail=True a short
    trailing surplus (at most MAX_UNMATCHED_TAIL, e.g. 332 scans and 331 poses at the end of a
    recording) is dropped with a warning naming it instead.
  - pose timestamps out of order: by order, a DataError (the file cannot be in scan order then); by
    time, a warning (matching by time does not need order).
  - the same timestamp twice in a pose file: DataError naming both lines (poses.read_tum).
  - NaN/inf points and points at (0, 0, 0) ("no return"): dropped, counted per reason (scans.read_scan,
    plus one total here); a scan file with no point left, or none at all, is a DataError naming it.
  - consecutive poses implausibly far apart: a warning naming both scan files
    (sequence.check_pose_jumps).
Every Sequence carries `files` (relative to the root), so later per-scan messages name the file.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from neld_jax.data import frames, ground_truth, synthetic
from neld_jax.data.poses import read_tum
from neld_jax.data.scans import SCAN_EXTENSIONS, read_scan, read_scan_counted
from neld_jax.data.sequence import Sequence, check_pose_jumps, match_by_timestamp
from neld_jax.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

DEFAULT_TIMESTAMP_TOLERANCE_S = 0.05
# drop_unmatched_tail forgives a recording cut a little unevenly at its end, not a different sequence.
MAX_UNMATCHED_TAIL = 5
FORMATS = ("generic", "fusionportable", "newer_college", "lio_keyframes", "hba", "synthetic")


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


def _relative(path: Path, root: Path | None) -> str:
    """path relative to root when it lies inside it (scans/000002.pcd), else the path as given."""
    if root is not None:
        try:
            return path.relative_to(root).as_posix()
        except ValueError:
            pass
    return str(path)


def _read_scans(files: list[Path]) -> list[np.ndarray]:
    """Read every scan; one log line with the totals dropped per reason (each file's own is in scans)."""
    scans, totals, affected = [], {"read": 0, "non-finite": 0, "zero": 0}, {"non-finite": 0, "zero": 0}
    for f in files:
        points, dropped = read_scan_counted(f)
        scans.append(points)
        for key in totals:
            totals[key] += dropped[key]
        for key in affected:
            affected[key] += dropped[key] > 0
    logger.info("read %d scans (%d points) from %s", len(scans), sum(len(s) for s in scans), files[0].parent)
    if totals["non-finite"] or totals["zero"]:
        logger.info("dropped %d of %d points: %d NaN/infinite (in %d scans), %d at (0, 0, 0), i.e. no return "
                    "(in %d scans)", totals["non-finite"] + totals["zero"], totals["read"], totals["non-finite"],
                    affected["non-finite"], totals["zero"], affected["zero"])
    return scans


class Alignment(NamedTuple):
    """What align_poses returns.

    poses:        [S', 4, 4] the pose of each kept scan
    timestamps:   [S'] the kept scans' times (scan_times if given, else the matched poses' times), or None
    scan_indices: [S'] int64 indices of the kept scans into scan_files (all of them unless
                  drop_unmatched_tail dropped a trailing few)
    """

    poses: np.ndarray
    timestamps: np.ndarray | None
    scan_indices: np.ndarray


def _listed(names: list[str], limit: int = 3) -> str:
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def align_poses(
    poses: np.ndarray,
    pose_times: np.ndarray | None,
    pose_file: str | os.PathLike,
    scan_files: list[Path],
    scan_times: np.ndarray | None = None,
    tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
    drop_unmatched_tail: bool = False,
    root: str | os.PathLike | None = None,
) -> Alignment:
    """Match poses read from pose_file to the scans in scan_files: by time if scan_times is given, else by order.

    poses: [P, 4, 4]; pose_times: [P] seconds (None for files without times, e.g. KITTI);
    scan_files: [S] scan paths (messages show them relative to `root` when given);
    scan_times: [S] seconds, or None to match by order; tol: seconds, for matching by time.

    By time: every scan needs a pose within `tol` seconds (else DataError naming the first scan file);
    pose times out of order are fine (a warning: the file may be a concatenation).
    By order: pose times, when given, must increase (else DataError naming the first pose that goes
    back in time: the file is then not in scan order). The counts must agree; if not, DataError saying
    which side is short, by how many, and which trailing scans (or pose times) are left over, e.g.
    "<root>: poses.txt has 331 poses but scans/ has 332 scans: the last 1 scan(s) (scans/000331.pcd) have
    no pose; delete them or add poses". With drop_unmatched_tail=True and at most MAX_UNMATCHED_TAIL left
    over, the surplus trailing scans (or poses) are dropped with a warning naming them instead.
    """
    pose_file = Path(pose_file)
    root = None if root is None else Path(root)
    poses = np.asarray(poses, dtype=np.float64)
    pose_times = None if pose_times is None else np.asarray(pose_times, dtype=np.float64).reshape(-1)
    labels = [_relative(Path(f), root) for f in scan_files]
    num_poses, num_scans = poses.shape[0], len(scan_files)

    if scan_times is not None:
        scan_times = np.asarray(scan_times, dtype=np.float64).reshape(-1)
        if pose_times is None:
            raise DataError(f"{pose_file}: has no timestamps, so its poses cannot be matched to scans by time")
        back = np.flatnonzero(np.diff(pose_times) < 0)
        if back.size:
            logger.warning("%s: timestamps are not in time order (pose %d at t=%.6f comes after t=%.6f; %d such "
                           "places); poses are matched by time, so this only matters if the file is a mix-up",
                           pose_file, back[0] + 2, pose_times[back[0] + 1], pose_times[back[0]], back.size)
        indices = match_by_timestamp(scan_times, pose_times, tol=tol, what=str(pose_file), scan_labels=labels)
        return Alignment(poses[indices], scan_times, np.arange(num_scans, dtype=np.int64))

    if pose_times is not None:
        back = np.flatnonzero(np.diff(pose_times) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise DataError(
                f"{pose_file}: timestamps are not in time order (pose {i + 1} at t={pose_times[i]:.6f} comes after "
                f"t={pose_times[i - 1]:.6f}; {back.size} such place(s)); poses are matched to the scans "
                "one to one, in order, so the file must be sorted by time (sort it by its first column)"
            )
    keep = min(num_poses, num_scans)
    extra = abs(num_poses - num_scans)
    if extra:
        if num_poses < num_scans:
            left_over = labels[keep:]
            what = (f"the last {extra} scan(s) ({_listed(left_over)}) have no pose; "
                    "delete them or add poses")
        else:
            left_over = ([f"pose {i + 1}" for i in range(keep, num_poses)] if pose_times is None
                         else [f"t={t:.6f}" for t in pose_times[keep:]])
            what = (f"the last {extra} pose(s) ({_listed(left_over)}) have no scan; "
                    "delete them or add the missing scans")
        folder = _relative(Path(scan_files[0]).parent, root) + "/" if scan_files else "the scan list"
        message = (f"{'' if root is None else f'{root}: '}{_relative(pose_file, root)} has {num_poses} poses "
                   f"but {folder} has {num_scans} scans: {what} (poses are matched to scans one to one, in order)")
        if not drop_unmatched_tail or extra > MAX_UNMATCHED_TAIL:
            if drop_unmatched_tail:
                message += f"; drop_unmatched_tail drops at most {MAX_UNMATCHED_TAIL}, not {extra}"
            raise DataError(message)
        logger.warning("%s; dropped them (drop_unmatched_tail)", message)
    times = None if pose_times is None else pose_times[:keep]
    return Alignment(poses[:keep], times, np.arange(keep, dtype=np.int64))


def build_sequence(root: Path, files: list[Path], poses: np.ndarray, timestamps: np.ndarray | None,
                   gt_poses: np.ndarray | None, pose_file: Path, gt_map_file: Path | None = None) -> Sequence:
    """Read the scans and the GT map (gt_map_file, else ROOT/gt_map.pcd|ply if present), build the Sequence
    (files relative to root), check for pose jumps."""
    seq = Sequence(
        scans=_read_scans(files),
        poses=poses,
        timestamps=timestamps,
        gt_poses=gt_poses,
        gt_map=read_scan(gt_map_file) if gt_map_file is not None else _read_gt_map(root),
        name=root.name,
        source=str(root),
        files=[_relative(f, root) for f in files],
    )
    check_pose_jumps(seq.poses, [seq.scan_label(i) for i in range(seq.num_scans)], what=str(pose_file))
    return seq


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


def load_generic(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
                 drop_unmatched_tail: bool = False) -> Sequence:
    """Load the generic layout (docs/design.md, "Data on disk"):

        ROOT/scans/*.{pcd,ply,bin,npy}   one scan per file, sensor frame, sorted by name
        ROOT/poses.txt                   initial poses, TUM
        ROOT/gt_poses.txt                optional ground-truth poses, TUM
        ROOT/gt_map.pcd | gt_map.ply     optional ground-truth map, world frame

    Poses match scans by order (their timestamps must then increase). Only when the counts differ and
    every scan name is a timestamp (1650000000.123456.pcd, or 10/13/16/19-digit integer s/ms/us/ns;
    zero-padded frame numbers such as 000012.pcd are not) are they matched by timestamp, nearest within
    `tol` seconds. Ground-truth poses follow the same rule (a different count is matched against the scan
    timestamps). drop_unmatched_tail: see align_poses (a few trailing scans without a pose are dropped
    with a warning instead of an error)."""
    root = _check_root(root)
    scan_folder = root / "scans"
    files = _sorted_by_name(_list_scans(scan_folder))
    name_times = [_timestamp_from_name(f) for f in files]
    names_are_times = all(t is not None for t in name_times)

    pose_file = root / "poses.txt"
    pose_times, poses = read_tum(pose_file)
    by_time = names_are_times and poses.shape[0] != len(files)
    scan_times = np.asarray(name_times, dtype=np.float64) if by_time else None
    aligned = align_poses(poses, pose_times, pose_file, files, scan_times, tol=tol,
                          drop_unmatched_tail=drop_unmatched_tail, root=root)
    files = [files[i] for i in aligned.scan_indices]
    timestamps = aligned.timestamps

    gt_poses = None
    gt_file = root / "gt_poses.txt"
    if gt_file.is_file():
        gt_times, gt_all = read_tum(gt_file)
        gt_by_time = by_time or (gt_all.shape[0] != len(files))
        gt_poses = align_poses(gt_all, gt_times, gt_file, files, timestamps if gt_by_time else None,
                               tol=tol, root=root).poses

    return build_sequence(root, files, aligned.poses, timestamps, gt_poses, pose_file)


# --------------------------------------------------------------------------------------------------
# Ground truth shared by the loaders (explicit paths, published frame offsets: neld_jax/data/ground_truth.py)
# --------------------------------------------------------------------------------------------------


def _matched_ground_truth(root: Path, files: list[Path], scan_times: np.ndarray | None, gt_file: Path, tol: float,
                          gt_from_scan: np.ndarray | None, gt_time_offset_s: float = 0.0) -> np.ndarray:
    """The ground-truth pose of each scan [S, 4, 4]: gt_file (TUM, or Newer College CSV for .csv) matched to the
    scans by time within tol (by order without scan times), then moved into the scan frame (T_world_G @ T_G_S).
    gt_time_offset_s is added to the scan stamps for this matching only (a ground truth stamped by another
    convention, e.g. -0.1 s to pair end-of-scan stamps with start-of-scan ground truth at 10 Hz).

    A scan without a ground-truth stamp within tol is a DataError naming it (match_by_timestamp): a scan is
    never given a neighbour's pose."""
    gt_times, gt_all = ground_truth.read_trajectory(gt_file)
    if scan_times is not None and gt_time_offset_s:
        scan_times = np.asarray(scan_times, dtype=np.float64) + gt_time_offset_s
    poses = align_poses(gt_all, gt_times, gt_file, files, scan_times, tol=tol, root=root).poses
    return poses if gt_from_scan is None else poses @ gt_from_scan


# --------------------------------------------------------------------------------------------------
# FusionPortable
# --------------------------------------------------------------------------------------------------

FUSIONPORTABLE_POSE_FILES = ("fastlio2_poses.txt", "poses.txt", "odometry.txt")
FUSIONPORTABLE_GT_FILES = ("gt_poses.txt", "traj/gt_poses.txt", "ground_truth.txt", "traj/ground_truth.txt")
# The devkit's exports (fusionportable_dataset_tools, src/data_loader/ros_msg/pointcloud.py and odometry.py, driven
# by src/write_alg_bag_to_data.ipynb and src/write_bag_to_data.ipynb): (scan folder, frame of its clouds).
# algorithm_result/ holds FAST-LIO2's /cloud_registered_body (frame body_imu, src/cfg/algorithm/cfg_fastlio2.py).
FUSIONPORTABLE_DEVKIT_SCANS = (("algorithm_result/ouster00_undistort/points", "body_imu"),
                               ("raw_data/ouster00/points", "ouster00"))
FUSIONPORTABLE_DEVKIT_ODOMETRY = ("algorithm_result/odometry/odometry.txt", "odometry.txt")


def load_fusionportable(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
                        gt_poses_file: Path | None = None, gt_map_file: Path | None = None,
                        gt_from_scan: np.ndarray | None = None, scan_frame: str = "",
                        gt_time_offset_s: float = 0.0) -> Sequence:
    """Load a FusionPortable sequence. ROOT is the devkit's sequence folder (<dataset_path>/<sequence>, e.g.
    .../sensor_data/handheld/20220216_canteen_day); its export, as the devkit writes it:

        ROOT/algorithm_result/ouster00_undistort/points/data/000000.pcd ...   FAST-LIO2's /cloud_registered_body,
                                                                               IMU (body_imu) frame
        ROOT/algorithm_result/ouster00_undistort/points/timestamps.txt         one stamp per cloud (sec.nsec),
                                                                               header stamps: END of the scan
        ROOT/algorithm_result/odometry/odometry.txt                            FAST-LIO2 /Odometry, TUM, same stamps
        (or ROOT/raw_data/ouster00/points/... raw Ouster clouds, frame ouster00, with ROOT/odometry.txt)

    and the dataset's ground truth, found beside or up to three folders above ROOT (the download's layout,
    fusionportable.github.io/dataset/fusionportable, "Data Organization"):

        groundtruth/traj/<sequence>.txt                  TUM, <sequence> = ROOT's folder name
        groundtruth/map/<sequence>/merged_scan.pcd       TLS map (1 cm), in the ground truth's world frame

    gt_poses_file / gt_map_file (config data.gt_poses_path / gt_map_path) override the search. Ground-truth poses
    are moved into the scans' frame by gt_from_scan (T_G_S; None: the published extrinsic for the scan frame,
    ground_truth.PUBLISHED_GT_FROM_SCAN; scan_frame overrides the frame the folder implies).

    Also read, as before: ROOT/scans/<timestamp>.pcd with ROOT/fastlio2_poses.txt (or poses.txt, odometry.txt) and
    ROOT/gt_poses.txt (or traj/gt_poses.txt, ground_truth.txt, traj/ground_truth.txt), ground truth in the scan
    frame unless gt_from_scan says otherwise. Odometry and ground truth are matched to the scans by nearest
    stamp within `tol` seconds; a scan without one is a DataError naming it."""
    root = _check_root(root)
    if (root / "scans").is_dir():
        scan_folder = root / "scans"
        files = _sorted_by_name(_list_scans(scan_folder))
        scan_times = _timestamps_from_names(files, scan_folder, "<timestamp>.pcd")
        return _timestamped_sequence(root, files, scan_times, FUSIONPORTABLE_POSE_FILES, FUSIONPORTABLE_GT_FILES,
                                     tol, gt_poses_file, gt_map_file, gt_from_scan, gt_time_offset_s)

    found = next(((root / folder, frame) for folder, frame in FUSIONPORTABLE_DEVKIT_SCANS
                  if (root / folder / "data").is_dir()), None)
    if found is None:
        looked = ", ".join(f"{folder}/data/" for folder, _ in FUSIONPORTABLE_DEVKIT_SCANS)
        raise DataError(f"{root}: no FusionPortable scans (looked for scans/ and the devkit's {looked})")
    points_folder, frame = found
    files = _sorted_by_name(_list_scans(points_folder / "data"))
    from neld_jax.data.lio_keyframes import read_times

    scan_times = read_times(points_folder / "timestamps.txt")
    if len(scan_times) != len(files):
        raise DataError(f"{points_folder / 'timestamps.txt'} has {len(scan_times)} stamps but {points_folder / 'data'} "
                        f"has {len(files)} scans (the devkit writes one stamp per cloud, in order)")
    if gt_from_scan is None:
        gt_from_scan = ground_truth.published_offset("fusionportable", scan_frame or frame)
    name = root.name
    gt_poses_file = gt_poses_file or ground_truth.first_upwards(root, f"groundtruth/traj/{name}.txt")
    gt_map_file = gt_map_file or ground_truth.first_upwards(root, f"groundtruth/map/{name}/merged_scan.pcd")
    return _timestamped_sequence(root, files, scan_times, FUSIONPORTABLE_DEVKIT_ODOMETRY, (), tol, gt_poses_file,
                                 gt_map_file, gt_from_scan, gt_time_offset_s)


def _timestamped_sequence(root: Path, files: list[Path], scan_times: np.ndarray, pose_files: tuple[str, ...],
                          gt_files: tuple[str, ...], tol: float, gt_poses_file: Path | None = None,
                          gt_map_file: Path | None = None, gt_from_scan: np.ndarray | None = None,
                          gt_time_offset_s: float = 0.0) -> Sequence:
    """The part that FusionPortable and Newer College share: scans with timestamps, initial poses (TUM) and
    optional ground truth (gt_poses_file, else the first of gt_files under root) matched to them by nearest
    timestamp, optional GT map (gt_map_file, else ROOT/gt_map.pcd|ply)."""
    pose_file = _first_existing(root, pose_files)
    if pose_file is None:
        raise DataError(f"{root}: no initial pose file (looked for {', '.join(pose_files)})")
    pose_times, poses = read_tum(pose_file)
    aligned = align_poses(poses, pose_times, pose_file, files, scan_times, tol=tol, root=root)

    gt_poses = None
    gt_file = gt_poses_file or _first_existing(root, gt_files)
    if gt_file is not None:
        gt_poses = _matched_ground_truth(root, files, scan_times, gt_file, tol, gt_from_scan, gt_time_offset_s)

    return build_sequence(root, files, aligned.poses, scan_times, gt_poses, pose_file, gt_map_file)


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
# 2021 ground truth as downloaded (gt-nc-quad-easy.csv ...; gt_state_easy.csv ... for the maths sequences) and as
# evalio's downloader names it (ground_truth.csv): github.com/contagon/evalio, newer_college_2021.py.
NEWER_COLLEGE_2021_GT_PATTERNS = ("gt-nc-*.csv", "gt_state_*.csv", "ground_truth.csv")
_NEWER_COLLEGE_CLOUD_NAME = re.compile(r"^cloud_(\d+)_(\d+)$")


def newer_college_release(gt_file: Path) -> str:
    """Which release a ground-truth file belongs to, by its name: registered_poses.csv is the 2020 release's,
    anything else (gt-nc-*.csv, gt_state_*.csv) the 2021 release's."""
    return "newer_college_2020" if gt_file.name == "registered_poses.csv" else "newer_college_2021"


def load_newer_college(root: str | os.PathLike, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
                       gt_poses_file: Path | None = None, gt_map_file: Path | None = None,
                       gt_from_scan: np.ndarray | None = None, scan_frame: str = "",
                       gt_time_offset_s: float = 0.0) -> Sequence:
    """Load a Newer College sequence, 2021 or 2020 release.

    2021 (multi-cam, OS0-128; the paper's quad/maths sequences) comes as rosbags: import the clouds and a
    FAST-LIO2 run with bin/import_rosbag.py, then put the ground-truth CSV beside them:

        ROOT/scans/000000.pcd ...                 clouds (bin/import_rosbag.py), sensor frame
        ROOT/poses.txt                            initial poses, TUM, one line per scan (scans match by order)
        ROOT/gt-nc-quad-easy.csv | gt_state_easy.csv   ground truth, sec,nsec,x,y,z,qx,qy,qz,qw, BASE frame

    2020 (stereo-cam, OS1-64) as extracted:

        ROOT/clouds/cloud_<sec>_<nsec>.pcd      Ouster scans in the sensor frame (also read from
                                                ROOT/raw_format/ouster_scan/ or ROOT/raw_format/clouds/)
        ROOT/odometry.txt                       initial poses, TUM (else ROOT/poses.txt or fastlio2_poses.txt)
        ROOT/registered_poses.csv               ground truth, '#sec,nsec,x,y,z,qx,qy,qz,qw'
                                                (also ROOT/ground_truth/registered_poses.csv)

    and, for both, an optional ROOT/gt_map.pcd|ply (or gt_map_file). gt_poses_file overrides the search. The
    ground truth is moved into the scans' frame by gt_from_scan (T_G_S; None: the published offset of the
    release the file name implies, newer_college_release, for scan_frame: '' = os_sensor, the raw clouds and
    FAST-LIO2's body frame as its shipped ouster64.yaml starts it (identity LiDAR-IMU extrinsic, estimated online
    unless mapping/extrinsic_est_en is false); 'os_imu' for a FAST-LIO2 run configured with the Ouster IMU's
    extrinsic; the two are 2.4 cm apart). Ground truth is matched to scans by
    nearest stamp within `tol` seconds; a scan without one is a DataError naming it. Points at the origin (no
    return in organised Ouster clouds) are dropped when read and counted in one log line."""
    root = _check_root(root)
    if (root / "scans").is_dir() and (root / "poses.txt").is_file():
        files = _sorted_by_name(_list_scans(root / "scans"))
        pose_file = root / "poses.txt"
        pose_times, poses = read_tum(pose_file)
        aligned = align_poses(poses, pose_times, pose_file, files, None, tol=tol, root=root)
        scan_times = aligned.timestamps
        gt_file = gt_poses_file or next((p for pattern in NEWER_COLLEGE_2021_GT_PATTERNS
                                         for p in sorted(root.glob(pattern))), None)
        gt_poses = None
        if gt_file is not None:
            offset = gt_from_scan if gt_from_scan is not None else ground_truth.published_offset(
                newer_college_release(gt_file), scan_frame)
            gt_poses = _matched_ground_truth(root, files, scan_times, gt_file, tol, offset, gt_time_offset_s)
        return build_sequence(root, files, aligned.poses, scan_times, gt_poses, pose_file, gt_map_file)

    scan_folder = next((root / f for f in NEWER_COLLEGE_SCAN_FOLDERS if (root / f).is_dir()), None)
    if scan_folder is None:
        raise DataError(f"{root}: no scan folder (looked for scans/ with poses.txt, "
                        f"{', '.join(NEWER_COLLEGE_SCAN_FOLDERS)})")
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
    gt_file = gt_poses_file or _first_existing(root, NEWER_COLLEGE_GT_FILES)
    if gt_from_scan is None and gt_file is not None:
        gt_from_scan = ground_truth.published_offset(newer_college_release(gt_file), scan_frame)
    return _timestamped_sequence(root, files, scan_times, NEWER_COLLEGE_POSE_FILES, NEWER_COLLEGE_GT_FILES, tol,
                                 gt_file, gt_map_file, gt_from_scan, gt_time_offset_s)


# --------------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------------

# Where each format looks for ground truth by itself (for the "evaluation is skipped" line).
GT_SEARCHED = {
    "generic": ("ROOT/gt_poses.txt", "ROOT/gt_map.pcd|ply"),
    "fusionportable": ("groundtruth/traj/<sequence>.txt in or above ROOT (or ROOT/gt_poses.txt)",
                       "groundtruth/map/<sequence>/merged_scan.pcd in or above ROOT (or ROOT/gt_map.pcd|ply)"),
    "newer_college": ("ROOT/gt-nc-*.csv, gt_state_*.csv or registered_poses.csv", "ROOT/gt_map.pcd|ply"),
    "lio_keyframes": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
    "hba": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
}


def load_sequence(data_cfg) -> Sequence:
    """Load the sequence that data_cfg (ml_collections.ConfigDict) names.

    Reads data_cfg.format (one of FORMATS), data_cfg.root (folder formats) and data_cfg.synthetic (for
    'synthetic'); an optional data_cfg.timestamp_tol_s overrides the 0.05 s matching tolerance.
    Ground truth: data_cfg.gt_poses_path / gt_map_path, when set, replace what the layout has (a path that is set
    but missing is a DataError naming it); data_cfg.gt_from_scan (7 numbers, T_G_S) replaces the published frame
    offset, data_cfg.scan_frame picks which published offset (neld_jax/data/ground_truth.py), data_cfg.gt_time_offset_s
    shifts the scan stamps when matching ground truth (another stamping convention). When no
    ground-truth trajectory is found the log says so, what was looked for, and that pose evaluation is skipped.
    Preprocessing is left to the caller (see preprocess.preprocess)."""
    fmt = str(data_cfg.format).lower()
    if fmt not in FORMATS:
        raise ConfigError(f"data.format: unknown format '{data_cfg.format}' (expected one of {', '.join(FORMATS)})")
    if fmt == "synthetic":
        return synthetic.make_sequence(data_cfg.get("synthetic", None))
    root = data_cfg.get("root", None)
    if not root:
        raise ConfigError(f"data.root must be set for format '{fmt}'")
    gt_poses_file = ground_truth.explicit_path(data_cfg, "gt_poses_path")
    gt_map_file = ground_truth.explicit_path(data_cfg, "gt_map_path")
    explicit_offset = tuple(data_cfg.get("gt_from_scan", ()) or ())
    offset = ground_truth.pose_from_tuple(explicit_offset) if explicit_offset else None
    scan_frame = str(data_cfg.get("scan_frame", "") or "")
    tol = float(data_cfg.get("timestamp_tol_s", DEFAULT_TIMESTAMP_TOLERANCE_S))
    drop_tail = bool(data_cfg.get("drop_unmatched_tail", False))
    gt_dt = float(data_cfg.get("gt_time_offset_s", 0.0))

    if fmt in ("fusionportable", "newer_college"):
        loader = load_fusionportable if fmt == "fusionportable" else load_newer_college
        seq = loader(root, tol=tol, gt_poses_file=gt_poses_file, gt_map_file=gt_map_file, gt_from_scan=offset,
                     scan_frame=scan_frame, gt_time_offset_s=gt_dt)
    else:
        if fmt == "lio_keyframes":
            from neld_jax.data.lio_keyframes import DEFAULT_POSE_FILE, load_lio_keyframes

            seq = load_lio_keyframes(root, pose_file=data_cfg.get("pose_file", "") or DEFAULT_POSE_FILE,
                                     drop_unmatched_tail=drop_tail)
        elif fmt == "hba":
            from neld_jax.data.hba import load_hba

            seq = load_hba(root, drop_unmatched_tail=drop_tail)
        else:
            seq = load_generic(root, tol=tol, drop_unmatched_tail=drop_tail)
        seq = _with_explicit_ground_truth(seq, Path(root).expanduser(), gt_poses_file, gt_map_file, offset, tol, gt_dt)
    # Poses sensor -> world and scans in the sensor frame: converted when the config says so, else checked (and
    # refused with a line naming the option when they look the other way).
    invert = bool(data_cfg.get("invert_poses", False))
    seq = frames.inverted_poses(seq, str(root)) if invert else seq
    seq = frames.in_sensor_frame(seq, str(root), bool(data_cfg.get("scans_in_world_frame", False)))
    if not invert:
        frames.check_pose_direction(seq, str(root))

    if seq.gt_poses is None:
        looked = f"data.gt_poses_path {gt_poses_file}" if gt_poses_file else GT_SEARCHED[fmt][0]
        logger.warning("%s: no ground-truth trajectory (looked for %s; set data.gt_poses_path to give one): pose "
                       "errors (ATE/RPE) will not be evaluated", root, looked)
    if seq.gt_map is None:
        logger.warning("%s: no ground-truth map (looked for %s; set data.gt_map_path to give one): map errors will "
                       "not be evaluated", root, GT_SEARCHED[fmt][1])
    return seq


def _with_explicit_ground_truth(seq: Sequence, root: Path, gt_poses_file: Path | None, gt_map_file: Path | None,
                                gt_from_scan: np.ndarray | None, tol: float, gt_time_offset_s: float = 0.0) -> Sequence:
    """seq with data.gt_poses_path / gt_map_path in place of the layout's own ground truth (formats whose loader
    does not search for it itself): poses matched by time when both sides have stamps, else by order."""
    if gt_poses_file is None and gt_map_file is None:
        return seq
    import dataclasses

    changes = {}
    if gt_poses_file is not None:
        files = [root / f for f in seq.files] if seq.files else [Path(f"scan {i}") for i in range(seq.num_scans)]
        gt_times, _ = ground_truth.read_trajectory(gt_poses_file)
        by_time = seq.timestamps is not None and gt_times is not None
        changes["gt_poses"] = _matched_ground_truth(root, files, seq.timestamps if by_time else None, gt_poses_file,
                                                    tol, gt_from_scan, gt_time_offset_s)
    if gt_map_file is not None:
        changes["gt_map"] = read_scan(gt_map_file)
    return dataclasses.replace(seq, **changes)
