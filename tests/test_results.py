"""benchmarks/results/*.json record commands that can be run today: every flag a recorded command gives is one its
script defines, and every config field it sets (--config.FIELD, --set=FIELD=..., an "overrides" list) is one of
neld_jax.config.defaults(). A record whose options the code does not have says why under "historical"; its
commands are not checked."""

import ast
import functools
import glob
import json
import os
import re

import pytest

from neld_jax import config as presets

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = sorted(glob.glob(os.path.join(REPO, "benchmarks", "results", "*.json")))
COMMAND_KEYS = ("command", "commands")
FLAG = re.compile(r"^\[?--([A-Za-z_][\w.]*)(?:=(\S*))?")
PLACEHOLDER = re.compile(r"^([A-Z_]+|\.\.\.)$")  # --set=OVERRIDE, --set=... in a command's template


def _field_paths(c, prefix: str = "") -> set:
    """Every field of a config and every group, dotted: {"train", "train.steps", ...}."""
    out = set()
    for key, value in c.items():
        out.add(prefix + key)
        if hasattr(value, "items"):
            out |= _field_paths(value, f"{prefix}{key}.")
    return out


FIELDS = _field_paths(presets.defaults())


def _local_modules(tree: ast.AST, path: str) -> list:
    """The files of the modules a script imports from this repository: neld_jax.commands.* and its own folder's."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    files = []
    for name in names:
        if name.startswith("neld_jax.commands"):
            files.append(os.path.join(REPO, *name.split(".")) + ".py")
        elif os.path.isfile(os.path.join(os.path.dirname(path), name + ".py")):
            files.append(os.path.join(os.path.dirname(path), name + ".py"))
    return files


@functools.lru_cache(maxsize=None)
def script_flags(path: str) -> frozenset:
    """The flags a script takes: its absl DEFINE_* calls, those of the local modules it imports, "config" where it
    parses a config file; a shell script takes those of the Python script it runs."""
    text = open(path).read()
    if path.endswith(".sh"):
        return frozenset().union(
            *(script_flags(os.path.join(REPO, p)) for p in re.findall(r"python3?\s+(\S+\.py)", text))
        )
    tree = ast.parse(text)
    flags = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            if name.startswith("DEFINE_") and node.args and isinstance(node.args[0], ast.Constant):
                flags.add(node.args[0].value)
            elif name == "main_with_config":
                flags.add("config")
    for module in _local_modules(tree, path):
        flags |= script_flags(module)
    return frozenset(flags)


def script_of(token: str) -> str | None:
    """The script a command's word runs: benchmarks/x.py, bin/x.py, benchmarks/x.sh or an installed neld-x."""
    if token.startswith("neld-"):
        return os.path.join(REPO, "neld_jax", "commands", token[len("neld-") :].replace("-", "_") + ".py")
    if token.endswith((".py", ".sh")) and os.path.isfile(os.path.join(REPO, token)):
        return os.path.join(REPO, token)
    return None


def command_problems(command: str, script: str | None = None) -> list:
    """What in one recorded command line does not exist today (empty: every flag and field does)."""
    problems = []
    for word in command.split():
        script = script_of(word) or script
        match = FLAG.match(word)
        if not match:
            continue
        name, value = match.group(1), (match.group(2) or "").rstrip("]")
        if script is None:
            problems.append(f"--{name}: no script named before it")
            continue
        flags = script_flags(script)
        here = os.path.relpath(script, REPO)
        if name.startswith("config.") and "config" in flags:
            if name[len("config.") :] not in FIELDS:
                problems.append(f"{here}: --{name}: the config has no such field")
        elif name not in flags and not (name.startswith("no") and name[2:] in flags):
            problems.append(f"{here}: --{name}: no such flag")
        elif name == "set" and not PLACEHOLDER.match(value) and value.split("=", 1)[0] not in FIELDS:
            problems.append(f"{here}: --set={value}: the config has no such field")
    return problems


def default_script(result_file: str) -> str | None:
    """The benchmark a results file without a named script comes from (an "argv" list): the longest
    benchmarks/NAME.py whose NAME begins the file's name."""
    stem = os.path.basename(result_file)
    names = [os.path.basename(p)[:-3] for p in glob.glob(os.path.join(REPO, "benchmarks", "*.py"))]
    names = sorted((n for n in names if stem.startswith(n)), key=len)
    return os.path.join(REPO, "benchmarks", names[-1] + ".py") if names else None


def record_problems(record, result_file: str, where: str = "") -> list:
    """Every problem of the commands, argv lists and overrides in a results record, outside "historical" ones."""
    if isinstance(record, list):
        return [p for i, item in enumerate(record) for p in record_problems(item, result_file, f"{where}/{i}")]
    if not isinstance(record, dict) or "historical" in record:
        return []
    problems = []
    for key, value in record.items():
        at = f"{where}/{key}"
        if key in COMMAND_KEYS:
            texts = [value] if isinstance(value, str) else list(value.values() if isinstance(value, dict) else value)
            problems += [f"{at}: {p}" for text in texts for p in command_problems(text)]
        elif key == "argv":
            problems += [f"{at}: {p}" for p in command_problems(" ".join(value), default_script(result_file))]
        elif key == "overrides":
            problems += [
                f"{at}: {item}: the config has no such field" for item in value if item.split("=", 1)[0] not in FIELDS
            ]
        else:
            problems += record_problems(value, result_file, at)
    return problems


@pytest.mark.parametrize("result_file", RESULTS, ids=os.path.basename)
def test_every_recorded_command_uses_options_that_exist(result_file):
    with open(result_file) as f:
        record = json.load(f)
    assert record_problems(record, result_file) == []


def test_the_check_finds_a_flag_or_field_that_does_not_exist():
    assert RESULTS, "no results files found"
    assert command_problems("python benchmarks/long_route.py --parts=accuracy --start=crisper --set=seed=1") == []
    assert command_problems("neld-train --config=configs/demo.py --config.train.steps=5 --config.max_minutes=0") == []
    assert command_problems("bash benchmarks/real_gpu.sh --names=a --set=OVERRIDE [--set=...]") == []
    assert command_problems("python benchmarks/long_route.py --init_poses=crisper")
    assert command_problems("python benchmarks/accuracy.py --set=train.max_minutes=0")
    assert command_problems("python bin/train.py --config=configs/demo.py --config.data.pose_file=x.txt")
    assert command_problems("--steps=3")  # no script to check it against
    historical = {"runs": [{"historical": "why", "overrides": ["train.gone=1"]}, {"overrides": ["train.gone=1"]}]}
    assert record_problems(historical, "x.json") == ["/runs/1/overrides: train.gone=1: the config has no such field"]
