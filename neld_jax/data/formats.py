"""The registry of dataset formats and `load_sequence`, which turns config.data into a `Sequence`.

Each format is one module with a `load(data_cfg) -> Sequence` (config.data.format names it):

    generic         generic.py         ROOT/scans/ + poses.txt (+ gt_poses.txt, gt_map.pcd|ply)
    fusionportable  fusionportable.py  the devkit's export of a FAST-LIO2 run, with the download's ground truth
    newer_college   newer_college.py   2021 (imported clouds + gt CSV) or 2020 (cloud_<sec>_<nsec>.pcd)
    lio_keyframes   lio_keyframes.py   Scans/ + KITTI poses + times.txt, as LiDAR-inertial front-ends save them
    hba             hba.py             HBA's input: pcd/<i>.pcd + pose.json
    kitti           kitti.py           KITTI odometry: sequences/NN/velodyne/*.bin + times.txt + calib.txt, poses/NN.txt
    synthetic       synthetic.py       a seeded synthetic sequence with exact ground truth (no files)

load_sequence adds what every folder format gets: the scan and pose frames converted or checked (frames.py), and a
warning naming what was looked for when no ground truth is found. Scans without poses get KISS-ICP's (odometry.py),
registered within the sensor's own range measured on the scans, the scans kept within the field's crop afterwards.
Those of a layout that may hold raw sweeps (RAW_SWEEP_FORMATS) and carry no per-point times are measured first: raw
sweeps get times from their azimuths, so that KISS-ICP and the trajectory deskew them, and deskewed scans are
registered as they are (sweep_times.py; data.deskew overrides, in any layout).
"""

from __future__ import annotations

import copy
import dataclasses
import logging

from neld_jax.data import (
    frames,
    fusionportable,
    generic,
    ground_truth,
    hba,
    kitti,
    lio_keyframes,
    newer_college,
    odometry,
    sweep_times,
    synthetic,
)
from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError

logger = logging.getLogger(__name__)

KISS_ICP = "kiss_icp"  # data.initial_poses: make them from the scans (odometry.py)

FORMATS = {
    "generic": generic.load,
    "fusionportable": fusionportable.load,
    "newer_college": newer_college.load,
    "lio_keyframes": lio_keyframes.load,
    "hba": hba.load,
    "kitti": kitti.load,
    "synthetic": synthetic.load,
}
# Layouts whose scans may be raw sweeps with no time field, which the data decides (sweep_times.py): the generic
# folder (a driver's PCD export, a LiDAR-inertial odometry's deskewed scans). KITTI's odometry scans are compensated
# for the motion already (kitti.py); keyframe layouts hold deskewed scans.
RAW_SWEEP_FORMATS = ("generic",)

# Where each folder format looks for ground truth by itself (for the "evaluation is skipped" warning).
GT_SEARCHED = {
    "generic": ("ROOT/gt_poses.txt", "ROOT/gt_map.pcd|ply"),
    "fusionportable": ("groundtruth/traj/<sequence>.txt in or above ROOT (or ROOT/gt_poses.txt)",
                       "groundtruth/map/<sequence>/merged_scan.pcd in or above ROOT (or ROOT/gt_map.pcd|ply)"),
    "newer_college": ("ROOT/gt-nc-*.csv, gt_state_*.csv or registered_poses.csv", "ROOT/gt_map.pcd|ply"),
    "lio_keyframes": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
    "hba": ("nothing (the layout has no ground truth)", "ROOT/gt_map.pcd|ply"),
    "kitti": ("../../poses/<NN>.txt or ROOT/poses.txt (KITTI 3x4, camera 0)", "ROOT/gt_map.pcd|ply"),
}


