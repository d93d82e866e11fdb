#!/usr/bin/env python
"""Accuracy of the bundle adjustment against the classical baseline on seeded synthetic sequences.

    python benchmarks/accuracy.py                         # easy and hard drift, the demo (cpu) budget
    python benchmarks/accuracy.py --sequences=hard --budget=paper --output_root=runs/acc
    python benchmarks/accuracy.py --sequences=hard --start=baseline   # NeLD-BA refines the baseline's poses

For each sequence: NeLD-BA (neld_jax.run) and the classical baseline (neld_jax.baseline) on the same
preprocessed scans, evaluated together; prints one JSON line per sequence with initial / baseline / optimised
ATE and map metrics and the wall time of each method, and writes the list of them to --out (benchmarks/harness.py).
"""

import json
import logging
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# name -> synthetic overrides. "easy" is the demo's sequence; "hard" doubles the odometry drift on another scene.
SEQUENCES = {
    "easy": {"seed": 0, "drift_trans_m": 0.05, "drift_rot_deg": 0.5},
    "hard": {"seed": 1, "drift_trans_m": 0.10, "drift_rot_deg": 1.0},
}

SEQ = flags.DEFINE_list("sequences", list(SEQUENCES), f"Which of {list(SEQUENCES)} to run.")
BUDGET = flags.DEFINE_string("budget", "cpu", "Config budget (cpu, gpu or paper).")
OUTPUT_ROOT = flags.DEFINE_string("output_root", "outputs/accuracy", "One output_dir per sequence below this.")
STEPS = flags.DEFINE_integer("steps", 0, "Override train.steps (0: the budget's).")
OVERRIDES = harness.overrides_flag("train.pose_lr_rot_init=1e-4")
START = flags.DEFINE_enum(
    "start",
    "input",
    ["input", "baseline", "crisper"],
    "start.poses: start NeLD-BA from the drifted odometry, the baseline's poses or the crisper.",
)


def _summary(evaluation: dict, method: str) -> dict:
    m = evaluation["methods"].get(method, {})
    out = {}
    if "ate" in m:
        out["ate_rmse_m"] = m["ate"]["translation_rmse_m"]
        out["rot_rmse_deg"] = m["ate"]["rotation_rmse_deg"]
    for kind in ("raw_map", "rendered_map"):
        if kind in m:
            out[f"{kind}_chamfer_l1_m"] = m[kind]["chamfer_l1_m"]
            out[f"{kind}_f1"] = m[kind]["f1"]
    return out


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING)
    from neld_jax.commands.baseline import run_baseline
    from neld_jax.config import apply_overrides, from_file
    from neld_jax.run import run
    from neld_jax.writing.evaluate import evaluate_run

    entries = []
    for name in SEQ.value:
        config = from_file(os.path.join(REPO, "configs", "demo.py"), BUDGET.value)
        config.data.synthetic.update(SEQUENCES[name])
        config.output_dir = os.path.join(OUTPUT_ROOT.value, f"{name}_{BUDGET.value}_{START.value}")
        config.start.poses = START.value
        # The rendered map is scored against the ground truth (F1, Chamfer): every ray, whatever the render takes.
        config.mapping.max_seconds = 0.0
        if STEPS.value:
            config.train.steps = STEPS.value
        apply_overrides(config, OVERRIDES.value)
        t0 = time.perf_counter()
        summary = run(config, progress=False)
        t_neld = time.perf_counter() - t0
        if "baseline_seconds" in summary["run"]:  # run() registered the baseline already and wrote its poses
            t_base = summary["run"]["baseline_seconds"]
        else:
            t0 = time.perf_counter()
            run_baseline(config, progress=False)
            t_base = time.perf_counter() - t0
        evaluation = evaluate_run(config.output_dir)
        entries.append(
            {
                "sequence": name,
                "budget": BUDGET.value,
                "start": START.value,
                "synthetic": SEQUENCES[name],
                "started_from": summary["run"]["started_from"],
                "steps": summary["run"]["steps"],
                "overrides": OVERRIDES.value,
                "initial": _summary(evaluation, "initial"),
                "baseline": dict(_summary(evaluation, "baseline"), wall_s=round(t_base, 1)),
                "neld_ba": dict(
                    _summary(evaluation, "optimized"), wall_s=round(t_neld, 1), train_s=summary["run"]["train_seconds"]
                ),
                "device": summary["run"]["device"],
            }
        )
        print(json.dumps(entries[-1]), flush=True)
        harness.write(harness.OUT.value, entries)


if __name__ == "__main__":
    reexec_with_huge_page_malloc()  # ~25% faster CPU steps: see neld_jax/hugepages.py
    app.run(main)
