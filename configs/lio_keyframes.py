"""Keyframe scans saved by a LiDAR-inertial odometry front-end (FAST-LIO2 + Scan Context and similar):
ROOT/Scans/NNNNNN.pcd (sensor frame), ROOT/odom_poses.txt (KITTI), ROOT/times.txt. No ground truth needed.

    python bin/train.py --config=configs/lio_keyframes.py --config.data.root=/data/HKU_1_bag
    python bin/train.py --config=configs/lio_keyframes.py --config.data.root=... \\
        --config.data.initial_poses=optimized_poses.txt

The scans are keyframes already (the front-end chose them), so every one is trained on.
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "lio_keyframes"
    c.data.keyframe_interval_s = 0.0  # the front-end chose the keyframes
    c.output_dir = "outputs/lio_keyframes"
    return c
