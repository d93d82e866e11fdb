"""The classical baseline: Open3D scan-to-map ICP, then a pose graph with loop closures.

What a user reaches for before a neural method, built the way LiDAR odometry back-ends are (docs/evaluation.md,
"The classical baseline"), starting from the initial (odometry) poses:
1. a scan-to-map chain: each scan is registered by multi-scale point-to-plane ICP to a local map of the
   `window` scans before it (already registered), from the odometry's increment as the initial guess. Scan to
   map is far more accurate than scan to scan on sparse keyframes (a few thousand points each), and every
   registration starts from the odometry's relative motion only, so the chain does not depend on how far the
   odometry drifted overall (measured on real keyframes: two starts 1.5 m apart give chains 1 cm apart); a link
   that moves the scan more than `max_link_correction_m` from that increment keeps the increment, and a chain
   whose links overlap their local maps too little is given up (`chain_min_median_overlap`: keyframes too far
   apart for ICP; steps 2 and 3 are skipped and step 4 starts from the input). At their coarse
   scales the ICPs here pair points only where their normals agree (`point_to_plane_icp`: thin walls). With
   `keep_input_tilt` (an IMU-aided odometry's input) every link keeps the input's up axis, so that the links' pitch
   errors do not bow the route (docs/evaluation.md, "Keeping the input's tilt"). Whether the input's tilt is to be
   trusted, the data decides: the chain runs twice, keeping the input's up axis and free, and the one whose raw map
   is crisper goes on (a tie keeps the input's tilt: an IMU-aided odometry's roll and pitch do not drift, a
   LiDAR-only odometry's do, and then the chain that keeps them blurs the map; `choose_chain`);
2. a pose graph on the chain's poses: one edge per consecutive pair (the chain's relative pose), and
   loop-closure edges between scans at least `window` apart that lie within `loop_radius_m` IN THE CHAIN'S
   FRAME (candidates found in a drifted frame are wrong or far off), each registered by multi-scale ICP
   (`loop_icp_distances_m`, without the chain's coarsest scale) and kept only when its fitness (overlap
   fraction) reaches `min_loop_fitness` and it moves the scan by at most `max_loop_correction_m` from where the
   chain puts it; loop edges are "uncertain", so the line process may prune them. Where ICP found too little
   overlap and no closure joins the same two stretches of the route, the chain may have drifted beyond ICP's
   reach: the nearest such pair per scan is registered again from FPFH features + RANSAC (`global_registration`)
   and kept, as a certain edge, within the drift a LiDAR odometry can build up over the path between the two
   scans (`loop_drift_fraction`);
3. Levenberg-Marquardt `global_optimization`, scan 0 held fixed;
4. `map_rounds` rounds of multi-view refinement: each scan is registered again, by point-to-plane ICP at
   `map_icp_distances_m`, to the map of the OTHER scans (voxel-downsampled, normals re-estimated). A round has two
   halves, the even scans against the odd scans' map, then the odd against the even, so that no scan meets its own
   points and one map (one KD-tree) serves half the scans. The gates of the loop closures apply. This is what makes
   the map crisp: the chain and the graph only align scans in pairs or to a few neighbours, and their errors of
   about a centimetre per link add up (measured on real keyframes: docs/evaluation.md). The rounds start from the
   crisper of the graph's and the chain's poses (a tie keeps the graph's), the input's only where the chain was
   given up: the rounds keep their start's route-long shape, and the input's is its drift (docs/evaluation.md,
   "Where the refinement starts").

Information matrices are Open3D's `get_information_matrix_from_point_clouds`, and ICP's steps its point-to-plane
estimation, both summed here in a fixed order (`_information`, `_point_to_plane_step`): Open3D sums them in parallel
in an order that changes from call to call, and the same input must give the same poses bit for bit. Open3D's
pose-graph convention: node s
holds T_world_scan[s]; an edge (source i, target j) holds T_j^-1 T_i, the ICP transform that maps scan i's
points into scan j's frame.

`register_sequence` is the algorithm (arrays in, poses out); its command-line edge is neld_jax.commands.baseline.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable, NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from neld_jax import judge
from neld_jax.data.feature_registration import fpfh_features, ransac_alignment
from neld_jax.geometry import nearest_rotations, register_scans, transform_points, with_up_axis_of

logger = logging.getLogger(__name__)
_reg = o3d.pipelines.registration


@dataclasses.dataclass(frozen=True)
class BaselineSettings:
    """The baseline's settings (config.baseline); metres unless named otherwise."""

    voxel_size_m: float = 0.1  # scans are downsampled to this grid before ICP
    normal_radius_m: float = 0.5  # normal estimation radius (LiDAR scans are sparse: at least 0.5 m)
    window: int = 10  # scans in the local map of the scan-to-map chain; loop closures are at least this far apart
    icp_distances_m: tuple = (1.0, 0.5, 0.25, 0.1)  # correspondence distances of the multi-scale ICP, coarse first
    icp_iterations: int = 30  # per scale
    # At the ICP scales above normal_check_above_m, points pair only where their normals agree this well (cosine):
    # at thin walls seen from both sides Open3D's plain nearest-neighbour pairs slide scans by the wall's thickness
    # (point_to_plane_icp). The finer scales pair as Open3D does: their distances do not reach across a wall, and
    # the check there cost accuracy (hard synthetic: 0.52 -> 1.0-1.1 mm ATE with it at every scale, cosine 0-0.5).
    min_normal_cos: float = 0.5
    normal_check_above_m: float = 0.25
    min_chain_fitness: float = 0.1  # below this overlap a chain link keeps the odometry's increment (and warns)
    # Scan-to-map ICP between keyframes that overlap their local map this little neither holds nor can be checked: on
    # MulRan Riverside02 (keyframes 7-8 m apart on roads, median overlap 19-20 %) the links slid by up to 8.6 m or
    # kept the odometry's increment (87-200 of the links), the chains bent 27 and 61 m and the run refused them after
    # 158-273 s of ICP; the handheld sequences' chains overlap 74-79 % (median) and keep no link. From
    # chain_check_links links on, once the links' median overlap falls below chain_min_median_overlap, the chain is
    # given up, the pose graph skipped, and the refinement starts from the input (what the run's refinement_start
    # chose there anyway). 0.4 lies midway between Riverside02's median over its first 30 links (16 and 31 %) and the
    # lowest running median of the handheld and long synthetic chains (52-77 %). 0 switches it off.
    chain_min_median_overlap: float = 0.4
    chain_check_links: int = 30
    # A chain link whose ICP result moves the scan more than this from the odometry's increment keeps the increment
    # (and warns): in corridors and stairwells ICP slides along the free axis with a good overlap (measured on
    # HKU_2: two links jumped 0.84 and 1.9 m between keyframes 0.2 m apart; docs/evaluation.md).
    max_link_correction_m: float = 0.5
    loop_radius_m: float = 10.0  # loop-closure candidates: scans closer than this in the chain's frame
    max_loops_per_scan: int = 4  # the nearest candidates only: dense trajectories give thousands of pairs
    min_loop_fitness: float = 0.3  # loop closures that overlap less are not added
    # Loop closures start from the chain, which is within dm of them, and corrections above max_loop_correction_m are
    # dropped anyway: the 1 m scale only cost time (HKU_2: 1018 candidates in 57 s instead of about 180 s, map as
    # crisp: entropy -3.408 against -3.405).
    loop_icp_distances_m: tuple = (0.5, 0.25, 0.1)
    # Loop closures whose ICP result moves scan i more than this from where the chain puts it (relative to j) are
    # not added: in corridors ICP slides along the free axis and still overlaps well (docs/evaluation.md).
    max_loop_correction_m: float = 0.2
    # A loop candidate whose ICP from the chain overlaps less than min_loop_fitness (the chain drifted beyond ICP's
    # basin: 4.5 m at the long synthetic route's loop), over a path long enough for loop_drift_fraction of it to
    # exceed max_loop_correction_m, and with no kept closure between the same stretches of the route, is registered
    # again from FPFH features + RANSAC, then multi-scale ICP (global_icp_distances_m), for at most
    # global_loops_per_scan of each scan's candidates, the nearest. Such a closure is kept when it overlaps at least
    # min_loop_fitness and moves the scan at most max_loop_correction_m + loop_drift_fraction x the chain's path
    # between the two scans (the drift a LiDAR odometry builds up, about 1 % of the distance travelled). Candidates
    # whose ICP overlapped well but slid (corridors) are not tried again: a slide is no drift. 0 switches it off.
    global_loops_per_scan: int = 1
    global_voxel_m: float = 0.5  # the features' grid: coarser than ICP's, for speed and repeatable neighbourhoods
    global_feature_radius_m: float = 2.5  # FPFH radius (5 voxels)
    global_icp_distances_m: tuple = (1.0, 0.5, 0.25, 0.1)
    loop_drift_fraction: float = 0.01
    global_seed: int = 0  # RANSAC's random draws (Open3D's global seed), for repeatable runs
    # RANSAC stops at 99.9 % confidence or after this many draws: pairs that share no surface (most candidates that
    # failed ICP on real data: rooms either side of a wall) run to the cap.
    global_ransac_iterations: int = 20000
    information_distance_m: float = 0.25  # correspondence distance of the information matrices and the pruning
    edge_prune_threshold: float = 0.25
    # Multi-view refinement after the graph (module docstring, step 4); 0 switches it off. On HKU_2 the rounds took
    # the map's entropy -3.405 -> -3.480 -> -3.491 -> -3.493, about 40-65 s each on 2 cores (docs/evaluation.md).
    map_rounds: int = 2
    map_icp_distances_m: tuple = (0.25, 0.1)
    # The ICP target: the map_gather_points map points nearest to each scan point and within map_gather_m of it
    # (one KD-tree query); 16 points at the 0.1 m grid cover a plane to about 0.2 m around each scan point.
    map_gather_points: int = 16
    map_gather_m: float = 0.5
    # The judge of the choices above (which chain, where the rounds start): the raw map's mean map entropy at this
    # radius over this many query points (the run's eval.crispness_radius_m / crispness_queries)
    crispness_radius_m: float = 0.3
    crispness_queries: int = 10_000

    @classmethod
    def from_config(cls, config) -> "BaselineSettings":
        """From a run's config: config.baseline's fields and the judge's (config.eval's crispness settings); the
        rest keep their defaults."""
        fields = dict(config.baseline)
        unknown = set(fields) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"config.baseline: unknown field(s) {sorted(unknown)}")
        return cls(**fields, crispness_radius_m=float(config.eval.crispness_radius_m),
                   crispness_queries=int(config.eval.crispness_queries))


