"""What every benchmark shares: its common flags, the machine stamp, and one JSON schema for what it writes.

A benchmark script imports this module (`import harness`: this folder's benchmarks/harness.py, beside the script) and

- takes `--out` from it (the JSON file written; a script may give it another default with `harness.default_out`),
  and `--set=KEY=VALUE` config overrides from `harness.overrides_flag()` where it runs the package's config;
- writes its JSON with `harness.write(path, results)`: one record in the schema below;
- reads a benchmark's JSON (its own, or another's) with `harness.load(path)`, which gives back the payload.

The schema (SCHEMA_VERSION 1), the top-level keys of every file a benchmark writes:

    benchmark   the script's name ("peers" for benchmarks/peers.py)
    command     the command line that reproduces it, from the repository root (`python benchmarks/peers.py ...`)
    machine     the stamp: CPU model, cores, memory, load average, Python / jax / jaxlib / numpy versions, the JAX
                devices, the date (UTC) and the code's git commit
    results     the script's own payload, as it was before the schema (downstream code and tests read it)
    schema      SCHEMA_VERSION

Files in benchmarks/results/ written before the schema have no "results" key: `load` gives them back whole.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys

from absl import flags

SCHEMA_VERSION = 1
SCHEMA_KEYS = ("benchmark", "command", "machine", "results", "schema")
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

OUT = flags.DEFINE_string(
    "out", "", "The JSON file written, in the benchmarks' schema (benchmarks/harness.py); none if empty."
)


def default_out(path: str) -> None:
    """Give `--out` this script's default (call at import, in the script run as __main__)."""
    flags.FLAGS.set_default("out", path)


def overrides_flag(example: str = "train.steps=2000"):
    """`--set=KEY=VALUE` (repeatable): overrides of the package's config, applied by neld_jax.config.apply_overrides."""
    return flags.DEFINE_multi_string("set", [], f"Config overrides KEY=VALUE (Python literal), e.g. {example}")


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def _git_commit() -> str | None:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + (" (modified)" if dirty.stdout.strip() else "")


def _versions() -> dict:
    versions = {"python": platform.python_version()}
    for name in ("jax", "jaxlib", "numpy"):
        try:
            versions[name] = __import__(name).__version__
        except ImportError:
            versions[name] = None
    return versions


def _devices() -> list | None:
    """The JAX devices ("cpu:cpu", "gpu:NVIDIA H200"), where the script has imported jax (it is not imported here)."""
    jax = sys.modules.get("jax")
    if jax is None:
        return None
    try:
        return [f"{d.platform}:{d.device_kind}" for d in jax.devices()]
    except RuntimeError:
        return None


def machine() -> dict:
    """The machine stamp: what ran it, how loaded, with which versions, when (UTC) and which code."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    load = [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "memory_gib": _memory_gib(),
        "load_average": load,
        **_versions(),
        "devices": _devices(),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "git_commit": _git_commit(),
    }


def command(argv: list | None = None) -> str:
    """The command line that reproduces this run from the repository root: `python benchmarks/NAME.py ARGS`."""
    argv = sys.argv if argv is None else argv
    script = os.path.relpath(os.path.abspath(argv[0]), REPO)
    return " ".join(["python", script, *(shlex.quote(a) for a in argv[1:])])


def benchmark_name(argv: list | None = None) -> str:
    return os.path.splitext(os.path.basename((sys.argv if argv is None else argv)[0]))[0]


def record(results, benchmark: str | None = None, argv: list | None = None) -> dict:
    """One record in the schema around a script's payload."""
    return {
        "benchmark": benchmark or benchmark_name(argv),
        "command": command(argv),
        "machine": machine(),
        "results": results,
        "schema": SCHEMA_VERSION,
    }


def write(
    path: str, results, benchmark: str | None = None, argv: list | None = None, stamped: dict | None = None
) -> dict:
    """Write `results` in the schema to `path` (folders made; nothing written if `path` is empty) and return the
    record. A script that writes as it goes passes the record of its first write as `stamped`: the machine stamp
    then stays the one from the start, the date included."""
    out = dict(stamped, results=results) if stamped else record(results, benchmark, argv)
    if path:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, "w") as f:
            json.dump(out, f, indent=1)
            f.write("\n")
    return out


def is_record(data) -> bool:
    return isinstance(data, dict) and "results" in data and "benchmark" in data and "schema" in data


def load(path: str):
    """A benchmark's payload from its JSON file: the "results" of a record in the schema, or an older file whole."""
    with open(path) as f:
        data = json.load(f)
    return data["results"] if is_record(data) else data
