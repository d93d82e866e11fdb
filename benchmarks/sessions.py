#!/usr/bin/env python
"""Several visits of one place in one run, against each visit run alone.

    python benchmarks/sessions.py --work=outputs/sessions --out=benchmarks/results/sessions_cpu.json

Writes --visits visits of the synthetic courtyard (neld-make-synthetic --session=K: another loop each, its own drift,
its initial poses in its own frame; ground truth in the scene's frame) into WORK/visit<K> in the generic layout, runs
each alone (WORK/alone<K>) and all of them merged (data.root=WORK/visit0,WORK/visit1,...; WORK/merged) with --config
and --set, and reports per visit:
- ATE [m] alone (its own SE(3) alignment), in the merged run under ONE alignment shared by every visit
  (metrics.json's sessions section), and in the merged run under its own alignment;
- the raw map's crispness (mean map entropy of its keyframes under the refined poses) alone, and of its keyframes'
  points in the merged map;
- wall time [s] of each run, end to end (the merged one with the placing of every later visit).
Targets, printed at the end: every visit's shared-alignment ATE at most --max_ate_m, no worse than its ATE alone,
and the merged run within --minutes_limit minutes.
"""

import json
import logging
import os
import shutil
import time

from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

VISITS = flags.DEFINE_integer("visits", 2, "Visits of the courtyard (sessions 0 .. N-1).")
SEED = flags.DEFINE_integer("seed", 0, "The courtyard's seed.")
NUM_SCANS = flags.DEFINE_integer("num_scans", 24, "Scans a visit (3 s apart, round the loop).")
GT_MAP_POINTS = flags.DEFINE_integer("gt_map_points", 50_000, "Points of each visit's ground-truth map.")
WORK = flags.DEFINE_string("work", "outputs/sessions", "The visits and the runs go below this.")
OUT = flags.DEFINE_string("out", "outputs/sessions/sessions.json", "JSON file of the results.")
CONFIG = flags.DEFINE_string("config", "configs/generic.py:cpu", "The runs' config, PATH[:BUDGET].")
OVERRIDES = flags.DEFINE_multi_string("set", [], "Config overrides KEY=VALUE (Python literal).")
SKIP_ALONE = flags.DEFINE_bool("skip_alone", False, "Run the merged run only (no visit alone).")
MAX_ATE_M = flags.DEFINE_float("max_ate_m", 0.01, "Target: each visit's ATE under the shared alignment.")
MINUTES_LIMIT = flags.DEFINE_float("minutes_limit", 15.0, "Target: the merged run's wall time.")


def run_config(root: str, out_dir: str):
    from neld_jax.config import apply_overrides, from_file

    path = CONFIG.value if os.path.isabs(CONFIG.value) else os.path.join(REPO, CONFIG.value)
    c = from_file(path)
    c.data.root, c.output_dir, c.viz.record = root, out_dir, False
    return apply_overrides(c, OVERRIDES.value)


def timed_run(root: str, out_dir: str) -> tuple[dict, float]:
    """(metrics.json, wall seconds) of one run into a fresh out_dir."""
    from neld_jax import run

    shutil.rmtree(out_dir, ignore_errors=True)
    started = time.perf_counter()
    metrics = run.run(run_config(root, out_dir), progress=False)
    return metrics, time.perf_counter() - started


def own_alignment_ate(poses_file: str, visit) -> float:
    """ATE [m] of a visit's trajectory file (TUM) under its own SE(3) alignment to its ground truth."""
    from neld_jax import metrics
    from neld_jax.data.poses import read_tum

    _, poses = read_tum(poses_file)
    return metrics.ate(poses, visit.gt_poses)["translation_rmse_m"]


def measure(visits: list, roots: list[str]) -> dict:
    work = os.path.abspath(WORK.value)
    alone = []
    for k, root in enumerate(roots if not SKIP_ALONE.value else []):
        m, seconds = timed_run(root, os.path.join(work, f"alone{k}"))
        alone.append({"ate_m": m["evaluation"]["methods"]["optimized"]["ate"]["translation_rmse_m"],
                      "input_ate_m": m["evaluation"]["methods"]["initial"]["ate"]["translation_rmse_m"],
                      "mean_map_entropy": m["crispness"]["optimized"]["mean_map_entropy"],
                      "started_from": m["run"]["started_from"], "wall_s": round(seconds, 1)})
    m, seconds = timed_run(",".join(roots), os.path.join(work, "merged"))
    merged = []
    for k, entry in enumerate(m["sessions"]["recordings"]):
        files = os.path.join(work, "merged", "sessions", entry["name"], "poses_optimized.txt")
        merged.append({"name": entry["name"], "closures": entry["closures"],
                       "ate_shared_alignment_m": entry["ate_shared_alignment"]["optimized"]["translation_rmse_m"],
                       "input_ate_shared_alignment_m": entry["ate_shared_alignment"]["initial"]["translation_rmse_m"],
                       "ate_own_alignment_m": own_alignment_ate(files, visits[k]), "crispness": entry["crispness"]})
    return {"alone": alone, "merged": {"visits": merged, "wall_s": round(seconds, 1),
                                       "started_from": m["run"]["started_from"], "steps": m["run"]["steps"],
                                       "mean_map_entropy": m["crispness"]["optimized"]["mean_map_entropy"]}}


def targets(result: dict) -> dict:
    merged, alone = result["merged"]["visits"], result["alone"]
    return {"shared_ate_at_most_m": all(v["ate_shared_alignment_m"] <= MAX_ATE_M.value for v in merged),
            "merged_no_worse_than_alone": (None if not alone else all(
                v["ate_shared_alignment_m"] <= a["ate_m"] for v, a in zip(merged, alone))),
            "within_minutes": result["merged"]["wall_s"] <= 60 * MINUTES_LIMIT.value}


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from neld_jax.data.synthetic import make_sequence, write_generic

    work = os.path.abspath(WORK.value)
    cfg = {"seed": SEED.value, "num_scans": NUM_SCANS.value, "gt_map_points": GT_MAP_POINTS.value}
    visits, roots = [], []
    for k in range(VISITS.value):
        visits.append(make_sequence(cfg, session=k))
        roots.append(os.path.join(work, f"visit{k}"))
        shutil.rmtree(roots[-1], ignore_errors=True)
        write_generic(visits[-1], roots[-1])
    result = measure(visits, roots)
    result["targets"] = targets(result)
    result.update(config=CONFIG.value, overrides=OVERRIDES.value, visit=cfg, visits=VISITS.value)
    os.makedirs(os.path.dirname(os.path.abspath(OUT.value)), exist_ok=True)
    with open(OUT.value, "w") as f:
        json.dump(result, f, indent=1)
    for k, v in enumerate(result["merged"]["visits"]):
        a = result["alone"][k] if result["alone"] else {}
        print(f"{v['name']}: ATE alone {100 * a.get('ate_m', float('nan')):.2f} cm, merged (shared alignment) "
              f"{100 * v['ate_shared_alignment_m']:.2f} cm, merged (own) {100 * v['ate_own_alignment_m']:.2f} cm; "
              f"entropy alone {v['crispness']['alone_keyframe_entropy']:.3f}, in the merged map "
              f"{v['crispness']['in_merged_keyframe_entropy']:.3f}", flush=True)
    print(f"merged run {result['merged']['wall_s']:.0f} s; targets {result['targets']}; written to {OUT.value}")


if __name__ == "__main__":
    reexec_with_huge_page_malloc()
    app.run(main)
