"""Quality of a run without ground truth (effects: files in output_dir): map crispness per method, the per-scan
report (scans_report.csv / .png) and the top view of the raw map before and after (map_topdown.png); and the same
crispness verdict for any trajectory files of a sequence's scans (bin/crispness.py).

The maths lives in neld_jax.crispness and neld_jax.report; this module feeds them a run's arrays.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from neld_jax import crispness, metrics, plots, report
from neld_jax.data.timing import match_by_timestamp
from neld_jax.errors import DataError
from neld_jax.export import read_json, write_json
from neld_jax.geometry import invert_poses, register_scans

logger = logging.getLogger(__name__)


def map_crispness(seq, methods: dict[str, np.ndarray], eval_cfg) -> tuple[dict, dict]:
    """Crispness of the keyframes' raw map (seq.scans, sensor frame) under each method's poses [K, 4, 4].

    Every method is measured on the same query points (the same scans, the same seed), so the figures compare.
    Returns ({method: crispness summary + radius}, {method: per-keyframe mean entropy [K]})."""
    radius = float(eval_cfg.get("crispness_radius_m", crispness.DEFAULT_RADIUS_M))
    max_queries = int(eval_cfg.get("crispness_queries", crispness.DEFAULT_MAX_QUERIES))
    scan_of_point = np.repeat(np.arange(seq.num_scans), [len(s) for s in seq.scans])
    queries = crispness.sample_queries(len(scan_of_point), max_queries, seed=0)
    summaries, per_scan = {}, {}
    for name, poses in methods.items():
        result = crispness.crispness(register_scans(seq.scans, poses), radius=radius, query_index=queries)
        summaries[name] = {**result.summary(), "radius_m": radius}
        per_scan[name] = crispness.per_scan_means(result.entropy, queries, scan_of_point, seq.num_scans)
    logger.info("raw-map crispness (radius %.2f m, %d query points): %s", radius, len(queries),
                "; ".join(f"{name}: entropy {s['mean_map_entropy']:.3f}, thickness "
                          f"{100 * s['mean_plane_thickness_m']:.2f} cm" for name, s in summaries.items()
                          if s["mean_map_entropy"] is not None))
    return summaries, per_scan


def crispness_margins(seq, methods: dict[str, np.ndarray], eval_cfg, against: str = "optimized",
                      first_draw: dict | None = None, deadline: float | None = None, progress: bool = False) -> dict:
    """How sure the crispness verdict is: the paired difference of the `against` method's mean map entropy from
    each other method's, on eval.crispness_draws draws of the query points (seeds 0, 1, ...; draw 0 is the one
    map_crispness uses). methods: {name: poses [K, 4, 4]} of the keyframes seq.scans. first_draw: map_crispness's
    summaries of these methods ({name: summary}), whose entropy is draw 0's, so only the later draws are measured.
    deadline: a time.perf_counter() value after which no draw starts (the run's clock); the margins then hold the
    draws made, and the log says so. progress: a progress bar over the draws.

    Returns {other: {"per_draw": [D], "mean", "std", "all_draws_agree"}} (negative: `against` is crisper), or {}
    with fewer than 2 draws or without the `against` method."""
    draws = int(eval_cfg.get("crispness_draws", 0))
    if draws < 2 or against not in methods:
        return {}
    maps = {name: register_scans(seq.scans, poses) for name, poses in methods.items()}
    entropy = crispness.entropy_over_query_draws(
        maps, list(range(1 if first_draw else 0, draws)),
        max_queries=int(eval_cfg.get("crispness_queries", crispness.DEFAULT_MAX_QUERIES)),
        radius=float(eval_cfg.get("crispness_radius_m", crispness.DEFAULT_RADIUS_M)), deadline=deadline,
        progress=progress)
    made = len(next(iter(entropy.values()), [])) + (1 if first_draw else 0)
    if made < draws:
        logger.warning("crispness margins: %d of %d query draws fit the run's clock (train.max_minutes + "
                       "mapping.max_seconds + eval.crispness_draws_max_seconds)%s", made, draws,
                       "" if made >= 2 else "; no margin without two")
    if made < 2:
        return {}
    if first_draw:
        entropy = {name: np.concatenate([[np.nan if first_draw[name]["mean_map_entropy"] is None
                                          else first_draw[name]["mean_map_entropy"]], values])
                   for name, values in entropy.items()}
    return {other: margin_over_draws(entropy[against] - entropy[other]) for other in methods if other != against}


def margin_over_draws(differences) -> dict:
    """One crispness_margins entry from the paired differences [D] (D >= 2) of the draws: {"per_draw", "mean",
    "std", "all_draws_agree"} (rounded to 1e-6 nats)."""
    diff = np.asarray(differences, dtype=np.float64)
    return {"per_draw": [round(float(d), 6) for d in diff], "mean": round(float(diff.mean()), 6),
            "std": round(float(diff.std(ddof=1)), 6), "all_draws_agree": bool((diff < 0).all() or (diff > 0).all())}


def describe_margin(other: str, margin: dict, against: str = "NeLD-BA") -> str:
    """One line for a crispness_margins entry: the mean difference, its spread, and the verdict."""
    draws = len(margin["per_draw"])
    if not margin["all_draws_agree"]:
        verdict = f"a tie: the {draws} draws disagree in sign"
    else:
        verdict = f"{'crisper' if margin['mean'] < 0 else 'blurrier'} on every one of {draws} draws"
    return (f"{against}'s raw map against the {other} poses' map: {margin['mean']:+.5f} nats of mean map entropy "
            f"(std {margin['std']:.5f} over query draws), {verdict}")


def trajectory_at_keyframes(path, loaded, keyframes, tol: float = 0.05, invert: bool = False) -> np.ndarray:
    """The poses [K, 4, 4] that a trajectory file (TUM, KITTI or Newer College CSV, in the convention of the
    sequence's own pose file; invert: world -> sensor, as data.invert_poses) gives the keyframes `keyframes` of the
    input scans `loaded`: by time when the file and the scans have timestamps (every keyframe needs a pose within
    `tol` s), else by order, one pose per input scan or one per keyframe. Another back-end's answer for the same
    scans is judged this way (bin/crispness.py); a file that fits neither is one DataError naming it."""
    from neld_jax.evaluate import read_trajectory  # it imports open3d; run.train_keyframes' imports must not

    stamps, poses = read_trajectory(path)
    poses = invert_poses(poses) if invert else poses
    index = keyframes.loaded_index
    if stamps is not None and loaded.timestamps is not None:
        labels = None if loaded.files is None else [loaded.files[i] for i in index]
        return poses[match_by_timestamp(loaded.timestamps[index], stamps, tol=tol, what=str(path), scan_labels=labels)]
    if len(poses) == loaded.num_scans:
        return poses[index]
    if len(poses) == keyframes.num_scans:
        return poses
    why = "has no timestamps" if stamps is None else "has timestamps but the scans have none"
    raise DataError(f"{path}: {len(poses)} poses for {loaded.num_scans} input scans ({keyframes.num_scans} "
                    f"keyframes); the file {why}, so it must hold one pose per input scan or per keyframe, in order")


def judge_trajectories(seq, methods: dict[str, np.ndarray], eval_cfg, progress: bool = False) -> dict:
    """Which trajectory gives the crispest raw map of the keyframes seq.scans, and how sure that is.

    methods: {name: poses [K, 4, 4]} (two or more). The crispest is the lowest mean map entropy over
    eval.crispness_draws draws of the query points (draw 0's alone with fewer than 2 draws). Returns
    {"crispness": {name: summary on draw 0}, "crispest": name, "margins": {other: the crispest's entropy minus
    other's per draw, mean, std, all_draws_agree}} (margins empty without draws). progress: a progress bar over
    the draws."""
    crisp, _ = map_crispness(seq, methods, eval_cfg)
    best = crispest(crisp)
    margins = (crispness_margins(seq, methods, eval_cfg, against=best, first_draw=crisp, progress=progress)
               if best else {})
    over_draws = crispest_over_draws(margins, against=best)
    if over_draws not in (None, best):  # draw 0 alone picked another
        margins, best = margins_against(margins, best, over_draws), over_draws
    return {"crispness": crisp, "crispest": best, "margins": margins}


def margins_against(margins: dict, reference: str, new: str) -> dict:
    """crispness_margins' answer for `reference` ({other: reference's entropy minus other's, per draw}) turned
    into the same for `new`, one of the others: new minus other = (reference - other) - (reference - new)."""
    to_new = np.asarray(margins[new]["per_draw"])
    moved = {other: margin_over_draws(np.asarray(m["per_draw"]) - to_new)
             for other, m in margins.items() if other != new}
    return {**moved, reference: margin_over_draws(-to_new)}


def aligned_corrections(T_before: np.ndarray, T_after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How each scan moved against the others from T_before to T_after ([S, 4, 4] each): the rigid motion of the
    whole trajectory (the gauge, e.g. the anchor scan's own correction) is removed first by aligning T_after to
    T_before (SE(3), with 3 scans or more). Returns (translation [S] metres, rotation [S] degrees)."""
    alignment = np.eye(4)
    if len(T_before) >= 3:
        rotation, translation, _ = metrics.umeyama_alignment(T_after[:, :3, 3], T_before[:, :3, 3])
        alignment = metrics.similarity_matrix(rotation, translation)
    return report.pose_corrections(T_before, alignment @ T_after)


def write_scan_report(out_dir, loaded, seq, keyframe_index, T_all, raysets, rendered, norm, per_scan_entropy,
                      min_opacity: float, start_poses: np.ndarray | None = None,
                      refined_poses: np.ndarray | None = None) -> list[dict]:
    """scans_report.csv and scans_report.png: one row per input scan (neld_jax.report).

    rendered: (mapping rays, MapRender) from the rendered map, or None (then no residuals). start_poses,
    refined_poses: [K, 4, 4] the keyframes' poses training started from and its answer, for the refinement columns
    (None: the correction from the input stands for it)."""
    num_keyframes = seq.num_scans
    rays_per_keyframe = np.bincount(raysets.scan_index, minlength=num_keyframes)
    residual = np.full(num_keyframes, np.nan)
    if rendered is not None:
        mapping_rays, render = rendered
        hit = render.opacity >= min_opacity
        error_m = np.abs(render.ranges - mapping_rays.ranges) / norm.scale
        # build_rays groups the rays by scan: split once instead of masking all rays for every scan.
        bounds = np.cumsum(np.bincount(mapping_rays.scan_index, minlength=num_keyframes))[:-1]
        for k, (errors, hits) in enumerate(zip(np.split(error_m, bounds), np.split(hit, bounds))):
            if hits.any():
                residual[k] = float(np.median(errors[hits]))
    correction_m, correction_deg = aligned_corrections(loaded.poses, T_all)
    refinement_m = refinement_deg = None
    if start_poses is not None and refined_poses is not None:
        refinement_m, refinement_deg = aligned_corrections(start_poses, refined_poses)
    rows = report.scan_report(loaded.num_scans, keyframe_index, loaded.files, loaded.timestamps, rays_per_keyframe,
                              residual, correction_m, correction_deg, per_scan_entropy.get("initial"),
                              per_scan_entropy.get("optimized"), refinement_m, refinement_deg)
    report.write_csv(os.path.join(out_dir, "scans_report.csv"), rows)
    plots.plot_scan_report(os.path.join(out_dir, "scans_report.png"), rows)
    logger.info("scans_report.csv: %d input scans, %d keyframes trained on", loaded.num_scans, num_keyframes)
    return rows


def write_topdown(out_dir, seq, methods: dict[str, np.ndarray]) -> None:
    """map_topdown.png: the keyframes' raw map from above under each method's poses, with close-ups where the
    first and the last differ most (plots.plot_map_topdown)."""
    plots.plot_map_topdown(os.path.join(out_dir, "map_topdown.png"),
                           {name: register_scans(seq.scans, poses) for name, poses in methods.items()})


def record_crispness(out_dir, summaries: dict) -> dict:
    """Merge {method: crispness summary} into the "crispness" section of OUT_DIR/metrics.json (the trainer and
    the baseline each add their methods); returns the merged section."""
    path = os.path.join(out_dir, "metrics.json")
    merged = {**read_json(path).get("crispness", {}), **summaries}
    write_json(path, {"crispness": merged})
    return merged


def crispest(summaries: dict) -> str | None:
    """The method of {method: crispness summary} with the lowest mean map entropy (the first of equals; None when
    none has one)."""
    scored = {name: s["mean_map_entropy"] for name, s in summaries.items() if s.get("mean_map_entropy") is not None}
    return min(scored, key=scored.get) if scored else None


def crispest_over_draws(margins: dict, against: str = "optimized") -> str | None:
    """The method with the lowest mean map entropy over the query draws of crispness_margins' answer
    ({other: {"mean": against's entropy minus other's, ...}}): `against` unless some other method's mean lies below
    its own (the first of equals); None for no margins."""
    if not margins:
        return None
    below = {other: m["mean"] for other, m in margins.items() if m["mean"] > 0}
    return max(below, key=below.get) if below else against


def warn_if_not_crispest(summaries: dict, refused: dict | None = None, margins: dict | None = None) -> str | None:
    """Log a warning when the refined poses ("optimized") do not give the crispest raw map of the run's methods,
    naming the poses file that does: a user must not take poses_optimized for the best answer when the run
    measured otherwise. refused: {method: why} the run did not trust whatever their crispness (a baseline bent
    as a whole: the judge is local); they are not named as the crispest. margins: crispness_margins' answer for
    "optimized"; given, the verdict is the mean over its query draws instead of draw 0's figures alone, and a
    crisper method whose draws disagree in sign is logged as a tie, not warned about. Returns the crispest trusted
    method."""
    refused = refused or {}
    trusted_margins = {name: m for name, m in (margins or {}).items() if name not in refused and name in summaries}
    if trusted_margins and "optimized" in summaries:
        best = crispest_over_draws(trusted_margins)
    else:
        best = crispest({name: s for name, s in summaries.items() if name not in refused})
    for name, why in refused.items():
        if name in summaries and crispest(summaries) == name:
            logger.info("the %s poses give a locally crisper raw map, but the run does not trust them: %s", name, why)
    if best is not None and "optimized" in summaries and best != "optimized":
        margin = trusted_margins.get(best)
        if margin is not None and not margin["all_draws_agree"]:
            logger.info("the raw map is a little crisper with the %s poses (%s) than after NeLD-BA, by %.5f nats of "
                        "mean map entropy over %d query draws, but the draws disagree in sign: a tie", best,
                        f"poses_{best}.txt", margin["mean"], len(margin["per_draw"]))
            return best
        entropy = summaries["optimized"]["mean_map_entropy"]
        logger.warning("the raw map is crisper with the %s poses (%s) than after NeLD-BA: mean map entropy %.3f "
                       "against %s%s", best, f"poses_{best}.txt", summaries[best]["mean_map_entropy"],
                       "-" if entropy is None else f"{entropy:.3f}",
                       "" if margin is None else f" (by {margin['mean']:.5f} on average over "
                                                 f"{len(margin['per_draw'])} query draws, every draw agreeing)")
    return best


def format_crispness_table(summaries: dict, ordered: bool = False, digits: int = 3) -> str:
    """Plain-text table of {method: crispness summary}: entropy (`digits` decimals) and plane thickness in cm (one
    fewer) of the raw map. Rows: initial, baseline, optimized, then the rest by name; ordered=True: the dict's order."""
    usual = ("initial", "baseline", "optimized")
    order = list(summaries) if ordered else [m for m in usual if m in summaries] + sorted(set(summaries) - set(usual))
    width = max([12, *(len(name) + 1 for name in order)])
    lines = ["raw-map crispness (no ground truth needed; lower is crisper)",
             f"{'method':<{width}} {'mean map entropy':>17} {'plane thickness [cm]':>21}"]
    for name in order:
        s = summaries[name]
        entropy, thickness = s.get("mean_map_entropy"), s.get("mean_plane_thickness_m")
        lines.append(f"{name:<{width}} {'-' if entropy is None else f'{entropy:.{digits}f}':>17} "
                     f"{'-' if thickness is None else f'{100 * thickness:.{digits - 1}f}':>21}")
    return "\n".join(lines)