def _prepare_scan(points: np.ndarray, voxel_size: float, normal_radius: float) -> o3d.geometry.PointCloud:
    """points: [N, 3] sensor frame -> voxel-downsampled Open3D cloud with normals (for point-to-plane)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if voxel_size > 0:
        cloud = cloud.voxel_down_sample(voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    # Normals face the sensor (at the origin of the scan frame); ICP does not need it, but it is cheap.
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


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
        self._radius = self.max_distance <= self.RADIUS_SEARCH_MAX_M and len(points) <= self.RADIUS_SEARCH_MAX_POINTS
        if self._radius:
            self._search.hybrid_index(self.max_distance)
        else:
            self._search.knn_index()
        self._last = None  # (distance, points, nearest, squared) of the last search

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
        return np.where(squared <= distance ** 2, nearest, -1), squared


def point_to_plane_icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, guess: np.ndarray,
                       distance: float, max_iterations: int, min_normal_cos: float | None, oriented: bool,
                       index: TargetIndex | None = None) -> IcpResult:
    """Point-to-plane ICP whose correspondences must also agree in normal direction.

    Open3D's registration_icp pairs each source point with its nearest target point within `distance`, whatever the
    surfaces' orientations. At a thin wall seen from both sides (a gate, a door) that pairs one face with the other
    and slides the scan by the wall's thickness, to a pose that overlaps BETTER than the true one (measured on the
    long synthetic route: 0.3-0.4 m at 6 of 199 chain links, docs/evaluation.md). Here a pair counts only when the
    normals' cosine (after moving the source) is at least min_normal_cos, |cosine| when `oriented` is False (target
    normals of unknown sign); min_normal_cos None pairs as Open3D's registration_icp does. Open3D does the search
    (index: a TargetIndex of target, built here if None); the point-to-plane step is Open3D's, with its sums in a
    fixed order (_point_to_plane_step), so that a run repeats bit for bit. Stops like Open3D's
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
            cosines = np.einsum("ij,ij->i", source_normals[within] @ transform[:3, :3].T,
                                target_normals[nearest[within]])
            compatible = np.zeros_like(within)
            compatible[within] = (cosines if oriented else np.abs(cosines)) >= min_normal_cos
        fitness = float(within.mean()) if len(within) else 0.0
        rmse = float(np.sqrt(np.mean(squared[compatible]))) if compatible.any() else 0.0
        result = IcpResult(transform.copy(), fitness, rmse, int(compatible.sum()))
        converged = previous is not None and (abs(fitness - previous.fitness) < 1e-6
                                              and abs(rmse - previous.inlier_rmse) < 1e-6)
        if converged or result.num_correspondences < 6 or iteration == max_iterations:
            return result
        previous = result
        paired = nearest[compatible]
        transform = _point_to_plane_step(moved[compatible], target_points[paired], target_normals[paired]) @ transform
    return result


