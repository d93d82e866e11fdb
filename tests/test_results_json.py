"""benchmarks/RESULTS.md quotes its JSON: every section names the files under benchmarks/results/ its figures come
from (`results/NAME.json` or `NAME.json`, a `*` matching several), and every decimal figure in its tables stands in
one of them, rounded as the table rounds it (in the unit the table gives: m, cm, mm, %, minutes). Also the
benchmarks' harness (benchmarks/harness.py): its schema, and reading old and new files alike."""

import glob
import json
import os
import re
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS_DIR = os.path.join(REPO, "benchmarks", "results")
sys.path.insert(0, os.path.join(REPO, "benchmarks"))
import harness  # noqa: E402

# A table's figure is the JSON's value times one of these: itself, m -> cm or fraction -> %, m -> mm, s -> minutes.
SCALES = (1.0, 100.0, 1000.0, 1 / 60)
FIGURE = re.compile(r"(?<![\w.])[-+]?\d+\.\d+(?![\w.])")
REFERENCE = re.compile(r"([\w*.-]+\.json)")


def _sections(text: str) -> list:
    """(heading, text) of each ## and ### section."""
    parts = re.split(r"\n(?=#{2,3} )", text)
    return [(part.splitlines()[0], part) for part in parts]


def _referenced(section: str) -> list:
    """The results files a section names (a `*` in a name matches several); a name with no file is kept, to fail."""
    files = []
    for name in REFERENCE.findall(section):
        found = sorted(glob.glob(os.path.join(RESULTS_DIR, os.path.basename(name))))
        files += found or [os.path.basename(name)]
    return sorted(set(files))


def _numbers(value, out: list) -> list:
    """Every number in a JSON value, those inside strings too ("0.0852 / 0.0560" in a note)."""
    if isinstance(value, bool) or value is None:
        return out
    if isinstance(value, (int, float)):
        out.append(float(value))
    elif isinstance(value, dict):
        for v in value.values():
            _numbers(v, out)
    elif isinstance(value, list):
        for v in value:
            _numbers(v, out)
    elif isinstance(value, str):
        out += [float(m) for m in FIGURE.findall(value)]
    return out


def _table_figures(section: str) -> list:
    """The decimal figures in a section's table bodies (header rows and code spans left out)."""
    figures = []
    lines = section.splitlines()
    for i, line in enumerate(lines):
        header = i + 1 < len(lines) and lines[i + 1].startswith("|---")
        if not line.startswith("|") or line.startswith("|---") or header:
            continue
        figures += FIGURE.findall(re.sub(r"`[^`]*`", "", line).replace(",", ""))
    return figures


def _derived(section_files: list) -> list:
    """Figures a table computes from two JSON values: the loop-closed poses' entropy minus the odometry's over the
    draws (NeLD-BA's margin to the odometry minus its margin to the loop-closed poses)."""
    out = []
    for path in section_files:
        if os.path.basename(path) == "loop_closed_poses_judged.json":
            for seq in harness.load(path)["sequences"].values():
                margins = seq["margins"]
                out.append(margins["input"]["mean"] - margins["sc_pgo"]["mean"])
    return out


def _stands_in(figure: str, values: list) -> bool:
    decimals = len(figure.split(".")[1])
    x, tol = float(figure), 0.5 * 10**-decimals + 1e-9
    return any(abs(abs(v * s) - abs(x)) <= tol for v in values for s in SCALES)


def missing_figures(text: str) -> dict:
    """{section heading: [table figures that stand in none of its JSON files, or a problem with its references]}."""
    problems = {}
    for heading, section in _sections(text):
        figures = _table_figures(section)
        if not figures:
            continue
        files = _referenced(section)
        absent = [f for f in files if not os.path.isfile(f)]
        if not files or absent:
            problems[heading] = [f"names no JSON file under benchmarks/results/ ({absent or 'none'})"]
            continue
        values = [v for path in files for v in _numbers(harness.load(path), [])] + _derived(files)
        missing = [f for f in figures if not _stands_in(f, values)]
        if missing:
            problems[heading] = missing
    return problems


def test_every_table_figure_in_results_md_stands_in_its_json():
    text = open(os.path.join(REPO, "benchmarks", "RESULTS.md")).read()
    assert sum(len(_table_figures(section)) for _, section in _sections(text)) > 300  # the check sees the tables
    assert missing_figures(text) == {}


def test_the_check_catches_a_figure_typed_by_hand():
    section = (
        "## Peers\n\nJSON: `results/peers_cpu.json`.\n\n| loop | method | ATE [m] |\n|---|---|---|\n"
        "| 10 m | KISS-ICP | {} |\n"
    )
    assert missing_figures(section.format("0.1229")) == {}  # the JSON's 0.12292..., as the table rounds it
    assert missing_figures(section.format("0.1231")) == {"## Peers": ["0.1231"]}
    unnamed = "## Train step\n\n| step ms | GFLOP/s |\n|---|---|\n| 198 | 73.6 |\n"
    assert list(missing_figures(unnamed)["## Train step"])[0].startswith("names no JSON file")


def test_harness_writes_the_schema_and_loads_old_and_new_files(tmp_path):
    out = tmp_path / "sub" / "x.json"
    argv = [os.path.join(REPO, "benchmarks", "peers.py"), "--set=train.steps=2", "--out=a b.json"]
    record = harness.write(str(out), {"sequences": [1]}, argv=argv)
    data = json.loads(out.read_text())
    assert data == record and set(data) == set(harness.SCHEMA_KEYS) and data["benchmark"] == "peers"
    assert data["command"] == "python benchmarks/peers.py --set=train.steps=2 '--out=a b.json'"
    machine = data["machine"]
    assert machine["cores"] >= 1 and machine["date_utc"].endswith(" UTC") and machine["numpy"]
    assert len(machine["load_average"]) == 3 and machine["cpu"]
    assert harness.load(str(out)) == {"sequences": [1]}
    again = harness.write(str(out), {"sequences": [1, 2]}, stamped=record)  # written as it goes: one stamp
    assert again["machine"] == record["machine"] and harness.load(str(out)) == {"sequences": [1, 2]}
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"command": "python benchmarks/peers.py", "sequences": []}))
    assert harness.load(str(old)) == {"command": "python benchmarks/peers.py", "sequences": []}
    assert harness.write("", {"a": 1}, argv=argv)["results"] == {"a": 1}  # no file without a path


@pytest.mark.parametrize("script", sorted(glob.glob(os.path.join(REPO, "benchmarks", "*.py"))), ids=os.path.basename)
def test_every_benchmark_that_writes_json_writes_it_through_the_harness(script):
    text = open(script).read()
    if os.path.basename(script) in (
        "harness.py",
        "packed_points.py",
        "real_targets.py",
        "kitti_layout.py",
        "real_gpu.py",
    ):
        return  # the harness, two helper modules, a data layout's writer, the GPU runs' own per-run file
    assert "import harness" in text
    assert "json.dump(" not in text.replace("json.dump(spec", ""), "JSON written around the harness"
