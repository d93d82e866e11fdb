"""Every input scan registered to the result: a scan that was not a keyframe starts from its interpolated
correction (neld_jax.trajectory) and is then registered to the keyframes' refined raw map by point-to-plane ICP, so
that it does not keep the odometry's error between keyframes.

The map's KD-tree and normals are built once (MapIndex); each scan registers its points on a coarse grid
(RegistrationSettings.icp_voxel_m), and many scans register together, one nearest-point search for all of them a
step (register_batch: the same poses as one at a time). A scan that cannot be registered keeps its interpolated
pose and is flagged: too few points in range, too little of it on the map (its fitness: the share of its points
near map points), or a result that moves it further from its interpolated pose than a bound. The same registration
poses the scans of another recording in a finished run's map (neld-localize). Registering in the trained field
instead (pose-only, the field frozen) was measured and lost to this (docs/evaluation.md, "Every input scan").
"""

from __future__ import annotations

import dataclasses
import logging
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from neld_jax.data.preprocess import crop_range
from neld_jax.geometry import invert_poses, register_scans, rotation_angles_deg
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)

TOO_FEW_POINTS = "too few points"
POOR_FITNESS = "poor fitness"
JUMP = "jump"
OUT_OF_TIME = "out of time"  # past the run's registration deadline (neld_jax.training.budget): not tried


@dataclasses.dataclass(frozen=True)
class RegistrationSettings:
    """How a scan is registered to the map, and when a registration is refused (metres unless named)."""

    voxel_size_m: float = 0.1  # the scan's and the map's grid
    normal_radius_m: float = 0.5
    icp_distances_m: tuple = (0.5, 0.25, 0.1)  # coarse first; the interpolated pose is within dm of the truth
    icp_iterations: int = 30  # at most, per distance
    # ICP registers one point of each cell of this grid (of the scan's points on voxel_size_m's): 2.5k of a KITTI
    # sweep's 54k, 8x faster than every point with the same ATE (docs/evaluation.md, "Every input scan")
    icp_voxel_m: float = 1.0
    icp_tolerance_m: float = 3e-3  # a distance's steps end once one moves the scan's points less than this (RMS)
    min_range_m: float = 0.5
    max_range_m: float = 80.0
    min_points: int = 100  # fewer points in range (on the grid): not registered
    fit_distance_m: float = 0.3  # a scan point within this of a map point lies on the map ...
    min_fitness: float = 0.5  # ... and a scan less of whose points do is not registered
    fit_points: int = 2048  # the fitness and residual over at most this many of the scan's points, evenly taken
    max_jump_m: float = 0.5  # a result further than this from the guess ...
    max_jump_deg: float = 5.0  # ... or turned more than this: not registered
    # Scans registered together, one nearest-point search for all of them a step; the deadline is checked between
    # batches
    batch_scans: int = 32

    @classmethod
    def from_groups(cls, data_cfg, baseline_cfg) -> "RegistrationSettings":
        """The run's range crop (data_cfg: config.data) and its map's grid (baseline_cfg: config.baseline, its
        voxel_size_m); the rest as above."""
        return cls(
            voxel_size_m=float(baseline_cfg.voxel_size_m),
            min_range_m=float(data_cfg.min_range_m),
            max_range_m=float(data_cfg.max_range_m),
        )


class ScanRegistration(NamedTuple):
    """poses [S, 4, 4]: every scan's pose in the map (the guess where it was not registered); residual_m [S] and
    fitness [S]: how its points lie on the map after ICP (fit_to_map; NaN where not tried); flag [S]: why a scan
    tried was not registered ("" registered or not tried); tried [S] bool."""

    poses: np.ndarray
    residual_m: np.ndarray
    fitness: np.ndarray
    flag: list
    tried: np.ndarray

    @property
    def registered(self) -> np.ndarray:
        """[S] bool: tried and kept."""
        return self.tried & np.array([not f for f in self.flag], bool)


