"""FusionPortable (2022 handheld sequences: 20220216_canteen_day, 20220215_canteen_night, 20220216_garden_day,
20220215_garden_night), as the dataset's devkit exports a FAST-LIO2 run
(neld_jax.data.fusionportable.load_fusionportable):

    python bin/train.py --config=configs/fusionportable.py --config.data.root=/data/FusionPortable/sensor_data/handheld/20220216_canteen_day

ROOT/algorithm_result/ouster00_undistort/points/{data/000000.pcd, timestamps.txt}, ROOT/algorithm_result/odometry/
odometry.txt; ground truth groundtruth/traj/<sequence>.txt and groundtruth/map/<sequence>/merged_scan.pcd are found
beside or above ROOT (or set data.gt_poses_path / data.gt_map_path). The ground truth is moved into the scans' frame
with the dataset's published extrinsic (neld_jax/data/ground_truth.py; data.gt_from_scan overrides it).
Budgets (neld_jax.config.apply_budget): none named = `:gpu` where JAX's default backend is a GPU, else `:paper`
(the paper's hyper-parameters, docs/method.md); `:cpu` sizes it for 2 CPU cores.
"""

from neld_jax.config import apply_budget, base_config, default_budget


def get_config(budget: str = ""):
    c = base_config()
    c.data.format = "fusionportable"
    c.output_dir = "outputs/fusionportable"
    c.eval.map_icp_m = 1.0  # the GT map (a survey) is registered on its own: refine its alignment by ICP
    return apply_budget(c, budget or default_budget("paper"))
