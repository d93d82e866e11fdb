"""FusionPortable (canteen/garden day/night): FAST-LIO2 initial poses, per-scan PCD, GT trajectory and map.

    python bin/train.py --config=configs/fusionportable.py --config.data.root=/data/canteen_day

The paper's hyper-parameters (docs/method.md); `:cpu` selects the CPU budget.
"""

from neld_jax.config import apply_budget, base_config


def get_config(budget: str = "gpu"):
    c = base_config()
    c.data.format = "fusionportable"
    c.output_dir = "outputs/fusionportable"
    return apply_budget(c, budget)
