"""The baseline's last step: whose distances travelled its poses keep (docs/evaluation.md, "Weak directions and the
distance travelled").

Scan registration fixes a path's shape, but not always its length: keyframes registered metres apart on a straight
road came out 0.22 % short per link against the ground truth where the LiDAR odometry over every consecutive sweep
was within 0.04 % (KITTI odometry 00, frames 15-100, the ground truth's own jump over frames 38-46 left out; the
run's KISS-ICP odometry), and along a street that no surface faces a registration cannot tell the length at all.
So the baseline's poses take the input's distance travelled over every window of distance_window_m
(trajectory.with_distances_of: their own rotations and directions of travel) unless their own distances give a
crisper raw map on every query draw: a loop that the baseline closed and a drifting input could not keeps the
baseline's. On KITTI the scans themselves side with the shorter path (the odometry's distances blur the keyframes'
map by 0.0074 nats on every draw), so there the baseline's are kept (docs/evaluation.md, "Weak directions and the
distance travelled").
"""

from __future__ import annotations

import logging

import numpy as np

from neld_jax.baseline.settings import BaselineSettings
from neld_jax.judging import judge
from neld_jax.judging.metrics import path_length_ratio
from neld_jax.trajectory import window_scales

logger = logging.getLogger(__name__)

# Poses whose distances differ from the input's by less than this (over every window) keep their own: nothing a map
# could tell apart, and no crispness draws spent on it.
NEGLIGIBLE_SCALE = 1e-4


def keep_input_distances(
    scans: list[np.ndarray], poses: np.ndarray, input_poses: np.ndarray, settings: BaselineSettings
) -> tuple[np.ndarray, dict | None]:
    """poses [S, 4, 4] with the input's [S, 4, 4] distances travelled (module docstring), unless their own give the
    keyframes' raw map (scans: S arrays [N_i, 3], sensor frame) a crisper map on every one of settings.
    crispness_draws query draws -> (poses [S, 4, 4], {"kept": "input" | "own", "path_ratio": the poses' path over
    the input's, "largest_window_change": the largest departure of a window's scale from 1, "margin": the paired
    entropy margin (own minus the input's distances; None without two draws)}), or (poses, None) when the
    comparison is off (distance_window_m 0) or the distances agree within NEGLIGIBLE_SCALE."""
    if settings.distance_window_m <= 0 or len(poses) < 2:
        return poses, None
    scales = window_scales(poses, input_poses, settings.distance_window_m)
    change = float(np.max(np.abs(scales - 1.0)))
    if change < NEGLIGIBLE_SCALE:
        return poses, None
    eval_cfg = {
        "crispness_draws": settings.crispness_draws,
        "crispness_queries": settings.crispness_queries,
        "crispness_radius_m": settings.crispness_radius_m,
    }
    kept, own_crisper, margin = judge.distances_judged(scans, poses, input_poses, settings.distance_window_m, eval_cfg)
    ratio = path_length_ratio(poses, input_poses)  # the input moves: window_scales differ from 1
    record = {
        "kept": "own" if own_crisper else "input",
        "path_ratio": round(ratio, 6),
        "largest_window_change": round(change, 6),
        "margin": None if margin is None else margin["mean"],
    }
    logger.info(
        "baseline: its path is %.3f%% %s than the input's (windows of %g m: up to %.3f%%); %s",
        100 * abs(ratio - 1),
        "shorter" if ratio < 1 else "longer",
        settings.distance_window_m,
        100 * change,
        "its own distances give the crisper map on every draw: kept"
        if own_crisper
        else "the input's distances travelled are kept (its own gave no crisper map on every draw"
        + ("" if margin is None else f": {margin['mean']:+.5f} nats")
        + ")",
    )
    return kept, record
