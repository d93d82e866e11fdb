"""A synthetic LiDAR sequence with exact ground truth, built by Open3D ray casting: the generator's fields
(`synthetic_defaults`, config.data.synthetic), the sequence of one route or visit (`make_sequence`) and its writing
in the generic layout (`write_generic`).

The scene is a procedurally generated courtyard, seeded and deterministic (neld_jax.synthetic.scene). A
spinning LiDAR drives round a smooth closed loop through it (neld_jax.synthetic.routes); its scans are cast
into the scene and the ground-truth map holds the surfaces they saw (neld_jax.synthetic.lidar). Initial poses
come from the ground truth by a random walk in the relative motions, like odometry drift. A later visit of the same
scene (`session` K >= 1) rides another loop with its own drift and noise, its initial poses in its own frame.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import ml_collections
import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError
from neld_jax.geometry import invert_poses
from neld_jax.synthetic.lidar import (  # noqa: F401  (the generator's public names, importable from here)
    FOV_DEG,
    GT_MAP_VISIBILITY_TOLERANCE_M,
    MIN_RANGE_M,
    cast_scan,
    cast_sweep,
    observed_surface_points,
    spinning_lidar_directions,
)
from neld_jax.synthetic.routes import (  # noqa: F401
    CAR_RATE_HZ,
    HANDHELD_RATE_HZ,
    SENSOR_HEIGHT_M,
    add_odometry_drift,
    car_drive,
    courtyard_route,
    handheld_walk,
    loop_poses,
    smooth_trajectory,
    visit_loop,
)
from neld_jax.synthetic.scene import (  # noqa: F401
    PATH_WOBBLE,
    make_courtyards_meshes,
    make_scene,
    make_scene_meshes,
    raycasting_scene,
)

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


SCAN_INTERVAL_S = 3.0  # 30 frames of 0.1 s: one keyframe per scan at the paper's 3 s spacing
ROUTES = ("loop", "courtyards", "handheld", "car")
VISIT_SEED_STEP = 100  # visit k draws its drift, range noise and map samples from seed + 100 k + (1, 2, 3)


def _resolve_config(cfg) -> ml_collections.ConfigDict:
    resolved = synthetic_defaults()
    if cfg is None:
        return resolved
    items = cfg.items() if hasattr(cfg, "items") else dict(cfg).items()
    for key, value in items:
        if key not in resolved:
            raise ConfigError(f"data.synthetic: unknown field '{key}' (known: {', '.join(sorted(resolved.keys()))})")
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
        0 < resolved.trajectory_radius_m * (1 + PATH_WOBBLE) < resolved.scene_size_m / 2 - 1.0
    ):
        raise ConfigError(
            f"data.synthetic: trajectory_radius_m ({resolved.trajectory_radius_m}) must be positive and leave the "
            f"loop inside the {resolved.scene_size_m} m courtyard"
        )
    if resolved.max_range_m <= MIN_RANGE_M or resolved.gt_map_points < 0:
        raise ConfigError("data.synthetic: max_range_m must exceed 0.5 m and gt_map_points must be >= 0")
    return resolved


def make_sequence(cfg=None, rate_hz: float = 0.0, session: int | None = None) -> Sequence:
    """A synthetic Sequence: scans cast from the ground-truth poses, drifted initial poses, GT poses and map.

    cfg: ConfigDict or dict with any of the fields of synthetic_defaults() (missing ones take the defaults, unknown
    ones raise ConfigError). Timestamps are SCAN_INTERVAL_S (3 s) apart, so keyframe selection at 3 s keeps every scan.

    rate_hz > 0: the raw sweeps of a LiDAR spinning at that rate instead, as a recording holds them (the loop
    route only): num_scans sweeps 1 / rate_hz apart, each point cast from where the sensor was at its column's
    instant, `point_times` [N_i] seconds after the sweep's stamp, ground truth at the sweeps' stamps (their
    starts), and no initial poses (poses None: a run makes them from the scans, neld_jax.frontend).
    The route "handheld" (handheld_walk round the loop, HANDHELD_RATE_HZ unless rate_hz is given) is rigid scans
    (deskewed, as a front-end writes them) 1 / rate_hz apart; the route "car" (car_drive along the courtyards' route
    of route_length_m, its corners eased, at CAR_RATE_HZ unless rate_hz is given: num_scans sweeps of a car that sets
    off from rest, cruises at 11 m/s and slows for the corners, round the route again where they outlast a lap) is
    raw sweeps as above (a car moves up to 1.1 m within a sweep). Both come with ground truth and no initial poses.
    session K (loop route, rigid scans): make_visit's K-th visit of the scene instead."""
    if session is not None:
        return make_visit(cfg, session)
    cfg = _resolve_config(cfg)
    if rate_hz > 0 and cfg.route == "courtyards":
        raise ConfigError(f"synthetic sweeps at {rate_hz} Hz follow the loop route, not {cfg.route!r}")
    started = time.perf_counter()
    scene, meshes, gt_poses = _scene_and_route(cfg, rate_hz)
    directions = spinning_lidar_directions(cfg.num_beams, FOV_DEG[1], FOV_DEG[0], cfg.num_columns)
    rng = np.random.default_rng(cfg.seed + 2)
    point_times, init_poses = None, None
    if cfg.route == "handheld":
        rate_hz = rate_hz or HANDHELD_RATE_HZ
        timestamps = np.arange(cfg.num_scans) / rate_hz
        scans = [cast_scan(scene, pose, directions, cfg.max_range_m, cfg.range_noise_m, rng) for pose in gt_poses]
    elif cfg.route == "car" or rate_hz > 0:  # raw sweeps; the car's at CAR_RATE_HZ unless given a rate
        rate_hz = rate_hz or CAR_RATE_HZ
        timestamps, scans, point_times = _raw_sweeps(cfg, rate_hz, scene, directions, rng)
    else:
        init_poses = add_odometry_drift(gt_poses, cfg.drift_trans_m, cfg.drift_rot_deg, cfg.seed + 1)
        timestamps = SCAN_INTERVAL_S * np.arange(cfg.num_scans, dtype=np.float64)
        scans = [cast_scan(scene, pose, directions, cfg.max_range_m, cfg.range_noise_m, rng) for pose in gt_poses]
    gt_map = _observed_map(cfg, meshes, scene, gt_poses, cfg.seed)
    logger.info(
        "synthetic sequence (seed %d): %d scans, %d points, gt map %d points, %d meshes, %.2f s",
        cfg.seed,
        len(scans),
        sum(len(s) for s in scans),
        0 if gt_map is None else len(gt_map),
        len(meshes),
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


def _observed_map(cfg, meshes, scene, gt_poses: np.ndarray, seed: int) -> np.ndarray | None:
    """The ground-truth map [cfg.gt_map_points, 3]: the surfaces the sensor saw from gt_poses [S, 4, 4]
    (observed_surface_points, drawn with seed + 3); None with gt_map_points 0."""
    if cfg.gt_map_points <= 0:
        return None
    return observed_surface_points(
        meshes,
        scene,
        gt_poses,
        cfg.gt_map_points,
        FOV_DEG[0],
        FOV_DEG[1],
        cfg.max_range_m,
        np.random.default_rng(seed + 3),
    )


def make_visit(cfg, session: int) -> Sequence:
    """The session-th visit (0, 1, ...) of the seed's courtyard, as a recording of it would be: the loop of
    synthetic_routes.visit_loop (another radius, start and direction each visit), its own drift and range-noise
    draws (seed + VISIT_SEED_STEP x session), and the initial poses in the visit's own frame (its first scan at the
    identity), as an odometry starts. The ground truth (poses and map) is in the scene's frame, shared by every
    visit. Scans SCAN_INTERVAL_S apart, as make_sequence's loop."""
    cfg = _resolve_config(cfg)
    if cfg.route != "loop" or session < 0:
        raise ConfigError(
            f"synthetic sessions (--session={session}) are visits of the loop route with drifted "
            f"poses: a session >= 0 and data.synthetic.route=loop (not {cfg.route!r})"
        )
    scene, meshes = make_scene(cfg.seed, cfg.scene_size_m, path_radius_m=cfg.trajectory_radius_m)
    gt_poses = visit_loop(cfg.num_scans, cfg.trajectory_radius_m, cfg.seed, session)
    seed = cfg.seed + VISIT_SEED_STEP * session
    directions = spinning_lidar_directions(cfg.num_beams, FOV_DEG[1], FOV_DEG[0], cfg.num_columns)
    rng = np.random.default_rng(seed + 2)
    scans = [cast_scan(scene, pose, directions, cfg.max_range_m, cfg.range_noise_m, rng) for pose in gt_poses]
    drifted = add_odometry_drift(gt_poses, cfg.drift_trans_m, cfg.drift_rot_deg, seed + 1)
    gt_map = _observed_map(cfg, meshes, scene, gt_poses, seed)
    return Sequence(
        scans=scans,
        poses=invert_poses(drifted[:1])[0] @ drifted,
        timestamps=SCAN_INTERVAL_S * np.arange(cfg.num_scans, dtype=np.float64),
        gt_poses=gt_poses,
        gt_map=gt_map,
        name=f"synthetic_seed{cfg.seed}_session{session}",
        source="synthetic",
    )


def _scene_and_route(cfg, rate_hz: float):
    """(RaycastingScene, meshes, ground-truth poses [S, 4, 4]) of the resolved cfg's route."""
    if cfg.route == "car":
        gt_poses, route_xy = car_drive(cfg.num_scans, cfg.route_length_m, cfg.seed, rate_hz or CAR_RATE_HZ)
        gt_poses = gt_poses[:, 0]
        meshes = make_courtyards_meshes(cfg.seed, route_xy)
        return raycasting_scene(meshes), meshes, gt_poses
    if cfg.route == "courtyards":
        gt_poses, route_xy = courtyard_route(cfg.num_scans, cfg.route_length_m, cfg.seed)
        meshes = make_courtyards_meshes(cfg.seed, route_xy)
        return raycasting_scene(meshes), meshes, gt_poses
    scene, meshes = make_scene(cfg.seed, cfg.scene_size_m, path_radius_m=cfg.trajectory_radius_m)
    if cfg.route == "handheld":
        return (
            scene,
            meshes,
            handheld_walk(cfg.num_scans, cfg.trajectory_radius_m, cfg.seed, rate_hz or HANDHELD_RATE_HZ),
        )
    return scene, meshes, smooth_trajectory(cfg.num_scans, cfg.trajectory_radius_m, cfg.seed)


def _raw_sweeps(cfg, rate_hz: float, scene, directions: np.ndarray, rng: np.random.Generator):
    """(stamps [S], sweeps [S] x [N_i, 3], per-point times [S] x [N_i]) of a LiDAR spinning at rate_hz round the
    loop, or along car_drive for the route "car" (at its 11 m/s a sweep spans 1.1 m): each column cast from where the
    sensor is at its instant."""
    timestamps, scans, point_times = np.arange(cfg.num_scans) / rate_hz, [], []
    column_fraction = np.arange(cfg.num_columns) / cfg.num_columns
    if cfg.route == "car":
        car_columns, _ = car_drive(cfg.num_scans, cfg.route_length_m, cfg.seed, rate_hz, column_fraction)
    for i in range(cfg.num_scans):
        column_poses = (
            car_columns[i]
            if cfg.route == "car"
            else loop_poses((i + column_fraction) / cfg.num_scans, cfg.trajectory_radius_m, cfg.seed)
        )
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
