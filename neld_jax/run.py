"""One bundle-adjustment run end to end: load, preprocess, normalise, train (resumable), write outputs, evaluate.

This is the effectful edge that `bin/train.py` calls; the maths lives in the pure modules.
Outputs in config.output_dir (docs/design.md): poses_initial/optimized (.txt TUM, .kitti; one line per input
scan), poses_baseline when the baseline ran (train.init_poses=baseline or crisper), poses_gt.txt when ground
truth exists, map_raw.ply, map_raw_initial.ply, map_rendered.ply, map_gt.ply, config.json, metrics.json (run,
crispness, scans_report, evaluation), history.json, scans_report.csv/.png, map_topdown.png, checkpoints/ and
the evaluation plots.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
import time
from typing import Callable

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from neld_jax import export, mapping, metrics, quality, report, submap_run, submaps, train
from neld_jax.checkpoint import Checkpointer, fit_resuming
from neld_jax.config import with_train
from neld_jax.errors import ConfigError
from neld_jax.data.normalize import fit_normalization
from neld_jax.data.preprocess import load_preprocessed, voxel_downsample
from neld_jax.data.rays import build_mapping_rays, build_rays
from neld_jax.geometry import transform_points
from neld_jax.mapping import render_map
from neld_jax.model import anchor_transform, scan_poses
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)

# Fields that do not change what is computed; a resumed run may change them.
_HASH_EXCLUDED = ("output_dir", "budget", "train.max_minutes", "train.log_every", "train.checkpoint_every", "mapping",
                  "eval", "data.gt_poses_path", "data.gt_map_path", "data.gt_from_scan", "data.scan_frame",
                  "data.gt_time_offset_s")  # budget: a name (its fields are hashed); data.gt_*: ground truth only


def config_hash(config: ml_collections.ConfigDict) -> str:
    d = json.loads(config.to_json_best_effort())
    for path in _HASH_EXCLUDED:
        node, *rest = path.split(".")
        if rest:
            d.get(node, {}).pop(rest[0], None)
        else:
            d.pop(node, None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


def load_and_prepare(config: ml_collections.ConfigDict):
    """Load the sequence named by config.data, preprocess it and fit the normalisation.

    Returns (loaded, keyframes, norm): every input scan as read, the preprocessed keyframes that training uses
    (keyframes.source_index indexes loaded), and the normalisation fitted to the keyframes."""
    loaded, seq = load_preprocessed(config.data)
    norm = fit_normalization(seq.scans, seq.poses, margin=config.data.normalization_margin)
    check_extent(seq, norm, config)
    return loaded, seq, norm


def check_extent(seq, norm, config: ml_collections.ConfigDict) -> None:
    """Stop with one clear line when the scene is larger than one field should hold (data.max_extent_m).

    One MLP in one cube has a fixed resolution: its finest Fourier period, 2^(2 - L) normalised units, grows
    with the scene (issue: submaps for larger sequences). Running such a sequence anyway gives a blurred field
    and poses worse than the odometry's, so it is refused with the way to run it in pieces."""
    extent_m = 2.0 * config.data.normalization_margin / norm.scale
    limit = float(config.data.max_extent_m)
    if submaps.submaps_wanted(config, extent_m):
        return  # split into submaps, each cube within submaps.max_detail_m (neld_jax.submaps)
    if limit > 0 and extent_m > limit:
        period_m = 2.0 ** (2 - int(config.model.pos_freqs)) / norm.scale
        raise ConfigError(
            f"{seq.source or seq.name}: the scans span {extent_m:.0f} m, more than data.max_extent_m={limit:g} m that "
            f"one field holds (its finest detail would be {period_m:.2f} m at model.pos_freqs="
            f"{config.model.pos_freqs}); train it as submaps with submaps.enabled=on, or run it in pieces with "
            f"data.first_scan / data.max_scans (or lower data.max_range_m, or raise data.max_extent_m to run it anyway)")


@dataclasses.dataclass(frozen=True)
class Start:
    """Where training starts (train.init_poses): poses [K, 4, 4] of the keyframes, and what chose them.

    baseline_poses [K, 4, 4] and baseline_seconds are set whenever the classical baseline ran (init_poses
    "baseline" or "crisper"), whichever start won; chosen is "input" or "baseline". judged: the crispness that
    chose the start ("crisper": quality.map_crispness's ({method: summary}, {method: per-keyframe entropy}) for
    "initial" and "baseline"), so that the run does not measure it again; ({}, {}) otherwise."""

    poses: np.ndarray
    chosen: str
    baseline_poses: np.ndarray | None = None
    baseline_seconds: float | None = None
    judged: tuple = ({}, {})
    departure_m: float | None = None  # trajectory_departure of the baseline from the input (when it ran)
    bent: bool = False  # the departure exceeds what train.max_baseline_departure allows
    refined_from: str | None = None  # where the baseline's multi-view refinement started ("graph" | "chain" | "input")
    # The rounds of that refinement completed: baseline.map_rounds, or a fraction when the run's deadline stopped them
    rounds_done: float | None = None


START_CHOICES = ("input", "baseline", "crisper")


