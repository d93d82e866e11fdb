"""Trajectory and map error metrics: ATE / RPE (as evo computes them), path length, KITTI's relative error over
distance segments, and Chamfer / F1 / inlier RMSE.

Pure numpy functions (nearest-neighbour queries go through Open3D's KD-tree). Poses are 4x4
homogeneous matrices `T_world_sensor`: [S, 4, 4]. Distances are in metres, angles in degrees.

Trajectory conventions follow evo (`evo_ape tum gt.txt est.txt -a`):
- The estimate is aligned to the ground truth by Umeyama's method on the positions only; the
  alignment `T_align` is applied on the left (`T_align @ T_est[s]`).
- The translation error of pose s is `|t_gt[s] - t_aligned[s]|`; the rotation error is the angle of
  `R_gt[s]^T R_aligned[s]`.
- RPE compares relative motions `T[i]^-1 T[i + delta]` of all overlapping pairs (evo's
  `--all_pairs`): `E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`.
- The path length is the sum of the steps between consecutive positions (evo's `PosePath3D.path_length`); an
  estimate's over the ground truth's shows a path stretched (> 1) or shortened (< 1), which an aligned ATE hides.
- KITTI's relative error follows the odometry devkit (`evaluate_odometry.cpp`): from every `step`-th first frame i,
  for each segment length L the last frame j is the first whose ground-truth path from i exceeds L, the error is
  `E = (P_i^-1 P_j)^-1 (G_i^-1 G_j)`, and |t(E)| / L and angle(E) / L are averaged over all segments.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from neld_jax.data.timing import nearest_times
from neld_jax.geometry import cumulative_path, invert_poses, rotation_angles_deg

logger = logging.getLogger(__name__)

ALIGN_MODES = ("se3", "sim3", "none")
MAP_MODES = ("paper", "clip", "sum")


# ---------------------------------------------------------------------------------------------
# Small geometry helpers
# ---------------------------------------------------------------------------------------------


def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape [S, 4, 4], got {poses.shape}")
    return poses


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape [N, 3], got {points.shape}")
    return points


def apply_alignment_to_poses(
    poses: np.ndarray, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0
) -> np.ndarray:
    """Left-apply a similarity to poses as evo does: p -> s R p + t, R_pose -> R R_pose.

    poses: [S, 4, 4], rotation: [3, 3], translation: [3] -> [S, 4, 4] (still rigid transforms).
    """
    poses = _check_poses(poses, "poses")
    aligned = np.array(poses)
    aligned[:, :3, :3] = np.einsum("ij,sjk->sik", rotation, poses[:, :3, :3])
    aligned[:, :3, 3] = scale * poses[:, :3, 3] @ np.asarray(rotation).T + np.asarray(translation)
    return aligned


def similarity_matrix(rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """[[s R, t], [0, 1]] as a [4, 4] array: maps estimate-frame points into the ground-truth frame."""
    transform = np.eye(4)
    transform[:3, :3] = scale * np.asarray(rotation)
    transform[:3, 3] = translation
    return transform


# ---------------------------------------------------------------------------------------------
# Trajectory metrics
# ---------------------------------------------------------------------------------------------


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (Umeyama 1991) minimising sum |dst - (s R src + t)|^2.

    src, dst: [N, 3] corresponding points -> (R [3, 3], t [3], s). s is 1.0 unless with_scale.
    When the points do not determine a rotation (N < 3 or all collinear; evo refuses these), R is
    the identity and only the translation (and scale) is estimated; a warning is logged.
    """
    src = _check_points(src, "src")
    dst = _check_points(dst, "dst")
    if src.shape != dst.shape or len(src) == 0:
        raise ValueError(f"umeyama_alignment needs equal, non-empty point sets, got {src.shape} and {dst.shape}")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mean_src, dst - mean_dst
    var_src = np.mean(np.sum(src_c**2, axis=1))
    covariance = dst_c.T @ src_c / len(src)
    if np.linalg.matrix_rank(covariance) < 2:
        logger.warning(
            "Umeyama alignment: %d positions do not determine a rotation (collinear or too few);"
            " aligning the translation only",
            len(src),
        )
        rotation = np.eye(3)
        scale = 1.0
        if with_scale and var_src > 0:
            scale = float(np.sqrt(np.mean(np.sum(dst_c**2, axis=1)) / var_src))
        return rotation, mean_dst - scale * mean_src, scale
    u, singular_values, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # reflection -> nearest proper rotation
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(singular_values) @ sign) / var_src) if with_scale else 1.0
    translation = mean_dst - scale * rotation @ mean_src
    return rotation, translation, scale


