"""The demo: a synthetic courtyard sequence with ground truth, generated on the fly, sized for a laptop CPU.

    python bin/train.py --config=configs/demo.py
    python bin/train.py --config=configs/demo.py:paper   # the paper's model and schedule on the same data
    python bin/train.py --config=configs/demo.py:gpu     # the GPU budget (the default where a GPU is JAX's backend)

Prints the pose and map error before and after the bundle adjustment.
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "synthetic"
    c.data.keyframe_interval_s = 0.0  # the generator already spaces its scans as keyframes
    c.output_dir = "outputs/demo"
    return apply_budget(c, budget or default_budget("cpu"))
