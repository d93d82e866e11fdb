"""The synthetic sensor's routes (ground-truth poses, sensor -> world): a smooth loop round the courtyard (and a
later visit of it: another radius, start and direction), a handheld walk that looks around, a long route through
connected courtyards and a car that drives it as a car does (from rest, slower through eased corners); and the drift
an odometry adds to them."""

from __future__ import annotations

import numpy as np

from neld_jax.synthetic.scene import PATH_WOBBLE

SENSOR_HEIGHT_M = 1.8
VISIT_RADIUS_STEP = 0.03  # a later visit of the loop rides this much nearer or further (of the radius) ...
VISIT_START_TURN = 0.37  # ... and starts this far further round (of a turn)
HANDHELD_RATE_HZ = 2.0  # the handheld route's scans, when make_sequence is given no rate
HANDHELD_SPEED_M_S = 1.4  # walking
HANDHELD_TURN_DEG = (40.0, 50.0)  # the turn between consecutive handheld scans, either side
HANDHELD_STEADY_SCANS = 8  # the handheld walk's first scans look ahead (an odometry learns the sensor's overlap)
CAR_RATE_HZ = 10.0  # the car route's scans, when make_sequence is given no rate
# The car drives as a car does (docs/datasets.md, "Synthetic scans without poses"): KITTI 00's frames 0-100 run at
# 4.4-10.6 m/s, up to 1.8 m/s^2 sideways, the yaw rate changing by at most 0.27 deg a sweep from one sweep to the next.
CAR_CRUISE_M_S = 11.0  # on the straights
CAR_LATERAL_M_S2 = 3.0  # at most, in the corners (a 10 m corner at 5.5 m/s)
CAR_ACCELERATION_M_S2 = 2.5  # speeding up and braking
CAR_EASE_M = 4.0  # the corners eased over a few of these: the yaw rate builds up over about a second


def smooth_trajectory(num_scans: int, radius_m: float, seed: int) -> np.ndarray:
    """Ground-truth poses [S, 4, 4] (sensor -> world) on a smooth closed loop around the origin, evenly spaced.

    The loop has radius radius_m with a gentle radial wobble (at most PATH_WOBBLE * radius_m); the
    sensor rides about 1.8 m above the ground, its yaw follows the motion, with small roll and pitch."""
    return loop_poses(np.arange(num_scans) / num_scans, radius_m, seed)


