#!/usr/bin/env python
"""NeLD-BA on real recordings, judged without ground truth: keyframe scans + FAST-LIO2 odometry in, a crisper
map out. Reads sequences in the lio_keyframes layout (Scans/, odom_poses.txt, times.txt) from a path; nothing is
downloaded or committed.

    python benchmarks/real_data.py --root=/data/Fast-LIO2_SC-SLAM/output --keep_tilt --work=/tmp/real \\
        --sequences=HKU_1_bag,HKU_2_bag,2020-09-16-quick-shack_bag,HKU_MB_2020-09-20-13-34-51_bag \\
        --out=benchmarks/results/real_data_cpu_handheld.json   # benchmarks/RESULTS.md, the cpu budget's tables

Per sequence (one JSON object each, also printed as a line):
- "recorded": from the recorded odometry, one NeLD-BA run per start in --recorded_starts (start.poses:
  "crisper", the config's own, by default; "input" and "baseline" to compare); the classical baseline is Open3D
  scan-to-map ICP + a loop-closed pose graph + multi-view refinement (neld_jax.baseline); the raw map's crispness
  (mean map entropy, plane thickness) under the odometry, the baseline and each NeLD-BA run, which start each run
  took, and whether the baseline kept the input's tilt (it decides that from the scans).
- "drift" (unless --skip_drift): the same scans with odometry-like drift added (bin/perturb.py's random walk,
  --drift_trans_m / --drift_rot_deg per keyframe, --seed; --keep_tilt: position and heading only, as an IMU-aided
  odometry drifts), the recorded odometry as pseudo ground truth, run with the first of --recorded_starts: ATE of
  the baseline and of NeLD-BA against the odometry, the crispness of each map, how far the baseline departs from
  the drifted input, and how far the baseline's and NeLD-BA's answers lie from the same configuration's answers
  from the recorded odometry (ATE between the two, SE(3)-aligned), and the split of NeLD-BA's ATE change from the
  baseline's (benchmarks/ate_change.py: its move off the baseline and how it correlates with the baseline's error).
  --drift_recipe=generic runs it with configs/generic.py instead, as a user's own data is run: keyframes by the caps
  (HKU_2's drifted copy: 50 of 266), every other scan registered to the result.
- "every_scan_map" in each: the raw map of EVERY input scan, not only the keyframes trained on, under the input's,
  the baseline's and NeLD-BA's poses of every scan, and NeLD-BA's margins (neld_jax.judging.judge.every_scan_crispness).
- "targets": the targets for real recordings read off the two (benchmarks/real_targets.py): the recorded run within
  --minutes_limit
  minutes end to end, one line per input scan in poses_optimized.txt, its map crisper than the odometry's and than
  the baseline's ("every draw", "a tie" or "blurrier" over the run's query draws); from drift, NeLD-BA's answer
  within 2 cm of its answer from the recorded odometry, its map at least as crisp as the recorded odometry's, and
  its ATE against the odometry at or below the baseline's. The run ends with one table of them.
A sequence that fails (for example one too large for one field) records its one-line error and the run goes on.
"""

import json
import logging
import os
import time
import traceback

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
import real_targets  # this folder's benchmarks/real_targets.py
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

ROOT = flags.DEFINE_string("root", None, "Folder holding one sub-folder per sequence (lio_keyframes layout).")
SEQUENCES = flags.DEFINE_list(
    "sequences", None, "Sub-folders of --root to run (default: every sub-folder with Scans/)."
)
WORK = flags.DEFINE_string("work", "outputs/real_data", "Output folders of the runs go below this.")
harness.default_out("outputs/real_data/real_data.json")  # --out: one entry per sequence
BUDGET = flags.DEFINE_string("budget", "cpu", "Config budget (cpu, gpu or paper).")
MAX_MINUTES = flags.DEFINE_float("max_minutes", -1.0, "Override max_minutes, the whole run's (-1: the budget's).")
RECORDED_STARTS = flags.DEFINE_list(
    "recorded_starts",
    ["crisper"],
    "Starts (start.poses) of the runs from the recorded odometry; the first is also the drift run's.",
)
SKIP_DRIFT = flags.DEFINE_bool("skip_drift", False, "Only the recorded-odometry runs.")
DRIFT_TRANS = flags.DEFINE_float("drift_trans_m", 0.05, "Injected drift per keyframe: translation sigma [m].")
DRIFT_ROT = flags.DEFINE_float("drift_rot_deg", 0.5, "Injected drift per keyframe: rotation sigma [deg].")
SEED = flags.DEFINE_integer("seed", 0, "Seed of the injected drift.")
KEEP_TILT = flags.DEFINE_bool(
    "keep_tilt",
    False,
    "The drift of an IMU-aided odometry: position and heading only "
    "(bin/perturb.py --keep_tilt); without it the drift turns all three axes.",
)
OVERRIDES = harness.overrides_flag()
DRIFT_RECIPE = flags.DEFINE_enum(
    "drift_recipe",
    "lio_keyframes",
    ["lio_keyframes", "generic"],
    "The drift run's config: lio_keyframes (every scan a keyframe) or generic (the "
    "own-data recipe: keyframes by the caps, the other scans registered to the result).",
)
MINUTES_LIMIT = flags.DEFINE_float(
    "minutes_limit", 10.0, "The end-to-end time target of a recorded run [min] (10 on the cpu budget's 2 cores)."
)
flags.mark_flag_as_required("root")