def _point_to_plane_step(points: np.ndarray, target_points: np.ndarray, target_normals: np.ndarray) -> np.ndarray:
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
    step[:3, :3] = (np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
                    @ np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
                    @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]]))
    step[:3, 3] = x[3:]
    return step


def multiscale_icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, guess: np.ndarray,
                   settings: BaselineSettings, oriented: bool = True) -> tuple[np.ndarray, IcpResult]:
    """Point-to-plane ICP (point_to_plane_icp) at each of settings.icp_distances_m in turn, each from the previous
    result: at the distances above settings.normal_check_above_m with its normal check (settings.min_normal_cos), at
    the others pairing as Open3D's registration_icp does. Not registration_icp itself: it sums its steps in an order
    that changes from run to run (_point_to_plane_step). One index serves the checked scales, one the others.

    oriented: whether target's normals face its sensors like the source's (False for re-estimated map normals).
    Returns (transform [4, 4] mapping source into target's frame, the IcpResult of the finest scale)."""
    transform, result, indices = np.asarray(guess, np.float64), None, {}
    checked = [d for d in settings.icp_distances_m if d > settings.normal_check_above_m]
    for distance in settings.icp_distances_m:
        check = distance in checked
        if check not in indices:
            group = checked if check else [d for d in settings.icp_distances_m if d not in checked]
            indices[check] = TargetIndex(target, max(group))
        result = point_to_plane_icp(source, target, transform, distance, settings.icp_iterations,
                                    settings.min_normal_cos if check else None, oriented, indices[check])
        transform = result.transformation
    return np.asarray(transform), result


def correction_m(guess: np.ndarray, transform: np.ndarray) -> float:
    """How far [m] an ICP result transform [4, 4] moves the scan's origin from where its guess [4, 4] put it
    (both map the scan into the same target frame): the gates on chain links and loop closures."""
    return float(np.linalg.norm((np.linalg.inv(guess) @ transform)[:3, 3]))


