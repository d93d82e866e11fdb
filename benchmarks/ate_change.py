#!/usr/bin/env python
"""Why a refinement's ATE against a pseudo ground truth moves: split the change of ATE between the classical
baseline's poses and NeLD-BA's (which starts from them) into what correlates with the baseline's error and what
does not.

    python benchmarks/ate_change.py --runs=/tmp/real/HKU_2_bag/drift,/tmp/real/HKU_MB_..._bag/drift \\
        --out=benchmarks/results/ate_change.json

Each run folder holds poses_gt.txt, poses_baseline.txt and poses_optimized.txt (TUM; a run of bin/train.py with
ground truth and train.init_poses=baseline or crisper, such as benchmarks/real_data.py's drift runs, whose
ground truth is the recorded odometry). With e_i the baseline's position error after its SE(3) alignment to the
ground truth and d_i NeLD-BA's move (its positions rigidly aligned onto the baseline's, so that a motion of the
whole trajectory does not count, then put through the baseline's alignment):

    ATE_optimized^2 <= mean |e_i + d_i|^2 = ATE_baseline^2 + 2 mean(e_i . d_i) + mean |d_i|^2

(re-aligning can only lower it). A move uncorrelated with e (correlation near 0, the chance level being about
1 / sqrt(3 N)) still raises the ATE by about mean |d|^2 / (2 ATE_baseline): a refinement that does not move
toward the pseudo ground truth's own shape comes out slightly worse against it, at second order.
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def ate_change_terms(T_baseline: np.ndarray, T_optimized: np.ndarray, T_gt: np.ndarray) -> dict:
    """The terms of the ATE change from T_baseline to T_optimized against T_gt (all [N, 4, 4], matched by
    index), in millimetres (mm^2 for the squared terms); see the module docstring."""
    from neld_jax.metrics import ate, ate_errors

    to_gt = ate_errors(T_baseline, T_gt, "se3")[2]  # [4, 4]: the baseline's frame -> the ground truth's
    onto_baseline = ate_errors(T_optimized, T_baseline, "se3")[2]
    p_baseline = T_baseline[:, :3, 3] @ to_gt[:3, :3].T + to_gt[:3, 3]
    p_moved = T_optimized[:, :3, 3] @ onto_baseline[:3, :3].T + onto_baseline[:3, 3]
    p_optimized = p_moved @ to_gt[:3, :3].T + to_gt[:3, 3]
    e, d = p_baseline - T_gt[:, :3, 3], p_optimized - p_baseline
    ate_b = ate(T_baseline, T_gt)["translation_rmse_m"]
    ate_o = ate(T_optimized, T_gt)["translation_rmse_m"]
    cross, square = 2.0 * np.mean(np.sum(e * d, axis=1)), np.mean(np.sum(d * d, axis=1))
    mm = 1e3
    return {
        "num_poses": int(len(T_gt)),
        "ate_baseline_mm": ate_b * mm,
        "ate_optimized_mm": ate_o * mm,
        "change_mm": (ate_o - ate_b) * mm,
        "move_rms_mm": float(np.sqrt(square)) * mm,  # NeLD-BA's move after rigid alignment onto the baseline
        "cross_term_mm2": float(cross) * mm**2,
        "square_term_mm2": float(square) * mm**2,
        "bound_change_mm": float(np.sqrt(ate_b**2 + cross + square) - ate_b) * mm,
        "uncorrelated_change_mm": float(np.sqrt(ate_b**2 + square) - ate_b) * mm,  # what the square term alone gives
        "correlation": float(np.sum(e * d) / max(np.sqrt(np.sum(e * e) * np.sum(d * d)), 1e-300)),
        "chance_correlation": float(1.0 / np.sqrt(e.size)),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", required=True, type=lambda text: text.split(","),
                        help="Run output folders, comma-separated (poses_gt.txt, poses_baseline.txt, "
                             "poses_optimized.txt in each).")
    parser.add_argument("--out", default="", help="JSON file (default: print only).")
    args = parser.parse_args()
    from neld_jax.data.poses import read_tum

    results = {}
    for run in args.runs:
        poses = {name: read_tum(os.path.join(run, f"poses_{name}.txt"))[1] for name in ("gt", "baseline", "optimized")}
        name = os.path.join(*os.path.normpath(run).split(os.sep)[-2:])  # <sequence>/drift for real_data.py's runs
        results[name] = ate_change_terms(poses["baseline"], poses["optimized"], poses["gt"])
    text = json.dumps(results, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
