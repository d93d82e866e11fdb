"""What the folder loaders share: the data.* options they read, checking the root, listing and naming scan files,
reading scans with counts, matching poses to scans, ground truth from a file, and building the Sequence.

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

import dataclasses
import logging
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from neld_jax.data import ground_truth
from neld_jax.data.poses import read_tum
from neld_jax.data.scan_source import ScanFiles
from neld_jax.data.scans import SCAN_EXTENSIONS, read_scan, read_scan_counted
from neld_jax.data.sequence import Sequence, check_pose_jumps
from neld_jax.data.timing import DEFAULT_TIMESTAMP_TOLERANCE_S, match_by_timestamp
from neld_jax.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

# drop_unmatched_tail forgives a recording cut a little unevenly at its end, not a different sequence.
MAX_UNMATCHED_TAIL = 5


# --------------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoadOptions:
    """The data.* settings that the folder formats read besides data.root (config_root) and their own fields: every
    folder loader (load_generic, load_kitti, load_fusionportable, ...) takes them as `options`, load_options makes
    them from the config, and a loader's docstring says which of them it does not read.

    tol:                 seconds, scan <-> pose matching by time (data.timestamp_tol_s)
    drop_unmatched_tail: drop a few trailing scans without a pose (align_poses) instead of an error
    gt_poses_file:       data.gt_poses_path, or None: the layout's own ground truth
    gt_map_file:         data.gt_map_path, or None: the layout's own map
    gt_from_scan:        [4, 4] T_G_S from data.gt_from_scan, or None: the format's published offset
    scan_frame:          data.scan_frame, which published offset applies ('' = the format's default)
    gt_time_offset_s:    seconds added to the scan stamps when matching ground truth
    """

    tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S
    drop_unmatched_tail: bool = False
    gt_poses_file: Path | None = None
    gt_map_file: Path | None = None
    gt_from_scan: np.ndarray | None = None
    scan_frame: str = ""
    gt_time_offset_s: float = 0.0


def config_root(data_cfg, fmt: str) -> str:
    """data_cfg.root, which every folder format needs; ConfigError naming the format when it is unset."""
    root = data_cfg.get("root", None)
    if not root:
        raise ConfigError(f"data.root must be set for format '{fmt}'")
    return root


def load_options(data_cfg) -> LoadOptions:
    """The LoadOptions of data_cfg (ml_collections.ConfigDict or a mapping with .get). A ground-truth path that is
    set but missing is a DataError naming it, a malformed gt_from_scan a ConfigError (ground_truth)."""
    gt_poses_file = ground_truth.explicit_path(data_cfg, "gt_poses_path")
    gt_map_file = ground_truth.explicit_path(data_cfg, "gt_map_path")
    explicit_offset = tuple(data_cfg.get("gt_from_scan", ()) or ())
    gt_from_scan = ground_truth.pose_from_tuple(explicit_offset) if explicit_offset else None
    return LoadOptions(
        gt_poses_file=gt_poses_file,
        gt_map_file=gt_map_file,
        gt_from_scan=gt_from_scan,
        scan_frame=str(data_cfg.get("scan_frame", "") or ""),
        tol=float(data_cfg.get("timestamp_tol_s", DEFAULT_TIMESTAMP_TOLERANCE_S)),
        drop_unmatched_tail=bool(data_cfg.get("drop_unmatched_tail", False)),
        gt_time_offset_s=float(data_cfg.get("gt_time_offset_s", 0.0)),
    )


# --------------------------------------------------------------------------------------------------
# Folders and file names
# --------------------------------------------------------------------------------------------------


def check_root(root: str | os.PathLike) -> Path:
    """root as a Path (~ expanded); DataError when it is not an existing folder."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"data root {root} does not exist (or is not a folder)")
    return root


def list_scans(folder: Path) -> list[Path]:
    """Scan files in folder with a known extension (hidden files and others are skipped and counted)."""
    if not folder.is_dir():
        raise DataError(f"scan folder {folder} does not exist")
    files, others = [], []
    for entry in folder.iterdir():
        if entry.name.startswith("."):
            continue
        (files if entry.is_file() and entry.suffix.lower() in SCAN_EXTENSIONS else others).append(entry)
    if others:
        logger.warning(
            "%s: ignored %d entries that are not scan files (%s)",
            folder,
            len(others),
            ", ".join(sorted(p.name for p in others)[:5]),
        )
    if not files:
        raise DataError(f"scan folder {folder} contains no scan files ({', '.join(SCAN_EXTENSIONS)})")
    return files


def _numeric_stem(path: Path) -> float | None:
    """The file name as a number (000012.pcd -> 12.0), else None; used for sorting."""
    try:
        return float(path.stem)
    except ValueError:
        return None


def timestamp_from_name(path: Path) -> float | None:
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


def sorted_by_name(files: list[Path]) -> list[Path]:
    """Sort by numeric value when every name is a number (timestamps of different lengths), else by name."""
    stems = [_numeric_stem(f) for f in files]
    if all(s is not None for s in stems):
        return [f for _, f in sorted(zip(stems, files), key=lambda pair: (pair[0], pair[1].name))]
    return sorted(files, key=lambda f: f.name)


def first_existing(root: Path, candidates: tuple[str, ...]) -> Path | None:
    """The first of root/<candidate> that is a file, else None."""
    for name in candidates:
        if (root / name).is_file():
            return root / name
    return None


def _relative(path: Path, root: Path | None) -> str:
    """path relative to root when it lies inside it (scans/000002.pcd), else the path as given."""
    if root is not None:
        try:
            return path.relative_to(root).as_posix()
        except ValueError:
            pass
    return str(path)


# --------------------------------------------------------------------------------------------------
# Reading scans
# --------------------------------------------------------------------------------------------------


def read_scans(files: list[Path]) -> ScanFiles:
    """The scans of files [S] ([N_i, 3] each), read from disk when used (data.scan_source). Each is read once here,
    in order, and dropped, so that a file that cannot be read is a DataError now rather than in the middle of a
    run; one log line with the totals dropped per reason (each file's own is in scans)."""
    totals, affected = {"read": 0, "non-finite": 0, "zero": 0}, {"non-finite": 0, "zero": 0}
    kept = 0
    for f in files:
        points, dropped = read_scan_counted(f)
        kept += len(points)
        for key in totals:
            totals[key] += dropped[key]
        for key in affected:
            affected[key] += dropped[key] > 0
    logger.info(
        "read %d scans (%d points) from %s; they are read again from disk when used", len(files), kept, files[0].parent
    )
    if totals["non-finite"] or totals["zero"]:
        logger.info(
            "dropped %d of %d points: %d NaN/infinite (in %d scans), %d at (0, 0, 0), i.e. no return (in %d scans)",
            totals["non-finite"] + totals["zero"],
            totals["read"],
            totals["non-finite"],
            affected["non-finite"],
            totals["zero"],
            affected["zero"],
        )
    return ScanFiles(files)


# --------------------------------------------------------------------------------------------------
# Matching poses to scans
# --------------------------------------------------------------------------------------------------


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
    if scan_times is not None:
        scan_times = np.asarray(scan_times, dtype=np.float64).reshape(-1)
        indices = _matched_by_time(pose_times, pose_file, scan_times, tol, labels)
        return Alignment(poses[indices], scan_times, np.arange(len(scan_files), dtype=np.int64))
    keep = _matched_by_order(poses.shape[0], pose_times, pose_file, scan_files, drop_unmatched_tail, root)
    times = None if pose_times is None else pose_times[:keep]
    return Alignment(poses[:keep], times, np.arange(keep, dtype=np.int64))


def _matched_by_time(
    pose_times: np.ndarray | None, pose_file: Path, scan_times: np.ndarray, tol: float, labels: list[str]
) -> np.ndarray:
    """align_poses by time: the index [S] of each scan's pose (nearest within tol); pose times out of order warned
    about."""
    if pose_times is None:
        raise DataError(f"{pose_file}: has no timestamps, so its poses cannot be matched to scans by time")
    back = np.flatnonzero(np.diff(pose_times) < 0)
    if back.size:
        logger.warning(
            "%s: timestamps are not in time order (pose %d at t=%.6f comes after t=%.6f; %d such "
            "places); poses are matched by time, so this only matters if the file is a mix-up",
            pose_file,
            back[0] + 2,
            pose_times[back[0] + 1],
            pose_times[back[0]],
            back.size,
        )
    return match_by_timestamp(scan_times, pose_times, tol=tol, what=str(pose_file), scan_labels=labels)


def _matched_by_order(
    num_poses: int,
    pose_times: np.ndarray | None,
    pose_file: Path,
    scan_files: list[Path],
    drop_unmatched_tail: bool,
    root: Path | None,
) -> int:
    """align_poses by order: how many leading scans and poses pair up (align_poses' errors and warnings)."""
    if pose_times is not None:
        back = np.flatnonzero(np.diff(pose_times) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise DataError(
                f"{pose_file}: timestamps are not in time order (pose {i + 1} at t={pose_times[i]:.6f} comes after "
                f"t={pose_times[i - 1]:.6f}; {back.size} such place(s)); poses are matched to the scans "
                "one to one, in order, so the file must be sorted by time (sort it by its first column)"
            )
    num_scans = len(scan_files)
    keep, extra = min(num_poses, num_scans), abs(num_poses - num_scans)
    if not extra:
        return keep
    if num_poses < num_scans:
        left_over = [_relative(Path(f), root) for f in scan_files[keep:]]
        what = f"the last {extra} scan(s) ({_listed(left_over)}) have no pose; delete them or add poses"
    else:
        left_over = (
            [f"pose {i + 1}" for i in range(keep, num_poses)]
            if pose_times is None
            else [f"t={t:.6f}" for t in pose_times[keep:]]
        )
        what = f"the last {extra} pose(s) ({_listed(left_over)}) have no scan; delete them or add the missing scans"
    folder = _relative(Path(scan_files[0]).parent, root) + "/" if scan_files else "the scan list"
    message = (
        f"{'' if root is None else f'{root}: '}{_relative(pose_file, root)} has {num_poses} poses "
        f"but {folder} has {num_scans} scans: {what} (poses are matched to scans one to one, in order)"
    )
    if not drop_unmatched_tail or extra > MAX_UNMATCHED_TAIL:
        if drop_unmatched_tail:
            message += f"; drop_unmatched_tail drops at most {MAX_UNMATCHED_TAIL}, not {extra}"
        raise DataError(message)
    logger.warning("%s; dropped them (drop_unmatched_tail)", message)
    return keep


# --------------------------------------------------------------------------------------------------
# Ground truth from a file (explicit paths, published frame offsets: ground_truth.py)
# --------------------------------------------------------------------------------------------------


def matched_ground_truth(
    root: Path,
    files: list[Path],
    scan_times: np.ndarray | None,
    gt_file: Path,
    tol: float,
    gt_from_scan: np.ndarray | None,
    gt_time_offset_s: float = 0.0,
) -> np.ndarray:
    """The ground-truth pose of each scan [S, 4, 4]: gt_file (TUM, or Newer College CSV for .csv) matched to the
    scans by time within tol (by order without scan times), then moved into the scan frame (T_world_G @ T_G_S).
    gt_time_offset_s is added to the scan stamps for this matching only (a ground truth stamped by another
    convention, e.g. -0.1 s to pair end-of-scan stamps with start-of-scan ground truth at 10 Hz).

    files: [S] scan paths; scan_times: [S] seconds or None; gt_from_scan: [4, 4] T_G_S or None (identity).
    A scan without a ground-truth stamp within tol is a DataError naming it (match_by_timestamp): a scan is
    never given a neighbour's pose."""
    gt_times, gt_all = ground_truth.read_trajectory(gt_file)
    if scan_times is not None and gt_time_offset_s:
        scan_times = np.asarray(scan_times, dtype=np.float64) + gt_time_offset_s
    poses = align_poses(gt_all, gt_times, gt_file, files, scan_times, tol=tol, root=root).poses
    return poses if gt_from_scan is None else poses @ gt_from_scan


def with_explicit_ground_truth(seq: Sequence, root: str | os.PathLike, options: LoadOptions) -> Sequence:
    """seq with data.gt_poses_path / gt_map_path (options) in place of the layout's own ground truth, for formats
    whose loader does not search for it itself: poses matched by time when both sides have stamps, else by
    order."""
    gt_poses_file, gt_map_file = options.gt_poses_file, options.gt_map_file
    if gt_poses_file is None and gt_map_file is None:
        return seq
    root = Path(root).expanduser()
    changes = {}
    if gt_poses_file is not None:
        files = [root / f for f in seq.files] if seq.files else [Path(f"scan {i}") for i in range(seq.num_scans)]
        gt_times, _ = ground_truth.read_trajectory(gt_poses_file)
        by_time = seq.timestamps is not None and gt_times is not None
        changes["gt_poses"] = matched_ground_truth(
            root,
            files,
            seq.timestamps if by_time else None,
            gt_poses_file,
            options.tol,
            options.gt_from_scan,
            options.gt_time_offset_s,
        )
    if gt_map_file is not None:
        changes["gt_map"] = read_scan(gt_map_file)
    return dataclasses.replace(seq, **changes)


# --------------------------------------------------------------------------------------------------
# The Sequence
# --------------------------------------------------------------------------------------------------


def _read_gt_map(root: Path) -> np.ndarray | None:
    path = first_existing(root, ("gt_map.pcd", "gt_map.ply"))
    return None if path is None else read_scan(path)


def build_sequence(
    root: Path,
    files: list[Path],
    poses: np.ndarray | None,
    timestamps: np.ndarray | None,
    gt_poses: np.ndarray | None,
    pose_file: Path | str,
    gt_map_file: Path | None = None,
) -> Sequence:
    """Read the scans and the GT map (gt_map_file, else ROOT/gt_map.pcd|ply if present), build the Sequence
    (files relative to root), check for pose jumps.

    files: [S] scan paths; poses: [S, 4, 4] or None (none in the layout); timestamps: [S] seconds or None;
    gt_poses: [S, 4, 4] or None;
    pose_file names the pose source in the pose-jump warning."""
    seq = Sequence(
        scans=read_scans(files),
        poses=poses,
        timestamps=timestamps,
        gt_poses=gt_poses,
        gt_map=read_scan(gt_map_file) if gt_map_file is not None else _read_gt_map(root),
        name=root.name,
        source=str(root),
        files=[_relative(f, root) for f in files],
    )
    if poses is not None:
        check_pose_jumps(seq.poses, [seq.scan_label(i) for i in range(seq.num_scans)], what=str(pose_file))
    return seq


def timestamped_sequence(
    root: Path,
    files: list[Path],
    scan_times: np.ndarray,
    pose_files: tuple[str, ...],
    gt_files: tuple[str, ...],
    options: LoadOptions,
) -> Sequence:
    """Scans with timestamps (files [S], scan_times [S] seconds), initial poses (the first of pose_files under
    root, TUM) and optional ground truth (options.gt_poses_file, else the first of gt_files under root) matched to
    them by nearest timestamp within options.tol and moved by options.gt_from_scan, optional GT map
    (options.gt_map_file, else ROOT/gt_map.pcd|ply): the part that the FusionPortable and Newer College loaders
    share."""
    pose_file = first_existing(root, pose_files)
    if pose_file is None:
        raise DataError(f"{root}: no initial pose file (looked for {', '.join(pose_files)})")
    pose_times, poses = read_tum(pose_file)
    aligned = align_poses(poses, pose_times, pose_file, files, scan_times, tol=options.tol, root=root)

    gt_poses = None
    gt_file = options.gt_poses_file or first_existing(root, gt_files)
    if gt_file is not None:
        gt_poses = matched_ground_truth(
            root, files, scan_times, gt_file, options.tol, options.gt_from_scan, options.gt_time_offset_s
        )

    return build_sequence(root, files, aligned.poses, scan_times, gt_poses, pose_file, options.gt_map_file)