def _config(fmt_config: str, root: str, out_dir: str, recipe: str = "lio_keyframes"):
    """configs/<recipe>.py's settings at --budget with this script's overrides: lio_keyframes (every keyframe, the
    recording recipe), for the drifted copy in the generic layout too; or generic (the own-data recipe: keyframes by
    the caps, every other scan registered to the result)."""
    from neld_jax.config import apply_overrides, from_file

    c = from_file(os.path.join(REPO, "configs", f"{recipe}.py"), BUDGET.value)
    c.data.format = fmt_config
    c.data.root = root
    c.output_dir = out_dir
    if MAX_MINUTES.value >= 0:
        c.max_minutes = MAX_MINUTES.value
    return apply_overrides(c, OVERRIDES.value)


def _crisp(summary: dict) -> dict:
    return {
        name: {"entropy": round(s["mean_map_entropy"], 4), "thickness_cm": round(100 * s["mean_plane_thickness_m"], 3)}
        for name, s in summary.items()
        if s.get("mean_map_entropy") is not None
    }


def _ate(evaluation: dict, method: str):
    m = evaluation["methods"].get(method, {})
    return None if "ate" not in m else round(m["ate"]["translation_rmse_m"], 6)  # hundredths of a mm matter


def every_scan_map(config, run_dir: str) -> dict:
    """The raw map of EVERY input scan of a finished run (config: its config) under its poses of every input scan
    (poses_{initial,baseline,optimized}.txt, where written): {"crispness": {method: entropy, thickness},
    "margin": {other: NeLD-BA's paired margin over the query draws}} (neld_jax.judging.judge.every_scan_crispness)."""
    from neld_jax.data.poses import read_tum
    from neld_jax.errors import DataError
    from neld_jax.judging import judge
    from neld_jax.steps.inputs import load_sequence

    loaded = load_sequence(config.data)
    methods = {}
    for m in ("initial", "baseline", "optimized"):
        path = os.path.join(run_dir, f"poses_{m}.txt")
        if os.path.exists(path):
            methods[m] = read_tum(path)[1]
            if len(methods[m]) != loaded.num_scans:
                raise DataError(f"{path}: {len(methods[m])} poses for {loaded.num_scans} input scans")
    crisp, margins = judge.every_scan_crispness(loaded.scans, methods, config.eval, against="optimized")
    return {"crispness": _crisp(crisp), "margin": margins}