def ate_errors(est: np.ndarray, gt: np.ndarray, align: str = "se3") -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per-pose absolute errors after alignment.

    est, gt: [S, 4, 4] matched poses -> (translation errors [S] m, rotation errors [S] deg,
    alignment [4, 4] = [[s R, t], [0, 1]] taking estimate-frame points into the GT frame, scale s).
    """
    est = _check_poses(est, "est")
    gt = _check_poses(gt, "gt")
    if est.shape != gt.shape or len(est) == 0:
        raise ValueError(f"ATE needs matched, non-empty trajectories, got {est.shape} and {gt.shape}")
    if align not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {align!r}")
    if align == "none":
        rotation, translation, scale = np.eye(3), np.zeros(3), 1.0
    else:
        rotation, translation, scale = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=align == "sim3")
    aligned = apply_alignment_to_poses(est, rotation, translation, scale)
    translation_errors = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    relative_rotations = np.einsum("sji,sjk->sik", gt[:, :3, :3], aligned[:, :3, :3])
    rotation_errors = rotation_angles_deg(relative_rotations)
    return translation_errors, rotation_errors, similarity_matrix(rotation, translation, scale), scale


def _rmse(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else float("nan")


def ate(est: np.ndarray, gt: np.ndarray, align: str = "se3") -> dict[str, Any]:
    """Absolute trajectory error, matching `evo_ape tum gt est -a` (se3) / `-as` (sim3).

    est, gt: [S, 4, 4] poses matched by index. align: "se3" (rigid Umeyama on positions, the paper's
    choice), "sim3" (with scale) or "none".
    Returns translation_rmse/mean/median/max/std_m, rotation_rmse/mean_deg, align, alignment (4x4
    nested list, estimate frame -> GT frame), scale and num_poses.
    """
    return ate_summary(*ate_errors(est, gt, align), align=align)


def ate_summary(
    translation_errors: np.ndarray, rotation_errors: np.ndarray, alignment: np.ndarray, scale: float, align: str = "se3"
) -> dict[str, Any]:
    """`ate`'s dictionary from `ate_errors`' outputs (for callers that also need the per-pose errors)."""
    return {
        "translation_rmse_m": _rmse(translation_errors),
        "translation_mean_m": float(np.mean(translation_errors)),
        "translation_median_m": float(np.median(translation_errors)),
        "translation_max_m": float(np.max(translation_errors)),
        "translation_std_m": float(np.std(translation_errors)),
        "rotation_rmse_deg": _rmse(rotation_errors),
        "rotation_mean_deg": float(np.mean(rotation_errors)),
        "align": align,
        "alignment": alignment.tolist(),
        "scale": float(scale),
        "num_poses": int(len(translation_errors)),
    }


def rpe_errors(est: np.ndarray, gt: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair relative pose errors over all pairs (i, i + delta).

    est, gt: [S, 4, 4] -> (translation errors [S - delta] m, rotation errors [S - delta] deg).
    """
    est = _check_poses(est, "est")
    gt = _check_poses(gt, "gt")
    if est.shape != gt.shape:
        raise ValueError(f"RPE needs matched trajectories, got {est.shape} and {gt.shape}")
    if delta < 1:
        raise ValueError(f"RPE delta must be >= 1, got {delta}")
    if len(est) <= delta:
        return np.zeros(0), np.zeros(0)
    est_motion = invert_poses(est[:-delta]) @ est[delta:]
    gt_motion = invert_poses(gt[:-delta]) @ gt[delta:]
    error = invert_poses(gt_motion) @ est_motion
    return np.linalg.norm(error[:, :3, 3], axis=1), rotation_angles_deg(error[:, :3, :3])


