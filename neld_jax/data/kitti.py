"""The KITTI odometry benchmark's LiDAR sequences as downloaded (www.cvlibs.net/datasets/kitti/eval_odometry.php):

    .../dataset/sequences/NN/velodyne/000000.bin ...   float32 records (x, y, z, reflectance), Velodyne HDL-64E frame
    .../dataset/sequences/NN/times.txt                  one stamp per scan, seconds from the sequence's start
    .../dataset/sequences/NN/calib.txt                  P0..P3 and Tr (velodyne -> camera 0), 12 numbers each
    .../dataset/poses/NN.txt                            ground truth (sequences 00-10): camera 0 in the first camera-0
                                                        frame, KITTI 3x4 rows; SemanticKITTI's sequences/NN/poses.txt
                                                        is read where that is missing

ROOT is sequences/NN. The layout has no odometry: the initial poses are made from the scans with KISS-ICP
(load_sequence). The ground truth is moved into the LiDAR's frame, T_lidar = Tr^-1 @ T_cam @ Tr, the first pose at
the identity as the camera's is.

The scans are rigid: the odometry benchmark's readme says its Velodyne scans are compensated for the car's motion
during the sweep (unlike the raw recordings), so they get no per-point times and KISS-ICP does not deskew them, as
its own KITTI odometry loader does not. Each point's elevation is raised by VERTICAL_ANGLE_OFFSET_DEG, the HDL-64E's
intrinsic calibration error that KISS-ICP corrects in its KITTI loader (the same rotation, written here).
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
    with_explicit_ground_truth,
)
from neld_jax.data.poses import read_kitti
from neld_jax.data.scan_source import lazy
from neld_jax.data.sequence import Sequence
from neld_jax.data.timing import read_times
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

VERTICAL_ANGLE_OFFSET_DEG = 0.205  # the HDL-64E's elevations in KITTI are this much too low (KISS-ICP's correction)
CALIB_TR = "Tr"  # velodyne -> camera 0, row-major 3x4


def corrected_elevations(points: np.ndarray, offset_deg: float = VERTICAL_ANGLE_OFFSET_DEG) -> np.ndarray:
    """points [N, 3] with each one's elevation raised by offset_deg, its range and azimuth kept: [N, 3]. Points on
    the vertical axis (no azimuth) are kept as they are."""
    horizontal = np.hypot(points[:, 0], points[:, 1])
    distance = np.linalg.norm(points, axis=1)
    elevation = np.arctan2(points[:, 2], horizontal) + np.deg2rad(offset_deg)
    on_axis = horizontal == 0.0
    scale = np.where(on_axis, 1.0, distance * np.cos(elevation) / np.where(on_axis, 1.0, horizontal))
    corrected = points * scale[:, None]
    corrected[:, 2] = np.where(on_axis, points[:, 2], distance * np.sin(elevation))
    return corrected


def read_calibration(path: Path) -> np.ndarray:
    """calib.txt -> Tr [4, 4] (velodyne -> camera 0). DataError naming the file for a missing file, a line that is
    not '<key>: <numbers>', or a Tr that is not 12 numbers with a rotation block."""
    if not path.is_file():
        raise DataError(f"{path}: calibration file does not exist (KITTI: 'Tr:' velodyne -> camera 0, 12 numbers)")
    rows = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, colon, values = line.partition(":")
        if not colon:
            raise DataError(f"{path}, line {number}: expected '<key>: <numbers>', got {line.strip()[:40]!r}")
        rows[key.strip()] = (number, values.split())
    if CALIB_TR not in rows:
        raise DataError(f"{path}: no '{CALIB_TR}:' line (velodyne -> camera 0, 12 numbers); keys: {', '.join(rows)}")
    number, fields = rows[CALIB_TR]
    try:
        values = np.array([float(v) for v in fields], dtype=np.float64)
    except ValueError:
        values = np.zeros(0)
    if values.size != 12 or not np.all(np.isfinite(values)):
        raise DataError(
            f"{path}, line {number}: '{CALIB_TR}:' must hold 12 finite numbers (row-major 3x4 velodyne -> "
            f"camera 0), got {' '.join(fields)[:60]!r}"
        )
    transform = np.eye(4)
    transform[:3, :4] = values.reshape(3, 4)
    rotation = transform[:3, :3]
    if not (np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) and np.linalg.det(rotation) > 0):
        raise DataError(f"{path}, line {number}: the rotation block of '{CALIB_TR}:' is not a rotation")
    return transform


def camera_to_lidar(camera_poses: np.ndarray, velodyne_to_camera: np.ndarray) -> np.ndarray:
    """KITTI ground truth (camera 0's poses [S, 4, 4] in the first camera-0 frame) -> the LiDAR's poses [S, 4, 4] in
    the first LiDAR frame: Tr^-1 @ T_cam @ Tr, Tr = velodyne_to_camera [4, 4]."""
    return np.linalg.inv(velodyne_to_camera) @ camera_poses @ velodyne_to_camera


def _scan_files(root: Path) -> list[Path]:
    """The velodyne/ scans in name order (a .bin that is not whole 16-byte records is a DataError when read:
    scans.read_scan); DataError for a missing folder."""
    velodyne = root / "velodyne"
    if not velodyne.is_dir():
        raise DataError(
            f"{root}: no velodyne/ folder (KITTI odometry: ROOT = sequences/NN with velodyne/NNNNNN.bin, "
            "times.txt, calib.txt)"
        )
    return sorted_by_name(list_scans(velodyne))


def _ground_truth_file(root: Path) -> Path | None:
    """The benchmark's poses/NN.txt two folders above ROOT, else SemanticKITTI's ROOT/poses.txt, else None."""
    for path in (root.parent.parent / "poses" / f"{root.name}.txt", root / "poses.txt"):
        if path.is_file():
            return path
    return None


def load_kitti(root: str | os.PathLike, options: LoadOptions = LoadOptions()) -> Sequence:
    """Load sequences/NN as this module's docstring describes: poses None, stamps from times.txt, ground truth in
    the LiDAR frame where poses/NN.txt exists (its count must match the scans', by order). DataErrors name the file:
    no velodyne/ folder, a .bin that is not whole 16-byte records, times.txt with another count than the scans, a
    calib.txt without a valid Tr (needed only with ground truth). options (layout.LoadOptions): gt_poses_file /
    gt_map_file, when set, replace the layout's ground truth (layout.with_explicit_ground_truth, with tol,
    gt_from_scan and gt_time_offset_s); drop_unmatched_tail and scan_frame are not read."""
    root = check_root(root)
    files = _scan_files(root)
    times = read_times(root / "times.txt")
    if len(times) != len(files):
        raise DataError(
            f"{root / 'times.txt'} has {len(times)} stamps but {root / 'velodyne'} has {len(files)} scans "
            "(one stamp per scan, in order)"
        )
    gt_file = _ground_truth_file(root)
    gt_poses = None
    if gt_file is not None:
        velodyne_to_camera = read_calibration(root / "calib.txt")
        camera_poses = align_poses(read_kitti(gt_file), None, gt_file, files, root=root).poses
        gt_poses = camera_to_lidar(camera_poses, velodyne_to_camera)
        logger.info("%s: ground truth from %s, moved into the LiDAR frame with calib.txt's Tr", root, gt_file)
    seq = build_sequence(root, files, None, times, gt_poses, "no poses", options.gt_map_file)
    seq = dataclasses.replace(seq, scans=lazy(seq.scans).map(lambda _, scan: corrected_elevations(scan)))
    return with_explicit_ground_truth(seq, root, options)


def load(data_cfg) -> Sequence:
    """data.format = 'kitti': load_kitti(data.root) with layout.load_options (data.gt_poses_path / gt_map_path ...)."""
    return load_kitti(config_root(data_cfg, "kitti"), load_options(data_cfg))
