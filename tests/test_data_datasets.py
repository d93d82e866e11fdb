"""Dataset loaders (generic, FusionPortable, Newer College), timestamp matching and load_sequence dispatch."""

import logging
import re

import ml_collections
import numpy as np
import pytest
from fixture_writers import write_newer_college_csv
from scipy.spatial.transform import Rotation

from neld_jax.config import defaults as base_config
from neld_jax.data.fusionportable import load_fusionportable
from neld_jax.data.generic import load_generic
from neld_jax.data.layout import LoadOptions, align_poses
from neld_jax.data.newer_college import load_newer_college
from neld_jax.data.poses import write_tum
from neld_jax.data.preprocess import KeyframeSettings, preprocess
from neld_jax.data.scans import write_scan
from neld_jax.data.sequence import Sequence, check_pose_jumps
from neld_jax.data.timing import DEFAULT_TIMESTAMP_TOLERANCE_S, match_by_timestamp
from neld_jax.errors import ConfigError, DataError
from neld_jax.steps.inputs import load_sequence


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


def test_load_generic_count_mismatch_says_which_side_is_short(tmp_path):
    write_generic_folder(tmp_path, make_scans(3), make_poses(5), np.arange(5.0))
    # zero-padded frame numbers are not timestamps, so there is no matching by time
    with pytest.raises(
        DataError,
        match=r"poses\.txt has 5 poses but scans/ has 3 scans: the last 2 pose\(s\) "
        r"\(t=3\.000000, t=4\.000000\) have no scan; delete them or add",
    ):
        load_generic(tmp_path)


def test_load_generic_one_scan_more_than_poses_names_the_scan(tmp_path):
    """The end of a real recording: 332 scans and stamps, 331 poses (here 4 and 3)."""
    write_generic_folder(tmp_path, make_scans(4), make_poses(3), np.arange(3.0))
    with pytest.raises(
        DataError,
        match=r"^"
        + re.escape(
            f"{tmp_path}: poses.txt has 3 poses but scans/ has 4 "
            "scans: the last 1 scan(s) (scans/000003.npy) have no "
            "pose; delete them or add poses"
        ),
    ):
        load_generic(tmp_path)


def test_load_generic_drop_unmatched_tail_drops_and_names_the_scan(tmp_path, caplog):
    scans, poses = make_scans(4), make_poses(3)
    write_generic_folder(tmp_path, scans, poses, np.arange(3.0))
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.layout"):
        seq = load_generic(tmp_path, LoadOptions(drop_unmatched_tail=True))
    assert seq.num_scans == 3 and seq.files == ["scans/000000.npy", "scans/000001.npy", "scans/000002.npy"]
    np.testing.assert_allclose(seq.poses, poses, atol=1e-12)
    np.testing.assert_allclose(seq.timestamps, np.arange(3.0))
    assert any("scans/000003.npy" in r.getMessage() and "dropped" in r.getMessage() for r in caplog.records)


def test_align_poses_drop_unmatched_tail_is_limited_and_works_for_extra_poses(tmp_path, caplog):
    files = [tmp_path / "scans" / f"{i:06d}.pcd" for i in range(20)]
    with pytest.raises(DataError, match=r"the last 8 scan\(s\).*drops at most 5, not 8"):
        align_poses(
            make_poses(12), np.arange(12.0), tmp_path / "poses.txt", files, drop_unmatched_tail=True, root=tmp_path
        )
    # more poses than scans: the trailing poses go, every scan stays; without times the poses are numbered
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.layout"):
        out = align_poses(make_poses(21), None, tmp_path / "poses.kitti", files, drop_unmatched_tail=True)
    assert out.poses.shape == (20, 4, 4) and out.timestamps is None
    np.testing.assert_array_equal(out.scan_indices, np.arange(20))
    assert any("the last 1 pose(s) (pose 21) have no scan" in r.getMessage() for r in caplog.records)


def test_load_generic_unsorted_pose_times_by_order_is_an_error(tmp_path):
    write_generic_folder(tmp_path, make_scans(3), make_poses(3), np.array([0.0, 2.0, 1.0]))
    with pytest.raises(
        DataError,
        match=r"poses\.txt: timestamps are not in time order \(pose 3 at t=1\.000000 "
        r"comes after t=2\.000000.*sort it",
    ):
        load_generic(tmp_path)


def test_load_generic_unsorted_pose_times_by_time_is_a_warning(tmp_path, caplog):
    scan_times = 1650000000.0 + np.array([0.0, 3.0])
    pose_times = 1650000000.0 + np.array([3.0, 0.0, 1.5])  # counts differ: matched by time
    poses = make_poses(3)
    write_generic_folder(tmp_path, make_scans(2), poses, pose_times, names=[f"{t:.6f}" for t in scan_times])
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.layout"):
        seq = load_generic(tmp_path)
    np.testing.assert_allclose(seq.poses, poses[[1, 0]], atol=1e-12)
    assert any("not in time order" in r.getMessage() for r in caplog.records)


