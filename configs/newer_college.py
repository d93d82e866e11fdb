"""Newer College: the 2021 release (quad/maths, easy to hard; OS0-128 rosbags) as downloaded or after
neld-import-rosbag, or the 2020 release's cloud_<sec>_<nsec>.pcd:

    python bin/train.py --config=configs/newer_college.py --config.data.root=/data/quad_easy   # *.bag + gt-nc-*.csv

The bags as downloaded: the Ouster's raw sweeps, made into poses by KISS-ICP (docs/datasets.md, "Scans without
poses"). A FAST-LIO2 run, the better start where present:

    python bin/import_rosbag.py --bag=fastlio_quad_easy.bag --out=/data/quad_easy   # FAST-LIO2's clouds + odometry
    cp gt-nc-quad-easy.csv /data/quad_easy/
    python bin/train.py --config=configs/newer_college.py --config.data.root=/data/quad_easy

The ground truth (base frame in 2021) is moved into the scans' frame with the published extrinsic
(data.scan_frame=os_imu for a FAST-LIO2 run with the Ouster IMU extrinsic, data.gt_from_scan for any other).
No budget named: cpu (within 10 minutes on 2 CPU cores), or gpu where JAX's default backend is a GPU; :paper is the
paper's schedule.
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "newer_college"
    c.output_dir = "outputs/newer_college"
    c.eval.map_icp_m = 1.0  # the ground-truth map is a survey registered on its own: refine its alignment by ICP
    return c