def loop_poses(fraction: np.ndarray, radius_m: float, seed: int, reverse: bool = False) -> np.ndarray:
    """Poses [K, 4, 4] (sensor -> world) at fractions [K] of the way round the seed's loop (smooth_trajectory's
    loop: fraction i / S is its scan i; any fraction in between is where the sensor is at that moment). reverse:
    the sensor drives the loop the other way (it looks along its motion, fractions decreasing)."""
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
    yaw = np.arctan2(dy, dx) + (np.pi if reverse else 0.0)
    pitch = np.deg2rad(1.5) * np.sin(3 * theta + pitch_phase)
    roll = np.deg2rad(2.0) * np.sin(2 * theta + roll_phase)

    poses = np.tile(np.eye(4), (theta.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses


def visit_loop(num_scans: int, radius_m: float, seed: int, visit: int) -> np.ndarray:
    """Ground-truth poses [S, 4, 4] (sensor -> world, the scene's frame) of visit `visit` of the seed's loop: visit
    0 is smooth_trajectory; visit k starts VISIT_START_TURN of a turn further on, drives the loop the other way when
    k is odd, and rides at 1 + VISIT_RADIUS_STEP x ceil(k / 2) of the radius (k odd) or 1 - that (k even), inside
    the band the scene keeps clear for a few visits."""
    sign = -1.0 if visit % 2 else 1.0
    scale = 1.0 - sign * VISIT_RADIUS_STEP * ((visit + 1) // 2)
    fraction = VISIT_START_TURN * visit + sign * np.arange(num_scans) / num_scans
    return loop_poses(fraction, radius_m * scale, seed, reverse=visit % 2 == 1)


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


def add_odometry_drift(
    gt_poses: np.ndarray, trans_sigma_m: float, rot_sigma_deg: float, seed: int, keep_tilt: bool = False
) -> np.ndarray:
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


def _rounded_rectangle(length_m: float, num_points: int = 4000) -> np.ndarray:
    """Points [num_points, 2] evenly spaced along a closed rounded rectangle (3:2, corner radius 0.15 of the
    short side) of perimeter length_m, centred at the origin, counter-clockwise."""
    # Perimeter of half sides (a, b), corner radius r: 4 (a - r) + 4 (b - r) + 2 pi r; a = 1.5 b, r = 0.3 b.
    b = length_m / (4 * 1.5 + 4 * 1.0 - 8 * 0.3 + 2 * np.pi * 0.3)
    a, r = 1.5 * b, 0.3 * b
    dense = []
    for cx, cy, start in (
        (a - r, b - r, 0.0),
        (-(a - r), b - r, np.pi / 2),
        (-(a - r), -(b - r), np.pi),
        (a - r, -(b - r), 1.5 * np.pi),
    ):
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
    dense = _rounded_rectangle(length_m)
    idx = (np.arange(num_scans) * len(dense)) // num_scans
    return _route_poses(dense, idx, idx + 1, np.zeros(num_scans), np.arange(num_scans) / num_scans, seed), dense


def _route_poses(
    dense: np.ndarray, before: np.ndarray, after: np.ndarray, blend: np.ndarray, fraction: np.ndarray, seed: int
) -> np.ndarray:
    """Poses [N, 4, 4] on the dense closed route [D, 2]: at blend [N] of the way from its point `before` [N] to
    `after` [N] (indices, wrapped), the yaw along the route there, and the wobble of height, roll and pitch at
    fraction [N] of the way round."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    z_phase, roll_phase, pitch_phase = rng.uniform(0.0, 2 * np.pi, size=3)
    n = len(dense)
    w = blend[:, None]
    xy = (1 - w) * dense[before % n] + w * dense[after % n]
    tangent = (1 - w) * (dense[(before + 1) % n] - dense[(before - 1) % n]) + w * (
        dense[(after + 1) % n] - dense[(after - 1) % n]
    )
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0])
    theta = 2 * np.pi * fraction
    pitch = np.deg2rad(1.5) * np.sin(7 * theta + pitch_phase)
    roll = np.deg2rad(2.0) * np.sin(5 * theta + roll_phase)
    poses = np.tile(np.eye(4), (len(fraction), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    poses[:, :3, 3] = np.stack([xy[:, 0], xy[:, 1], SENSOR_HEIGHT_M + 0.1 * np.sin(3 * theta + z_phase)], axis=1)
    return poses


def car_drive(
    num_scans: int, length_m: float, seed: int, rate_hz: float, sweep_fractions: np.ndarray = np.zeros(1)
) -> tuple[np.ndarray, np.ndarray]:
    """The poses of a car driving car_route(length_m) from rest, as a car drives (docs/datasets.md, "Synthetic scans
    without poses"), and that route [N, 2]: one sweep each 1 / rate_hz s; it speeds up and brakes at
    CAR_ACCELERATION_M_S2, cruises at CAR_CRUISE_M_S on the straights and takes the eased corners no faster than
    CAR_LATERAL_M_S2 allows, round the route again where the sweeps outlast a lap. Returns poses [S, F, 4, 4] at
    sweep_fractions [F] of each sweep's period after its stamp (the default [0.0]: at the stamps), between the
    route's samples where they fall."""
    dense = car_route(length_m)
    times = (np.arange(num_scans)[:, None] + np.asarray(sweep_fractions, np.float64)[None, :]) / rate_hz
    travelled, lap_m = _car_travelled(dense, times.ravel())
    fraction = np.mod(travelled / lap_m, 1.0)
    at = fraction * len(dense)
    before = np.floor(at).astype(np.int64)
    poses = _route_poses(dense, before, before + 1, at - before, fraction, seed)
    return poses.reshape(*times.shape, 4, 4), dense


def car_route(length_m: float) -> np.ndarray:
    """The car's closed route [N, 2], evenly spaced, counter-clockwise: courtyard_route's rounded rectangle of
    length_m with its corners eased (smoothed along it by a Gaussian of CAR_EASE_M), so that its curvature, and a
    car's yaw rate, builds up and dies down over metres as a road's does rather than at once, starting halfway
    along its right-hand straight (the car sets off on a straight). A little shorter than length_m (the corners cut)."""
    from scipy.ndimage import gaussian_filter1d

    dense = _rounded_rectangle(length_m)
    start = np.argmin(np.abs(dense[:, 1]) + np.where(dense[:, 0] > 0, 0.0, np.inf))  # x = a, y = 0
    dense = gaussian_filter1d(np.roll(dense, -start, axis=0), CAR_EASE_M * len(dense) / length_m, axis=0, mode="wrap")
    closed = np.concatenate([dense, dense[:1]])
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    even = np.linspace(0.0, along[-1], len(dense), endpoint=False)
    return np.stack([np.interp(even, along, closed[:, 0]), np.interp(even, along, closed[:, 1])], axis=1)


def _car_speed_limit(dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The closed route [N, 2]'s steps [N] (from each sample to the next, m) and the car's speed limit there [N]
    (m/s): CAR_CRUISE_M_S, or the speed at which its curvature takes CAR_LATERAL_M_S2 of lateral acceleration."""
    steps = np.linalg.norm(np.roll(dense, -1, axis=0) - dense, axis=1)
    ahead, behind = np.roll(dense, -1, axis=0), np.roll(dense, 1, axis=0)
    heading = np.arctan2(ahead[:, 1] - behind[:, 1], ahead[:, 0] - behind[:, 0])
    turn = np.angle(np.exp(1j * (np.roll(heading, -1) - np.roll(heading, 1))))  # over two steps, wrapped
    curvature = np.abs(turn) / (steps + np.roll(steps, 1))
    return steps, np.minimum(CAR_CRUISE_M_S, np.sqrt(CAR_LATERAL_M_S2 / np.maximum(curvature, 1e-12)))


def _car_travelled(dense: np.ndarray, times_s: np.ndarray) -> tuple[np.ndarray, float]:
    """How far [T] the car has gone along the closed route [N, 2] at times_s [T] (from rest at 0), and the route's
    length: the fastest speed profile within the speed limit (_car_speed_limit) that speeds up and brakes at no
    more than CAR_ACCELERATION_M_S2, over as many laps as the times need; each step at constant acceleration."""
    steps, limit = _car_speed_limit(dense)
    lap_m = float(steps.sum())
    laps = int(np.ceil(max(float(np.max(times_s, initial=0.0)), 1.0) * CAR_CRUISE_M_S / lap_m)) + 2
    steps, limit = np.tile(steps, laps), np.tile(limit, laps)
    speed = np.empty(len(limit) + 1)
    speed[0], speed[-1] = 0.0, limit[0]
    for i in range(1, len(limit)):  # speeding up ...
        speed[i] = min(limit[i], np.sqrt(speed[i - 1] ** 2 + 2 * CAR_ACCELERATION_M_S2 * steps[i - 1]))
    for i in range(len(limit) - 1, 0, -1):  # ... and braking ahead of the corners
        speed[i] = min(speed[i], np.sqrt(speed[i + 1] ** 2 + 2 * CAR_ACCELERATION_M_S2 * steps[i]))
    durations = 2 * steps / np.maximum(speed[:-1] + speed[1:], 1e-12)
    start_s = np.concatenate([[0.0], np.cumsum(durations)])
    start_m = np.concatenate([[0.0], np.cumsum(steps)])
    k = np.clip(np.searchsorted(start_s, times_s, side="right") - 1, 0, len(steps) - 1)
    tau = times_s - start_s[k]
    acceleration = (speed[k + 1] - speed[k]) / np.maximum(durations[k], 1e-12)
    return start_m[k] + speed[k] * tau + 0.5 * acceleration * tau**2, lap_m
