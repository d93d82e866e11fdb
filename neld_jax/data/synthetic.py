"""A synthetic LiDAR sequence with exact ground truth, built by Open3D ray casting.

The scene is a procedurally generated courtyard (ground plane, surrounding walls, box buildings, poles,
trees and bushes), seeded and deterministic. A spinning LiDAR (rings of beams at fixed elevations)
drives around a smooth closed loop through the courtyard; objects keep clear of the loop. Initial poses
come from the ground truth by a random walk in the relative motions, like odometry drift.

Ground-truth map: points sampled uniformly (by area) on the mesh surfaces and kept when they are
VISIBLE from at least one ground-truth sensor pose: inside the vertical field of view, within the
LiDAR's range limits and not occluded (checked by casting a ray from the sensor to the point). So the
map covers the surfaces the scans observed, at a uniform density, without the gaps between beam rings.

The generator's fields and their defaults (config.data.synthetic) are `synthetic_defaults`; `write_generic` writes a
sequence in the generic layout.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import ml_collections
import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError

# Open3D and SciPy are imported in the functions that use them: config.py imports synthetic_defaults from here, and
# the training path imports the config on machines without Open3D.
if TYPE_CHECKING:
    import open3d as o3d

logger = logging.getLogger(__name__)


def synthetic_defaults() -> ml_collections.ConfigDict:
    """Every field of the synthetic sequence generator with its default."""
    s = ml_collections.ConfigDict()
    s.seed = 0
    s.route = "loop"
    s.route_length_m = 600.0
    s.num_scans = 24
    s.scene_size_m = 60.0
    s.trajectory_radius_m = 15.0
    s.num_beams = 32
    s.num_columns = 512
    s.max_range_m = 60.0
    s.range_noise_m = 0.01
    s.drift_trans_m = 0.05
    s.drift_rot_deg = 0.5
    s.gt_map_points = 200_000
    return s



MIN_RANGE_M = 0.5  # LiDAR minimum range, as in the paper's preprocessing
FOV_DEG = (-15.0, 15.0)  # the simulated LiDAR's vertical field of view: its lowest and highest beams
SENSOR_HEIGHT_M = 1.8
PATH_WOBBLE = 0.08  # relative radial wobble of the loop; the scene keeps this band clear
SCAN_INTERVAL_S = 3.0  # 30 frames of 0.1 s: one keyframe per scan at the paper's 3 s spacing
GT_MAP_VISIBILITY_TOLERANCE_M = 0.02
ROUTES = ("loop", "courtyards", "handheld", "car")
HANDHELD_RATE_HZ = 2.0  # the handheld route's scans, when make_sequence is given no rate
HANDHELD_SPEED_M_S = 1.4  # walking
HANDHELD_TURN_DEG = (40.0, 50.0)  # the turn between consecutive handheld scans, either side
HANDHELD_STEADY_SCANS = 8  # the handheld walk's first scans look ahead (an odometry learns the sensor's overlap)
CAR_RATE_HZ = 10.0  # the car route's scans, when make_sequence is given no rate
CAR_START_S = 4.0  # the car speeds up from rest over this long
CAR_ROUTE_SAMPLES_PER_SCAN = 20  # the car's poses are the route's nearest samples, this many a scan apart


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ground(half_size: float) -> o3d.geometry.TriangleMesh:
    import open3d as o3d

    h = half_size
    vertices = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))


def _box(size_xyz, centre_xy, yaw: float = 0.0, base_z: float = 0.0) -> o3d.geometry.TriangleMesh:
    """A box standing on z = base_z, centred at centre_xy, rotated by yaw about z."""
    import open3d as o3d

    sx, sy, sz = size_xyz
    mesh = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    mesh.translate((-sx / 2, -sy / 2, 0.0))
    mesh.rotate(_yaw_matrix(yaw), center=(0.0, 0.0, 0.0))
    mesh.translate((centre_xy[0], centre_xy[1], base_z))
    return mesh


def _cylinder(radius: float, height: float, centre_xy, base_z: float = 0.0) -> o3d.geometry.TriangleMesh:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=height, resolution=12, split=1)
    mesh.translate((centre_xy[0], centre_xy[1], base_z + height / 2))
    return mesh


def _blob(radii, centre, rng: np.random.Generator) -> o3d.geometry.TriangleMesh:
    """A lumpy ellipsoid (vegetation-like): a sphere with per-vertex radial noise, scaled per axis."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=8)
    vertices = np.asarray(mesh.vertices)
    vertices = vertices * rng.uniform(0.85, 1.15, size=(len(vertices), 1)) * np.asarray(radii)
    vertices = vertices @ _yaw_matrix(rng.uniform(0, np.pi)).T + np.asarray(centre)
    mesh.vertices = o3d.utility.Vector3dVector(vertices)
    return mesh


