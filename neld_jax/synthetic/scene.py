"""The synthetic scenes: a seeded courtyard (ground, walls, box buildings, poles, trees and bushes) that keeps a
band clear for the sensor's loop, and a ring of connected courtyards along a long route; Open3D meshes and the
ray-casting scene that holds them."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

# Open3D and SciPy are imported in the functions that use them: config.py imports the synthetic package module,
# and the training path imports the config on machines without Open3D.
if TYPE_CHECKING:
    import open3d as o3d

logger = logging.getLogger(__name__)

PATH_WOBBLE = 0.08  # relative radial wobble of the loop; the scene keeps this band clear
ROUTE_CLEARANCE_M = 3.0  # buildings and walls keep this far from the route; poles and trees 2 m
COURTYARD_SPACING_M = 45.0  # a wall with a gate crosses the route every this many metres of route


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

    meshes = [_ground(half + 1.0)] + _walls(rng, size_m)
    placed = [
        _buildings(rng, half, band(path_clearance_m)),
        _poles(rng, half, band(1.0)),
        _vegetation(rng, half, band(1.0)),
    ]
    for objects, _ in placed:
        meshes.extend(objects)
    num_skipped = sum(skipped for _, skipped in placed)
    if num_skipped:
        logger.debug("make_scene_meshes: %d objects found no free place and were left out", num_skipped)
    return meshes


def _walls(rng: np.random.Generator, size_m: float) -> list:
    """Four walls of different heights, their inner faces on the border of the size_m courtyard."""
    thickness, walls = 0.5, []
    for side in range(4):
        height = rng.uniform(4.0, 8.0)
        wall = _box((size_m + 2 * thickness, thickness, height), (0.0, size_m / 2.0 + thickness / 2))
        wall.rotate(_yaw_matrix(side * np.pi / 2), center=(0.0, 0.0, 0.0))
        walls.append(wall)
    return walls


def _buildings(rng: np.random.Generator, half: float, band: tuple[float, float]) -> tuple[list, int]:
    """8-12 box buildings out of the band -> (their meshes, how many found no place)."""
    meshes, skipped = [], 0
    for _ in range(int(rng.integers(8, 13))):
        width, depth, height = rng.uniform(3.0, 9.0), rng.uniform(3.0, 9.0), rng.uniform(3.0, 12.0)
        yaw = rng.uniform(0.0, np.pi / 2)
        centre = _place(rng, 0.5 * np.hypot(width, depth), half, band)
        if centre is None:
            skipped += 1
            continue
        meshes.append(_box((width, depth, height), centre, yaw))
    return meshes, skipped


def _poles(rng: np.random.Generator, half: float, band: tuple[float, float]) -> tuple[list, int]:
    """10-15 poles out of the band -> (their meshes, how many found no place)."""
    meshes, skipped = [], 0
    for _ in range(int(rng.integers(10, 16))):
        radius, height = rng.uniform(0.08, 0.2), rng.uniform(3.0, 7.0)
        centre = _place(rng, radius, half, band)
        if centre is None:
            skipped += 1
            continue
        meshes.append(_cylinder(radius, height, centre))
    return meshes, skipped


def _vegetation(rng: np.random.Generator, half: float, band: tuple[float, float]) -> tuple[list, int]:
    """8-11 trees (trunk + crown) and bushes, alternately, out of the band -> (their meshes, how many found no
    place)."""
    meshes, skipped = [], 0
    for i in range(int(rng.integers(8, 12))):
        if i % 2 == 0:
            trunk_height = rng.uniform(1.5, 3.0)
            crown = rng.uniform([1.0, 1.0, 1.0], [2.0, 2.0, 2.5])
            centre = _place(rng, float(crown[:2].max()) * 1.15, half, band)
            if centre is None:
                skipped += 1
                continue
            meshes.append(_cylinder(0.15, trunk_height + crown[2] * 0.5, centre))
            meshes.append(_blob(crown, (centre[0], centre[1], trunk_height + crown[2]), rng))
        else:
            radii = rng.uniform([0.5, 0.5, 0.4], [1.5, 1.5, 1.0])
            centre = _place(rng, float(radii[:2].max()) * 1.15, half, band)
            if centre is None:
                skipped += 1
                continue
            meshes.append(_blob(radii, (centre[0], centre[1], radii[2] * 0.8), rng))
    return meshes, skipped


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


def street_meshes(
    length_m: float = 400.0, width_m: float = 12.0, wall_height_m: float = 8.0
) -> list[o3d.geometry.TriangleMesh]:
    """A straight street along x, centred at the origin: the ground and two long walls (house fronts) at y = +-
    width_m / 2, and nothing across it, so that no surface faces along the street: a scan registered there is fixed
    in every direction but the motion along x (the case where scan registration has to leave that motion to the
    odometry)."""
    thickness = 0.5
    side = width_m / 2.0 + thickness / 2.0
    return [
        _ground(length_m / 2.0 + 1.0),
        _box((length_m, thickness, wall_height_m), (0.0, side)),
        _box((length_m, thickness, wall_height_m), (0.0, -side)),
    ]
