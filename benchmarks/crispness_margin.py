#!/usr/bin/env python
"""How sure is a run's crispness verdict? The raw map's mean map entropy under a run's poses, over several draws
of the query points, and the paired differences between the run's methods.

    python benchmarks/crispness_margin.py --run_dir=runs/hku1 --out=/tmp/hku1_margin.json
    python benchmarks/crispness_margin.py --run_dir=runs/hku1 --root=/data/HKU_1_bag --draws=10

A run judges itself on one draw of 10,000 query points (eval.crispness_queries, seed 0). The draw alone moves a
sequence's entropy by about 0.01 nats; the methods are measured on the same points, so most of that cancels in
their difference, but not all. Every run also writes the margin over eval.crispness_draws
(5) draws to metrics.json (run.crispness_margin, neld_jax.judging.judge.crispness_margins); this script measures it
for a finished run, written before or with other draws. It reads the run's config.json (the sequence, its
preprocessing, eval.crispness_radius_m) and its poses_<method>.kitti (initial, baseline when present, optimized),
measures the entropy of the keyframes' raw map under each on --draws draws (seeds 0, 1, ...; draw 0 is the run's
own) and prints, for optimized against each other method, the paired difference (optimized minus other;
negative: NeLD-BA's map is crisper) on every draw, its mean and spread, and whether every draw agrees in sign.
--root replaces the run's data.root (a sequence moved since the run). --mean_of=<run>,<run>... judges, as the
optimized poses, the mean on se(3) of this run's and those runs' corrections from this run's initial poses (other
training seeds from the same start: what the seeds agree on, each seed's own part shrunk; a run that started
elsewhere is refused with one line). Writes one JSON object to --out.

    python benchmarks/crispness_margin.py --run_dir=runs/seed0 --mean_of=runs/seed1,runs/seed2
"""

import json
import os

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

RUN_DIR = flags.DEFINE_string("run_dir", None, "Output folder of a bin/train.py run (config.json, poses_*.kitti).")
ROOT = flags.DEFINE_string("root", "", "The sequence's folder, if it is not the run's data.root any more.")
DRAWS = flags.DEFINE_integer("draws", 5, "Draws of the query points (seeds 0 .. draws-1).")
QUERIES = flags.DEFINE_integer("queries", 0, "Query points a draw (0: the run's eval.crispness_queries).")
MEAN_OF = flags.DEFINE_list(
    "mean_of",
    [],
    "Other run folders from the same start (other training seeds): the answer "
    "judged is the mean, on se(3), of this run's and their corrections from this run's initial "
    "poses (`mean_of_corrections`).",
)
flags.mark_flag_as_required("run_dir")

METHODS = ("initial", "baseline", "optimized")


def mean_of_corrections(T_start, answers):
    """The poses [S, 4, 4] T_start Exp(mean_n Log(T_start^-1 T_n)): the mean of N answers' right corrections from
    one start, on se(3) (N training seeds' refined poses from the same start: their mean keeps what the seeds agree
    on and shrinks what each seed adds on its own). T_start: [S, 4, 4]; answers: [N, S, 4, 4] (N >= 1)."""
    import numpy as np

    from neld_jax.lie import se3_exp_float64, se3_log_float64

    T_start = np.asarray(T_start, np.float64)
    answers = np.asarray(answers, np.float64)
    if answers.ndim != 4 or answers.shape[1:] != T_start.shape or len(answers) == 0:
        raise ValueError(f"answers of shape {answers.shape} for start poses of shape {T_start.shape}")
    xi = se3_log_float64(np.linalg.inv(T_start)[None] @ answers)  # [N, S, 6]
    return T_start @ se3_exp_float64(xi.mean(axis=0))


def _run_poses(folder: str, loaded_index) -> dict:
    """{method: [S, 4, 4]} of the poses_<method>.kitti a run folder holds (the keyframes the sequence loads);
    one line naming the folder when it holds no answer."""
    from neld_jax.data.poses import read_kitti

    poses = {
        method: read_kitti(path)[loaded_index]
        for method in METHODS
        if os.path.exists(path := os.path.join(folder, f"poses_{method}.kitti"))
    }
    if "optimized" not in poses:
        raise SystemExit(f"{folder}: no poses_optimized.kitti (is it a bin/train.py run's folder?)")
    return poses


def _check_same_start(folder: str, initial, own_initial, tol: float = 1e-6) -> None:
    """One line naming the folder when a --mean_of run did not start from this run's initial poses ([S, 4, 4]
    each, or None when it wrote none): corrections from different starts have no common origin to average."""
    import numpy as np

    if initial is None:
        raise SystemExit(
            f"{folder}: no poses_initial.kitti, so --mean_of cannot check it started where {RUN_DIR.value} did"
        )
    gap = float(np.abs(initial - own_initial).max())
    if gap > tol:
        raise SystemExit(
            f"{folder}: its poses_initial.kitti differ from {RUN_DIR.value}'s by up to {gap:.3g} "
            "(matrix elements; metres in the translations): --mean_of averages runs from one start"
        )


def main(argv):
    del argv
    import ml_collections
    import numpy as np

    from neld_jax.judging import crispness, judge
    from neld_jax.steps.inputs import load_keyframes

    with open(os.path.join(RUN_DIR.value, "config.json")) as f:
        config = ml_collections.ConfigDict(json.load(f))
    if ROOT.value:
        config.data.root = ROOT.value
    config.eval.crispness_draws = DRAWS.value
    if QUERIES.value:
        config.eval.crispness_queries = QUERIES.value
    _, seq = load_keyframes(config.data)
    methods = _run_poses(RUN_DIR.value, seq.loaded_index)
    if MEAN_OF.value:
        if "initial" not in methods:
            raise SystemExit(f"{RUN_DIR.value}: no poses_initial.kitti, the start --mean_of averages from")
        answers = [methods["optimized"]]
        for other in MEAN_OF.value:
            poses = _run_poses(other, seq.loaded_index)
            _check_same_start(other, poses.get("initial"), methods["initial"])
            answers.append(poses["optimized"])
        methods["optimized"] = mean_of_corrections(methods["initial"], np.stack(answers))
    margins = judge.crispness_margins(seq, methods, config.eval)
    result = {
        "run_dir": RUN_DIR.value,
        "sequence": config.data.root,
        "draws": DRAWS.value,
        "queries": int(config.eval.get("crispness_queries", crispness.DEFAULT_MAX_QUERIES)),
        "radius_m": float(config.eval.get("crispness_radius_m", crispness.DEFAULT_RADIUS_M)),
        "mean_of": MEAN_OF.value,
        "optimized_minus": margins,
    }
    for other, margin in margins.items():
        print(judge.describe_margin(other, margin) + ": " + " ".join(f"{d:+.5f}" for d in margin["per_draw"]))
    harness.write(harness.OUT.value, result)


if __name__ == "__main__":
    app.run(main)