def _progress_bar(what: str, progress: bool, iterable=None, total: int | None = None):
    """A tqdm bar over the scans or pairs of one step of the baseline (minutes on real recordings), off unless
    `progress`."""
    from tqdm.auto import tqdm  # an effect at the edge, as train.fit's bar

    return tqdm(iterable, total=total, desc=f"baseline: {what}", unit=" registrations", disable=not progress,
                dynamic_ncols=True)


def scan_to_map_chain(clouds: list, init_poses: np.ndarray, settings: BaselineSettings, keep_input_tilt: bool = False,
                      deadline: float | None = None, progress: bool = False) -> tuple[np.ndarray | None, np.ndarray]:
    """Register each scan to the local map of the `settings.window` scans before it.

    clouds: S Open3D clouds (sensor frame, with normals); init_poses: [S, 4, 4] sensor -> world.
    Returns (poses [S, 4, 4] with poses[0] = init_poses[0], fitness [S] of each link, fitness[0] = 1); with
    keep_input_tilt every pose has its init_poses' up axis (geometry.with_up_axis_of). A link
    whose fitness is below settings.min_chain_fitness, or whose ICP moved the scan further than
    settings.max_link_correction_m, keeps the odometry's increment; one warning per reason lists those scans.
    poses is None when the chain was given up (settings.chain_min_median_overlap, or the time.perf_counter() value
    `deadline` passed before its last link; one warning says which); fitness then holds the links registered
    before, NaN after. progress: a progress bar over the links.
    """
    poses = [np.asarray(init_poses[0], np.float64)]
    fitness = np.ones(len(clouds))
    kept = {"overlap": [], "slide": []}  # links that kept the odometry's increment, by reason: one warning each
    links = _progress_bar(f"scan-to-map chain ({'the input' if keep_input_tilt else 'its own'} tilt)", progress,
                          range(1, len(clouds)))
    for s in links:
        if s - 1 >= max(settings.chain_check_links, 1) and np.median(fitness[1:s]) < settings.chain_min_median_overlap:
            logger.warning("baseline: the first %d chain links overlap their local maps by %.2f%% (median; less "
                           "than chain_min_median_overlap=%.0f%%: keyframes too far apart for scan-to-map ICP): the "
                           "chain is given up, the pose graph skipped, and the multi-view refinement starts from the "
                           "input poses: it sharpens the map locally, but drift the input poses gather along the "
                           "route stays in the answer",
                           s - 1, 100 * np.median(fitness[1:s]), 100 * settings.chain_min_median_overlap)
            fitness[s:] = np.nan
            break
        if deadline is not None and time.perf_counter() > deadline:
            # A half-registered chain cannot feed the pose graph, and the rounds would stop at once anyway.
            logger.warning("baseline: the run's deadline passed after %d of the %d chain links: the chain is given up, "
                           "the pose graph skipped, and the input poses are the baseline's start", s - 1,
                           len(clouds) - 1)
            fitness[s:] = np.nan
            break
        guess = poses[s - 1] @ np.linalg.inv(init_poses[s - 1]) @ init_poses[s]  # the odometry's increment
        if keep_input_tilt:
            guess = with_up_axis_of(guess, init_poses[s])
        local_map = o3d.geometry.PointCloud()
        for k in range(max(0, s - settings.window), s):
            local_map += o3d.geometry.PointCloud(clouds[k]).transform(poses[k])  # normals rotate along
        transform, result = multiscale_icp(clouds[s], local_map, guess, settings)
        fitness[s] = result.fitness
        moved_m = correction_m(guess, transform)
        if result.fitness < settings.min_chain_fitness:
            kept["overlap"].append(f"{s} ({100 * result.fitness:.1f}%)")
            transform = guess
        elif moved_m > settings.max_link_correction_m:
            kept["slide"].append(f"{s} ({moved_m:.2f} m)")
            transform = guess
        poses.append(with_up_axis_of(transform, init_poses[s]) if keep_input_tilt else transform)
    links.close()
    if kept["overlap"]:
        logger.warning("baseline: %d scan(s) overlap the map of the %d scans before them by less than "
                       "min_chain_fitness=%.0f%% and keep the odometry's increment: %s", len(kept["overlap"]),
                       settings.window, 100 * settings.min_chain_fitness, _first(kept["overlap"]))
    if kept["slide"]:
        logger.warning("baseline: ICP moved %d scan(s) further than max_link_correction_m=%.2g m from the odometry's "
                       "increment (a slide along a featureless direction?); they keep the increment: %s",
                       len(kept["slide"]), settings.max_link_correction_m, _first(kept["slide"]))
    return (np.stack(poses) if len(poses) == len(clouds) else None), fitness


def _first(items: list[str], count: int = 12) -> str:
    """The first `count` items, comma-separated, and how many more (for one log line)."""
    more = f" and {len(items) - count} more" if len(items) > count else ""
    return ", ".join(items[:count]) + more