def _place(
    rng: np.random.Generator, footprint_radius: float, half_size: float, band: tuple[float, float], tries: int = 100
):
    """A random centre [2] whose disc of footprint_radius stays inside the walls and out of the radial band
    (lo, hi) around the path; None if no such centre was found."""
    limit = half_size - 1.0 - footprint_radius
    if limit <= 0:
        return None
    for _ in range(tries):
        centre = rng.uniform(-limit, limit, size=2)
        distance = float(np.linalg.norm(centre))
        if distance + footprint_radius < band[0] or distance - footprint_radius > band[1]:
            return centre
    return None


def make_scene_meshes(
    seed: int, size_m: float = 60.0, path_radius_m: float | None = None, path_clearance_m: float = 2.5
) -> list[o3d.geometry.TriangleMesh]:
    """Legacy triangle meshes of a courtyard of size_m x size_m centred at the origin, ground at z = 0.

    path_radius_m: radius of the sensor's loop (default size_m / 4); buildings keep path_clearance_m
    and small objects 1 m away from the band that the loop sweeps."""
    rng = np.random.default_rng(seed)
    half = size_m / 2.0
    path_radius = size_m / 4.0 if path_radius_m is None else float(path_radius_m)
    wobble = PATH_WOBBLE * path_radius

    def band(clearance: float) -> tuple[float, float]:
        return path_radius - wobble - clearance, path_radius + wobble + clearance

    meshes = [_ground(half + 1.0)]
    thickness = 0.5
    for side in range(4):  # walls of different heights, inner faces on the courtyard border
        height = rng.uniform(4.0, 8.0)
        wall = _box((size_m + 2 * thickness, thickness, height), (0.0, half + thickness / 2))
        wall.rotate(_yaw_matrix(side * np.pi / 2), center=(0.0, 0.0, 0.0))
        meshes.append(wall)

    num_skipped = 0
    for _ in range(int(rng.integers(8, 13))):  # box buildings
        width, depth, height = rng.uniform(3.0, 9.0), rng.uniform(3.0, 9.0), rng.uniform(3.0, 12.0)
        yaw = rng.uniform(0.0, np.pi / 2)
        centre = _place(rng, 0.5 * np.hypot(width, depth), half, band(path_clearance_m))
        if centre is None:
            num_skipped += 1
            continue
        meshes.append(_box((width, depth, height), centre, yaw))

    for _ in range(int(rng.integers(10, 16))):  # poles
        radius, height = rng.uniform(0.08, 0.2), rng.uniform(3.0, 7.0)
        centre = _place(rng, radius, half, band(1.0))
        if centre is None:
            num_skipped += 1
            continue
        meshes.append(_cylinder(radius, height, centre))

    for i in range(int(rng.integers(8, 12))):  # vegetation: trees (trunk + crown) and bushes
        if i % 2 == 0:
            trunk_height = rng.uniform(1.5, 3.0)
            crown = rng.uniform([1.0, 1.0, 1.0], [2.0, 2.0, 2.5])
            centre = _place(rng, float(crown[:2].max()) * 1.15, half, band(1.0))
            if centre is None:
                num_skipped += 1
                continue
            meshes.append(_cylinder(0.15, trunk_height + crown[2] * 0.5, centre))
            meshes.append(_blob(crown, (centre[0], centre[1], trunk_height + crown[2]), rng))
        else:
            radii = rng.uniform([0.5, 0.5, 0.4], [1.5, 1.5, 1.0])
            centre = _place(rng, float(radii[:2].max()) * 1.15, half, band(1.0))
            if centre is None:
                num_skipped += 1
                continue
            meshes.append(_blob(radii, (centre[0], centre[1], radii[2] * 0.8), rng))
    if num_skipped:
        logger.debug("make_scene_meshes: %d objects found no free place and were left out", num_skipped)
    return meshes