def map_cloud(scans: list[np.ndarray], poses: np.ndarray, settings: RegistrationSettings):
    """The target: scans (list of [N_i, 3], sensor frames) registered with poses [K, 4, 4] on the settings' grid,
    with normals (unoriented: the map's points come from several sensors). An Open3D cloud."""
    return cloud_with_normals(register_scans(scans, poses), settings)


def cloud_with_normals(points: np.ndarray, settings: RegistrationSettings, sensor_frame: bool = False):
    """points [N, 3] -> an Open3D cloud on the settings' grid with normals (facing the origin when sensor_frame)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud = cloud.voxel_down_sample(settings.voxel_size_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=settings.normal_radius_m, max_nn=30))
    if sensor_frame:
        cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


class MapIndex(NamedTuple):
    """The target map's points [M, 3] and normals [M, 3] with their KD-tree (scipy's cKDTree), built once for every
    scan registered to it (map_index)."""

    points: np.ndarray
    normals: np.ndarray
    tree: object

    def nearest(self, points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
        """points [N, 3] -> (index [N] of the nearest map point, -1 where none lies within distance; the squared
        distance [N], inf there): baseline.TargetIndex's search, on every core (the scans are independent)."""
        found, nearest = self.tree.query(points, distance_upper_bound=distance, workers=-1)
        return np.where(np.isfinite(found), nearest, -1), found**2

    def normals_of(self, nearest: np.ndarray) -> np.ndarray:
        """nearest [N] (map point indices, -1: none) -> their normals [N, 3], zero for -1."""
        return np.where((nearest >= 0)[:, None], self.normals[nearest], 0.0)


def map_index(target, indices: dict | None = None) -> MapIndex:
    """The MapIndex of a target map (map_cloud), kept in indices (a caller's dict, None: built here) under "map"."""
    from scipy.spatial import cKDTree

    if indices is not None and "map" in indices:
        return indices["map"]
    points = np.asarray(target.points, np.float64)
    index = MapIndex(points, np.asarray(target.normals, np.float64), cKDTree(points))
    if indices is not None:
        indices["map"] = index
    return index


class ScanPoints(NamedTuple):
    """A scan made ready for registration: icp [N, 3] one point of each icp_voxel_m cell (sensor frame); fit [F, 3]
    at most fit_points of its points on voxel_size_m's grid, evenly taken (fit_to_map); None for a scan with fewer
    than min_points points there (prepare_scan)."""

    icp: np.ndarray
    fit: np.ndarray


def prepare_scan(scan: np.ndarray, settings: RegistrationSettings) -> ScanPoints | None:
    """scan [N, 3] (sensor frame) -> its ScanPoints within the range crop, or None for too few points. KISS-ICP's
    voxel grid (the first point of each cell): a third of Open3D's time on a KITTI sweep."""
    from kiss_icp.voxelization import voxel_down_sample

    points = np.ascontiguousarray(crop_range(scan, settings.min_range_m, settings.max_range_m), np.float64)
    fine = voxel_down_sample(points, settings.voxel_size_m)
    if len(fine) < settings.min_points:
        return None
    every = -(-len(fine) // settings.fit_points)
    return ScanPoints(voxel_down_sample(fine, settings.icp_voxel_m), fine[::every])


def moved_by(points: list[np.ndarray], poses: np.ndarray) -> np.ndarray:
    """B point sets (list of [N_b, 3]) each moved by its pose [B, 4, 4] -> [sum N_b, 3], concatenated."""
    return np.concatenate([p @ T[:3, :3].T + T[:3, 3] for p, T in zip(points, poses)])


def normal_equations(moved: np.ndarray, starts: np.ndarray, centres: np.ndarray, index: MapIndex, distance: float):
    """Point-to-plane ICP's Gauss-Newton system of B scans at once: moved [N, 3] their points in the map, scan b's
    from starts[b] on; centres [B, 3] where each scan's correction turns about. Each point pairs with its nearest
    map point within distance. Returns (J^T J [B, 6, 6], J^T r [B, 6], pairs [B]), the correction x = (rotation
    vector, translation)."""
    nearest, _ = index.nearest(moved, distance)
    paired, normals = nearest >= 0, index.normals_of(nearest)
    scan = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(moved)]))
    arms = moved - centres[scan]
    residuals = np.einsum("ij,ij->i", moved - index.points[nearest], normals)  # 0 where unpaired (normal 0)
    jacobians = np.hstack([np.cross(arms, normals), normals])  # [N, 6]
    jtj = np.stack([j.T @ j for j in np.split(jacobians, starts[1:])])
    jtr = np.stack([j.T @ r for j, r in zip(np.split(jacobians, starts[1:]), np.split(residuals, starts[1:]))])
    return jtj, jtr, np.add.reduceat(paired.astype(np.int64), starts)


