#!/usr/bin/env python
"""What registering every input scan to the result gains (neld_jax.steps.registration): ATE against the ground truth
over every sweep, over the keyframes and over the other sweeps, and the raw map of every sweep's crispness, for the
odometry (the run's input), the keyframes' interpolated corrections (what every other sweep had before), and every
sweep registered to the keyframes' refined map; and the registration's time: in all, the map's build (its normals
and search structure, once a map) and each sweep's (s_per_sweep: read, cropped, gridded, registered, judged), with
the machine's 1-minute load before and after (timings are upper bounds on a shared machine).

    neld-make-synthetic --config=configs/demo.py --root=/tmp/sweeps --rate_hz=10 \\
        --config.data.synthetic.num_scans=300 --config.data.synthetic.max_range_m=40
    neld-train --config=configs/generic.py:cpu --config.data.root=/tmp/sweeps --config.output_dir=/tmp/sweeps_run \\
        --config.data.initial_poses=kiss_icp
    python benchmarks/every_scan.py --runs=/tmp/sweeps_run --out=/tmp/every_scan.json

Each run folder is a finished run with ground truth (its config.json names the sequence, which is loaded again as
the run loaded it). The keyframes' refined poses are read from its poses_optimized.txt; the registration is run
again here from them (and timed), the interpolation recomputed. The target: ATE over
every sweep at most 1.2 x the keyframes' ATE.
"""

import json
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import numpy as np
from absl import app, flags


def ate_cm(T: np.ndarray, gt: np.ndarray) -> float:
    from neld_jax.judging.metrics import ate

    return round(100 * ate(T, gt)["translation_rmse_m"], 3)


def figures(T: np.ndarray, loaded, keyframe: np.ndarray, radius_m: float) -> dict:
    """ATE [cm] over every sweep, the keyframes and the others; the raw map of every sweep's mean map entropy."""
    from neld_jax.geometry import register_scans
    from neld_jax.judging.crispness import crispness

    gt = loaded.gt_poses
    summary = crispness(register_scans(loaded.scans, T), radius=radius_m, max_queries=20_000, seed=0).summary()
    return {
        "ate_every_sweep_cm": ate_cm(T, gt),
        "ate_keyframes_cm": ate_cm(T[keyframe], gt[keyframe]),
        "ate_other_sweeps_cm": ate_cm(T[~keyframe], gt[~keyframe]),
        "entropy_every_sweep": round(summary["mean_map_entropy"], 4),
        "thickness_every_sweep_cm": round(100 * summary["mean_plane_thickness_m"], 3),
    }


def measure(run_dir: str) -> dict:
    import ml_collections

    from neld_jax.data.poses import read_tum
    from neld_jax.steps import registration
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.trajectory import propagate_corrections
    from neld_jax.writing.export import read_json

    config = ml_collections.ConfigDict(read_json(f"{run_dir}/config.json"))
    loaded, keyframes = load_keyframes(config.data)
    keyframe = np.zeros(loaded.num_scans, bool)
    keyframe[keyframes.loaded_index] = True
    _, written = read_tum(f"{run_dir}/poses_optimized.txt")
    refined = written[keyframes.loaded_index]
    interpolated = propagate_corrections(loaded.poses, keyframes.loaded_index, refined, loaded.timestamps)
    settings = registration.RegistrationSettings.from_groups(config.data, config.baseline)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    registered = registration.register_every_scan(loaded, keyframes, refined, settings)
    seconds = time.perf_counter() - t0
    load_after = os.getloadavg()[0]
    t0 = time.perf_counter()  # the map and its search structure again, alone: built once a map, not a sweep
    registration.map_index(registration.map_cloud(keyframes.scans, refined, settings))
    map_seconds = time.perf_counter() - t0
    radius = float(config.eval.crispness_radius_m)
    entry = {
        "run": run_dir,
        "input_scans": loaded.num_scans,
        "keyframes": keyframes.num_scans,
        "num_registered": int(registered.registered.sum()),
        "num_refused": int(sum(map(bool, registered.flag))),
        "registration_s": round(seconds, 1),
        "map_s": round(map_seconds, 1),
        # each sweep tried: read from disk, cropped, gridded, registered and judged (the map's build left out)
        "s_per_sweep": round((seconds - map_seconds) / max(int(registered.tried.sum()), 1), 4),
        "load_average_1min": [round(load_before, 2), round(load_after, 2)],
        "median_residual_cm": round(100 * float(np.nanmedian(registered.residual_m)), 3),
    }
    for name, poses in (("odometry", loaded.poses), ("interpolated", interpolated), ("registered", registered.poses)):
        entry[name] = figures(poses, loaded, keyframe, radius)
    after = entry["registered"]
    entry["every_sweep_over_keyframes"] = round(after["ate_every_sweep_cm"] / after["ate_keyframes_cm"], 3)
    entry["target_met"] = entry["every_sweep_over_keyframes"] <= 1.2
    return entry


RUNS = flags.DEFINE_list("runs", [], "Finished run folders with ground truth.")


def main(argv) -> None:
    del argv
    if not RUNS.value:
        raise app.UsageError("--runs: name at least one finished run folder")
    entries = [measure(run_dir) for run_dir in RUNS.value]
    print(json.dumps(entries, indent=1))
    harness.write(harness.OUT.value, entries)  # one entry per run


if __name__ == "__main__":
    app.run(main)