def rpe(est: np.ndarray, gt: np.ndarray, delta: int = 1) -> dict[str, Any]:
    """Relative pose error of motions over `delta` poses (evo_rpe with --all_pairs, delta in frames).

    est, gt: [S, 4, 4] matched poses. Independent of any global alignment. Values are NaN when
    S <= delta.
    """
    translation_errors, rotation_errors = rpe_errors(est, gt, delta)
    empty = len(translation_errors) == 0
    return {
        "translation_rmse_m": _rmse(translation_errors),
        "translation_mean_m": float("nan") if empty else float(np.mean(translation_errors)),
        "rotation_rmse_deg": _rmse(rotation_errors),
        "rotation_mean_deg": float("nan") if empty else float(np.mean(rotation_errors)),
        "delta": int(delta),
        "num_pairs": int(len(translation_errors)),
    }


def path_length(poses: np.ndarray) -> float:
    """Length [m] of the path through the positions of poses [S, 4, 4]: the sum of the S - 1 steps (0 for S < 2)."""
    return float(cumulative_path(_check_poses(poses, "poses"))[-1])


def path_length_ratio(est: np.ndarray, gt: np.ndarray) -> float:
    """The estimate's path length over the ground truth's, est and gt: [S, 4, 4] matched poses (1.0: the right
    length, 0.99: 1 % short). NaN when the ground truth does not move. Jitter lengthens a path (a step's sideways
    error adds to it), so a noisy estimate reads longer than its scale; Sim(3)'s scale (`ate(align="sim3")`) does
    not."""
    est, gt = _check_poses(est, "est"), _check_poses(gt, "gt")
    if est.shape != gt.shape:
        raise ValueError(f"the path-length ratio needs matched trajectories, got {est.shape} and {gt.shape}")
    gt_length = path_length(gt)
    return path_length(est) / gt_length if gt_length > 0 else float("nan")


KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)  # the devkit's segments
KITTI_STEP = 10  # the devkit's step between first frames


def kitti_segment_errors(
    est: np.ndarray, gt: np.ndarray, lengths_m=KITTI_LENGTHS_M, step: int = KITTI_STEP
) -> dict[str, np.ndarray]:
    """Every segment of KITTI's relative error (the odometry devkit's calcSequenceErrors).

    est, gt: [S, 4, 4] matched poses; lengths_m: [L] segment lengths [m]; step: frames between first frames.
    For each first frame i = 0, step, 2 step, ... and length L, the last frame j is the first whose ground-truth
    path from i exceeds L (segments that run past the end are left out); E = (P_i^-1 P_j)^-1 (G_i^-1 G_j).
    Returns K segments: "first" [K], "last" [K] (frame indices), "length_m" [K], "translation_m" [K] (|t(E)|),
    "rotation_deg" [K] (angle of E).
    """
    est, gt = _check_poses(est, "est"), _check_poses(gt, "gt")
    if est.shape != gt.shape:
        raise ValueError(f"KITTI's relative error needs matched trajectories, got {est.shape} and {gt.shape}")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    lengths = np.asarray(lengths_m, dtype=np.float64).reshape(-1)
    if np.any(lengths <= 0):
        raise ValueError(f"segment lengths must be positive, got {lengths}")
    travelled = cumulative_path(gt)
    first = np.repeat(np.arange(0, len(gt), step), len(lengths))
    length = np.tile(lengths, len(np.arange(0, len(gt), step)))
    last = np.searchsorted(travelled, travelled[first] + length, side="right")  # the first frame past L
    keep = last < len(gt)
    first, last, length = first[keep], last[keep], length[keep]
    gt_motion = invert_poses(gt[first]) @ gt[last]
    est_motion = invert_poses(est[first]) @ est[last]
    error = invert_poses(est_motion) @ gt_motion
    return {
        "first": first,
        "last": last,
        "length_m": length,
        "translation_m": np.linalg.norm(error[:, :3, 3], axis=1),
        "rotation_deg": rotation_angles_deg(error[:, :3, :3]),
    }


