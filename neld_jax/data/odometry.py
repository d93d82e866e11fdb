"""Initial poses from the scans themselves, for a sequence that comes without any: KISS-ICP (Vizzo et al., RA-L
2023; PyPI `kiss-icp`), the field's reference LiDAR-only odometry, over every input scan in time order. Nothing of
its algorithm is rewritten here: this module feeds it the sweeps, puts its answer on the sweeps' own stamps and
checks that it kept track (docs/datasets.md, "Scans without poses").

Time. Where the points carry their own times (raw sweeps), KISS-ICP deskews each sweep to its LAST point's instant
and gives the sensor's pose at that instant (measured on synthetic sweeps: its deskewed points lie 2 cm from the
truth in the frame at the sweep's end, 23 cm in the frame at its start). The sequence's stamps and ground truth
refer to the sweeps' stamps (an Ouster stamps a sweep at its start), so the poses are interpolated from those
end instants to the stamps. The sweeps are then deskewed again, each point along the finished trajectory
(deskewed_along): KISS-ICP deskews a sweep before registering it, by the motion of the sweep before; the trajectory
knows the motion during the sweep itself. Measured on 300 synthetic 10 Hz sweeps, keyframes one a second: the
keyframes' raw map under the true poses -3.73 nats deskewed by KISS-ICP, -4.23 along the trajectory (-5.09 with the
true motion, -3.74 not deskewed), and the classical baseline from them 2.6 cm -> 1.6 cm ATE (0.09 cm, 6.9 cm).

Losing track. A jump or a dropped stretch does not stop KISS-ICP: it registers the next sweep wherever its
constant-velocity guess and ICP lead, and the map bends. After each registration, the share of the sweep's
registration points within one of KISS-ICP's voxels of the previous sweep's (both in the world, under the new
poses) says how well the two still overlap. That share depends on the sensor (a non-repetitive pattern overlaps
less from sweep to sweep), so a sweep has lost track when its share falls below LOST_OVERLAP_RATIO times the median
of the last OVERLAP_WINDOW sweeps'; the load stops with one line naming the scan. Measured: synthetic 10 Hz
sweeps (32 beams, 60 m range, voxel 0.6 m) overlap 0.78-0.90, 0.20 after a jump into another courtyard (0.24 of the
median), 0.23 after a 2 s gap; FAST-LIO2's keyframes of four real handheld recordings (5 Hz, gaps up to 6 s, 40 m,
voxel 0.4 m) 0.61-0.69 in the median, and no tracked step below 0.71 of its median, while an absolute threshold of
0.5 would have stopped HKU_2 at a tracked step (0.49). What the share cannot see: ICP that slides along the scene
and keeps the overlap (on those keyframes, which are not KISS-ICP's input, it went 0.5-2 m wrong on single steps
with overlaps like the tracked steps'; the rule fired at that step on the main building, 60-200 keyframes later on
the other three). A gap of GAP_WARNING_PERIODS sweep periods or more in the stamps is warned about, naming the
scan: after a 1 s gap the synthetic overlap stays at 0.71 but the trajectory's error doubled.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

LOST_OVERLAP_RATIO = 0.5  # a sweep overlapping its predecessor less than this x the recent median has lost track
OVERLAP_WINDOW = 50  # sweeps whose median overlap is the recent median
MIN_OVERLAP_HISTORY = 5  # sweeps registered before the rule applies
GAP_WARNING_PERIODS = 5.0  # stamps further apart than this many median sweep periods: a dropped stretch
VOXELS_PER_RANGE = 1.0 / 100.0  # KISS-ICP's own voxel: a hundredth of the maximum range


def kiss_icp_odometry(scans: list[np.ndarray], point_times: list[np.ndarray] | None, labels: list[str],
                      min_range_m: float, max_range_m: float, keep_sweeps: bool = True,
                      progress: bool = False) -> tuple[np.ndarray, list[np.ndarray] | None, np.ndarray]:
    """KISS-ICP over scans [S] x [N_i, 3] (sensor frame, time order), deskewing where point_times [S] x [N_i]
    (seconds after each scan's stamp) are given. labels [S] name the scans in a lost-track error.

    Returns (poses [S, 4, 4] sensor -> world at each sweep's reference instant (scan 0's at the identity),
    the sweeps [S] x [M_i, 3] deskewed into the frame at that instant and cropped to the ranges (None unless
    keep_sweeps: a caller that deskews again need not hold a second copy of every sweep), offsets [S] seconds from
    each stamp to that instant: the last point's time, 0 without point times)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP
    from scipy.spatial import cKDTree
    from tqdm.auto import tqdm

    config = KISSConfig()
    config.data.min_range, config.data.max_range = float(min_range_m), float(max_range_m)
    config.data.deskew = point_times is not None
    config.mapping.voxel_size = VOXELS_PER_RANGE * float(max_range_m)
    odometry = KissICP(config)
    voxel = config.mapping.voxel_size
    poses, sweeps, previous, overlaps = [], [], None, []
    for i in tqdm(range(len(scans)), disable=not progress, desc="KISS-ICP odometry", unit="scan"):
        times = np.zeros(0) if point_times is None else np.asarray(point_times[i], np.float64)
        sweep, source = odometry.register_frame(np.asarray(scans[i], np.float64), times)
        pose = np.array(odometry.last_pose, np.float64)
        source_world = np.asarray(source) @ pose[:3, :3].T + pose[:3, 3]
        if previous is not None and len(source_world):
            overlap = float(np.mean(previous.query(source_world, distance_upper_bound=voxel)[0] <= voxel))
            if lost_track(np.asarray(overlaps), overlap):
                raise DataError(
                    f"{labels[i]}: KISS-ICP lost track here: {overlap:.0%} of its points lie within {voxel:.2f} m of "
                    f"{labels[i - 1]}'s after registration, against {recent_overlap(np.asarray(overlaps)):.0%} "
                    "from sweep to sweep before (a jump or a dropped stretch); give the sequence its poses "
                    "(poses.txt, an odometry topic) or split its scans here and run the parts apart")
            overlaps.append(overlap)
        if len(source_world):
            previous = cKDTree(source_world)
        poses.append(pose)
        if keep_sweeps:
            sweeps.append(np.asarray(sweep, np.float64))
    offsets = np.zeros(len(scans)) if point_times is None else last_point_offsets(point_times)
    return np.stack(poses), (sweeps if keep_sweeps else None), offsets


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
    out[:, :3, :3] = poses[lower, :3, :3] @ Rotation.from_rotvec(
        relative.as_rotvec() * fraction[:, None]).as_matrix()
    out[:, :3, 3] = poses[lower, :3, 3] + fraction[:, None] * (poses[upper, :3, 3] - poses[lower, :3, 3])
    return out


def deskewed_along(trajectory_times: np.ndarray, trajectory: np.ndarray, stamp: float, points: np.ndarray,
                   point_times: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
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
        logger.warning("%s: %.2f s after the previous scan (%.0f sweep periods; scans dropped?): KISS-ICP guesses "
                       "each sweep from constant velocity, check the trajectory here", labels[i], steps[i - 1],
                       steps[i - 1] / period)
    return gaps


def with_kiss_icp_poses(seq: Sequence, min_range_m: float, max_range_m: float, progress: bool = True) -> Sequence:
    """seq with KISS-ICP's poses (poses_from "kiss_icp"): raw sweeps (point_times set) deskewed and moved into the
    frame at their stamps, and the poses interpolated to the stamps; every scan cropped to the ranges as KISS-ICP
    reads it. Logs that it ran and how long it took."""
    labels = [seq.scan_label(i) for i in range(seq.num_scans)]
    if seq.timestamps is not None:
        if np.any(np.diff(seq.timestamps) <= 0):
            raise DataError(f"{seq.source or seq.name}: the scans' stamps must increase for odometry (first out of "
                            f"order: {labels[int(np.argmax(np.diff(seq.timestamps) <= 0)) + 1]})")
        warn_about_gaps(seq.timestamps, labels)
    point_times = seq.point_times
    logger.info("%s: making the initial poses from the %d scans with KISS-ICP (%s)", seq.source or seq.name,
                seq.num_scans, "deskewing by the points' own times" if point_times is not None else "rigid scans")
    if point_times is not None and seq.timestamps is None:
        logger.warning("%s: the scans have per-point times but no stamps: each pose and deskewed scan is the "
                       "sensor's at its sweep's last point", seq.source or seq.name)
    started = time.perf_counter()
    along_trajectory = point_times is not None and seq.timestamps is not None and seq.num_scans >= 2
    poses, sweeps, offsets = kiss_icp_odometry(seq.scans, point_times, labels, min_range_m, max_range_m,
                                               keep_sweeps=not along_trajectory, progress=progress)
    if along_trajectory:  # from the sweeps' last instants to their stamps, deskewed along the trajectory
        sweeps = [deskewed_along(seq.timestamps + offsets, poses, stamp, scan, times, min_range_m, max_range_m)
                  for stamp, scan, times in zip(seq.timestamps, seq.scans, point_times)]
        poses = poses_at_stamps(seq.timestamps, offsets, poses)
    logger.info("KISS-ICP odometry: %d scans in %.1f s (ranges %.1f-%.1f m, voxel %.2f m)", seq.num_scans,
                time.perf_counter() - started, min_range_m, max_range_m, VOXELS_PER_RANGE * max_range_m)
    return dataclasses.replace(seq, scans=sweeps, poses=poses, point_times=None, poses_from="kiss_icp")
