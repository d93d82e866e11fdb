"""Reading and writing single LiDAR scans (point clouds in the sensor frame).

Supported formats, chosen by file extension:
  .pcd / .ply  Open3D point-cloud I/O, float32 or float64 positions (write_scan: .pcd float32, .ply float64)
  .bin         KITTI velodyne layout: float32 records (x, y, z, intensity)
  .npy         numpy array [N, 3] or [N, >=3] (first three columns are x, y, z)

Every reader returns `points: [N, 3] float64` without the points that are no measurement: non-finite ones
(NaN/inf) and ones exactly at the origin (0, 0, 0), which many drivers and organised clouds (Ouster, ROS
bags) use for "no return". Each file's drops are logged with a count per reason: a warning naming the file
when there are non-finite points or when the scan loses more than half its points (MANY_DROPPED_FRACTION),
else at debug level (organised clouds lose some zeros in every scan; the loader logs one total).
Bad input raises `DataError` with a message that names the file; so does a file that holds no point
(0 bytes, a PCD/PLY whose header says 0 points, an empty array) or only points that are no measurement.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

SCAN_EXTENSIONS = (".pcd", ".ply", ".bin", ".npy")
# A scan that loses more than this fraction to NaN/inf/(0,0,0) is worth a warning with its name.
MANY_DROPPED_FRACTION = 0.5


def _extension(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in SCAN_EXTENSIONS:
        raise DataError(
            f"{path}: unknown scan file extension '{path.suffix}' (expected one of {', '.join(SCAN_EXTENSIONS)})"
        )
    return ext


def _header_point_count(path: Path, ext: str) -> int | None:
    """The point count a PCD ('POINTS n') or PLY ('element vertex n') header states, else None."""
    key = b"POINTS" if ext == ".pcd" else b"element vertex"
    end = b"DATA" if ext == ".pcd" else b"end_header"
    with open(path, "rb") as f:
        for _ in range(64):  # headers are a dozen lines; stop early on binary junk
            line = f.readline()
            if not line:
                break
            if line.startswith(key):
                try:
                    return int(line[len(key) :].split()[0])
                except (ValueError, IndexError):
                    return None
            if line.startswith(end):
                break
    return None


def _read_open3d(path: Path, ext: str) -> np.ndarray:
    import open3d as o3d  # only where a cloud is read: the training step's imports stay without it

    # Open3D cannot tell "0 points" from "unreadable" (it fails on a PCD header with POINTS 0), so ask
    # the header first for a clearer message.
    if _header_point_count(path, ext) == 0:
        raise DataError(f"{path}: scan file holds 0 points (its header says so)")
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
    size = path.stat().st_size  # the file's, not what fromfile reads: it drops a trailing partial float unsaid
    if size % 16 != 0:
        raise DataError(f"{path}: KITTI .bin size {size} bytes is not a multiple of 16 (float32 x, y, z, intensity)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)


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
    """Read one scan. Returns points: [N, 3] float64 without NaN/inf and (0, 0, 0) points (counts logged)."""
    return _read_scan(Path(path))[0]


def read_scan_counted(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, int]]:
    """read_scan that also returns what was dropped: counts {'read', 'non-finite', 'zero', 'total'}."""
    return _read_scan(Path(path))


def _read_scan(path: Path) -> tuple[np.ndarray, dict[str, int]]:
    ext = _extension(path)
    if not path.is_file():
        raise DataError(f"{path}: scan file does not exist")
    if path.stat().st_size == 0:
        raise DataError(f"{path}: scan file is empty (0 bytes)")
    if ext in (".pcd", ".ply"):
        points = _read_open3d(path, ext)
    elif ext == ".bin":
        points = _read_kitti_bin(path)
    else:
        points = _read_npy(path)

    if points.shape[0] == 0:
        raise DataError(f"{path}: scan file holds 0 points")
    points, dropped = drop_invalid_points(points)
    if dropped["total"]:
        many = dropped["total"] > MANY_DROPPED_FRACTION * dropped["read"]
        level = logging.WARNING if dropped["non-finite"] or many else logging.DEBUG
        logger.log(
            level,
            "%s: dropped %d of %d points (%d with NaN or infinite coordinates, %d at (0, 0, 0): no return)",
            path,
            dropped["total"],
            dropped["read"],
            dropped["non-finite"],
            dropped["zero"],
        )
    if points.shape[0] == 0:
        raise DataError(
            f"{path}: scan has no valid points (all {dropped['read']} points were NaN or infinite "
            f"({dropped['non-finite']}) or at (0, 0, 0) ({dropped['zero']}), i.e. no return)"
        )
    return points, dropped


def valid_points(points: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """points: [N, 3] -> (keep [N] bool: finite and not exactly (0, 0, 0), counts as drop_invalid_points gives).

    For callers that must drop something else with the points (e.g. per-point times)."""
    finite = np.isfinite(points).all(axis=1)
    zero = finite & ~points.any(axis=1)  # exactly (0, 0, 0): the "no return" encoding
    keep = finite & ~zero
    counts = {"read": int(points.shape[0]), "non-finite": int((~finite).sum()), "zero": int(zero.sum())}
    counts["total"] = counts["non-finite"] + counts["zero"]
    return keep, counts


def drop_invalid_points(points: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """points: [N, 3] -> (points without NaN/inf rows and without exact (0, 0, 0) rows [N', 3], counts).

    counts: {'read': N, 'non-finite': ..., 'zero': ..., 'total': N - N'}."""
    keep, counts = valid_points(points)
    return (points if counts["total"] == 0 else points[keep]), counts


def write_scan(path: str | os.PathLike, points: np.ndarray) -> None:
    """Write points: [N, 3] to .pcd, .ply, .bin (KITTI, intensity 0) or .npy, chosen by extension."""
    path = Path(path)
    ext = _extension(path)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points to write must have shape [N, 3], got {points.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if ext in (".pcd", ".ply"):
        import open3d as o3d  # only where a cloud is written: the training step's imports stay without it

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if not o3d.io.write_point_cloud(str(path), cloud):
            raise DataError(f"{path}: Open3D could not write the point cloud")
    elif ext == ".bin":
        records = np.zeros((points.shape[0], 4), dtype=np.float32)
        records[:, :3] = points
        records.tofile(path)
    else:
        np.save(path, points)
