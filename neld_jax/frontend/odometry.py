"""Initial poses from the scans themselves, for a sequence that comes without any: KISS-ICP (Vizzo et al., RA-L
2023; PyPI `kiss-icp`), the field's reference LiDAR-only odometry, over every input scan in time order. Nothing of
its algorithm is rewritten here: this module feeds it the sweeps, puts its answer on the sweeps' own stamps and
checks that it kept track (docs/datasets.md, "Scans without poses"); odometry_check.py checks its steps against
global registration of sampled pairs of scans, which does not slide with it.

Ranges. KISS-ICP registers with its own settings for the sensor, not the field's crop: its maximum range is the
sensor's, measured on the data (registration_range_m: the RANGE_PERCENTILE-th percentile of the point distances of
RANGE_SCANS scans evenly spaced over the recording, at most KISS-ICP's default 100 m), its voxel a hundredth of
that (as its own pipeline derives it) and its minimum range its default (0 m). The field's crop
(data.min_range_m..data.max_range_m, 40 m in the recording recipe) applies to the scans this module returns,
deskewed or not: only the registration sees the full range. Measured on a real 2 Hz car drive (HDL-32E, sweeps 4.5 m
apart): KISS-ICP at 40 m kept 57 % of the path length, at its own 100 m 96 %.

Time. Where the points carry their own times (raw sweeps) and the sweeps their stamps, KISS-ICP runs twice, its own
deskewing off both times (two_pass_odometry). The first pass registers each sweep as it is, and its pose is taken as
the sensor's at about the mean instant of the sweep's points; the second registers each sweep deskewed along that
first trajectory into the frame at its stamp, so its poses are at the stamps, which the sequence's ground truth
refers to (an Ouster stamps a sweep at its start). The two go together, each sweep read once, the second a sweep
behind. One pass does less for half the CPU: over six synthetic cars (300 sweeps each) KISS-ICP's own deskewing
erred more from sweep to sweep on every one (2.1-9.6 against 1.8-4.6 cm, 0.066-0.113 against 0.050-0.070 deg), its
ATE 0.054-0.267 against 0.051-0.268 m (benchmarks/RESULTS.md, "The front-end's pace"). The sweeps are then deskewed
along the finished trajectory (deskewed_along). Why not KISS-ICP's own deskewing: it deskews a sweep by the motion
its registration of the sweep before found, and that registration took the deskewing before it: where the motion
changes at once the two feed each other and the poses swing from sweep to sweep. Measured on an earlier synthetic
car's 300 raw sweeps (64 beams, 80 m, 11 m/s, turning into and out of its corners at once, which no car does):
heading errors of 1.27 deg RMS a sweep and 2.72 m ATE with KISS-ICP's own deskewing, 0.38 deg and 1.80 m not
deskewed, 0.22 deg and 0.15 m in two passes (0.14 m with every sweep deskewed along the true motion); on the car
that drives as cars do, KISS-ICP's own pipeline 0.167 against 0.166 m (benchmarks/RESULTS.md, "Peers"); over the
first 40 sweeps of the 10 m loop (seed 0) with KISS-ICP's own deskewing against two passes 7.0 against 7.5 cm at 2.1
m/s, 6.4 against 2.5 cm at 6.3 m/s. Earlier, with KISS-ICP's own deskewing, deskewing the sweeps again along the
finished trajectory took the 300 synthetic loop sweeps' keyframes' raw map under the true poses from -3.73 to -4.23
nats (-5.09 with the true motion, -3.74 not deskewed). Sweeps with point times but no stamps are registered once, by
KISS-ICP with its own deskewing, each pose the sensor's at its sweep's last point; where their times were derived
from the azimuths (data.sweep_times, at an assumed period) they are put that period apart and registered in two
passes instead (a common time scale: the poses do not depend on it).

Losing track. A jump or a dropped stretch does not stop KISS-ICP: it registers the next sweep wherever its
constant-velocity guess and ICP lead, and the map bends. After each registration, the share of the sweep's
registration points within one of KISS-ICP's voxels of those of the OVERLAP_SCANS sweeps before it (all in the world,
under the new poses: a local map, so that one odd scan does not decide) says how well it still overlaps. That share
depends on the sensor (a non-repetitive pattern overlaps less from sweep to sweep), so a sweep has lost track when its
share falls below LOST_OVERLAP_RATIO times the median of the last OVERLAP_WINDOW sweeps'. Such a sweep is registered
again (Tracker.recover: KISS-ICP's registration undone, then its ICP against the rebuilt local map from RANSAC on FPFH
features of the last OVERLAP_SCANS scans, RECOVERY_SEEDS runs, and from four motion guesses, the best overlap kept)
and KISS-ICP goes on from there, its motion model the motion of the last sweep it tracked itself (a jump or a dropped
stretch is no new velocity) unless the recovered step turned TURN_DEG more than that motion would over its length (a
handheld sensor turned: turned_more); only when no start brings the overlap back to the recent range does the load
stop, with one line naming the scan. Measured (docs/datasets.md, "A lost track", with the figures behind each
choice): the synthetic handheld walk that KISS-ICP alone loses at its first turn, 1.6-1.7 m ATE alone and 4-5 cm
recovered; the bare keyframes of a real car drive (Riverside02) whose dropped keyframe 13.1 m past the last stopped
the load, now posed to the end; what a sweep overlaps on synthetic sweeps and on real keyframes, and why the rule is
relative to the recent median. What the share cannot see: ICP that slides along the scene and keeps the overlap (on
FAST-LIO2's keyframes of four handheld recordings, which are not KISS-ICP's input, it went 0.5-2 m wrong on single
steps with overlaps like the tracked steps'; the rule fired at that step on the main building, 60-200 keyframes later
on the other three): odometry_check.py sees it. A gap of GAP_WARNING_PERIODS sweep periods or more in
the stamps is warned about, naming the scan: after a 1 s gap the synthetic overlap stays at 0.71 but the trajectory's
error doubled.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from typing import Callable

import numpy as np

from neld_jax.data.scan_source import LazyScans, lazy
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.frontend import odometry_check
from neld_jax.geometry import rotation_angles_deg

logger = logging.getLogger(__name__)

LOST_OVERLAP_RATIO = 0.5  # a sweep overlapping its predecessor less than this x the recent median has lost track
OVERLAP_WINDOW = 50  # sweeps whose median overlap is the recent median
MIN_OVERLAP_HISTORY = 5  # sweeps registered before the rule applies
GAP_WARNING_PERIODS = 5.0  # stamps further apart than this many median sweep periods: a dropped stretch
VOXELS_PER_RANGE = 1.0 / 100.0  # KISS-ICP's own voxel: a hundredth of the maximum range
# The sensor's range, measured: a high percentile of the point distances (a few stray far returns do not count) over
# a handful of scans spread over the recording (a long one is not read twice).
RANGE_PERCENTILE = 99.9
RANGE_SCANS = 8
# Scans whose map points rebuild KISS-ICP's local map when a registration is undone. Measured on HKU_1 (keyframes
# 0.23 m apart, 50 m range), the odometry's every-scan map: 20 (4.6 m of path, far less than KISS-ICP's map holds)
# -2.79 nats, scan 130 lost after the thinned map; 100 -3.05, 400 -3.05. Riverside02: 20 -3.30, 100 -3.24.
RECENT_FRAMES = 100
OVERLAP_SCANS = 5  # a scan's overlap is with the registration points of this many scans before it (module docstring)
FEATURE_VOXELS = 2.0  # a recovery's FPFH and RANSAC on a grid twice KISS-ICP's voxel (odometry_check.py's)
FEATURE_RADIUS_VOXELS = 5.0  # FPFH radius, in feature-grid voxels (the classical baseline's ratio)
# A recovery's RANSAC: RECOVERY_SEEDS runs of all RECOVERY_ITERATIONS draws (no confidence stop). Measured on the
# synthetic keyframes' 6 m jump (tests/test_odometry.py) against the last five scans: 10 of 10 runs within 1 m of the
# truth so; 2-6 of 10 with 20 000 draws and Open3D's 99.9 % confidence stop (its threads make runs differ), 0-1 of 10
# against the previous scan alone.
RECOVERY_SEEDS = 2
RECOVERY_ITERATIONS = 100_000
# A recovered step that turns this much more than the motion before it (over the step's length) was a turn, and
# KISS-ICP's motion model goes on from it; else (a jump, a dropped stretch, a slide) the model keeps the motion before
# it (module docstring).
TURN_DEG = 5.0
RECOVERY_ICP_VOXELS = 3.0  # ICP from RANSAC's pose pairs points this far apart first, then as KISS-ICP does
# KISS-ICP's ICP stops when a step moves less than this (its own default: 1e-4), in both passes. Measured
# (benchmarks/frontend_pace.py, 2 cores at load 4-5): KITTI 00's 101 sweeps 0.071 against 0.091 s a sweep, ATE 0.1335
# against 0.1333 m; the synthetic car's 200 raw sweeps in two passes 0.18 against 0.26 s, 0.146 against 0.137 m. Its
# iteration cap at 10 (KISS-ICP's default: 500) saves 3 % on KITTI 00 and loses its 2 Hz thinning (19.6 m ATE against
# 0.136 m); a voxel of 1.5 % of the range 0.182 m on the car.
CONVERGENCE = 1e-3
# KISS-ICP's poses of the same sweeps differ in their last bits from run to run (about 5e-15 m), and a second pass over
# sweeps deskewed along the first turned that into centimetres (3.6-4.2 cm over 80 sweeps of the 10 m loop: a point
# on a voxel's edge goes to the other voxel). Rounded to a nanometre, two runs agree to KISS-ICP's last bits.
POSE_DECIMALS = 9


def kiss_icp_odometry(
    scans,
    point_times,
    labels: list[str],
    ranges: tuple[float, float],
    keep_sweeps: bool = True,
    progress: bool = False,
    motion_guesses: dict | None = None,
    seen: Callable | None = None,
) -> tuple[np.ndarray, list[np.ndarray] | None, np.ndarray]:
    """KISS-ICP over scans [S] x [N_i, 3] (sensor frame, time order; a list or a LazyScans, read one at a time),
    deskewing where point_times [S] x [N_i] (seconds after each scan's stamp) are given; a scan that lost track is
    registered again (Tracker.register). Of the scans it keeps only its poses (and its bounded local map).
    ranges: (min, max) m of its registration. motion_guesses: {scan i: its motion [4, 4] from scan i - 1} that
    replace KISS-ICP's constant-velocity guess for those scans (odometry_check.py: global registration's steps).
    labels [S] name the scans in the logs and in the error of a track that could not be recovered. seen(i, scan
    [N_i, 3]) is called with each scan as it is read (odometry_check registers its pairs from that one read).

    Returns (poses [S, 4, 4] sensor -> world at each sweep's reference instant (scan 0's at the identity; rounded to
    POSE_DECIMALS), the sweeps [S] x [M_i, 3] deskewed into the frame at that instant and cropped to the ranges (None
    unless keep_sweeps: a caller that deskews again need not hold a second copy of every sweep), offsets [S] seconds
    from each stamp to that instant: the last point's time, 0 without point times)."""
    from tqdm.auto import tqdm

    tracker = Tracker(*ranges, deskew=point_times is not None)
    poses, sweeps, offsets = [], [], np.zeros(len(scans))
    for i in tqdm(range(len(scans)), disable=not progress, desc="KISS-ICP odometry", unit="scan"):
        scan = np.asarray(scans[i], np.float64)
        if seen is not None:
            seen(i, scan)
        times = np.zeros(0) if point_times is None else np.asarray(point_times[i], np.float64)
        if len(times):  # the instant its pose refers to
            offsets[i] = float(np.max(times))
        sweep = tracker.register(scan, times, labels, i, (motion_guesses or {}).get(i))
        poses.append(tracker.pose())
        if keep_sweeps:
            sweeps.append(np.asarray(sweep, np.float64))
    return np.stack(poses), (sweeps if keep_sweeps else None), offsets


