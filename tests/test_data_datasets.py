"""Dataset loaders (generic, FusionPortable, Newer College), timestamp matching and load_sequence dispatch."""

import ml_collections
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax.config import base_config
from neld_jax.data.datasets import (DEFAULT_TIMESTAMP_TOLERANCE_S, load_fusionportable, load_generic,
                                    load_newer_college, load_sequence)
from neld_jax.data.poses import write_newer_college_csv, write_tum
from neld_jax.data.scans import write_scan
from neld_jax.data.sequence import Sequence, match_by_timestamp
from neld_jax.errors import ConfigError, DataError


def make_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (n, 1))).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    return poses


def make_scans(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-10, 10, size=(30 + 5 * i, 3)) for i in range(n)]


def write_generic_folder(root, scans, poses, times, ext=".npy", gt=None, gt_map=None, names=None):
    for i, scan in enumerate(scans):
        write_scan(root / "scans" / f"{names[i] if names else f'{i:06d}'}{ext}", scan)
    write_tum(root / "poses.txt", times, poses)
    if gt is not None:
        write_tum(root / "gt_poses.txt", gt[0], gt[1])
    if gt_map is not None:
        write_scan(root / "gt_map.ply", gt_map)


# ---------------------------------------------------------------------------------------------- generic


def test_load_generic_by_order(tmp_path):
    scans, poses, times = make_scans(4), make_poses(4), np.arange(4) * 3.0
    gt = make_poses(4, seed=1)
    gt_map = np.random.default_rng(2).normal(size=(50, 3))
    write_generic_folder(tmp_path, scans, poses, times, gt=(times, gt), gt_map=gt_map)
    (tmp_path / "scans" / "README").write_text("not a scan")  # ignored with a warning
    seq = load_generic(tmp_path)
    assert seq.num_scans == 4 and seq.name == tmp_path.name and seq.source == str(tmp_path)
    for a, b in zip(seq.scans, scans):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses, gt, atol=1e-12)
    np.testing.assert_allclose(seq.timestamps, times)
    np.testing.assert_array_equal(seq.gt_map, gt_map)


def test_load_generic_matches_timestamp_names_when_counts_differ(tmp_path):
    scan_times = 1650000000.0 + np.array([0.0, 3.0, 6.0])
    pose_times = 1650000000.0 + np.arange(0.0, 7.0, 0.5)  # 14 poses at 2 Hz
    poses = make_poses(len(pose_times))
    names = [f"{t:.6f}" for t in scan_times]
    write_generic_folder(tmp_path, make_scans(3), poses, pose_times, ext=".pcd", names=names)
    seq = load_generic(tmp_path)
    np.testing.assert_allclose(seq.poses, poses[[0, 6, 12]], atol=1e-12)
    np.testing.assert_allclose(seq.timestamps, scan_times, atol=1e-6)


def test_load_generic_count_mismatch_names_both_counts(tmp_path):
    write_generic_folder(tmp_path, make_scans(3), make_poses(5), np.arange(5.0))
    # zero-padded frame numbers are not timestamps, so there is no matching by time
    with pytest.raises(DataError, match=r"poses\.txt: 5 poses but 3 scans"):
        load_generic(tmp_path)


def test_load_generic_timestamp_names_without_close_pose(tmp_path):
    names = ["100.000000", "200.000000"]
    write_generic_folder(tmp_path, make_scans(2), make_poses(3), np.array([100.0, 100.5, 101.0]), names=names)
    with pytest.raises(DataError, match=r"poses\.txt.*no pose within.*3 poses for 2 scans"):
        load_generic(tmp_path)


def test_load_generic_missing_root(tmp_path):
    with pytest.raises(DataError, match="data root .*nowhere does not exist"):
        load_generic(tmp_path / "nowhere")


def test_load_generic_missing_scans_folder(tmp_path):
    write_tum(tmp_path / "poses.txt", np.arange(2.0), make_poses(2))
    with pytest.raises(DataError, match=r"scans does not exist"):
        load_generic(tmp_path)


def test_load_generic_missing_pose_file(tmp_path):
    write_scan(tmp_path / "scans" / "000000.npy", make_scans(1)[0])
    with pytest.raises(DataError, match=r"poses\.txt.*does not exist"):
        load_generic(tmp_path)


