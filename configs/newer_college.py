"""Newer College (quad/math easy/hard): per-scan cloud_<sec>_<nsec>.pcd, registered_poses.csv ground truth.

    python bin/train.py --config=configs/newer_college.py --config.data.root=/data/quad_easy

No budget named: `:gpu` where JAX's default backend is a GPU, else `:paper` (neld_jax.config.apply_budget).
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "newer_college"
    c.output_dir = "outputs/newer_college"
    return apply_budget(c, budget or default_budget("paper"))
