#!/usr/bin/env python
"""The classical baseline: Open3D multiway registration (point-to-plane ICP + pose graph).

    python bin/baseline.py --config=configs/demo.py
    python bin/baseline.py --config=configs/generic.py --config.data.root=/data/seq --config.output_dir=runs/seq

Loads and preprocesses the sequence exactly like bin/train.py, refines the initial poses, writes
poses_baseline.txt/.kitti and map_raw_baseline.ply into config.output_dir and, when the sequence has
ground truth, evaluates the folder and prints the table (initial / baseline / optimized if present).
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from absl import flags  # noqa: E402

from neld_jax.cli import main_with_config  # noqa: E402

VOXEL_SIZE = flags.DEFINE_float("voxel_size", 0.2, "Voxel size (m) of the scans given to ICP.")
MAX_CORR_DIST = flags.DEFINE_float("max_corr_dist", 1.0, "ICP correspondence distance (m).")
LOOP_RADIUS = flags.DEFINE_float("loop_radius", 10.0, "Register non-neighbouring scans closer than this (m).")


def job(config):
    from neld_jax.baseline import run_baseline
    from neld_jax.evaluate import format_table
    from neld_jax.quality import format_crispness_table

    result = run_baseline(config, voxel_size=VOXEL_SIZE.value, max_corr_dist=MAX_CORR_DIST.value,
                          loop_radius_m=LOOP_RADIUS.value)
    print(f"baseline ({result['seconds']:.0f} s) written to {config.output_dir}")
    print(format_crispness_table(result["crispness"]))
    if result["evaluation"] is not None:
        print(format_table(result["evaluation"]))


if __name__ == "__main__":
    main_with_config(job)
