"""A KITTI odometry sequence as downloaded (www.cvlibs.net/datasets/kitti/eval_odometry.php, "velodyne laser data"
and "ground truth poses"):

    python bin/train.py --config=configs/kitti.py --config.data.root=/data/kitti/dataset/sequences/07

ROOT holds velodyne/000000.bin ..., times.txt and calib.txt; the ground truth ../../poses/NN.txt (sequences 00-10)
is moved into the LiDAR frame with calib.txt's Tr. The layout has no odometry: KISS-ICP makes the initial poses from
the scans (docs/datasets.md, "KITTI odometry"). No budget named: gpu where JAX's default backend is a GPU, else
paper; :cpu sizes it for 2 CPU cores.
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "kitti"
    c.output_dir = "outputs/kitti"
    return c
