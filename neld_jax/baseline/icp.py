"""The baseline's ICP: scans prepared for point-to-plane registration, a nearest-neighbour index of a target, the
point-to-plane ICP with its normal check, its multi-scale form, and the information matrix of a registered pair.

Information matrices are Open3D's `get_information_matrix_from_point_clouds`, and ICP's steps its point-to-plane
estimation, both summed here in a fixed order (`information`, `point_to_plane_step`): Open3D sums them in parallel
in an order that changes from call to call, and the same input must give the same poses bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from neld_jax.baseline.settings import BaselineSettings
from neld_jax.geometry import transform_points


def prepare_scan(points: np.ndarray, voxel_size: float, normal_radius: float) -> o3d.geometry.PointCloud:
    """points: [N, 3] sensor frame -> voxel-downsampled Open3D cloud with normals (for point-to-plane)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if voxel_size > 0:
        cloud = cloud.voxel_down_sample(voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    # Normals face the sensor (at the origin of the scan frame); ICP does not need it, but it is cheap.
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def prepare_clouds(scans: list[np.ndarray], settings: BaselineSettings) -> list:
    """scans: S arrays [N_i, 3] (sensor frame) -> the S Open3D clouds every step of the baseline registers
    (settings.voxel_size_m grid, normals within settings.normal_radius_m)."""
    return [prepare_scan(scan, settings.voxel_size_m, settings.normal_radius_m) for scan in scans]


@dataclasses.dataclass(frozen=True)
class IcpResult:
    """The outcome of one ICP scale. fitness: the fraction of source points with a target point within the
    correspondence distance (Open3D's definition, whatever the normals: the gates' thresholds mean what they meant
    with Open3D's ICP); inlier_rmse [m]: of the correspondences used; num_correspondences: those used (normals
    compatible)."""

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    num_correspondences: int


class TargetIndex:
    """Open3D's nearest-neighbour index of a target cloud's points, for searches up to max_distance.

    Which search is fastest depends on how many points lie within the distance (measured on HKU_2, 4,000-point scans
    as queries): a radius search ("hybrid", nearest within the radius) took 0.8 ms against one scan at 0.5 m (the
    nearest-neighbour search 1.9 ms), but 13-14 ms against a refinement target of 25-29k map points at 0.25 m (the
    nearest 4-7 ms) and 130-200 ms against a 40k-point local map at 1 m (the nearest 3 ms; scipy's KD-tree 5-7 ms).
    So the radius search for scan-sized targets and short distances, the nearest otherwise."""

    RADIUS_SEARCH_MAX_M = 0.5
    RADIUS_SEARCH_MAX_POINTS = 15_000

    def __init__(self, target: o3d.geometry.PointCloud, max_distance: float):
        self.max_distance = float(max_distance)
        points = np.asarray(target.points)
        self._search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(points))
        self._radius = self.searches_radius(len(points), self.max_distance)
        if self._radius:
            self._search.hybrid_index(self.max_distance)
        else:
            self._search.knn_index()
        self._last = None  # (distance, points, nearest, squared) of the last search

    @classmethod
    def searches_radius(cls, num_points: int, max_distance: float) -> bool:
        """Whether the index of num_points target points for searches up to max_distance searches a radius (else
        the nearest point: then one index serves every distance)."""
        return max_distance <= cls.RADIUS_SEARCH_MAX_M and num_points <= cls.RADIUS_SEARCH_MAX_POINTS

    def nearest(self, points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
        """points [N, 3] -> (index [N] of the nearest target point, squared distance [N]); index -1 where none lies
        within distance (<= max_distance)."""
        last = self._last
        # multiscale_icp's last pass at one scale and its first at the next, shorter one query the same points: the
        # nearest point within the longer distance, kept where it lies within the shorter, is the nearest there.
        if not (last is not None and distance <= last[0] and np.array_equal(points, last[1])):
            if self._radius:
                nearest, squared, _ = self._search.hybrid_search(o3d.core.Tensor(points), distance, 1)
            else:
                nearest, squared = self._search.knn_search(o3d.core.Tensor(points), 1)
            last = self._last = (distance, np.array(points), nearest.numpy()[:, 0], squared.numpy()[:, 0])
        _, _, nearest, squared = last
        return np.where(squared <= distance**2, nearest, -1), squared


def point_to_plane_icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    guess: np.ndarray,
    distance: float,
    max_iterations: int,
    min_normal_cos: float | None,
    oriented: bool,
    index: TargetIndex | None = None,
) -> IcpResult:
    """Point-to-plane ICP whose correspondences must also agree in normal direction.

    Open3D's registration_icp pairs each source point with its nearest target point within `distance`, whatever the
    surfaces' orientations. At a thin wall seen from both sides (a gate, a door) that pairs one face with the other
    and slides the scan by the wall's thickness, to a pose that overlaps BETTER than the true one (measured on the
    long synthetic route: 0.3-0.4 m at 6 of 199 chain links, docs/evaluation.md). Here a pair counts only when the
    normals' cosine (after moving the source) is at least min_normal_cos, |cosine| when `oriented` is False (target
    normals of unknown sign); min_normal_cos None pairs as Open3D's registration_icp does. Open3D does the search
    (index: a TargetIndex of target, built here if None); the point-to-plane step is Open3D's, with its sums in a
    fixed order (point_to_plane_step), so that a run repeats bit for bit. Stops like Open3D's
    ICPConvergenceCriteria (fitness and rmse changing by less than 1e-6) or after max_iterations steps.

    source, target: Open3D clouds with normals; guess, returned transformation: [4, 4], source -> target frame.
    """
    source_points, source_normals = np.asarray(source.points), np.asarray(source.normals)
    target_points, target_normals = np.asarray(target.points), np.asarray(target.normals)
    index = index if index is not None else TargetIndex(target, distance)
    transform = np.array(guess, dtype=np.float64)
    previous = None
    for iteration in range(max_iterations + 1):  # the last pass only measures the final transform
        moved = source_points @ transform[:3, :3].T + transform[:3, 3]
        nearest, squared = index.nearest(moved, distance)
        within = nearest >= 0
        if min_normal_cos is None:
            compatible = within
        else:
            cosines = np.einsum(
                "ij,ij->i", source_normals[within] @ transform[:3, :3].T, target_normals[nearest[within]]
            )
            compatible = np.zeros_like(within)
            compatible[within] = (cosines if oriented else np.abs(cosines)) >= min_normal_cos
        fitness = float(within.mean()) if len(within) else 0.0
        rmse = float(np.sqrt(np.mean(squared[compatible]))) if compatible.any() else 0.0
        result = IcpResult(transform.copy(), fitness, rmse, int(compatible.sum()))
        converged = previous is not None and (
            abs(fitness - previous.fitness) < 1e-6 and abs(rmse - previous.inlier_rmse) < 1e-6
        )
        if converged or result.num_correspondences < 6 or iteration == max_iterations:
            return result
        previous = result
        paired = nearest[compatible]
        transform = point_to_plane_step(moved[compatible], target_points[paired], target_normals[paired]) @ transform
    return result