def test_load_generic_duplicate_pose_timestamp_names_both_lines(tmp_path):
    write_generic_folder(tmp_path, make_scans(4), make_poses(4), np.array([0.0, 1.0, 2.0, 1.0]))
    # line 1 is the header: the poses are on lines 2-5
    with pytest.raises(DataError, match=r"poses\.txt, lines 3 and 5: the same timestamp 1\.000000000 twice"):
        load_generic(tmp_path)


def test_load_generic_fills_files_and_keeps_them_through_preprocess(tmp_path):
    times = np.array([0.0, 1.0, 3.0, 4.0])
    write_generic_folder(tmp_path, make_scans(4), make_poses(4), times)
    seq = load_generic(tmp_path)
    assert seq.files == [f"scans/{i:06d}.npy" for i in range(4)]
    assert seq.scan_label(2) == "scans/000002.npy (t=3.000000)"
    out = preprocess(seq, KeyframeSettings(keyframe_interval_s=3.0, min_range=0.0, max_range=100.0, voxel_size=0.0))
    assert out.files == ["scans/000000.npy", "scans/000002.npy"]


def test_load_fusionportable_and_newer_college_fill_files(tmp_path):
    for name, scan in zip(["1.0", "4.0"], make_scans(2)):
        write_scan(tmp_path / "fp" / "scans" / f"{name}.pcd", scan)
    write_tum(tmp_path / "fp" / "poses.txt", np.array([1.0, 4.0]), make_poses(2))
    assert load_fusionportable(tmp_path / "fp").files == ["scans/1.0.pcd", "scans/4.0.pcd"]
    write_scan(tmp_path / "nc" / "clouds" / "cloud_5_0.pcd", make_scans(1)[0])
    write_tum(tmp_path / "nc" / "odometry.txt", np.array([5.0]), make_poses(1))
    assert load_newer_college(tmp_path / "nc").files == ["clouds/cloud_5_0.pcd"]


def test_load_generic_zero_and_infinite_points_are_dropped_and_counted(tmp_path, caplog):
    scans = make_scans(2)
    scans[1][:4] = 0.0  # "no return"
    scans[1][5] = [np.inf, 0.0, 1.0]
    write_generic_folder(tmp_path, scans, make_poses(2), np.arange(2.0))
    with caplog.at_level(logging.INFO, logger="neld_jax.data"):
        seq = load_generic(tmp_path)
    assert len(seq.scans[1]) == len(scans[1]) - 5 and np.isfinite(seq.scans[1]).all()
    assert seq.scans[1].any(axis=1).all()
    assert any(
        "dropped 5 of" in r.getMessage() and "1 NaN/infinite (in 1 scans), 4 at (0, 0, 0)" in r.getMessage()
        for r in caplog.records
    )


def test_load_generic_empty_scan_file_names_it(tmp_path):
    write_generic_folder(tmp_path, make_scans(3), make_poses(3), np.arange(3.0), ext=".pcd")
    (tmp_path / "scans" / "000001.pcd").write_bytes(b"")
    with pytest.raises(DataError, match=r"scans/000001\.pcd: scan file is empty \(0 bytes\)"):
        load_generic(tmp_path)


def test_load_generic_warns_about_a_pose_jump_naming_both_scans(tmp_path, caplog):
    poses = np.tile(np.eye(4), (20, 1, 1))
    poses[:, 0, 3] = 0.5 * np.arange(20)
    poses[12:, 0, 3] += 100.0  # odometry glitch between scans 11 and 12
    write_generic_folder(tmp_path, make_scans(20), poses, np.arange(20.0))
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.sequence"):
        load_generic(tmp_path)
    jumps = [r.getMessage() for r in caplog.records if "jumps" in r.getMessage()]
    assert len(jumps) == 1
    assert "100 m from scans/000011.npy (t=11.000000) to scans/000012.npy (t=12.000000)" in jumps[0]


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


def test_load_generic_without_pose_file_leaves_the_poses_to_the_odometry(tmp_path):
    write_scan(tmp_path / "scans" / "000000.npy", make_scans(1)[0])
    seq = load_generic(tmp_path)  # load_sequence makes them with KISS-ICP (tests/test_odometry.py)
    assert seq.poses is None and seq.num_scans == 1 and seq.timestamps is None


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
    # 2020 ground truth is in another body frame: moved into the LiDAR's with the published offset
    from neld_jax.data.ground_truth import published_offset

    np.testing.assert_allclose(seq.gt_poses, gt @ published_offset("newer_college_2020", "os_sensor"), atol=1e-12)
    identity = load_newer_college(tmp_path, LoadOptions(gt_from_scan=np.eye(4)))
    np.testing.assert_allclose(identity.gt_poses, gt, atol=1e-12)


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

    cfg = ml_collections.ConfigDict(
        {
            "format": "synthetic",
            "root": "",
            "synthetic": {"num_scans": 2, "num_beams": 4, "num_columns": 32, "gt_map_points": 100},
        }
    )
    seq = load_sequence(cfg)
    assert seq.num_scans == 2 and seq.source == "synthetic" and seq.gt_map.shape == (100, 3)


