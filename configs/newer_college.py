"""Newer College: the 2021 release (quad/maths, easy to hard; OS0-128 rosbags) after bin/import_rosbag.py, or the
2020 release's cloud_<sec>_<nsec>.pcd (neld_jax.data.newer_college.load_newer_college):

    python bin/import_rosbag.py --bag=fastlio_quad_easy.bag --out=/data/quad_easy   # FAST-LIO2's clouds + odometry
    cp gt-nc-quad-easy.csv /data/quad_easy/
    python bin/train.py --config=configs/newer_college.py --config.data.root=/data/quad_easy

The ground truth (base frame in 2021) is moved into the scans' frame with the published extrinsic
(neld_jax/data/ground_truth.py; data.scan_frame=os_imu for a FAST-LIO2 run with the Ouster IMU extrinsic,
data.gt_from_scan for any other).

No budget named: `:gpu` where JAX's default backend is a GPU, else `:paper` (neld_jax.config.apply_budget).
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "newer_college"
    c.output_dir = "outputs/newer_college"
    c.eval.map_icp_m = 1.0  # the GT map (a survey) is registered on its own: refine its alignment by ICP
    return apply_budget(c, budget or default_budget("paper"))