def candidate_pairs(positions: np.ndarray, loop_radius_m: float, max_loops_per_scan: int = 4,
                    min_index_gap: int = 2) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Scan pairs to register. positions: [S, 3].

    Returns (odometry pairs [(s, s + 1)], loop pairs [(i, j)] with j >= i + min_index_gap and
    |p_i - p_j| < radius). Each scan i keeps at most `max_loops_per_scan` partners j, the nearest ones.
    """
    num_scans = len(positions)
    odometry = [(s, s + 1) for s in range(num_scans - 1)]
    distances = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
    within = [(i, j) for i in range(num_scans) for j in range(i + max(min_index_gap, 1), num_scans)
              if distances[i, j] < loop_radius_m]
    return odometry, _nearest_per_scan(within, positions, max_loops_per_scan)


def _passes_loop_gates(result, moved_m: float, settings: BaselineSettings, drift_allowance_m: float = 0.0) -> bool:
    """A loop closure's (or a multi-view refinement's) ICP result is kept when it overlaps enough and moves the scan
    at most max_loop_correction_m (+ drift_allowance_m, for global closures) from where it started (moved_m)."""
    return not (result.fitness < settings.min_loop_fitness
                or moved_m > settings.max_loop_correction_m + drift_allowance_m)


def _information(source, target, transform, settings: BaselineSettings) -> np.ndarray:
    """Open3D's get_information_matrix_from_point_clouds (the 6x6 information of the edge source -> target at
    transform [4, 4], from the target points paired within information_distance_m), its sums taken in a fixed order:
    Open3D's threaded sum changes the last bits from run to run (_point_to_plane_step)."""
    distance = settings.information_distance_m
    nearest, _ = TargetIndex(target, distance).nearest(transform_points(np.asarray(source.points), transform),
                                                       distance)
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


def _fpfh(cloud: o3d.geometry.PointCloud, settings: BaselineSettings):
    """cloud (sensor frame) -> (the cloud on the global_voxel_m grid with normals, its FPFH features)."""
    return fpfh_features(cloud, settings.global_voxel_m, settings.global_feature_radius_m)


def global_registration(source, target, source_features, target_features, settings: BaselineSettings):
    """FPFH + RANSAC, then multi-scale ICP at global_icp_distances_m: registration from no initial guess.

    source, target: Open3D clouds with normals (sensor frames); source_features, target_features: their
    (coarse cloud, FPFH features) from _fpfh. Returns (transform [4, 4] mapping source into target's frame, the
    IcpResult of the finest ICP scale)."""
    guess = ransac_alignment(source_features, target_features, settings.global_voxel_m,
                             settings.global_ransac_iterations, settings.global_seed)
    refine = dataclasses.replace(settings, icp_distances_m=settings.global_icp_distances_m)
    return multiscale_icp(source, target, guess, refine)


class LoopClosures(NamedTuple):
    """What loop_closed_graph did: candidates registered by ICP, closures kept (all), pairs registered globally
    and closures kept of those."""

    tried: int
    kept: int
    global_tried: int
    global_kept: int


