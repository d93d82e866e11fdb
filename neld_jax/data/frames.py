"""Which frame the scans are in: the sensor's (what every layout expects) or the world's (already registered).

A common slip with real recordings: FAST-LIO2 publishes each scan twice, /cloud_registered_body (sensor frame)
and /cloud_registered (world frame), and its PCD saving writes world-frame points. World-frame scans read as
sensor-frame ones are moved by their pose a second time: the map is garbage and nothing says why. The check
here looks where each scan's points are: a LiDAR scan surrounds its sensor, so in the sensor frame its points lie
nearer the frame's origin than the scan's pose position t, and in the world frame nearer t. Each scan far enough
from the origin to tell (|t| >= 1 m and at least half the scan's typical range) votes by the 25th percentile of
its points' distances to the origin and to t.

Measured on the six FAST-LIO2 sequences of daxuanzi515/Fast-LIO2_SC-SLAM (benchmarks/RESULTS.md, thirteenth
session; 164-198 voters of up to 200 scans): sensor-frame scans vote "world" 0-35 % of the time (indoor scans whose
pose lies inside what they see vote either way), the same scans moved into the world frame 100 %; Hilti
quick-shack (a room, |t| < 0.5 m) has no voters, so nothing is decided there.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

MIN_VOTERS = 20  # fewer scans far enough from the origin decide nothing
WORLD_SHARE = 0.9  # this share of world votes (or more) stops the load
_MAX_SCANS, _MAX_POINTS = 200, 2000  # evenly spaced scans and points per scan: enough to vote, fast on any layout


def world_frame_votes(scans: list[np.ndarray], poses: np.ndarray, quantile: float = 25.0,
                      min_offset_m: float = 1.0) -> tuple[int, float]:
    """(voters, share of them whose points lie nearer their pose position than the origin); scans: [[N_i, 3]],
    poses: [S, 4, 4] sensor -> world. See the module docstring."""
    picked = np.unique(np.linspace(0, len(scans) - 1, min(len(scans), _MAX_SCANS)).round().astype(int))
    votes = []
    for i in picked:
        points = np.asarray(scans[i], dtype=np.float64)
        if len(points) == 0:
            continue
        points = points[:: max(1, len(points) // _MAX_POINTS)]
        position = poses[i, :3, 3]
        to_origin = np.percentile(np.linalg.norm(points, axis=1), quantile)
        to_position = np.percentile(np.linalg.norm(points - position, axis=1), quantile)
        if np.linalg.norm(position) < max(min_offset_m, 0.5 * min(to_origin, to_position)):
            continue  # too near the origin to tell
        votes.append(to_position < to_origin)
    return len(votes), float(np.mean(votes)) if votes else 0.0


def to_sensor_frame(scans: list[np.ndarray], poses: np.ndarray) -> list[np.ndarray]:
    """World-frame scans [[N_i, 3]] moved into their sensors' frames: R_i^T (p - t_i)."""
    return [(np.asarray(scan) - pose[:3, 3]) @ pose[:3, :3] for scan, pose in zip(scans, poses)]


def in_sensor_frame(seq: Sequence, where: str, scans_in_world_frame: bool = False) -> Sequence:
    """seq with its scans in the sensor frame: moved there when `scans_in_world_frame` (data.scans_in_world_frame),
    else checked; a DataError naming `where` when they look registered already (module docstring)."""
    if scans_in_world_frame:
        logger.info("%s: moving %d world-frame scans into their sensors' frames (data.scans_in_world_frame)", where,
                    seq.num_scans)
        return dataclasses.replace(seq, scans=to_sensor_frame(seq.scans, seq.poses))
    voters, share = world_frame_votes(seq.scans, seq.poses)
    if voters >= MIN_VOTERS and share >= WORLD_SHARE:
        raise DataError(
            f"{where}: the scans look registered already (world frame): in {share:.0%} of the {voters} scans far "
            "enough from the origin to tell, the points lie nearer the scan's pose than the origin. Give scans in "
            "the sensor frame (FAST-LIO2: /cloud_registered_body, not /cloud_registered or PCD/scans_*.pcd), or "
            "set data.scans_in_world_frame=True to have them moved into it")
    return seq
