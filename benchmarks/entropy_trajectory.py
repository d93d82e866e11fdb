#!/usr/bin/env python
"""The raw map's crispness along one training run: how the pose steps move a real sequence's map, step by step.

    python benchmarks/entropy_trajectory.py --root=<output>/HKU_2_bag \\
        --pose_file=/tmp/real/HKU_2_bag/recorded_crisper/poses_baseline.kitti \\
        --set=train.pose_lr_trans_init=5e-6 --out=/tmp/hku2_trajectory.json
    python benchmarks/entropy_trajectory.py --root=<output>/HKU_2_bag --pose_file=.../poses_baseline.kitti \\
        --as_baseline --out=/tmp/hku2_from_baseline.json

Trains the lio_keyframes config (cpu budget) from the poses in --pose_file (KITTI, one line per scan of ROOT;
default: the layout's odom_poses.txt) exactly as `bin/train.py` would from those poses (start.poses=input, no
wall-clock budget: the same plan of cubes, rays, trainer and fit as neld_jax.steps.refine), and every --every steps
measures the mean map entropy of the keyframes' raw map under the current poses (anchored on keyframe 0, as the
run writes them; the same 10,000 query points each time). Writes one JSON object: the overrides and, per
measurement, the step, the entropy, the last batch's range error (mean and median) and the mean pose correction so
far. Nothing is written besides --out. A baseline's poses file is an input here; --as_baseline trains with the pose
steps a run takes from the baseline's poses (neld_jax.steps.start.pose_steps_from_baseline: learning rates capped at
start.pose_lr_from_baseline, the prior of start.prior_from_baseline, heavier where the start's map is thinner
than start.THIN_MAP_M, and the start's scale kept) to measure what such a run does.
"""

import functools
import json
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

ROOT = flags.DEFINE_string("root", None, "A sequence in the lio_keyframes layout (Scans/, odom_poses.txt, times.txt).")
POSE_FILE = flags.DEFINE_string("pose_file", "", "KITTI poses to start from (absolute, or relative to --root).")
EVERY = flags.DEFINE_integer("every", 250, "Measure the map's crispness every this many steps.")
AS_BASELINE = flags.DEFINE_bool(
    "as_baseline",
    False,
    "Train with the pose steps of a run that starts from the classical baseline's poses (module docstring).",
)
harness.default_out("outputs/entropy_trajectory.json")
OVERRIDES = harness.overrides_flag("train.pose_lr_trans_init=5e-6")


def main(argv):
    del argv
    import jax
    import numpy as np

    from neld_jax.config import apply_overrides, from_file
    from neld_jax.field.model import world_poses
    from neld_jax.field.normalize import Normalization
    from neld_jax.geometry import anchored_on_first
    from neld_jax.judging import judge
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.training import submaps, train
    from neld_jax.training.rays import build_rays

    config = from_file(os.path.join(REPO, "configs", "lio_keyframes.py"), "cpu")
    config.data.root, config.data.initial_poses = ROOT.value, POSE_FILE.value
    config.start.poses, config.max_minutes, config.train.checkpoint_every = "input", 0.0, EVERY.value
    apply_overrides(config, OVERRIDES.value)
    _, keyframes = load_keyframes(config.data)
    start_poses, num_scans = keyframes.poses, keyframes.num_scans
    if AS_BASELINE.value:
        from neld_jax.steps.start import pose_steps_from_baseline

        judged, _ = judge.map_crispness(keyframes, {"start": start_poses}, config.eval)
        pose_steps = pose_steps_from_baseline(config.start, config.train, judged["start"].get("mean_plane_thickness_m"))
    else:
        pose_steps = train.PoseSteps.from_config(config)
    # The training of a run (neld_jax.steps.refine.refine_keyframes) without its checkpoints, the measurements in
    # their place
    devices = len(jax.devices())
    plan = submaps.plan_from_config(keyframes, config, num_devices=devices)
    rays_m = build_rays(
        keyframes, Normalization(1.0), max_rays_per_scan=(config.data.max_rays_per_scan or None), seed=config.seed
    )
    mesh = train.make_mesh(submaps.mesh_size(plan, devices))
    rays, frames = train.device_data(submaps.submap_arrays(plan, rays_m, start_poses), mesh)
    plan_of = functools.partial(
        train.make_trainer, config, num_scans, plan.num_submaps, pose_steps, start_poses, mesh=mesh
    )
    state = train.init_state(config, plan_of(int(config.train.steps)), num_scans, plan.num_submaps)
    records = []

    def measure(step: int, poses, history: list) -> None:
        in_field = world_poses(start_poses, np.asarray(poses), plan.ref_scale)
        T_world, _ = anchored_on_first(in_field, start_poses[0])  # keyframe 0 stays
        summary, _ = judge.map_crispness(keyframes, {"poses": T_world}, config.eval)
        last = history[-1] if history else {}
        records.append(
            {
                "step": step,
                "mean_map_entropy": summary["poses"]["mean_map_entropy"],
                "mean_plane_thickness_m": summary["poses"]["mean_plane_thickness_m"],
                "range_err_m": last.get("range_err_m"),
                "range_residual_median_m": last.get("range_residual_median_m"),
                "pose_trans_mean_m": last.get("pose_trans_mean_m", 0.0),
                "pose_rot_mean_deg": last.get("pose_rot_mean_deg", 0.0),
            }
        )
        print(json.dumps(records[-1]), flush=True)
        harness.write(
            harness.OUT.value,
            {
                "root": ROOT.value,
                "pose_file": POSE_FILE.value,
                "overrides": OVERRIDES.value,
                "as_baseline": AS_BASELINE.value,
                "pose_steps": pose_steps.to_dict(),
                "scans": num_scans,
                "submaps": plan.num_submaps,
                "records": records,
            },
        )

    t0 = time.perf_counter()
    measure(0, np.zeros((num_scans, 6)), [])
    train.fit(
        config,
        plan_of,
        train.TrainingData(rays, frames, plan.ref_scale),
        state,
        checkpoint_fn=lambda state, history, seconds: measure(int(state.step), state.params["poses"], history),
        settings=train.FitSettings(progress=False),
    )
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    flags.mark_flag_as_required("root")
    app.run(main)
