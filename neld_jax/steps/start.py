"""Where training starts, and how the poses may move from there: the start policy of a run (config.start).

- "input": the loaded poses, moved with the config's own pose steps (train.pose_lr_*).
- "baseline": the classical baseline's poses (neld_jax.baseline), for a start that drifted beyond the field's
  basin of convergence. They are registered to a few mm and the field only refines them, so the pose steps are
  capped (start.pose_lr_from_baseline), a prior holds each pose near its start (start.prior_from_baseline; heavier on
  the translations where the start's raw map is thinner than THIN_MAP_M) and the trajectory's scale is kept
  (docs/method.md, "Which start", "A prior on the pose corrections", "Keeping the start's scale").
- "crisper": the baseline runs, and training starts from whichever of the two gives the crisper raw map (lower mean
  map entropy; a tie keeps the input). The field refines within a few cm and does not undo a blurrier start, and
  without ground truth the map's crispness is the judge at hand.

What the data decides, the baseline decides from the scans and the log says: whether the input's tilt is trusted
(neld_jax.baseline.choose_chain) and whether its chain could follow the scans at all (a chain whose links overlap
too little is given up, and its refinement keeps the input's route). How far the baseline departs from the input is
measured and recorded, not judged: an input may have drifted by any amount.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time

import ml_collections
import numpy as np

from neld_jax.baseline import BaselineSettings, Segments, register_sequence
from neld_jax.errors import ConfigError, DataError
from neld_jax.judging import judge, metrics
from neld_jax.steps.choices import START_POSES
from neld_jax.training.train import PoseSteps, fixed_rows

logger = logging.getLogger(__name__)

CHOICES = START_POSES  # start.poses
FILE = "start_poses.npz"  # the start a run chose, kept for a resume (the baseline's deadline may not repeat)


@dataclasses.dataclass(frozen=True)
class Start:
    """Where training starts: the keyframes' poses [K, 4, 4], which they are ("input" | "baseline"), and the pose
    steps from there. When the baseline ran: its poses [K, 4, 4], seconds, what it decided (baseline.BaselineResult's
    report), how far it departs from the input (metres, largest position difference after rigid alignment) and the
    crispness that judged the start ({method: summary}, {method: per-keyframe entropy}; ({}, {}) when not judged)."""

    poses: np.ndarray
    chosen: str
    pose_steps: PoseSteps
    baseline_poses: np.ndarray | None = None
    baseline_seconds: float | None = None
    baseline_report: dict = dataclasses.field(default_factory=dict)
    departure_m: float | None = None
    judged: tuple = ({}, {})

    def record(self) -> dict:
        """What metrics.json says of the start."""
        out = {"started_from": self.chosen, "pose_steps": self.pose_steps.to_dict()}
        if self.baseline_poses is not None:
            report = self.baseline_report
            out.update(
                baseline_seconds=round(self.baseline_seconds, 2),
                baseline_departure_m=round(self.departure_m, 3),
                baseline_tilt=report.get("tilt"),
                baseline_refined_from=report.get("refined_from"),
                baseline_rounds_done=report.get("map_rounds_done"),
            )
        return out

    def save(self, out_dir: str, config_hash: str, input_poses: np.ndarray) -> None:
        """out_dir/FILE: this start (when the baseline ran), with the config hash and the input poses [K, 4, 4] it
        came from (`resumed`)."""
        if self.baseline_poses is None:
            return
        meta = {
            "config_hash": config_hash,
            "chosen": self.chosen,
            "pose_steps": self.pose_steps.to_dict(),
            "baseline_seconds": self.baseline_seconds,
            "baseline_report": _plain(self.baseline_report),
            "departure_m": self.departure_m,
        }
        path = os.path.join(out_dir, FILE)
        temporary = path + ".tmp.npz"
        np.savez(
            temporary,
            poses=self.poses,
            baseline_poses=self.baseline_poses,
            input_poses=input_poses,
            meta=np.array(json.dumps(meta)),
        )
        os.replace(temporary, path)

    @classmethod
    def resumed(cls, out_dir: str, config_hash: str, input_poses: np.ndarray) -> "Start | None":
        """The start a run in out_dir saved, when it has a checkpoint to resume; None when there is none (the start
        is chosen). A saved start of another config hash or other input poses [K, 4, 4] (beyond 1e-9) is an error
        before anything runs: the checkpoint's corrections are relative to that start."""
        path = os.path.join(out_dir, FILE)
        if not os.path.isfile(path) or not os.path.isdir(os.path.join(out_dir, "checkpoints")):
            return None
        with np.load(path) as saved:
            meta = json.loads(str(saved["meta"]))
            same_input = saved["input_poses"].shape == np.shape(input_poses) and np.allclose(
                saved["input_poses"], input_poses, rtol=0.0, atol=1e-9
            )
            if meta.get("config_hash") != config_hash:
                raise ConfigError(
                    f"{path} was saved under another configuration (hash {meta.get('config_hash')} != "
                    f"{config_hash}); use a new output_dir, or neld-train --restart to start over"
                )
            if not same_input:
                raise DataError(
                    f"{path} was saved for other input poses than the data's now; use a new output_dir, "
                    "or neld-train --restart to start over"
                )
            steps = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["pose_steps"].items()}
            return cls(
                saved["poses"],
                meta["chosen"],
                PoseSteps(**steps),
                saved["baseline_poses"],
                meta["baseline_seconds"],
                meta["baseline_report"],
                meta["departure_m"],
            )


