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
from neld_jax.data.timing import DEFAULT_TIMESTAMP_TOLERANCE_S
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


def load_newer_college(
    root: str | os.PathLike,
    tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
    gt_poses_file: Path | None = None,
    gt_map_file: Path | None = None,
    gt_from_scan: np.ndarray | None = None,
    scan_frame: str = "",
    gt_time_offset_s: float = 0.0,
) -> Sequence:
    """Load a Newer College sequence, 2021 or 2020 release, from ROOT in any of the layouts of the module docstring.

    gt_map_file overrides ROOT/gt_map.pcd|ply, gt_poses_file the search for the ground truth. The ground truth is
    moved into the scans' frame by gt_from_scan (T_G_S [4, 4]; None: the published offset of the release the file
    name implies, newer_college_release, for scan_frame: '' = os_sensor, the raw clouds and FAST-LIO2's body frame
    as its shipped ouster64.yaml starts it (identity LiDAR-IMU extrinsic, estimated online unless
    mapping/extrinsic_est_en is false); 'os_imu' for a FAST-LIO2 run configured with the Ouster IMU's extrinsic;
    the two are 2.4 cm apart). Ground truth is matched to scans by nearest stamp within `tol` seconds; a scan
    without one is a DataError naming it. Points at the origin (no return in organised Ouster clouds) are dropped
    when read and counted in one log line."""
    root = check_root(root)
    if (root / "scans").is_dir() and (root / "poses.txt").is_file():
        return _load_imported_2021(root, tol, gt_poses_file, gt_map_file, gt_from_scan, scan_frame, gt_time_offset_s)

    scan_folder = next((root / f for f in SCAN_FOLDERS if (root / f).is_dir()), None)
    if scan_folder is None:
        bags = raw_bags.bags_in(root)
        if bags:
            return load_newer_college_bags(
                root, bags, tol, gt_poses_file, gt_map_file, gt_from_scan, scan_frame, gt_time_offset_s
            )
        raise DataError(
            f"{root}: no scan folder (looked for scans/ with poses.txt, {', '.join(SCAN_FOLDERS)}) and no *.bag"
        )
    files, scan_times = _clouds_by_name(list_scans(scan_folder))
    gt_file = gt_poses_file or first_existing(root, GT_FILES)
    if gt_from_scan is None and gt_file is not None:
        gt_from_scan = ground_truth.published_offset(newer_college_release(gt_file), scan_frame)
    return timestamped_sequence(
        root,
        files,
        scan_times,
        POSE_FILES,
        GT_FILES,
        LoadOptions(
            tol=tol,
            gt_poses_file=gt_file,
            gt_map_file=gt_map_file,
            gt_from_scan=gt_from_scan,
            gt_time_offset_s=gt_time_offset_s,
        ),
    )


def _load_imported_2021(
    root: Path,
    tol: float,
    gt_poses_file: Path | None,
    gt_map_file: Path | None,
    gt_from_scan: np.ndarray | None,
    scan_frame: str,
    gt_time_offset_s: float,
) -> Sequence:
    """The 2021 release's clouds as bin/import_rosbag.py writes them, ROOT/scans/ with ROOT/poses.txt, and its
    ground truth (gt_poses_file, else ROOT/gt-nc-*.csv, gt_state_*.csv); arguments as load_newer_college's."""
    files = sorted_by_name(list_scans(root / "scans"))
    pose_file = root / "poses.txt"
    pose_times, poses = read_tum(pose_file)
    aligned = align_poses(poses, pose_times, pose_file, files, None, tol=tol, root=root)
    scan_times = aligned.timestamps
    gt_file = gt_poses_file or _gt_2021_file(root)
    gt_poses = None
    if gt_file is not None:
        offset = (
            gt_from_scan
            if gt_from_scan is not None
            else ground_truth.published_offset(newer_college_release(gt_file), scan_frame)
        )
        gt_poses = matched_ground_truth(root, files, scan_times, gt_file, tol, offset, gt_time_offset_s)
    return build_sequence(root, files, aligned.poses, scan_times, gt_poses, pose_file, gt_map_file)


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


def load_newer_college_bags(
    root: Path,
    bags: list[Path],
    tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S,
    gt_poses_file: Path | None = None,
    gt_map_file: Path | None = None,
    gt_from_scan: np.ndarray | None = None,
    scan_frame: str = "",
    gt_time_offset_s: float = 0.0,
) -> Sequence:
    """The 2021 bag(s) as downloaded, as raw sweeps (raw_bags): LIDAR_TOPIC, poses None, per-point times, files
    "<bag>:/os_cloud_node/points#000123". Ground truth (gt_poses_file, else ROOT/gt-nc-*.csv, gt_state_*.csv)
    matched to the scan stamps within tol and moved into the scan frame by gt_from_scan (None: the published
    offset for scan_frame, default os_sensor, the raw clouds' frame)."""
    sweeps = raw_bags.read_lidar_bag(bags, LIDAR_TOPIC)
    gt_file = gt_poses_file or _gt_2021_file(root)
    if gt_file is not None and gt_from_scan is None:
        gt_from_scan = ground_truth.published_offset(newer_college_release(gt_file), scan_frame or LIDAR_FRAME)
    return raw_bags.sweeps_sequence(root, sweeps, gt_file, gt_from_scan, tol, gt_time_offset_s, gt_map_file)


def load(data_cfg) -> Sequence:
    """data.format = 'newer_college': load_newer_college(data.root) with the ground-truth options of
    layout.load_options (explicit paths, gt_from_scan, scan_frame, gt_time_offset_s) and data.timestamp_tol_s."""
    root = config_root(data_cfg, "newer_college")
    options = load_options(data_cfg)
    return load_newer_college(
        root,
        tol=options.tol,
        gt_poses_file=options.gt_poses_file,
        gt_map_file=options.gt_map_file,
        gt_from_scan=options.gt_from_scan,
        scan_frame=options.scan_frame,
        gt_time_offset_s=options.gt_time_offset_s,
    )