def test_load_generic_empty_scan_folder(tmp_path):
    (tmp_path / "scans").mkdir()
    with pytest.raises(DataError, match="contains no scan files"):
        load_generic(tmp_path)


def test_load_generic_bad_scan_names_the_scan(tmp_path):
    write_generic_folder(tmp_path, make_scans(2), make_poses(2), np.arange(2.0), ext=".pcd")
    (tmp_path / "scans" / "000001.pcd").write_text("garbage")
    with pytest.raises(DataError, match=r"000001\.pcd"):
        load_generic(tmp_path)


# ---------------------------------------------------------------------------------------------- FusionPortable


def test_load_fusionportable(tmp_path):
    scan_times = 1649327985.0 + np.array([0.05, 3.05, 6.05])
    names = [f"{t:.6f}" for t in scan_times]
    for name, scan in zip(names, make_scans(3)):
        write_scan(tmp_path / "scans" / f"{name}.pcd", scan)
    odo_times = 1649327985.0 + np.arange(0.0, 7.0, 0.1)  # 10 Hz odometry
    odo = make_poses(len(odo_times))
    write_tum(tmp_path / "fastlio2_poses.txt", odo_times, odo)
    gt_times = 1649327985.0 + np.arange(0.0, 7.0, 0.01)  # 100 Hz ground truth
    gt = make_poses(len(gt_times), seed=3)
    write_tum(tmp_path / "traj" / "gt_poses.txt", gt_times, gt)
    seq = load_fusionportable(tmp_path)
    assert seq.num_scans == 3
    nearest = [int(np.argmin(np.abs(odo_times - t))) for t in scan_times]
    np.testing.assert_allclose(seq.poses, odo[nearest], atol=1e-12)
    nearest_gt = [int(np.argmin(np.abs(gt_times - t))) for t in scan_times]
    np.testing.assert_allclose(seq.gt_poses, gt[nearest_gt], atol=1e-12)
    assert seq.gt_map is None


def test_load_fusionportable_nanosecond_names(tmp_path):
    ns = [1649327985000000000, 1649327988000000000]
    for name, scan in zip(ns, make_scans(2)):
        write_scan(tmp_path / "scans" / f"{name}.bin", scan)
    write_tum(tmp_path / "poses.txt", np.array(ns) * 1e-9, make_poses(2))
    seq = load_fusionportable(tmp_path)
    np.testing.assert_allclose(seq.timestamps, np.array(ns) * 1e-9, atol=1e-6)


def test_load_fusionportable_requires_timestamp_names(tmp_path):
    write_scan(tmp_path / "scans" / "scan_a.pcd", make_scans(1)[0])
    write_tum(tmp_path / "poses.txt", np.zeros(1), make_poses(1))
    with pytest.raises(DataError, match=r"scan_a\.pcd"):
        load_fusionportable(tmp_path)


def test_load_fusionportable_missing_pose_file(tmp_path):
    write_scan(tmp_path / "scans" / "1.0.pcd", make_scans(1)[0])
    with pytest.raises(DataError, match="no initial pose file"):
        load_fusionportable(tmp_path)


# ---------------------------------------------------------------------------------------------- Newer College


def test_load_newer_college(tmp_path):
    secs, nsecs = [1583836591, 1583836594, 1583836597], [182590976, 182590976, 999999999]
    scan_times = np.array([s + n * 1e-9 for s, n in zip(secs, nsecs)])
    scans = make_scans(3)
    # written out of order on purpose: the loader sorts by time
    for i in (2, 0, 1):
        write_scan(tmp_path / "raw_format" / "ouster_scan" / f"cloud_{secs[i]}_{nsecs[i]}.pcd", scans[i])
    odo = make_poses(3)
    write_tum(tmp_path / "odometry.txt", scan_times + 0.01, odo)
    gt = make_poses(3, seed=9)
    write_newer_college_csv(tmp_path / "ground_truth" / "registered_poses.csv", scan_times, gt)
    seq = load_newer_college(tmp_path)
    np.testing.assert_allclose(seq.timestamps, scan_times, atol=1e-6)
    for a, b in zip(seq.scans, scans):
        np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_allclose(seq.poses, odo, atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses, gt, atol=1e-12)


