"""Newer College (ori-drs.github.io/newer-college-dataset): the 2021 release's clouds imported from its rosbags with
a FAST-LIO2 run or its rosbags as downloaded (raw Ouster sweeps, no poses), or the 2020 release's
cloud_<sec>_<nsec>.pcd as extracted, each with its ground truth (load_newer_college).

2021 (multi-cam, OS0-128; the paper's quad/maths sequences) comes as rosbags: import the clouds and a FAST-LIO2 run
with bin/import_rosbag.py, then put the ground-truth CSV beside them:

    ROOT/scans/000000.pcd ...                 clouds (bin/import_rosbag.py), sensor frame
    ROOT/poses.txt                            initial poses, TUM, one line per scan (scans match by order)
    ROOT/gt-nc-quad-easy.csv | gt_state_easy.csv   ground truth, sec,nsec,x,y,z,qx,qy,qz,qw, BASE frame

or the 2021 bags as downloaded (load_newer_college_bags), when ROOT has neither of the folders below:

    ROOT/2021-07-01-10-37-38-quad-easy.bag ...   every ROOT/*.bag, parts of one recording read in stamp order;
                                                 LIDAR_TOPIC's raw sweeps, per-point times, no poses
    ROOT/gt-nc-quad-easy.csv                     ground truth as above

2020 (stereo-cam, OS1-64) as extracted:

    ROOT/clouds/cloud_<sec>_<nsec>.pcd      Ouster scans in the sensor frame (also read from
                                            ROOT/raw_format/ouster_scan/ or ROOT/raw_format/clouds/)
    ROOT/odometry.txt                       initial poses, TUM (else ROOT/poses.txt or fastlio2_poses.txt)
    ROOT/registered_poses.csv               ground truth, '#sec,nsec,x,y,z,qx,qy,qz,qw'
                                            (also ROOT/ground_truth/registered_poses.csv)

and, for both, an optional ROOT/gt_map.pcd|ply.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from neld_jax.data import ground_truth
from neld_jax.data.bags import raw_bags
from neld_jax.data.layout import (
    LoadOptions,
    align_poses,
    build_sequence,
    check_root,
    config_root,
    first_existing,
    list_scans,
    load_options,
    matched_ground_truth,
    sorted_by_name,
    timestamped_sequence,
)
from neld_jax.data.poses import read_tum
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

SCAN_FOLDERS = ("clouds", "raw_format/ouster_scan", "raw_format/clouds")
POSE_FILES = ("odometry.txt", "poses.txt", "fastlio2_poses.txt")
GT_FILES = ("registered_poses.csv", "ground_truth/registered_poses.csv")
# 2021 ground truth as downloaded (gt-nc-quad-easy.csv ...; gt_state_easy.csv ... for the maths sequences) and as
# evalio's downloader names it (ground_truth.csv): github.com/contagon/evalio, newer_college_2021.py.
GT_2021_PATTERNS = ("gt-nc-*.csv", "gt_state_*.csv", "ground_truth.csv")
# The 2021 bags' Ouster clouds, frame os_sensor (the topic FAST-LIO2's ouster64.yaml reads: docs/datasets.md).
LIDAR_TOPIC = "/os_cloud_node/points"
LIDAR_FRAME = "os_sensor"
_CLOUD_NAME = re.compile(r"^cloud_(\d+)_(\d+)$")


def newer_college_release(gt_file: Path) -> str:
    """Which release a ground-truth file belongs to, by its name: registered_poses.csv is the 2020 release's,
    anything else (gt-nc-*.csv, gt_state_*.csv) the 2021 release's."""
    return "newer_college_2020" if gt_file.name == "registered_poses.csv" else "newer_college_2021"


def load_newer_college(root: str | os.PathLike, options: LoadOptions = LoadOptions()) -> Sequence:
    """Load a Newer College sequence, 2021 or 2020 release, from ROOT in any of the layouts of the module docstring,
    with the ground-truth and matching settings of options (layout.LoadOptions; drop_unmatched_tail is not read).

    options.gt_map_file overrides ROOT/gt_map.pcd|ply, options.gt_poses_file the search for the ground truth. The
    ground truth is moved into the scans' frame by options.gt_from_scan (T_G_S [4, 4]; None: the published offset
    of the release the file name implies, newer_college_release, for options.scan_frame: '' = os_sensor, the raw
    clouds and FAST-LIO2's body frame as its shipped ouster64.yaml starts it (identity LiDAR-IMU extrinsic,
    estimated online unless mapping/extrinsic_est_en is false); 'os_imu' for a FAST-LIO2 run configured with the
    Ouster IMU's extrinsic; the two are 2.4 cm apart). Ground truth is matched to scans by nearest stamp within
    options.tol seconds (after adding options.gt_time_offset_s to the scan stamps); a scan without one is a
    DataError naming it. Points at the origin (no return in organised Ouster clouds) are dropped when read and
    counted in one log line."""
    root = check_root(root)
    if (root / "scans").is_dir() and (root / "poses.txt").is_file():
        return _load_imported_2021(root, options)

    scan_folder = next((root / f for f in SCAN_FOLDERS if (root / f).is_dir()), None)
    if scan_folder is None:
        bags = raw_bags.bags_in(root)
        if bags:
            return load_newer_college_bags(root, bags, options)
        raise DataError(
            f"{root}: no scan folder (looked for scans/ with poses.txt, {', '.join(SCAN_FOLDERS)}) and no *.bag"
        )
    files, scan_times = _clouds_by_name(list_scans(scan_folder))
    resolved = _with_ground_truth(options, options.gt_poses_file or first_existing(root, GT_FILES))
    return timestamped_sequence(root, files, scan_times, POSE_FILES, GT_FILES, resolved)