def run_sequence(name: str, root: str) -> dict:
    from neld_jax.data.poses import read_tum
    from neld_jax.judging.metrics import ate
    from neld_jax.run import run
    from neld_jax.steps.inputs import load_sequence
    from neld_jax.synthetic.generator import write_generic
    from neld_jax.synthetic.pseudo_gt import with_drift

    entry = {"sequence": name, "recorded": {}}
    out = os.path.join(WORK.value, name)
    recorded = _config("lio_keyframes", root, "")
    for start in RECORDED_STARTS.value:
        config = _config("lio_keyframes", root, os.path.join(out, f"recorded_{start}"))
        config.start.poses = start
        t0 = time.perf_counter()
        summary = run(config, progress=False)
        r = summary["run"]
        entry["recorded"][start] = {
            "scans": r["num_input_scans"],
            "keyframes": r["num_scans"],
            "steps": r["steps"],
            "schedule_steps": r["schedule_steps"],
            "wall_s": round(time.perf_counter() - t0, 1),
            "map_rays": r["map_rays"],
            "map_rays_rendered": r["map_rays_rendered"],
            "baseline_wall_s": r.get("baseline_seconds"),
            "started_from": r["started_from"],
            "baseline_tilt": r.get("baseline_tilt"),
            "baseline_refined_from": r.get("baseline_refined_from"),
            "baseline_rounds_done": r.get("baseline_rounds_done"),
            "baseline_departure_m": r.get("baseline_departure_m"),
            "crispness": _crisp(summary["crispness"]),
            "crispness_margin": r["crispness_margin"],
            "pose_lines": len(read_tum(os.path.join(out, f"recorded_{start}", "poses_optimized.txt"))[0]),
            "final_range_err_m": round(r["final"].get("range_err_m", float("nan")), 4),
            "final_range_residual_median_m": round(r["final"].get("range_residual_median_m", float("nan")), 4),
            "every_scan_map": every_scan_map(config, os.path.join(out, f"recorded_{start}")),
        }
        print(json.dumps(entry), flush=True)
    if SKIP_DRIFT.value:
        return entry

    drift_root = os.path.join(out, "drifted_input")
    seq = with_drift(load_sequence(recorded.data), DRIFT_TRANS.value, DRIFT_ROT.value, SEED.value, KEEP_TILT.value)
    write_generic(seq, drift_root)
    config = _config("generic", drift_root, os.path.join(out, "drift"), DRIFT_RECIPE.value)
    drift_start = RECORDED_STARTS.value[0]
    config.start.poses = drift_start
    t0 = time.perf_counter()
    summary = run(config, progress=False)
    t_neld = time.perf_counter() - t0
    evaluation, r = summary["evaluation"], summary["run"]
    entry["drift"] = {
        "drift_per_keyframe": {
            "trans_m": DRIFT_TRANS.value,
            "rot_deg": DRIFT_ROT.value,
            "seed": SEED.value,
            "keep_tilt": KEEP_TILT.value,
        },
        "ate_vs_odometry_m": {m: _ate(evaluation, m) for m in ("initial", "baseline", "optimized")},
        "crispness": _crisp(summary["crispness"]),
        "crispness_margin": r["crispness_margin"],
        "neld_wall_s": round(t_neld, 1),
        "baseline_wall_s": r.get("baseline_seconds"),
        "map_rays": r["map_rays"],
        "map_rays_rendered": r["map_rays_rendered"],
        "steps": r["steps"],
        "schedule_steps": r["schedule_steps"],
        "start": drift_start,
        "recipe": DRIFT_RECIPE.value,
        "scans": r["num_input_scans"],
        "keyframes": r["num_scans"],
        "started_from": r["started_from"],
        "baseline_tilt": r.get("baseline_tilt"),
        "baseline_refined_from": r.get("baseline_refined_from"),
        "baseline_rounds_done": r.get("baseline_rounds_done"),
        "baseline_departure_m": r.get("baseline_departure_m"),
        "every_scan_map": every_scan_map(config, os.path.join(out, "drift")),
    }

    def apart(method: str, recorded_run: str) -> float:
        _, T_rec = read_tum(os.path.join(out, recorded_run, f"poses_{method}.txt"))
        _, T_drift = read_tum(os.path.join(out, "drift", f"poses_{method}.txt"))
        return round(ate(T_drift, T_rec, align="se3")["translation_rmse_m"], 4)

    # The same configuration from the two starts (the baseline's answers exist whenever the baseline ran).
    if os.path.exists(os.path.join(out, f"recorded_{drift_start}", "poses_baseline.txt")):
        entry["drift"]["baseline_apart_from_recorded_m"] = apart("baseline", f"recorded_{drift_start}")
    entry["drift"]["optimized_apart_from_recorded_m"] = apart("optimized", f"recorded_{drift_start}")
    if "input" in RECORDED_STARTS.value and drift_start != "input":  # against NeLD-BA from the recorded odometry
        entry["drift"]["optimized_apart_from_recorded_input_m"] = apart("optimized", "recorded_input")
    if os.path.exists(os.path.join(out, "drift", "poses_baseline.txt")):
        # Why NeLD-BA's ATE against the odometry differs from the baseline's it started from (ate_change.py)
        from ate_change import ate_change_terms  # this folder's benchmarks/ate_change.py

        T = {
            m: read_tum(os.path.join(out, "drift", f"poses_{m}.txt"))[1]
            for m in ("gt", "baseline", "optimized", "initial")
        }
        terms = ate_change_terms(T["baseline"], T["optimized"], T["gt"], T["initial"])
        entry["drift"]["ate_change_vs_odometry"] = {k: round(v, 6) for k, v in terms.items()}
    print(json.dumps(entry), flush=True)
    return entry


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    names = SEQUENCES.value or sorted(
        d for d in os.listdir(ROOT.value) if os.path.isdir(os.path.join(ROOT.value, d, "Scans"))
    )
    results, stamped = [], None
    if os.path.exists(harness.OUT.value):  # the other sequences of an earlier run stay
        results = [r for r in harness.load(harness.OUT.value).get("sequences", []) if r["sequence"] not in names]
    for name in names:
        try:
            entry = run_sequence(name, os.path.join(ROOT.value, name))
            entry["targets"] = real_targets.target_verdicts(entry, RECORDED_STARTS.value[0], MINUTES_LIMIT.value)
        except Exception as e:  # one line per failed sequence; the others still run
            entry = {"sequence": name, "error": f"{type(e).__name__}: {e}"}
            logging.error("%s failed:\n%s", name, traceback.format_exc())
            print(json.dumps(entry), flush=True)
        results.append(entry)
        stamped = harness.write(
            harness.OUT.value,
            {
                "budget": BUDGET.value,
                "overrides": OVERRIDES.value,
                "keep_tilt": KEEP_TILT.value,
                "drift_recipe": DRIFT_RECIPE.value,
                "sequences": results,
            },
            stamped=stamped,
        )
    print("targets for real recordings (benchmarks/RESULTS.md):\n" + real_targets.format_targets(results), flush=True)


if __name__ == "__main__":
    reexec_with_huge_page_malloc()
    app.run(main)
