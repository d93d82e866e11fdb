"""Which poses give the crisper raw map, and how sure that is: the crispness (neld_jax.judging.crispness) of one set of
scans registered with each method's poses, on the same query points, and the paired differences over several
draws of them (docs/evaluation.md, "How sure a difference is"). No ground truth needed.

Methods are named: "initial" (the input), "baseline" (the classical baseline), "optimized" (NeLD-BA), or any
trajectory a user brings (neld-crispness).
"""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np

from neld_jax.geometry import register_scans
from neld_jax.judging import crispness
from neld_jax.trajectory import with_distances_of

logger = logging.getLogger(__name__)


def compare_maps(
    scans: list[np.ndarray],
    methods: dict[str, np.ndarray],
    radius: float = crispness.DEFAULT_RADIUS_M,
    max_queries: int = crispness.DEFAULT_MAX_QUERIES,
) -> tuple[dict, dict]:
    """Crispness of the raw map of `scans` (K arrays [N_i, 3], sensor frame) under each method's poses [K, 4, 4].

    Every method is measured on the same query points (the same scans, seed 0), so the figures compare.
    Returns ({method: crispness summary + radius}, {method: per-keyframe mean entropy [K]})."""
    scan_of_point = np.repeat(np.arange(len(scans)), [len(s) for s in scans])
    queries = crispness.sample_queries(len(scan_of_point), int(max_queries), seed=0)
    summaries, per_scan = {}, {}
    for name, poses in methods.items():
        result = crispness.crispness(register_scans(scans, poses), radius=float(radius), query_index=queries)
        summaries[name] = {**result.summary(), "radius_m": float(radius)}
        per_scan[name] = crispness.per_scan_means(result.entropy, queries, scan_of_point, len(scans))
    logger.info(
        "raw-map crispness (radius %.2f m, %d query points): %s",
        radius,
        len(queries),
        "; ".join(
            f"{name}: entropy {s['mean_map_entropy']:.3f}, thickness {100 * s['mean_plane_thickness_m']:.2f} cm"
            for name, s in summaries.items()
            if s["mean_map_entropy"] is not None
        ),
    )
    return summaries, per_scan


def map_crispness(keyframes, methods: dict[str, np.ndarray], eval_cfg) -> tuple[dict, dict]:
    """`compare_maps` of a sequence's keyframes with config.eval's crispness settings."""
    return compare_maps(
        keyframes.scans, methods, float(eval_cfg["crispness_radius_m"]), int(eval_cfg["crispness_queries"])
    )


EVERY_SCAN_POINTS = 4096  # of each scan in the map of every scan: 300 sweeps about as many points as 30 keyframes


def every_scan_crispness(
    scans, methods: dict[str, np.ndarray], eval_cfg, against: str, points_per_scan: int = EVERY_SCAN_POINTS
) -> tuple[dict, dict]:
    """The raw map of EVERY input scan, not only the keyframes': `points_per_scan` random points of each of the S
    scans (scans: S arrays [N_i, 3], sensor frames, read once each; the same points for every method, seeded by
    the scan's index) under each method's poses [S, 4, 4]. Returns (map_crispness's summaries, crispness_margins
    against `against`), as the keyframes' map gets them."""
    from types import SimpleNamespace

    kept = []
    for i in range(len(scans)):
        points = np.asarray(scans[i], np.float64)
        keep = np.random.default_rng(i).permutation(len(points))[:points_per_scan]
        kept.append(points[np.sort(keep)])
    every = SimpleNamespace(scans=kept)
    crisp, _ = map_crispness(every, methods, eval_cfg)
    return crisp, crispness_margins(every, methods, eval_cfg, against=against, first_draw=crisp)