def _plain(report: dict) -> dict:
    return json.loads(json.dumps(report, default=float))


@dataclasses.dataclass(frozen=True)
class StartSettings:
    """What choosing the start reads, each group as the config has it: start (config.start: the policy, the caps
    from the baseline), train (config.train: the config's own pose steps, fixed_scans), baseline (config.baseline),
    eval (config.eval: the crispness that judges a crisper start, and the baseline's own judge) and max_minutes
    (config.max_minutes, which a log line names). Built once at the edge (`from_config`)."""

    start: ml_collections.ConfigDict
    train: ml_collections.ConfigDict
    baseline: ml_collections.ConfigDict
    eval: ml_collections.ConfigDict
    max_minutes: float

    @classmethod
    def from_config(cls, config: ml_collections.ConfigDict) -> "StartSettings":
        """The groups of a run's config that the start reads."""
        return cls(config.start, config.train, config.baseline, config.eval, config.max_minutes)


def choose_start(
    settings: StartSettings, keyframes, deadline: float | None = None, progress: bool = False, recordings=None
) -> Start:
    """The start of training on `keyframes` (settings: StartSettings; settings.start.poses, module docstring).
    deadline: a time.perf_counter() value after which the baseline's multi-view refinement registers no more scans
    (neld_jax.training.budget). recordings: neld_jax.data.sessions.Sessions where keyframes joins several recordings
    (None: one): the baseline's chain restarts at each later one's first keyframe, and the closures that placed it
    join its pose graph."""
    how = str(settings.start.poses).lower()
    if how not in CHOICES:
        raise ConfigError(f"start.poses: unknown value {settings.start.poses!r} ({' | '.join(CHOICES)})")
    fixed_rows(settings.train, keyframes.num_scans)  # train.fixed_scans names keyframes: checked before the baseline
    if how == "input":
        return Start(keyframes.poses, "input", PoseSteps.from_train(settings.train))
    t0 = time.perf_counter()
    result = register_sequence(
        keyframes.scans,
        keyframes.poses,
        BaselineSettings.from_groups(settings.baseline, settings.eval),
        deadline=deadline,
        progress=progress,
        segments=segments_of(recordings),
    )
    seconds = time.perf_counter() - t0
    baseline, report = result.poses, result.report()
    if report.get("stopped_at_deadline"):
        logger.warning(
            "the classical baseline's multi-view refinement stopped after %.2f of its %d rounds, so that "
            "training keeps its share of max_minutes=%g (max_minutes=0 lifts the limit)",
            report["map_rounds_done"],
            int(settings.baseline.map_rounds),
            settings.max_minutes,
        )
    departure_m, path_m = trajectory_departure(keyframes.poses, baseline)
    logger.info(
        "the classical baseline took %.1f s; it departs from the input by up to %.2f m after alignment (%.2f%% "
        "of the %.0f m path)",
        seconds,
        departure_m,
        100 * departure_m / max(path_m, 1e-9),
        path_m,
    )
    methods = {"baseline": baseline} if how == "baseline" else {"initial": keyframes.poses, "baseline": baseline}
    judged = judge.map_crispness(keyframes, methods, settings.eval)
    entropy = {name: summary["mean_map_entropy"] for name, summary in judged[0].items()}
    chosen = "baseline"
    if how == "crisper":
        # A tie keeps the input; the baseline when neither map could be judged.
        chosen = "baseline" if judge.crispest(judged[0]) in ("baseline", None) else "input"
        logger.info(
            "start.poses=crisper: training starts from the %s poses (raw-map entropy: input %s, baseline %s)",
            chosen,
            _text(entropy["initial"]),
            _text(entropy["baseline"]),
        )
    thickness = judged[0]["baseline"].get("mean_plane_thickness_m")
    pose_steps = (
        pose_steps_from_baseline(settings.start, settings.train, thickness)
        if chosen == "baseline"
        else PoseSteps.from_train(settings.train)
    )
    return Start(
        baseline if chosen == "baseline" else keyframes.poses,
        chosen,
        pose_steps,
        baseline,
        seconds,
        report,
        departure_m,
        judged,
    )