def kitti_relative_error(
    est: np.ndarray, gt: np.ndarray, lengths_m=KITTI_LENGTHS_M, step: int = KITTI_STEP
) -> dict[str, Any]:
    """KITTI's relative error over distance segments (see `kitti_segment_errors`), averaged over all segments as the
    devkit averages them.

    est, gt: [S, 4, 4] matched poses; lengths_m: [L] segment lengths [m]; step: frames between first frames.
    Returns translation_pct (mean |t(E)| / L, in percent), rotation_deg_per_m (mean angle(E) / L), num_segments,
    lengths_m, step, and per_length {f"{L:g}": {translation_pct, rotation_deg_per_m, num_segments}}; the means are
    NaN where no segment fits (the path shorter than the lengths).
    """
    segments = kitti_segment_errors(est, gt, lengths_m, step)

    def summary(mask: np.ndarray) -> dict[str, Any]:
        empty = not np.any(mask)
        length = segments["length_m"][mask]
        return {
            "translation_pct": float("nan")
            if empty
            else float(100 * np.mean(segments["translation_m"][mask] / length)),
            "rotation_deg_per_m": float("nan") if empty else float(np.mean(segments["rotation_deg"][mask] / length)),
            "num_segments": int(np.sum(mask)),
        }

    lengths = [float(v) for v in np.asarray(lengths_m, dtype=np.float64).reshape(-1)]
    out = summary(np.ones(len(segments["first"]), dtype=bool))
    out.update(
        lengths_m=lengths, step=int(step), per_length={f"{v:g}": summary(segments["length_m"] == v) for v in lengths}
    )
    return out


