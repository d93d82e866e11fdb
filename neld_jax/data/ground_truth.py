"""Ground truth for a loaded sequence: explicit paths (config.data.gt_poses_path / gt_map_path), the frame offset
between the ground truth's body frame and the scans' frame, and the published offsets of the public datasets.

A ground-truth trajectory gives T_world_G(t) for ITS body frame G (a dataset's "base", a LiDAR, an IMU); the
scans are in frame S. The ground-truth pose of a scan is then

    T_world_S = T_world_G @ T_G_S            (T_G_S: "gt_from_scan", the pose of the scan frame in G)

`config.data.gt_from_scan` holds T_G_S as (tx, ty, tz, qx, qy, qz, qw); left empty, the format's published value
below is used (identity for formats whose ground truth is already in the scan frame). Only poses move: the
ground-truth MAP is in the ground-truth world frame whatever G is.

Published offsets (T_G_S, metres and unit quaternions), where they come from, and what is not verified:

- Newer College 2021 (multi-cam release, Ouster OS0-128): ground truth (gt-nc-quad-easy.csv style, and
  gt_state_*.csv for the maths sequences; columns sec, nsec, x, y, z, qx, qy, qz, qw) is in the device's base
  frame, not the LiDAR's. The values are those of the evalio project's loader (github.com/contagon/evalio,
  python/evalio/datasets/newer_college_2021.py: imu_T_lidar and imu_T_gt, both relative to the Ouster IMU):
  T_G_S = inv(imu_T_gt) @ imu_T_S. The dataset's own calibration page
  (ori-drs.github.io/newer-college-dataset/multi-cam/) was not reached to cross-check them.
    scan frame "os_sensor": raw /os_cloud_node/points clouds (evalio reads these as its lidar frame)
    scan frame "os_imu": the body frame of FAST-LIO2 run with the Ouster IMU and its extrinsic
    (/cloud_registered_body); FAST-LIO2's shipped config/ouster64.yaml (github.com/hku-mars/FAST_LIO) starts from
    an identity extrinsic instead, i.e. from "os_sensor", and estimates it online unless extrinsic_est_en is false
- Newer College 2020 (stereo-cam release, Ouster OS1-64): registered_poses.csv (sec, nsec, x, y, z, qx, qy, qz,
  qw); same source (evalio, newer_college_2020.py: imu_T_lidar, imu_T_gt). Which physical frame G is (a
  camera frame, by some accounts) is not stated in the sources reached; only the transform is.
- FusionPortable (2022 handheld sequences, e.g. 20220216_canteen_day): the paper says the ground truth of these
  sequences is the LiDAR's pose from NDT localisation in the prior map (Jiao et al., IROS 2022, Sec. IV-B,
  doc/paper_fusionportable_iros2022.pdf in github.com/fusionportable/fusionportable_dataset_tools), so G is
  taken to be the Ouster frame ouster00 (os_sensor); the trajectory file's own frame is not documented in the
  sources reached. The extrinsic is the dataset's calibration (github.com/fusionportable/calibration_files,
  20220209_calib/calib/ouster00.yaml: quaternion_sensor_body_imu (qw, qx, qy, qz) and
  translation_sensor_body_imu, "from the sensor (reference) to body_imu (target)", i.e. the pose of body_imu in
  the Ouster frame, the convention its os_imu entry confirms with `tf_echo os_sensor os_imu`).
    scan frame "body_imu": the devkit's export of FAST-LIO2's /cloud_registered_body (STIM300 IMU frame)
    scan frame "ouster00": raw Ouster clouds
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from neld_jax.data.poses import make_poses, read_newer_college_csv, read_tum
from neld_jax.errors import ConfigError, DataError
from neld_jax.geometry import invert_poses

logger = logging.getLogger(__name__)


def pose_from_tuple(values, what: str = "data.gt_from_scan") -> np.ndarray:
    """(tx, ty, tz, qx, qy, qz, qw) -> 4x4; ConfigError naming `what` for a wrong length or a quaternion norm
    off by more than 1e-3."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.shape != (7,) or not np.all(np.isfinite(values)):
        raise ConfigError(f"{what}: expected 7 numbers (tx, ty, tz, qx, qy, qz, qw), got {tuple(values.tolist())}")
    norm = np.linalg.norm(values[3:])
    if abs(norm - 1.0) > 1e-3:
        raise ConfigError(f"{what}: quaternion norm {norm:.6g} is not 1")
    return make_poses(values[None, :3], values[None, 3:] / norm)[0]


