"""Frame conventions of the input, checked at load time: scans in the sensor frame, poses sensor -> world.

Scans: a common slip with real recordings is FAST-LIO2's /cloud_registered (world frame) or its PCD saving (world-
frame points) instead of /cloud_registered_body (sensor frame). World-frame scans read as sensor-frame ones are
moved by their pose a second time: the map is garbage and nothing says why. A LiDAR scan surrounds its sensor, so
in the sensor frame its points lie nearer the frame's origin than the scan's pose position t, and in the world
frame nearer t. Each scan far enough from the origin to tell (|t| >= 1 m and at least half the scan's typical
range) votes by the 25th percentile of its points' distances to the origin and to t.

Measured on the six FAST-LIO2 sequences of daxuanzi515/Fast-LIO2_SC-SLAM (EPYC,
2026-12-03; 164-198 voters of up to 200 scans): sensor-frame scans vote "world" 0-35 % of the time (indoor scans whose
pose lies inside what they see vote either way), the same scans moved into the world frame 100 %; Hilti
quick-shack (a room, |t| < 0.5 m) has no voters, so nothing is decided there.

Poses: a file of world -> sensor transforms (a tf lookup the other way round) gives the same garbage. Scans a
little apart along the route (moved 1 m or turned 10 deg, at most 5 scans on) overlap under the right poses: the
median distance from one's points to the other's nearest is small. Under the inverted poses it grows. The check
compares the two over up to 20 such pairs. On the six sequences above the inverted poses' distance is 5-7 times
the poses' own on the four handheld ones and 1.1-1.6 times on Riverside02's sparse keyframes 7 m apart, where
scans overlap little either way; poses count as inverted only when inverting them halves the distance.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.spatial import cKDTree

from neld_jax.data.scan_source import LazyScans, lazy
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.geometry import transform_points

logger = logging.getLogger(__name__)

MIN_VOTERS = 20  # fewer scans far enough from the origin decide nothing
WORLD_SHARE = 0.9  # this share of world votes (or more) stops the load
_MAX_SCANS, _MAX_POINTS = 200, 2000  # evenly spaced scans and points per scan: enough to vote, fast on any layout
MIN_PAIRS, MAX_PAIRS = 5, 20  # pairs of scans compared for the poses' direction
INVERTED_RATIO = 0.5  # poses count as inverted when inverting them halves the pairs' distance


def _thinned(scan: np.ndarray) -> np.ndarray:
    """Every k-th point of a scan [N, 3] (float64), about _MAX_POINTS of them: enough to vote or compare."""
    points = np.asarray(scan, dtype=np.float64)
    return points[:: max(1, len(points) // _MAX_POINTS)]


def world_frame_votes(
    scans: list[np.ndarray], poses: np.ndarray, quantile: float = 25.0, min_offset_m: float = 1.0
) -> tuple[int, float]:
    """(voters, share of them whose points lie nearer their pose position than the origin); scans: [[N_i, 3]],
    poses: [S, 4, 4] sensor -> world. See the module docstring."""
    picked = np.unique(np.linspace(0, len(scans) - 1, min(len(scans), _MAX_SCANS)).round().astype(int))
    votes = []
    for i in picked:
        if len(scans[i]) == 0:
            continue
        points = _thinned(scans[i])
        position = poses[i, :3, 3]
        to_origin = np.percentile(np.linalg.norm(points, axis=1), quantile)
        to_position = np.percentile(np.linalg.norm(points - position, axis=1), quantile)
        if np.linalg.norm(position) < max(min_offset_m, 0.5 * min(to_origin, to_position)):
            continue  # too near the origin to tell
        votes.append(to_position < to_origin)
    return len(votes), float(np.mean(votes)) if votes else 0.0


def to_sensor_frame(scans, poses: np.ndarray) -> LazyScans:
    """World-frame scans [[N_i, 3]] (a list or a LazyScans) moved into their sensors' frames: R_i^T (p - t_i), each
    when it is used (data.scan_source)."""
    sensor_from_world = np.linalg.inv(poses)
    return lazy(scans).map(lambda i, scan: transform_points(scan, sensor_from_world[i]))


def in_sensor_frame(seq: Sequence, where: str, scans_in_world_frame: bool = False) -> Sequence:
    """seq with its scans in the sensor frame: moved there when `scans_in_world_frame` (data.scans_in_world_frame),
    else checked; a DataError naming `where` when they look registered already (module docstring)."""
    if scans_in_world_frame:
        logger.info(
            "%s: moving %d world-frame scans into their sensors' frames (data.scans_in_world_frame)",
            where,
            seq.num_scans,
        )
        return dataclasses.replace(seq, scans=to_sensor_frame(seq.scans, seq.poses))
    voters, share = world_frame_votes(seq.scans, seq.poses)
    if voters >= MIN_VOTERS and share >= WORLD_SHARE:
        raise DataError(
            f"{where}: the scans look registered already (world frame): in {share:.0%} of the {voters} scans far "
            "enough from the origin to tell, the points lie nearer the scan's pose than the origin. Give scans in "
            "the sensor frame (FAST-LIO2: /cloud_registered_body, not /cloud_registered or PCD/scans_*.pcd), or "
            "set data.scans_in_world_frame=True to have them moved into it"
        )
    return seq


def _overlap_pairs(
    poses: np.ndarray, min_move_m: float = 1.0, min_turn_deg: float = 10.0, max_gap: int = 5
) -> list[tuple[int, int]]:
    """Up to MAX_PAIRS (i, j), j the first scan within max_gap after i that moved or turned that far from it."""
    pairs = []
    starts = np.unique(np.linspace(0, len(poses) - 2, min(len(poses) - 1, 4 * MAX_PAIRS)).round().astype(int))
    for i in starts if len(poses) >= 2 else []:
        for j in range(i + 1, min(i + max_gap, len(poses) - 1) + 1):
            relative = np.linalg.inv(poses[i]) @ poses[j]
            turn_deg = np.degrees(np.arccos(np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
            if np.linalg.norm(relative[:3, 3]) >= min_move_m or turn_deg >= min_turn_deg:
                pairs.append((int(i), j))
                break
        if len(pairs) >= MAX_PAIRS:
            break
    return pairs


def pair_distance(scans: list[np.ndarray], poses: np.ndarray, pairs: list[tuple[int, int]]) -> float:
    """Median over pairs (i, j) of the median distance from scan i's points to scan j's nearest, both registered
    with poses [S, 4, 4] (sensor -> world)."""

    def registered(k):
        return transform_points(_thinned(scans[k]), poses[k])

    return float(np.median([np.median(cKDTree(registered(j)).query(registered(i))[0]) for i, j in pairs]))


def inverted_poses(seq: Sequence, where: str) -> Sequence:
    """seq with its poses inverted (data.invert_poses: the file holds world -> sensor transforms)."""
    logger.info("%s: inverting %d poses (data.invert_poses: the file holds world -> sensor)", where, seq.num_scans)
    return dataclasses.replace(seq, poses=np.linalg.inv(seq.poses))


def check_pose_direction(seq: Sequence, where: str) -> None:
    """A DataError naming `where` when inverting seq's poses makes scans a little apart overlap far better
    (module docstring); scans in the sensor frame."""
    pairs = _overlap_pairs(seq.poses)
    if len(pairs) < MIN_PAIRS or any(len(seq.scans[k]) == 0 for pair in pairs for k in pair):
        return
    given = pair_distance(seq.scans, seq.poses, pairs)
    inverted = pair_distance(seq.scans, np.linalg.inv(seq.poses), pairs)
    if inverted < INVERTED_RATIO * given:
        raise DataError(
            f"{where}: the poses look inverted (world -> sensor): scans a little apart overlap far better under their "
            f"inverses (median nearest-point distance {inverted:.2f} m against {given:.2f} m over {len(pairs)} pairs). "
            "Give sensor -> world poses (TUM and KITTI files hold those), or set data.invert_poses=True"
        )