class Tracker:
    """KISS-ICP (`kiss`: its KissICP, driven by the caller) and what a recovery from a lost track needs: the last
    RECENT_FRAMES scans' map points (KISS-ICP's local map holds no history to undo a registration with), the
    deviations from its motion model that its adaptive threshold learned, the overlaps, and the last OVERLAP_SCANS
    scans' registration points in the world."""

    def __init__(self, min_range_m: float, max_range_m: float, deskew: bool):
        from kiss_icp.kiss_icp import KissICP

        self.config = kiss_icp_config(min_range_m, max_range_m, deskew)
        self.voxel = self.config.mapping.voxel_size
        self.kiss = KissICP(self.config)
        self.frames = collections.deque(maxlen=RECENT_FRAMES)  # (map points [M, 3] sensor frame, pose [4, 4])
        self.deviations = []  # [4, 4] each: a kept scan's pose against KISS-ICP's guess of it
        self.steady = np.eye(4)  # [4, 4] the motion of the last scan KISS-ICP tracked itself (not recovered)
        self.overlaps = np.zeros(0)  # [K] each kept scan's overlap with the OVERLAP_SCANS scans before
        self.recent = collections.deque(maxlen=OVERLAP_SCANS)  # the last scans' registration points [N, 3], world
        self.previous = None  # a cKDTree of their union (None before the first scan)

    def register(
        self, scan: np.ndarray, times: np.ndarray, labels: list[str], i: int, motion_guess: np.ndarray | None = None
    ) -> np.ndarray:
        """Register scan i [N, 3] (sensor frame; deskewed by its point times [N] where given, else empty) after the
        scans before it; motion_guess [4, 4] replaces KISS-ICP's constant-velocity guess. A scan that lost track is
        registered again (recover); a DataError naming it (labels [S]) where that fails. Returns the sweep [M, 3] as
        KISS-ICP deskewed and cropped it."""
        if motion_guess is not None:  # KISS-ICP starts its ICP (and deskews) by last_delta
            self.kiss.last_delta = np.array(motion_guess, np.float64)
        before = self.motion()
        sweep, source = self.kiss.register_frame(scan, times)
        overlap = self.overlap(source, self.kiss.last_pose)
        if overlap is not None and lost_track(self.overlaps, overlap):
            recovered = self.recover(sweep, source, before)
            recent = recent_overlap(self.overlaps)
            if lost_track(self.overlaps, recovered):
                raise DataError(
                    f"{labels[i]}: KISS-ICP lost track here: {overlap:.0%} of its points lie within "
                    f"{self.voxel:.2f} m of those of the {len(self.recent)} scans up to {labels[i - 1]} after "
                    f"registration, against {recent:.0%} for the scans before, and {recovered:.0%} registered again "
                    "to its local map from FPFH features or from no motion, constant velocity, the last turn or two "
                    "steps (a jump or a dropped stretch); give the sequence its poses (poses.txt, an odometry topic) "
                    "or split its scans here and run the parts apart"
                )
            logger.info(
                "%s: KISS-ICP lost track (%.0f%% overlap with the %d scans up to %s after registration, against "
                "%.0f%% before); registered again: %.0f%%",
                labels[i],
                100 * overlap,
                len(self.recent),
                labels[i - 1],
                100 * recent,
                100 * recovered,
            )
            overlap = recovered
            before = None
        self.keep(sweep, source, overlap, before)
        return sweep

    def pose(self) -> np.ndarray:
        """KISS-ICP's last pose [4, 4], rounded to POSE_DECIMALS."""
        return np.round(np.array(self.kiss.last_pose, np.float64), POSE_DECIMALS)

    def motion(self) -> tuple[np.ndarray, np.ndarray]:
        """(last pose [4, 4], last motion [4, 4]): KISS-ICP's state before a registration."""
        return np.array(self.kiss.last_pose, np.float64), np.array(self.kiss.last_delta, np.float64)

    def overlap(self, source: np.ndarray, pose: np.ndarray) -> float | None:
        """The share of the registration points source [N, 3] (sensor frame) at pose [4, 4] within one voxel of those
        of the last OVERLAP_SCANS scans (module docstring); None for the first scan or an empty one."""
        if self.previous is None or not len(source):
            return None
        world = np.asarray(source) @ pose[:3, :3].T + pose[:3, 3]
        return float(np.mean(self.previous.query(world, distance_upper_bound=self.voxel)[0] <= self.voxel))

    def keep(self, sweep: np.ndarray, source: np.ndarray, overlap: float | None, before: tuple | None) -> None:
        """Record the scan KISS-ICP has just registered (sweep [M, 3] deskewed, its registration points source
        [N, 3]) at its last pose, with its overlap (None: the first) and KISS-ICP's state before it (motion();
        None for a recovered scan: its deviation from the motion model is no ICP error for the threshold to learn)."""
        from scipy.spatial import cKDTree

        pose = np.array(self.kiss.last_pose, np.float64)
        self.frames.append((self.kiss.voxelize(np.asarray(sweep))[1], pose))
        if before is not None:
            self.deviations.append(np.linalg.inv(before[0] @ before[1]) @ pose)
            self.steady = np.linalg.inv(before[0]) @ pose
        if overlap is not None:
            self.overlaps = np.append(self.overlaps, overlap)
        if len(source):
            self.recent.append(np.asarray(source) @ pose[:3, :3].T + pose[:3, 3])
            self.previous = cKDTree(np.concatenate(self.recent))

    def recover(self, sweep: np.ndarray, source: np.ndarray, before: tuple[np.ndarray, np.ndarray]) -> float:
        """Undo KISS-ICP's registration of a scan that lost track (sweep [M, 3] deskewed, registration points source
        [N, 3]; before: motion() before it) and register it again, by KISS-ICP's ICP against the rebuilt local map,
        from each of: RANSAC on FPFH features against the local map of the last OVERLAP_SCANS scans (RECOVERY_SEEDS
        runs), no motion, constant velocity, the last turn without the last step, two steps (a dropped scan).
        Keeps the result that overlaps the last scans most, as KISS-ICP's last pose and in its map, with the motion
        of the last scan KISS-ICP tracked itself as its motion model unless the result turned more (turned_more);
        returns that overlap."""
        from kiss_icp.threshold import get_threshold_estimator

        self.kiss.local_map.clear()
        for points, pose in self.frames:
            self.kiss.local_map.update(points, pose)
        self.kiss.adaptive_threshold = get_threshold_estimator(self.config)
        for deviation in self.deviations:  # what it learned, less the lost registration
            self.kiss.adaptive_threshold.update_model_deviation(deviation)
        sigma = self.kiss.adaptive_threshold.get_threshold()
        # RANSAC's pose is off by up to a voxel or two: ICP pairs points further apart first
        coarse = [
            self._icp(source, start, RECOVERY_ICP_VOXELS * self.voxel, self.voxel)
            for start in self._feature_guesses(sweep)
        ]
        poses = [self._icp(source, start, 3 * sigma, sigma) for start in coarse + guesses(*before)]
        overlaps = [self.overlap(source, pose) or 0.0 for pose in poses]
        best = poses[int(np.argmax(overlaps))]
        self.kiss.local_map.update(self.kiss.voxelize(np.asarray(sweep))[1], best)
        step = np.linalg.inv(before[0]) @ best
        # a jump or a dropped stretch is no new velocity: the next scan is guessed from the last tracked motion
        self.kiss.last_pose, self.kiss.last_delta = best, step if turned_more(step, self.steady) else self.steady
        return max(overlaps)

    def _icp(self, source: np.ndarray, start: np.ndarray, distance: float, kernel: float) -> np.ndarray:
        """KISS-ICP's registration of the points source [N, 3] (sensor frame) to its local map from the pose start
        [4, 4], pairing points within `distance`, its robust kernel's scale `kernel`: the pose [4, 4]."""
        return self.kiss.registration.align_points_to_map(
            points=source,
            voxel_map=self.kiss.local_map,
            initial_guess=start,
            max_correspondance_distance=distance,
            kernel=kernel,
        )

    def _feature_guesses(self, sweep: np.ndarray) -> list[np.ndarray]:
        """Poses [RECOVERY_SEEDS][4, 4] of sweep [M, 3] (sensor frame) in the world from RANSAC on FPFH features
        (feature_registration.py, on a grid FEATURE_VOXELS x KISS-ICP's voxel) against the local map of the last
        OVERLAP_SCANS scans' map points, one a seed."""
        from neld_jax.frontend.feature_registration import fpfh_features, point_cloud, ransac_alignment

        recent = list(self.frames)[-OVERLAP_SCANS:]
        local = np.concatenate([points @ pose[:3, :3].T + pose[:3, 3] for points, pose in recent])
        voxel = FEATURE_VOXELS * self.voxel
        source, target = (
            fpfh_features(point_cloud(points), voxel, FEATURE_RADIUS_VOXELS * voxel) for points in (sweep, local)
        )
        return [
            ransac_alignment(source, target, voxel, RECOVERY_ITERATIONS, seed, 1.0) for seed in range(RECOVERY_SEEDS)
        ]


