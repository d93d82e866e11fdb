#!/usr/bin/env python
"""Peak resident memory and wall time of the own-data command on a long raw recording.

    python benchmarks/memory.py --sweeps=300,1000 --beams=128 --columns=1024 --work_dir=/tmp/memory \\
        --out=benchmarks/results/memory_cpu.json
    python benchmarks/memory.py --sweeps=300 --repo=/path/to/another/checkout --label=before   # the same, older code
    python benchmarks/memory.py --sweeps=250,500,1000,2000 --beams=64 --columns=1024 --sweeps_per_lap=500 \
        --max_minutes=0 --set=train.steps=300 --work_dir=/tmp/cost --out=<json>      # the cost curve

For each size it writes a synthetic 10 Hz recording of raw sweeps to WORK_DIR/sweeps_<S> in the generic layout
without poses (scans/<stamp>.pcd, point_times/<stamp>.npy, gt_poses.txt), one sweep at a time (never the whole
recording in memory): the sensor rounds the synthetic courtyard's loop once over the recording, each column cast
from where the sensor is at its instant (neld_jax.synthetic.generator's per-sweep functions); with --sweeps_per_lap
it rounds the loop once every that many sweeps instead, at the same speed at every size, so that the keyframes and
the revisits grow with the recording as they do on a long one. Then it runs

    python bin/train.py --config=configs/generic.py:cpu --config.data.root=WORK_DIR/sweeps_<S> \\
        --config.output_dir=WORK_DIR/run_<S> --config.max_minutes=M

in a subprocess (from --repo, its code on PYTHONPATH) and polls the resident memory of it and its children every
POLL_S: the peak of their sum over the run and over its load (step 1: the sweeps read, KISS-ICP, the keyframes),
the wall time, what the log reports (KISS-ICP's seconds, the keyframes) and what the run answered (its
metrics.json: steps, start, whose poses the answer holds, the crispness margins, every sweep's ATE per method, each
step's seconds). With several sizes, the cost curve: each step's seconds a sweep at every size, and at the largest
over the smallest (`curve`; linear growth keeps it near 1). One JSON object on stdout (and in --out).
"""

import collections
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import numpy as np
from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
POLL_S = 0.2
RATE_HZ = 10.0

SWEEPS = flags.DEFINE_list("sweeps", ["300"], "Recording sizes (sweeps) to measure, each its own recording.")
BEAMS = flags.DEFINE_integer("beams", 128, "Beams of the simulated spinning LiDAR.")
COLUMNS = flags.DEFINE_integer("columns", 1024, "Columns (firings per turn) of the simulated LiDAR.")
WORK_DIR = flags.DEFINE_string("work_dir", "/tmp/neld_memory", "Recordings and run folders go here.")
CODE = flags.DEFINE_string("repo", REPO, "The checkout whose bin/train.py runs (e.g. an older one, to compare).")
LABEL = flags.DEFINE_string("label", "", "A name for this code in the JSON (e.g. before / after).")
MAX_MINUTES = flags.DEFINE_float("max_minutes", 3.0, "config.max_minutes of each run (the clock of training).")
GENERATE_ONLY = flags.DEFINE_bool("generate_only", False, "Write the recordings and stop.")
SEED = flags.DEFINE_integer("seed", 0, "The synthetic scene's and route's seed.")
SWEEPS_PER_LAP = flags.DEFINE_integer(
    "sweeps_per_lap", 0, "Sweeps the sensor takes to round the loop once (0: the whole recording is one lap)."
)
OVERRIDES = harness.overrides_flag("train.steps=300")


