"""HBA's input layout (github.com/hku-mars/HBA): ROOT/pcd/0.pcd ... and ROOT/pose.json ('tx ty tz qw qx qy qz'
per line, no stamps), so the same scans and initial poses can be refined by both (neld_jax/data/hba.py):

    python bin/train.py --config=configs/hba.py:cpu --config.data.root=/data/park

Without stamps keyframes are chosen by distance (data.keyframe_distance_m; every scan when 0).
"""

from neld_jax.config import apply_budget, base_config


def get_config(budget: str = "gpu"):
    c = base_config()
    c.data.format = "hba"
    c.data.keyframe_interval_s = 0.0  # no stamps in this layout
    c.output_dir = "outputs/hba"
    return apply_budget(c, budget)
