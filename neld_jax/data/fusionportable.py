"""FusionPortable (fusionportable.github.io): a sequence as the dataset's devkit exports a FAST-LIO2 run, or its bag
as downloaded (raw Ouster sweeps, no poses), with the download's ground truth; or scans named by timestamp beside a
pose file (load_fusionportable).

ROOT is the devkit's sequence folder (<dataset_path>/<sequence>, e.g. .../sensor_data/handheld/20220216_canteen_day);
its export, as the devkit writes it:

    ROOT/algorithm_result/ouster00_undistort/points/data/000000.pcd ...   FAST-LIO2's /cloud_registered_body,
                                                                           IMU (body_imu) frame
    ROOT/algorithm_result/ouster00_undistort/points/timestamps.txt         one stamp per cloud (sec.nsec),
                                                                           header stamps: END of the scan
    ROOT/algorithm_result/odometry/odometry.txt                            FAST-LIO2 /Odometry, TUM, same stamps
    (or ROOT/raw_data/ouster00/points/... raw Ouster clouds, frame ouster00, with ROOT/odometry.txt)

or, without an export, the download's bag itself (load_fusionportable_bag): ROOT/<sequence>.bag (else the ROOT/*.bag),
the Ouster's raw sweeps on LIDAR_TOPICS (frame ouster00) with per-point times and no poses (load_sequence makes them);

and the dataset's ground truth, found beside or up to three folders above ROOT (the download's layout,
fusionportable.github.io/dataset/fusionportable, "Data Organization"):

    groundtruth/traj/<sequence>.txt                  TUM, <sequence> = ROOT's folder name
    groundtruth/map/<sequence>/merged_scan.pcd       TLS map (1 cm), in the ground truth's world frame

Also read: ROOT/scans/<timestamp>.pcd with ROOT/fastlio2_poses.txt (or poses.txt, odometry.txt) and
ROOT/gt_poses.txt (or traj/gt_poses.txt, ground_truth.txt, traj/ground_truth.txt), ground truth in the scan frame
unless gt_from_scan says otherwise.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from neld_jax.data import ground_truth
from neld_jax.data.bags import raw_bags
from neld_jax.data.layout import (
    LoadOptions,
    check_root,
    config_root,
    list_scans,
    load_options,
    sorted_by_name,
    timestamp_from_name,
    timestamped_sequence,
)
from neld_jax.data.sequence import Sequence
from neld_jax.data.timing import read_times
from neld_jax.errors import DataError

POSE_FILES = ("fastlio2_poses.txt", "poses.txt", "odometry.txt")
GT_FILES = ("gt_poses.txt", "traj/gt_poses.txt", "ground_truth.txt", "traj/ground_truth.txt")
# The devkit's exports (fusionportable_dataset_tools, src/data_loader/ros_msg/pointcloud.py and odometry.py, driven
# by src/write_alg_bag_to_data.ipynb and src/write_bag_to_data.ipynb): (scan folder, frame of its clouds).
# algorithm_result/ holds FAST-LIO2's /cloud_registered_body (frame body_imu, src/cfg/algorithm/cfg_fastlio2.py).
DEVKIT_SCANS = (("algorithm_result/ouster00_undistort/points", "body_imu"), ("raw_data/ouster00/points", "ouster00"))
DEVKIT_ODOMETRY = ("algorithm_result/odometry/odometry.txt", "odometry.txt")
# The Ouster's clouds in the downloaded bag <sequence>.bag: topic and frame from the devkit's topic table for the
# handheld sequences (fusionportable_dataset_tools, cfg/dataset/cfg_handheld.py, 'ouster_points'). The second topic
# is the frame's own name, read when a bag has it instead (not seen in the devkit).
LIDAR_TOPICS = ("/os_cloud_node/points", "/ouster00/points")
LIDAR_FRAME = "ouster00"


def load_fusionportable(root: str | os.PathLike, options: LoadOptions = LoadOptions()) -> Sequence:
    """Load a FusionPortable sequence from ROOT in any of the layouts of the module docstring, with the
    ground-truth and matching settings of options (layout.LoadOptions; drop_unmatched_tail is not read).

    options.gt_poses_file / gt_map_file (config data.gt_poses_path / gt_map_path) override the search. Ground-truth
    poses are moved into the scans' frame by options.gt_from_scan (T_G_S [4, 4]; None: the published extrinsic for
    the scan frame, ground_truth.PUBLISHED_GT_FROM_SCAN; options.scan_frame overrides the frame the folder implies).
    Odometry and ground truth are matched to the scans by nearest stamp within options.tol seconds (after adding
    options.gt_time_offset_s to the scan stamps for the ground truth); a scan without one is a DataError naming
    it."""
    root = check_root(root)
    if (root / "scans").is_dir():
        scan_folder = root / "scans"
        files = sorted_by_name(list_scans(scan_folder))
        scan_times = _timestamps_from_names(files, scan_folder, "<timestamp>.pcd")
        return timestamped_sequence(root, files, scan_times, POSE_FILES, GT_FILES, options)

    found = next(((root / folder, frame) for folder, frame in DEVKIT_SCANS if (root / folder / "data").is_dir()), None)
    if found is None:
        bags = raw_bags.bags_in(root, f"{root.name}.bag")
        if bags:
            return load_fusionportable_bag(root, bags, options)
        looked = ", ".join(f"{folder}/data/" for folder, _ in DEVKIT_SCANS)
        raise DataError(
            f"{root}: no FusionPortable scans (looked for scans/, the devkit's {looked} and the "
            f"download's {root.name}.bag or any *.bag)"
        )
    points_folder, frame = found
    files, scan_times = _devkit_scans(points_folder)
    resolved = _download_ground_truth(root, options, frame)
    return timestamped_sequence(root, files, scan_times, DEVKIT_ODOMETRY, (), resolved)


def load_fusionportable_bag(root: Path, bags: list[Path], options: LoadOptions = LoadOptions()) -> Sequence:
    """The download's bag(s) as raw sweeps (raw_bags): the first of LIDAR_TOPICS the bag has, poses None,
    per-point times, files "<sequence>.bag:<topic>#000123". Ground truth as for the devkit's raw ouster00 clouds
    (options: layout.LoadOptions, as load_fusionportable reads them): options.gt_poses_file, else
    groundtruth/traj/<sequence>.txt (in or above ROOT), matched to the scan stamps within options.tol, moved into
    the scan frame by options.gt_from_scan (None: the published extrinsic of options.scan_frame, default
    ouster00)."""
    topic = raw_bags.pick_topic(bags, LIDAR_TOPICS)
    sweeps = raw_bags.read_lidar_bag(bags, topic)
    return raw_bags.sweeps_sequence(root, sweeps, _download_ground_truth(root, options, LIDAR_FRAME))


def _devkit_scans(points_folder: Path) -> tuple[list[Path], np.ndarray]:
    """The devkit's export of one cloud topic: its scans (points_folder/data/, by name) and their stamps [S]
    (points_folder/timestamps.txt, one per cloud in order); DataError when the counts differ."""
    files = sorted_by_name(list_scans(points_folder / "data"))
    scan_times = read_times(points_folder / "timestamps.txt")
    if len(scan_times) != len(files):
        raise DataError(
            f"{points_folder / 'timestamps.txt'} has {len(scan_times)} stamps but {points_folder / 'data'} "
            f"has {len(files)} scans (the devkit writes one stamp per cloud, in order)"
        )
    return files, scan_times


def _download_ground_truth(root: Path, options: LoadOptions, frame: str) -> LoadOptions:
    """options with the ground truth of sequence ROOT resolved: the trajectory and map files given, else the
    download's groundtruth/traj/<sequence>.txt and groundtruth/map/<sequence>/merged_scan.pcd in or above ROOT
    (None: none), and gt_from_scan given, else the published extrinsic of options.scan_frame or else `frame`, the
    frame of the clouds read."""
    name = root.name
    gt_from_scan = options.gt_from_scan
    if gt_from_scan is None:
        gt_from_scan = ground_truth.published_offset("fusionportable", options.scan_frame or frame)
    return dataclasses.replace(
        options,
        gt_poses_file=options.gt_poses_file or ground_truth.first_upwards(root, f"groundtruth/traj/{name}.txt"),
        gt_map_file=options.gt_map_file or ground_truth.first_upwards(root, f"groundtruth/map/{name}/merged_scan.pcd"),
        gt_from_scan=gt_from_scan,
    )


def _timestamps_from_names(files: list[Path], folder: Path, pattern: str) -> np.ndarray:
    """The stamps [S] that the scan names encode (layout.timestamp_from_name); DataError naming the first that
    does not."""
    times = [timestamp_from_name(f) for f in files]
    bad = [f.name for f, t in zip(files, times) if t is None]
    if bad:
        raise DataError(f"{folder}: scan names must be timestamps ({pattern}); not a timestamp: {bad[0]}")
    return np.asarray(times, dtype=np.float64)


def load(data_cfg) -> Sequence:
    """data.format = 'fusionportable': load_fusionportable(data.root) with layout.load_options (data.timestamp_tol_s,
    the explicit ground-truth paths, gt_from_scan, scan_frame, gt_time_offset_s)."""
    return load_fusionportable(config_root(data_cfg, "fusionportable"), load_options(data_cfg))