def _with_ground_truth(options: LoadOptions, gt_file: Path | None, default_frame: str = "") -> LoadOptions:
    """options with gt_poses_file = gt_file (None: no ground truth) and gt_from_scan given, else (with a gt_file)
    the published offset of its release for options.scan_frame, or else default_frame."""
    gt_from_scan = options.gt_from_scan
    if gt_from_scan is None and gt_file is not None:
        release = newer_college_release(gt_file)
        gt_from_scan = ground_truth.published_offset(release, options.scan_frame or default_frame)
    return dataclasses.replace(options, gt_poses_file=gt_file, gt_from_scan=gt_from_scan)


def _load_imported_2021(root: Path, options: LoadOptions) -> Sequence:
    """The 2021 release's clouds as bin/import_rosbag.py writes them, ROOT/scans/ with ROOT/poses.txt, and its
    ground truth (options.gt_poses_file, else ROOT/gt-nc-*.csv, gt_state_*.csv); options as load_newer_college's."""
    files = sorted_by_name(list_scans(root / "scans"))
    pose_file = root / "poses.txt"
    pose_times, poses = read_tum(pose_file)
    aligned = align_poses(poses, pose_times, pose_file, files, None, tol=options.tol, root=root)
    scan_times = aligned.timestamps
    resolved = _with_ground_truth(options, options.gt_poses_file or _gt_2021_file(root))
    gt_poses = None
    if resolved.gt_poses_file is not None:
        gt_poses = matched_ground_truth(
            root,
            files,
            scan_times,
            resolved.gt_poses_file,
            resolved.tol,
            resolved.gt_from_scan,
            resolved.gt_time_offset_s,
        )
    return build_sequence(root, files, aligned.poses, scan_times, gt_poses, pose_file, resolved.gt_map_file)


def _clouds_by_name(files: list[Path]) -> tuple[list[Path], np.ndarray]:
    """The 2020 release's cloud_<sec>_<nsec> scans in stamp order, with their stamps [S] in seconds; DataError
    naming the first scan named otherwise."""
    times = []
    for f in files:
        match = _CLOUD_NAME.match(f.stem)
        if match is None:
            raise DataError(f"{f}: Newer College scan names must be cloud_<sec>_<nsec>{f.suffix}")
        times.append(int(match.group(1)) + int(match.group(2)) * 1e-9)
    order = np.argsort(times, kind="stable")
    return [files[i] for i in order], np.asarray(times, dtype=np.float64)[order]


def _gt_2021_file(root: Path) -> Path | None:
    """The first ground-truth file of the 2021 release in ROOT (GT_2021_PATTERNS, in order; None: none)."""
    return next((p for pattern in GT_2021_PATTERNS for p in sorted(root.glob(pattern))), None)


def load_newer_college_bags(root: Path, bags: list[Path], options: LoadOptions = LoadOptions()) -> Sequence:
    """The 2021 bag(s) as downloaded, as raw sweeps (raw_bags): LIDAR_TOPIC, poses None, per-point times, files
    "<bag>:/os_cloud_node/points#000123". Ground truth (options.gt_poses_file, else ROOT/gt-nc-*.csv,
    gt_state_*.csv) matched to the scan stamps within options.tol and moved into the scan frame by
    options.gt_from_scan (None: the published offset for options.scan_frame, default os_sensor, the raw clouds'
    frame); options (layout.LoadOptions) as load_newer_college's."""
    sweeps = raw_bags.read_lidar_bag(bags, LIDAR_TOPIC)
    resolved = _with_ground_truth(options, options.gt_poses_file or _gt_2021_file(root), LIDAR_FRAME)
    return raw_bags.sweeps_sequence(root, sweeps, resolved)


def load(data_cfg) -> Sequence:
    """data.format = 'newer_college': load_newer_college(data.root) with layout.load_options (data.timestamp_tol_s,
    the explicit ground-truth paths, gt_from_scan, scan_frame, gt_time_offset_s)."""
    return load_newer_college(config_root(data_cfg, "newer_college"), load_options(data_cfg))
