"""The demo: a synthetic courtyard sequence with ground truth, generated on the fly, sized for a laptop CPU.

    python bin/train.py --config=configs/demo.py
    python bin/train.py --config=configs/demo.py:paper   # the paper's model and schedule on the same data
    python bin/train.py --config=configs/demo.py:gpu     # the gpu budget (the default where a GPU is JAX's backend)

No budget named: cpu, or gpu where JAX's default backend is a GPU.

Prints the pose and map error before and after the bundle adjustment.
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.synthetic(budget)
    c.output_dir = "outputs/demo"
    return c
