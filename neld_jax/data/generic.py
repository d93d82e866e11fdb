"""The generic layout (docs/design.md, "Data on disk"): the one bin/import_rosbag.py and synthetic.write_generic
write.

    ROOT/scans/*.{pcd,ply,bin,npy}   one scan per file, sensor frame, sorted by name
    ROOT/poses.txt                   initial poses, TUM (without it: made from the scans, neld_jax.frontend)
    ROOT/gt_poses.txt                optional ground-truth poses, TUM
    ROOT/gt_map.pcd | gt_map.ply     optional ground-truth map, world frame
    ROOT/point_times/<scan name>.npy optional, [N] float64 seconds after the scan's stamp per point (raw sweeps,
                                     bin/import_rosbag.py without odometry): read when every scan has one
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from neld_jax.data.layout import (
    LoadOptions,
    align_poses,
    build_sequence,
    check_root,
    config_root,
    list_scans,
    load_options,
    sorted_by_name,
    timestamp_from_name,
    with_explicit_ground_truth,
)
from neld_jax.data.poses import read_tum
from neld_jax.data.scan_source import ScanFiles
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

POINT_TIMES_FOLDER = "point_times"  # raw sweeps' per-point times beside scans/ (which takes any .npy as a scan)


def load_generic(root: str | os.PathLike, options: LoadOptions = LoadOptions()) -> Sequence:
    """Load the layout of this module's docstring, with the matching and ground-truth settings of options
    (layout.LoadOptions; scan_frame is not read, gt_from_scan and gt_time_offset_s only for options.gt_poses_file).

    Poses match scans by order (their timestamps must then increase). Only when the counts differ and
    every scan name is a timestamp (1650000000.123456.pcd, or 10/13/16/19-digit integer s/ms/us/ns;
    zero-padded frame numbers such as 000012.pcd are not) are they matched by timestamp, nearest within
    options.tol seconds. Ground-truth poses follow the same rule (a different count is matched against the scan
    timestamps). options.drop_unmatched_tail: see layout.align_poses (a few trailing scans without a pose are
    dropped with a warning instead of an error). Without poses.txt: the scans in name order, stamped by their names
    when those are times, poses None (load_sequence makes them). options.gt_poses_file / gt_map_file, when set,
    replace the layout's ground truth (layout.with_explicit_ground_truth)."""
    root = check_root(root)
    scan_folder = root / "scans"
    files = sorted_by_name(list_scans(scan_folder))
    name_times = [timestamp_from_name(f) for f in files]
    names_are_times = all(t is not None for t in name_times)

    pose_file = root / "poses.txt"
    if not pose_file.is_file():  # load_sequence makes the poses from the scans
        logger.info("%s: no poses.txt: the initial poses will be made from the %d scans", root, len(files))
        timestamps = np.asarray(name_times, dtype=np.float64) if names_are_times else None
        gt_poses = _ground_truth(root, files, timestamps, False, options.tol)
        seq = build_sequence(root, files, None, timestamps, gt_poses, "no poses")
        return with_explicit_ground_truth(with_point_times(seq, root), root, options)
    pose_times, poses = read_tum(pose_file)
    by_time = names_are_times and poses.shape[0] != len(files)
    scan_times = np.asarray(name_times, dtype=np.float64) if by_time else None
    aligned = align_poses(
        poses,
        pose_times,
        pose_file,
        files,
        scan_times,
        tol=options.tol,
        drop_unmatched_tail=options.drop_unmatched_tail,
        root=root,
    )
    files = [files[i] for i in aligned.scan_indices]
    gt_poses = _ground_truth(root, files, aligned.timestamps, by_time, options.tol)
    seq = build_sequence(root, files, aligned.poses, aligned.timestamps, gt_poses, pose_file)
    return with_explicit_ground_truth(with_point_times(seq, root), root, options)


def _ground_truth(
    root: Path, files: list[Path], timestamps: np.ndarray | None, by_time: bool, tol: float
) -> np.ndarray | None:
    """ROOT/gt_poses.txt matched to the scans files [S] ([S, 4, 4]), None without the file: by time (timestamps [S])
    when the poses were matched by time or the counts differ, else by order."""
    gt_file = root / "gt_poses.txt"
    if not gt_file.is_file():
        return None
    gt_times, gt_all = read_tum(gt_file)
    gt_by_time = by_time or gt_all.shape[0] != len(files)
    return align_poses(gt_all, gt_times, gt_file, files, timestamps if gt_by_time else None, tol=tol, root=root).poses


def with_point_times(seq: Sequence, root: Path) -> Sequence:
    """seq with point_times from ROOT/point_times/<scan stem>.npy when every scan has that file (else seq as it
    is, with a warning when only some have one), read from disk when used (data.scan_source). A times file whose
    length is not its scan's point count is a DataError naming the scan when the two are used together
    (odometry.deskewed_sweeps)."""
    if not (root / POINT_TIMES_FOLDER).is_dir() or not seq.files:
        return seq
    paths = [root / POINT_TIMES_FOLDER / f"{Path(f).stem}.npy" for f in seq.files]
    present = [p.is_file() for p in paths]
    if not all(present):
        logger.warning(
            "%s: %d of %d scans have no %s/<scan>.npy (first: %s); per-point times are not used",
            root,
            present.count(False),
            len(paths),
            POINT_TIMES_FOLDER,
            seq.files[present.index(False)],
        )
        return seq
    return dataclasses.replace(seq, point_times=ScanFiles(paths, read_point_times))


def read_point_times(path: Path) -> np.ndarray:
    """One scan's per-point times [N] float64 from path (.npy); a DataError naming it when unreadable."""
    try:
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.float64).reshape(-1)
    except (ValueError, OSError, EOFError) as exc:
        raise DataError(f"{path}: unreadable per-point times ({exc})") from exc


def load(data_cfg) -> Sequence:
    """data.format = 'generic': load_generic(data.root) with layout.load_options (data.timestamp_tol_s,
    data.drop_unmatched_tail, data.gt_poses_path / gt_map_path ...)."""
    return load_generic(config_root(data_cfg, "generic"), load_options(data_cfg))
