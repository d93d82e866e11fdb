"""Writing a run's outputs in the formats the field uses: TUM / KITTI poses, PLY / PCD maps, JSON reports.

Everything here writes files (creating parent folders) and raises
`DataError` naming the file when it cannot.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from neld_jax.data.poses import write_kitti, write_tum
from neld_jax.data.preprocess import voxel_downsample
from neld_jax.errors import DataError
from neld_jax.geometry import register_scans
from neld_jax.jsonable import to_jsonable  # noqa: F401  (re-exported: callers write JSON through export)
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)

POINT_CLOUD_EXTENSIONS = (".ply", ".pcd")


def write_poses(
    output_dir: str | os.PathLike, stem: str, timestamps: np.ndarray | None, poses: np.ndarray
) -> tuple[Path, Path]:
    """Write poses: [S, 4, 4] as `<output_dir>/<stem>.txt` (TUM) and `<stem>.kitti` (KITTI 3x4).

    timestamps: [S] seconds, or None for 0, 1, ..., S-1 (TUM needs a time column).
    Returns (tum_path, kitti_path).
    """
    output_dir = Path(output_dir)
    poses = np.asarray(poses, dtype=np.float64)
    if timestamps is None:
        timestamps = np.arange(len(poses), dtype=np.float64)
    tum_path, kitti_path = output_dir / f"{stem}.txt", output_dir / f"{stem}.kitti"
    write_tum(tum_path, timestamps, poses)
    write_kitti(kitti_path, poses)
    return tum_path, kitti_path


def write_keyframe_poses(
    output_dir: str | os.PathLike, stem: str, loaded, keyframes, T_keyframes: np.ndarray
) -> np.ndarray:
    """The keyframes' poses T_keyframes [K, 4, 4] carried to every input scan of `loaded` (the scans between
    keyframes take their keyframes' interpolated correction: trajectory.propagate_corrections) and written as
    `write_poses` does. loaded, keyframes: neld_jax.steps.inputs.load_keyframes's. Returns the poses [S, 4, 4]
    written."""
    T_all = propagate_corrections(loaded.poses, keyframes.loaded_index, T_keyframes, loaded.timestamps)
    write_poses(output_dir, stem, loaded.timestamps, T_all)
    return T_all


def write_point_cloud(path: str | os.PathLike, points: np.ndarray) -> Path:
    """Write points: [N, 3] as a float64 .ply (binary) or .pcd (binary) through Open3D. Returns path."""
    path = Path(path)
    if path.suffix.lower() not in POINT_CLOUD_EXTENSIONS:
        raise DataError(f"{path}: unsupported point-cloud extension '{path.suffix}' (use .ply or .pcd)")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points to write must have shape [N, 3], got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise DataError(
            f"{path}: refusing to write {int(np.sum(~np.isfinite(points).all(axis=1)))} NaN or infinite points"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    import open3d as o3d  # here: training imports this module on GPU images without open3d (docs/design.md)

    cloud = o3d.t.geometry.PointCloud()
    # float64: float32 spacing is 0.25 m at UTM-sized coordinates (4e6 m), and the map metrics read these files.
    cloud.point.positions = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float64))
    if not o3d.t.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise DataError(f"{path}: Open3D could not write the point cloud")
    return path


def write_raw_map(
    path: str | os.PathLike, scans: list[np.ndarray], poses: np.ndarray, voxel_size: float = 0.0
) -> np.ndarray:
    """Register scans (list of [N_i, 3]) with poses [S, 4, 4], optionally voxel-downsample, write.

    Returns the written points [K, 3].
    """
    points = voxel_downsample(register_scans(scans, poses), voxel_size)
    write_point_cloud(path, points)
    logger.info("wrote raw map %s (%d points, voxel %.3g m)", path, len(points), voxel_size)
    return points


def read_json(path: str | os.PathLike) -> dict[str, Any]:
    """Read a JSON object; a missing file is an empty dict."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def write_json(path: str | os.PathLike, obj: dict[str, Any], merge: bool = True) -> dict[str, Any]:
    """Write a JSON object (indented, keys in insertion order); returns what was written.

    merge=True keeps the top-level keys already in the file and replaces only the keys of `obj`,
    so the trainer and the evaluator can each own a section of metrics.json. The file is replaced
    atomically (write to a temporary file, then rename), so a killed run never leaves half a file.
    """
    path = Path(path)
    content = to_jsonable(obj)
    if merge:
        content = {**read_json(path), **content}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(content, indent=2, allow_nan=False) + "\n")
    os.replace(temporary, path)
    return content