def loop_closed_graph(clouds: list, chain_poses: np.ndarray, settings: BaselineSettings, progress: bool = False
                      ) -> tuple[np.ndarray, LoopClosures]:
    """The pose graph of the chain plus loop closures, optimised (scan 0 fixed).

    Returns (poses [S, 4, 4] with poses[0] = chain_poses[0], what the loop closures did). progress: a progress bar
    over the loop-closure candidates."""
    graph = _reg.PoseGraph()
    for pose in chain_poses:
        graph.nodes.append(_reg.PoseGraphNode(pose))
    positions = chain_poses[:, :3, 3]
    odometry_pairs, loop_pairs = candidate_pairs(positions, settings.loop_radius_m, settings.max_loops_per_scan,
                                                 min_index_gap=settings.window)
    for s, following in odometry_pairs:  # the chain's links: edge (source s + 1, target s) maps s + 1 into s
        relative = np.linalg.inv(chain_poses[s]) @ chain_poses[following]
        information = _information(clouds[following], clouds[s], relative, settings)
        if information[5, 5] <= 0:  # no correspondences at all: keep the link, weakly, so the graph stays connected
            information = np.eye(6)
        graph.edges.append(_reg.PoseGraphEdge(following, s, relative, information, uncertain=False))
    # The chain's path length up to each scan: a global loop closure may correct loop_drift_fraction of the path.
    path_m = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])

    def drift_allowance_m(i: int, j: int) -> float:
        return settings.loop_drift_fraction * abs(path_m[j] - path_m[i])

    kept = kept_global = 0
    drifted, closed = [], []  # loop pairs for the global registration (below); those ICP closed
    loop_icp = dataclasses.replace(settings, icp_distances_m=settings.loop_icp_distances_m)
    for i, j in _progress_bar("loop closures", progress, loop_pairs):
        guess = np.linalg.inv(chain_poses[j]) @ chain_poses[i]
        transform, result = multiscale_icp(clouds[i], clouds[j], guess, loop_icp)
        moved_m = correction_m(guess, transform)
        if not _passes_loop_gates(result, moved_m, settings):
            # Too little overlap where the chain can have drifted further than ICP's closures may move a scan: a
            # case for the global registration. Over a short path a failed ICP means the scans share too little.
            if result.fitness < settings.min_loop_fitness and drift_allowance_m(i, j) > settings.max_loop_correction_m:
                drifted.append((i, j))
            continue
        graph.edges.append(_reg.PoseGraphEdge(i, j, transform, _information(clouds[i], clouds[j], transform, settings),
                                              uncertain=True))
        closed.append((i, j))
        kept += 1
    features = {}
    # Where ICP closed a loop between the same two stretches of the route, the chain is within ICP's reach there:
    # a failed neighbouring pair only lacks overlap (HKU_2 without this test: 196 global registrations, none kept).
    closed = np.array(closed, dtype=np.int64).reshape(-1, 2)
    near_closed = [np.any((np.abs(closed[:, 0] - i) <= settings.window) & (np.abs(closed[:, 1] - j) <= settings.window))
                   for i, j in drifted]
    unexplained = [pair for pair, explained in zip(drifted, near_closed) if not explained]
    global_pairs = _nearest_per_scan(unexplained, positions, settings.global_loops_per_scan)
    for i, j in global_pairs:
        for k in (i, j):
            if k not in features:
                features[k] = _fpfh(clouds[k], settings)
        guess = np.linalg.inv(chain_poses[j]) @ chain_poses[i]
        transform, result = global_registration(clouds[i], clouds[j], features[i], features[j], settings)
        if not _passes_loop_gates(result, correction_m(guess, transform), settings, drift_allowance_m(i, j)):
            continue
        # Certain: the line process would prune a closure this far from the chain (its residual is the whole
        # drift), and the gates above are what vouch for it.
        graph.edges.append(_reg.PoseGraphEdge(i, j, transform, _information(clouds[i], clouds[j], transform, settings),
                                              uncertain=False))
        kept += 1
        kept_global += 1
    option = _reg.GlobalOptimizationOption(max_correspondence_distance=settings.information_distance_m,
                                           edge_prune_threshold=settings.edge_prune_threshold,
                                           preference_loop_closure=1.0, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        _reg.global_optimization(graph, _reg.GlobalOptimizationLevenbergMarquardt(),
                                 _reg.GlobalOptimizationConvergenceCriteria(), option)
    optimized = np.stack([np.asarray(node.pose) for node in graph.nodes])
    return optimized, LoopClosures(len(loop_pairs), kept, len(global_pairs), kept_global)


def _nearest_per_scan(pairs: list[tuple[int, int]], positions: np.ndarray, per_scan: int) -> list[tuple[int, int]]:
    """Of the pairs [(i, j)], each scan i's `per_scan` nearest (positions [S, 3]; ties by j), in (i, j) order."""
    partners_of: dict[int, list[int]] = {}
    for i, j in pairs:
        partners_of.setdefault(i, []).append(j)
    chosen = []
    for i in sorted(partners_of):
        partners = sorted(partners_of[i], key=lambda j: (float(np.linalg.norm(positions[i] - positions[j])), j))
        chosen.extend((i, j) for j in sorted(partners[:max(per_scan, 0)]))
    return chosen


def _world_map(clouds: list, poses: np.ndarray, scans, settings: BaselineSettings) -> o3d.geometry.PointCloud:
    """The scans `scans` (indices) in the world frame at poses [S, 4, 4], merged, voxel-downsampled, with normals
    estimated again (averaging the normals of overlapping scans would blur or cancel them)."""
    points = register_scans([np.asarray(clouds[k].points) for k in scans], poses[list(scans)])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if settings.voxel_size_m > 0:
        cloud = cloud.voxel_down_sample(settings.voxel_size_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=settings.normal_radius_m, max_nn=30))
    return cloud


@dataclasses.dataclass(frozen=True)
class Refinement:
    """What `refine_against_map` did: rounds_done, the rounds completed, with the fraction of the last one when a
    deadline stopped it (1.4: one round and 40 % of the scans of the second); rejected, the fraction of its
    registrations the gates rejected; stopped, whether the deadline stopped it before settings.map_rounds."""

    rounds_done: float
    rejected: float
    stopped: bool


