#!/usr/bin/env python
"""Why a refinement's ATE against a pseudo ground truth moves: split the change of ATE between the classical
baseline's poses and NeLD-BA's (which starts from them) into what correlates with the baseline's error and what
does not.

    python benchmarks/ate_change.py --runs=/tmp/real/HKU_2_bag/drift,/tmp/real/HKU_MB_..._bag/drift \\
        --out=/tmp/ate_change.json

Each run folder holds poses_gt.txt, poses_baseline.txt and poses_optimized.txt (TUM; a run of bin/train.py with
ground truth and start.poses=baseline or crisper, such as benchmarks/real_data.py's drift runs, whose
ground truth is the recorded odometry). With e_i the baseline's position error after its SE(3) alignment to the
ground truth and d_i NeLD-BA's move (its positions rigidly aligned onto the baseline's, so that a motion of the
whole trajectory does not count, then put through the baseline's alignment):

    ATE_optimized^2 <= mean |e_i + d_i|^2 = ATE_baseline^2 + 2 mean(e_i . d_i) + mean |d_i|^2

(re-aligning can only lower it). A move uncorrelated with e (correlation near 0) still raises the ATE by about
mean |d|^2 / (2 ATE_baseline): a refinement that does not move toward the pseudo ground truth's own shape comes out
slightly worse against it, at second order.

Whether a correlation is more than chance: e and d are smooth along the trajectory (drift is a random walk), so they
have far fewer independent values than 3 N; 1 / sqrt(3 N) understates the chance level, and two independent random
walks often correlate at +-0.5. The null here keeps both signals whole and turns e by uniformly random rotations
(e_i -> R e_i for every i): it asks whether d points along e's directions, not only whether both are smooth.
`correlation_rotation_sd` is its spread, `correlation_rotation_p` the share of rotations whose correlation is at
least as large in magnitude (on 200 pairs of independent random walks, 6.5 % of its p values fell below 0.05, and
9.5 % after the alignments the ATE makes: read p < 0.05 as a hint, not proof). With the input's poses too
(poses_initial.txt), the same for the move against the input's departure from the ground truth
(`toward_input_correlation`): a refinement pulled back toward its start would show there.
"""

import json
import os

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import numpy as np
from absl import app, flags


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Uncentred correlation of two [N, 3] vector fields (a move and an error have no mean to remove)."""
    return float(np.sum(a * b) / max(np.sqrt(np.sum(a * a) * np.sum(b * b)), 1e-300))


def rotation_null(d: np.ndarray, x: np.ndarray, draws: int = 4000, seed: int = 0) -> tuple[float, float, float]:
    """(correlation of d and x, spread of the random-rotation null, share of rotations at least as correlated in
    magnitude); d, x: [N, 3] along the trajectory (module docstring)."""
    from scipy.spatial.transform import Rotation

    observed = _correlation(d, x)
    pairing = x.T @ d  # [3, 3]: sum_i x_i d_i^T, so that sum_i d_i . (R x_i) = trace(R pairing)
    rotations = Rotation.random(draws, random_state=seed).as_matrix()  # [draws, 3, 3]
    scale = max(np.sqrt(np.sum(d * d) * np.sum(x * x)), 1e-300)
    null = np.einsum("kab,ba->k", rotations, pairing) / scale
    return observed, float(null.std()), float(np.mean(np.abs(null) >= abs(observed)))


def _onto(T: np.ndarray, T_reference: np.ndarray) -> np.ndarray:
    """T's positions [N, 3] rigidly aligned onto T_reference's."""
    from neld_jax.judging.metrics import ate_errors

    A = ate_errors(T, T_reference, "se3")[2]
    return T[:, :3, 3] @ A[:3, :3].T + A[:3, 3]


def ate_change_terms(
    T_baseline: np.ndarray, T_optimized: np.ndarray, T_gt: np.ndarray, T_input: np.ndarray | None = None
) -> dict:
    """The terms of the ATE change from T_baseline to T_optimized against T_gt (all [N, 4, 4], matched by
    index), in millimetres (mm^2 for the squared terms); with T_input (the poses both started from), also how
    the move correlates with the input's departure from T_gt. See the module docstring."""
    from neld_jax.judging.metrics import ate, ate_errors

    to_gt = ate_errors(T_baseline, T_gt, "se3")[2]  # [4, 4]: the baseline's frame -> the ground truth's
    p_baseline = T_baseline[:, :3, 3] @ to_gt[:3, :3].T + to_gt[:3, 3]
    p_optimized = _onto(T_optimized, T_baseline) @ to_gt[:3, :3].T + to_gt[:3, 3]
    e, d = p_baseline - T_gt[:, :3, 3], p_optimized - p_baseline
    ate_b = ate(T_baseline, T_gt)["translation_rmse_m"]
    ate_o = ate(T_optimized, T_gt)["translation_rmse_m"]
    cross, square = 2.0 * np.mean(np.sum(e * d, axis=1)), np.mean(np.sum(d * d, axis=1))
    mm = 1e3
    correlation, null_sd, null_p = rotation_null(d, e)
    terms = {
        "num_poses": int(len(T_gt)),
        "ate_baseline_mm": ate_b * mm,
        "ate_optimized_mm": ate_o * mm,
        "change_mm": (ate_o - ate_b) * mm,
        "move_rms_mm": float(np.sqrt(square)) * mm,  # NeLD-BA's move after rigid alignment onto the baseline
        "cross_term_mm2": float(cross) * mm**2,
        "square_term_mm2": float(square) * mm**2,
        "bound_change_mm": float(np.sqrt(ate_b**2 + cross + square) - ate_b) * mm,
        "uncorrelated_change_mm": float(np.sqrt(ate_b**2 + square) - ate_b) * mm,  # what the square term alone gives
        "correlation": correlation,
        "chance_correlation": float(1.0 / np.sqrt(e.size)),  # for independent values; see correlation_rotation_sd
        "correlation_rotation_sd": null_sd,
        "correlation_rotation_p": null_p,
    }
    if T_input is not None:
        departure = _onto(T_input, T_baseline) @ to_gt[:3, :3].T + to_gt[:3, 3] - T_gt[:, :3, 3]
        terms["toward_input_correlation"], terms["toward_input_rotation_sd"], terms["toward_input_rotation_p"] = (
            rotation_null(d, departure)
        )
    return terms


def main(argv):
    del argv
    from neld_jax.data.poses import read_tum

    results = {}
    for run in RUNS.value:
        poses = {name: read_tum(os.path.join(run, f"poses_{name}.txt"))[1] for name in ("gt", "baseline", "optimized")}
        initial = os.path.join(run, "poses_initial.txt")
        T_input = read_tum(initial)[1] if os.path.exists(initial) else None
        name = os.path.join(*os.path.normpath(run).split(os.sep)[-2:])  # <sequence>/drift for real_data.py's runs
        results[name] = ate_change_terms(poses["baseline"], poses["optimized"], poses["gt"], T_input)
    print(json.dumps(results, indent=1))
    harness.write(harness.OUT.value, results)


if __name__ == "__main__":  # the flag defined here: tests import the module's functions, more than once
    RUNS = flags.DEFINE_list(
        "runs",
        None,
        "Run output folders, comma-separated (poses_gt.txt, poses_baseline.txt, "
        "poses_optimized.txt in each; poses_initial.txt where present).",
    )
    flags.mark_flag_as_required("runs")
    app.run(main)
