"""A sequence in the generic layout (docs/design.md): ROOT/scans/*, ROOT/poses.txt (TUM), optional ground truth;
what neld-import-rosbag and neld-perturb write.

    python bin/train.py --config=configs/generic.py --config.data.root=/data/seq --config.output_dir=runs/seq

No budget named: cpu (within 10 minutes on 2 CPU cores), or gpu where JAX's default backend is a GPU; :paper is the
paper's schedule (neld_jax.config).
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "generic"
    c.output_dir = "outputs/generic"
    return c