def starting_poses(config: ml_collections.ConfigDict, seq, deadline: float | None = None,
                   progress: bool = False) -> Start:
    """The keyframe poses training starts from (train.init_poses).

    "input": the loaded poses (odometry). "baseline": the classical baseline's (Open3D scan-to-map ICP +
    loop-closed pose graph + multi-view refinement, config.baseline; the refinement starts from the graph's or
    the input's poses: `refinement_start`) run from them first, for starts that drifted further than the
    field's basin of convergence. "crisper": the baseline runs, and training starts from whichever of the two
    gives the crisper raw map (lower mean map entropy, config.eval's crispness settings). The field refines
    within a few cm and cannot undo a blurrier start (docs/method.md, "Which start"); without ground truth the
    map's crispness is the judge that is at hand. deadline: a time.perf_counter() value after which the baseline's
    multi-view refinement registers no more scans (`baseline_deadline`; None: it runs all its rounds). progress: the
    baseline's progress bars."""
    how = str(config.train.init_poses).lower()
    if how not in START_CHOICES:
        raise ConfigError(f"train.init_poses: unknown value {config.train.init_poses!r} ({' | '.join(START_CHOICES)})")
    if how == "input":
        return Start(seq.poses, "input")
    from neld_jax.baseline import BaselineSettings, register_sequence

    t0 = time.perf_counter()
    decided, refined = {}, {}
    settings = BaselineSettings.from_config(config.get("baseline"))
    poses = register_sequence(seq.scans, seq.poses, settings, refinement_start(config, seq, decided),
                              deadline=deadline, report=refined, progress=progress)
    seconds = time.perf_counter() - t0
    logger.info("train.init_poses=%s: the classical baseline took %.1f s", how, seconds)
    if refined.get("stopped_at_deadline"):
        logger.warning("the classical baseline's multi-view refinement stopped after %.2f of its %d rounds, so that "
                       "training keeps %.0f%% of train.max_minutes=%g (its poses are taken as they are; "
                       "train.max_minutes=0 lifts the limit)", refined["map_rounds_done"], settings.map_rounds,
                       100 * MIN_TRAINING_SHARE, config.train.max_minutes)
    rounds_done = refined.get("map_rounds_done")
    refined_from = decided.get("refined_from") or refined.get("refined_from")  # the latter: the chain was given up
    bent, departure_m, path_m, allowed_m = departure_check(config, seq.poses, poses)
    limit = float(config.train.get("max_baseline_departure", 0.0))
    if bent:
        logger.warning("the baseline's trajectory departs from the input's by up to %.2f m after alignment, %.2f%% of "
                       "the %.0f m path (more than the %.2f m allowed: train.max_baseline_departure=%g of the path, "
                       "at least train.baseline_departure_floor_m; the drift expected of the input): its chain may "
                       "have bent on scans that overlap too little; compare poses_baseline with poses_initial",
                       departure_m, 100 * departure_m / max(path_m, 1e-9), path_m, allowed_m, limit)
    if how == "baseline":
        return Start(poses, "baseline", poses, seconds, departure_m=departure_m, bent=bent,
                     refined_from=refined_from, rounds_done=rounds_done)
    # The input's crispness, measured when the refinement's start was chosen, is not measured again.
    measured = decided.get("input_judged")
    if measured is None:
        judged = quality.map_crispness(seq, {"initial": seq.poses, "baseline": poses}, config.eval)
    else:
        baseline_judged = quality.map_crispness(seq, {"baseline": poses}, config.eval)
        judged = tuple({**first, **then} for first, then in zip(measured, baseline_judged))
    entropy = {name: summary["mean_map_entropy"] for name, summary in judged[0].items()}
    # A tie keeps the input; the baseline when neither map could be judged. The judge is local (0.3 m
    # neighbourhoods): a baseline that bent the whole trajectory can still give the crisper map, hence `bent`.
    chosen = "baseline" if quality.crispest(judged[0]) in ("baseline", None) and not bent else "input"
    logger.info("train.init_poses=crisper: training starts from the %s poses (raw-map entropy: input %s, "
                "baseline %s%s)", chosen, _entropy_text(entropy["initial"]), _entropy_text(entropy["baseline"]),
                "; the baseline departs too far from the input" if bent else "")
    return Start(poses if chosen == "baseline" else seq.poses, chosen, poses, seconds, judged, departure_m, bent,
                 refined_from, rounds_done)


# The poses a run's training started from when the classical baseline ran, kept in its output_dir for a resume: the
# baseline's refinement stops at a wall-clock deadline (`baseline_deadline`), so running it again could give other
# poses, and the checkpoint's pose corrections are relative to the first run's.
START_FILE = "start_poses.npz"


def save_start(out_dir: str, start: Start, config_hash_: str, input_poses: np.ndarray) -> None:
    """Write `start` (when the baseline ran) to out_dir/START_FILE with the config hash and the input poses [K, 4, 4]
    it came from (`resumed_start` checks both)."""
    if start.baseline_poses is None:
        return
    meta = {"config_hash": config_hash_, "chosen": start.chosen, "baseline_seconds": start.baseline_seconds,
            "departure_m": start.departure_m, "bent": start.bent, "refined_from": start.refined_from,
            "rounds_done": start.rounds_done}
    path = os.path.join(out_dir, START_FILE)
    temporary = path + ".tmp.npz"
    np.savez(temporary, poses=start.poses, baseline_poses=start.baseline_poses, input_poses=input_poses,
             meta=np.array(json.dumps(meta)))
    os.replace(temporary, path)