def write_recording(root: Path, num_sweeps: int, beams: int, columns: int, seed: int, sweeps_per_lap: int) -> dict:
    """A 10 Hz raw recording of num_sweeps sweeps in the generic layout, written one sweep at a time, the loop
    rounded once every sweeps_per_lap sweeps; returns its size (points, bytes on disk, seconds)."""
    from neld_jax.data.generic import POINT_TIMES_FOLDER
    from neld_jax.data.poses import write_tum
    from neld_jax.data.scans import write_scan
    from neld_jax.synthetic import generator

    defaults = generator.synthetic_defaults()
    started = time.perf_counter()
    scene, _ = generator.make_scene(seed, defaults.scene_size_m, path_radius_m=defaults.trajectory_radius_m)
    directions = generator.spinning_lidar_directions(beams, generator.FOV_DEG[1], generator.FOV_DEG[0], columns)
    rng = np.random.default_rng(seed + 2)
    column_fraction = np.arange(columns) / columns
    (root / "scans").mkdir(parents=True, exist_ok=True)
    (root / POINT_TIMES_FOLDER).mkdir(exist_ok=True)
    stamps, points_written = np.arange(num_sweeps) / RATE_HZ, 0
    for i, stamp in enumerate(stamps):
        column_poses = generator.loop_poses((i + column_fraction) / sweeps_per_lap, defaults.trajectory_radius_m, seed)
        points, column = generator.cast_sweep(
            scene, column_poses, directions, defaults.max_range_m, defaults.range_noise_m, rng
        )
        write_scan(root / "scans" / f"{stamp:.9f}.pcd", points)
        np.save(root / POINT_TIMES_FOLDER / f"{stamp:.9f}.npy", (column_fraction[column] / RATE_HZ).astype(np.float32))
        points_written += len(points)
    lapped = generator.loop_poses(np.arange(num_sweeps) / sweeps_per_lap, defaults.trajectory_radius_m, seed)
    write_tum(root / "gt_poses.txt", stamps, lapped)
    disk = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    return {
        "points": int(points_written),
        "disk_gb": round(disk / 1e9, 3),
        "seconds": round(time.perf_counter() - started, 1),
    }


def tree_rss(process) -> int:
    """Resident bytes of a psutil process and its children, 0 once it is gone."""
    import psutil

    total = 0
    for p in [process] + process.children(recursive=True):
        try:
            total += p.memory_info().rss
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total


def stage_times(log: str) -> dict:
    """Seconds of the stages the run's log reports."""
    found = {}
    match = re.search(r"KISS-ICP odometry: \d+ scans in ([\d.]+) s", log)
    if match:
        found["kiss_icp_s"] = float(match.group(1))
    match = re.search(r"keyframes: kept (\d+) of (\d+) scans", log)
    if match:
        found["keyframes"], found["scans"] = int(match.group(1)), int(match.group(2))
    return found


def load_peak_gb(samples: list[tuple[float, int]], log: str) -> float | None:
    """The peak of samples [(time.time(), bytes)] up to the log line that ends the load (step 1: keyframes made,
    "neld_jax.run: budget ..."), in GB; None when the log has no such line."""
    import datetime

    match = re.search(r"^(\d\d):(\d\d):(\d\d) INFO neld_jax\.run: budget", log, re.MULTILINE)
    if match is None or not samples:
        return None
    start = datetime.datetime.fromtimestamp(samples[0][0])
    end = start.replace(hour=int(match.group(1)), minute=int(match.group(2)), second=int(match.group(3)))
    if end < start - datetime.timedelta(minutes=1):  # the run passed midnight
        end += datetime.timedelta(days=1)
    until = end.timestamp() + 1.0
    return round(max((rss for t, rss in samples if t <= until), default=0) / 1e9, 3)


def run_outcome(out_dir: Path) -> dict:
    """What the run's metrics.json says it did: steps, start, answer, the margins (its answer's mean map entropy
    minus each other method's, mean and whether every draw agrees) and every sweep's ATE [m] per method."""
    metrics = json.loads((out_dir / "metrics.json").read_text())
    r = metrics["run"]
    methods = metrics.get("evaluation", {}).get("methods", {})
    return {
        "steps": r["steps"],
        "started_from": r["started_from"],
        "answer": r.get("answer"),
        "crispness_margin": {
            other: {"mean": m["mean"], "all_draws_agree": m["all_draws_agree"]}
            for other, m in r["crispness_margin"].items()
        },
        "ate_m": {name: round(m["ate"]["translation_rmse_m"], 5) for name, m in methods.items() if "ate" in m},
        "stage_seconds": r.get("stage_seconds", {}),
        "flags": dict(collections.Counter(row["flag"] for row in metrics["scans_report"]["flagged"])),
    }


