"""evaluate_run on a hand-made output folder, the table, and bin/evaluate.py's error line."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax.data.poses import write_kitti, write_tum
from neld_jax.errors import DataError
from neld_jax.writing import export
from neld_jax.writing.evaluate import (
    RunArtifacts,
    Trajectory,
    evaluate,
    evaluate_run,
    find_trajectories,
    format_table,
    map_files,
    match_poses,
)

REPO = Path(__file__).resolve().parents[1]


def _scene_and_run(root: Path, num_scans: int = 6):
    """A GT world (three walls and a floor), scans seen from GT poses, and a run folder in which
    'optimized' is the GT trajectory expressed in another (odometry) frame and 'initial' is drifted."""
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-10, 10, (4000, 2)), np.zeros(4000)]
    wall_x = np.c_[np.full(1500, 10.0), rng.uniform(-10, 10, 1500), rng.uniform(0, 3, 1500)]
    wall_y = np.c_[rng.uniform(-10, 10, 1500), np.full(1500, 10.0), rng.uniform(0, 3, 1500)]
    wall_y2 = np.c_[rng.uniform(-10, 10, 1500), np.full(1500, -10.0), rng.uniform(0, 3, 1500)]
    world = np.concatenate([floor, wall_x, wall_y, wall_y2])

    gt = np.tile(np.eye(4), (num_scans, 1, 1))
    gt[:, :3, :3] = Rotation.from_euler("z", np.linspace(0, 60, num_scans)[:, None], degrees=True).as_matrix()
    gt[:, :3, 3] = np.c_[np.linspace(-4, 4, num_scans), np.sin(np.arange(num_scans)), np.full(num_scans, 1.5)]
    scans = [(world - pose[:3, 3]) @ pose[:3, :3] for pose in gt]  # every scan sees the whole (small) world

    odometry_frame = np.eye(4)
    odometry_frame[:3, :3] = Rotation.from_euler("xyz", [3, -2, 40], degrees=True).as_matrix()
    odometry_frame[:3, 3] = [100.0, -50.0, 2.0]
    optimized = odometry_frame @ gt
    drift = np.tile(np.eye(4), (num_scans, 1, 1))
    drift[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, (num_scans, 3))).as_matrix()
    drift[:, :3, 3] = rng.normal(0, 0.3, (num_scans, 3))
    initial = odometry_frame @ gt @ drift

    stamps = 100.0 + 3.0 * np.arange(num_scans)
    root.mkdir(parents=True, exist_ok=True)
    write_tum(root / "poses_gt.txt", stamps, gt)
    export.write_poses(root, "poses_optimized", stamps, optimized)
    export.write_poses(root, "poses_initial", stamps, initial)
    export.write_point_cloud(root / "map_gt.ply", world)
    export.write_raw_map(root / "map_raw.ply", scans, optimized)
    export.write_raw_map(root / "map_raw_initial.ply", scans, initial)
    rendered = world[::2] + rng.normal(0, 0.03, (len(world[::2]), 3))  # a rendered map, in the odometry frame
    rendered = rendered @ odometry_frame[:3, :3].T + odometry_frame[:3, 3]
    export.write_point_cloud(root / "map_rendered.ply", rendered)
    export.write_json(root / "metrics.json", {"run": {"steps": 5}})
    return gt, stamps


def test_evaluate_run_measures_and_aligns(tmp_path):
    run = tmp_path / "run"
    _scene_and_run(run)
    result = evaluate_run(run)

    assert list(result["methods"]) == ["initial", "optimized"]
    optimized, initial = result["methods"]["optimized"], result["methods"]["initial"]
    assert optimized["matching"] == "timestamp" and optimized["matched_poses"] == 6
    assert optimized["ate"]["translation_rmse_m"] < 1e-6
    assert initial["ate"]["translation_rmse_m"] > 0.1
    assert optimized["rpe"]["translation_rmse_m"] < 1e-6 < initial["rpe"]["translation_rmse_m"]
    # The maps were moved from the odometry frame into the GT frame with the ATE alignment.
    assert optimized["raw_map"]["aligned_to_gt"]
    assert optimized["raw_map"]["chamfer_l1_m"] < 1e-3
    assert optimized["raw_map"]["cutoff_m"] == 1.0
    assert initial["raw_map"]["chamfer_l1_m"] > 10 * optimized["raw_map"]["chamfer_l1_m"]
    assert optimized["rendered_map"]["cutoff_m"] is None
    assert optimized["rendered_map"]["precision"] > 0.99  # 3 cm noise << 20 cm threshold
    assert 0.5 < optimized["rendered_map"]["f1"] < 1.0  # half the points: some GT points have none near
    assert 0.02 < optimized["rendered_map"]["inlier_rmse_m"] < 0.1

    saved = json.loads((run / "metrics.json").read_text())
    assert saved["run"] == {"steps": 5}  # the trainer's section is kept
    assert saved["evaluation"]["methods"]["optimized"]["ate"]["translation_rmse_m"] == pytest.approx(
        optimized["ate"]["translation_rmse_m"]
    )
    for name in ("trajectory.png", "pose_error.png", "error_histogram.png"):
        assert (run / name).stat().st_size > 1000
        assert name in result["plots"]

    table = format_table(result)
    lines = table.splitlines()
    assert "ATE RMSE [m]" in lines[0] and "raw L1-CD [cm]" in lines[0] and "rend. F1 [%]" in lines[0]
    assert lines[2].startswith("initial") and lines[3].startswith("optimized")
    assert "-" in lines[2].split()  # initial has no rendered map


def test_the_arrays_a_run_holds_measure_as_the_files_it_wrote(tmp_path):
    # The run evaluates what it has in memory (evaluate); neld-evaluate reads the same from the folder: the same
    # figures, to the files' precision. The arrays are the ones _scene_and_run wrote.
    run = tmp_path / "run"
    gt, stamps = _scene_and_run(run)
    from_files = evaluate_run(run, write_plots=False)
    read = __import__("open3d").io.read_point_cloud
    maps = {
        "optimized": {
            "raw": np.asarray(read(str(run / "map_raw.ply")).points),
            "rendered": np.asarray(read(str(run / "map_rendered.ply")).points),
        },
        "initial": {"raw": np.asarray(read(str(run / "map_raw_initial.ply")).points)},
    }
    from neld_jax.data.poses import read_kitti

    gt_map = np.asarray(read(str(run / "map_gt.ply")).points)
    artifacts = RunArtifacts(
        {name: Trajectory(stamps, read_kitti(run / f"poses_{name}.kitti")) for name in ("initial", "optimized")},
        maps,
        Trajectory(stamps, gt),
        gt_map,
    )
    in_memory = evaluate(artifacts).result
    assert set(in_memory) == {"threshold_m", "raw_cutoff_m", "map_icp_m", "methods"}
    assert list(in_memory["methods"]) == list(from_files["methods"]) == ["initial", "optimized"]
    for name, entry in in_memory["methods"].items():
        on_disk = from_files["methods"][name]
        assert entry.keys() == on_disk.keys()
        assert entry["poses"] == on_disk["poses"] == f"poses_{name}.txt"
        assert entry["raw_map"]["file"] == on_disk["raw_map"]["file"]
        for section in ("ate", "rpe", "raw_map"):
            for key, value in entry[section].items():
                if isinstance(value, float):
                    assert value == pytest.approx(on_disk[section][key], rel=1e-6, abs=1e-9), (name, section, key)
    # No GT at all: the trajectories are listed, nothing measured.
    bare = evaluate(RunArtifacts(artifacts.trajectories, {})).result["methods"]["optimized"]
    assert bare == {"poses": "poses_optimized.txt", "num_poses": 6}


def test_explicit_gt_in_kitti_format_matches_by_order(tmp_path):
    run = tmp_path / "run"
    gt, _ = _scene_and_run(run)
    (run / "poses_gt.txt").unlink()
    write_kitti(tmp_path / "gt.kitti", gt)
    result = evaluate_run(run, gt_poses_path=tmp_path / "gt.kitti", write_plots=False)
    assert result["methods"]["optimized"]["matching"] == "order"
    assert result["methods"]["optimized"]["ate"]["translation_rmse_m"] < 1e-6
    assert result["plots"] == []


def test_without_ground_truth_only_trajectories_are_listed(tmp_path):
    run = tmp_path / "run"
    _scene_and_run(run)
    (run / "poses_gt.txt").unlink()
    (run / "map_gt.ply").unlink()
    result = evaluate_run(run)
    assert "ate" not in result["methods"]["optimized"] and "raw_map" not in result["methods"]["optimized"]
    assert result["plots"] == ["trajectory.png"]
    assert "no ground-truth poses" in format_table(result)


def test_discovery_of_methods_and_maps(tmp_path):
    for name in (
        "poses_gt.txt",
        "poses_zeta.txt",
        "poses_optimized.txt",
        "poses_baseline.txt",
        "poses_initial.txt",
        "map_raw.ply",
        "map_raw_baseline.ply",
        "map_rendered.ply",
    ):
        (tmp_path / name).write_text("")
    assert list(find_trajectories(tmp_path)) == ["initial", "baseline", "optimized", "zeta"]
    assert set(map_files(tmp_path, "optimized")) == {"raw", "rendered"}
    assert map_files(tmp_path, "baseline")["raw"].name == "map_raw_baseline.ply"
    assert map_files(tmp_path, "initial") == {}


def test_match_poses_errors_name_both_counts():
    with pytest.raises(DataError, match="5 poses to 7 ground-truth poses"):
        match_poses(np.arange(5.0), np.arange(7.0) + 1000, 5, 7, "est.txt")
    est_idx, gt_idx, how = match_poses(np.arange(5.0), np.arange(5.0) + 1000, 5, 5, "est.txt")
    assert how == "order" and list(est_idx) == list(gt_idx) == [0, 1, 2, 3, 4]


def test_missing_folder_or_poses_are_data_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        evaluate_run(tmp_path / "nope")
    with pytest.raises(DataError, match="no trajectory"):
        evaluate_run(tmp_path)


def _run_cli(*args):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.run(
        [sys.executable, str(REPO / "bin" / "evaluate.py"), *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_cli_prints_table_and_one_line_errors(tmp_path):
    run = tmp_path / "run"
    _scene_and_run(run)
    ok = _run_cli(f"--output_dir={run}")
    assert ok.returncode == 0, ok.stderr
    assert "optimized" in ok.stdout and "ATE RMSE" in ok.stdout

    missing = _run_cli(f"--output_dir={tmp_path / 'nope'}")
    assert missing.returncode == 1
    assert missing.stderr.strip().splitlines() == [f"error: {tmp_path / 'nope'}: output directory does not exist"]

    empty = tmp_path / "empty"
    empty.mkdir()
    no_poses = _run_cli(f"--output_dir={empty}")
    assert no_poses.returncode == 1
    assert no_poses.stderr.startswith("error: ") and "Traceback" not in no_poses.stderr


def test_gt_map_in_a_slightly_different_frame_is_aligned_by_icp(tmp_path):
    """The GT map is given in a frame rotated 2 deg and shifted 0.3 m from the GT trajectory's (a survey map
    registered on its own): the trajectory alignment alone leaves the maps apart; refined by ICP they meet."""
    run = tmp_path / "run"
    _scene_and_run(run)
    world = np.asarray(__import__("open3d").io.read_point_cloud(str(run / "map_gt.ply")).points)
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("xyz", [0.5, -0.5, 2.0], degrees=True).as_matrix()
    offset[:3, 3] = [0.3, -0.2, 0.1]
    export.write_point_cloud(run / "map_gt.ply", world @ offset[:3, :3].T + offset[:3, 3])
    plain = evaluate_run(run, write_plots=False)["methods"]["optimized"]["raw_map"]
    assert plain["icp"] is None and plain["chamfer_l1_m"] > 0.1
    refined = evaluate_run(run, write_plots=False, map_icp_m=1.0)
    raw = refined["methods"]["optimized"]["raw_map"]
    assert raw["chamfer_l1_m"] < 0.02 and raw["aligned_to_gt"]
    assert raw["icp"]["fitness"] > 0.9 and 0.2 < raw["icp"]["correction_m"] < 1.0
    assert 1.0 < raw["icp"]["correction_deg"] < 3.5
    assert refined["map_icp_m"] == 1.0
    # the rendered map moves with the same correction
    assert refined["methods"]["optimized"]["rendered_map"]["precision"] > 0.99


def test_gt_map_without_gt_poses_is_aligned_by_icp_from_the_odometry_frame(tmp_path):
    run = tmp_path / "run"
    _scene_and_run(run)
    (run / "poses_gt.txt").unlink()
    world = np.asarray(__import__("open3d").io.read_point_cloud(str(run / "map_gt.ply")).points)
    # GT map in the odometry frame up to 3 deg and 0.4 m: ICP from the identity finds it
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_euler("xyz", [3, -2, 40], degrees=True).as_matrix()
    frame[:3, 3] = [100.0, -50.0, 2.0]
    near = np.eye(4)
    near[:3, :3] = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
    near[:3, 3] = [0.4, 0.0, 0.0]
    moved = frame @ near  # 3 deg about the scene's own centre, not about the far-away odometry origin
    export.write_point_cloud(run / "map_gt.ply", world @ moved[:3, :3].T + moved[:3, 3])
    result = evaluate_run(run, write_plots=False, map_icp_m=1.0)
    raw = result["methods"]["optimized"]["raw_map"]
    assert raw["aligned_to_gt"] and raw["chamfer_l1_m"] < 0.02