def correction_steps(jtj: np.ndarray, jtr: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Gauss-Newton systems [B, 6, 6], [B, 6] about centres [B, 3] -> the steps [B, 4, 4] (map frame, applied on
    the left); no step where a system is singular (every pair on one plane)."""
    from scipy.spatial.transform import Rotation

    x = np.zeros((len(jtj), 6))
    for b in range(len(jtj)):  # one solve a scan: a singular one must not stop the others
        try:
            x[b] = np.linalg.solve(jtj[b], -jtr[b])
        except np.linalg.LinAlgError:
            pass
    steps = np.tile(np.eye(4), (len(jtj), 1, 1))
    steps[:, :3, :3] = Rotation.from_rotvec(x[:, :3]).as_matrix()
    steps[:, :3, 3] = centres + x[:, 3:] - np.einsum("bij,bj->bi", steps[:, :3, :3], centres)
    return steps


def point_to_plane_batch(
    points: list[np.ndarray], guesses: np.ndarray, index: MapIndex, settings: RegistrationSettings
) -> np.ndarray:
    """Point-to-plane ICP of B scans' points (list of [N_b, 3], sensor frames) from their guesses [B, 4, 4] to the
    map, at each of settings.icp_distances_m in turn: a scan's steps at a distance end after icp_iterations, once a
    step moves its points by less than icp_tolerance_m (RMS), or with fewer than six pairs. Every step searches the
    nearest map points of all scans still stepping at once; each scan's sums are its own, so a scan's pose does not
    depend on the others. Returns the poses [B, 4, 4]."""
    poses = np.array(guesses, np.float64, copy=True)
    for distance in settings.icp_distances_m:
        active = np.arange(len(points))
        for _ in range(settings.icp_iterations):
            if not len(active):
                break
            sets = [points[b] for b in active]
            moved = moved_by(sets, poses[active])
            starts = np.cumsum([0] + [len(p) for p in sets[:-1]])
            centres = poses[active, :3, 3]
            jtj, jtr, pairs = normal_equations(moved, starts, centres, index, distance)
            steps = correction_steps(jtj, jtr, centres)
            stepping = pairs >= 6
            poses[active[stepping]] = steps[stepping] @ poses[active[stepping]]
            shifts = moved_by(np.split(moved, starts[1:]), steps) - moved  # each point's move by its scan's step
            rms = np.sqrt(
                np.add.reduceat(np.einsum("ij,ij->i", shifts, shifts), starts) / np.diff(np.r_[starts, len(moved)])
            )
            active = active[stepping & (rms >= settings.icp_tolerance_m)]
    return poses


def fit_to_map(points: np.ndarray, pose: np.ndarray, target, distance_m: float, index=None) -> tuple[float, float]:
    """How a scan's points [N, 3] (sensor frame) under pose [4, 4] lie on the target map (an Open3D cloud with
    normals): (fitness: the fraction with a map point within distance_m, residual [m]: the RMS distance of those to
    their map point's plane; NaN without one). index: the target's MapIndex (None: built here)."""
    index = map_index(target) if index is None else index
    moved = points @ pose[:3, :3].T + pose[:3, 3]
    return fit_of(moved, index.nearest(moved, distance_m)[0], index)


def fit_of(moved: np.ndarray, nearest: np.ndarray, index: MapIndex) -> tuple[float, float]:
    """fit_to_map's (fitness, residual [m]) of points [N, 3] in the map paired with map points nearest [N] (-1:
    none within the distance)."""
    paired = nearest >= 0
    if not paired.any():
        return 0.0, float("nan")
    along_normal = np.einsum("ij,ij->i", moved[paired] - index.points[nearest[paired]], index.normals[nearest[paired]])
    return float(paired.mean()), float(np.sqrt(np.mean(along_normal**2)))


def pose_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """How far [m] and how much [deg] a pose [4, 4] moved, in its own frame: before^-1 after."""
    delta = invert_poses(before[None])[0] @ after
    return float(np.linalg.norm(delta[:3, 3])), float(rotation_angles_deg(delta[None, :3, :3])[0])


def register_batch(
    scans: list, guesses: np.ndarray, index: MapIndex, settings: RegistrationSettings
) -> list[tuple[np.ndarray, float, float, str]]:
    """B scans (list of [N_b, 3], sensor frames) from their guesses [B, 4, 4] to the map of index, together
    (point_to_plane_batch), then each judged: (pose [4, 4], residual_m, fitness, flag) a scan, the guess and a flag
    where it is refused (too few points, poor fitness, a jump)."""
    prepared = [prepare_scan(scan, settings) for scan in scans]
    ready = [b for b, p in enumerate(prepared) if p is not None]
    poses = np.array(guesses, np.float64, copy=True)
    if ready:
        poses[ready] = point_to_plane_batch([prepared[b].icp for b in ready], poses[ready], index, settings)
    return [
        (guesses[b], np.nan, np.nan, TOO_FEW_POINTS)
        if scan is None
        else judged(scan, guesses[b], poses[b], index, settings)
        for b, scan in enumerate(prepared)
    ]


def judged(
    scan: ScanPoints, guess: np.ndarray, pose: np.ndarray, index: MapIndex, settings: RegistrationSettings
) -> tuple[np.ndarray, float, float, str]:
    """A scan's ICP result pose [4, 4] from guess [4, 4] held to the guess along the directions its pairs barely fix
    (held_along_weak_directions, as every ICP of the baseline: along a straight street between parallel walls), then
    judged by its fitness and its jump: (pose, residual_m, fitness, flag), the guess where it is refused."""
    from neld_jax.baseline.icp import direction_shares, held_along_weak_directions
    from neld_jax.baseline.settings import BaselineSettings

    min_share, reach = BaselineSettings.min_direction_share, min(settings.fit_distance_m, HOLD_REACH_M)
    moved = scan.fit @ pose[:3, :3].T + pose[:3, 3]
    nearest, squared = index.nearest(moved, settings.fit_distance_m)  # one search: the directions' and the fit's
    close = squared <= reach**2
    weak = close.sum() >= 6 and direction_shares(moved[close], index.normals[nearest[close]])[0][0] < min_share
    if min_share > 0 and weak:
        search = SimpleNamespace(nearest=index.nearest, max_distance=reach)
        pose = held_along_weak_directions(SimpleNamespace(points=scan.fit), index, guess, pose, min_share, search)
        fitness, residual = fit_to_map(scan.fit, pose, None, settings.fit_distance_m, index)
    else:
        fitness, residual = fit_of(moved, nearest, index)
    jump_m, jump_deg = pose_change(guess, pose)
    flag = POOR_FITNESS if fitness < settings.min_fitness else ""
    flag = flag or (JUMP if jump_m > settings.max_jump_m or jump_deg > settings.max_jump_deg else "")
    return (guess if flag else pose), residual, fitness, flag


# The pairs that judge a scan's directions reach this far: the finest distances' reach in the baseline's ICP
HOLD_REACH_M = 0.25


def register_scan(
    scan: np.ndarray, guess: np.ndarray, target, settings: RegistrationSettings, indices: dict | None = None
):
    """One scan [N, 3] (sensor frame) from its guess [4, 4] (sensor -> map) to the target map (map_cloud): a batch
    of one (register_batch). indices: a dict that keeps the map's MapIndex for a caller that registers many scans to
    it (None: built here).

    Returns (pose [4, 4], residual_m, fitness, flag): the guess and a flag where it is refused."""
    return register_batch([scan], np.asarray(guess)[None], map_index(target, indices), settings)[0]


def register_to_map(
    scans: list[np.ndarray],
    guesses: np.ndarray,
    target,
    settings: RegistrationSettings,
    which: np.ndarray | None = None,
    progress: bool = False,
    label=str,
    deadline: float | None = None,
) -> ScanRegistration:
    """Register the scans (list of S [N_i, 3], sensor frames) chosen by which [S] bool (None: every one) from
    their guesses [S, 4, 4] to the target map (map_cloud), settings.batch_scans at a time (register_batch). The
    others keep their guesses, untried. label(s): how the log names scan s. deadline: a time.perf_counter() value
    after which the scans left keep their guesses, flagged OUT_OF_TIME (None: no limit)."""
    import time

    from tqdm.auto import tqdm

    num_scans = len(scans)
    which = np.ones(num_scans, bool) if which is None else np.asarray(which, bool)
    poses = np.array(guesses, np.float64, copy=True)
    residual, fitness, flags = np.full(num_scans, np.nan), np.full(num_scans, np.nan), [""] * num_scans
    chosen = np.flatnonzero(which)
    index = map_index(target) if len(chosen) else None  # the map's search structure, built once for every scan
    with tqdm(total=len(chosen), disable=not progress, desc="registering scans", unit="scan") as bar:
        for batch in np.array_split(chosen, -(-len(chosen) // settings.batch_scans) or 1):
            if deadline is not None and time.perf_counter() > deadline:
                for s in batch:
                    flags[s] = OUT_OF_TIME
                continue
            results = register_batch([scans[s] for s in batch], poses[batch], index, settings)
            for s, (pose, residual[s], fitness[s], flags[s]) in zip(batch, results):
                poses[s] = pose
            bar.update(len(batch))
    registration = ScanRegistration(poses, residual, fitness, flags, which)
    log_refused(registration, label)
    return registration


def log_refused(registration: ScanRegistration, label=str) -> None:
    """One warning per scan that was tried and refused (it keeps its guess; label(s) names it), one for the scans
    the deadline left (OUT_OF_TIME), and a count."""
    late = [s for s, flag in enumerate(registration.flag) if flag == OUT_OF_TIME]
    if late:
        logger.warning(
            "%d scans from %s on were not registered: the run's time (max_minutes) ran out; they keep "
            "their interpolated poses, flagged in scans_report.csv",
            len(late),
            label(late[0]),
        )
    for s, flag in enumerate(registration.flag):
        if flag and flag != OUT_OF_TIME:
            logger.warning(
                "%s not registered (%s: fitness %.2f, residual %.3f m): it keeps its guess",
                label(s),
                flag,
                registration.fitness[s],
                registration.residual_m[s],
            )
    logger.info(
        "registered %d of %d scans tried to the map (median residual %.3f m)",
        int(registration.registered.sum()),
        int(registration.tried.sum()),
        float(np.nanmedian(registration.residual_m)) if np.isfinite(registration.residual_m).any() else np.nan,
    )


def register_every_scan(
    loaded,
    keyframes,
    keyframe_poses: np.ndarray,
    settings: RegistrationSettings,
    progress: bool = False,
    deadline: float | None = None,
) -> ScanRegistration:
    """After training: every input scan (loaded: the input Sequence) that is not a keyframe (keyframes: the trained
    ones, keyframes.loaded_index into loaded) registered to the keyframes' raw map under their refined poses
    keyframe_poses [K, 4, 4], from its interpolated correction (trajectory.propagate_corrections), until deadline
    (register_to_map). The keyframes keep their poses, untried: they make the map."""
    guesses = propagate_corrections(loaded.poses, keyframes.loaded_index, keyframe_poses, loaded.timestamps)
    which = np.ones(loaded.num_scans, bool)
    which[keyframes.loaded_index] = False
    if not which.any():  # every scan a keyframe: nothing to register, no map to build
        nothing = np.full(loaded.num_scans, np.nan)
        return ScanRegistration(guesses, nothing, nothing.copy(), [""] * loaded.num_scans, which)
    target = map_cloud(keyframes.scans, keyframe_poses, settings)
    return register_to_map(loaded.scans, guesses, target, settings, which, progress, loaded.scan_label, deadline)


def place_first_scan(
    scan: np.ndarray, pose: np.ndarray, target, settings: RegistrationSettings, indices: dict | None = None
) -> tuple[np.ndarray, str]:
    """Where scan [N, 3] (sensor frame) lies in the target map (map_cloud), its own pose [4, 4] being in a frame
    that may not be the map's: ICP from that pose, or where that is refused, global registration (FPFH + RANSAC,
    then ICP: neld_jax.baseline.global_registration) checked as any registration. Returns (pose [4, 4] in the map,
    "icp" or "global"); a DataError when neither places it. indices: as register_scan's."""
    from neld_jax.baseline import BaselineSettings, fpfh_features, global_registration
    from neld_jax.errors import DataError

    placed, _, _, flag = register_scan(scan, pose, target, settings, indices)
    if not flag:
        return placed, "icp"
    source = cloud_with_normals(
        crop_range(scan, settings.min_range_m, settings.max_range_m), settings, sensor_frame=True
    )
    features = BaselineSettings()
    transform, _ = global_registration(
        source, target, fpfh_features(source, features), fpfh_features(target, features), features
    )
    placed, residual, fitness, flag = register_scan(scan, transform, target, settings, indices)
    if flag:
        raise DataError(
            f"the first scan could not be placed in the map: ICP from its own pose and global "
            f"registration both failed ({flag}: {fitness:.0%} of its points on the map, residual "
            f"{residual:.3f} m); are these scans of the mapped place?"
        )
    return placed, "global"


