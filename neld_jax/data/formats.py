"""The registry of folder formats and `read_sequence`, which reads the sequence config.data names.

Each format is one module with a `load(data_cfg) -> Sequence` (config.data.format names it):

    generic         generic.py         ROOT/scans/ + poses.txt (+ gt_poses.txt, gt_map.pcd|ply)
    fusionportable  fusionportable.py  the devkit's export of a FAST-LIO2 run, with the download's ground truth
    newer_college   newer_college.py   2021 (imported clouds + gt CSV) or 2020 (cloud_<sec>_<nsec>.pcd)
    lio_keyframes   lio_keyframes.py   Scans/ + KITTI poses + times.txt, as LiDAR-inertial front-ends save them
    hba             hba.py             HBA's input: pcd/<i>.pcd + pose.json
    kitti           kitti.py           KITTI odometry: sequences/NN/velodyne/*.bin + times.txt + calib.txt, poses/NN.txt

read_sequence adds what every folder format gets: the scan and pose frames converted or checked (frames.py);
`report_missing_ground_truth` a warning naming what was looked for when no ground truth is found. Scans without
poses are left to the front-end (neld_jax.frontend), which neld_jax.steps.inputs runs after reading; the synthetic
format is made, not read (neld_jax.synthetic).
"""

from __future__ import annotations

import copy
import dataclasses
import logging

from neld_jax.data import frames, fusionportable, generic, ground_truth, hba, kitti, lio_keyframes, newer_college
from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError

logger = logging.getLogger(__name__)

KISS_ICP = "kiss_icp"  # data.initial_poses: the front-end makes them from the scans (neld_jax.frontend)

FORMATS = {
    "generic": generic.load,
    "fusionportable": fusionportable.load,
    "newer_college": newer_college.load,
    "lio_keyframes": lio_keyframes.load,
    "hba": hba.load,
    "kitti": kitti.load,
}
# Layouts whose scans may be raw sweeps with no time field, which the front-end decides (neld_jax.frontend): the
# generic folder (a driver's PCD export, a LiDAR-inertial odometry's deskewed scans). KITTI's odometry scans are
# compensated for the motion already (kitti.py); keyframe layouts hold deskewed scans.
RAW_SWEEP_FORMATS = ("generic",)

# Where each folder format looks for ground truth by itself (for the "evaluation is skipped" warning).
GT_SEARCHED = {
    "generic": ("ROOT/gt_poses.txt", "ROOT/gt_map.pcd|ply"),
    "fusionportable": (
        "groundtruth/traj/<sequence>.txt in or above ROOT (or ROOT/gt_poses.txt)",
        "groundtruth/map/<sequence>/merged_scan.pcd in or above ROOT (or ROOT/gt_map.pcd|ply)",
    ),
    "newer_college": ("ROOT/gt-nc-*.csv, gt_state_*.csv or registered_poses.csv", "ROOT/gt_map.pcd|ply"),
    "lio_keyframes": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
    "hba": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
    "kitti": ("../../poses/<NN>.txt or ROOT/poses.txt (KITTI 3x4, camera 0)", "ROOT/gt_map.pcd|ply"),
}


def read_sequence(data_cfg) -> Sequence:
    """Read the folder sequence that data_cfg (ml_collections.ConfigDict) names, and nothing else: no
    registration, no generated scans (those are neld_jax.steps.inputs's).

    Reads data_cfg.format (one of FORMATS) and data_cfg.root; an optional data_cfg.timestamp_tol_s overrides the
    0.05 s matching tolerance. Ground truth: data_cfg.gt_poses_path / gt_map_path, when set, replace what the
    layout has (a path that is set but missing is a DataError naming it); data_cfg.gt_from_scan (7 numbers, T_G_S)
    replaces the published frame offset, data_cfg.scan_frame picks which published offset
    (neld_jax/data/ground_truth.py), data_cfg.gt_time_offset_s shifts the scan stamps when matching ground truth
    (another stamping convention); layout.load_options reads them for every folder format.
    Returns the sequence with poses None when the front-end is to make them (the layout has none, or
    data.initial_poses = KISS_ICP); given poses come converted or checked (frames.py)."""
    fmt = str(data_cfg.format).lower()
    if fmt not in FORMATS:
        raise ConfigError(f"data.format: unknown format '{data_cfg.format}' (expected one of {', '.join(FORMATS)})")
    make_poses = wants_odometry(data_cfg)
    if make_poses:  # the layout reads its scans as usual; its own poses file, if any, is not the start
        data_cfg = copy.deepcopy(data_cfg)
        data_cfg.initial_poses = ""
    seq = FORMATS[fmt](data_cfg)
    root = data_cfg.get("root", None)
    if seq.poses is None or make_poses:  # the scans are all there is: the front-end makes the poses
        if data_cfg.get("scans_in_world_frame", False) or data_cfg.get("invert_poses", False):
            raise ConfigError(
                f"{root}: data.scans_in_world_frame / data.invert_poses need the layout's own poses, "
                f"not data.initial_poses={KISS_ICP} or none"
            )
        return dataclasses.replace(seq, poses=None)
    if seq.point_times is not None:
        logger.info(
            "%s: the scans carry per-point times; the given poses are used as they are, without deskewing "
            "(data.initial_poses=%s deskews them with KISS-ICP's odometry)",
            root,
            KISS_ICP,
        )
        seq = dataclasses.replace(seq, point_times=None)
    # Poses sensor -> world and scans in the sensor frame: converted when the config says so, else checked (and
    # refused with a line naming the option when they look the other way).
    invert = bool(data_cfg.get("invert_poses", False))
    seq = frames.inverted_poses(seq, str(root)) if invert else seq
    seq = frames.in_sensor_frame(seq, str(root), bool(data_cfg.get("scans_in_world_frame", False)))
    if not invert:
        frames.check_pose_direction(seq, str(root))
    return seq


def wants_odometry(data_cfg) -> bool:
    """Whether the config asks for poses made from the scans even where the layout has its own."""
    return str(data_cfg.get("initial_poses", "")) == KISS_ICP


def report_missing_ground_truth(seq: Sequence, data_cfg) -> Sequence:
    """seq, after a warning for each kind of ground truth it lacks (what was looked for, what is skipped)."""
    fmt, root = str(data_cfg.format).lower(), data_cfg.get("root", None)
    if seq.gt_poses is None:
        gt_poses_file = ground_truth.explicit_path(data_cfg, "gt_poses_path")
        looked = f"data.gt_poses_path {gt_poses_file}" if gt_poses_file else GT_SEARCHED[fmt][0]
        logger.warning(
            "%s: no ground-truth trajectory (looked for %s; set data.gt_poses_path to give one): pose "
            "errors (ATE/RPE) will not be evaluated",
            root,
            looked,
        )
    if seq.gt_map is None:
        logger.warning(
            "%s: no ground-truth map (looked for %s; set data.gt_map_path to give one): map errors will "
            "not be evaluated",
            root,
            GT_SEARCHED[fmt][1],
        )
    return seq
