"""A sequence in the generic layout (docs/design.md): ROOT/scans/*, ROOT/poses.txt (TUM), optional ground truth;
what neld-import-rosbag and neld-perturb write.

    python bin/train.py --config=configs/generic.py:cpu --config.data.root=/data/seq --config.output_dir=runs/seq

No budget named: gpu where JAX's default backend is a GPU, else paper (neld_jax.config).
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "generic"
    c.output_dir = "outputs/generic"
    return c