def test_load_sequence_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown format 'kitti360'"):
        load_sequence(ml_collections.ConfigDict({"format": "kitti360", "root": str(tmp_path)}))
    with pytest.raises(DataError, match="data root .*missing does not exist"):
        load_sequence(ml_collections.ConfigDict({"format": "newer_college", "root": str(tmp_path / "missing")}))
    with pytest.raises(ConfigError, match="unknown field 'num_scan'"):
        load_sequence(ml_collections.ConfigDict({"format": "synthetic", "synthetic": {"num_scan": 3}}))


def test_check_pose_jumps_threshold():
    # A car that waits for half the recording, then drives 2 m per scan: normal, no jump
    # (the median step is 0, which is why the default threshold uses the 90th percentile).
    poses = np.tile(np.eye(4), (40, 1, 1))
    poses[20:, 0, 3] = 2.0 * np.arange(1, 21)
    assert check_pose_jumps(poses).size == 0
    poses[30:, 1, 3] += 30.0  # a 30 m glitch between scans 29 and 30
    np.testing.assert_array_equal(check_pose_jumps(poses), [29])
    # an explicit threshold overrides the derived one
    np.testing.assert_array_equal(check_pose_jumps(poses, max_step_m=1.5), np.arange(19, 39))
    # a standing platform: centimetre jitter is below the 1 m floor
    still = np.tile(np.eye(4), (10, 1, 1))
    still[:, 2, 3] = np.random.default_rng(0).normal(scale=0.01, size=10)
    assert check_pose_jumps(still).size == 0
    assert check_pose_jumps(still[:1]).size == 0


def test_check_pose_jumps_lists_a_few_then_counts(caplog):
    poses = np.tile(np.eye(4), (60, 1, 1))
    poses[:, 0, 3] = 0.1 * np.arange(60)
    for i in range(10, 60, 10):
        poses[i:, 0, 3] += 50.0  # five jumps
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.sequence"):
        jumps = check_pose_jumps(poses, what="odo.txt")
    np.testing.assert_array_equal(jumps, [9, 19, 29, 39, 49])
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 4 and "from scan 9 to scan 10" in messages[0]
    assert messages[-1].startswith("odo.txt: 2 more pose jumps") and "(5 in all)" in messages[-1]


def test_sequence_files_validated_and_labels():
    with pytest.raises(DataError, match="1 file names for 2 scans"):
        Sequence(scans=make_scans(2), poses=make_poses(2), files=["a.pcd"])
    seq = Sequence(scans=make_scans(2), poses=make_poses(2), files=["scans/a.pcd", "scans/b.pcd"])
    assert seq.scan_label(1) == "scans/b.pcd"
    seq = Sequence(scans=make_scans(3), poses=make_poses(3), timestamps=[0.0, 1.0, 2.5])
    assert seq.scan_label(2) == "scan 2 (t=2.500000)"  # synthetic: no file to name
    with pytest.raises(DataError, match=r"scans/b\.pcd must have shape \[N, 3\]"):
        Sequence(scans=[np.zeros((3, 3)), np.zeros((3, 2))], poses=make_poses(2), files=["scans/a.pcd", "scans/b.pcd"])


def test_match_by_timestamp_names_the_scan_file():
    with pytest.raises(DataError, match=r"first: scans/5\.0\.pcd at t=5\.000000"):
        match_by_timestamp([0.0, 5.0], [0.0, 1.0], scan_labels=["scans/0.0.pcd", "scans/5.0.pcd"])


def test_load_newer_college_duplicate_ground_truth_stamp_names_both_lines(tmp_path):
    write_scan(tmp_path / "clouds" / "cloud_5_0.pcd", make_scans(1)[0])
    write_tum(tmp_path / "odometry.txt", np.array([5.0]), make_poses(1))
    write_newer_college_csv(tmp_path / "registered_poses.csv", np.array([4.0, 5.0, 5.0]), make_poses(3))
    with pytest.raises(DataError, match=r"registered_poses\.csv, lines 3 and 4: the same timestamp"):
        load_newer_college(tmp_path)


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
    argv = [
        "train.py",
        f"--config={configs / 'generic.py'}",
        f"--config.data.root={tmp_path}",
        "--config.data.timestamp_tol_s=0.1",
    ]
    flag_values = flags.FlagValues()  # as bin/train.py parses it: a locked config
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    data_cfg = flag_values.config.data
    assert data_cfg.timestamp_tol_s == 0.1
    np.testing.assert_allclose(load_sequence(data_cfg).poses, poses[:2], atol=1e-12)
    data_cfg.timestamp_tol_s = DEFAULT_TIMESTAMP_TOLERANCE_S
    with pytest.raises(DataError, match="no pose within"):
        load_sequence(data_cfg)
