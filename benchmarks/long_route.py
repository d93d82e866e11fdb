#!/usr/bin/env python
"""The long synthetic route: submaps against one cube, and the submap step's throughput on 1-8 devices.

    python benchmarks/long_route.py                                  # the full target: 200 keyframes, 600 m
    python benchmarks/long_route.py --num_scans=66 --route_length_m=200 --steps=600   # a shortened run
    python benchmarks/long_route.py --parts=throughput --devices=1,2,4,8               # steps/s only
    python benchmarks/long_route.py --parts=accuracy --init_poses=crisper --single_cube=false

accuracy: the generic cpu budget on a synthetic `courtyards` route (data.synthetic.route), run twice on the same
sequence: with submaps (switched on by the rule, not by a flag) and as one cube (submaps.enabled=off,
data.max_extent_m=0). Prints initial / optimised ATE, seconds and the split for each.
throughput: one subprocess per device count d with XLA_FLAGS=--xla_force_host_platform_device_count=d (the flag
must be set before jax starts) timing the sharded submap step on the same M submaps; steps/s, rays/s and the
efficiency (steps/s relative to one device). On a CPU the simulated devices share the machine's cores.
One JSON object on stdout (and in --output).
"""

import json
import logging
import os
import re
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from absl import app, flags  # noqa: E402

PARTS = flags.DEFINE_list("parts", ["split", "accuracy", "throughput"], "split, accuracy and/or throughput.")
NUM_SCANS = flags.DEFINE_integer("num_scans", 200, "Keyframes of the route (one every 3 s).")
ROUTE_M = flags.DEFINE_float("route_length_m", 600.0, "Length of the closed route.")
STEPS = flags.DEFINE_integer("steps", 0, "train.steps (0: the cpu budget's).")
SUBMAP_BATCH = flags.DEFINE_integer("submap_batch_rays", 0, "submaps.batch_rays: rays per submap per step (0: the "
                                    "config's rule, train.batch_rays shared among the submaps).")
SINGLE = flags.DEFINE_bool("single_cube", True, "Also run the single cube on the same route.")
WITH_SUBMAPS = flags.DEFINE_bool("submaps", True, "Run with submaps (false: only the single cube, with --single_cube).")
INIT_POSES = flags.DEFINE_enum("init_poses", "input", ["input", "baseline", "crisper"],
                               "train.init_poses of both runs: the drifted odometry, or the classical baseline's "
                               "poses (its pose graph closes the loop that the drift hides).")
OUTPUT_ROOT = flags.DEFINE_string("output_root", "outputs/long_route", "Run directories below this.")
OUTPUT = flags.DEFINE_string("output", "", "Also write the JSON here.")
OVERRIDES = flags.DEFINE_multi_string("set", [], "Config overrides KEY=VALUE (Python literal) for the accuracy runs, "
                                      "e.g. train.keep_scale_from_baseline=False.")
DEVICES = flags.DEFINE_list("devices", ["1", "2", "4", "8"], "Device counts for the throughput part.")
TP_SUBMAPS = flags.DEFINE_integer("throughput_submaps", 8, "Submaps in the throughput part.")
TP_STEPS = flags.DEFINE_integer("throughput_steps", 10, "Timed steps per device count (after one warm-up).")
WORKER = flags.DEFINE_integer("worker_devices", 0, "Internal: time the step on this many devices and exit.")

ROUTE = {"route": "courtyards", "seed": 0, "drift_trans_m": 0.02, "drift_rot_deg": 0.1, "max_range_m": 30.0}


