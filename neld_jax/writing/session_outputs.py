"""A run over several recordings of one place (data.root with several folders, neld_jax.steps.session_alignment): what
each recording gets of the merged run. metrics.json's "sessions" section (`sessions_record`: each recording's
crispness alone and in the merged map, its closures with the first recording and their overlaps, and with ground
truth its ATE under ONE alignment shared by every recording, so that a misplaced recording shows), and per
recording `sessions/<k>_<folder name>/`: poses_optimized.txt (TUM, its own stamps, the first recording's world
frame), poses_optimized.kitti and scans_report.csv (`write_session_files`).
"""

from __future__ import annotations

import logging
import os

import numpy as np

from neld_jax.judging import judge, metrics, report
from neld_jax.writing.evaluate import RunArtifacts
from neld_jax.writing.export import write_poses

logger = logging.getLogger(__name__)

FOLDER = "sessions"


def shared_alignment_ate(trajectory: np.ndarray, gt: np.ndarray, labels: np.ndarray) -> list[dict]:
    """Each recording's ATE under one SE(3) alignment of the whole trajectory [S, 4, 4] to the ground truth [S, 4, 4]
    (matched by index; labels [S]: each pose's recording) -> one ate summary per recording (metrics.ate_summary,
    every one holding the shared alignment)."""
    translation, rotation, alignment, scale = metrics.ate_errors(trajectory, gt, "se3")
    return [
        metrics.ate_summary(translation[labels == r], rotation[labels == r], alignment, scale)
        for r in range(int(labels.max()) + 1)
    ]


def crispness_alone_and_merged(keyframes, poses: np.ndarray, sessions, eval_cfg) -> list[dict]:
    """Each recording's raw-map crispness: its keyframes alone under poses [K, 4, 4] (their slice), and its
    keyframes' points in the merged map of every recording (the mean of their per-keyframe entropy, on the merged
    map's query points) beside the same mean alone."""
    radius, queries = float(eval_cfg["crispness_radius_m"]), int(eval_cfg["crispness_queries"])
    _, merged_per_keyframe = judge.compare_maps(keyframes.scans, {"merged": poses}, radius, queries)
    out = []
    for r in range(sessions.count):
        part = sessions.keyframes_of(r)
        alone, alone_per_keyframe = judge.compare_maps(keyframes.scans[part], {"alone": poses[part]}, radius, queries)
        out.append(
            {
                "alone_mean_map_entropy": alone["alone"]["mean_map_entropy"],
                "alone_keyframe_entropy": _mean(alone_per_keyframe["alone"]),
                "in_merged_keyframe_entropy": _mean(merged_per_keyframe["merged"][part]),
            }
        )
    return out


def _mean(values: np.ndarray) -> float | None:
    values = np.asarray(values, np.float64)
    return float(np.nanmean(values)) if np.isfinite(values).any() else None


def sections(sessions, keyframes, keyframe_poses: np.ndarray, written: RunArtifacts, eval_cfg) -> dict:
    """metrics.json's sections of a run over several recordings: {"sessions": sessions_record(...)}; {} for one
    recording (sessions None)."""
    if sessions is None:
        return {}
    return {"sessions": sessions_record(sessions, keyframes, keyframe_poses, written, eval_cfg)}


def sessions_record(sessions, keyframes, keyframe_poses: np.ndarray, written: RunArtifacts, eval_cfg) -> dict:
    """metrics.json's "sessions" section: {"count", "recordings": [{name, scans, keyframes, to_first [4, 4],
    closures, crispness, [ate_shared_alignment: {method: ate}]}]} (module docstring). keyframe_poses [K, 4, 4]:
    the refined keyframes'; written: the run's trajectories of every input scan and its ground truth."""
    crisp = crispness_alone_and_merged(keyframes, keyframe_poses, sessions, eval_cfg)
    shared = {}
    if written.gt is not None:
        labels = sessions.scan_labels()
        for method in ("initial", "optimized"):
            shared[method] = shared_alignment_ate(written.trajectories[method].poses, written.gt.poses, labels)
    recordings = []
    for r, name in enumerate(sessions.names):
        entry = {
            "name": name,
            "scans": int(np.diff(sessions.scan_bounds)[r]),
            "keyframes": int(np.diff(sessions.keyframe_bounds)[r]),
            "to_first": sessions.to_first[r].tolist(),
            "closures": sessions.closures[r] if sessions.closures else [],
            "crispness": crisp[r],
        }
        if shared:
            entry["ate_shared_alignment"] = {method: ates[r] for method, ates in shared.items()}
            logger.info(
                "%s: ATE %.2f cm under the alignment shared by every recording (%.2f cm from the input)",
                name,
                100 * entry["ate_shared_alignment"]["optimized"]["translation_rmse_m"],
                100 * entry["ate_shared_alignment"]["initial"]["translation_rmse_m"],
            )
        recordings.append(entry)
    return {"count": sessions.count, "recordings": recordings}


def write_session_files(out_dir: str, sessions, written: RunArtifacts, rows: list[dict]) -> list[str]:
    """Per recording, out_dir/sessions/<name>/: poses_optimized.txt / .kitti (its input scans, its own stamps, the
    first recording's world frame) and scans_report.csv (its rows of the run's report, rows: one per joined input
    scan). Returns the folders written (none for one recording: sessions None)."""
    if sessions is None:
        return []
    trajectory = written.trajectories["optimized"]
    folders = []
    for r, name in enumerate(sessions.names):
        folder = os.path.join(out_dir, FOLDER, name)
        os.makedirs(folder, exist_ok=True)
        part = sessions.scans_of(r)
        write_poses(folder, "poses_optimized", sessions.stamps(r, trajectory.stamps), trajectory.poses[part])
        report.write_csv(os.path.join(folder, "scans_report.csv"), rows[part])
        folders.append(folder)
    logger.info("per recording: poses and scans_report.csv in %s", ", ".join(folders))
    return folders