def point_to_plane_step(points: np.ndarray, target_points: np.ndarray, target_normals: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step of Open3D's TransformationEstimationPointToPlane, its sums taken in a fixed order.

    Open3D (0.20) sums the 6x6 system with TBB's parallel_reduce, whose split of the pairs changes from call to call,
    and with it the last bits of the step; over the baseline's thousands of steps two runs' poses came out up to 2e-5
    apart (OMP_NUM_THREADS does not reach TBB). numpy's sums here depend only on the number of pairs.
    points: [N, 3] the source points, moved; target_points, target_normals: [N, 3] their partners -> [4, 4]."""
    (px, py, pz), normals = points.T, np.ascontiguousarray(target_normals.T)
    nx, ny, nz = normals
    residuals = ((points - target_points).T * normals).sum(axis=0)
    # The Jacobian's rows [6, N]: p x n, then n; each sum below runs along one contiguous row.
    jacobians = np.stack([py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx, nx, ny, nz])
    jtj = np.stack([(row * jacobians).sum(axis=1) for row in jacobians])
    jtr = (jacobians * residuals).sum(axis=1)
    try:
        x = np.linalg.solve(jtj, -jtr)
    except np.linalg.LinAlgError:  # degenerate pairs (all on one plane): no step
        return np.eye(4)
    # Open3D's TransformVector6dToMatrix4d: x = (roll, pitch, yaw, translation), R = Rz(yaw) Ry(pitch) Rx(roll).
    (ca, cb, cc), (sa, sb, sc) = np.cos(x[:3]), np.sin(x[:3])
    step = np.eye(4)
    step[:3, :3] = (
        np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
        @ np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
        @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    )
    step[:3, 3] = x[3:]
    return step


def multiscale_icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    guess: np.ndarray,
    settings: BaselineSettings,
    oriented: bool = True,
    indices: dict | None = None,
) -> tuple[np.ndarray, IcpResult]:
    """Point-to-plane ICP (point_to_plane_icp) at each of settings.icp_distances_m in turn, each from the previous
    result: at the distances above settings.normal_check_above_m with its normal check (settings.min_normal_cos), at
    the others pairing as Open3D's registration_icp does. Not registration_icp itself: it sums its steps in an order
    that changes from run to run (point_to_plane_step). One radius index serves the checked scales, one the others;
    one nearest-point index serves them all (TargetIndex). At every scale but the finest a source of more than
    COARSE_SOURCE_POINTS points registers every k-th of them only (coarse_source).

    oriented: whether target's normals face its sensors like the source's (False for re-estimated map normals).
    indices: the target's TargetIndex by search kind and reach, kept by a caller that registers many sources to one
    target so that its index is built once (None: built for this call).
    Returns (transform [4, 4] mapping source into target's frame, the IcpResult of the finest scale)."""
    transform, result = np.asarray(guess, np.float64), None
    indices = {} if indices is None else indices
    checked = [d for d in settings.icp_distances_m if d > settings.normal_check_above_m]
    coarse = coarse_source(source)
    for distance in settings.icp_distances_m:
        check = distance in checked
        reach = max(checked if check else [d for d in settings.icp_distances_m if d not in checked])
        key = (check if TargetIndex.searches_radius(len(target.points), reach) else "nearest", reach)
        if key not in indices:
            indices[key] = TargetIndex(target, reach)
        scan = source if distance == settings.icp_distances_m[-1] else coarse
        result = point_to_plane_icp(
            scan,
            target,
            transform,
            distance,
            settings.icp_iterations,
            settings.min_normal_cos if check else None,
            oriented,
            indices[key],
        )
        transform = result.transformation
    if settings.min_direction_share > 0:
        held = held_along_weak_directions(
            source,
            target,
            np.asarray(guess, np.float64),
            np.asarray(transform),
            settings.min_direction_share,
            indices[key],
        )
        if held is not transform:
            result = dataclasses.replace(result, transformation=held)
            transform = held
    return np.asarray(transform), result


# Consecutive raw sweeps (40k points each on the 0.1 m grid) spent most of a chain link's time in the nearest-point
# searches of every point at every scale; a quarter of the points finds the pose as well at all but the finest
# scale, which uses every point (synthetic 64-beam sweeps: the same chain to 0.1 mm, links 1.8x faster).
COARSE_SOURCE_POINTS = 10_000


def coarse_source(source: o3d.geometry.PointCloud) -> o3d.geometry.PointCloud:
    """source itself when it has at most COARSE_SOURCE_POINTS points, else every k-th of its points (and normals),
    k the smallest that leaves at most that many: deterministic, and the keyframes of a LIO front-end (a few
    thousand points) register as they are."""
    every = -(-len(source.points) // COARSE_SOURCE_POINTS)
    return source if every <= 1 else source.uniform_down_sample(every)


def correction_m(guess: np.ndarray, transform: np.ndarray) -> float:
    """How far [m] an ICP result transform [4, 4] moves the scan's origin from where its guess [4, 4] put it
    (both map the scan into the same target frame): the gates on chain links and loop closures."""
    return float(np.linalg.norm((np.linalg.inv(guess) @ transform)[:3, 3]))


def information(source, target, transform, settings: BaselineSettings) -> np.ndarray:
    """Open3D's get_information_matrix_from_point_clouds (the 6x6 information of the edge source -> target at
    transform [4, 4], from the target points paired within information_distance_m), its sums taken in a fixed order:
    Open3D's threaded sum changes the last bits from run to run (point_to_plane_step)."""
    distance = settings.information_distance_m
    nearest, _ = TargetIndex(target, distance).nearest(transform_points(np.asarray(source.points), transform), distance)
    points = np.ascontiguousarray(np.asarray(target.points)[nearest[nearest >= 0]].T)  # [3, N]
    # Each pair adds G^T G, G = [[p]x^T, I] (3 x 6) at its target point p: [[|p|^2 I - p p^T, [p]x], [[p]x^T, I]].
    x, y, z = points.sum(axis=1)
    outer = np.stack([(row * points).sum(axis=1) for row in points])  # sum of p p^T
    information = np.zeros((6, 6))
    information[:3, :3] = np.eye(3) * np.trace(outer) - outer
    information[:3, 3:] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    information[3:, :3] = information[:3, 3:].T
    information[3:, 3:] = np.eye(3) * points.shape[1]
    return information


def direction_shares(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """How well point-to-plane pairs fix each of the six directions of a pose correction.

    points [N, 3]: the source points moved onto the target; normals [N, 3]: their partners' normals. The Hessian
    of the point-to-plane residuals, J^T J / N with J = [(p - c) x n, n] (a correction about the points' centroid c,
    its rotation in metres of arc at the points' RMS distance L from c), so that each eigenvalue is the share of the
    pairs' normal energy along its eigenvector: a translation that every normal faces has a share of about 1/3 in an
    open scene; one that no normal faces (along a tunnel, a straight street between parallel walls) about 0.
    Returns (shares [6] ascending, eigenvectors [6, 6] (columns; rotation [m], translation [m]), c [3], L)."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    lever = float(np.sqrt(np.mean(np.einsum("ij,ij->i", centred, centred)))) or 1.0
    jacobians = np.hstack([np.cross(centred, normals) / lever, normals])  # [N, 6]
    shares, vectors = np.linalg.eigh(jacobians.T @ jacobians / len(points))
    return shares, vectors, centroid, lever


def held_along_weak_directions(
    source, target, guess: np.ndarray, transform: np.ndarray, min_share: float, index: TargetIndex
) -> np.ndarray:
    """ICP's transform [4, 4] with its correction of the guess [4, 4] removed along every direction that its final
    pairs fix with a share below min_share (direction_shares), then HELD_STEPS point-to-plane steps in the other
    directions only: along a weak direction the geometry does not say where the scan is, and ICP's answer is where
    its start, noise and the map's ends led it, so the guess (the odometry's motion, the chain's pose) stays. The
    transform itself (the same object) where no direction is that weak.
    source, target: the Open3D clouds ICP registered (target with normals); index: a TargetIndex of target reaching
    its finest scales' distance."""
    pairs = _pairs(source, target, transform, index)
    if pairs is None:
        return transform
    shares, vectors, centroid, lever = direction_shares(pairs[0], pairs[2])
    weak, strong = vectors[:, shares < min_share], vectors[:, shares >= min_share]
    if not weak.shape[1]:
        return transform
    motion = _small_motion(transform @ np.linalg.inv(guess), centroid, lever)
    held = _motion_matrix(motion - weak @ (weak.T @ motion), centroid, lever) @ guess
    for _ in range(HELD_STEPS):  # the strong directions settle again with the weak ones held
        pairs = _pairs(source, target, held, index)
        if pairs is None:
            break
        points, partners, normals = pairs
        jacobians = np.hstack([np.cross(points - centroid, normals) / lever, normals]) @ strong  # [N, 6 - W]
        residuals = np.einsum("ij,ij->i", points - partners, normals)
        step = -strong @ np.linalg.solve(jacobians.T @ jacobians, jacobians.T @ residuals)
        held = _motion_matrix(step, centroid, lever) @ held
    return held


HELD_STEPS = 3  # Gauss-Newton steps in the strong directions after the weak ones are held


def _pairs(source, target, transform: np.ndarray, index: TargetIndex):
    """(source points moved by transform [N, 3], their nearest target points [N, 3] and normals [N, 3]) within the
    index's reach, or None for fewer than six pairs."""
    points = np.asarray(source.points) @ transform[:3, :3].T + transform[:3, 3]
    nearest, _ = index.nearest(points, index.max_distance)
    paired = nearest >= 0
    if paired.sum() < 6:
        return None
    return points[paired], np.asarray(target.points)[nearest[paired]], np.asarray(target.normals)[nearest[paired]]


def _small_motion(motion: np.ndarray, centroid: np.ndarray, lever: float) -> np.ndarray:
    """A rigid motion [4, 4] (target frame) -> [6]: its rotation vector about centroid [3] in metres of arc at lever
    [m], then its translation (direction_shares' coordinates)."""
    about = np.eye(4)
    about[:3, 3] = centroid
    local = np.linalg.inv(about) @ motion @ about
    return np.r_[Rotation.from_matrix(local[:3, :3]).as_rotvec() * lever, local[:3, 3]]


def _motion_matrix(motion: np.ndarray, centroid: np.ndarray, lever: float) -> np.ndarray:
    """_small_motion's inverse: [6] -> [4, 4]."""
    local = np.eye(4)
    local[:3, :3] = Rotation.from_rotvec(motion[:3] / lever).as_matrix()
    local[:3, 3] = motion[3:]
    about = np.eye(4)
    about[:3, 3] = centroid
    return about @ local @ np.linalg.inv(about)