def guesses(last_pose: np.ndarray, last_delta: np.ndarray) -> list[np.ndarray]:
    """Where a scan may be [4][4, 4] from the pose [4, 4] and motion [4, 4] of the scan before: no motion, constant
    velocity (KISS-ICP's own guess), the last turn without the last step (a sensor turned on the spot), two steps
    of it (a scan dropped in between)."""
    turn = np.eye(4)
    turn[:3, :3] = last_delta[:3, :3]
    return [last_pose, last_pose @ last_delta, last_pose @ turn, last_pose @ last_delta @ last_delta]


def turned_more(step: np.ndarray, motion: np.ndarray) -> bool:
    """Whether the recovered step [4, 4] turned TURN_DEG more than the motion [4, 4] before it would over the step's
    length (a longer step along a bend turns as much more as it is longer): a turn, not a jump along the way."""
    lengths = np.linalg.norm(step[:3, 3]), np.linalg.norm(motion[:3, 3])
    step_deg, motion_deg = rotation_angles_deg(np.stack([step[:3, :3], motion[:3, :3]]))
    return step_deg > motion_deg * max(1.0, lengths[0] / max(lengths[1], 1e-9)) + TURN_DEG


def recent_overlap(overlaps: np.ndarray) -> float:
    """The median of the last OVERLAP_WINDOW sweep-to-sweep overlaps [K] (K >= 1)."""
    return float(np.median(overlaps[-OVERLAP_WINDOW:]))