def segments_of(recordings) -> Segments:
    """The baseline's view of joined recordings (neld_jax.data.sessions.Sessions; None: one recording): where each
    later one's keyframes begin, and the closures that placed it as links between keyframes."""
    if recordings is None or recordings.count < 2:
        return Segments()
    return Segments(tuple(int(k) for k in recordings.keyframe_bounds[1:-1]), tuple(recordings.keyframe_links()))


# From the baseline's poses, the translations' prior is (THIN_MAP_M / thickness)^2 heavier where the start's raw map is
# thinner than this: dense precise scans (the synthetic baselines' maps 0.86-0.98 cm), where ICP's translations beat
# what the field resolves; real keyframe maps (3.2-4.4 cm) keep the prior as set (docs/method.md, "A prior").
THIN_MAP_M = 0.02


def pose_steps_from_baseline(
    start_cfg: ml_collections.ConfigDict, train_cfg: ml_collections.ConfigDict, thickness_m: float | None
) -> PoseSteps:
    """The pose steps from the baseline's poses: the config's learning rates (train_cfg: config.train) capped at
    start.pose_lr_from_baseline, a prior of start.prior_from_baseline (start_cfg: config.start), (THIN_MAP_M /
    thickness)^2 times heavier on the translations when the start's raw map is thinner than THIN_MAP_M (scans
    precise enough for ICP's translations to beat what the field resolves), and the start's scale kept.
    thickness_m: the start's raw map's mean plane thickness [m] (None: not judged)."""
    cap = tuple(start_cfg.pose_lr_from_baseline or ())
    if cap and len(cap) != 2:
        raise ConfigError(f"start.pose_lr_from_baseline: expected (init, final) or (), got {cap!r}")
    own = PoseSteps.from_train(train_cfg)

    def capped(pair):
        return tuple(min(float(v), float(c)) for v, c in zip(pair, cap)) if cap else pair

    prior = float(start_cfg.prior_from_baseline)
    thin_m = THIN_MAP_M
    heavier = 1.0
    if prior > 0 and thin_m > 0 and thickness_m is not None and 0 < thickness_m < thin_m:
        heavier = (thin_m / thickness_m) ** 2
    steps = PoseSteps(capped(own.lr_trans), capped(own.lr_rot), prior * heavier, prior, keep_scale=True)
    logger.info(
        "training starts from the baseline's poses: pose learning rates %s, a prior of %g on the translations "
        "and %g on the rotations%s, the start's scale kept",
        " -> ".join(f"{v:g}" for v in steps.lr_trans),
        steps.prior_trans,
        steps.prior_rot,
        "" if heavier == 1.0 else f" (the start's map is {100 * thickness_m:.2f} cm thin, under {100 * thin_m:g} cm)",
    )
    return steps


def trajectory_departure(T_input: np.ndarray, T_other: np.ndarray) -> tuple[float, float]:
    """How far another trajectory departs from the input's: (the largest position difference [m] after the best rigid
    alignment of the two, the input's path length [m]). T_input, T_other: [K, 4, 4] matched poses."""
    if len(T_input) < 3:
        return 0.0, 0.0
    errors, _, _, _ = metrics.ate_errors(np.asarray(T_other), np.asarray(T_input), "se3")
    path_m = float(np.linalg.norm(np.diff(np.asarray(T_input)[:, :3, 3], axis=0), axis=1).sum())
    return float(errors.max()), path_m


def _text(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"
