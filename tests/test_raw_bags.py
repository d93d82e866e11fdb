"""neld_jax.data.bags.raw_bags: raw LiDAR sweeps read from ROS1 bags written with rosbags' writer (Ouster-style clouds),
and the FusionPortable / Newer College 2021 downloads (raw_bag_downloads) loaded by their format loaders."""

import numpy as np
import pytest
from fixture_writers import write_lidar_bag
from raw_bag_downloads import (
    write_fusionportable_download,
    write_newer_college_download,
)
from scipy.spatial.transform import Rotation

from neld_jax.config import defaults
from neld_jax.data import fusionportable, newer_college
from neld_jax.data.bags.raw_bags import read_lidar_bag
from neld_jax.errors import DataError

T0 = 1_650_000_000.123456789
ROWS, COLUMNS = 8, 64
TOPIC = "/os_cloud_node/points"


def _sweeps(n, seed=0):
    """n organised sweeps of ROWS x COLUMNS points on three planes (floor, two walls); t = column / COLUMNS * 0.1 s.
    Returns (stamps [n], scans, point times)."""
    rng = np.random.default_rng(seed)
    scans, times = [], []
    for _ in range(n):
        azimuth = np.tile(np.linspace(0, 2 * np.pi, COLUMNS, endpoint=False), ROWS)
        elevation = np.repeat(np.linspace(-0.4, 0.2, ROWS), COLUMNS)
        direction = np.stack(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
        )
        # distance to the first of: floor z = -1.5, walls x = +-6 (and y = +-8)
        with np.errstate(divide="ignore"):
            candidates = np.stack([-1.5 / direction[:, 2], 6 / np.abs(direction[:, 0]), 8 / np.abs(direction[:, 1])])
        candidates[candidates <= 0] = np.inf
        scans.append(direction * candidates.min(axis=0)[:, None] + rng.normal(0, 0.01, (ROWS * COLUMNS, 3)))
        times.append(np.tile(np.arange(COLUMNS) / COLUMNS * 0.1, ROWS))
    return T0 + 0.1 * np.arange(n), scans, times


def _poses(n, seed=1):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("zyx", np.cumsum(rng.uniform(-0.05, 0.05, (n, 3)), axis=0)).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.uniform(0.05, 0.2, (n, 3)), axis=0)
    return poses


def test_round_trip_keeps_stamps_points_and_times(tmp_path):
    stamps, scans, times = _sweeps(3)
    write_lidar_bag(tmp_path / "a.bag", TOPIC, "os_sensor", stamps, scans, times, rows=ROWS)
    sweeps = read_lidar_bag(tmp_path / "a.bag", TOPIC)
    assert sweeps.frame_id == "os_sensor" and sweeps.time_field == "t" and sweeps.clouds_read == 3
    assert sweeps.labels == [f"a.bag:{TOPIC}#{i:06d}" for i in range(3)]
    np.testing.assert_allclose(sweeps.timestamps, stamps, rtol=0, atol=1e-6)
    for got, want, got_t, want_t in zip(sweeps.scans, scans, sweeps.point_times, times):
        assert got.dtype == np.float64 and got.shape == want.shape
        np.testing.assert_array_equal(got, want.astype(np.float32))
        np.testing.assert_allclose(got_t, want_t, rtol=0, atol=1e-9)


def test_invalid_points_are_dropped_with_their_times_and_counted(tmp_path):
    stamps, scans, times = _sweeps(2)
    scans[1][[3, 70]] = 0.0  # no return
    scans[1][5, 1] = np.nan
    scans[0][9, 2] = np.inf
    write_lidar_bag(tmp_path / "a.bag", TOPIC, "os_sensor", stamps, scans, times, rows=ROWS)
    sweeps = read_lidar_bag(tmp_path / "a.bag", TOPIC)
    assert sweeps.dropped == {"non-finite": 2, "zero": 2}
    keep = np.ones(ROWS * COLUMNS, bool)
    keep[[3, 5, 70]] = False
    np.testing.assert_array_equal(sweeps.scans[1], scans[1][keep].astype(np.float32))
    np.testing.assert_allclose(sweeps.point_times[1], times[1][keep], atol=1e-9)
    assert sweeps.scans[0].shape[0] == sweeps.point_times[0].shape[0] == ROWS * COLUMNS - 1


def test_clouds_without_a_time_field_give_no_point_times(tmp_path, caplog):
    stamps, scans, _ = _sweeps(2)
    write_lidar_bag(tmp_path / "a.bag", TOPIC, "os_sensor", stamps, scans, None)
    sweeps = read_lidar_bag(tmp_path / "a.bag", TOPIC)
    assert sweeps.point_times is None and sweeps.time_field == ""
    assert sum("no per-point time" in r.getMessage() for r in caplog.records) == 1


