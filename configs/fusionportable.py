"""FusionPortable (canteen/garden day/night): FAST-LIO2 initial poses, per-scan PCD, GT trajectory and map.

    python bin/train.py --config=configs/fusionportable.py --config.data.root=/data/canteen_day

Budgets (neld_jax.config.apply_budget): none named = `:gpu` where JAX's default backend is a GPU, else `:paper`
(the paper's hyper-parameters, docs/method.md); `:cpu` sizes it for 2 CPU cores.
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "fusionportable"
    c.output_dir = "outputs/fusionportable"
    return apply_budget(c, budget or default_budget("paper"))
