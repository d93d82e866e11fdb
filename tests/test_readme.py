"""README.md keeps its promises: the two commands in its first 40 lines, at most 250 lines, its library example
runs as written (three steps instead of the budget's), and every measured figure it quotes is the one in its results
file under benchmarks/results/, rounded as the README rounds it."""

import json
import os
import re

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _readme() -> str:
    return open(os.path.join(REPO, "README.md")).read()


def test_the_two_commands_are_in_the_first_40_lines():
    head = "\n".join(_readme().splitlines()[:40])
    assert "bash scripts/setup.sh && python bin/train.py --config=configs/demo.py" in head
    assert "bash scripts/setup.sh && python -m pytest -q" in head
    assert len(_readme().splitlines()) <= 250


def test_the_library_example_runs():
    code = re.search(r"```python\n(.*?)```", _readme(), re.S).group(1)
    code = code.replace("range(config.train.steps)", "range(3)")
    code = code.replace(
        "make_sequence(config.data.synthetic)",
        'make_sequence({"num_scans": 3, "num_beams": 8, "num_columns": 64, "gt_map_points": 0, '
        '"scene_size_m": 30.0, "trajectory_radius_m": 5.0, "max_range_m": 30.0})',
    )
    assert code.count("range(3)") == 1 and "num_scans" in code  # the example still has the lines replaced
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert scope["T_refined"].shape == (3, 4, 4) and int(scope["state"].step) == 3


# Every measured figure the README quotes, with the results file it comes from (benchmarks/results/) and how the
# README rounds it. A row of the demo's table: (the row's first words, its column, file, key path, format).
RESULTS = os.path.join(REPO, "benchmarks", "results")
DEMO_TABLE = [
    ("initial", 1, "demo_cpu.json", "initial.ate_rmse_m", "{:.3f}"),
    ("initial", 2, "demo_cpu.json", "initial.rot_rmse_deg", "{:.2f}"),
    ("initial", 3, "demo_cpu.json", "initial.raw_map_chamfer_l1_m", "cm1"),
    ("initial", 4, "demo_cpu.json", "initial.entropy|initial.thickness_cm", "{:.3f} / {:.2f}"),
    ("classical baseline", 1, "accuracy_easy_from_baseline_cpu.json", "result.baseline.ate_rmse_m", "{:.5f}"),
    ("classical baseline", 2, "accuracy_easy_from_baseline_cpu.json", "result.baseline.rot_rmse_deg", "{:.4f}"),
    ("**NeLD-BA** (", 1, "demo_cpu.json", "neld_ba.ate_rmse_m", "{:.4f}"),
    ("**NeLD-BA** (", 2, "demo_cpu.json", "neld_ba.rot_rmse_deg", "{:.3f}"),
    ("**NeLD-BA** (", 3, "demo_cpu.json", "neld_ba.raw_map_chamfer_l1_m", "cm1"),
    ("**NeLD-BA** (", 4, "demo_cpu.json", "neld_ba.entropy|neld_ba.thickness_cm", "{:.3f} / {:.2f}"),
    ("**NeLD-BA** (", 5, "demo_cpu.json", "neld_ba.rendered_map_f1", "percent1"),
    ("**NeLD-BA from", 1, "accuracy_easy_from_baseline_cpu.json", "result.neld_ba.ate_rmse_m", "{:.5f}"),
    ("**NeLD-BA from", 2, "accuracy_easy_from_baseline_cpu.json", "result.neld_ba.rot_rmse_deg", "{:.4f}"),
    ("**NeLD-BA from", 3, "accuracy_easy_from_baseline_cpu.json", "result.neld_ba.raw_map_chamfer_l1_m", "cm1"),
    ("**NeLD-BA from", 5, "accuracy_easy_from_baseline_cpu.json", "result.neld_ba.rendered_map_f1", "percent1"),
]
NUMBER_WORDS = {5: "five", 6: "six"}


def _result(file: str, path: str):
    with open(os.path.join(RESULTS, file)) as f:
        value = json.load(f)
    for key in path.split("."):
        value = value[int(key)] if isinstance(value, list) else value[key]
    return value


def _formatted(file: str, paths: str, form: str) -> str:
    values = [_result(file, path) for path in paths.split("|")]
    if form == "cm1":
        return f"{100 * values[0]:.1f}"
    if form == "percent1":
        return f"{100 * values[0]:.1f} %"
    return form.format(*values)