def test_a_missing_topic_or_bag_is_one_line_naming_the_bag_and_its_topics(tmp_path):
    stamps, scans, times = _sweeps(1)
    write_lidar_bag(tmp_path / "a.bag", TOPIC, "os_sensor", stamps, scans, times)
    with pytest.raises(DataError) as info:
        read_lidar_bag(tmp_path / "a.bag", "/velodyne_points")
    message = str(info.value)
    assert "\n" not in message and str(tmp_path / "a.bag") in message and "/velodyne_points" in message
    assert f"{TOPIC} (sensor_msgs/msg/PointCloud2)" in message
    with pytest.raises(DataError, match="b.bag: bag does not exist"):
        read_lidar_bag(tmp_path / "b.bag", TOPIC)


def _data_cfg(fmt, root):
    cfg = defaults().data
    cfg.format, cfg.root = fmt, str(root)
    return cfg


def test_fusionportable_download_loads_from_the_bag(tmp_path):
    n = 4
    stamps, scans, times = _sweeps(n)
    gt = _poses(n)
    folder = write_fusionportable_download(
        tmp_path / "FusionPortable", "20220216_canteen_day", stamps, scans, times, gt, rows=ROWS
    )
    seq = fusionportable.load(_data_cfg("fusionportable", folder))
    assert seq.poses is None and seq.num_scans == n and seq.name == "20220216_canteen_day"
    assert seq.files[2] == f"20220216_canteen_day.bag:{fusionportable.LIDAR_TOPICS[0]}#000002"
    assert seq.point_times is not None and all(len(t) == len(s) for t, s in zip(seq.point_times, seq.scans))
    np.testing.assert_allclose(seq.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(seq.gt_poses, gt, atol=1e-6)
    np.testing.assert_allclose(seq.scans[0], scans[0], atol=1e-5)


def test_newer_college_download_in_parts_loads_in_time_order(tmp_path):
    n = 5
    stamps, scans, times = _sweeps(n)
    gt = _poses(n)
    root = write_newer_college_download(tmp_path / "quad_easy", "quad-easy", stamps, scans, times, gt, parts=2)
    seq = newer_college.load(_data_cfg("newer_college", root))
    assert seq.poses is None and seq.num_scans == n
    assert seq.files[0].startswith("2021-07-01-10-37-38_0-quad-easy.bag:/os_cloud_node/points#")
    assert seq.files[-1] == "2021-07-01-10-37-38_1-quad-easy.bag:/os_cloud_node/points#000001"
    np.testing.assert_allclose(seq.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(seq.gt_poses, gt, atol=1e-6)
    for got, want in zip(seq.point_times, times):
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_import_without_odometry_writes_raw_sweeps_that_the_generic_loader_reads_with_times(tmp_path):
    from neld_jax.data.bags.rosbag_import import ImportSettings, import_bag
    from neld_jax.data.generic import load_generic
    from neld_jax.data.poses import write_tum

    n = 3
    stamps, scans, times = _sweeps(n)
    scans[0][4] = 0.0
    write_lidar_bag(tmp_path / "raw.bag", TOPIC, "os_sensor", stamps, scans, times, rows=ROWS)
    # no /Odometry in the bag
    result = import_bag(tmp_path / "raw.bag", tmp_path / "out", ImportSettings(cloud_topic=TOPIC), progress=False)
    assert result.odometry_topic == "" and result.scans_written == n and result.point_times_written == n
    assert result.points_skipped == {"non-finite": 0, "zero": 1} and "KISS-ICP" in result.note
    out = tmp_path / "out"
    assert not (out / "poses.txt").exists()
    names = sorted(p.stem for p in (out / "scans").iterdir())
    assert names == [f"{t:.9f}" for t in stamps] == sorted(p.stem for p in (out / "point_times").iterdir())
    # poses.txt added by hand: the layout's stamps and times read back with the scans
    write_tum(out / "poses.txt", stamps, np.tile(np.eye(4), (n, 1, 1)))
    seq = load_generic(out)
    np.testing.assert_allclose(seq.timestamps, stamps, atol=1e-6)
    keep = np.ones(ROWS * COLUMNS, bool)
    keep[4] = False
    np.testing.assert_allclose(seq.point_times[0], times[0][keep], atol=1e-9)
    np.testing.assert_allclose(seq.scans[0], scans[0][keep], atol=1e-5)
    np.testing.assert_allclose(seq.point_times[2], times[2], atol=1e-9)
