"""Newer College (quad/math easy/hard): per-scan cloud_<sec>_<nsec>.pcd, registered_poses.csv ground truth.

    python bin/train.py --config=configs/newer_college.py --config.data.root=/data/quad_easy
"""

from neld_jax.config import apply_budget, base_config


def get_config(budget: str = "gpu"):
    c = base_config()
    c.data.format = "newer_college"
    c.output_dir = "outputs/newer_college"
    return apply_budget(c, budget)
