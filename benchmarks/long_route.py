#!/usr/bin/env python
"""The long synthetic route: submaps against one cube, and the submap step's throughput on 1-8 devices.

    python benchmarks/long_route.py                                  # the full target: 200 keyframes, 600 m
    python benchmarks/long_route.py --num_scans=66 --route_length_m=200 --steps=600   # a shortened run
    python benchmarks/long_route.py --parts=throughput --devices=1,2,4,8               # steps/s only
    python benchmarks/long_route.py --parts=accuracy --start=crisper --single_cube=false

accuracy: the generic cpu budget on a synthetic `courtyards` route (data.synthetic.route), run twice on the same
sequence: with submaps (switched on by the rule, not by a flag) and as one cube (submaps.enabled=off). Prints
initial / optimised ATE, seconds and the split for each.
throughput: one subprocess per device count d with XLA_FLAGS=--xla_force_host_platform_device_count=d (the flag
must be set before jax starts) timing the sharded submap step on the same M submaps; steps/s, rays/s and the
efficiency (steps/s relative to one device). On a CPU the simulated devices share the machine's cores.
One JSON object on stdout (and in --out, in the schema of benchmarks/harness.py; --output is its older name).
"""

import json
import logging
import os
import re
import subprocess
import sys
import time

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PARTS = flags.DEFINE_list("parts", ["split", "accuracy", "throughput"], "split, accuracy and/or throughput.")
NUM_SCANS = flags.DEFINE_integer("num_scans", 200, "Keyframes of the route (one every 3 s).")
ROUTE_M = flags.DEFINE_float("route_length_m", 600.0, "Length of the closed route.")
STEPS = flags.DEFINE_integer("steps", 0, "train.steps (0: the cpu budget's).")
SINGLE = flags.DEFINE_bool("single_cube", True, "Also run the single cube on the same route.")
WITH_SUBMAPS = flags.DEFINE_bool("submaps", True, "Run with submaps (false: only the single cube, with --single_cube).")
START = flags.DEFINE_enum(
    "start",
    "input",
    ["input", "baseline", "crisper"],
    "start.poses of both runs: the drifted odometry, the classical baseline's poses (its pose "
    "graph closes the loop that the drift hides) or the crisper of the two.",
)
OUTPUT_ROOT = flags.DEFINE_string("output_root", "outputs/long_route", "Run directories below this.")
flags.DEFINE_alias("output", "out")  # the name the recorded commands give
OVERRIDES = harness.overrides_flag("submaps.step_rays_factor=2.0 (the accuracy runs)")
DEVICES = flags.DEFINE_list("devices", ["1", "2", "4", "8"], "Device counts for the throughput part.")
TP_SUBMAPS = flags.DEFINE_integer("throughput_submaps", 8, "Submaps in the throughput part.")
TP_STEPS = flags.DEFINE_integer("throughput_steps", 10, "Timed steps per device count (after one warm-up).")
WORKER = flags.DEFINE_integer("worker_devices", 0, "Internal: time the step on this many devices and exit.")

ROUTE = {"route": "courtyards", "seed": 0, "drift_trans_m": 0.02, "drift_rot_deg": 0.1, "max_range_m": 30.0}


def route_config(output_dir: str, submaps_on: bool):
    from neld_jax.config import apply_overrides, from_file

    c = from_file(os.path.join(REPO, "configs", "generic.py"), "cpu")
    c.data.format = "synthetic"
    c.data.synthetic.update(dict(ROUTE, num_scans=NUM_SCANS.value, route_length_m=ROUTE_M.value))
    c.data.max_range_m = ROUTE["max_range_m"]
    c.data.keyframe_interval_s = 0.0
    c.max_minutes = 0.0  # measure the whole run, not the clock
    c.mapping.max_seconds = 0.0  # and score every ray of the rendered map against the ground truth
    c.start.poses = START.value
    if STEPS.value:
        c.train.steps = STEPS.value
    if not submaps_on:
        c.submaps.enabled = "off"
    c.output_dir = output_dir
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
        methods, r = summary["evaluation"]["methods"], summary["run"]
        out[name] = {
            "submaps": r["submaps"],
            "steps": r["steps"],
            "train_seconds": r["train_seconds"],
            "total_seconds": round(time.perf_counter() - t0, 1),
            "ate_initial_m": methods["initial"]["ate"]["translation_rmse_m"],
            "ate_optimized_m": methods["optimized"]["ate"]["translation_rmse_m"],
            "rot_initial_deg": methods["initial"]["ate"]["rotation_rmse_deg"],
            "rot_optimized_deg": methods["optimized"]["ate"]["rotation_rmse_deg"],
            "start": START.value,
            "started_from": r["started_from"],
            "baseline_seconds": r.get("baseline_seconds"),
            "crispness": {
                m: round(v["mean_map_entropy"], 4)
                for m, v in summary["crispness"].items()
                if v.get("mean_map_entropy") is not None
            },
        }
        if "baseline" in methods and "ate" in methods["baseline"]:
            out[name]["ate_baseline_m"] = methods["baseline"]["ate"]["translation_rmse_m"]
            out[name]["rot_baseline_deg"] = methods["baseline"]["ate"]["rotation_rmse_deg"]
        out[name]["ate_ratio"] = out[name]["ate_optimized_m"] / out[name]["ate_initial_m"]
        logging.warning("%s: %s", name, out[name])
    return out