def lost_track(overlaps: np.ndarray, overlap: float) -> bool:
    """Whether a sweep overlapping its predecessor by `overlap` (a share in [0, 1]) has lost track, after the
    sweeps before it overlapped theirs by overlaps [K] (module docstring): below LOST_OVERLAP_RATIO x their recent
    median, once MIN_OVERLAP_HISTORY of them are known."""
    return len(overlaps) >= MIN_OVERLAP_HISTORY and overlap < LOST_OVERLAP_RATIO * recent_overlap(overlaps)


def last_point_offsets(point_times: list[np.ndarray]) -> np.ndarray:
    """[S] seconds from each sweep's stamp to its last point (per-point times [S] x [N_i]; 0 for an empty sweep):
    the instant KISS-ICP's pose of a deskewed sweep refers to."""
    return np.array([float(np.max(t)) if len(t) else 0.0 for t in point_times])


def poses_at_stamps(timestamps: np.ndarray, offsets: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses [S, 4, 4] at the stamps [S] from poses [S, 4, 4] at stamps + offsets [S] (interpolate_poses), scan 0
    at the identity as KISS-ICP starts."""
    at_stamps = interpolate_poses(timestamps + offsets, poses, timestamps)
    return np.linalg.inv(at_stamps[0]) @ at_stamps


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses [Q, 4, 4] at query [Q] seconds from poses [S, 4, 4] at increasing times [S] (S >= 2): the rotation by
    slerp and the position linearly between the two nearest, extrapolated from the first or last two outside."""
    from scipy.spatial.transform import Rotation

    upper = np.clip(np.searchsorted(times, query), 1, len(times) - 1)
    lower = upper - 1
    fraction = (query - times[lower]) / np.maximum(times[upper] - times[lower], 1e-12)
    relative = Rotation.from_matrix(np.einsum("qji,qjk->qik", poses[lower, :3, :3], poses[upper, :3, :3]))
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3] = poses[lower, :3, :3] @ Rotation.from_rotvec(relative.as_rotvec() * fraction[:, None]).as_matrix()
    out[:, :3, 3] = poses[lower, :3, 3] + fraction[:, None] * (poses[upper, :3, 3] - poses[lower, :3, 3])
    return out


