"""A run's outputs (docs/design.md, "Outputs of a run"): the poses of every input scan and the maps, then the
verdict: the raw map's crispness before and after (and the classical baseline's), how sure that is over query
draws, the per-scan report and, where ground truth exists, the evaluation against it, all in metrics.json, which
is built in memory and written once. The output folder itself and config.json: neld_jax.writing.output_folder.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from typing import Any

import jax
import ml_collections
import numpy as np

from neld_jax.data.preprocess import voxel_downsample
from neld_jax.geometry import register_scans
from neld_jax.judging import judge, report
from neld_jax.judging.metrics import path_length_ratio
from neld_jax.training.budget import TimeBudget
from neld_jax.trajectory import propagate_corrections, window_scales
from neld_jax.writing import plots
from neld_jax.writing.evaluate import GT_POSES_FILE, EvalSettings, RunArtifacts, Trajectory, evaluation_record
from neld_jax.writing.export import write_json, write_point_cloud, write_poses, write_raw_map

logger = logging.getLogger(__name__)

# Fields that do not change what training computes: outside the hash that guards a checkpoint and a saved start (the
# budget is a name of the others). A rerun into a run's folder must match its config.json in every field but
# output_folder.UNCOMPARED before it gets that far.
NOT_HASHED = (
    "output_dir",
    "budget",
    "max_minutes",
    "train.log_every",
    "train.checkpoint_every",
    "mapping",
    "eval",
    "viz",
    "data.gt_poses_path",
    "data.gt_map_path",
    "data.gt_from_scan",
    "data.scan_frame",
    "data.gt_time_offset_s",
)


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


@dataclasses.dataclass(frozen=True)
class RunSteps:
    """What a run's steps made: every input scan (`loaded`) and the keyframes (step 1), the start (2), the refined
    poses and fields (3), the rendered map (4; None with mapping off) and every other input scan registered to the
    result (5; neld_jax.steps.registration.ScanRegistration, None where nothing was registered); neld_ba: NeLD-BA's
    poses of every input scan [S, 4, 4] where the start's poses are the answer instead (neld_jax.judging.answer), else
    None; every_scan and travelled: the answer's poses of every input scan where the check of the distance
    travelled took the input's, and that check's record (neld_jax.judging.answer.keep_travel_of_input)."""

    loaded: Any
    keyframes: Any
    start: Any
    refined: Any
    render: Any = None
    registration: Any = None
    neld_ba: np.ndarray | None = None
    every_scan: np.ndarray | None = None
    travelled: dict | None = None

    def every_scan_poses(self) -> np.ndarray:
        """The answer's poses of every input scan [S, 4, 4]: where the check of the distance travelled took the
        input's (neld_jax.judging.answer.keep_travel_of_input), those; else the scans between keyframes registered
        to the result, or, where nothing was registered (or a scan was refused), their keyframes' interpolated
        correction."""
        if self.every_scan is not None:
            return self.every_scan
        if self.registration is not None:
            return self.registration.poses
        return propagate_corrections(
            self.loaded.poses, self.keyframes.loaded_index, self.refined.poses, self.loaded.timestamps
        )


def write_outputs(out_dir: str, mapping_cfg: ml_collections.ConfigDict, made: RunSteps) -> RunArtifacts:
    """Into out_dir: poses_initial / poses_optimized (TUM .txt and KITTI .kitti, one line per input scan: the answer,
    made.every_scan_poses), poses_neld_ba where the start's poses are the answer (neld_jax.judging.answer),
    poses_baseline when the baseline ran, poses_gt where ground truth exists, poses_odometry when the input poses were
    made from the scans (KISS-ICP; the same poses as poses_initial, under the name that says where they came from);
    map_raw.ply (the keyframes registered with the answer's poses), map_raw_initial.ply, map_rendered.ply,
    map_gt.ply, on the grid of mapping_cfg (config.mapping: voxel_size_m, and min_opacity named when the rendered
    map is empty). Returns what it wrote, as arrays (the evaluation measures them without reading the files back);
    trajectories["optimized"]: every input scan's poses [S, 4, 4]."""
    loaded, keyframes, refined, render = made.loaded, made.keyframes, made.refined, made.render
    index = keyframes.loaded_index
    stamps = loaded.timestamps if loaded.timestamps is not None else np.arange(loaded.num_scans, dtype=np.float64)
    trajectories = {"initial": loaded.poses}
    if made.start.baseline_poses is not None:
        trajectories["baseline"] = propagate_corrections(
            loaded.poses, index, made.start.baseline_poses, loaded.timestamps
        )
    trajectories["optimized"] = made.every_scan_poses()
    if made.neld_ba is not None:
        trajectories["neld_ba"] = made.neld_ba
    if loaded.poses_from == "kiss_icp":
        trajectories["odometry"] = loaded.poses
    for name, poses in trajectories.items():
        write_poses(out_dir, f"poses_{name}", stamps, poses)
    if loaded.gt_poses is not None:
        write_poses(out_dir, "poses_gt", stamps, loaded.gt_poses)
    voxel = float(mapping_cfg.voxel_size_m)
    maps = {
        "optimized": {
            "raw": write_raw_map(os.path.join(out_dir, "map_raw.ply"), keyframes.scans, refined.poses, voxel_size=voxel)
        },
        "initial": {
            "raw": write_raw_map(
                os.path.join(out_dir, "map_raw_initial.ply"), keyframes.scans, keyframes.poses, voxel_size=voxel
            )
        },
    }
    if keyframes.gt_map is not None:
        write_point_cloud(os.path.join(out_dir, "map_gt.ply"), keyframes.gt_map)
    if render is not None:
        if len(render.points):
            maps["optimized"]["rendered"] = voxel_downsample(render.points, voxel)
            write_point_cloud(os.path.join(out_dir, "map_rendered.ply"), maps["optimized"]["rendered"])
        else:
            logger.warning(
                "rendered map is empty: no ray reached opacity %.2f (train longer or lower "
                "mapping.min_opacity); map_rendered.ply not written",
                mapping_cfg.min_opacity,
            )
    return RunArtifacts(
        {name: Trajectory(stamps, poses) for name, poses in trajectories.items()},
        maps,
        None if loaded.gt_poses is None else Trajectory(stamps, loaded.gt_poses),
        keyframes.gt_map,
    )


def judge_run(
    out_dir: str,
    config: ml_collections.ConfigDict,
    made: RunSteps,
    written: RunArtifacts,
    budget: TimeBudget,
    judged: tuple,
    sections: dict | None = None,
) -> tuple[dict, list[dict]]:
    """The verdict of a run (judged: judge_crispness' answer for `made`; config: the run's whole config, whose hash
    metrics.json records, its mapping.min_opacity and eval.map_icp_m read): metrics.json (run, scans_report,
    crispness; evaluation where ground truth exists; and the caller's `sections`, e.g. a run over several
    recordings' "sessions"), built here and written once, whole (a rerun into the folder inherits nothing of an
    earlier metrics.json), history.json, scans_report.csv / .png, map_topdown.png and the evaluation's plots.
    Returns (metrics.json's content, the per-scan report's rows)."""
    keyframes, refined = made.keyframes, made.refined
    crisp, per_scan_entropy, margins = judged
    T_all = written.trajectories["optimized"].poses  # made.every_scan_poses(), as write_outputs wrote them
    rows = write_scan_report(out_dir, made, T_all, per_scan_entropy, float(config.mapping.min_opacity))
    plots.plot_map_topdown(
        os.path.join(out_dir, "map_topdown.png"),
        {
            "input poses": register_scans(keyframes.scans, keyframes.poses),
            ("after NeLD-BA" if made.neld_ba is None else f"kept: the {made.start.chosen} poses"): register_scans(
                keyframes.scans, refined.poses
            ),
        },
    )
    crispest = judge.warn_if_not_crispest(crisp, margins)
    summary = {
        "run": run_record(config_hash(config), made, T_all, budget, margins, crispest),
        "scans_report": report.summarize(rows),
        "crispness": crisp,
    }
    if written.gt is not None or written.gt_map is not None:
        gt_files = {
            "gt_poses": None if written.gt is None else os.path.join(out_dir, GT_POSES_FILE),
            "gt_map": None if written.gt_map is None else os.path.join(out_dir, "map_gt.ply"),
        }
        settings = EvalSettings(map_icp_m=float(config.eval.map_icp_m))
        summary["evaluation"] = evaluation_record(out_dir, written, settings, gt_files)
    summary.update(sections or {})
    write_json(os.path.join(out_dir, "metrics.json"), summary, merge=False)
    with open(os.path.join(out_dir, "history.json"), "w") as f:
        json.dump(refined.result.history, f)
    return summary, rows


def judge_crispness(
    eval_cfg: ml_collections.ConfigDict, made: RunSteps, budget: TimeBudget, progress: bool = True
) -> tuple[dict, dict, dict]:
    """The raw map's crispness under the input's, the baseline's (where it ran) and the refined poses, on the same
    query points (the start's figures reused as they are), and how sure the verdict is over query draws (up to the
    budget's judging deadline), with eval_cfg's crispness settings (config.eval): ({method: summary}, {method:
    per-keyframe entropy [K]}, crispness_margins' answer)."""
    keyframes = made.keyframes
    methods = {"initial": keyframes.poses, "optimized": made.refined.poses}
    if made.start.baseline_poses is not None:
        methods["baseline"] = made.start.baseline_poses
    judged, judged_per_scan = made.start.judged
    crisp, per_scan_entropy = judge.map_crispness(
        keyframes, {name: poses for name, poses in methods.items() if name not in judged}, eval_cfg
    )
    crisp, per_scan_entropy = {**judged, **crisp}, {**judged_per_scan, **per_scan_entropy}
    margins = judge.crispness_margins(
        keyframes, methods, eval_cfg, first_draw=crisp, deadline=budget.judging_deadline(), progress=progress
    )
    for other, margin in margins.items():
        logger.info("%s", judge.describe_margin(other, margin))
    return crisp, per_scan_entropy, margins


def run_record(
    run_hash: str, made: RunSteps, T_all: np.ndarray, budget: TimeBudget, margins: dict, crispest: str | None
) -> dict:
    """metrics.json's "run" section: what ran (run_hash: the config's hash, `config_hash`), what the run decided, how
    long it took, the crispness verdict (T_all: the answer's poses of every input scan [S, 4, 4],
    made.every_scan_poses())."""
    result, render = made.refined.result, made.render
    return {
        "config_hash": run_hash,
        "num_input_scans": made.loaded.num_scans,
        "num_scans": made.keyframes.num_scans,  # keyframes: the scans trained on
        "submaps": made.refined.plan.num_submaps,
        "steps": int(result.state.step),
        "schedule_steps": result.schedules.total_steps,  # the plan that ran: fewer than asked when compressed
        "stopped_early": bool(result.stopped_early),
        "train_seconds": round(result.train_seconds, 2),
        "total_seconds": round(budget.run_seconds(), 2),  # every process of a resumed run, as train_seconds
        "plan": None if budget.plan is None else budget.plan.record(),  # each step's seconds, planned at the start
        "stage_seconds": dict(budget.clock.seconds),  # each step's seconds as it ran, in this process
        "device": str(jax.devices()[0]),
        "map_rays": None if render is None else int(render.rays.num_rays),
        "map_rays_rendered": None if render is None else render.num_rendered,
        "final": result.history[-1] if result.history else {},
        **made.start.record(),
        "answer": "neld_ba" if made.neld_ba is None else made.start.chosen,  # whose poses poses_optimized holds
        "crispest": crispest,
        "crispness_margin": margins,  # {other method: the answer's entropy minus its, per draw and mean}
        "path_vs_input": path_vs_input(T_all, made.loaded.poses),
        "travelled": made.travelled,  # the check of the distance travelled against the input's (answer.py)
    }


def path_vs_input(answer: np.ndarray, input_poses: np.ndarray, window_m: float = 50.0) -> dict:
    """How the answer's poses of every input scan [S, 4, 4] change the distance travelled against the input's
    [S, 4, 4]: {"ratio": its whole path over the input's, "largest_window_change": the largest departure from 1 of
    trajectory.window_scales over a window_m window (the input's distance over the answer's, as the distance check
    judging.answer records it), "window_m"}."""
    ratio = path_length_ratio(answer, input_poses)  # NaN where the input does not move
    change = float(np.max(np.abs(window_scales(answer, input_poses, window_m) - 1.0))) if len(answer) > 1 else 0.0
    return {
        "ratio": round(ratio, 6) if np.isfinite(ratio) else None,
        "largest_window_change": round(change, 6),
        "window_m": window_m,
    }


def write_scan_report(
    out_dir: str, made: RunSteps, T_all: np.ndarray, per_scan_entropy: dict, min_opacity: float
) -> list[dict]:
    """scans_report.csv and scans_report.png: one row per input scan (neld_jax.judging.report; T_all: every input scan's
    refined poses [S, 4, 4]); the residuals from the rendered map (none without it), the refinement from the poses
    training started from, and each scan's registration to the result (made.registration, where it ran)."""
    loaded, keyframes, refined, render = made.loaded, made.keyframes, made.refined, made.render
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
    refinement_m, refinement_deg = report.aligned_corrections(made.start.poses, refined.poses)
    rows = report.scan_report(
        report.ScanList(loaded.num_scans, keyframes.loaded_index, loaded.files, loaded.timestamps),
        report.KeyframeMeasures(
            refined.rays_per_keyframe,
            residual,
            per_scan_entropy.get("initial"),
            per_scan_entropy.get("optimized"),
            refinement_m,
            refinement_deg,
        ),
        correction_m,
        correction_deg,
    )
    if made.registration is not None:
        rows = report.add_registration(rows, made.registration.residual_m, made.registration.flag)
    report.write_csv(os.path.join(out_dir, "scans_report.csv"), rows)
    plots.plot_scan_report(os.path.join(out_dir, "scans_report.png"), rows)
    logger.info("scans_report.csv: %d input scans, %d keyframes trained on", loaded.num_scans, num_keyframes)
    return rows
