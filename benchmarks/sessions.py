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
  points in the merged map (metrics.json's; biased: another visit's points around them, docs/sessions.md);
- with the runs alone, the same points judged under two sets of poses ("same_points"): each visit's own keyframes
  under the merged run's poses against its poses alone, and every visit's keyframes under the merged run's poses
  against each visit's poses alone laid rigidly in the first's frame (to_first, then ICP of the maps), overall and
  on the keyframes within --overlap_m of another visit's; NeLD-BA's margins over the query draws;
- wall time [s] of each run, end to end (the merged one with the placing of every later visit).
With --split_root=FOLDER (a lio_keyframes folder: Scans/, odom_poses.txt, times.txt of a recording that comes back
to where it started) the two halves of that recording are the visits instead (WORK/first, WORK/second: the scans
linked, the second half's poses re-anchored in its own frame: its first keyframe at the origin, its heading turned,
gravity kept), and the runs use --config as given (e.g. configs/lio_keyframes.py:cpu); no ground truth, so the
same-points crispness is the measure:

    python benchmarks/sessions.py --split_root=/data/HKU_2_bag --config=configs/lio_keyframes.py:cpu \
        --work=outputs/sessions_hku2 --out=benchmarks/results/sessions_hku2_cpu.json

Targets, printed at the end: every visit's shared-alignment ATE at most --max_ate_m, no worse than its ATE alone,
and the merged run within --minutes_limit minutes; without ground truth, the merged run's poses at least as crisp as
the runs alone on the same points (each visit's, then all together: "every draw" crisper, "a tie" or "blurrier").
"""

import logging
import os
import shutil
import time

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
import numpy as np
import real_targets  # this folder's benchmarks/real_targets.py: the margins' verdicts
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

VISITS = flags.DEFINE_integer("visits", 2, "Visits of the courtyard (sessions 0 .. N-1).")
SEED = flags.DEFINE_integer("seed", 0, "The courtyard's seed.")
NUM_SCANS = flags.DEFINE_integer("num_scans", 24, "Scans a visit (3 s apart, round the loop).")
GT_MAP_POINTS = flags.DEFINE_integer("gt_map_points", 50_000, "Points of each visit's ground-truth map.")
WORK = flags.DEFINE_string("work", "outputs/sessions", "The visits and the runs go below this.")
harness.default_out("outputs/sessions/sessions.json")
CONFIG = flags.DEFINE_string("config", "configs/generic.py:cpu", "The runs' config, PATH[:BUDGET].")
OVERRIDES = harness.overrides_flag()
SKIP_ALONE = flags.DEFINE_bool("skip_alone", False, "Run the merged run only (no visit alone).")
SPLIT_ROOT = flags.DEFINE_string("split_root", "", "A lio_keyframes folder whose two halves are the visits.")
MAX_ATE_M = flags.DEFINE_float("max_ate_m", 0.01, "Target: each visit's ATE under the shared alignment.")
MINUTES_LIMIT = flags.DEFINE_float("minutes_limit", 15.0, "Target: the merged run's wall time.")
OVERLAP_M = flags.DEFINE_float(
    "overlap_m",
    5.0,
    "Same-points crispness: a keyframe within this distance [m] of "
    "another visit's keyframe is where the visits overlap.",
)
PLACING_ICP_M = (1.0, 0.3, 0.1)  # the alone maps' rigid placing: point-to-plane ICP, coarse to fine


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


def split_in_two(root: str, work: str) -> list[str]:
    """WORK/first and WORK/second: the halves of a lio_keyframes folder, the second re-anchored (module docstring)."""
    import numpy as np

    rows = np.loadtxt(os.path.join(root, "odom_poses.txt")).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows
    times = open(os.path.join(root, "times.txt")).read().split()
    half = len(poses) // 2
    yaw = np.arctan2(poses[half, 1, 0], poses[half, 0, 0])
    anchor = np.eye(4)
    anchor[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    anchor[:3, 3] = poses[half, :3, 3]
    out = []
    for name, part, frame in (("first", slice(0, half), np.eye(4)), ("second", slice(half, len(poses)), anchor)):
        folder = os.path.join(work, name)
        shutil.rmtree(folder, ignore_errors=True)
        os.makedirs(os.path.join(folder, "Scans"))
        for k, i in enumerate(range(len(poses))[part]):
            os.symlink(
                os.path.join(os.path.abspath(root), "Scans", f"{i:06d}.pcd"),
                os.path.join(folder, "Scans", f"{k:06d}.pcd"),
            )
        moved = np.linalg.inv(frame) @ poses[part]
        np.savetxt(os.path.join(folder, "odom_poses.txt"), moved[:, :3, :].reshape(-1, 12))
        with open(os.path.join(folder, "times.txt"), "w") as f:
            f.write("\n".join(times[part]) + "\n")
        out.append(folder)
    return out


def own_alignment_ate(poses_file: str, visit) -> float | None:
    """ATE [m] of a visit's trajectory file (TUM) under its own SE(3) alignment to its ground truth."""
    from neld_jax.data.poses import read_tum
    from neld_jax.judging import metrics

    if visit is None:
        return None
    _, poses = read_tum(poses_file)
    return metrics.ate(poses, visit.gt_poses)["translation_rmse_m"]


def measure(visits: list, roots: list[str]) -> dict:
    work = os.path.abspath(WORK.value)
    alone = []
    for k, root in enumerate(roots if not SKIP_ALONE.value else []):
        m, seconds = timed_run(root, os.path.join(work, f"alone{k}"))
        ate = {
            name: method["ate"]["translation_rmse_m"]
            for name, method in m.get("evaluation", {}).get("methods", {}).items()
            if "ate" in method
        }
        alone.append(
            {
                "ate_m": ate.get("optimized"),
                "input_ate_m": ate.get("initial"),
                "mean_map_entropy": m["crispness"]["optimized"]["mean_map_entropy"],
                "started_from": m["run"]["started_from"],
                "wall_s": round(seconds, 1),
            }
        )
    m, seconds = timed_run(",".join(roots), os.path.join(work, "merged"))
    merged = []
    for k, entry in enumerate(m["sessions"]["recordings"]):
        files = os.path.join(work, "merged", "sessions", entry["name"], "poses_optimized.txt")
        shared = {name: ate["translation_rmse_m"] for name, ate in entry.get("ate_shared_alignment", {}).items()}
        merged.append(
            {
                "name": entry["name"],
                "closures": entry["closures"],
                "ate_shared_alignment_m": shared.get("optimized"),
                "input_ate_shared_alignment_m": shared.get("initial"),
                "ate_own_alignment_m": own_alignment_ate(files, visits[k]),
                "crispness": entry["crispness"],
            }
        )
    result = {
        "alone": alone,
        "merged": {
            "visits": merged,
            "wall_s": round(seconds, 1),
            "started_from": m["run"]["started_from"],
            "steps": m["run"]["steps"],
            "mean_map_entropy": m["crispness"]["optimized"]["mean_map_entropy"],
        },
    }
    if alone:
        result["same_points"] = same_points_crispness(roots, work, m)
    return result


def visit_keyframes(root: str):
    """(loaded, keyframes) of one visit as the runs read it (--config, --set)."""
    from neld_jax.steps.inputs import load_keyframes

    return load_keyframes(run_config(root, "").data)


def placed_rigidly(moving: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """The rigid transform [4, 4] that best lays the point cloud `moving` [N, 3] on `fixed` [M, 3], which it nearly
    fits already: Open3D's point-to-plane ICP from the identity, at PLACING_ICP_M's correspondence distances in turn."""
    import open3d as o3d

    def cloud(points):
        c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(PLACING_ICP_M[-1])
        c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
        return c

    source, target, transform = cloud(moving), cloud(fixed), np.eye(4)
    for distance in PLACING_ICP_M:
        transform = o3d.pipelines.registration.registration_icp(
            source, target, distance, transform, o3d.pipelines.registration.TransformationEstimationPointToPlane()
        ).transformation
    return np.asarray(transform)


def same_points_crispness(roots: list[str], work: str, merged_metrics: dict) -> dict:
    """The crispness verdict over the same points (the bias of "in the merged map": docs/sessions.md). Per visit, its
    own keyframes under the merged run's poses against its poses alone; and every visit's keyframes together under
    the merged run's poses against each visit's poses alone, laid in the first visit's frame by its to_first and then
    rigidly by ICP of its alone map on the first's (the best a rigid placing of the runs alone gives). Margins
    (merged minus the other, negative: merged crisper) over eval.crispness_draws draws, and the same on the keyframes
    within --overlap_m of another visit's (per-keyframe means of the first draw)."""
    from types import SimpleNamespace

    from neld_jax.geometry import register_scans
    from neld_jax.judging import judge
    from neld_jax.writing.evaluate import trajectory_at_keyframes

    eval_cfg = run_config(roots[0], "").eval
    scans, merged, alone, labels, per_visit = [], [], [], [], []
    for k, (root, entry) in enumerate(zip(roots, merged_metrics["sessions"]["recordings"])):
        loaded, kf = visit_keyframes(root)
        ours = trajectory_at_keyframes(
            os.path.join(work, "merged", "sessions", entry["name"], "poses_optimized.txt"), loaded, kf
        )
        own = trajectory_at_keyframes(os.path.join(work, f"alone{k}", "poses_optimized.txt"), loaded, kf)
        poses = {"merged": ours, "alone": own}
        crisp, _ = judge.map_crispness(kf, poses, eval_cfg)
        margin = judge.crispness_margins(kf, poses, eval_cfg, against="merged", first_draw=crisp).get("alone")
        per_visit.append(
            {
                "merged_entropy": crisp["merged"]["mean_map_entropy"],
                "alone_entropy": crisp["alone"]["mean_map_entropy"],
                "merged_margin": margin,
            }
        )
        placing = np.asarray(entry["to_first"])  # placed the visit's input; then its map alone on the first's
        if k:
            own_map, first_map = register_scans(kf.scans, placing @ own), register_scans(scans[0], alone[0])
            placing = placed_rigidly(own_map, first_map) @ placing
        scans.append(list(kf.scans))
        merged.append(ours)
        alone.append(placing @ own)
        labels.append(np.full(len(ours), k))
    together = SimpleNamespace(scans=[s for part in scans for s in part])
    poses = {"merged": np.concatenate(merged), "alone_placed": np.concatenate(alone)}
    labels = np.concatenate(labels)
    crisp, per_keyframe = judge.map_crispness(together, poses, eval_cfg)
    margin = judge.crispness_margins(together, poses, eval_cfg, against="merged", first_draw=crisp).get("alone_placed")
    near = overlapping_keyframes(poses["merged"][:, :3, 3], labels, OVERLAP_M.value)
    return {
        "per_visit": per_visit,
        "together": {
            "merged_entropy": crisp["merged"]["mean_map_entropy"],
            "alone_placed_entropy": crisp["alone_placed"]["mean_map_entropy"],
            "merged_margin": margin,
            "overlap_keyframes": int(near.sum()),
            "overlap_merged_entropy": float(np.nanmean(per_keyframe["merged"][near])),
            "overlap_alone_placed_entropy": float(np.nanmean(per_keyframe["alone_placed"][near])),
        },
    }


def overlapping_keyframes(positions: np.ndarray, labels: np.ndarray, distance_m: float) -> np.ndarray:
    """[K] bool: the keyframes (positions [K, 3], visit labels [K]) within distance_m of another visit's keyframe."""
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    gaps[labels[:, None] == labels[None]] = np.inf
    return gaps.min(axis=1) <= distance_m


def targets(result: dict) -> dict:
    merged, alone = result["merged"]["visits"], result["alone"]
    if any(v["ate_shared_alignment_m"] is None for v in merged):  # no ground truth: the crispness is the measure
        same = result.get("same_points")  # None without the runs alone
        parts = [] if same is None else same["per_visit"] + [same["together"]]
        return {
            "merged_as_crisp_as_alone": None
            if same is None
            else [real_targets.margin_verdict(part["merged_margin"]) for part in parts],
            "within_minutes": result["merged"]["wall_s"] <= 60 * MINUTES_LIMIT.value,
        }
    return {
        "shared_ate_at_most_m": all(v["ate_shared_alignment_m"] <= MAX_ATE_M.value for v in merged),
        "merged_no_worse_than_alone": (
            None if not alone else all(v["ate_shared_alignment_m"] <= a["ate_m"] for v, a in zip(merged, alone))
        ),
        "within_minutes": result["merged"]["wall_s"] <= 60 * MINUTES_LIMIT.value,
    }


def _cm(metres: float | None) -> str:
    return "-" if metres is None else f"{100 * metres:.2f} cm"


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from neld_jax.synthetic.generator import make_sequence, write_generic

    work = os.path.abspath(WORK.value)
    cfg = {"seed": SEED.value, "num_scans": NUM_SCANS.value, "gt_map_points": GT_MAP_POINTS.value}
    visits, roots = [], []
    if SPLIT_ROOT.value:
        roots = split_in_two(SPLIT_ROOT.value, work)
        visits, cfg = [None, None], {"split_root": SPLIT_ROOT.value}
    for k in range(0 if SPLIT_ROOT.value else VISITS.value):
        visits.append(make_sequence(cfg, session=k))
        roots.append(os.path.join(work, f"visit{k}"))
        shutil.rmtree(roots[-1], ignore_errors=True)
        write_generic(visits[-1], roots[-1])
    result = measure(visits, roots)
    result["targets"] = targets(result)
    result.update(config=CONFIG.value, overrides=OVERRIDES.value, visit=cfg, visits=VISITS.value)
    harness.write(harness.OUT.value, result)
    for k, v in enumerate(result["merged"]["visits"]):
        a = result["alone"][k] if result["alone"] else {}
        print(
            f"{v['name']}: ATE alone {_cm(a.get('ate_m'))}, merged (shared alignment) "
            f"{_cm(v['ate_shared_alignment_m'])}, merged (own) {_cm(v['ate_own_alignment_m'])}; "
            f"entropy alone {v['crispness']['alone_keyframe_entropy']:.3f}, in the merged map "
            f"{v['crispness']['in_merged_keyframe_entropy']:.3f}",
            flush=True,
        )
    for k, part in enumerate(result.get("same_points", {}).get("per_visit", [])):
        print(
            f"visit {k}'s own keyframes, same points: merged {part['merged_entropy']:.3f}, alone "
            f"{part['alone_entropy']:.3f}, margin {part['merged_margin']}",
            flush=True,
        )
    if "same_points" in result:
        t = result["same_points"]["together"]
        print(
            f"every visit's keyframes, same points: merged {t['merged_entropy']:.3f}, alone and placed "
            f"{t['alone_placed_entropy']:.3f}, margin {t['merged_margin']}; the {t['overlap_keyframes']} keyframes "
            f"where the visits overlap: {t['overlap_merged_entropy']:.3f} against "
            f"{t['overlap_alone_placed_entropy']:.3f}",
            flush=True,
        )
    print(f"merged run {result['merged']['wall_s']:.0f} s; targets {result['targets']}; written to {harness.OUT.value}")


if __name__ == "__main__":
    reexec_with_huge_page_malloc()
    app.run(main)