def deskewed_along(
    trajectory_times: np.ndarray,
    trajectory: np.ndarray,
    stamp: float,
    points: np.ndarray,
    point_times: np.ndarray,
    min_range_m: float,
    max_range_m: float,
) -> np.ndarray:
    """A raw sweep's points [N, 3] (each in the sensor frame at stamp + its point_times [N] seconds) within the
    ranges, moved into the sensor frame at `stamp` along the trajectory [S, 4, 4] at trajectory_times [S]
    (interpolate_poses): [M, 3]. Each point moves by the motion the trajectory has between the stamp and its own
    instant, not by a constant velocity guessed from the sweep before (module docstring)."""
    distance = np.linalg.norm(points, axis=1)
    keep = (distance >= min_range_m) & (distance <= max_range_m)
    instants, which = np.unique(point_times[keep], return_inverse=True)  # a spinning LiDAR's columns share times
    at = interpolate_poses(trajectory_times, trajectory, np.r_[stamp, stamp + instants])
    relative = np.linalg.inv(at[0]) @ at[1:]  # [U, 4, 4]: the sensor at each instant in the frame at the stamp
    rotation, translation = relative[which, :3, :3], relative[which, :3, 3]
    return np.einsum("nij,nj->ni", rotation, points[keep]) + translation


