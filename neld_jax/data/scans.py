"""Reading and writing single LiDAR scans (point clouds in the sensor frame).

Supported formats, chosen by file extension:
  .pcd / .ply  Open3D point-cloud I/O, float32 or float64 positions (write_scan: .pcd float32, .ply float64)
  .bin         KITTI velodyne layout: float32 records (x, y, z, intensity)
  .npy         numpy array [N, 3] or [N, >=3] (first three columns are x, y, z)

Every reader returns `points: [N, 3] float64` with non-finite points removed (and counted in the log).
Bad input raises `DataError` with a message that names the file.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import open3d as o3d

from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

SCAN_EXTENSIONS = (".pcd", ".ply", ".bin", ".npy")


def _extension(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in SCAN_EXTENSIONS:
        raise DataError(
            f"{path}: unknown scan file extension '{path.suffix}' (expected one of {', '.join(SCAN_EXTENSIONS)})"
        )
    return ext


def _read_open3d(path: Path) -> np.ndarray:
    # The tensor reader: the legacy one reads float64 (SIZE 8) PCD fields as zeros, and maps are float64.
    # Open3D does not raise on a corrupt file; it logs a warning and returns a cloud without positions.
    cloud = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    if "positions" not in cloud.point:
        raise DataError(f"{path}: no points could be read (unreadable or empty point cloud)")
    points = np.asarray(cloud.point.positions.numpy(), dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        raise DataError(f"{path}: no points could be read (unreadable or empty point cloud)")
    return points


def _read_kitti_bin(path: Path) -> np.ndarray:
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4 != 0:
        raise DataError(
            f"{path}: KITTI .bin size {raw.size * 4} bytes is not a multiple of 16 (float32 x, y, z, intensity)"
        )
    return raw.reshape(-1, 4)[:, :3].astype(np.float64)


def _read_npy(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DataError(f"{path}: unreadable .npy file ({exc})") from exc
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"{path}: expected an array of shape [N, 3] or [N, >=3], got {array.shape}")
    if not np.issubdtype(array.dtype, np.number):
        raise DataError(f"{path}: expected a numeric array, got dtype {array.dtype}")
    return np.asarray(array[:, :3], dtype=np.float64)


def read_scan(path: str | os.PathLike) -> np.ndarray:
    """Read one scan. Returns points: [N, 3] float64 (non-finite points dropped, with a warning)."""
    path = Path(path)
    ext = _extension(path)
    if not path.is_file():
        raise DataError(f"{path}: scan file does not exist")
    if path.stat().st_size == 0:
        raise DataError(f"{path}: scan file is empty (0 bytes)")
    if ext in (".pcd", ".ply"):
        points = _read_open3d(path)
    elif ext == ".bin":
        points = _read_kitti_bin(path)
    else:
        points = _read_npy(path)

    finite = np.isfinite(points).all(axis=1)
    num_dropped = int(points.shape[0] - finite.sum())
    if num_dropped:
        logger.warning("%s: dropped %d of %d points with NaN or infinite coordinates", path, num_dropped, len(points))
        points = points[finite]
    if points.shape[0] == 0:
        raise DataError(f"{path}: scan has no valid points (all {num_dropped} points were NaN or infinite)")
    return points


def write_scan(path: str | os.PathLike, points: np.ndarray) -> None:
    """Write points: [N, 3] to .pcd, .ply, .bin (KITTI, intensity 0) or .npy, chosen by extension."""
    path = Path(path)
    ext = _extension(path)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points to write must have shape [N, 3], got {points.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if ext in (".pcd", ".ply"):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if not o3d.io.write_point_cloud(str(path), cloud):
            raise DataError(f"{path}: Open3D could not write the point cloud")
    elif ext == ".bin":
        records = np.zeros((points.shape[0], 4), dtype=np.float32)
        records[:, :3] = points
        records.tofile(path)
    else:
        np.save(path, points)