def associate_timestamps(
    stamps_est: np.ndarray, stamps_gt: np.ndarray, max_diff: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Match each estimate timestamp to the nearest ground-truth timestamp within max_diff seconds.

    stamps_est: [S], stamps_gt: [G] -> (indices into est [K], indices into gt [K]), K <= S. A GT
    stamp is used at most once (the closest estimate wins), so matched pose pairs are distinct.
    """
    stamps_est = np.asarray(stamps_est, dtype=np.float64)
    stamps_gt = np.asarray(stamps_gt, dtype=np.float64)
    if len(stamps_est) == 0 or len(stamps_gt) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    nearest, diffs = nearest_times(stamps_est, stamps_gt)  # indices into stamps_gt
    best_for_gt: dict[int, int] = {}
    for est_index in np.argsort(diffs, kind="stable"):
        if diffs[est_index] > max_diff:
            break
        best_for_gt.setdefault(int(nearest[est_index]), int(est_index))
    est_indices = np.array(sorted(best_for_gt.values()), dtype=int)
    gt_of_est = {est_index: gt_index for gt_index, est_index in best_for_gt.items()}
    gt_indices = np.array([gt_of_est[i] for i in est_indices], dtype=int)
    return est_indices, gt_indices


# ---------------------------------------------------------------------------------------------
# Map metrics
# ---------------------------------------------------------------------------------------------


def _to_o3d(points: np.ndarray):
    """An open3d.geometry.PointCloud of points [N, 3]; open3d is imported here, so that the trajectory metrics
    work where it is not installed (the GPU image, benchmarks/gpu_suite.py)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return cloud


def nearest_neighbor_distances(query: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance from each query point to its nearest reference point (Open3D KD-tree, multithreaded).

    query: [N, 3], reference: [M, 3] with M > 0 -> [N].
    """
    query = _check_points(query, "query")
    reference = _check_points(reference, "reference")
    if len(reference) == 0:
        raise ValueError("nearest_neighbor_distances: the reference point set is empty")
    if len(query) == 0:
        return np.zeros(0)
    return np.asarray(_to_o3d(query).compute_point_cloud_distance(_to_o3d(reference)), dtype=np.float64)


def map_metrics_from_distances(
    est_to_gt: np.ndarray,
    gt_to_est: np.ndarray,
    threshold: float = 0.2,
    cutoff: float | None = None,
    mode: str = "paper",
) -> dict[str, Any]:
    """Compare an estimated map with a ground-truth map (same frame) from their nearest-neighbour distances
    (`nearest_neighbor_distances`): est_to_gt [N], each estimated point's to its nearest GT point ("accuracy");
    gt_to_est [M], each GT point's to its nearest estimated point ("completeness").

    Chamfer conventions (`mode`), `cutoff` in metres (the paper: 1 m for raw maps, none for rendered maps):
    "paper" (default): L1-Chamfer = 1/2 mean(d_acc) + 1/2 mean(d_comp), as the NeLD-BA paper and the FusionPortable /
    MapEval tools, distances beyond `cutoff` DROPPED from both means; "clip": the same, distances CLIPPED to `cutoff`
    (outliers count with the maximum penalty); "sum": mean(d_acc) + mean(d_comp), unhalved (some FusionPortable
    scripts), dropping as "paper". With cutoff=None all three use every distance. Whatever the mode: precision =
    fraction of d_acc <= threshold, recall = fraction of d_comp <= threshold, f1 = 2PR / (P + R), inlier_rmse = RMSE
    of the d_acc <= threshold. Returns accuracy_m, completeness_m, chamfer_l1_m, precision, recall, f1,
    inlier_rmse_m, threshold_m, cutoff_m, mode, num_est, num_gt, num_est/gt_within_cutoff, num_inliers (a mean over
    no points is NaN).
    """
    if mode not in MAP_MODES:
        raise ValueError(f"map metrics mode must be one of {MAP_MODES}, got {mode!r}")
    if threshold <= 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    if cutoff is not None and cutoff <= 0:
        raise ValueError(f"cutoff must be positive or None, got {cutoff}")
    est_to_gt = np.asarray(est_to_gt, dtype=np.float64)
    gt_to_est = np.asarray(gt_to_est, dtype=np.float64)

    def _cut(distances: np.ndarray) -> np.ndarray:
        if cutoff is None:
            return distances
        if mode == "clip":
            return np.minimum(distances, cutoff)
        return distances[distances <= cutoff]  # "paper" and "sum": far points are outliers, dropped

    accuracy_distances, completeness_distances = _cut(est_to_gt), _cut(gt_to_est)
    accuracy = float(np.mean(accuracy_distances)) if len(accuracy_distances) else float("nan")
    completeness = float(np.mean(completeness_distances)) if len(completeness_distances) else float("nan")
    chamfer = accuracy + completeness if mode == "sum" else 0.5 * (accuracy + completeness)

    precision = float(np.mean(est_to_gt <= threshold)) if len(est_to_gt) else 0.0
    recall = float(np.mean(gt_to_est <= threshold)) if len(gt_to_est) else 0.0
    f1 = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    inliers = est_to_gt[est_to_gt <= threshold]
    return {
        "accuracy_m": accuracy,
        "completeness_m": completeness,
        "chamfer_l1_m": float(chamfer),
        "precision": precision,
        "recall": recall,
        "f1": float(f1),
        "inlier_rmse_m": _rmse(inliers),
        "threshold_m": float(threshold),
        "cutoff_m": None if cutoff is None else float(cutoff),
        "mode": mode,
        "num_est": int(len(est_to_gt)),
        "num_gt": int(len(gt_to_est)),
        "num_est_within_cutoff": int(len(est_to_gt) if cutoff is None else np.sum(est_to_gt <= cutoff)),
        "num_gt_within_cutoff": int(len(gt_to_est) if cutoff is None else np.sum(gt_to_est <= cutoff)),
        "num_inliers": int(len(inliers)),
    }