def warn_about_gaps(timestamps: np.ndarray, labels: list[str]) -> np.ndarray:
    """Warn (naming the scan) where consecutive stamps [S] lie GAP_WARNING_PERIODS median periods apart or more;
    returns the indices [G] of the scans after a gap."""
    if len(timestamps) < 3:
        return np.zeros(0, dtype=np.int64)
    steps = np.diff(timestamps)
    period = float(np.median(steps))
    gaps = np.flatnonzero(steps >= GAP_WARNING_PERIODS * period) + 1
    for i in gaps:
        logger.warning(
            "%s: %.2f s after the previous scan (%.0f sweep periods; scans dropped?): KISS-ICP guesses "
            "each sweep from constant velocity, check the trajectory here",
            labels[i],
            steps[i - 1],
            steps[i - 1] / period,
        )
    return gaps


def kiss_icp_default_ranges() -> tuple[float, float]:
    """KISS-ICP's own (minimum, maximum) range in metres (its KISSConfig's defaults: 0 and 100 m)."""
    from kiss_icp.config import KISSConfig

    data = KISSConfig().data
    return float(data.min_range), float(data.max_range)


def sensor_range_m(scans) -> float:
    """The sensor's range measured on scans [S] x [N_i, 3] (sensor frame; a list or a LazyScans): the
    RANGE_PERCENTILE-th percentile of the point distances of RANGE_SCANS scans evenly spaced over them, at most
    KISS-ICP's default maximum range; that maximum for scans without points."""
    cap = kiss_icp_default_ranges()[1]
    picked = np.unique(np.linspace(0, len(scans) - 1, min(len(scans), RANGE_SCANS)).round().astype(int))
    distances = np.concatenate([np.linalg.norm(np.asarray(scans[i], np.float64), axis=1) for i in picked])
    return min(float(np.percentile(distances, RANGE_PERCENTILE)), cap) if len(distances) else cap


def registration_range_m(seq: Sequence, override_m: float = 0.0) -> float:
    """The maximum range [m] KISS-ICP registers seq's scans with: override_m where > 0 (a caller that knows it),
    else the sensor's, measured (sensor_range_m). Logs it, the voxel it gives and the evidence in one line."""
    where = seq.source or seq.name
    if override_m > 0:
        range_m, evidence = float(override_m), "given"
    else:
        range_m = sensor_range_m(seq.scans)
        cap = kiss_icp_default_ranges()[1]
        evidence = (
            f"measured: the {RANGE_PERCENTILE:g}th percentile of the point distances of "
            f"{min(seq.num_scans, RANGE_SCANS)} scans evenly spaced, at most KISS-ICP's default {cap:g} m"
        )
    logger.info(
        "%s: KISS-ICP registers the points within %.1f m (%s), voxel %.2f m (a hundredth of it, KISS-ICP's "
        "rule); the scans after it keep the field's crop",
        where,
        range_m,
        evidence,
        VOXELS_PER_RANGE * range_m,
    )
    return range_m