def cost_curve(sizes: dict) -> dict:
    """Each step's seconds a sweep at every size ({sweeps: run_command's result}) and its largest size's over its
    smallest's: {stage: {"s_per_sweep": {sweeps: s}, "largest_over_smallest": ratio}}."""
    measured = {int(n): size["run"]["stage_seconds"] for n, size in sizes.items() if size.get("run")}
    if len(measured) < 2:
        return {}
    smallest, largest = min(measured), max(measured)
    curve = {}
    for stage in measured[smallest]:
        per_sweep = {n: round(stages.get(stage, float("nan")) / n, 5) for n, stages in sorted(measured.items())}
        low = per_sweep[smallest]
        curve[stage] = {
            "s_per_sweep": {str(n): s for n, s in per_sweep.items()},
            "largest_over_smallest": round(per_sweep[largest] / low, 3) if low > 0 else None,
        }
    return curve


def run_command(root: Path, out_dir: Path, repo: str, max_minutes: float, overrides: list) -> dict:
    """Run the own-data command on root (overrides: KEY=VALUE config overrides); its peak resident memory (GB, the
    process tree's sum), wall time and stages."""
    import psutil

    command = [
        sys.executable,
        "bin/train.py",
        "--config=configs/generic.py:cpu",
        f"--config.data.root={root}",
        f"--config.output_dir={out_dir}",
        f"--config.max_minutes={max_minutes}",
        "--restart",
        *(f"--config.{override}" for override in overrides),
    ]
    env = dict(os.environ, PYTHONPATH=repo)
    log_path = out_dir.parent / f"{out_dir.name}.log"
    started, samples = time.perf_counter(), []
    with open(log_path, "w") as log:
        child = subprocess.Popen(command, cwd=repo, env=env, stdout=log, stderr=subprocess.STDOUT)
        process = psutil.Process(child.pid)
        while child.poll() is None:
            samples.append((time.time(), tree_rss(process)))
            time.sleep(POLL_S)
    wall = time.perf_counter() - started
    peak = max((rss for _, rss in samples), default=0)
    text = log_path.read_text(errors="replace")
    if child.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({child.returncode}); its log: {log_path}\n{text[-2000:]}")
    return {
        "peak_rss_gb": round(peak / 1e9, 3),
        "load_peak_rss_gb": load_peak_gb(samples, text),
        "wall_s": round(wall, 1),
        **stage_times(text),
        "run": run_outcome(out_dir),
        "command": " ".join(command),
        "log": str(log_path),
    }


def main(argv):
    del argv
    work = Path(WORK_DIR.value)
    sizes = {}
    for sweeps in (int(s) for s in SWEEPS.value):
        lapped = f"_lap{SWEEPS_PER_LAP.value}" if SWEEPS_PER_LAP.value else ""
        root = work / f"sweeps_{sweeps}_{BEAMS.value}x{COLUMNS.value}{lapped}"
        if not (root / "gt_poses.txt").is_file():
            lap = SWEEPS_PER_LAP.value or sweeps
            recording = write_recording(root, sweeps, BEAMS.value, COLUMNS.value, SEED.value, lap)
            (root / "recording.json").write_text(json.dumps(recording))
        recording = json.loads((root / "recording.json").read_text())
        print(f"{sweeps} sweeps: {recording}", file=sys.stderr, flush=True)
        if GENERATE_ONLY.value:
            sizes[str(sweeps)] = {"recording": recording}
            continue
        out_dir = work / f"run_{sweeps}_{LABEL.value or 'code'}"
        measured = run_command(root, out_dir, CODE.value, MAX_MINUTES.value, OVERRIDES.value)
        print(f"{sweeps} sweeps: {measured}", file=sys.stderr, flush=True)
        sizes[str(sweeps)] = {"recording": recording, **measured}
    result = {
        "benchmark": "memory",
        "label": LABEL.value,
        "repo": CODE.value,
        "beams": BEAMS.value,
        "columns": COLUMNS.value,
        "rate_hz": RATE_HZ,
        "max_minutes": MAX_MINUTES.value,
        "sweeps_per_lap": SWEEPS_PER_LAP.value,
        "overrides": OVERRIDES.value,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "sizes": sizes,
        "curve": cost_curve(sizes),
    }
    print(json.dumps(result, indent=2))
    harness.write(harness.OUT.value, result)


if __name__ == "__main__":
    app.run(main)
