"""A dataset in the generic layout (docs/design.md): ROOT/scans/*, ROOT/poses.txt (TUM), optional ground truth.

    python bin/train.py --config=configs/generic.py --config.data.root=/data/seq --config.output_dir=runs/seq
    python bin/train.py --config=configs/generic.py:cpu ...   # sized for 2 CPU cores, ~10 minutes

No budget named: `:gpu` where JAX's default backend is a GPU, else `:paper` (neld_jax.config.apply_budget).
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "generic"
    c.output_dir = "outputs/generic"
    return apply_budget(c, budget or default_budget("paper"))