def test_load_newer_college_bad_name(tmp_path):
    write_scan(tmp_path / "clouds" / "frame7.pcd", make_scans(1)[0])
    write_tum(tmp_path / "odometry.txt", np.zeros(1), make_poses(1))
    with pytest.raises(DataError, match=r"frame7\.pcd.*cloud_<sec>_<nsec>"):
        load_newer_college(tmp_path)


# ---------------------------------------------------------------------------------------------- Sequence & matching


def test_match_by_timestamp_nearest_and_unsorted():
    pose_times = np.array([3.0, 0.0, 1.0, 2.0])
    np.testing.assert_array_equal(match_by_timestamp([0.01, 1.96, 2.99], pose_times), [1, 3, 0])
    with pytest.raises(DataError, match="1 of 2 scans have no pose within 0.05 s"):
        match_by_timestamp([0.0, 5.0], pose_times)


def test_sequence_validates_counts():
    with pytest.raises(DataError, match="3 poses for 2 scans"):
        Sequence(scans=make_scans(2), poses=make_poses(3), name="x", source="here")
    with pytest.raises(DataError, match="1 timestamps for 2 scans"):
        Sequence(scans=make_scans(2), poses=make_poses(2), timestamps=[0.0])
    with pytest.raises(DataError, match="3 ground-truth poses .* for 2 scans"):
        Sequence(scans=make_scans(2), poses=make_poses(2), gt_poses=make_poses(3))
    seq = Sequence(scans=make_scans(2), poses=make_poses(2))
    assert seq.num_scans == 2


# ---------------------------------------------------------------------------------------------- dispatch


def test_load_sequence_dispatch(tmp_path):
    write_generic_folder(tmp_path, make_scans(2), make_poses(2), np.arange(2.0))
    cfg = ml_collections.ConfigDict({"format": "generic", "root": str(tmp_path)})
    assert load_sequence(cfg).num_scans == 2

    cfg = ml_collections.ConfigDict({"format": "synthetic", "root": "", "synthetic": {
        "num_scans": 2, "num_beams": 4, "num_columns": 32, "gt_map_points": 100}})
    seq = load_sequence(cfg)
    assert seq.num_scans == 2 and seq.source == "synthetic" and seq.gt_map.shape == (100, 3)


def test_load_sequence_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown format 'kitti360'"):
        load_sequence(ml_collections.ConfigDict({"format": "kitti360", "root": str(tmp_path)}))
    with pytest.raises(DataError, match="data root .*missing does not exist"):
        load_sequence(ml_collections.ConfigDict({"format": "newer_college", "root": str(tmp_path / "missing")}))
    with pytest.raises(ConfigError, match="unknown field 'num_scan'"):
        load_sequence(ml_collections.ConfigDict({"format": "synthetic", "synthetic": {"num_scan": 3}}))


def test_timestamp_tolerance_is_a_config_field_set_from_the_command_line(tmp_path):
    from pathlib import Path

    from absl import flags
    from ml_collections import config_flags

    assert base_config().data.timestamp_tol_s == DEFAULT_TIMESTAMP_TOLERANCE_S
    # Scans 80 ms after their poses; 2 scans, 3 poses, so they are matched by time.
    names = ["100.080000", "101.080000"]
    poses = make_poses(3)
    write_generic_folder(tmp_path, make_scans(2), poses, np.array([100.0, 101.0, 102.0]), names=names)
    configs = Path(__file__).resolve().parent.parent / "configs"
    argv = ["train.py", f"--config={configs / 'generic.py'}", f"--config.data.root={tmp_path}",
            "--config.data.timestamp_tol_s=0.1"]
    flag_values = flags.FlagValues()  # as bin/train.py parses it: a locked config
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    data_cfg = flag_values.config.data
    assert data_cfg.timestamp_tol_s == 0.1
    np.testing.assert_allclose(load_sequence(data_cfg).poses, poses[:2], atol=1e-12)
    data_cfg.timestamp_tol_s = DEFAULT_TIMESTAMP_TOLERANCE_S
    with pytest.raises(DataError, match="no pose within"):
        load_sequence(data_cfg)
