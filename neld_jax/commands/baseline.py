"""neld-baseline (bin/baseline.py): the classical baseline on a sequence, into a run's output folder.

    neld-baseline --config=configs/demo.py
    neld-baseline --config=configs/generic.py --config.data.root=/data/seq --config.output_dir=runs/seq

Loads and preprocesses the sequence exactly like neld-train, registers the keyframes (Open3D scan-to-map ICP, a
loop-closed pose graph, multi-view refinement; neld_jax.baseline), carries their corrections to every input scan,
writes poses_baseline.txt / .kitti and map_raw_baseline.ply (and the input's and the ground truth's where the folder
lacks them, so that it can be evaluated on its own), the raw map's crispness into metrics.json and, where ground
truth exists, evaluates the folder (initial / baseline / optimized if present).
"""

import dataclasses
import logging
import time
from pathlib import Path

from neld_jax.cli import main_with_config

logger = logging.getLogger(__name__)


def run_baseline(config, progress: bool = True) -> dict:
    """Run the baseline on config.data into config.output_dir. Returns {"seconds", "crispness": {method: summary},
    "evaluation": evaluate_run's result or None, "report": what the baseline decided}."""
    from neld_jax.baseline import BaselineSettings, register_sequence
    from neld_jax.judging import judge
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.writing.evaluate import GT_MAP_FILES, GT_POSES_FILE, evaluate_run
    from neld_jax.writing.export import (
        read_json,
        write_json,
        write_keyframe_poses,
        write_point_cloud,
        write_poses,
        write_raw_map,
    )

    loaded, keyframes = load_keyframes(config.data)
    settings = BaselineSettings.from_config(config)
    t0 = time.perf_counter()
    result = register_sequence(keyframes.scans, keyframes.poses, settings, progress=progress)
    seconds = time.perf_counter() - t0
    poses, report = result.poses, result.report()

    out = Path(config.output_dir)
    voxel = float(config.mapping.voxel_size_m)
    write_keyframe_poses(out, "poses_baseline", loaded, keyframes, poses)
    write_raw_map(out / "map_raw_baseline.ply", keyframes.scans, poses, voxel_size=voxel)
    if not (out / "poses_initial.txt").exists():
        write_poses(out, "poses_initial", loaded.timestamps, loaded.poses)
    if not (out / "map_raw_initial.ply").exists():
        write_raw_map(out / "map_raw_initial.ply", keyframes.scans, keyframes.poses, voxel_size=voxel)
    if loaded.gt_poses is not None and not (out / GT_POSES_FILE).exists():
        write_poses(out, GT_POSES_FILE[: -len(".txt")], loaded.timestamps, loaded.gt_poses)
    if keyframes.gt_map is not None and not any((out / name).exists() for name in GT_MAP_FILES):
        write_point_cloud(out / GT_MAP_FILES[0], keyframes.gt_map)
    crisp, _ = judge.map_crispness(keyframes, {"initial": keyframes.poses, "baseline": poses}, config.eval)
    # Its sections join the folder's metrics.json (a run's, say): its methods' crispness beside the run's.
    crisp = {**read_json(out / "metrics.json").get("crispness", {}), **crisp}
    write_json(
        out / "metrics.json",
        {
            "crispness": crisp,
            "baseline": {"seconds": round(seconds, 2), "decided": report, "settings": dataclasses.asdict(settings)},
        },
        merge=True,
    )
    logger.info("baseline outputs written to %s (registration took %.1f s)", out, seconds)
    evaluation = None
    if keyframes.gt_poses is not None or keyframes.gt_map is not None:
        evaluation = evaluate_run(out, map_icp_m=float(config.eval.map_icp_m))
    return {"seconds": seconds, "crispness": crisp, "evaluation": evaluation, "report": report}


def job(config) -> None:
    from neld_jax.judging.judge import format_crispness_table
    from neld_jax.writing.evaluate import format_table

    result = run_baseline(config)
    print(f"baseline ({result['seconds']:.0f} s) written to {config.output_dir}")
    print(format_crispness_table(result["crispness"]))
    if result["evaluation"] is not None:
        print(format_table(result["evaluation"]))


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()