def refine_against_map(clouds: list, poses: np.ndarray, settings: BaselineSettings,
                       on_round: Callable[[int, np.ndarray], None] | None = None,
                       deadline: float | None = None, progress: bool = False) -> tuple[np.ndarray, Refinement]:
    """`settings.map_rounds` rounds of multi-view refinement (module docstring, step 4); scan 0 stays.

    clouds: S Open3D clouds (sensor frame); poses: [S, 4, 4] sensor -> world. on_round(r, poses [S, 4, 4]), when
    given, sees a copy of the poses after each round r = 1 .. map_rounds (benchmarks/baseline_rounds.py).
    deadline: a time.perf_counter() value; no scan is registered after it (each registration moves one scan against
    the others' map, so the poses between two registrations are an answer too; neld_jax.run's `baseline_deadline`).
    progress: a progress bar over the scans of all rounds. Returns (poses [S, 4, 4], Refinement)."""
    poses = np.array(poses, dtype=np.float64)
    map_icp = dataclasses.replace(settings, icp_distances_m=settings.map_icp_distances_m)
    tried = rejected = 0
    bar = _progress_bar(f"{settings.map_rounds} round(s) of multi-view refinement", progress,
                        total=settings.map_rounds * len(clouds))

    def report(rounds_done: float, stopped: bool) -> tuple[np.ndarray, Refinement]:
        bar.close()
        return poses, Refinement(round(rounds_done, 3), rejected / max(tried, 1), stopped)

    for round_index in range(1, settings.map_rounds + 1):
        visited = 0  # scans of this round registered, or skipped as the gauge, before a deadline
        for half in (0, 1):
            others = [k for k in range(len(clouds)) if k % 2 != half]
            if not others:
                continue
            if deadline is not None and time.perf_counter() > deadline:
                return report(round_index - 1 + visited / len(clouds), True)
            world = _world_map(clouds, poses, others, settings)
            world_points, world_normals = np.asarray(world.points), np.asarray(world.normals)
            tree = cKDTree(world_points)
            for s in range(half, len(clouds), 2):
                if deadline is not None and time.perf_counter() > deadline:
                    return report(round_index - 1 + visited / len(clouds), True)
                visited += 1
                bar.update()
                if s == 0:  # the gauge
                    continue
                scan_in_world = transform_points(np.asarray(clouds[s].points), poses[s])
                # The target: each scan point's nearest map points (one vectorised query; "missing" ones come back
                # as index len(world_points)).
                _, near = tree.query(scan_in_world, k=settings.map_gather_points,
                                     distance_upper_bound=settings.map_gather_m)
                near = np.unique(near[near < len(world_points)])
                tried += 1
                if len(near) < 3:
                    rejected += 1
                    continue
                target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world_points[near]))
                target.normals = o3d.utility.Vector3dVector(world_normals[near])
                # sensor -> world; the map's normals were estimated again, their signs unknown
                transform, result = multiscale_icp(clouds[s], target, poses[s], map_icp, oriented=False)
                if not _passes_loop_gates(result, correction_m(poses[s], transform), settings):
                    rejected += 1
                    continue
                poses[s] = transform
        if on_round is not None:
            on_round(round_index, poses.copy())
    return report(settings.map_rounds, False)


# A chain that keeps the input's tilt is kept unless the free chain's raw map is crisper by more than this (mean map
# entropy, nats). Measured (docs/evaluation.md, "Keeping the input's tilt"): with an IMU-aided odometry's tilt the free
# chain came out crisper by 0.012-0.030 on three real sequences, while keeping the tilt gave the better route; with
# a tilt that drifted 0.2-0.5 deg a keyframe the chain that keeps it was blurrier by 0.68-0.78.
TILT_MARGIN = 0.1


def choose_chain(chains: dict, scans: list[np.ndarray], settings: BaselineSettings) -> tuple[str, dict]:
    """Which chain goes on: {"input tilt": poses, "free": poses} (None: given up) -> (the name, {name: mean map
    entropy of its raw map}). The free chain wins only when crisper by more than TILT_MARGIN."""
    held = {name: poses for name, poses in chains.items() if poses is not None}
    if len(held) < 2:
        return next(iter(held), "free"), {}
    summaries, _ = judge.compare_maps(scans, held, settings.crispness_radius_m, settings.crispness_queries)
    entropy = {name: summary["mean_map_entropy"] for name, summary in summaries.items()}
    tilt, free = entropy["input tilt"], entropy["free"]
    chosen = "free" if tilt is not None and free is not None and free < tilt - TILT_MARGIN else "input tilt"
    return chosen, entropy


def choose_refinement_start(graph: np.ndarray, chain: np.ndarray, scans: list[np.ndarray],
                            settings: BaselineSettings) -> tuple[str, dict]:
    """Where the multi-view refinement starts: the crisper of the graph's and the chain's poses [S, 4, 4] (a tie, or
    no judge, keeps the graph) -> ("graph" | "chain", {name: mean map entropy})."""
    summaries, _ = judge.compare_maps(scans, {"graph": graph, "chain": chain}, settings.crispness_radius_m,
                                      settings.crispness_queries)
    entropy = {name: summary["mean_map_entropy"] for name, summary in summaries.items()}
    crisper = judge.crispest(summaries)
    return ("chain" if crisper == "chain" and entropy["chain"] < entropy["graph"] else "graph"), entropy


def _entropy_text(entropy: dict) -> str:
    return ", ".join(f"{name} {'-' if value is None else f'{value:.3f}'}" for name, value in entropy.items())


