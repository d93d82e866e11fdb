"""The targets read off one sequence's entry of a benchmark (pure functions, no flags, so tests import them).

benchmarks/real_data.py's, for real recordings (target_verdicts): the recorded run within the time limit, one pose
line per input scan, its map crisper than the odometry's and than the classical baseline's; from injected drift,
NeLD-BA within 2 cm of its answer from the recorded odometry, its map at least as crisp as the recorded odometry's,
its ATE against the odometry at or below the baseline's. A margin's verdict is the run's own (run.crispness_margin
over eval.crispness_draws query draws): "every draw" (crisper on each), "a tie" (the draws disagree in sign) or
"blurrier" (blurrier on each).

benchmarks/peers.py's (peer_target_verdicts): NeLD-BA against KISS-ICP and KISS-SLAM, and its ATE and path length
against its own classical start (the baseline) and its odometry.
"""

from __future__ import annotations


def margin_verdict(margin: dict | None):
    """run.crispness_margin's entry for one other method -> "every draw" (NeLD-BA crisper on each query draw),
    "a tie" (the draws disagree in sign), "blurrier" (blurrier on each), or None without draws."""
    if not margin:
        return None
    if not margin["all_draws_agree"]:
        return "a tie"
    return "every draw" if margin["mean"] < 0 else "blurrier"


def target_verdicts(entry: dict, start: str, minutes_limit: float = 10.0) -> dict:
    """The targets for real recordings, for one sequence's entry of benchmarks/real_data.py: {"recorded": {...}} for the
    recorded run from `start` (start.poses; the drift run's own), and {"drift": {...}} when there is a drift
    run. Each target is True / False, a margin's verdict ("every draw", "a tie", "blurrier"), or None where the
    entry lacks what it needs."""

    def entropy(crispness: dict, method: str):
        return crispness.get(method, {}).get("entropy")

    def below(a, b, strictly=False):  # None when either figure is missing
        return None if a is None or b is None else (a < b if strictly else a <= b)

    recorded = entry["recorded"].get(start)
    out = {}
    if recorded is not None:
        crisp = recorded["crispness"]
        out["recorded"] = {
            "within_minutes": recorded["wall_s"] <= 60 * minutes_limit,
            "every_scan_a_pose": (
                None if recorded.get("pose_lines") is None else recorded["pose_lines"] == recorded["scans"]
            ),
            "crisper_than_odometry": below(entropy(crisp, "optimized"), entropy(crisp, "initial"), strictly=True),
            "crisper_than_baseline": margin_verdict((recorded.get("crispness_margin") or {}).get("baseline")),
        }
    drift = entry.get("drift")
    if drift is not None:
        apart = drift.get("optimized_apart_from_recorded_m")
        # The ATE split's own figures where there are (unrounded: the two ATEs differ by hundredths of a mm)
        split = drift.get("ate_change_vs_odometry") or {}
        ate = (
            {"baseline": split["ate_baseline_mm"], "optimized": split["ate_optimized_mm"]}
            if "ate_optimized_mm" in split
            else drift["ate_vs_odometry_m"]
        )
        out["drift"] = {
            "within_2cm_of_recorded_answer": below(apart, 0.02),
            "as_crisp_as_odometry": below(
                entropy(drift["crispness"], "optimized"),
                None if recorded is None else entropy(recorded["crispness"], "initial"),
            ),
            "ate_at_or_below_baseline": below(ate.get("optimized"), ate.get("baseline")),
            "crisper_than_baseline": margin_verdict((drift.get("crispness_margin") or {}).get("baseline")),
        }
        if "every_scan_map" in drift:  # every input scan's map, not only the keyframes'
            margin = drift["every_scan_map"]["margin"]
            out["drift"].update(
                every_scan_map_crisper_than_odometry=margin_verdict(margin.get("initial")),
                every_scan_map_crisper_than_baseline=margin_verdict(margin.get("baseline")),
            )
    return out


PATH_SCALE_TOLERANCE = 0.001  # NeLD-BA's path length within 0.1 % of its odometry's: the neural part keeps the scale


def peer_target_verdicts(entry: dict, minutes_limit: float = 10.0) -> dict:
    """The targets of one sequence's entry of benchmarks/peers.py: NeLD-BA's ATE below KISS-ICP's and KISS-SLAM's;
    its ATE over KISS-ICP's, over the classical baseline's it started from (what the neural part adds) and over its
    odometry's (4 decimals); its path length over the odometry's (path_scale_vs_odometry: the ratio of their
    path_ratio figures, 6 decimals) and whether that is within PATH_SCALE_TOLERANCE of 1; its raw maps (the
    keyframes', every sweep's) crisper than both peers on every draw (the verdict: "every draw", "a tie",
    "blurrier"); its whole run within minutes_limit. None where a figure is missing."""
    rows = entry["methods"]
    neld = rows["neld_ba"]

    def below(peer):
        a, b = neld.get("ate_m"), rows[peer].get("ate_m")
        return None if a is None or b is None else a < b

    def over(method, key="ate_m"):
        a, b = neld.get(key), rows[method].get(key)
        return None if a is None or not b else round(a / b, 4 if key == "ate_m" else 6)

    scale = over("odometry", "path_ratio")
    return {
        "ate_below_kiss_icp": below("kiss_icp"),
        "ate_below_kiss_slam": below("kiss_slam"),
        "ate_over_kiss_icp": over("kiss_icp"),
        "ate_over_baseline": over("baseline"),
        "ate_over_odometry": over("odometry"),
        "path_scale_vs_odometry": scale,
        "path_scale_within_0.1pct": None if scale is None else abs(scale - 1.0) <= PATH_SCALE_TOLERANCE,
        "crisper_than_kiss_icp": rows["kiss_icp"].get("neld_ba_verdict"),
        "crisper_than_kiss_slam": rows["kiss_slam"].get("neld_ba_verdict"),
        "every_sweep_map_crisper_than_kiss_icp": rows["kiss_icp"].get("every_sweep_map", {}).get("neld_ba_verdict"),
        "every_sweep_map_crisper_than_kiss_slam": rows["kiss_slam"].get("every_sweep_map", {}).get("neld_ba_verdict"),
        "within_minutes": None if neld.get("wall_s") is None else neld["wall_s"] <= 60 * minutes_limit,
    }


def format_targets(results: list[dict]) -> str:
    """One line per sequence and target group: the sequence, then each target's verdict (or the error)."""
    lines = []
    for entry in results:
        if "error" in entry:
            lines.append(f"{entry['sequence']}: failed: {entry['error']}")
            continue
        for group, verdicts in entry.get("targets", {}).items():
            cells = ", ".join(
                f"{name} {'yes' if v is True else 'NO' if v is False else v}" for name, v in verdicts.items()
            )
            lines.append(f"{entry['sequence']} ({group}): {cells}")
    return "\n".join(lines)
