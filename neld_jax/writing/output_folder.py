"""The output folder of a run (config.output_dir) and what a rerun into it does (docs/design.md, "Resume").

A run writes its configuration to config.json before anything else, once. A rerun into a folder that holds one
compares its configuration with it before it writes or computes anything:
- the same (every field but those in UNCOMPARED): the run resumes from the folder's checkpoint and saved start;
- another: one ConfigError naming the fields that differ, and the folder is left exactly as it was;
- restart (neld-train --restart): the earlier run's files (RUN_FILES) are deleted, the log naming them, and the run
  starts over.
"""

from __future__ import annotations

import glob
import json
import logging
import os
import shutil
from typing import Any

import ml_collections

from neld_jax.errors import ConfigError
from neld_jax.jsonable import to_jsonable
from neld_jax.writing.export import read_json, write_json

logger = logging.getLogger(__name__)

CONFIG_FILE = "config.json"
# The seconds of the run's processes so far ({"seconds": s}), so that metrics.json's total_seconds spans a resume
# as train_seconds does: written at each checkpoint and at the run's end, read when a process starts.
CLOCK_FILE = "run_seconds.json"
# Where the run writes and how it is watched (run.rrd, a live view): never what it computes or writes, so a rerun
# may change them and still resume. Every other field must match.
UNCOMPARED = ("output_dir", "viz")
# What neld-train (and neld-baseline, neld-evaluate) write into an output folder: what --restart deletes. Any other
# file in the folder is left alone.
RUN_FILES = (
    "config.json",
    CLOCK_FILE,
    "metrics.json",
    "history.json",
    "start_poses.npz",
    "run.rrd",
    "checkpoints",
    "scans_report.csv",
    "scans_report.png",
    "map_topdown.png",
    "trajectory.png",
    "pose_error.png",
    "error_histogram.png",
    "poses_*.txt",
    "poses_*.kitti",
    "map_*.ply",
)
MAX_LISTED = 6  # differences named in the error line


def prepare(config: ml_collections.ConfigDict, restart: bool = False) -> str:
    """The run's output folder (absolute), checked and ready: a folder of another configuration is a ConfigError
    (nothing written); restart=True deletes the earlier run's files first. Writes config.json when the folder has
    none (a resumed run keeps its first run's)."""
    out_dir = os.path.abspath(config.output_dir)
    now = to_jsonable(json.loads(config.to_json_best_effort()))  # as config.json holds it (no NaN)
    path = os.path.join(out_dir, CONFIG_FILE)
    if restart:
        delete_run_files(out_dir)
    elif os.path.isfile(path):
        differences = config_differences(read_json(path), now)
        if differences:
            raise ConfigError(refusal(path, differences))
        logger.info("%s holds the same configuration: the run resumes where the earlier one stopped", path)
    if not os.path.isfile(path):
        os.makedirs(out_dir, exist_ok=True)
        write_json(path, now, merge=False)
    return out_dir


def earlier_seconds(out_dir: str) -> float:
    """The seconds earlier processes of the run in out_dir took, up to each one's last checkpoint or end (0: none)."""
    return float(read_json(os.path.join(out_dir, CLOCK_FILE)).get("seconds", 0.0))


def record_seconds(out_dir: str, budget) -> None:
    """Record the run's seconds so far (budget: its TimeBudget, earlier processes' seconds included) in out_dir."""
    write_json(os.path.join(out_dir, CLOCK_FILE), {"seconds": round(budget.run_seconds(), 2)}, merge=False)


def config_differences(saved: dict, now: dict) -> list[str]:
    """The fields (dotted names) in which two configurations (config.json's form) differ, UNCOMPARED aside:
    ["train.steps: 12 -> 20", ...] (a field one of them lacks reads "(absent)"), sorted by name."""
    old, new = _flat(saved), _flat(now)
    names = sorted(
        name
        for name in old.keys() | new.keys()
        if not any(name == top or name.startswith(top + ".") for top in UNCOMPARED)
        and old.get(name, _ABSENT) != new.get(name, _ABSENT)
    )
    return [f"{name}: {_text(old.get(name, _ABSENT))} -> {_text(new.get(name, _ABSENT))}" for name in names]


def refusal(path: str, differences: list[str]) -> str:
    """The one line that refuses a rerun of another configuration into a run's folder."""
    listed = "; ".join(differences[:MAX_LISTED])
    more = f"; and {len(differences) - MAX_LISTED} more" if len(differences) > MAX_LISTED else ""
    return (
        f"{path} holds another configuration ({listed}{more}): set a new output_dir for this one, or rerun "
        f"neld-train with --restart to delete the earlier run's files and start over"
    )


def delete_run_files(out_dir: str) -> list[str]:
    """Delete what a run wrote into out_dir (RUN_FILES; other files stay), logging what; returns the names."""
    paths = sorted({found for pattern in RUN_FILES for found in glob.glob(os.path.join(glob.escape(out_dir), pattern))})
    if not paths:
        return []
    names = [os.path.basename(p) + ("/" if os.path.isdir(p) else "") for p in paths]
    logger.warning("--restart: deleting the earlier run's files in %s: %s", out_dir, ", ".join(names))
    for p in paths:
        if os.path.isdir(p):
            shutil.rmtree(p)
        else:
            os.remove(p)
    return names


_ABSENT = object()


def _flat(tree: dict, prefix: str = "") -> dict[str, Any]:
    """{dotted name: value} of a nested dict's leaves (an empty dict is a leaf)."""
    out = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(_flat(value, name + "."))
        else:
            out[name] = value
    return out


def _text(value: Any) -> str:
    return "(absent)" if value is _ABSENT else json.dumps(value)
