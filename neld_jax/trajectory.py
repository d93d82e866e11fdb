"""Carrying the keyframes' refined poses to every input scan.

NeLD-BA trains on keyframes. A scan between two keyframes gets their corrections interpolated: with the left
(world-frame) correction C_k = T_refined[k] T_input[k]^-1 of keyframe k, the scan j between keyframes a and b
(a < j < b in scan order) gets

    C_j = C_a Exp(u Log(C_a^-1 C_b)),   u = (t_j - t_a) / (t_b - t_a)   (time, or scan index without stamps)
    T_refined[j] = C_j T_input[j]

so the odometry's motion between keyframes (which is accurate over short spans) is kept, and the correction
varies smoothly along the trajectory. Scans before the first / after the last keyframe take its correction.
"""

from __future__ import annotations

import numpy as np

from neld_jax import lie
from neld_jax.geometry import cumulative_path, invert_poses


def propagate_corrections(
    T_input: np.ndarray, keyframe_index: np.ndarray, T_keyframes: np.ndarray, times: np.ndarray | None = None
) -> np.ndarray:
    """Refined poses [S, 4, 4] of every input scan.

    T_input: [S, 4, 4] input poses of all scans; keyframe_index: [K] increasing indices into them;
    T_keyframes: [K, 4, 4] the keyframes' refined poses; times: [S] seconds (None: interpolate by index).
    Keyframes get exactly T_keyframes.
    """
    T_input = np.asarray(T_input, np.float64)
    keyframe_index = np.asarray(keyframe_index, np.int64)
    T_keyframes = np.asarray(T_keyframes, np.float64)
    if len(keyframe_index) != len(T_keyframes) or len(keyframe_index) == 0:
        raise ValueError(f"{len(keyframe_index)} keyframe indices for {len(T_keyframes)} refined poses")
    if np.any(np.diff(keyframe_index) <= 0):
        raise ValueError("keyframe_index must be strictly increasing")
    num_scans = len(T_input)
    position = np.asarray(times, np.float64) if times is not None else np.arange(num_scans, dtype=np.float64)
    corrections = T_keyframes @ invert_poses(T_input[keyframe_index])  # [K, 4, 4]
    # For each scan, the keyframe at or before it (a) and the fraction u of the way to the next one (b).
    a = np.clip(np.searchsorted(keyframe_index, np.arange(num_scans), side="right") - 1, 0, len(keyframe_index) - 1)
    b = np.minimum(a + 1, len(keyframe_index) - 1)
    span = position[keyframe_index[b]] - position[keyframe_index[a]]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(span > 0, (position - position[keyframe_index[a]]) / span, 0.0)
    u = np.clip(u, 0.0, 1.0)  # before the first keyframe: its correction (u = 0 at a = 0 below it)
    delta = lie.se3_log_float64(invert_poses(corrections[a]) @ corrections[b])  # [S, 6]
    C = corrections[a] @ lie.se3_exp_float64(u[:, None] * delta)
    refined = C @ T_input
    refined[keyframe_index] = T_keyframes  # exact, without the round trip through exp/log
    return refined


def window_scales(poses: np.ndarray, reference: np.ndarray, window_m: float) -> np.ndarray:
    """[S - 1] for each step of poses [S, 4, 4]: the reference's [S, 4, 4] path length over the steps whose midpoints
    lie within window_m / 2 of this step's (along the reference's path) divided by poses' over the same steps (1 where
    poses do not move there)."""
    along, own_along = cumulative_path(reference), cumulative_path(poses)
    mid = 0.5 * (along[1:] + along[:-1])
    lo = np.searchsorted(mid, mid - 0.5 * window_m, side="left")
    hi = np.searchsorted(mid, mid + 0.5 * window_m, side="right")
    own = own_along[hi] - own_along[lo]  # the steps lo..hi-1 of each window, summed
    return np.where(own > 0, (along[hi] - along[lo]) / np.where(own > 0, own, 1.0), 1.0)


def with_distances_of(poses: np.ndarray, reference: np.ndarray, window_m: float, beyond: float = 0.0) -> np.ndarray:
    """poses [S, 4, 4] with each step's translation scaled by window_scales (the reference's [S, 4, 4] distance
    travelled over a window_m window around it): the same rotations and directions of travel, the reference's
    distances; pose 0 stays. Where a registration measures the shape of a path but a LiDAR odometry over
    consecutive sweeps measures the distance travelled better (docs/evaluation.md, "Weak directions and the distance
    travelled"). beyond: only the steps whose window's scale departs from 1 by more than this take the reference's
    distances; the others keep their own."""
    poses = np.array(poses, np.float64)
    scales = window_scales(poses, reference, window_m)
    scales = np.where(np.abs(scales - 1.0) > beyond, scales, 1.0)
    steps = np.diff(poses[:, :3, 3], axis=0) * scales[:, None]
    poses[1:, :3, 3] = poses[0, :3, 3] + np.cumsum(steps, axis=0)
    return poses
