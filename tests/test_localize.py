"""A finished run registers every input scan to its result (scans_report.csv's registration residual), and
neld-localize poses the same scans, written in another world frame, back in the run's map."""

import csv
import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import make_tiny_config

from neld_jax import lie, run
from neld_jax.data.poses import read_kitti, read_tum
from neld_jax.synthetic.generator import make_sequence, write_generic

SCENE = {
    "num_scans": 6,
    "num_beams": 32,
    "num_columns": 512,
    "gt_map_points": 1000,
    "scene_size_m": 40.0,
    "trajectory_radius_m": 6.0,
    "max_range_m": 30.0,
    "range_noise_m": 0.0,
}
# The other recording's world: turned 40 deg and 6 m away from the run's
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OTHER_FRAME = lie.se3_exp_float64(np.array([[6.0, -3.0, 0.5, 0.0, 0.0, np.radians(40.0)]]))[0]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A short run on 6 synthetic scans 3 s apart whose input is the truth, every other one a keyframe."""
    root = tmp_path_factory.mktemp("localize")
    seq = make_sequence(SCENE)
    write_generic(dataclasses.replace(seq, poses=seq.gt_poses), root / "data")
    c = make_tiny_config(str(root / "run"), steps=20)
    c.data.format, c.data.root = "generic", str(root / "data")
    c.data.keyframe_interval_s, c.data.max_range_m = 6.0, 30.0
    c.data.keyframe_distance_m, c.data.keyframe_angle_deg = 1000.0, 360.0  # the time cap alone: every other scan
    c.viz.record, c.mapping.enabled, c.eval.crispness_draws, c.eval.crispness_queries = False, False, 1, 2000
    for k in ("rot", "trans"):  # a few steps of training: the poses stay at the truth
        c.train[f"pose_lr_{k}_init"], c.train[f"pose_lr_{k}_final"] = 1e-6, 1e-7
    run.run(c, progress=False)
    return root, seq


def read_report(path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_the_run_registers_the_scans_between_keyframes_and_reports_their_residuals(finished_run):
    root, seq = finished_run
    rows = read_report(root / "run" / "scans_report.csv")
    assert [row["keyframe"] for row in rows] == ["1", "0", "1", "0", "1", "0"]
    assert all(row["registration_residual_m"] == "" for row in rows if row["keyframe"] == "1")
    assert all(0 <= float(row["registration_residual_m"]) < 0.05 for row in rows if row["keyframe"] == "0")
    _, T = read_tum(root / "run" / "poses_optimized.txt")
    assert np.linalg.norm(T[:, :3, 3] - seq.gt_poses[:, :3, 3], axis=1).max() < 0.02


def test_localize_poses_scans_of_another_frame_in_the_run_map(finished_run):
    root, seq = finished_run
    # The same scans in another world frame, each a little off (odometry)
    rng = np.random.default_rng(3)
    noise = lie.se3_exp_float64(np.concatenate([rng.normal(0, 0.05, (6, 3)), rng.normal(0, 0.005, (6, 3))], 1))
    other = dataclasses.replace(seq, poses=OTHER_FRAME @ seq.gt_poses @ noise, gt_poses=None, gt_map=None)
    write_generic(other, root / "other")
    out = root / "localized"
    done = subprocess.run(
        [
            sys.executable,
            "bin/localize.py",
            f"--run={root / 'run'}",
            "--config=configs/generic.py",
            f"--config.data.root={root / 'other'}",
            f"--config.output_dir={out}",
            "--config.data.max_range_m=30.0",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "6 of 6 scans registered" in done.stdout and "global registration" in done.stdout

    _, T = read_tum(out / "poses_localized.txt")
    _, T_run = read_tum(root / "run" / "poses_optimized.txt")
    assert np.linalg.norm(T[:, :3, 3] - T_run[:, :3, 3], axis=1).max() < 0.03
    angles = np.degrees(np.linalg.norm(lie.se3_log_float64(np.linalg.inv(T_run) @ T)[:, 3:], axis=1))
    assert angles.max() < 0.3
    np.testing.assert_allclose(read_kitti(out / "poses_localized.kitti")[:, :3], T[:, :3], atol=1e-6)
    rows = read_report(out / "scans_report.csv")
    assert len(rows) == 6 and all(row["flag"] == "" and float(row["fitness"]) > 0.5 for row in rows)


def test_localize_without_a_finished_run_is_one_error_line(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "bin/localize.py",
            f"--run={tmp_path}",
            "--config=configs/demo.py",
            f"--config.output_dir={tmp_path / 'out'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"error: --run: {tmp_path / 'map_raw.ply'} not found (give a finished run's output folder)"
    ]
