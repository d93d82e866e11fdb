"""The run's answer (poses_optimized, map_raw.ply): NeLD-BA's poses, unless they made the keyframes' raw map
blurrier than the poses training started from on every query draw of the crispness margins; then the start's poses
are the answer and NeLD-BA's are written beside them as poses_neld_ba (docs/evaluation.md, "The answer"). A run's
answer is never worse than its start by the one measure a run without ground truth has; a tie (draws disagreeing)
keeps NeLD-BA's, and so does a run whose clock fitted fewer than two draws (no margin to judge by).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.judging import judge

logger = logging.getLogger(__name__)

REFINED = "optimized"  # the answer's name in metrics.json and the poses files
NELD_BA = "neld_ba"  # NeLD-BA's poses under their own name when the start is the answer
START_METHOD = {"input": "initial", "baseline": "baseline"}  # Start.chosen -> its method in the crispness tables


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
    logger.warning("NeLD-BA's poses made the keyframes' raw map blurrier than the %s poses training started from, on "
                   "every one of %d query draws (by %.5f nats of mean map entropy): the answer (poses_optimized, "
                   "map_raw.ply) is the start's poses; NeLD-BA's are in poses_%s", chosen, len(margin["per_draw"]),
                   margin["mean"], NELD_BA)
    kept = dataclasses.replace(made, refined=dataclasses.replace(made.refined, poses=made.start.poses),
                               registration=None, neld_ba=made.every_scan_poses())
    return kept, start_as_answer(judged, chosen)