def load_start(out_dir: str) -> tuple[Start, str | None, np.ndarray] | None:
    """(the Start, the config hash, the input poses [K, 4, 4] it came from) that a run in out_dir saved
    (`save_start`), or None when it saved none (its training started from the input)."""
    path = os.path.join(out_dir, START_FILE)
    if not os.path.isfile(path):
        return None
    with np.load(path) as saved:
        meta = json.loads(str(saved["meta"]))
        start = Start(saved["poses"], meta["chosen"], saved["baseline_poses"], meta["baseline_seconds"],
                      departure_m=meta["departure_m"], bent=meta["bent"], refined_from=meta["refined_from"],
                      rounds_done=meta["rounds_done"])
        return start, meta.get("config_hash"), saved["input_poses"]


def same_input_poses(saved_input: np.ndarray, input_poses: np.ndarray) -> bool:
    """Whether a saved start (load_start) came from these input poses [K, 4, 4]: the same keyframes, read from the
    same files (to 1e-9)."""
    return saved_input.shape == np.shape(input_poses) and np.allclose(saved_input, input_poses, rtol=0.0, atol=1e-9)


def resumed_start(out_dir: str, config_hash_: str, input_poses: np.ndarray) -> Start | None:
    """The Start a run in out_dir saved (`save_start`), when that run left a checkpoint to resume, had the same
    config hash and started from the same input poses [K, 4, 4]; None otherwise (the start is chosen again)."""
    saved = load_start(out_dir)
    if saved is None:
        return None
    checkpoints = Checkpointer(os.path.join(out_dir, "checkpoints"))  # what fit_resuming would resume from
    resumable = checkpoints.latest_step() is not None
    checkpoints.close()
    start, saved_hash, saved_input = saved
    return start if resumable and saved_hash == config_hash_ and same_input_poses(saved_input, input_poses) else None