def split() -> dict:
    """Windows against spatial tiles on the route (initial poses, raw scans within 30 m): how many submaps hold
    each keyframe either way (neld_jax.training.submaps: the measurement behind choosing windows)."""
    import numpy as np

    from neld_jax.field.normalize import NORMALIZATION_MARGIN, fit_normalization
    from neld_jax.synthetic.generator import make_sequence
    from neld_jax.training import submaps

    config = route_config("", True)
    seq = make_sequence(config.data.synthetic)
    norm = fit_normalization(seq.scans, seq.poses, NORMALIZATION_MARGIN)
    plan = submaps.plan_from_config(seq, config)
    lower, upper = submaps.scan_bounds(seq.scans, seq.poses)
    cube = 2.0 * NORMALIZATION_MARGIN / float(np.median(plan.scales))
    tiles = submaps.tile_memberships(lower, upper, cube)
    windows = submaps.describe_membership(plan, seq.num_scans)
    return {
        "extent_m": round(2.0 * NORMALIZATION_MARGIN / norm.scale, 1),
        "submaps": int((plan.weight > 0).sum()),
        "keyframes_per_submap": plan.window,
        "median_cube_m": round(cube, 1),
        "submaps_per_keyframe_windows": {int(k): int(v) for k, v in zip(*np.unique(windows, return_counts=True))},
        "tiles_per_keyframe_same_size": {int(k): int(v) for k, v in zip(*np.unique(tiles, return_counts=True))},
    }


def throughput_worker(devices: int) -> dict:
    """Time the sharded step of M submaps (the cpu budget's field and sampler; train.make_trainer on a mesh of
    `devices` devices, as a run builds it) on `devices` devices."""
    import jax
    import numpy as np

    from neld_jax.config import from_file
    from neld_jax.field.normalize import NORMALIZATION_MARGIN
    from neld_jax.training import submaps, train
    from neld_jax.training.rays import RaySet, sphere_scene_rays

    assert len(jax.devices()) >= devices, jax.devices()  # GPUs: the first `devices` of them
    config = from_file(os.path.join(REPO, "configs", "generic.py"), "cpu")
    m, window = TP_SUBMAPS.value, 4
    num_scans = m * (window - 1) + 1
    rays_n, T = sphere_scene_rays(num_scans, 2048, seed=0)
    metres = 40.0  # the analytic scene (a sphere of radius 0.8) as 64 m across, the scale of a recorded scene
    rays_m = RaySet(rays_n.directions, (rays_n.ranges * metres).astype(np.float32), rays_n.scan_index)
    T_m = np.array(T, np.float64)
    T_m[:, :3, 3] *= metres
    scans = [
        rays_m.directions[rays_m.scan_index == s] * rays_m.ranges[rays_m.scan_index == s, None]
        for s in range(num_scans)
    ]
    plan = submaps.plan_submaps(scans, T_m, window, 1, NORMALIZATION_MARGIN, num_devices=devices)
    mesh = train.make_mesh(devices)
    rays, frames = train.device_data(submaps.submap_arrays(plan, rays_m, T_m), mesh)
    trainer = train.make_trainer(
        config, num_scans, plan.num_submaps, train.PoseSteps.from_config(config), T_m, mesh=mesh
    )
    state = train.init_state(config, trainer, num_scans, plan.num_submaps)
    step = jax.jit(trainer.step, static_argnames=("sampler",), donate_argnums=(0,))
    # The collectives XLA put into the partitioned step (expected: the pose gradient's all-reduce, no all-gather).
    t0 = time.perf_counter()
    compiled = step.lower(state, rays, frames, sampler=trainer.sampler(0)).compile()
    compile_s = time.perf_counter() - t0
    hlo = compiled.as_text()
    collectives = {
        op: len(re.findall(rf"\b{op}(?:-start)?\(", hlo))
        for op in ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")
    }
    state, metrics = compiled(state, rays, frames)  # warm-up
    jax.block_until_ready(metrics)
    t0 = time.perf_counter()
    for _ in range(TP_STEPS.value):
        state, metrics = compiled(state, rays, frames)
    jax.block_until_ready(metrics)
    seconds = time.perf_counter() - t0
    steps_per_s = TP_STEPS.value / seconds
    per_submap = trainer.batch_rays
    return {
        "devices": devices,
        "submaps": plan.num_submaps,
        "rays_per_submap": per_submap,
        "steps_per_s": steps_per_s,
        "rays_per_s": steps_per_s * plan.num_submaps * per_submap,
        "compile_s": round(compile_s, 2),
        "platform": jax.devices()[0].platform,
        "collectives": collectives,
        "loss_finite": bool(np.isfinite(float(metrics["loss"]))),
    }


def throughput() -> list:
    rows = []
    for d in (int(x) for x in DEVICES.value):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={d}")
        cmd = [
            sys.executable,
            os.path.abspath(__file__),
            f"--worker_devices={d}",
            f"--throughput_submaps={TP_SUBMAPS.value}",
            f"--throughput_steps={TP_STEPS.value}",
        ]
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
    result = {"route": dict(ROUTE, num_scans=NUM_SCANS.value, route_length_m=ROUTE_M.value), "argv": sys.argv[1:]}
    if "split" in PARTS.value:
        result["split"] = split()
    if "accuracy" in PARTS.value:
        result["accuracy"] = accuracy()
    if "throughput" in PARTS.value:
        result["throughput"] = throughput()
    print(json.dumps(result, indent=1))
    harness.write(harness.OUT.value, result)


if __name__ == "__main__":
    app.run(main)
