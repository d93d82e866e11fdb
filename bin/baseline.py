#!/usr/bin/env python
"""The classical baseline: Open3D scan-to-map ICP, then a pose graph with loop closures.

    python bin/baseline.py --config=configs/demo.py
    python bin/baseline.py --config=configs/generic.py --config.data.root=/data/seq --config.output_dir=runs/seq
    python bin/baseline.py --config=configs/demo.py --config.baseline.window=5   # settings: config.baseline

Loads and preprocesses the sequence exactly like bin/train.py, refines the initial poses, writes
poses_baseline.txt/.kitti and map_raw_baseline.ply into config.output_dir and, when the sequence has
ground truth, evaluates the folder and prints the table (initial / baseline / optimized if present).
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from neld_jax.cli import main_with_config  # noqa: E402


def job(config):
    from neld_jax.baseline import run_baseline
    from neld_jax.evaluate import format_table
    from neld_jax.quality import format_crispness_table

    result = run_baseline(config)
    print(f"baseline ({result['seconds']:.0f} s) written to {config.output_dir}")
    print(format_crispness_table(result["crispness"]))
    if result["evaluation"] is not None:
        print(format_table(result["evaluation"]))


if __name__ == "__main__":
    main_with_config(job)
