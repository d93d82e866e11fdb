"""The public datasets as users have them, each as a small fixture written here: FusionPortable's devkit export
with the download's groundtruth/ tree, Newer College 2021 (imported clouds + gt-nc CSV in the base frame), HBA's
pcd/ + pose.json; explicit ground-truth paths, frame offsets, and the log line when evaluation is skipped."""

import json
import logging
import os
import subprocess
import sys

import ml_collections
import numpy as np
import pytest
from fixture_writers import write_newer_college_csv
from scipy.spatial.transform import Rotation

from neld_jax.config import defaults as base_config
from neld_jax.data.ground_truth import published_offset
from neld_jax.data.poses import rotation_to_quat, write_tum
from neld_jax.data.scans import write_scan
from neld_jax.errors import ConfigError, DataError
from neld_jax.geometry import invert_poses
from neld_jax.steps.inputs import load_sequence

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEQ = "20220216_canteen_day"
T0 = 1644987000


def write_hba_poses(path, poses: np.ndarray) -> None:
    """Write poses [S, 4, 4] as HBA's pose.json ('tx ty tz qw qx qy qz', full precision)."""
    q = rotation_to_quat(poses[:, :3, :3])
    lines = [" ".join(repr(float(v)) for v in (*pose[:3, 3], qi[3], qi[0], qi[1], qi[2])) for pose, qi in zip(poses, q)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def _data_cfg(fmt, root, **fields):
    cfg = base_config().data
    cfg.format, cfg.root = fmt, str(root)
    for key, value in fields.items():
        cfg[key] = value
    return cfg


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", np.cumsum(rng.uniform(0.0, 0.3, n))[:, None]).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.uniform(0.1, 0.4, (n, 3)), axis=0)
    return poses


def _scans(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-15, 15, (40 + i, 3)).astype(np.float32).astype(np.float64) for i in range(n)]


def _stamp(t):
    sec = int(np.floor(t))
    return sec, int(round((t - sec) * 1e9))