def with_kiss_icp_poses(
    seq: Sequence,
    min_range_m: float,
    max_range_m: float,
    progress: bool = True,
    odometry_range_m: float = 0.0,
    unstamped_period_s: float | None = None,
) -> Sequence:
    """seq with KISS-ICP's poses (poses_from "kiss_icp"): raw sweeps with stamps (point_times set) registered in two
    passes (two_pass_odometry), deskewed along the result into the frame at their stamps; every scan returned cropped
    to the field's ranges min_range_m..max_range_m. KISS-ICP itself registers the points within its default minimum
    range and odometry_range_m (0: registration_range_m measures it), its voxel a hundredth of that (module
    docstring, "Ranges"). unstamped_period_s: sweeps with point times and no stamps are put this far apart for the
    two passes (their times derived from azimuths at that period: the poses do not depend on it); None: they are
    registered once, with KISS-ICP's own deskewing. The poses are checked against global registration of sampled
    pairs of the scans, and made again from its steps where they disagree (odometry_check.checked_odometry: a
    DataError where they still do). Logs that it ran and how long it took.

    The sweeps are read one at a time and KISS-ICP keeps nothing of them but its poses (and its local map); the
    returned scans are a view (data.scan_source) that deskews and crops each sweep again when it is used."""
    labels = [seq.scan_label(i) for i in range(seq.num_scans)]
    stamps = _checked_stamps(seq, labels, unstamped_period_s)
    point_times = None if seq.point_times is None else checked_point_times(seq, labels)
    logger.info(
        "%s: making the initial poses from the %d scans with KISS-ICP (%s)",
        seq.source or seq.name,
        seq.num_scans,
        "deskewing by the points' own times" if point_times is not None else "rigid scans",
    )
    if point_times is not None and stamps is None:
        logger.warning(
            "%s: the scans have per-point times but no stamps: each pose and deskewed scan is the "
            "sensor's at its sweep's last point (KISS-ICP's deskewed sweeps are kept in memory)",
            seq.source or seq.name,
        )
    started = time.perf_counter()
    crop = (min_range_m, max_range_m)
    registration = (kiss_icp_default_ranges()[0], odometry_range_m or registration_range_m(seq))
    two_passes = point_times is not None and stamps is not None and seq.num_scans >= 2

    def odometry(motion_guesses: dict, seen: Callable) -> tuple:  # (poses [S, 4, 4], deskewed sweeps or None)
        if two_passes:
            return two_pass_odometry(
                seq.scans, point_times, stamps, labels, registration, progress, motion_guesses, seen
            ), None
        return kiss_icp_odometry(
            seq.scans,
            point_times,
            labels,
            registration,
            keep_sweeps=point_times is not None,
            progress=progress,
            motion_guesses=motion_guesses,
            seen=seen,
        )[:2]

    # checked against global registration of sampled pairs of the scans as they came, from the odometry's one read
    # of each (odometry_check.py)
    poses, sweeps = odometry_check.checked_odometry(
        seq.scans, odometry, labels, registration, VOXELS_PER_RANGE * registration[1], seq.source or seq.name
    )
    if two_passes:
        sweeps = deskewed_sweeps(seq.scans, point_times, stamps, np.zeros(seq.num_scans), poses, crop)
        return _with_odometry(seq, sweeps, poses, started, registration, crop)
    cropped = kiss_icp_crop(*crop)  # KISS-ICP returns its own range: the field's crop from here on
    sweeps = lazy(seq.scans).map(cropped) if sweeps is None else [cropped(i, s) for i, s in enumerate(sweeps)]
    return _with_odometry(seq, sweeps, poses, started, registration, crop)


def _checked_stamps(seq: Sequence, labels: list[str], unstamped_period_s: float | None) -> np.ndarray | None:
    """seq's stamps [S] (DataError when they do not increase; gaps warned about), or for raw sweeps without any,
    stamps unstamped_period_s apart (None without that period)."""
    if seq.timestamps is None:
        if seq.point_times is None or unstamped_period_s is None:
            return None
        logger.info(
            "%s: the sweeps have no stamps: put %.3f s apart for the odometry's two passes (assumed; it sets "
            "only their time scale, not the poses)",
            seq.source or seq.name,
            unstamped_period_s,
        )
        return float(unstamped_period_s) * np.arange(seq.num_scans, dtype=np.float64)
    if np.any(np.diff(seq.timestamps) <= 0):
        raise DataError(
            f"{seq.source or seq.name}: the scans' stamps must increase for odometry (first out of "
            f"order: {labels[int(np.argmax(np.diff(seq.timestamps) <= 0)) + 1]})"
        )
    warn_about_gaps(seq.timestamps, labels)
    return seq.timestamps


def _with_odometry(
    seq: Sequence,
    sweeps,
    poses: np.ndarray,
    started: float,
    registration: tuple[float, float],
    crop: tuple[float, float],
) -> Sequence:
    """seq with the odometry's sweeps [S] x [M_i, 3] and poses [S, 4, 4]; logs how long it took (since `started`, a
    time.perf_counter() value), KISS-ICP's ranges and voxel (registration: (min, max) m) and the crop (min, max) m."""
    logger.info(
        "KISS-ICP odometry: %d scans in %.1f s (registered within %.1f-%.1f m, voxel %.2f m; scans kept "
        "within %.1f-%.1f m)",
        seq.num_scans,
        time.perf_counter() - started,
        *registration,
        VOXELS_PER_RANGE * registration[1],
        *crop,
    )
    return dataclasses.replace(seq, scans=sweeps, point_times=None, poses=poses, poses_from="kiss_icp")


