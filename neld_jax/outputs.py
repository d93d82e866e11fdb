"""A run's outputs (docs/design.md, "Outputs of a run"): the output folder and config.json, the poses of every
input scan and the maps, then the verdict: the raw map's crispness before and after (and the classical
baseline's), how sure that is over query draws, the per-scan report, metrics.json and, where ground truth
exists, the evaluation against it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os

import jax
import ml_collections
import numpy as np

from neld_jax import judge, plots, report
from neld_jax.budget import TimeBudget
from neld_jax.data.preprocess import voxel_downsample
from neld_jax.export import read_json, write_json, write_keyframe_poses, write_point_cloud, write_poses, write_raw_map
from neld_jax.geometry import register_scans
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)

# Fields that do not change what is computed: a resumed run may change them (the budget is a name of the others)
NOT_HASHED = ("output_dir", "budget", "max_minutes", "train.log_every", "train.checkpoint_every", "mapping", "eval",
              "viz", "data.gt_poses_path", "data.gt_map_path", "data.gt_from_scan", "data.scan_frame",
              "data.gt_time_offset_s")


def config_hash(config: ml_collections.ConfigDict) -> str:
    """12 hex digits of the settings that decide what a run computes (a checkpoint resumes only under the same)."""
    d = json.loads(config.to_json_best_effort())
    for path in NOT_HASHED:
        node, *rest = path.split(".")
        if rest:
            d.get(node, {}).pop(rest[0], None)
        else:
            d.pop(node, None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


def prepare(config: ml_collections.ConfigDict) -> tuple[str, str]:
    """Create the output folder and write config.json, the settings of the run as given (once; the run never
    rewrites them). Returns (the folder's absolute path, the config hash)."""
    out_dir = os.path.abspath(config.output_dir)
    os.makedirs(out_dir, exist_ok=True)
    write_json(os.path.join(out_dir, "config.json"), json.loads(config.to_json_best_effort()), merge=False)
    return out_dir, config_hash(config)


def write_outputs(out_dir: str, config: ml_collections.ConfigDict, loaded, keyframes, start, refined,
                  render) -> np.ndarray:
    """poses_initial / poses_optimized (TUM .txt and KITTI .kitti, one line per input scan: the scans between
    keyframes take their keyframes' interpolated correction), poses_baseline when the baseline ran, poses_gt where
    ground truth exists, poses_odometry when the input poses were made from the scans (KISS-ICP; the same poses as
    poses_initial, under the name that says where they came from); map_raw.ply (the keyframes registered with the
    optimised poses), map_raw_initial.ply, map_rendered.ply, map_gt.ply. Returns the poses of every input scan [S, 4, 4]."""
    index = keyframes.loaded_index
    T_all = propagate_corrections(loaded.poses, index, refined.poses, loaded.timestamps)
    write_poses(out_dir, "poses_initial", loaded.timestamps, loaded.poses)
    write_poses(out_dir, "poses_optimized", loaded.timestamps, T_all)
    if start.baseline_poses is not None:
        write_keyframe_poses(out_dir, "poses_baseline", loaded, keyframes, start.baseline_poses)
    if loaded.gt_poses is not None:
        write_poses(out_dir, "poses_gt", loaded.timestamps, loaded.gt_poses)
    if loaded.poses_from == "kiss_icp":
        write_poses(out_dir, "poses_odometry", loaded.timestamps, loaded.poses)
    voxel = float(config.mapping.voxel_size_m)
    write_raw_map(os.path.join(out_dir, "map_raw.ply"), keyframes.scans, refined.poses, voxel_size=voxel)
    write_raw_map(os.path.join(out_dir, "map_raw_initial.ply"), keyframes.scans, keyframes.poses, voxel_size=voxel)
    if keyframes.gt_map is not None:
        write_point_cloud(os.path.join(out_dir, "map_gt.ply"), keyframes.gt_map)
    if render is not None:
        if len(render.points):
            write_point_cloud(os.path.join(out_dir, "map_rendered.ply"), voxel_downsample(render.points, voxel))
        else:
            logger.warning("rendered map is empty: no ray reached opacity %.2f (train longer or lower "
                           "mapping.min_opacity); map_rendered.ply not written", config.mapping.min_opacity)
    return T_all


def judge_run(out_dir: str, config: ml_collections.ConfigDict, loaded, keyframes, start, refined, render, T_all,
              budget: TimeBudget, config_hash_: str, progress: bool = True) -> tuple[dict, list[dict]]:
    """The verdict of a run, written to metrics.json (run, crispness, scans_report; evaluation where ground truth
    exists), history.json, scans_report.csv / .png and map_topdown.png. Returns (metrics.json's content, the
    per-scan report's rows)."""
    methods = {"initial": keyframes.poses, "optimized": refined.poses}
    if start.baseline_poses is not None:
        methods["baseline"] = start.baseline_poses
    # The same query points for every method, so the start's figures are reused as they are.
    judged, judged_per_scan = start.judged
    crisp, per_scan_entropy = judge.map_crispness(
        keyframes, {name: poses for name, poses in methods.items() if name not in judged}, config.eval)
    crisp, per_scan_entropy = {**judged, **crisp}, {**judged_per_scan, **per_scan_entropy}
    margins = judge.crispness_margins(keyframes, methods, config.eval, first_draw=crisp,
                                      deadline=budget.judging_deadline(), progress=progress)
    for other, margin in margins.items():
        logger.info("%s", judge.describe_margin(other, margin))
    rows = write_scan_report(out_dir, loaded, keyframes, T_all, refined, render, per_scan_entropy,
                             float(config.mapping.min_opacity), start.poses)
    plots.plot_map_topdown(os.path.join(out_dir, "map_topdown.png"),
                           {"input poses": register_scans(keyframes.scans, keyframes.poses),
                            "after NeLD-BA": register_scans(keyframes.scans, refined.poses)})
    result = refined.result
    run = {
        "config_hash": config_hash_,
        "num_input_scans": loaded.num_scans,
        "num_scans": keyframes.num_scans,  # keyframes: the scans trained on
        "submaps": refined.plan.num_submaps,
        "steps": int(result.state.step),
        "schedule_steps": result.schedules.total_steps,  # the plan that ran: fewer than asked when compressed
        "stopped_early": bool(result.stopped_early),
        "train_seconds": round(result.train_seconds, 2),
        "total_seconds": round(budget.elapsed(), 2),
        "device": str(jax.devices()[0]),
        "map_rays": None if render is None else int(render.rays.num_rays),
        "map_rays_rendered": None if render is None else render.num_rendered,
        "final": result.history[-1] if result.history else {},
        **start.record(),
        "crispest": judge.warn_if_not_crispest(crisp, {}, margins),
        "crispness_margin": margins,  # {other method: NeLD-BA's entropy minus its, per draw and mean}
    }
    summary = {"run": run, "scans_report": report.summarize(rows)}
    write_json(os.path.join(out_dir, "metrics.json"), summary)
    summary["crispness"] = record_crispness(out_dir, crisp)
    with open(os.path.join(out_dir, "history.json"), "w") as f:
        json.dump(result.history, f)
    if keyframes.gt_poses is not None or keyframes.gt_map is not None:
        from neld_jax.evaluate import evaluate_run

        summary["evaluation"] = evaluate_run(out_dir, map_icp_m=float(config.eval.map_icp_m))
    return summary, rows


def write_scan_report(out_dir: str, loaded, keyframes, T_all: np.ndarray, refined, render, per_scan_entropy: dict,
                      min_opacity: float, start_poses: np.ndarray) -> list[dict]:
    """scans_report.csv and scans_report.png: one row per input scan (neld_jax.report); the residuals from the
    rendered map (none without it), the refinement from the poses training started from."""
    num_keyframes = keyframes.num_scans
    residual = np.full(num_keyframes, np.nan)
    if render is not None:
        error_m = np.abs(render.ranges - render.rays.ranges)
        hit = render.opacity >= min_opacity
        # the rays are grouped by keyframe
        bounds = np.cumsum(np.bincount(render.rays.scan_index, minlength=num_keyframes))[:-1]
        for k, (errors, hits) in enumerate(zip(np.split(error_m, bounds), np.split(hit, bounds))):
            if hits.any():
                residual[k] = float(np.median(errors[hits]))
    correction_m, correction_deg = report.aligned_corrections(loaded.poses, T_all)
    refinement_m, refinement_deg = report.aligned_corrections(start_poses, refined.poses)
    rows = report.scan_report(loaded.num_scans, keyframes.loaded_index, loaded.files, loaded.timestamps,
                              refined.rays_per_keyframe, residual, correction_m, correction_deg,
                              per_scan_entropy.get("initial"), per_scan_entropy.get("optimized"), refinement_m,
                              refinement_deg)
    report.write_csv(os.path.join(out_dir, "scans_report.csv"), rows)
    plots.plot_scan_report(os.path.join(out_dir, "scans_report.png"), rows)
    logger.info("scans_report.csv: %d input scans, %d keyframes trained on", loaded.num_scans, num_keyframes)
    return rows


def record_crispness(out_dir: str, summaries: dict) -> dict:
    """Merge {method: crispness summary} into the "crispness" section of OUT_DIR/metrics.json (the run and the
    baseline each add their methods); returns the merged section."""
    path = os.path.join(out_dir, "metrics.json")
    merged = {**read_json(path).get("crispness", {}), **summaries}
    write_json(path, {"crispness": merged})
    return merged