def write_fusionportable(base, scans, body_poses, times, gt_lidar=None, gt_times=None, gt_map=None):
    """The download's tree (fusionportable.github.io/dataset/fusionportable) with the devkit's FAST-LIO2 export in
    the sequence folder, written in the devkit's own text formats (pointcloud.py, odometry.py)."""
    root = base / "sensor_data" / "handheld" / SEQ
    points = root / "algorithm_result" / "ouster00_undistort" / "points"
    (points / "data").mkdir(parents=True)
    for i, scan in enumerate(scans):
        header = (
            "# .PCD v.7 - Point Cloud Data file format\nVERSION .7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
            f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {len(scan)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {len(scan)}\nDATA ascii\n"
        )
        rows = "".join(f"{np.float32(x)} {np.float32(y)} {np.float32(z)} 7.0\n" for x, y, z in scan)
        (points / "data" / f"{i:06d}.pcd").write_text(header + rows)
    (points / "timestamps.txt").write_text("".join("{}.{:09d}\n".format(*_stamp(t)) for t in times))
    (root / "algorithm_result" / "odometry").mkdir(parents=True)
    lines = []
    for t, pose in zip(times, body_poses):
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        lines.append(
            "{}.{:09d} ".format(*_stamp(t))
            + "".join("{:3f} ".format(v) for v in pose[:3, 3])
            + "".join("{:3f} ".format(v) for v in q)
            + "\n"
        )
    (root / "algorithm_result" / "odometry" / "odometry.txt").write_text("".join(lines))
    if gt_lidar is not None:
        write_tum(base / "groundtruth" / "traj" / f"{SEQ}.txt", gt_times, gt_lidar)
    if gt_map is not None:
        write_scan(base / "groundtruth" / "map" / SEQ / "merged_scan.pcd", gt_map)
    return root


def test_fusionportable_devkit_export_with_the_downloads_ground_truth(tmp_path):
    n = 5
    scans, body, times = _scans(n), _poses(n), T0 + 0.1 * np.arange(n) + 0.0371
    T_lidar_body = published_offset("fusionportable", "body_imu")
    gt_lidar = body @ invert_poses(T_lidar_body)  # the LiDAR's ground truth that goes with these body poses
    gt_map = np.random.default_rng(5).normal(size=(300, 3))
    root = write_fusionportable(tmp_path / "FusionPortable", scans, body, times, gt_lidar, times + 0.002, gt_map)
    seq = load_sequence(_data_cfg("fusionportable", root))
    assert seq.files[0] == "algorithm_result/ouster00_undistort/points/data/000000.pcd" and seq.num_scans == n
    for got, want in zip(seq.scans, scans):
        np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_allclose(seq.timestamps, times, atol=1e-6)
    np.testing.assert_allclose(seq.poses, body, atol=2e-5)  # odometry.txt has 6 decimals
    np.testing.assert_allclose(seq.gt_poses, body, atol=1e-9)  # ground truth moved into the body frame
    np.testing.assert_allclose(seq.gt_map, gt_map, atol=1e-6)
    # raw Ouster clouds: the ground truth is already in their frame
    ouster = load_sequence(_data_cfg("fusionportable", root, scan_frame="ouster00"))
    np.testing.assert_allclose(ouster.gt_poses, gt_lidar, atol=1e-9)
    with pytest.raises(ConfigError, match="data.scan_frame: 'os_sensor' is not a frame of fusionportable"):
        load_sequence(_data_cfg("fusionportable", root, scan_frame="os_sensor"))


def test_explicit_ground_truth_paths_and_what_is_missing(tmp_path, caplog):
    n = 4
    scans, body, times = _scans(n), _poses(n), T0 + 0.1 * np.arange(n)
    root = write_fusionportable(tmp_path / "FP", scans, body, times)
    with caplog.at_level(logging.WARNING):
        seq = load_sequence(_data_cfg("fusionportable", root))
    assert seq.gt_poses is None and seq.gt_map is None
    assert "no ground-truth trajectory (looked for groundtruth/traj/<sequence>.txt" in caplog.text
    assert "pose errors (ATE/RPE) will not be evaluated" in caplog.text and "map errors will not be" in caplog.text
    with pytest.raises(DataError, match=r"nope.txt: data.gt_poses_path is set but the file does not exist"):
        load_sequence(_data_cfg("fusionportable", root, gt_poses_path=str(tmp_path / "nope.txt")))
    # explicit files anywhere, with an explicit offset (identity here)
    write_tum(tmp_path / "elsewhere" / "gt.txt", times, body)
    write_scan(tmp_path / "elsewhere" / "map.ply", np.ones((10, 3)))
    seq = load_sequence(
        _data_cfg(
            "fusionportable",
            root,
            gt_poses_path=str(tmp_path / "elsewhere" / "gt.txt"),
            gt_map_path=str(tmp_path / "elsewhere" / "map.ply"),
            gt_from_scan=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        )
    )
    np.testing.assert_allclose(seq.gt_poses, body, atol=1e-9)
    assert seq.gt_map.shape == (10, 3)
    # ground truth that stops before the last scan: the scan is named, never paired with a neighbour's pose
    write_tum(tmp_path / "short.txt", times[:-1], body[:-1])
    with pytest.raises(
        DataError,
        match=r"short.txt: 1 of 4 scans have no pose within 0.05 s \(first: "
        r"algorithm_result/ouster00_undistort/points/data/000003.pcd",
    ):
        load_sequence(_data_cfg("fusionportable", root, gt_poses_path=str(tmp_path / "short.txt")))
    with pytest.raises(ConfigError, match="data.gt_from_scan: expected 7 numbers"):
        load_sequence(_data_cfg("fusionportable", root, gt_from_scan=(0.0, 1.0)))


def test_generic_layout_takes_explicit_ground_truth_too(tmp_path):
    n = 3
    for i, scan in enumerate(_scans(n)):
        write_scan(tmp_path / "seq" / "scans" / f"{i:06d}.pcd", scan)
    poses, times = _poses(n), 10.0 + np.arange(n)
    write_tum(tmp_path / "seq" / "poses.txt", times, poses)
    write_tum(tmp_path / "gt.txt", times + 0.01, poses @ invert_poses(poses[:1]))
    seq = load_sequence(_data_cfg("generic", tmp_path / "seq", gt_poses_path=str(tmp_path / "gt.txt")))
    np.testing.assert_allclose(seq.gt_poses, poses @ invert_poses(poses[:1]), atol=1e-9)


def write_newer_college_2021(root, scans, lidar_poses, times, frame="os_sensor"):
    """bin/import_rosbag.py's output (scans/, poses.txt) plus the 2021 ground truth as downloaded: base frame."""
    for i, scan in enumerate(scans):
        write_scan(root / "scans" / f"{i:06d}.pcd", scan)
    write_tum(root / "poses.txt", times, lidar_poses)
    base = lidar_poses @ invert_poses(published_offset("newer_college_2021", frame))
    gt_times = np.sort(np.r_[times + 0.001, times[:-1] + 0.05])  # denser than the scans, a little off
    gt = np.concatenate([base, base[:-1]])[np.argsort(np.r_[times + 0.001, times[:-1] + 0.05])]
    write_newer_college_csv(root / "gt-nc-quad-easy.csv", gt_times, gt)
    return base


def test_newer_college_2021_ground_truth_in_the_base_frame(tmp_path):
    n = 4
    scans, lidar, times = _scans(n), _poses(n), 1623000000.0 + 0.1 * np.arange(n)
    base = write_newer_college_2021(tmp_path, scans, lidar, times)
    assert np.abs(base[:, :3, 3] - lidar[:, :3, 3]).max() > 0.05  # the base frame is not the LiDAR's
    seq = load_sequence(_data_cfg("newer_college", tmp_path))
    np.testing.assert_allclose(seq.gt_poses, lidar, atol=1e-9)
    np.testing.assert_allclose(seq.poses, lidar, atol=1e-9)
    imu = load_sequence(_data_cfg("newer_college", tmp_path, scan_frame="os_imu"))
    np.testing.assert_allclose(imu.gt_poses, base @ published_offset("newer_college_2021", "os_imu"), atol=1e-9)


def test_hba_layout(tmp_path):
    n = 4
    scans, poses = _scans(n), _poses(n)
    for i, scan in enumerate(scans):
        write_scan(tmp_path / "park" / "pcd" / f"{i:05d}.pcd", scan)  # zero-padded, as HBA's pcd_name_fill_num=5
    write_hba_poses(tmp_path / "park" / "pose.json", poses)
    line = (tmp_path / "park" / "pose.json").read_text().splitlines()[1].split()
    q = Rotation.from_matrix(poses[1, :3, :3]).as_quat()
    np.testing.assert_allclose(
        [float(v) for v in line[3:]],
        [q[3], q[0], q[1], q[2]] if q[3] >= 0 else [-q[3], -q[0], -q[1], -q[2]],
        atol=1e-12,
    )  # qw first
    seq = load_sequence(_data_cfg("hba", tmp_path / "park"))
    assert seq.files == [f"pcd/{i:05d}.pcd" for i in range(n)] and seq.timestamps is None
    np.testing.assert_allclose(seq.poses, poses, atol=1e-9)
    for got, want in zip(seq.scans, scans):
        np.testing.assert_allclose(got, want, atol=1e-6)
    write_tum(tmp_path / "gt.txt", np.arange(n) * 1.0, poses)  # no scan stamps: matched by order
    with_gt = load_sequence(_data_cfg("hba", tmp_path / "park", gt_poses_path=str(tmp_path / "gt.txt")))
    np.testing.assert_allclose(with_gt.gt_poses, poses, atol=1e-9)
    (tmp_path / "park" / "pcd" / "00002.pcd").unlink()
    with pytest.raises(DataError, match=r"pcd: scan index 2 is missing"):
        load_sequence(_data_cfg("hba", tmp_path / "park"))


def test_fusionportable_download_to_train_end_to_end(tmp_path):
    """README's FusionPortable steps on a tiny synthetic sequence written in the devkit's layout: bin/train.py with
    configs/fusionportable.py reads it, finds the ground truth above the sequence folder and evaluates."""
    from neld_jax.synthetic.generator import make_sequence

    syn = make_sequence(
        ml_collections.ConfigDict(
            {
                "num_scans": 4,
                "num_beams": 8,
                "num_columns": 64,
                "gt_map_points": 2000,
                "scene_size_m": 30.0,
                "trajectory_radius_m": 5.0,
                "max_range_m": 30.0,
            }
        )
    )
    times = T0 + 0.5 * np.arange(4)
    T_lidar_body = published_offset("fusionportable", "body_imu")
    root = write_fusionportable(
        tmp_path / "FusionPortable",
        syn.scans,
        syn.poses,
        times,
        syn.gt_poses @ invert_poses(T_lidar_body),
        times,
        syn.gt_map,
    )
    out = tmp_path / "out"
    args = [
        "--config=configs/fusionportable.py:cpu",
        f"--config.data.root={root}",
        f"--config.output_dir={out}",
        "--config.data.keyframe_interval_s=0",
        "--config.model.width=16",
        "--config.model.depth=2",
        "--config.model.skip_layers=(1,)",
        "--config.model.pos_freqs=6",
        "--config.model.dir_freqs=2",
        "--config.sampling.coarse_stages=(8,)",
        "--config.sampling.fine_stages=(4,)",
        "--config.train.steps=8",
        "--config.train.batch_rays=32",
        "--config.train.log_every=4",
        "--config.data.max_rays_per_scan=128",
        "--config.mapping.enabled=False",
        "--config.eval.crispness_queries=300",
        "--config.eval.crispness_radius_m=3.0",
    ]
    result = subprocess.run(
        [sys.executable, os.path.join(REPO, "bin", "train.py"), *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
        env={**os.environ, "NELD_JAX_HUGEPAGES": "0"},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    evaluation = json.loads((out / "metrics.json").read_text())["evaluation"]
    assert evaluation["gt_poses"].endswith("poses_gt.txt") and evaluation["map_icp_m"] == 1.0
    initial = evaluation["methods"]["initial"]
    assert initial["matched_poses"] == 4 and initial["ate"]["translation_rmse_m"] > 0.0
    assert initial["raw_map"]["icp"]["fitness"] > 0.5


def test_ground_truth_fields_from_the_command_line(tmp_path):
    """README's rosbag route for FusionPortable: an imported run (generic layout) with the download's ground truth
    and the published extrinsic given on the command line, as bin/train.py parses it."""
    from pathlib import Path

    from absl import flags
    from ml_collections import config_flags

    n = 3
    body, times = _poses(n), T0 + 0.1 * np.arange(n)
    for i, scan in enumerate(_scans(n)):
        write_scan(tmp_path / "run" / "scans" / f"{i:06d}.pcd", scan)
    write_tum(tmp_path / "run" / "poses.txt", times, body)
    T_lidar_body = published_offset("fusionportable", "body_imu")
    write_tum(tmp_path / "groundtruth" / "traj" / f"{SEQ}.txt", times, body @ invert_poses(T_lidar_body))
    configs = Path(REPO) / "configs"
    argv = [
        "train.py",
        f"--config={configs / 'generic.py'}",
        f"--config.data.root={tmp_path / 'run'}",
        f"--config.data.gt_poses_path={tmp_path / 'groundtruth' / 'traj' / f'{SEQ}.txt'}",
        "--config.data.gt_from_scan=(-0.037354, 0.006824, -0.020190, 0.004028, -0.002505, 0.003725, 0.999982)",
    ]
    flag_values = flags.FlagValues()
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    seq = load_sequence(flag_values.config.data)
    np.testing.assert_allclose(seq.gt_poses, body, atol=1e-6)


def test_fusionportable_raw_ouster_export_in_the_lidar_frame(tmp_path):
    """The devkit's raw export (write_bag_to_data.ipynb: organised Ouster clouds with its 9-field ASCII header) with
    the user's odometry of the LiDAR: the ground truth (the LiDAR's) needs no offset."""
    n = 3
    root = tmp_path / "FusionPortable" / "sensor_data" / "handheld" / SEQ
    points = root / "raw_data" / "ouster00" / "points"
    (points / "data").mkdir(parents=True)
    scans = [np.random.default_rng(i).uniform(1, 9, (2, 3, 3)) for i in range(n)]
    for i, scan in enumerate(scans):
        header = (
            "# .PCD v.7 - Point Cloud Data file format\nVERSION .7\n"
            "FIELDS x y z intensity t reflectivity ring ambient range\nSIZE 4 4 4 4 4 2 1 2 4\n"
            "TYPE F F F F U U U U U\nCOUNT 1 1 1 1 1 1 1 1 1\nWIDTH 3\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\n"
            "POINTS 6\nDATA ascii\n"
        )
        rows = "".join(
            f"{np.float32(x)} {np.float32(y)} {np.float32(z)} 3.0 1234 7 {k} 9 1000\n"
            for k, (x, y, z) in enumerate(scan.reshape(-1, 3))
        )
        (points / "data" / f"{i:06d}.pcd").write_text(header + rows)
    times = T0 + 0.1 * np.arange(n)
    (points / "timestamps.txt").write_text("".join("{}.{:09d}\n".format(*_stamp(t)) for t in times))
    lidar = _poses(n)
    write_tum(root / "odometry.txt", times, lidar)
    write_tum(tmp_path / "FusionPortable" / "groundtruth" / "traj" / f"{SEQ}.txt", times, lidar)
    seq = load_sequence(_data_cfg("fusionportable", root))
    assert seq.files[0] == "raw_data/ouster00/points/data/000000.pcd"
    np.testing.assert_allclose(seq.scans[1], scans[1].reshape(-1, 3), atol=1e-5)
    np.testing.assert_allclose(seq.gt_poses, lidar, atol=1e-9)


def test_ground_truth_stamped_at_the_start_of_the_scan(tmp_path):
    """Scans stamped at their end (FAST-LIO2) against a 10 Hz ground truth stamped at the start of each scan:
    scan i's stamp is scan i+1's ground-truth stamp, so the last scan has none (named); gt_time_offset_s=-0.1
    pairs each scan with its own ground truth."""
    n = 4
    scans, lidar, times = _scans(n), _poses(n), 1623000000.0 + 0.1 * np.arange(1, n + 1)
    for i, scan in enumerate(scans):
        write_scan(tmp_path / "scans" / f"{i:06d}.pcd", scan)
    write_tum(tmp_path / "poses.txt", times, lidar)
    write_tum(tmp_path / "gt.txt", times - 0.1, lidar)
    with pytest.raises(DataError, match=r"gt.txt: 1 of 4 scans have no pose within 0.05 s \(first: scans/000003.pcd"):
        load_sequence(_data_cfg("generic", tmp_path, gt_poses_path=str(tmp_path / "gt.txt")))
    seq = load_sequence(_data_cfg("generic", tmp_path, gt_poses_path=str(tmp_path / "gt.txt"), gt_time_offset_s=-0.1))
    np.testing.assert_allclose(seq.gt_poses, lidar, atol=1e-9)
    np.testing.assert_allclose(seq.timestamps, times, atol=1e-9)  # the scans keep their own stamps
