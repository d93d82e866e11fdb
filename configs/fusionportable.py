"""FusionPortable (2022 handheld sequences: 20220216_canteen_day, 20220215_canteen_night, 20220216_garden_day,
20220215_garden_night), as downloaded or as the dataset's devkit exports a FAST-LIO2 run:

    python bin/train.py --config=configs/fusionportable.py \\
        --config.data.root=/data/FusionPortable/sensor_data/handheld/20220216_canteen_day

As downloaded, ROOT/<sequence>.bag: the Ouster's raw sweeps, made into poses by KISS-ICP (docs/datasets.md, "Scans
without poses"). The devkit's export, the better start where present:
ROOT/algorithm_result/ouster00_undistort/points/{data/000000.pcd, timestamps.txt},
ROOT/algorithm_result/odometry/odometry.txt; ground truth groundtruth/traj/<sequence>.txt and
groundtruth/map/<sequence>/merged_scan.pcd are found
beside or above ROOT (or set data.gt_poses_path / data.gt_map_path), moved into the scans' frame with the dataset's
published extrinsic (data.gt_from_scan overrides it). No budget named: cpu (within 10 minutes on 2 CPU
cores, but for KISS-ICP over a download's every sweep, which no clock cuts: about 0.7 s a 128 x 1024 sweep), or gpu
where JAX's default backend is a GPU; :paper is the paper's schedule.
"""

from neld_jax import config


def get_config(budget: str = ""):
    c = config.recording(budget)
    c.data.format = "fusionportable"
    c.output_dir = "outputs/fusionportable"
    c.eval.map_icp_m = 1.0  # the ground-truth map is a survey registered on its own: refine its alignment by ICP
    return c