def route_config(output_dir: str, submaps_on: bool):
    from configs.generic import get_config

    c = get_config("cpu")
    c.data.format = "synthetic"
    c.data.synthetic.update(dict(ROUTE, num_scans=NUM_SCANS.value, route_length_m=ROUTE_M.value))
    c.data.max_range_m = ROUTE["max_range_m"]
    c.data.keyframe_interval_s = 0.0
    c.train.max_minutes = 0.0  # measure the whole run, not the guard
    c.mapping.max_seconds = 0.0  # and score every ray of the rendered map against the ground truth
    c.submaps.batch_rays = SUBMAP_BATCH.value
    c.train.init_poses = INIT_POSES.value
    if STEPS.value:
        c.train.steps = STEPS.value
    if not submaps_on:
        c.submaps.enabled = "off"
        c.data.max_extent_m = 0.0
    c.output_dir = output_dir
    from neld_jax.config import apply_overrides

    return apply_overrides(c, OVERRIDES.value)


def accuracy() -> dict:
    from neld_jax.run import run

    out = {}
    for name, on in (("submaps", True), ("single_cube", False)):
        if (name == "single_cube" and not SINGLE.value) or (name == "submaps" and not WITH_SUBMAPS.value):
            continue
        config = route_config(os.path.join(OUTPUT_ROOT.value, f"{name}_{NUM_SCANS.value}"), on)
        t0 = time.perf_counter()
        summary = run(config, progress=False)
        methods = summary["evaluation"]["methods"]
        out[name] = {
            "submaps": summary["submaps"], "steps": summary["steps"], "train_seconds": summary["train_seconds"],
            "total_seconds": round(time.perf_counter() - t0, 1),
            "ate_initial_m": methods["initial"]["ate"]["translation_rmse_m"],
            "ate_optimized_m": methods["optimized"]["ate"]["translation_rmse_m"],
            "rot_initial_deg": methods["initial"]["ate"]["rotation_rmse_deg"],
            "rot_optimized_deg": methods["optimized"]["ate"]["rotation_rmse_deg"],
            "init_poses": INIT_POSES.value, "baseline_seconds": summary.get("baseline_seconds"),
            "crispness": {m: round(v["mean_map_entropy"], 4) for m, v in summary["crispness"].items()
                          if v.get("mean_map_entropy") is not None},
        }
        if "baseline" in methods and "ate" in methods["baseline"]:
            out[name]["ate_baseline_m"] = methods["baseline"]["ate"]["translation_rmse_m"]
            out[name]["rot_baseline_deg"] = methods["baseline"]["ate"]["rotation_rmse_deg"]
        out[name]["ate_ratio"] = out[name]["ate_optimized_m"] / out[name]["ate_initial_m"]
        logging.warning("%s: %s", name, out[name])
    return out


def split() -> dict:
    """Windows against spatial tiles on the route (initial poses, raw scans within 30 m): how many submaps hold
    each keyframe either way (neld_jax.submaps: the measurement behind choosing windows)."""
    import numpy as np

    from neld_jax import submaps
    from neld_jax.data.normalize import fit_normalization
    from neld_jax.data.synthetic import make_sequence

    config = route_config("", True)
    seq = make_sequence(config.data.synthetic)
    norm = fit_normalization(seq.scans, seq.poses, config.data.normalization_margin)
    plan = submaps.plan_from_config(seq, norm, config)
    lower, upper = submaps.scan_bounds(seq.scans, seq.poses)
    cube = 2.0 * config.data.normalization_margin / float(np.median(plan.scales))
    tiles = submaps.tile_memberships(lower, upper, cube)
    windows = submaps.describe_membership(plan, seq.num_scans)
    return {"extent_m": round(2.0 * config.data.normalization_margin / norm.scale, 1),
            "submaps": int((plan.weight > 0).sum()), "keyframes_per_submap": plan.window,
            "median_cube_m": round(cube, 1),
            "submaps_per_keyframe_windows": {int(k): int(v) for k, v in zip(*np.unique(windows, return_counts=True))},
            "tiles_per_keyframe_same_size": {int(k): int(v) for k, v in zip(*np.unique(tiles, return_counts=True))}}


