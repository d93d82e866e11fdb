#!/usr/bin/env python
"""The raw map's crispness along one training run: how the pose steps move a real sequence's map, step by step.

    python benchmarks/entropy_trajectory.py --root=<output>/HKU_2_bag \\
        --pose_file=/tmp/real/HKU_2_bag/recorded_crisper/poses_baseline.kitti \\
        --set=train.pose_lr_trans_init=5e-6 --out=/tmp/hku2_trajectory.json

Trains the lio_keyframes config (cpu budget) from the poses in --pose_file (KITTI, one line per scan of ROOT;
default: the layout's odom_poses.txt) exactly as `bin/train.py` would from those poses (train.init_poses=input,
no wall-clock guard), and every --every steps measures the mean map entropy of the keyframes' raw map under the
current poses (anchored on train.anchor_scan, 0, as the run writes them; the same 10,000 query points each
time). Writes one JSON object: the overrides and, per measurement, the step, the entropy, the last batch's range
error (mean and median) and the mean pose correction so far. Nothing is written besides --out. A baseline's
poses file is an input here: a run from the baseline also gets train.pose_prior_from_baseline and
train.keep_scale_from_baseline, so pass --set=train.pose_prior_weight=300.0 --set=train.keep_start_scale=True to
measure what such a run does.
"""

import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from absl import app, flags  # noqa: E402

ROOT = flags.DEFINE_string("root", None, "A sequence in the lio_keyframes layout (Scans/, odom_poses.txt, times.txt).")
POSE_FILE = flags.DEFINE_string("pose_file", "", "KITTI poses to start from (absolute, or relative to --root).")
EVERY = flags.DEFINE_integer("every", 250, "Measure the map's crispness every this many steps.")
OUT = flags.DEFINE_string("out", "outputs/entropy_trajectory.json", "The JSON file written.")
OVERRIDES = flags.DEFINE_multi_string("set", [], "Config overrides KEY=VALUE, e.g. train.pose_lr_trans_init=5e-6.")


def main(argv):
    del argv
    import jax.numpy as jnp

    from configs import lio_keyframes
    from neld_jax import quality, run, train
    from neld_jax.config import apply_overrides
    from neld_jax.data.rays import build_rays

    config = lio_keyframes.get_config("cpu")
    config.data.root, config.data.pose_file = ROOT.value, POSE_FILE.value
    config.train.init_poses, config.train.max_minutes, config.train.checkpoint_every = "input", 0.0, EVERY.value
    apply_overrides(config, OVERRIDES.value)
    _, seq, norm = run.load_and_prepare(config)
    rays = train.device_rays(build_rays(seq, norm, max_rays_per_scan=(config.data.max_rays_per_scan or None),
                                        seed=config.seed))
    T_init = jnp.asarray(norm.poses_to_normalized(seq.poses), jnp.float32)
    records = []

    def measure(step: int, poses, history: list) -> None:
        T_n, G_n = run.field_poses(poses, T_init, config.train.anchor_scan)
        T_world = norm.poses_to_world(G_n @ T_n)
        summary, _ = quality.map_crispness(seq, {"poses": T_world}, config.eval)
        last = history[-1] if history else {}
        records.append({"step": step, "mean_map_entropy": summary["poses"]["mean_map_entropy"],
                        "mean_plane_thickness_m": summary["poses"]["mean_plane_thickness_m"],
                        "range_err_m": last.get("range_err_m"),
                        "range_residual_median_m": last.get("range_residual_median_m"),
                        "pose_trans_mean_m": last.get("pose_trans_mean_m", 0.0),
                        "pose_rot_mean_deg": last.get("pose_rot_mean_deg", 0.0)})
        print(json.dumps(records[-1]), flush=True)
        with open(OUT.value, "w") as f:
            json.dump({"root": ROOT.value, "pose_file": POSE_FILE.value, "overrides": OVERRIDES.value,
                       "scans": seq.num_scans, "records": records}, f, indent=1)

    t0 = time.perf_counter()
    measure(0, jnp.zeros((seq.num_scans, 6)), [])
    train.fit(config, rays, T_init, norm.scale, progress=False,
              checkpoint_fn=lambda state, history, seconds: measure(int(state.step), state.params["poses"], history))
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    flags.mark_flag_as_required("root")
    app.run(main)