def _tq(tx, ty, tz, qx, qy, qz, qw) -> np.ndarray:
    return pose_from_tuple((tx, ty, tz, qx, qy, qz, qw), "published offset")


# evalio's values, relative to the Ouster IMU (module docstring).
_NC2021_IMU_T_LIDAR = _tq(0.013801, -0.012207, -0.01514, 0.0032925, -0.004627, -0.0024302, 0.99998)
_NC2021_IMU_T_GT = _tq(0.013642, -0.011607, -0.10583, 0.0032925, -0.004627, -0.0024302, 0.99998)
_NC2020_IMU_T_LIDAR = _tq(0.006252999883145094, -0.011775000020861626, 0.007644999772310257, 0.0, 0.0, 1.0, 0.0)
_NC2020_IMU_T_GT = _tq(0.035643, 0.089026, -0.021653, 0.0, 0.0, 0.38268, 0.92388)
# FusionPortable 20220209_calib/calib/ouster00.yaml: the pose of body_imu in the Ouster frame (qw first there).
_FP_OUSTER_T_BODY = _tq(-0.037354, 0.006824, -0.020190, 0.004028, -0.002505, 0.003725, 0.999982)

# (format or release, scan frame) -> T_G_S; the first frame listed per release is its default.
PUBLISHED_GT_FROM_SCAN = {
    ("newer_college_2021", "os_sensor"): invert_poses(_NC2021_IMU_T_GT) @ _NC2021_IMU_T_LIDAR,
    ("newer_college_2021", "os_imu"): invert_poses(_NC2021_IMU_T_GT),
    ("newer_college_2020", "os_sensor"): invert_poses(_NC2020_IMU_T_GT) @ _NC2020_IMU_T_LIDAR,
    ("newer_college_2020", "os_imu"): invert_poses(_NC2020_IMU_T_GT),
    ("fusionportable", "body_imu"): _FP_OUSTER_T_BODY,
    ("fusionportable", "ouster00"): np.eye(4),
}
# data.scan_frame's choices by data.format: the frames its releases publish (newer_college: both releases)
SCAN_FRAMES = {
    fmt: tuple(dict.fromkeys(frame for (release, frame) in PUBLISHED_GT_FROM_SCAN if release.startswith(fmt)))
    for fmt in ("fusionportable", "newer_college")
}


def published_offset(release: str, scan_frame: str = "") -> np.ndarray:
    """T_G_S for a release ('newer_college_2021', 'newer_college_2020', 'fusionportable') and scan frame
    ('' = the release's default frame); identity for releases not listed. ConfigError for an unknown frame."""
    frames = [frame for (name, frame) in PUBLISHED_GT_FROM_SCAN if name == release]
    if not frames:
        return np.eye(4)
    frame = scan_frame or frames[0]
    if frame not in frames:
        raise ConfigError(f"data.scan_frame: '{scan_frame}' is not a frame of {release} (one of {', '.join(frames)})")
    return PUBLISHED_GT_FROM_SCAN[(release, frame)].copy()


def read_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A ground-truth trajectory: Newer College CSV (.csv, sec,nsec,...) or TUM (anything else).

    Returns (timestamps [P], poses [P, 4, 4] of the ground truth's body frame)."""
    path = Path(path)
    return read_newer_college_csv(path) if path.suffix.lower() == ".csv" else read_tum(path)


def explicit_path(data_cfg, key: str) -> Path | None:
    """data_cfg[key] as a Path, or None when unset; DataError naming it when it is set but does not exist."""
    value = str(data_cfg.get(key, "") or "")
    if not value:
        return None
    path = Path(value).expanduser()
    if not path.is_file():
        raise DataError(f"{path}: data.{key} is set but the file does not exist")
    return path


def first_upwards(start: Path, relative: str, levels: int = 3) -> Path | None:
    """The first existing `relative` path under start or one of its `levels` parents (a dataset's groundtruth/
    folder sits beside its sensor_data/ tree), else None."""
    folder = start
    for _ in range(levels + 1):
        if (folder / relative).is_file():
            return folder / relative
        if folder.parent == folder:
            break
        folder = folder.parent
    return None
