"""Every input scan registered to the result: a scan that was not a keyframe starts from its interpolated
correction (neld_jax.trajectory) and is then registered to the keyframes' refined raw map by point-to-plane ICP
(neld_jax.baseline.multiscale_icp), so that it does not keep the odometry's error between keyframes.

A scan that cannot be registered keeps its interpolated pose and is flagged: too few points in range, too little
of it on the map (its fitness: the share of its points near map points), or a result that moves it further from
its interpolated pose than a bound. The same registration poses the scans of another recording in a finished run's
map (neld-localize). Registering in the trained field instead (pose-only, the field frozen) was measured and lost
to this (docs/evaluation.md, "Every input scan").
"""

from __future__ import annotations

import dataclasses
import logging
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
    icp_iterations: int = 30
    min_range_m: float = 0.5
    max_range_m: float = 80.0
    min_points: int = 100  # fewer points in range (on the grid): not registered
    fit_distance_m: float = 0.3  # a scan point within this of a map point lies on the map ...
    min_fitness: float = 0.5  # ... and a scan less of whose points do is not registered
    max_jump_m: float = 0.5  # a result further than this from the guess ...
    max_jump_deg: float = 5.0  # ... or turned more than this: not registered

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


def register_scan(
    scan: np.ndarray, guess: np.ndarray, target, settings: RegistrationSettings, indices: dict | None = None
):
    """One scan [N, 3] (sensor frame) from its guess [4, 4] (sensor -> map) to the target map (map_cloud). indices:
    the map's nearest-point indices, kept by a caller that registers many scans to it (baseline.multiscale_icp).

    Returns (pose [4, 4], residual_m, fitness, flag): the guess and a flag where it is refused."""
    from neld_jax.baseline import BaselineSettings, TargetIndex, multiscale_icp

    indices = {} if indices is None else indices

    source = cloud_with_normals(
        crop_range(scan, settings.min_range_m, settings.max_range_m), settings, sensor_frame=True
    )
    if len(source.points) < settings.min_points:
        return guess, np.nan, np.nan, TOO_FEW_POINTS
    icp = BaselineSettings(
        voxel_size_m=settings.voxel_size_m,
        normal_radius_m=settings.normal_radius_m,
        icp_distances_m=tuple(settings.icp_distances_m),
        icp_iterations=settings.icp_iterations,
    )
    pose, _ = multiscale_icp(source, target, guess, icp, oriented=False, indices=indices)
    fit = ("fit", settings.fit_distance_m)
    if fit not in indices:
        indices[fit] = TargetIndex(target, settings.fit_distance_m)
    fitness, residual = fit_to_map(np.asarray(source.points), pose, target, settings.fit_distance_m, indices[fit])
    if fitness < settings.min_fitness:
        return guess, residual, fitness, POOR_FITNESS
    jump_m, jump_deg = pose_change(guess, pose)
    if jump_m > settings.max_jump_m or jump_deg > settings.max_jump_deg:
        return guess, residual, fitness, JUMP
    return pose, residual, fitness, ""


def fit_to_map(points: np.ndarray, pose: np.ndarray, target, distance_m: float, index=None) -> tuple[float, float]:
    """How a scan's points [N, 3] (sensor frame) under pose [4, 4] lie on the target map (an Open3D cloud with
    normals): (fitness: the fraction with a map point within distance_m, residual [m]: the RMS distance of those to
    their map point's plane; NaN without one). index: the target's TargetIndex for searches up to distance_m (None:
    built here)."""
    from neld_jax.baseline import TargetIndex

    moved = points @ pose[:3, :3].T + pose[:3, 3]
    index = TargetIndex(target, distance_m) if index is None else index
    nearest, _ = index.nearest(moved, distance_m)
    paired = nearest >= 0
    if not paired.any():
        return 0.0, float("nan")
    offsets = moved[paired] - np.asarray(target.points)[nearest[paired]]
    along_normal = np.einsum("ij,ij->i", offsets, np.asarray(target.normals)[nearest[paired]])
    return float(paired.mean()), float(np.sqrt(np.mean(along_normal**2)))


def pose_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """How far [m] and how much [deg] a pose [4, 4] moved, in its own frame: before^-1 after."""
    delta = invert_poses(before[None])[0] @ after
    return float(np.linalg.norm(delta[:3, 3])), float(rotation_angles_deg(delta[None, :3, :3])[0])


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
    their guesses [S, 4, 4] to the target map (map_cloud). The others keep their guesses, untried. label(s): how the
    log names scan s. deadline: a time.perf_counter() value after which the scans left keep their guesses, flagged
    OUT_OF_TIME (None: no limit)."""
    import time

    from tqdm.auto import tqdm

    num_scans = len(scans)
    which = np.ones(num_scans, bool) if which is None else np.asarray(which, bool)
    poses = np.array(guesses, np.float64, copy=True)
    residual, fitness, flags = np.full(num_scans, np.nan), np.full(num_scans, np.nan), [""] * num_scans
    indices = {}  # the map's search indices, built once for every scan
    for s in tqdm(np.flatnonzero(which), disable=not progress, desc="registering scans", unit="scan"):
        if deadline is not None and time.perf_counter() > deadline:
            flags[s] = OUT_OF_TIME
            continue
        poses[s], residual[s], fitness[s], flags[s] = register_scan(scans[s], poses[s], target, settings, indices)
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
    scan: np.ndarray, pose: np.ndarray, target, settings: RegistrationSettings
) -> tuple[np.ndarray, str]:
    """Where scan [N, 3] (sensor frame) lies in the target map (map_cloud), its own pose [4, 4] being in a frame
    that may not be the map's: ICP from that pose, or where that is refused, global registration (FPFH + RANSAC,
    then ICP: neld_jax.baseline.global_registration) checked as any registration. Returns (pose [4, 4] in the map,
    "icp" or "global"); a DataError when neither places it."""
    from neld_jax.baseline import BaselineSettings, fpfh_features, global_registration
    from neld_jax.errors import DataError

    placed, _, _, flag = register_scan(scan, pose, target, settings)
    if not flag:
        return placed, "icp"
    source = cloud_with_normals(
        crop_range(scan, settings.min_range_m, settings.max_range_m), settings, sensor_frame=True
    )
    features = BaselineSettings()
    transform, _ = global_registration(
        source, target, fpfh_features(source, features), fpfh_features(target, features), features
    )
    placed, residual, fitness, flag = register_scan(scan, transform, target, settings)
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
    placed, how = place_first_scan(scans[0], poses[0], target, settings)
    correction = placed @ invert_poses(poses[:1])[0]
    out = np.array(poses, np.float64, copy=True)
    residual, fitness, flags = np.full(num_scans, np.nan), np.full(num_scans, np.nan), [""] * num_scans
    indices = {}  # the map's search indices, built once for every scan
    for s in tqdm(range(num_scans), disable=not progress, desc="localizing scans", unit="scan"):
        out[s], residual[s], fitness[s], flags[s] = register_scan(
            scans[s], correction @ poses[s], target, settings, indices
        )
        if not flags[s]:
            correction = out[s] @ invert_poses(poses[s : s + 1])[0]
    registration = ScanRegistration(out, residual, fitness, flags, np.ones(num_scans, bool))
    log_refused(registration, label)
    return registration, how
