"""neld-evaluate (bin/evaluate.py): evaluate a run's output folder against ground truth and print a table.

    neld-evaluate --output_dir=outputs/demo
    neld-evaluate --output_dir=runs/canteen --gt_poses=/data/canteen/gt_poses.txt --gt_map=/data/canteen/gt_map.pcd

Reads poses_*.txt and map_*.ply from the folder (neld_jax/writing/evaluate.py), writes plots and merges the numbers into
OUTPUT_DIR/metrics.json under "evaluation".
"""

import logging
import os

from absl import flags

from neld_jax.cli import main_with_flags

OUTPUT_DIR = flags.DEFINE_string("output_dir", None, "Folder written by neld-train or neld-baseline.", required=True)
GT_POSES = flags.DEFINE_string(
    "gt_poses",
    None,
    "Ground-truth trajectory (TUM, KITTI or Newer College CSV); default OUTPUT_DIR/poses_gt.txt if present.",
)
GT_MAP = flags.DEFINE_string("gt_map", None, "Ground-truth map (.ply/.pcd); default OUTPUT_DIR/map_gt.ply if present.")
THRESHOLD = flags.DEFINE_float("threshold", 0.2, "F1 / inlier distance threshold in metres.")
RAW_CUTOFF = flags.DEFINE_float("raw_cutoff", 1.0, "Chamfer cutoff of raw maps in metres.")
MAP_ICP = flags.DEFINE_float(
    "map_icp_m",
    0.0,
    "Refine the map alignment by ICP with this correspondence distance in metres (0: the trajectory alignment alone).",
)


def evaluate() -> int:
    from neld_jax.writing.evaluate import evaluate_run, format_table

    result = evaluate_run(
        OUTPUT_DIR.value,
        gt_poses_path=GT_POSES.value,
        gt_map_path=GT_MAP.value,
        threshold=THRESHOLD.value,
        raw_cutoff=RAW_CUTOFF.value,
        map_icp_m=MAP_ICP.value,
    )
    print(format_table(result))
    print(f"metrics written to {os.path.join(OUTPUT_DIR.value, 'metrics.json')}")
    return 0


def main() -> None:
    main_with_flags(evaluate, log_level=logging.WARNING, doc=__doc__)


if __name__ == "__main__":
    main()