def crispness_margins(
    keyframes,
    methods: dict[str, np.ndarray],
    eval_cfg,
    against: str = "optimized",
    first_draw: dict | None = None,
    deadline: float | None = None,
    progress: bool = False,
) -> dict:
    """How sure the crispness verdict is: the paired difference of the `against` method's mean map entropy from
    each other method's, on eval.crispness_draws draws of the query points (seeds 0, 1, ...; draw 0 is the one
    map_crispness uses). methods: {name: poses [K, 4, 4]} of the keyframes' scans. first_draw: map_crispness's
    summaries of these methods ({name: summary}), whose entropy is draw 0's, so only the later draws are measured.
    deadline: a time.perf_counter() value after which no draw starts (the run's clock); the margins then hold the
    draws made, and the log says so. progress: a progress bar over the draws.

    Returns {other: {"per_draw": [D], "mean", "std", "all_draws_agree"}} (negative: `against` is crisper), or {}
    with fewer than 2 draws or without the `against` method."""
    draws = int(eval_cfg["crispness_draws"])
    if draws < 2 or against not in methods:
        return {}
    maps = {name: register_scans(keyframes.scans, poses) for name, poses in methods.items()}
    entropy = crispness.entropy_over_query_draws(
        maps,
        list(range(1 if first_draw else 0, draws)),
        max_queries=int(eval_cfg["crispness_queries"]),
        radius=float(eval_cfg["crispness_radius_m"]),
        deadline=deadline,
        progress=progress,
    )
    made = len(next(iter(entropy.values()), [])) + (1 if first_draw else 0)
    if made < draws:
        logger.warning(
            "crispness margins: %d of %d query draws fit the run's clock (max_minutes)%s",
            made,
            draws,
            "" if made >= 2 else "; no margin without two",
        )
    if made < 2:
        return {}
    if first_draw:
        entropy = {
            name: np.concatenate(
                [
                    [np.nan if first_draw[name]["mean_map_entropy"] is None else first_draw[name]["mean_map_entropy"]],
                    values,
                ]
            )
            for name, values in entropy.items()
        }
    return {other: margin_over_draws(entropy[against] - entropy[other]) for other in methods if other != against}


def margin_over_draws(differences) -> dict:
    """One crispness_margins entry from the paired differences [D] (D >= 2) of the draws: {"per_draw", "mean",
    "std", "all_draws_agree"} (rounded to 1e-6 nats)."""
    diff = np.asarray(differences, dtype=np.float64)
    return {
        "per_draw": [round(float(d), 6) for d in diff],
        "mean": round(float(diff.mean()), 6),
        "std": round(float(diff.std(ddof=1)), 6),
        "all_draws_agree": bool((diff < 0).all() or (diff > 0).all()),
    }


def describe_margin(other: str, margin: dict, against: str = "NeLD-BA") -> str:
    """One line for a crispness_margins entry: the mean difference, its spread, and the verdict."""
    draws = len(margin["per_draw"])
    if not margin["all_draws_agree"]:
        verdict = f"a tie: the {draws} draws disagree in sign"
    else:
        verdict = f"{'crisper' if margin['mean'] < 0 else 'blurrier'} on every one of {draws} draws"
    return (
        f"{against}'s raw map against the {other} poses' map: {margin['mean']:+.5f} nats of mean map entropy "
        f"(std {margin['std']:.5f} over query draws), {verdict}"
    )


def judge_trajectories(keyframes, methods: dict[str, np.ndarray], eval_cfg, progress: bool = False) -> dict:
    """Which trajectory gives the crispest raw map of the keyframes' scans, and how sure that is.

    methods: {name: poses [K, 4, 4]} (two or more). The crispest is the lowest mean map entropy over
    eval.crispness_draws draws of the query points (draw 0's alone with fewer than 2 draws). Returns
    {"crispness": {name: summary on draw 0}, "crispest": name, "margins": {other: the crispest's entropy minus
    other's per draw, mean, std, all_draws_agree}} (margins empty without draws). progress: a progress bar over
    the draws."""
    crisp, _ = map_crispness(keyframes, methods, eval_cfg)
    best = crispest(crisp)
    margins = (
        crispness_margins(keyframes, methods, eval_cfg, against=best, first_draw=crisp, progress=progress)
        if best
        else {}
    )
    over_draws = crispest_over_draws(margins, against=best)
    if over_draws not in (None, best):  # draw 0 alone picked another
        margins, best = margins_against(margins, best, over_draws), over_draws
    return {"crispness": crisp, "crispest": best, "margins": margins}


def margins_against(margins: dict, reference: str, new: str) -> dict:
    """crispness_margins' answer for `reference` ({other: reference's entropy minus other's, per draw}) turned
    into the same for `new`, one of the others: new minus other = (reference - other) - (reference - new)."""
    to_new = np.asarray(margins[new]["per_draw"])
    moved = {
        other: margin_over_draws(np.asarray(m["per_draw"]) - to_new) for other, m in margins.items() if other != new
    }
    return {**moved, reference: margin_over_draws(-to_new)}


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