def throughput_worker(devices: int) -> dict:
    """Time the sharded step of M submaps (cpu-budget field and sampler) on `devices` devices."""
    import jax
    import numpy as np

    from configs.generic import get_config
    from neld_jax import submap_train, submaps
    from neld_jax.data.rays import sphere_scene_rays

    assert len(jax.devices()) >= devices, jax.devices()  # GPUs: the first `devices` of them
    config = get_config("cpu")
    config.submaps.batch_rays = SUBMAP_BATCH.value
    m, window = TP_SUBMAPS.value, 4
    num_scans = m * (window - 1) + 1
    rays_np, T = sphere_scene_rays(num_scans, 2048, seed=0)
    scans = [rays_np.directions[rays_np.scan_index == s] * rays_np.ranges[rays_np.scan_index == s, None]
             for s in range(num_scans)]
    plan = submaps.plan_submaps(scans, T, window, 1, 0.9, num_devices=devices)
    rays, frames = submap_train.from_arrays(submaps.submap_arrays(plan, rays_np, T))
    mesh = submap_train.make_mesh(devices)
    setup = submap_train.create_submap_state(config, num_scans, plan.num_submaps, mesh)
    rays = submap_train.place(rays, submap_train.data_sharding(rays, mesh))
    frames = submap_train.place(frames, submap_train.data_sharding(frames, mesh))
    sampler = setup.sampler(0)
    # The collectives XLA put into the partitioned step (expected: the pose gradient's all-reduce, no all-gather).
    t0 = time.perf_counter()
    compiled = setup.step_fn.lower(setup.state, rays, frames, sampler).compile()
    compile_s = time.perf_counter() - t0
    hlo = compiled.as_text()
    collectives = {op: len(re.findall(rf"\b{op}(?:-start)?\(", hlo))
                   for op in ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")}
    state, metrics = compiled(setup.state, rays, frames)  # warm-up
    jax.block_until_ready(metrics)
    t0 = time.perf_counter()
    for _ in range(TP_STEPS.value):
        state, metrics = compiled(state, rays, frames)
    jax.block_until_ready(metrics)
    seconds = time.perf_counter() - t0
    steps_per_s = TP_STEPS.value / seconds
    per_submap = submap_train.submap_batch_rays(config, plan.num_submaps)
    return {"devices": devices, "submaps": plan.num_submaps, "rays_per_submap": per_submap,
            "steps_per_s": steps_per_s, "rays_per_s": steps_per_s * plan.num_submaps * per_submap,
            "compile_s": round(compile_s, 2), "platform": jax.devices()[0].platform, "collectives": collectives,
            "loss_finite": bool(np.isfinite(float(metrics["loss"])))}


def throughput() -> list:
    rows = []
    for d in (int(x) for x in DEVICES.value):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={d}")
        cmd = [sys.executable, os.path.abspath(__file__), f"--worker_devices={d}",
               f"--throughput_submaps={TP_SUBMAPS.value}", f"--throughput_steps={TP_STEPS.value}",
               f"--submap_batch_rays={SUBMAP_BATCH.value}"]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        logging.warning("throughput: %s", rows[-1])
    for row in rows:  # the same M submaps on every count: speedup = steps/s ratio, efficiency = speedup per device
        row["speedup"] = row["steps_per_s"] / rows[0]["steps_per_s"]
        row["efficiency"] = row["speedup"] * rows[0]["devices"] / row["devices"]
    return rows


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING)
    if WORKER.value:
        print(json.dumps(throughput_worker(WORKER.value)))
        return
    result = {"route": dict(ROUTE, num_scans=NUM_SCANS.value, route_length_m=ROUTE_M.value),
              "submap_batch_rays": SUBMAP_BATCH.value, "argv": sys.argv[1:]}
    if "split" in PARTS.value:
        result["split"] = split()
    if "accuracy" in PARTS.value:
        result["accuracy"] = accuracy()
    if "throughput" in PARTS.value:
        result["throughput"] = throughput()
    text = json.dumps(result, indent=1)
    print(text)
    if OUTPUT.value:
        with open(OUTPUT.value, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    app.run(main)