def raycasting_scene(meshes: list[o3d.geometry.TriangleMesh]) -> o3d.t.geometry.RaycastingScene:
    """An Open3D RaycastingScene holding all the meshes."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for mesh in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def make_scene(
    seed: int, size_m: float = 60.0, path_radius_m: float | None = None
) -> tuple[o3d.t.geometry.RaycastingScene, list[o3d.geometry.TriangleMesh]]:
    """(RaycastingScene, legacy meshes) of the seeded courtyard; see make_scene_meshes."""
    meshes = make_scene_meshes(seed, size_m, path_radius_m=path_radius_m)
    return raycasting_scene(meshes), meshes


# --------------------------------------------------------------------------------------------------
# Sensor and trajectory
# --------------------------------------------------------------------------------------------------


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


def smooth_trajectory(num_scans: int, radius_m: float, seed: int) -> np.ndarray:
    """Ground-truth poses [S, 4, 4] (sensor -> world) on a smooth closed loop around the origin, evenly spaced.

    The loop has radius radius_m with a gentle radial wobble (at most PATH_WOBBLE * radius_m); the
    sensor rides about 1.8 m above the ground, its yaw follows the motion, with small roll and pitch."""
    return loop_poses(np.arange(num_scans) / num_scans, radius_m, seed)


def loop_poses(fraction: np.ndarray, radius_m: float, seed: int) -> np.ndarray:
    """Poses [K, 4, 4] (sensor -> world) at fractions [K] of the way round the seed's loop (smooth_trajectory's
    loop: fraction i / S is its scan i; any fraction in between is where the sensor is at that moment)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    start, wobble_phase, z_phase, roll_phase, pitch_phase = rng.uniform(0.0, 2 * np.pi, size=5)
    wobble = PATH_WOBBLE * rng.uniform(0.5, 1.0)
    lobes = int(rng.integers(2, 4))
    theta = start + 2 * np.pi * np.asarray(fraction, dtype=np.float64).reshape(-1)

    rho = radius_m * (1.0 + wobble * np.sin(lobes * theta + wobble_phase))
    d_rho = radius_m * wobble * lobes * np.cos(lobes * theta + wobble_phase)
    x, y = rho * np.cos(theta), rho * np.sin(theta)
    dx = d_rho * np.cos(theta) - rho * np.sin(theta)
    dy = d_rho * np.sin(theta) + rho * np.cos(theta)
    z = SENSOR_HEIGHT_M + 0.1 * np.sin(theta + z_phase)
    yaw = np.arctan2(dy, dx)
    pitch = np.deg2rad(1.5) * np.sin(3 * theta + pitch_phase)
    roll = np.deg2rad(2.0) * np.sin(2 * theta + roll_phase)

    poses = np.tile(np.eye(4), (theta.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses


def handheld_walk(num_scans: int, radius_m: float, seed: int, rate_hz: float) -> np.ndarray:
    """Ground-truth poses [S, 4, 4] (sensor -> world) of a handheld LiDAR carried round the seed's loop at
    HANDHELD_SPEED_M_S, one scan each 1 / rate_hz s, turned about the vertical by HANDHELD_TURN_DEG (40-50 degrees)
    between consecutive scans, left or right at random, after HANDHELD_STEADY_SCANS scans looking ahead: the walker
    sets off, then looks around. A constant-velocity guess is then wrong by up to 100 degrees whenever the turn
    changes side."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed + 4)
    step_m = HANDHELD_SPEED_M_S / rate_hz
    poses = loop_poses(np.arange(num_scans) * step_m / (2 * np.pi * radius_m), radius_m, seed)
    turns = rng.uniform(*HANDHELD_TURN_DEG, size=num_scans) * rng.choice([-1.0, 1.0], size=num_scans)
    steady = min(HANDHELD_STEADY_SCANS, num_scans)
    turns[:steady] = 0.0
    heading = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    # about the world's vertical, so that the turn from scan to scan is the drawn one, whatever the loop's heading
    look = np.deg2rad(np.cumsum(turns))
    look[steady:] -= heading[steady:] - heading[steady - 1]
    poses[:, :3, :3] = Rotation.from_euler("z", look[:, None]).as_matrix() @ poses[:, :3, :3]
    return poses


def add_odometry_drift(gt_poses: np.ndarray, trans_sigma_m: float, rot_sigma_deg: float, seed: int,
                       keep_tilt: bool = False) -> np.ndarray:
    """Initial poses [S, 4, 4] that drift from gt_poses [S, 4, 4] like odometry.

    T_init[0] = T_gt[0]; T_init[s] = T_init[s-1] @ rel_gt(s-1, s) @ exp(noise_s), where the noise has
    rotation vector ~ N(0, rot_sigma_deg) and translation ~ N(0, trans_sigma_m) per axis and step
    (exp taken as [Exp(omega) | rho], which is the SE(3) exponential to first order): the drift of a LiDAR-only
    odometry, in all six degrees of freedom.

    keep_tilt: the drift of an IMU-aided odometry instead, whose roll and pitch gravity keeps: each step's rotation
    noise is a turn ~ N(0, rot_sigma_deg) about the world's up axis (+z) through the scan, and the translation
    noise ~ N(0, trans_sigma_m) per world axis; every scan keeps gt's up axis (position and heading drift)."""
    from scipy.spatial.transform import Rotation

    gt_poses = np.asarray(gt_poses, dtype=np.float64)
    rng = np.random.default_rng(seed)
    num_steps = max(gt_poses.shape[0] - 1, 0)
    rotation_noise = rng.normal(0.0, np.deg2rad(rot_sigma_deg), size=(num_steps, 3))
    translation_noise = rng.normal(0.0, trans_sigma_m, size=(num_steps, 3))
    if keep_tilt:
        rotation_noise[:, :2] = 0.0  # the same draws, so that seed s drifts the same headings either way
    noise = np.tile(np.eye(4), (num_steps, 1, 1))
    if num_steps:
        noise[:, :3, :3] = Rotation.from_rotvec(rotation_noise).as_matrix()
        noise[:, :3, 3] = translation_noise

    init = gt_poses.copy()
    for s in range(1, gt_poses.shape[0]):
        moved = init[s - 1] @ np.linalg.inv(gt_poses[s - 1]) @ gt_poses[s]
        if keep_tilt:  # noise in the world frame, its turn about the vertical through the scan
            turn = noise[s - 1][:3, :3]
            init[s] = moved
            init[s, :3, :3] = turn @ moved[:3, :3]
            init[s, :3, 3] = moved[:3, 3] + noise[s - 1][:3, 3]
        else:
            init[s] = moved @ noise[s - 1]
    return init


# --------------------------------------------------------------------------------------------------
# A long route through connected courtyards
# --------------------------------------------------------------------------------------------------

ROUTE_CLEARANCE_M = 3.0  # buildings and walls keep this far from the route; poles and trees 2 m
COURTYARD_SPACING_M = 45.0  # a wall with a gate crosses the route every this many metres of route


def _rounded_rectangle(length_m: float, num_points: int = 4000) -> np.ndarray:
    """Points [num_points, 2] evenly spaced along a closed rounded rectangle (3:2, corner radius 0.15 of the
    short side) of perimeter length_m, centred at the origin, counter-clockwise."""
    # Perimeter of half sides (a, b), corner radius r: 4 (a - r) + 4 (b - r) + 2 pi r; a = 1.5 b, r = 0.3 b.
    b = length_m / (4 * 1.5 + 4 * 1.0 - 8 * 0.3 + 2 * np.pi * 0.3)
    a, r = 1.5 * b, 0.3 * b
    dense = []
    for cx, cy, start in ((a - r, b - r, 0.0), (-(a - r), b - r, np.pi / 2), (-(a - r), -(b - r), np.pi),
                          (a - r, -(b - r), 1.5 * np.pi)):
        t = np.linspace(start, start + np.pi / 2, 200)
        dense.append(np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1))
    # The arcs joined in order form the closed curve (the straight sides between them are implied).
    dense = np.concatenate(dense + [dense[0][:1]])
    seg = np.linalg.norm(np.diff(dense, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s_new = np.linspace(0.0, s[-1], num_points, endpoint=False)
    return np.stack([np.interp(s_new, s, dense[:, 0]), np.interp(s_new, s, dense[:, 1])], axis=1)


def courtyard_route(num_scans: int, length_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses [S, 4, 4] evenly along a closed route of length_m (a rounded rectangle, so that it
    passes a ring of courtyards), and the dense route [N, 2] for placing the scene. Yaw follows the route;
    height, roll and pitch wobble a little as in smooth_trajectory."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    z_phase, roll_phase, pitch_phase = rng.uniform(0.0, 2 * np.pi, size=3)
    dense = _rounded_rectangle(length_m)
    n = len(dense)
    idx = (np.arange(num_scans) * n) // num_scans
    xy = dense[idx]
    tangent = dense[(idx + 1) % n] - dense[(idx - 1) % n]
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0])
    theta = 2 * np.pi * np.arange(num_scans) / num_scans
    pitch = np.deg2rad(1.5) * np.sin(7 * theta + pitch_phase)
    roll = np.deg2rad(2.0) * np.sin(5 * theta + roll_phase)
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    poses[:, :3, 3] = np.stack([xy[:, 0], xy[:, 1], SENSOR_HEIGHT_M + 0.1 * np.sin(3 * theta + z_phase)], axis=1)
    return poses, dense


def car_drive(num_scans: int, length_m: float, seed: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """courtyard_route's poses [S, 4, 4] and dense route [N, 2] for a car that starts from rest: one scan each
    1 / rate_hz s, speeding up evenly over CAR_START_S, then at the speed that brings it round the closed route of
    length_m by the time of scan S (the ground truth of the route's samples nearest each scan's distance)."""
    samples = CAR_ROUTE_SAMPLES_PER_SCAN * num_scans
    poses, dense = courtyard_route(samples, length_m, seed)
    times = np.arange(num_scans + 1) / rate_hz
    travelled = np.where(times < CAR_START_S, times ** 2 / (2 * CAR_START_S), times - CAR_START_S / 2)  # x speed
    index = np.rint(travelled[:-1] / travelled[-1] * samples).astype(np.int64) % samples
    return poses[index], dense


def make_courtyards_meshes(seed: int, route_xy: np.ndarray) -> list[o3d.geometry.TriangleMesh]:
    """Meshes of a ring of connected courtyards along a closed route [N, 2]: a ground plane, a wall across the
    route every COURTYARD_SPACING_M with a gate where the route passes, box buildings, poles and trees beside
    the route (none within ROUTE_CLEARANCE_M of it). Seeded and deterministic."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    tree = cKDTree(route_xy)
    lo, hi = route_xy.min(axis=0) - 40.0, route_xy.max(axis=0) + 40.0
    half = float(max(np.abs(lo).max(), np.abs(hi).max()))
    meshes = [_ground(half)]
    n = len(route_xy)
    step_m = float(np.linalg.norm(np.diff(route_xy, axis=0), axis=1).mean())

    def clear(centre, radius, clearance):
        return tree.query(centre)[0] > radius + clearance

    tangents = np.roll(route_xy, -1, axis=0) - np.roll(route_xy, 1, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normals = np.stack([-tangents[:, 1], tangents[:, 0]], axis=1)
    every = max(int(COURTYARD_SPACING_M / step_m), 1)
    for i in range(0, n, every):  # walls across the route, a 2 * clearance gate in the middle, on both sides
        height, length = rng.uniform(3.0, 7.0), rng.uniform(12.0, 25.0)
        for side in (-1.0, 1.0):
            mid = route_xy[i] + side * normals[i] * (ROUTE_CLEARANCE_M + length / 2)
            yaw = float(np.arctan2(normals[i, 1], normals[i, 0]))
            if clear(mid, length / 2, ROUTE_CLEARANCE_M - 0.5):
                meshes.append(_box((length, 0.4, height), mid, yaw))
    for i in range(0, n, max(int(9.0 / step_m), 1)):  # buildings beside the route, both sides
        for side in (-1.0, 1.0):
            if rng.random() < 0.35:
                continue
            w, d, h = rng.uniform(3.0, 10.0), rng.uniform(3.0, 10.0), rng.uniform(3.0, 14.0)
            radius = 0.5 * np.hypot(w, d)
            along = rng.uniform(-4.0, 4.0)
            centre = route_xy[i] + tangents[i] * along + side * normals[i] * rng.uniform(radius + 3.5, radius + 14.0)
            if clear(centre, radius, ROUTE_CLEARANCE_M):
                meshes.append(_box((w, d, h), centre, rng.uniform(0.0, np.pi / 2)))
    for i in range(0, n, max(int(6.0 / step_m), 1)):  # poles and trees close to the route
        side = rng.choice([-1.0, 1.0])
        centre = route_xy[i] + side * normals[i] * rng.uniform(2.5, 7.0)
        if rng.random() < 0.5:
            radius, height = rng.uniform(0.08, 0.2), rng.uniform(3.0, 7.0)
            if clear(centre, radius, 2.0):
                meshes.append(_cylinder(radius, height, centre))
        else:
            trunk, crown = rng.uniform(1.5, 3.0), rng.uniform([1.0, 1.0, 1.0], [2.0, 2.0, 2.5])
            if clear(centre, float(crown[:2].max()) * 1.15, 2.0):
                meshes.append(_cylinder(0.15, trunk + crown[2] * 0.5, centre))
                meshes.append(_blob(crown, (centre[0], centre[1], trunk + crown[2]), rng))
    return meshes


# --------------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------------
# Ground-truth map
# --------------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------------
# Whole sequence
# --------------------------------------------------------------------------------------------------


def _resolve_config(cfg) -> ml_collections.ConfigDict:
    resolved = synthetic_defaults()
    if cfg is None:
        return resolved
    items = cfg.items() if hasattr(cfg, "items") else dict(cfg).items()
    for key, value in items:
        if key not in resolved:
            raise ConfigError(
                f"data.synthetic: unknown field '{key}' (known: {', '.join(sorted(resolved.keys()))})"
            )
        try:
            resolved[key] = type(resolved[key])(value)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"data.synthetic.{key}: cannot use {value!r} ({exc})") from exc
    if resolved.num_scans < 1 or resolved.num_beams < 1 or resolved.num_columns < 1:
        raise ConfigError("data.synthetic: num_scans, num_beams and num_columns must be at least 1")
    if resolved.route not in ROUTES:
        raise ConfigError(f"data.synthetic.route: unknown route {resolved.route!r} ({' | '.join(ROUTES)})")
    if resolved.route in ("courtyards", "car") and resolved.route_length_m < 100.0:
        raise ConfigError(f"data.synthetic.route_length_m ({resolved.route_length_m}) must be at least 100 m")
    if resolved.route in ("loop", "handheld") and not (
            0 < resolved.trajectory_radius_m * (1 + PATH_WOBBLE) < resolved.scene_size_m / 2 - 1.0):
        raise ConfigError(
            f"data.synthetic: trajectory_radius_m ({resolved.trajectory_radius_m}) must be positive and leave the "
            f"loop inside the {resolved.scene_size_m} m courtyard"
        )
    if resolved.max_range_m <= MIN_RANGE_M or resolved.gt_map_points < 0:
        raise ConfigError("data.synthetic: max_range_m must exceed 0.5 m and gt_map_points must be >= 0")
    return resolved


def make_sequence(cfg=None, rate_hz: float = 0.0) -> Sequence:
    """A synthetic Sequence: scans cast from the ground-truth poses, drifted initial poses, GT poses and map.

    cfg: ConfigDict or dict with any of the fields of synthetic_defaults() (missing ones take the
    defaults, unknown ones raise ConfigError). Timestamps are SCAN_INTERVAL_S (3 s) apart, so keyframe
    selection at 3 s keeps every scan.

    rate_hz > 0: the raw sweeps of a LiDAR spinning at that rate instead, as a recording holds them (the loop
    route only): num_scans sweeps 1 / rate_hz apart, each point cast from where the sensor was at its column's
    instant, `point_times` [N_i] seconds after the sweep's stamp, ground truth at the sweeps' stamps (their
    starts), and no initial poses (poses None: a run makes them from the scans, data/odometry.py).

    The routes "handheld" (handheld_walk round the loop, HANDHELD_RATE_HZ unless rate_hz is given) and "car"
    (car_drive along the courtyards' route at CAR_RATE_HZ unless rate_hz is given: num_scans over route_length_m,
    from rest) are rigid scans
    (deskewed, as a front-end writes them) 1 / rate_hz apart, with ground truth and no initial poses."""
    cfg = _resolve_config(cfg)
    if rate_hz > 0 and cfg.route == "courtyards":
        raise ConfigError(f"synthetic sweeps at {rate_hz} Hz follow the loop route, not {cfg.route!r}")
    started = time.perf_counter()
    scene, meshes, gt_poses = _scene_and_route(cfg, rate_hz)
    directions = spinning_lidar_directions(cfg.num_beams, FOV_DEG[1], FOV_DEG[0], cfg.num_columns)
    rng = np.random.default_rng(cfg.seed + 2)
    point_times, init_poses = None, None
    if cfg.route in ("handheld", "car"):
        rate_hz = rate_hz or (HANDHELD_RATE_HZ if cfg.route == "handheld" else CAR_RATE_HZ)
        timestamps = np.arange(cfg.num_scans) / rate_hz
        scans = [cast_scan(scene, pose, directions, cfg.max_range_m, cfg.range_noise_m, rng) for pose in gt_poses]
    elif rate_hz > 0:
        timestamps, scans, point_times = _raw_sweeps(cfg, rate_hz, scene, directions, rng)
    else:
        init_poses = add_odometry_drift(gt_poses, cfg.drift_trans_m, cfg.drift_rot_deg, cfg.seed + 1)
        timestamps = SCAN_INTERVAL_S * np.arange(cfg.num_scans, dtype=np.float64)
        scans = [cast_scan(scene, pose, directions, cfg.max_range_m, cfg.range_noise_m, rng) for pose in gt_poses]
    gt_map = None
    if cfg.gt_map_points > 0:
        gt_map = observed_surface_points(
            meshes, scene, gt_poses, cfg.gt_map_points, FOV_DEG[0], FOV_DEG[1], cfg.max_range_m,
            np.random.default_rng(cfg.seed + 3),
        )
    logger.info(
        "synthetic sequence (seed %d): %d scans, %d points, gt map %d points, %d meshes, %.2f s",
        cfg.seed, len(scans), sum(len(s) for s in scans), 0 if gt_map is None else len(gt_map), len(meshes),
        time.perf_counter() - started,
    )
    suffix = f"_{cfg.route}" if cfg.route in ("handheld", "car") else ""
    return Sequence(
        scans=scans,
        poses=init_poses,
        timestamps=timestamps,
        gt_poses=gt_poses,
        gt_map=gt_map,
        name=f"synthetic_seed{cfg.seed}{suffix}" + (f"_{rate_hz:g}hz" if rate_hz > 0 else ""),
        source="synthetic",
        point_times=point_times,
    )


def _scene_and_route(cfg, rate_hz: float):
    """(RaycastingScene, meshes, ground-truth poses [S, 4, 4]) of the resolved cfg's route."""
    if cfg.route == "car":
        gt_poses, route_xy = car_drive(cfg.num_scans, cfg.route_length_m, cfg.seed, rate_hz or CAR_RATE_HZ)
        meshes = make_courtyards_meshes(cfg.seed, route_xy)
        return raycasting_scene(meshes), meshes, gt_poses
    if cfg.route == "courtyards":
        gt_poses, route_xy = courtyard_route(cfg.num_scans, cfg.route_length_m, cfg.seed)
        meshes = make_courtyards_meshes(cfg.seed, route_xy)
        return raycasting_scene(meshes), meshes, gt_poses
    scene, meshes = make_scene(cfg.seed, cfg.scene_size_m, path_radius_m=cfg.trajectory_radius_m)
    if cfg.route == "handheld":
        return scene, meshes, handheld_walk(cfg.num_scans, cfg.trajectory_radius_m, cfg.seed,
                                            rate_hz or HANDHELD_RATE_HZ)
    return scene, meshes, smooth_trajectory(cfg.num_scans, cfg.trajectory_radius_m, cfg.seed)


def _raw_sweeps(cfg, rate_hz: float, scene, directions: np.ndarray, rng: np.random.Generator):
    """(stamps [S], sweeps [S] x [N_i, 3], per-point times [S] x [N_i]) of a LiDAR spinning at rate_hz round the
    loop: each column cast from where the sensor is at its instant."""
    timestamps, scans, point_times = np.arange(cfg.num_scans) / rate_hz, [], []
    column_fraction = np.arange(cfg.num_columns) / cfg.num_columns
    for i in range(cfg.num_scans):
        column_poses = loop_poses((i + column_fraction) / cfg.num_scans, cfg.trajectory_radius_m, cfg.seed)
        points, column = cast_sweep(scene, column_poses, directions, cfg.max_range_m, cfg.range_noise_m, rng)
        scans.append(points)
        point_times.append(column_fraction[column] / rate_hz)
    return timestamps, scans, point_times


def load(data_cfg) -> Sequence:
    """data.format = 'synthetic': make_sequence(data.synthetic) (data.root is not read)."""
    return make_sequence(data_cfg.get("synthetic", None))


def write_generic(seq: Sequence, root) -> None:
    """Write seq in the generic layout: ROOT/scans/%06d.pcd, poses.txt, gt_poses.txt (TUM), gt_map.pcd.

    Scans are written as binary PCD (float32 coordinates). Without timestamps, 0, 1, 2, ... are written. Scans
    without poses (None: no poses.txt) are named by their stamps (<seconds>.pcd), which the layout reads them by,
    raw sweeps (point_times set) with point_times/<stamp>.npy beside, as bin/import_rosbag.py writes a bag without
    odometry."""
    from neld_jax.data.generic import POINT_TIMES_FOLDER
    from neld_jax.data.poses import write_tum
    from neld_jax.data.scans import write_scan

    root = Path(root)
    (root / "scans").mkdir(parents=True, exist_ok=True)
    timestamps = seq.timestamps if seq.timestamps is not None else np.arange(seq.num_scans, dtype=np.float64)
    if seq.point_times is not None:
        (root / POINT_TIMES_FOLDER).mkdir(exist_ok=True)
    for i, scan in enumerate(seq.scans):
        name = f"{i:06d}" if seq.poses is not None else f"{timestamps[i]:.9f}"
        write_scan(root / "scans" / f"{name}.pcd", scan)
        if seq.point_times is not None:
            np.save(root / POINT_TIMES_FOLDER / f"{name}.npy", seq.point_times[i])
    if seq.poses is not None:
        write_tum(root / "poses.txt", timestamps, seq.poses)
    if seq.gt_poses is not None:
        write_tum(root / "gt_poses.txt", timestamps, seq.gt_poses)
    if seq.gt_map is not None:
        write_scan(root / "gt_map.pcd", seq.gt_map)
    logger.info("wrote %d scans in the generic layout to %s", seq.num_scans, root)