def two_pass_odometry(
    scans,
    point_times,
    stamps: np.ndarray,
    labels: list[str],
    ranges: tuple[float, float],
    progress: bool = False,
    motion_guesses: dict | None = None,
    seen: Callable | None = None,
) -> np.ndarray:
    """KISS-ICP twice over raw sweeps scans [S] x [N_i, 3] with point_times [S] x [N_i] (seconds after their stamps
    [S]; lists or LazyScans), its own deskewing off both times -> poses [S, 4, 4] at the stamps, scan 0 at the
    identity (module docstring, "Time"). The first pass registers each sweep as it is, its pose the sensor's at
    about the mean instant of its points; the second registers each sweep deskewed along that trajectory into the
    frame at its stamp. Each sweep is read once: the two passes go together, the second a sweep or two behind, as
    soon as the first's trajectory reaches past the sweep's last point (from there on its interpolation between the
    two nearest poses no longer changes). ranges: (min, max) m of KISS-ICP's registration; motion_guesses
    (kiss_icp_odometry) serve both passes (a step between sweeps is about the same between their mean instants and
    between their stamps); seen as kiss_icp_odometry's."""
    from tqdm.auto import tqdm

    first, second = Tracker(*ranges, deskew=False), Tracker(*ranges, deskew=False)
    guesses = motion_guesses or {}
    instants, trajectory, poses = [], [], []
    waiting = collections.deque()  # (i, sweep, its point times, its last instant): read, not yet in the second pass
    for i in tqdm(range(len(scans)), disable=not progress, desc="KISS-ICP odometry, two passes", unit="scan"):
        scan, times = np.asarray(scans[i], np.float64), np.asarray(point_times[i], np.float64)
        if seen is not None:
            seen(i, scan)
        first.register(scan, np.zeros(0), labels, i, guesses.get(i))
        instants.append(stamps[i] + (float(np.mean(times)) if len(times) else 0.0))
        trajectory.append(first.pose())
        waiting.append((i, scan, times, stamps[i] + (float(np.max(times)) if len(times) else 0.0)))
        while waiting and (waiting[0][3] < instants[-1] or i == len(scans) - 1):
            j, sweep, sweep_times, _ = waiting.popleft()
            deskewed = deskewed_along(np.array(instants), np.stack(trajectory), stamps[j], sweep, sweep_times, *ranges)
            second.register(deskewed, np.zeros(0), labels, j, guesses.get(j))
            poses.append(second.pose())
    poses = np.stack(poses)
    return np.linalg.inv(poses[0]) @ poses


def checked_point_times(seq: Sequence, labels: list[str]) -> LazyScans:
    """seq.point_times as a LazyScans whose item i is a DataError naming scan i when its length is not the scan's
    point count (checked when the two are read together)."""

    def checked(i: int, scan: np.ndarray, times: np.ndarray) -> np.ndarray:
        if len(times) != len(scan):
            raise DataError(
                f"{seq.source or seq.name}: {labels[i]} has {len(scan)} points and {len(times)} point times"
            )
        return times

    return lazy(seq.scans).map(checked, lazy(seq.point_times))


def deskewed_sweeps(
    scans, point_times, stamps: np.ndarray, offsets: np.ndarray, poses: np.ndarray, ranges: tuple[float, float]
) -> LazyScans:
    """The raw sweeps scans [S] x [N_i, 3] with point_times [S] x [N_i] (lists or LazyScans) moved into the frame at
    their stamps [S] along KISS-ICP's trajectory (poses [S, 4, 4] at stamps + offsets [S]) and cropped to ranges
    (min, max) m: deskewed_along for each sweep when it is used."""
    trajectory_times = stamps + offsets
    return lazy(scans).map(
        lambda i, scan, times: deskewed_along(trajectory_times, poses, stamps[i], scan, times, *ranges),
        lazy(point_times),
    )


def kiss_icp_config(min_range_m: float, max_range_m: float, deskew: bool):
    """KISS-ICP's own configuration (KISSConfig) for the ranges [m], its voxel a hundredth of the maximum range
    (VOXELS_PER_RANGE, as its own pipeline derives it), deskewing by the points' times or not."""
    from kiss_icp.config import KISSConfig

    config = KISSConfig()
    config.data.min_range, config.data.max_range = float(min_range_m), float(max_range_m)
    config.data.deskew = deskew
    config.mapping.voxel_size = VOXELS_PER_RANGE * float(max_range_m)
    config.registration.convergence_criterion = CONVERGENCE
    return config


def kiss_icp_crop(min_range_m: float, max_range_m: float):
    """transform(i, scan [N, 3]) -> the scan's points within the ranges as KISS-ICP's preprocessor keeps them
    (without deskewing): what it returns for a rigid scan."""
    from kiss_icp.preprocess import get_preprocessor

    preprocessor = get_preprocessor(kiss_icp_config(min_range_m, max_range_m, deskew=False))
    return lambda _, scan: preprocessor.preprocess(np.asarray(scan, np.float64), np.zeros(0), np.eye(4))