def _entropy_text(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def departure_check(config: ml_collections.ConfigDict, T_input: np.ndarray,
                    T_other: np.ndarray) -> tuple[bool, float, float, float]:
    """Whether another trajectory (the baseline's, or its pose graph's) is bent away from the input's: (bent,
    departure_m, path_m, allowed_m), with `trajectory_departure`'s figures and the departure allowed,
    train.max_baseline_departure of the input's path and at least train.baseline_departure_floor_m. Never bent
    when train.max_baseline_departure is 0 (allowed_m: infinite)."""
    departure_m, path_m = trajectory_departure(T_input, T_other)
    train_cfg = config.get("train", {})
    limit = float(train_cfg.get("max_baseline_departure", 0.0))
    # A short path (Hilti quick-shack: 7 m walked in a room, the baseline 0.27 m from FAST-LIO2's poses and far
    # crisper) says little about the odometry's drift, which also grows with time: at least the floor is allowed.
    allowed_m = max(limit * path_m, float(train_cfg.get("baseline_departure_floor_m", 0.0))) if limit > 0 else math.inf
    return departure_m > allowed_m, departure_m, path_m, allowed_m


def refinement_start(config: ml_collections.ConfigDict, seq,
                     decided: dict | None = None) -> Callable[[np.ndarray], np.ndarray] | None:
    """baseline.register_sequence's `refine_from` for config.baseline.refine_from="crisper" or "scans" (None for
    "graph"): given the pose graph's poses [K, 4, 4] (chain + loop closures), the poses its multi-view refinement
    starts from. "crisper": the graph's, unless they give a blurrier raw map than the input's (seq.poses; mean map
    entropy, config.eval's settings) or depart from them further than `departure_check` allows; then the input's.
    Given the chain's poses too (baseline.keep_input_tilt), the crispest of the three that is not bent. "scans":
    the crisper of the graph's and the chain's that is not bent, however crisp the input; the input's only when
    both are bent (the rounds keep their start's route-long shape, and the input's is its drift: main building,
    the two starts' answers 2.79 cm apart refined from the odometry and the chain, 0.34 cm from the two chains).

    The refinement moves each scan by at most the loop closures' gate, so from the input it cannot bend the
    trajectory. Measured (docs/evaluation.md, "Where the refinement starts"): HKU main building, graph -3.256 and
    FAST-LIO2's odometry -3.310, refined from the graph -3.368 and from the odometry -3.395; MulRan Riverside02,
    the graph bent by 33.7 m, refined from the odometry -3.331 against the odometry's -3.307. `decided`, when
    given, receives {"refined_from": "graph" | "chain" | "input", "graph_entropy", "input_entropy",
    "graph_departure_m", with the chain "chain_entropy" and "chain_departure_m", "input_judged":
    quality.map_crispness's pair for the input alone, as "initial" (`starting_poses` reuses it)}."""
    choice = str(config.get("baseline", {}).get("refine_from", "crisper")).lower()
    if choice not in ("crisper", "scans", "graph"):
        raise ConfigError(f"baseline.refine_from: unknown value {choice!r} (crisper | scans | graph)")
    if choice == "graph":
        return None
    decided = {} if decided is None else decided

    def choose(graph_poses: np.ndarray, chain_poses: np.ndarray | None = None) -> np.ndarray:
        candidates = {"graph": graph_poses} if chain_poses is None else {"graph": graph_poses, "chain": chain_poses}
        checked = {name: departure_check(config, seq.poses, poses) for name, poses in candidates.items()}
        judged = quality.map_crispness(seq, {**candidates, "initial": seq.poses}, config.get("eval", {}))
        entropy = {name: summary["mean_map_entropy"] for name, summary in judged[0].items()}
        unbent = {name: summary for name, summary in judged[0].items() if name == "initial" or not checked[name][0]}
        bent, departure_m, _, allowed_m = checked["graph"]
        # A tie (or no judge) keeps the graph, as the baseline always did; a bent candidate is never taken.
        if choice == "scans":  # the input only when every candidate the scans gave is bent
            from_scans = {name: summary for name, summary in unbent.items() if name != "initial"}
            picked = quality.crispest(from_scans) or next(iter(from_scans), "initial")
        else:
            picked = quality.crispest(unbent) or ("initial" if bent else "graph")
        decided.update(refined_from="input" if picked == "initial" else picked, graph_entropy=entropy["graph"],
                       input_entropy=entropy["initial"], graph_departure_m=departure_m,
                       input_judged=tuple({"initial": part["initial"]} for part in judged))
        if chain_poses is not None:
            decided.update(chain_entropy=entropy["chain"], chain_departure_m=checked["chain"][1])
        chain_departure = "" if chain_poses is None else (
            f"; the chain {checked['chain'][1]:.2f} m{': bent' if checked['chain'][0] else ''}")
        allowed = (f"{allowed_m:.2f} m allowed" if math.isfinite(allowed_m)
                   else "no limit: train.max_baseline_departure=0")
        logger.info("baseline: the multi-view refinement starts from the %s poses (raw-map entropy: input %s, pose "
                    "graph %s%s; the graph departs %.2f m from the input%s%s, %s)",
                    decided["refined_from"], _entropy_text(entropy["initial"]), _entropy_text(entropy["graph"]),
                    "" if chain_poses is None else f", chain {_entropy_text(entropy['chain'])}",
                    departure_m, ": bent" if bent else "", chain_departure, allowed)
        if bent:
            logger.warning("the baseline's pose graph departs %.2f m from the input's trajectory, more than the %.2f m "
                           "allowed (train.max_baseline_departure, train.baseline_departure_floor_m): its chain may "
                           "have bent, so the %s poses are refined instead; if the input drifts more than that, "
                           "set train.max_baseline_departure=0", departure_m, allowed_m, decided["refined_from"])
        return {"graph": graph_poses, "chain": chain_poses, "initial": seq.poses}[picked]

    return choose


def trajectory_departure(T_input: np.ndarray, T_other: np.ndarray) -> tuple[float, float]:
    """How far another trajectory departs from the input's: (the largest position difference [m] after the best
    rigid alignment of the two, the input's path length [m]). T_input, T_other: [K, 4, 4] matched poses.

    Local crispness cannot see a trajectory bent as a whole; this can, against a prior on the input's drift."""
    if len(T_input) < 3:
        return 0.0, 0.0
    errors, _, _, _ = metrics.ate_errors(np.asarray(T_other), np.asarray(T_input), "se3")
    path_m = float(np.linalg.norm(np.diff(np.asarray(T_input)[:, :3, 3], axis=0), axis=1).sum())
    return float(errors.max()), path_m


def judge_start(config: ml_collections.ConfigDict, seq, start: Start) -> Start:
    """start, with the crispness of its map measured (judged["baseline"]) when training starts from the baseline's
    poses, train.pose_prior_thin_map_m needs that map's thickness (`start_thickness`) and the crisper start's
    judge did not measure it (a start from the baseline alone, a resumed start). The run's crispness table reuses
    it, as it does the judge's (the same query points, so the same figures)."""
    if (start.chosen != "baseline" or float(config.train.get("pose_prior_thin_map_m", 0.0)) <= 0
            or "baseline" in start.judged[0]):
        return start
    summaries, per_scan = quality.map_crispness(seq, {"baseline": start.poses}, config.get("eval", {}))
    return dataclasses.replace(start, judged=({**start.judged[0], **summaries}, {**start.judged[1], **per_scan}))


def start_thickness(start: Start) -> float | None:
    """The mean plane thickness [m] of the keyframes' raw map under the baseline's poses when training starts from
    them and it was measured (`judge_start`); None otherwise (`pose_steps_for_start`)."""
    if start.chosen != "baseline":
        return None
    return start.judged[0].get("baseline", {}).get("mean_plane_thickness_m")


def pose_steps_for_start(config: ml_collections.ConfigDict, chosen: str,
                         start_thickness_m: float | None = None) -> ml_collections.ConfigDict:
    """config, or a copy for a start from the classical baseline's poses (chosen == "baseline"): its pose learning
    rates capped at train.pose_lr_from_baseline = (init, final), its pose prior at least
    train.pose_prior_from_baseline, and its trajectory's scale kept (train.keep_start_scale) when
    train.keep_scale_from_baseline. Those poses are registered to a few mm and the field only refines them: the
    cpu budget's pose steps (1e-3) walked the long synthetic route's baseline from 0.0064 to 0.0366 m ATE
    (docs/method.md, "Which start"), without the prior the first pose steps blur a real baseline's map
    (docs/method.md, "A prior on the pose corrections"), and the field's rendering shrinks the trajectory
    (docs/method.md, "Keeping the start's scale"). From the odometry the prior would hold back the corrections
    the field makes (HKU_2: -3.421 -> -3.441 with it, -3.453 without), and a drifted start's scale is part of its
    drift, so neither is set there.

    start_thickness_m: the mean plane thickness [m] of the raw map under the start's poses (`start_thickness`).
    Below train.pose_prior_thin_map_m the prior on the translation columns is (thin_map_m / thickness)^2 times
    heavier, the rotation columns' weight unchanged: a thin map means scans precise enough for ICP's translations
    to be better than the field resolves (docs/method.md, "A prior on the pose corrections")."""
    if chosen != "baseline":
        return config
    cap = tuple(config.train.get("pose_lr_from_baseline", ()) or ())
    if cap and len(cap) != 2:
        raise ConfigError(f"train.pose_lr_from_baseline: expected (init, final) or (), got {cap!r}")
    changed = {f"pose_lr_{part}_{which}": min(float(config.train[f"pose_lr_{part}_{which}"]), float(limit))
               for part in ("rot", "trans") for which, limit in zip(("init", "final"), cap)}
    weight = float(config.train.get("pose_prior_weight", 0.0))
    prior = max(float(config.train.get("pose_prior_from_baseline", 0.0)), weight)
    if prior > weight:
        changed["pose_prior_weight"] = prior
    thin_map_m = float(config.train.get("pose_prior_thin_map_m", 0.0))
    heavier = 1.0
    if prior > 0 and thin_map_m > 0 and start_thickness_m is not None and 0 < start_thickness_m < thin_map_m:
        heavier = (thin_map_m / start_thickness_m) ** 2
        changed["pose_prior_weight"] = prior * heavier
        changed["pose_prior_rot_factor"] = float(config.train.get("pose_prior_rot_factor", 1.0)) / heavier
    if config.train.get("keep_scale_from_baseline", False):  # with_train keeps config when it is already on
        changed["keep_start_scale"] = True
    adapted = with_train(config, **changed)
    if adapted is not config:
        thin_text = "" if heavier == 1.0 else (
            f" on the translations ({heavier:.2f}x: the start's map is {100 * start_thickness_m:.2f} cm thin, "
            f"train.pose_prior_thin_map_m={100 * thin_map_m:g} cm), "
            f"{adapted.train.pose_prior_weight * adapted.train.pose_prior_rot_factor:g} on the rotations")
        logger.info("training starts from the baseline's poses: pose learning rates capped at %s, pose prior %g%s, "
                    "the start's scale %s (train.pose_lr_from_baseline, train.pose_prior_from_baseline, "
                    "train.keep_scale_from_baseline)", " -> ".join(f"{v:g}" for v in cap) or "(no cap)",
                    adapted.train.get("pose_prior_weight", 0.0), thin_text,
                    "kept" if adapted.train.get("keep_start_scale", False) else "free")
    return adapted


# Training always gets at least this share of train.max_minutes, however long the run took before it.
MIN_TRAINING_SHARE = 0.25


def training_seconds(config: ml_collections.ConfigDict, spent_s: float) -> float:
    """The wall-clock seconds training may take in a run that has spent `spent_s` before it (loading, the
    classical baseline): train.max_minutes counts from the run's start, so that a budget's whole run keeps its
    time whatever the baseline took (HKU main building: about 5 minutes of baseline), but training gets at least
    MIN_TRAINING_SHARE of it. 0 when train.max_minutes is 0 (no limit)."""
    limit = float(config.train.max_minutes) * 60.0
    if limit <= 0:
        return 0.0
    return max(limit - float(spent_s), MIN_TRAINING_SHARE * limit)


def baseline_deadline(config: ml_collections.ConfigDict, t_start: float) -> float | None:
    """The time.perf_counter() value after which the classical baseline's multi-view refinement registers no more
    scans in a run started at t_start: when the run has used all of train.max_minutes but training's floor
    (MIN_TRAINING_SHARE), so that the whole run keeps its time however slow the registration is (MulRan Riverside02:
    a 451 s baseline on a slow spell took the run to 10.6 minutes; docs/design.md, "The loop"); a scan-to-map chain
    still running then is given up (half a chain cannot feed the pose graph), and the pose graph always
    finishes. None when train.max_minutes is 0 (no limit)."""
    limit = float(config.train.max_minutes) * 60.0
    if limit <= 0:
        return None
    return t_start + (1.0 - MIN_TRAINING_SHARE) * limit


# The rendered map always gets at least this share of mapping.max_seconds, however late the run is.
MIN_RENDERING_SHARE = 0.25


def rendering_seconds(config: ml_collections.ConfigDict, elapsed_s: float) -> float:
    """The rendered map's time limit in a run `elapsed_s` seconds old: mapping.max_seconds, less the seconds the
    run is past train.max_minutes (training's floor, MIN_TRAINING_SHARE, can carry it past: Riverside02's 400 s
    baseline), so that the run still ends near train.max_minutes + mapping.max_seconds; at least
    MIN_RENDERING_SHARE of mapping.max_seconds. Unchanged when either limit is 0 (none)."""
    limit = float(config.mapping.max_seconds)
    deadline = float(config.train.max_minutes) * 60.0
    if limit <= 0 or deadline <= 0:
        return limit
    return max(limit - max(float(elapsed_s) - deadline, 0.0), MIN_RENDERING_SHARE * limit)


def margins_deadline(config: ml_collections.ConfigDict, t_start: float) -> float | None:
    """The time.perf_counter() value after which the crispness margins start no more query draws in a run started
    at t_start: train.max_minutes + mapping.max_seconds + eval.crispness_draws_max_seconds, so that the run stays
    near its 10 minutes on the largest maps (HKU_1's 1.5 M points: 15 s a draw of three maps, and a run of 10 min
    22 s with every draw). None when train.max_minutes or eval.crispness_draws_max_seconds is 0 (no limit)."""
    limit = float(config.train.max_minutes) * 60.0
    extra = float(config.eval.get("crispness_draws_max_seconds", 0.0))
    if limit <= 0 or extra <= 0:
        return None
    return t_start + limit + max(float(config.mapping.max_seconds), 0.0) + extra


def train_single_cube(config: ml_collections.ConfigDict, seq, norm, raysets, T_start: np.ndarray, out_dir: str,
                      chash: str, progress: bool, max_seconds: float | None = None):
    """Train one field over the whole sequence (resuming from out_dir's checkpoints), the paper's setting.

    T_start: [K, 4, 4] world poses training starts from; max_seconds: the training guard (None: train.max_minutes).
    Returns (FitResult, T_field_n [K, 4, 4] the poses in the field's normalised frame, G_n [4, 4] the anchoring
    transform of train.anchor_scan)."""
    rays = train.device_rays(raysets)
    T_init = jnp.asarray(norm.poses_to_normalized(T_start), jnp.float32)

    # Resume from the latest checkpoint of this output_dir, if any, with its history and training seconds.
    metadata = {"config_hash": chash, "normalization": norm.to_dict(), "num_scans": seq.num_scans}
    result = fit_resuming(os.path.join(out_dir, "checkpoints"), metadata,
                          lambda: train.initial_state(config, seq.num_scans, norm.scale),
                          functools.partial(train.fit, config, rays, T_init, norm.scale, progress=progress,
                                            max_seconds=max_seconds))

    T_field_n, G_n = field_poses(result.state.params["poses"], T_init, config.train.anchor_scan)
    return result, T_field_n, G_n


def training_frame(config: ml_collections.ConfigDict, seq, norm, start: Start, num_devices: int):
    """(the normalisation, the submap plan or None) that training uses from `start`: norm, the one fitted to the
    input poses, when training starts from them; else refitted to start.poses. The plan splits the keyframes at
    start.poses over num_devices devices (submaps.plan_from_config)."""
    if start.chosen != "input":
        # The cube and the submaps are fitted to the poses training starts from: from a drifted start the
        # baseline moves scans by metres, and a loop that the drift hid is closed in its poses.
        norm = fit_normalization(seq.scans, start.poses, margin=config.data.normalization_margin)
    plan = submaps.plan_from_config(dataclasses.replace(seq, poses=start.poses), norm, config,
                                    num_devices=num_devices)
    return norm, plan


@dataclasses.dataclass(frozen=True)
class Trained:
    """What training gave (train_keyframes): the FitResult, the keyframes' world poses T_opt [K, 4, 4], and what the
    rendered map needs: the submaps' SubmapResult, or the single cube's T_field_n [K, 4, 4] and G_n [4, 4]."""

    result: train.FitResult
    T_opt: np.ndarray
    submaps: submap_run.SubmapResult | None = None
    T_field_n: np.ndarray | None = None
    G_n: np.ndarray | None = None


def train_keyframes(config: ml_collections.ConfigDict, seq, norm, raysets, T_start: np.ndarray, plan, out_dir: str,
                    chash: str, progress: bool, max_seconds: float | None = None) -> Trained:
    """Train the field(s) over the keyframes from T_start [K, 4, 4] (world): one cube, or the submaps of `plan`
    (not None: the sequence outgrows one cube). Resumes from out_dir's checkpoints. The one step of a run that
    needs no open3d: benchmarks/real_gpu.py runs it alone on a GPU image without it."""
    if plan is not None:  # the sequence outgrows one cube: submaps (neld_jax.submap_run), same outputs
        trained = submap_run.train_submaps(config, seq, norm, T_start, plan, out_dir, chash, progress, max_seconds)
        return Trained(trained.result, trained.G @ trained.T_field, submaps=trained)
    result, T_field_n, G_n = train_single_cube(config, seq, norm, raysets, T_start, out_dir, chash, progress,
                                               max_seconds)
    return Trained(result, norm.poses_to_world(G_n @ T_field_n), T_field_n=T_field_n, G_n=G_n)


def field_poses(pose_params, T_init, anchor_scan: int) -> tuple[np.ndarray, np.ndarray]:
    """The scans' poses in the field's normalised frame (what the field renders with) and the anchoring transform
    that keeps scan `anchor_scan` at its initial pose (identity when anchor_scan < 0); the world poses are
    norm.poses_to_world(G_n @ T_field_n). pose_params: [K, 6]; T_init: [K, 4, 4] normalised.
    Returns (T_field_n [K, 4, 4], G_n [4, 4]), float64."""
    T_field_n = np.asarray(scan_poses(pose_params, T_init), np.float64)
    G_n = np.eye(4)
    if anchor_scan >= 0:
        G_n = np.asarray(anchor_transform(T_field_n, np.asarray(T_init, np.float64), int(anchor_scan)))
    return T_field_n, G_n


def run(config: ml_collections.ConfigDict, progress: bool = True) -> dict:
    """Run the bundle adjustment described by `config`; returns the summary written to metrics.json."""
    t_start = time.perf_counter()
    out_dir = os.path.abspath(config.output_dir)
    os.makedirs(out_dir, exist_ok=True)
    chash = config_hash(config)
    logger.info("budget %s (jax's default backend: %s)", config.get("budget", "?"), jax.default_backend())

    loaded, seq, norm = load_and_prepare(config)
    start = resumed_start(out_dir, chash, seq.poses)
    if start is None:
        start = starting_poses(config, seq, deadline=baseline_deadline(config, t_start), progress=progress)
        save_start(out_dir, start, chash, seq.poses)
    else:
        logger.info("resuming: training starts from the %s poses the first run chose (%s; the classical baseline is "
                    "not run again)", start.chosen, START_FILE)
    start = judge_start(config, seq, start)
    config = pose_steps_for_start(config, start.chosen, start_thickness(start))
    # The config as trained (the start can cap the pose steps); the hash above stays the user's, for resuming.
    export.write_json(os.path.join(out_dir, "config.json"), json.loads(config.to_json_best_effort()))
    T_start = start.poses
    norm, plan = training_frame(config, seq, norm, start, num_devices=submap_run.num_devices(config))
    raysets = build_rays(seq, norm, max_rays_per_scan=(config.data.max_rays_per_scan or None), seed=config.seed)
    logger.info("%d keyframes of %d input scans, %d training rays, normalisation scale %.5f "
                "(1 normalised unit = %.2f m)", seq.num_scans, loaded.num_scans, raysets.num_rays, norm.scale,
                1.0 / norm.scale)
    spent_s = time.perf_counter() - t_start
    max_seconds = training_seconds(config, spent_s)
    if max_seconds > 0 and max_seconds < float(config.train.max_minutes) * 60.0:
        logger.info("the run spent %.0f s before training: training may take %.1f of the run's %g minutes "
                    "(train.max_minutes)", spent_s, max_seconds / 60.0, config.train.max_minutes)
    trained = train_keyframes(config, seq, norm, raysets, T_start, plan, out_dir, chash, progress, max_seconds)
    result, T_opt = trained.result, trained.T_opt
    state, train_seconds = result.state, result.train_seconds
    if result.total_steps and result.total_steps != int(config.train.steps):
        # The guard compressed the schedule: the rendered map's window and config.json follow the plan that ran.
        config = train.with_steps(config, result.total_steps)
        export.write_json(os.path.join(out_dir, "config.json"), json.loads(config.to_json_best_effort()))

    # Every input scan gets a pose: keyframes their own, the others their keyframes' interpolated correction.
    keyframe_index = seq.loaded_index
    T_all = propagate_corrections(loaded.poses, keyframe_index, T_opt, loaded.timestamps)
    export.write_poses(out_dir, "poses_initial", loaded.timestamps, loaded.poses)
    export.write_poses(out_dir, "poses_optimized", loaded.timestamps, T_all)
    if start.baseline_poses is not None:  # the baseline's own result, for every input scan too
        export.write_poses(out_dir, "poses_baseline", loaded.timestamps, propagate_corrections(
            loaded.poses, keyframe_index, start.baseline_poses, loaded.timestamps))
    if loaded.gt_poses is not None:
        export.write_poses(out_dir, "poses_gt", loaded.timestamps, loaded.gt_poses)
    if seq.gt_map is not None:
        export.write_point_cloud(os.path.join(out_dir, "map_gt.ply"), seq.gt_map)
    voxel = float(config.mapping.voxel_size_m)
    export.write_raw_map(os.path.join(out_dir, "map_raw.ply"), seq.scans, T_opt, voxel_size=voxel)
    export.write_raw_map(os.path.join(out_dir, "map_raw_initial.ply"), seq.scans, seq.poses, voxel_size=voxel)

    rendered = None
    if config.mapping.enabled:
        elapsed_s = time.perf_counter() - t_start
        map_seconds = rendering_seconds(config, elapsed_s)
        if map_seconds < float(config.mapping.max_seconds):
            logger.info("the run is %.0f s past train.max_minutes=%g: the rendered map may take %.0f of its %g s "
                        "(mapping.max_seconds)", elapsed_s - float(config.train.max_minutes) * 60.0,
                        config.train.max_minutes, map_seconds, config.mapping.max_seconds)
        if plan is not None:
            rendered = submap_run.write_rendered_map(config, trained.submaps, plan, norm, seq, out_dir, progress,
                                                     map_seconds)
        else:
            rendered = _write_rendered_map(config, state, norm, seq, trained.T_field_n, trained.G_n, out_dir,
                                           progress, map_seconds)

    # Quality without ground truth: crispness of the keyframes' raw map, and the per-scan report.
    # The same query points for every method, so the starts' figures from starting_poses are reused as they are.
    methods = {"initial": seq.poses, "optimized": T_opt}
    if start.baseline_poses is not None:
        methods["baseline"] = start.baseline_poses
    judged, judged_per_scan = start.judged
    crisp, per_scan_entropy = quality.map_crispness(
        seq, {name: poses for name, poses in methods.items() if name not in judged}, config.eval)
    crisp, per_scan_entropy = {**judged, **crisp}, {**judged_per_scan, **per_scan_entropy}
    rows = quality.write_scan_report(out_dir, loaded, seq, keyframe_index, T_all, raysets, rendered, norm,
                                     per_scan_entropy, min_opacity=float(config.mapping.min_opacity),
                                     start_poses=start.poses, refined_poses=T_opt)
    quality.write_topdown(out_dir, seq, {"input poses": seq.poses, "after NeLD-BA": T_opt})
    # How sure that verdict is: the same comparison over eval.crispness_draws draws of the query points (the
    # figures above are draw 0's)
    margins = quality.crispness_margins(seq, methods, config.eval, first_draw=crisp,
                                        deadline=margins_deadline(config, t_start), progress=progress)
    for other, margin in margins.items():
        logger.info("%s", quality.describe_margin(other, margin))

    summary = {
        "config_hash": chash,
        "num_input_scans": loaded.num_scans,
        "num_scans": seq.num_scans,  # keyframes: the scans trained on
        "num_rays": int(raysets.num_rays),
        "steps": int(state.step),
        "schedule_steps": int(config.train.steps),  # the plan that ran: fewer than asked when compressed to time
        "stopped_early": bool(result.stopped_early),
        "train_seconds": round(train_seconds, 2),
        "total_seconds": round(time.perf_counter() - t_start, 2),
        "device": str(jax.devices()[0]),
        "submaps": None if plan is None else int((plan.weight > 0).sum()),
        # The rendered map's rays, and how many of them its time limit (mapping.max_seconds) let render
        "map_rays": None if rendered is None else int(rendered[0].num_rays),
        "map_rays_rendered": None if rendered is None else rendered[1].num_rendered,
        "final": result.history[-1] if result.history else {},
    }
    summary["started_from"] = start.chosen
    # The method whose poses give the crispest raw map over the query draws, of those the run trusts (not a bent
    # baseline)
    refused = {} if not start.bent else {"baseline": f"its trajectory departs {start.departure_m:.2f} m from the "
                                                     "input's (train.max_baseline_departure)"}
    summary["crispest"] = quality.warn_if_not_crispest(crisp, refused, margins)
    summary["crispness_margin"] = margins  # {other method: NeLD-BA's entropy minus its, per draw and mean}
    if start.baseline_seconds is not None:
        summary["baseline_seconds"] = round(start.baseline_seconds, 2)
        summary["baseline_departure_m"] = round(start.departure_m, 3)
        summary["baseline_refined_from"] = start.refined_from  # "graph" | "chain" | "input" (refinement_start), or None
        summary["baseline_rounds_done"] = start.rounds_done  # fewer than baseline.map_rounds: baseline_deadline
    scans_summary = report.summarize(rows)
    export.write_json(os.path.join(out_dir, "metrics.json"), {"run": summary, "scans_report": scans_summary})
    summary["scans_report"] = scans_summary
    summary["crispness"] = quality.record_crispness(out_dir, crisp)
    with open(os.path.join(out_dir, "history.json"), "w") as f:
        json.dump(result.history, f)
    if seq.gt_poses is not None or seq.gt_map is not None:
        from neld_jax.evaluate import evaluate_run

        summary["evaluation"] = evaluate_run(out_dir, threshold=config.eval.f1_threshold_m,
                                             raw_cutoff=config.eval.raw_cutoff_m,
                                             map_icp_m=config.eval.get("map_icp_m", 0.0))
    return summary


def _write_rendered_map(config, state, norm, seq, T_field_n, G_n, out_dir, progress, max_seconds: float):
    """Render the map with the poses in the field's frame (T_field_n), then move it by the anchor transform G_n,
    in at most max_seconds (0: no limit; rendering_seconds).

    Returns (the mapping rays, their MapRender) for the per-scan residuals."""
    m = config.mapping
    mapping_rays = build_mapping_rays(config, seq, norm)
    sampler = train.sampler_settings(config, norm.scale, m.num_coarse, m.num_fine)
    # The map is rendered with the paper's sampler (no measured ranges), whatever the training options.
    sampler = dataclasses.replace(sampler, guided_samples=0)
    alpha = float(train.make_schedules(config).alpha(int(state.step)))  # the window the field was trained with
    rendered = render_map(state.params["field"], train.make_field(config), sampler, T_field_n,
                          mapping_rays.directions, mapping_rays.scan_index, alpha, rays_per_batch=int(m.rays_per_batch),
                          min_opacity=float(m.min_opacity), progress=progress, max_seconds=max_seconds,
                          seed=config.seed + 1)
    points_n = rendered.points
    mapping.log_rendered_rays(len(points_n), rendered.num_rendered, mapping_rays.num_rays, max_seconds)
    if len(points_n) == 0:
        logger.warning("rendered map is empty: no ray reached opacity %.2f (train longer or lower "
                       "mapping.min_opacity); map_rendered.ply not written", m.min_opacity)
    else:
        points = norm.points_to_world(transform_points(points_n, G_n))
        export.write_point_cloud(os.path.join(out_dir, "map_rendered.ply"), voxel_downsample(points, float(m.voxel_size_m)))
    return mapping_rays, rendered
