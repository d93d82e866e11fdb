"""HBA's input layout (github.com/hku-mars/HBA): ROOT/pcd/0.pcd ... and ROOT/pose.json ('tx ty tz qw qx qy qz' per
line, no stamps), so that the same scans and initial poses can be refined by both:

    python bin/train.py --config=configs/hba.py --config.data.root=/data/park

Without stamps, keyframes are chosen by distance (data.keyframe_distance_m; every scan when 0).
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "hba"
    c.data.keyframe_interval_s = 0.0  # no stamps in this layout
    c.output_dir = "outputs/hba"
    return c
