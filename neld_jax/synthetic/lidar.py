"""The synthetic LiDAR: a spinning sensor's beams, scans and sweeps cast into the scene (Open3D ray casting), and
the ground-truth map: points uniform by area on the surfaces some pose saw, within the field of view and range and
unoccluded, so that the map covers what the scans observed without the gaps between beam rings."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

# Open3D and SciPy are imported in the functions that use them: config.py imports the synthetic package module,
# and the training path imports the config on machines without Open3D.
if TYPE_CHECKING:
    import open3d as o3d

MIN_RANGE_M = 0.5  # LiDAR minimum range, as in the paper's preprocessing
FOV_DEG = (-15.0, 15.0)  # the simulated LiDAR's vertical field of view: its lowest and highest beams
GT_MAP_VISIBILITY_TOLERANCE_M = 0.02


def spinning_lidar_directions(
    num_beams: int = 32, fov_up_deg: float = 15.0, fov_down_deg: float = -15.0, num_columns: int = 512
) -> np.ndarray:
    """Unit ray directions [num_beams * num_columns, 3] in the sensor frame (x forward, z up).

    Beam-major order: index b * num_columns + c is beam b (elevations evenly from fov_down to fov_up)
    at azimuth 2 pi c / num_columns."""
    elevation = np.deg2rad(np.linspace(fov_down_deg, fov_up_deg, num_beams))
    azimuth = 2.0 * np.pi * np.arange(num_columns) / num_columns
    elevation, azimuth = np.meshgrid(elevation, azimuth, indexing="ij")
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    )
    return directions.reshape(-1, 3)


def _cast(scene: o3d.t.geometry.RaycastingScene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """origins: [R, 3] or [3], directions: [R, 3] unit (world) -> first-hit distances [R] float64 (inf: miss)."""
    import open3d as o3d

    rays = np.empty((directions.shape[0], 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = directions
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)


def cast_scan(
    scene: o3d.t.geometry.RaycastingScene,
    pose: np.ndarray,
    directions: np.ndarray,
    max_range: float,
    range_noise_m: float,
    rng: np.random.Generator,
    min_range: float = MIN_RANGE_M,
) -> np.ndarray:
    """One LiDAR scan. pose: [4, 4] sensor -> world; directions: [R, 3] unit, sensor frame.

    Returns points [N, 3] in the sensor frame: hits with Gaussian range noise (sigma range_noise_m),
    keeping min_range <= range <= max_range (misses are dropped)."""
    ranges = _cast(scene, pose[:3, 3], directions @ pose[:3, :3].T)
    hit = np.isfinite(ranges)
    directions, ranges = directions[hit], ranges[hit]
    if range_noise_m > 0:
        ranges = ranges + rng.normal(0.0, range_noise_m, size=ranges.shape)
    keep = (ranges >= min_range) & (ranges <= max_range)
    return directions[keep] * ranges[keep, None]


def cast_sweep(
    scene: o3d.t.geometry.RaycastingScene,
    column_poses: np.ndarray,
    directions: np.ndarray,
    max_range: float,
    range_noise_m: float,
    rng: np.random.Generator,
    min_range: float = MIN_RANGE_M,
) -> tuple[np.ndarray, np.ndarray]:
    """One sweep of a moving spinning LiDAR: each column of beams fires from where the sensor is at its instant.

    column_poses: [C, 4, 4] sensor -> world at the C columns' instants; directions: [B * C, 3] unit, sensor frame,
    beam-major (spinning_lidar_directions). Returns (points [N, 3] each in the sensor frame AT ITS OWN INSTANT, as a
    LiDAR reports them: the motion during the sweep is in them; column [N] int64, which column each point is)."""
    num_columns = column_poses.shape[0]
    column = np.tile(np.arange(num_columns), directions.shape[0] // num_columns)
    rotations, origins = column_poses[column, :3, :3], column_poses[column, :3, 3]
    ranges = _cast(scene, origins, np.einsum("nij,nj->ni", rotations, directions))
    hit = np.isfinite(ranges)
    if range_noise_m > 0:
        ranges[hit] += rng.normal(0.0, range_noise_m, size=int(hit.sum()))
    keep = hit & (ranges >= min_range) & (ranges <= max_range)
    return directions[keep] * ranges[keep, None], column[keep]


def _sample_surface(vertices: np.ndarray, triangles: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """count points [count, 3] uniformly by area on the triangles [T, 3] of vertices [V, 3]."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    chosen = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0  # fold the unit square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = a[chosen], b[chosen], c[chosen]
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def _visible_from_any(
    scene: o3d.t.geometry.RaycastingScene,
    points: np.ndarray,
    poses: np.ndarray,
    fov_down_deg: float,
    fov_up_deg: float,
    max_range: float,
) -> np.ndarray:
    """points: [K, 3] on the surfaces -> mask [K]: seen from some pose within FOV and range, unoccluded."""
    visible = np.zeros(len(points), dtype=bool)
    sin_low, sin_high = np.sin(np.deg2rad([fov_down_deg - 0.5, fov_up_deg + 0.5]))
    for pose in poses:
        candidates = np.flatnonzero(~visible)
        offsets = points[candidates] - pose[:3, 3]
        distances = np.linalg.norm(offsets, axis=1)
        directions = offsets / np.maximum(distances, 1e-12)[:, None]
        sin_elevation = directions @ pose[:3, 2]  # z axis of the sensor in the world
        in_view = (distances >= MIN_RANGE_M) & (distances <= max_range)
        in_view &= (sin_elevation >= sin_low) & (sin_elevation <= sin_high)
        candidates, distances, directions = candidates[in_view], distances[in_view], directions[in_view]
        if candidates.size == 0:
            continue
        hits = _cast(scene, pose[:3, 3], directions)
        visible[candidates[hits >= distances - GT_MAP_VISIBILITY_TOLERANCE_M]] = True
    return visible


def observed_surface_points(
    meshes: list[o3d.geometry.TriangleMesh],
    scene: o3d.t.geometry.RaycastingScene,
    poses: np.ndarray,
    num_points: int,
    fov_down_deg: float,
    fov_up_deg: float,
    max_range: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """About num_points points [M, 3] (world), uniform by area on the surfaces visible from poses [S, 4, 4]."""
    vertices, triangles, base = [], [], 0
    for mesh in meshes:
        vertices.append(np.asarray(mesh.vertices))
        triangles.append(np.asarray(mesh.triangles) + base)
        base += len(mesh.vertices)
    vertices, triangles = np.concatenate(vertices), np.concatenate(triangles)

    kept: list[np.ndarray] = []
    num_kept, to_sample = 0, 2 * num_points
    for _ in range(6):  # sample, keep the visible ones, top up with an estimate of the visible fraction
        candidates = _sample_surface(vertices, triangles, to_sample, rng)
        visible = candidates[_visible_from_any(scene, candidates, poses, fov_down_deg, fov_up_deg, max_range)]
        kept.append(visible)
        num_kept += len(visible)
        if num_kept >= num_points:
            break
        fraction = max(len(visible) / to_sample, 0.02)
        to_sample = int(np.ceil(1.2 * (num_points - num_kept) / fraction))
    points = np.concatenate(kept)
    if len(points) > num_points:
        points = points[np.sort(rng.choice(len(points), size=num_points, replace=False))]
    return points
