"""The run's answer (poses_optimized, map_raw.ply): NeLD-BA's poses, unless they made the keyframes' raw map
blurrier than the poses training started from on every query draw of the crispness margins; then the start's poses
are the answer and NeLD-BA's are written beside them as poses_neld_ba (docs/evaluation.md, "The answer"). A run's
answer is never worse than its start by the one measure a run without ground truth has; a tie (draws disagreeing)
keeps NeLD-BA's, and so does a run whose clock fitted fewer than two draws (no margin to judge by).

Before that verdict, the trajectory: where the poses of every input scan change the distance travelled over a
window by more than a LiDAR odometry drifts (ODOMETRY_DRIFT over TRAVEL_WINDOW_M), they take the input's distances
there unless their own give every scan's raw map a crisper map on every query draw (keep_input_travel). A map of
keyframes far apart can prefer a shortened path that the sweeps between them contradict.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.preprocess import voxel_downsample
from neld_jax.judging import judge
from neld_jax.judging.metrics import path_length_ratio
from neld_jax.trajectory import window_scales

logger = logging.getLogger(__name__)

REFINED = "optimized"  # the answer's name in metrics.json and the poses files
NELD_BA = "neld_ba"  # NeLD-BA's poses under their own name when the start is the answer
START_METHOD = {"input": "initial", "baseline": "baseline"}  # Start.chosen -> its method in the crispness tables
# How far a window's distance travelled may depart from the input's before every scan's map must say why: a LiDAR
# odometry's own distance error over such a window (KISS-ICP on KITTI 00 frames 15-100: 0.47 % of the path short;
# its published relative error on KITTI, 0.5-1 %), so that a run does not move the input's distances by less than
# what the input itself may be off.
ODOMETRY_DRIFT = 0.01
TRAVEL_WINDOW_M = 50.0
# Every scan's points on a grid of this fraction of the crispness radius for the judgement of the travel: a map of
# thousands of sweeps in memory at once, and the entropy still of surfaces thinner than the radius.
TRAVEL_GRID_OF_RADIUS = 1 / 3


def keep_input_travel(scans, poses: np.ndarray, input_poses: np.ndarray, eval_cfg) -> tuple[np.ndarray, dict]:
    """The poses of every input scan [S, 4, 4] with the input's [S, 4, 4] distances travelled over the windows where
    theirs depart from the input's by more than ODOMETRY_DRIFT, unless their own give every scan's raw map (scans: S
    arrays [N_i, 3], sensor frame, read one at a time) a crisper map on every one of eval_cfg's query draws.
    Returns (poses [S, 4, 4], record): record {"largest_window_change", "steps_beyond" (the fraction of steps whose
    window departs beyond ODOMETRY_DRIFT), "kept": "own" | "input" | None (None: nothing beyond), "margin" (own minus
    the input's distances, mean entropy; None unless judged), "path_ratio" (what is returned over the input)}."""
    record = {"window_m": TRAVEL_WINDOW_M, "drift": ODOMETRY_DRIFT, "kept": None, "margin": None}
    if len(poses) < 2:
        return poses, {**record, "largest_window_change": 0.0, "steps_beyond": 0.0, "path_ratio": None}
    change = np.abs(window_scales(poses, input_poses, TRAVEL_WINDOW_M) - 1.0)
    record.update(
        largest_window_change=round(float(change.max()), 6),
        steps_beyond=round(float(np.mean(change > ODOMETRY_DRIFT)), 4),
    )
    kept = poses
    if change.max() > ODOMETRY_DRIFT:
        gridded = _on_travel_grid(scans, float(eval_cfg["crispness_radius_m"]))
        kept, own_crisper, margin = judge.distances_judged(
            gridded, poses, input_poses, TRAVEL_WINDOW_M, eval_cfg, beyond=ODOMETRY_DRIFT
        )
        record.update(kept="own" if own_crisper else "input", margin=None if margin is None else margin["mean"])
        logger.log(
            logging.INFO if own_crisper else logging.WARNING,
            "the answer changes the distance travelled by up to %.2f%% over %g m windows (%.1f%% of its steps "
            "beyond the %.0f%% an odometry drifts): %s",
            100 * change.max(),
            TRAVEL_WINDOW_M,
            100 * record["steps_beyond"],
            100 * ODOMETRY_DRIFT,
            "its own distances give every scan's map the crisper map on every draw: kept"
            if own_crisper
            else "the input's distances are kept there (its own gave every scan's map no crisper map on every draw"
            + ("" if margin is None else f": {margin['mean']:+.5f} nats")
            + ")",
        )
    ratio = path_length_ratio(kept, input_poses)
    record["path_ratio"] = round(ratio, 6) if np.isfinite(ratio) else None
    return kept, record


def _on_travel_grid(scans, radius_m: float) -> list[np.ndarray]:
    """Every scan (S arrays [N_i, 3], read one at a time) on a grid of TRAVEL_GRID_OF_RADIUS of the crispness radius."""
    return [voxel_downsample(np.asarray(scan, np.float64), TRAVEL_GRID_OF_RADIUS * radius_m) for scan in scans]


def keep_travel_of_input(made, eval_cfg) -> object:
    """made (outputs.RunSteps) with the answer's poses of every input scan checked by keep_input_travel against the
    input's (made.every_scan set where the input's distances were kept; the keyframes' poses follow), and the
    record in made.travelled."""
    every_scan = made.every_scan_poses()
    kept, record = keep_input_travel(made.loaded.scans, every_scan, made.loaded.poses, eval_cfg)
    if record["kept"] != "input":
        return dataclasses.replace(made, travelled=record)
    refined = dataclasses.replace(made.refined, poses=kept[made.keyframes.loaded_index])
    return dataclasses.replace(made, refined=refined, every_scan=kept, travelled=record)


def blurred_the_start(margins: dict, chosen: str) -> bool:
    """Whether NeLD-BA's keyframe map is blurrier than the start's (`chosen`: "input" | "baseline") on every query
    draw: margins is crispness_margins' answer for the refined poses ({other: refined minus other, per draw})."""
    margin = margins.get(START_METHOD[chosen])
    return margin is not None and margin["all_draws_agree"] and margin["mean"] > 0


def start_as_answer(judged: tuple, chosen: str) -> tuple:
    """The crispness verdict (crisp {method: summary}, per-keyframe entropy {method: [K]}, margins) with the start's
    poses as the refined answer: the start's figures under REFINED, NeLD-BA's under NELD_BA, and the margins taken
    against the start (against itself: zero on every draw, a tie)."""
    crisp, per_scan, margins = judged
    start = START_METHOD[chosen]
    crisp = {**crisp, REFINED: crisp[start], NELD_BA: crisp[REFINED]}
    per_scan = {**per_scan, REFINED: per_scan[start], NELD_BA: per_scan[REFINED]}
    moved = judge.margins_against(margins, REFINED, start)
    moved[NELD_BA] = moved.pop(REFINED)
    moved[start] = judge.margin_over_draws(np.zeros(len(moved[NELD_BA]["per_draw"])))
    return crisp, per_scan, moved


def keep_the_better(made, judged: tuple) -> tuple:
    """(made, judged) with the start's poses as the answer where NeLD-BA's blurred the start (blurred_the_start),
    else as they are. made: outputs.RunSteps; judged: outputs.judge_crispness' answer for it. Kept, the refined
    keyframe poses become the start's, the scans between keyframes keep the start's interpolated correction (their
    registration was to the map that lost), and NeLD-BA's poses of every input scan go to made.neld_ba."""
    margins = judged[2]
    chosen = made.start.chosen
    if not blurred_the_start(margins, chosen):
        return made, judged
    margin = margins[START_METHOD[chosen]]
    logger.warning(
        "NeLD-BA's poses made the keyframes' raw map blurrier than the %s poses training started from, on "
        "every one of %d query draws (by %.5f nats of mean map entropy): the answer (poses_optimized, "
        "map_raw.ply) is the start's poses; NeLD-BA's are in poses_%s",
        chosen,
        len(margin["per_draw"]),
        margin["mean"],
        NELD_BA,
    )
    kept = dataclasses.replace(
        made,
        refined=dataclasses.replace(made.refined, poses=made.start.poses),
        registration=None,
        every_scan=None,
        neld_ba=made.every_scan_poses(),
    )
    return kept, start_as_answer(judged, chosen)