def register_sequence(scans: list[np.ndarray], init_poses: np.ndarray,
                      settings: BaselineSettings = BaselineSettings(),
                      on_round: Callable[[int, np.ndarray], None] | None = None,
                      deadline: float | None = None, report: dict | None = None, progress: bool = False) -> np.ndarray:
    """The baseline: the scan-to-map chains (the input's tilt kept and free; the crisper goes on), the loop-closed
    pose graph, then the multi-view refinement from the crisper of the graph and the chain (module docstring).

    scans: list of S arrays [N_i, 3] in the sensor frame; init_poses: [S, 4, 4] sensor -> world.
    on_round(r, poses [S, 4, 4]): `refine_against_map`'s, called with r = 0 and the poses the refinement starts
    from too; they are the poses returned up to the final re-anchoring on scan 0 (one rigid transform).
    deadline: a time.perf_counter() value after which the multi-view refinement registers no more scans
    (`refine_against_map`) and a chain not yet finished is given up (`scan_to_map_chain`); the pose graph always
    runs to the end. report, when given, receives what was decided and done: {"tilt": "input" | "free" (the chain
    that went on; None when both were given up), "chain_entropy": {name: entropy}, "chain_given_up",
    "refined_from": "graph" | "chain" | "input", "start_entropy": {name: entropy}, "map_rounds_done" (a fraction when
    the deadline stopped them), "stopped_at_deadline", "seconds": {step: seconds}}. progress: progress bars over
    each step's registrations.
    Returns refined poses [S, 4, 4] with pose 0 equal to init_poses[0] and orthonormal rotations.
    """
    init_poses = np.asarray(init_poses, dtype=np.float64)
    if init_poses.ndim != 3 or init_poses.shape[1:] != (4, 4):
        raise ValueError(f"init_poses must have shape [S, 4, 4], got {init_poses.shape}")
    if len(scans) != len(init_poses):
        raise ValueError(f"{len(scans)} scans but {len(init_poses)} initial poses")
    report = {} if report is None else report
    if len(scans) < 2:
        return init_poses.copy()
    clouds = prepare_clouds(scans, settings)
    seconds = report.setdefault("seconds", {})
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        t0 = time.perf_counter()
        chains, fitness = {}, {}
        for name, keep_tilt in (("input tilt", True), ("free", False)):
            chains[name], fitness[name] = scan_to_map_chain(clouds, init_poses, settings, keep_tilt, deadline, progress)
        chosen, entropy = choose_chain(chains, scans, settings)
        chain = chains[chosen]
        seconds["chains"] = time.perf_counter() - t0
        report.update(tilt=None if chain is None else ("input" if chosen == "input tilt" else "free"),
                      chain_entropy=entropy, chain_given_up=chain is None)
        if chain is None:  # given up (scan_to_map_chain warned): no graph, the refinement starts from the input
            optimized = init_poses
            report["refined_from"] = "input"
            logger.info("baseline: scan-to-map chain given up after %.1f s", seconds["chains"])
        else:
            logger.info("baseline: the chain %s (raw-map entropy: %s; median overlap %.0f%%), %.1f s for both",
                        "keeps the input's tilt" if chosen == "input tilt" else
                        "finds its own tilt: the input's drifted", _entropy_text(entropy) or "one chain held",
                        100 * np.nanmedian(fitness[chosen][1:]), seconds["chains"])
            t1 = time.perf_counter()
            optimized, loops = loop_closed_graph(clouds, chain, settings, progress)
            seconds["graph"] = time.perf_counter() - t1
            logger.info("baseline: pose graph with %d of %d loop-closure candidates (overlap >= %.0f%%), %d of them "
                        "from %d global registrations, in %.1f s", loops.kept, loops.tried,
                        100 * settings.min_loop_fitness, loops.global_kept, loops.global_tried, seconds["graph"])
        if settings.map_rounds > 0:
            # The graph's poses carry round-off in the rotations; re-orthonormalise before moving clouds with them.
            optimized = _orthonormal(optimized)
            if chain is not None:
                start, entropy = choose_refinement_start(optimized, _orthonormal(chain), scans, settings)
                report.update(refined_from=start, start_entropy=entropy)
                logger.info("baseline: the multi-view refinement starts from the %s's poses (raw-map entropy: %s)",
                            start, _entropy_text(entropy))
                optimized = _orthonormal(chain) if start == "chain" else optimized
            if on_round is not None:
                on_round(0, optimized.copy())
            t2 = time.perf_counter()
            optimized, refinement = refine_against_map(clouds, optimized, settings, on_round, deadline, progress)
            seconds["refinement"] = time.perf_counter() - t2
            logger.info("baseline: %g round(s) of multi-view refinement in %.1f s (%.0f%% of the registrations "
                        "rejected by the gates)", refinement.rounds_done, seconds["refinement"],
                        100 * refinement.rejected)
            report.update(map_rounds_done=refinement.rounds_done, stopped_at_deadline=refinement.stopped)
    # Re-anchor exactly on scan 0 (the gauge), whatever the optimiser did with the reference node.
    return anchored(optimized, init_poses[0])


def prepare_clouds(scans: list[np.ndarray], settings: BaselineSettings) -> list:
    """scans: S arrays [N_i, 3] (sensor frame) -> the S Open3D clouds every step of the baseline registers
    (settings.voxel_size_m grid, normals within settings.normal_radius_m)."""
    return [_prepare_scan(scan, settings.voxel_size_m, settings.normal_radius_m) for scan in scans]


def anchored(poses: np.ndarray, pose0: np.ndarray) -> np.ndarray:
    """poses [S, 4, 4] moved rigidly so that poses[0] is pose0 [4, 4] exactly (the gauge), rotations
    re-orthonormalised."""
    return _orthonormal(pose0 @ np.linalg.inv(poses[0]) @ poses)


def _orthonormal(poses: np.ndarray) -> np.ndarray:
    """poses [S, 4, 4] with the nearest rotations in their rotation blocks (removes an optimiser's round-off)."""
    poses = np.array(poses, dtype=np.float64)
    poses[:, :3, :3] = nearest_rotations(poses[:, :3, :3])
    return poses