def localize(
    scans: list[np.ndarray],
    poses: np.ndarray,
    target,
    settings: RegistrationSettings,
    progress: bool = False,
    label=str,
) -> tuple[ScanRegistration, str]:
    """Pose scans (list of S [N_i, 3], sensor frames, in time order) in a map (map_cloud) whose frame their own
    poses [S, 4, 4] (layout or odometry) need not share: the first scan placed by place_first_scan, then each scan
    by ICP from its own pose carried by the last registered scan's correction (the odometry holds between them).
    A refused scan keeps that guess. Returns (the registration, how the first scan was placed)."""
    from tqdm.auto import tqdm

    num_scans = len(scans)
    indices = {}  # the map's search structure, built once for every scan
    placed, how = place_first_scan(scans[0], poses[0], target, settings, indices)
    correction = placed @ invert_poses(poses[:1])[0]
    out = np.array(poses, np.float64, copy=True)
    residual, fitness, flags = np.full(num_scans, np.nan), np.full(num_scans, np.nan), [""] * num_scans
    for s in tqdm(range(num_scans), disable=not progress, desc="localizing scans", unit="scan"):
        out[s], residual[s], fitness[s], flags[s] = register_scan(
            scans[s], correction @ poses[s], target, settings, indices
        )
        if not flags[s]:
            correction = out[s] @ invert_poses(poses[s : s + 1])[0]
    registration = ScanRegistration(out, residual, fitness, flags, np.ones(num_scans, bool))
    log_refused(registration, label)
    return registration, how