def load_sequence(data_cfg) -> Sequence:
    """Load the sequence that data_cfg (ml_collections.ConfigDict) names.

    Reads data_cfg.format (one of FORMATS), data_cfg.root (folder formats) and data_cfg.synthetic (for
    'synthetic'); an optional data_cfg.timestamp_tol_s overrides the 0.05 s matching tolerance.
    Ground truth: data_cfg.gt_poses_path / gt_map_path, when set, replace what the layout has (a path that is set
    but missing is a DataError naming it); data_cfg.gt_from_scan (7 numbers, T_G_S) replaces the published frame
    offset, data_cfg.scan_frame picks which published offset (neld_jax/data/ground_truth.py), data_cfg.gt_time_offset_s
    shifts the scan stamps when matching ground truth (another stamping convention); layout.load_options reads
    them for every folder format. When no ground-truth trajectory is found the log says so, what was looked for,
    and that pose evaluation is skipped. Preprocessing is left to the caller (see preprocess.preprocess)."""
    fmt = str(data_cfg.format).lower()
    if fmt not in FORMATS:
        raise ConfigError(f"data.format: unknown format '{data_cfg.format}' (expected one of {', '.join(FORMATS)})")
    make_poses = str(data_cfg.get("initial_poses", "")) == KISS_ICP
    if make_poses:  # the layout reads its scans as usual; its own poses file, if any, is not the start
        data_cfg = copy.deepcopy(data_cfg)
        data_cfg.initial_poses = ""
    seq = FORMATS[fmt](data_cfg)
    root = data_cfg.get("root", None)
    if seq.poses is None or make_poses:  # the scans are all there is: odometry from them, in the sensor frame
        if data_cfg.get("scans_in_world_frame", False) or data_cfg.get("invert_poses", False):
            raise ConfigError(f"{root}: data.scans_in_world_frame / data.invert_poses need the layout's own poses, "
                              f"not data.initial_poses={KISS_ICP} or none")
        seq = _with_odometry(seq, data_cfg, fmt)
        return seq if fmt == "synthetic" else _report_missing_ground_truth(seq, data_cfg, fmt, root)
    if fmt == "synthetic":  # generated in the sensor frame with exact ground truth: nothing to convert or report
        return seq
    if seq.point_times is not None:
        logger.info("%s: the scans carry per-point times; the given poses are used as they are, without deskewing "
                    "(data.initial_poses=%s deskews them with KISS-ICP's odometry)", root, KISS_ICP)
        seq = dataclasses.replace(seq, point_times=None)
    # Poses sensor -> world and scans in the sensor frame: converted when the config says so, else checked (and
    # refused with a line naming the option when they look the other way).
    invert = bool(data_cfg.get("invert_poses", False))
    seq = frames.inverted_poses(seq, str(root)) if invert else seq
    seq = frames.in_sensor_frame(seq, str(root), bool(data_cfg.get("scans_in_world_frame", False)))
    if not invert:
        frames.check_pose_direction(seq, str(root))
    return _report_missing_ground_truth(seq, data_cfg, fmt, root)


def _with_odometry(seq: Sequence, data_cfg, fmt: str) -> Sequence:
    """seq with KISS-ICP's poses, registered within the sensor's range, measured (odometry.registration_range_m);
    scans without per-point times are raw sweeps or deskewed as data.deskew says ("auto": measured, in the layouts
    of RAW_SWEEP_FORMATS; the others' scans are deskewed by what the layout is)."""
    range_m = odometry.registration_range_m(seq)
    deskew = str(data_cfg.get("deskew", sweep_times.AUTO)).lower()
    period = None
    if seq.point_times is None and (fmt in RAW_SWEEP_FORMATS or deskew != sweep_times.AUTO):
        seq = sweep_times.with_azimuth_times(seq, deskew, range_m)
        period = sweep_times.DEFAULT_PERIOD_S if seq.point_times is not None else None  # used without stamps
    return odometry.with_kiss_icp_poses(seq, data_cfg.min_range_m, data_cfg.max_range_m,
                                        odometry_range_m=range_m, unstamped_period_s=period)


def _report_missing_ground_truth(seq: Sequence, data_cfg, fmt: str, root) -> Sequence:
    """seq, after a warning for each kind of ground truth it lacks (what was looked for, what is skipped)."""
    if seq.gt_poses is None:
        gt_poses_file = ground_truth.explicit_path(data_cfg, "gt_poses_path")
        looked = f"data.gt_poses_path {gt_poses_file}" if gt_poses_file else GT_SEARCHED[fmt][0]
        logger.warning("%s: no ground-truth trajectory (looked for %s; set data.gt_poses_path to give one): pose "
                       "errors (ATE/RPE) will not be evaluated", root, looked)
    if seq.gt_map is None:
        logger.warning("%s: no ground-truth map (looked for %s; set data.gt_map_path to give one): map errors will "
                       "not be evaluated", root, GT_SEARCHED[fmt][1])
    return seq