def warn_if_not_crispest(summaries: dict, margins: dict | None = None) -> str | None:
    """Log a warning when the refined poses ("optimized") do not give the crispest raw map of the run's methods,
    naming the poses file that does: a user must not take poses_optimized for the best answer when the run
    measured otherwise. margins: crispness_margins' answer for "optimized"; given, the verdict is the mean over its
    query draws instead of draw 0's figures alone, and a crisper method whose draws disagree in sign is logged as a
    tie, not warned about. Returns the crispest method."""
    known_margins = {name: m for name, m in (margins or {}).items() if name in summaries}
    best = crispest_over_draws(known_margins) if known_margins and "optimized" in summaries else crispest(summaries)
    if best is not None and "optimized" in summaries and best != "optimized":
        margin = known_margins.get(best)
        if margin is not None and not margin["all_draws_agree"]:
            logger.info(
                "the raw map is a little crisper with the %s poses (%s) than after NeLD-BA, by %.5f nats of "
                "mean map entropy over %d query draws, but the draws disagree in sign: a tie",
                best,
                f"poses_{best}.txt",
                margin["mean"],
                len(margin["per_draw"]),
            )
            return best
        entropy = summaries["optimized"]["mean_map_entropy"]
        logger.warning(
            "the raw map is crisper with the %s poses (%s) than after NeLD-BA: mean map entropy %.3f against %s%s",
            best,
            f"poses_{best}.txt",
            summaries[best]["mean_map_entropy"],
            "-" if entropy is None else f"{entropy:.3f}",
            ""
            if margin is None
            else f" (by {margin['mean']:.5f} on average over "
            f"{len(margin['per_draw'])} query draws, every draw agreeing)",
        )
    return best


def format_crispness_table(summaries: dict, ordered: bool = False, digits: int = 3) -> str:
    """Plain-text table of {method: crispness summary}: entropy (`digits` decimals) and plane thickness in cm (one
    fewer) of the raw map. Rows: initial, baseline, optimized, then the rest by name; ordered=True: the dict's order."""
    usual = ("initial", "baseline", "optimized")
    order = list(summaries) if ordered else [m for m in usual if m in summaries] + sorted(set(summaries) - set(usual))
    width = max([12, *(len(name) + 1 for name in order)])
    lines = [
        "raw-map crispness (no ground truth needed; lower is crisper)",
        f"{'method':<{width}} {'mean map entropy':>17} {'plane thickness [cm]':>21}",
    ]
    for name in order:
        s = summaries[name]
        entropy, thickness = s.get("mean_map_entropy"), s.get("mean_plane_thickness_m")
        lines.append(
            f"{name:<{width}} {'-' if entropy is None else f'{entropy:.{digits}f}':>17} "
            f"{'-' if thickness is None else f'{100 * thickness:.{digits - 1}f}':>21}"
        )
    return "\n".join(lines)


def distances_judged(
    scans: list[np.ndarray], poses: np.ndarray, reference: np.ndarray, window_m: float, eval_cfg, beyond: float = 0.0
) -> tuple[np.ndarray, bool, dict | None]:
    """Whose distances travelled poses [S, 4, 4] keep: their own, or the reference's [S, 4, 4] over window_m windows
    on the steps whose window departs beyond `beyond` (trajectory.with_distances_of), judged by the raw map of scans
    (S arrays [N_i, 3], sensor frame) under both on eval_cfg's query draws (its crispness_radius_m,
    crispness_queries, crispness_draws). Returns (the poses kept: their own where they give the crisper map on every
    draw, else those with the reference's distances; whether their own were kept; the margin of the reference's
    distances against their own, crispness_margins' {"per_draw", "mean", "std", "all_draws_agree"}, None with fewer
    than two draws)."""
    candidate = with_distances_of(poses, reference, window_m, beyond)
    methods = {"own": poses, "input": candidate}
    first, _ = compare_maps(scans, methods, float(eval_cfg["crispness_radius_m"]), int(eval_cfg["crispness_queries"]))
    margin = crispness_margins(SimpleNamespace(scans=scans), methods, eval_cfg, against="own", first_draw=first).get(
        "input"
    )
    own_crisper = margin is not None and margin["all_draws_agree"] and margin["mean"] < 0
    return (poses if own_crisper else candidate), own_crisper, margin