def _table_cell(readme: str, row_start: str, column: int) -> str:
    rows = [line for line in readme.splitlines() if line.startswith("| " + row_start)]
    assert len(rows) == 1, f"README: {len(rows)} table rows start with {row_start!r}"
    return rows[0].strip("|").split("|")[column].strip().strip("*")


def _peers():
    """The peers' benchmark: NeLD-BA's whole-run minutes and its ATE over KISS-ICP's, per sequence."""
    sequences = _result("peers_cpu.json", "sequences")
    minutes = [s["methods"]["neld_ba"]["wall_s"] / 60 for s in sequences]
    ratios = [s["methods"]["neld_ba"]["ate_m"] / s["methods"]["kiss_icp"]["ate_m"] for s in sequences]
    return minutes, ratios


def _real_recordings():
    """The six recordings end to end on the cpu budget: minutes, crisper than the odometry, crisper than the
    baseline on every draw."""
    runs = [s["recorded"]["crisper"] for s in _result("real_data_cpu_handheld.json", "sequences")]
    out = [
        (
            r["wall_s"] / 60,
            r["crispness_margin"]["initial"]["mean"] < 0,
            r["crispness_margin"]["baseline"]["mean"] < 0 and r["crispness_margin"]["baseline"]["all_draws_agree"],
        )
        for r in runs
    ]
    for part in ("recorded_281", "recorded_331"):
        r = _result("real_data_cpu_riverside02.json", part)
        e = r["entropy_thickness"]
        margin = r["margin_vs_baseline"]
        out.append(
            (
                r["total_seconds"] / 60,
                e["optimized"][0] < e["initial"][0],
                margin["mean"] < 0 and margin["all_draws_agree"],
            )
        )
    return out


def _prose_figures() -> list:
    """(the README's words with the figures in them, as the results files give them)."""
    minutes, ratios = _peers()
    recordings = _real_recordings()
    run_minutes = [m for m, _, _ in recordings]
    long_runs = [r["total_seconds"] / 60 for r in _result("real_data_cpu_6000_steps.json", "end_to_end_alone").values()]
    gpu = [r["training"]["train_seconds"] for r in _result("real_data_gpu.json", "runs") if r["name"] != "hard"]
    visits = [
        [100 * v["ate_shared_alignment_m"] for v in _result(file, "merged.visits")]
        for file in ("sessions_cpu.json", "sessions_merged_3000_steps_cpu.json")
    ]
    alone = [100 * a["ate_m"] for a in _result("sessions_cpu.json", "alone")]
    return [
        f"the whole run takes {min(minutes):.1f}-{max(minutes):.1f} minutes on 2 cores",
        f"ends at {min(ratios):.2f}-{max(ratios):.2f}x KISS-ICP's",
        f"each run takes {min(run_minutes):.1f}-{max(run_minutes):.1f} minutes end to end on 2 cores",
        f"crisper than the odometry's on all {NUMBER_WORDS[sum(c for _, c, _ in recordings)]} and than the classical "
        f"baseline's on {NUMBER_WORDS[sum(b for _, _, b in recordings)]}",
        f"take {min(long_runs):.0f}-{max(long_runs):.0f} minutes and give crisper maps",
        f"its training took {min(gpu):.0f}-{max(gpu):.0f} s on the real recordings",
        "two synthetic visits: {:.3f} / {:.3f} cm at 1500 steps, {:.3f} / {:.3f} cm at 3000, {:.3f} / {:.3f} cm "
        "alone".format(*visits[0], *visits[1], *alone),
    ]


def test_the_demo_table_quotes_the_results_files():
    readme = _readme()
    wrong = [
        (row, column, _table_cell(readme, row, column), _formatted(file, path, form))
        for row, column, file, path, form in DEMO_TABLE
        if _table_cell(readme, row, column) != _formatted(file, path, form)
    ]
    assert wrong == [], "README cell != results file: " + repr(wrong)


def test_the_figures_in_the_text_quote_the_results_files():
    text = " ".join(_readme().split())
    missing = [words for words in _prose_figures() if words not in text]
    assert missing == [], f"README lacks (or rounds otherwise): {missing}"
