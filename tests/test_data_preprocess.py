"""Keyframes, range crop, voxel grid, normalisation into the cube, and training rays."""

import logging
import re

import numpy as np
import pytest
from conftest import poses_to_world
from scipy.spatial.transform import Rotation

from neld_jax.data.preprocess import (
    KeyframeSettings,
    crop_range,
    keyframe_caps,
    preprocess,
    select_keyframes,
    voxel_downsample,
)
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.field.normalize import Normalization, fit_normalization
from neld_jax.training.rays import build_rays


def make_sequence(num_scans=5, points_per_scan=400, seed=0, timestamps=None):
    rng = np.random.default_rng(seed)
    scans = [rng.uniform(-30, 30, size=(points_per_scan, 3)) for _ in range(num_scans)]
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[:, :3, :3] = Rotation.random(num_scans, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(loc=[100.0, -50.0, 10.0], scale=20.0, size=(num_scans, 3))
    return Sequence(scans=scans, poses=poses, timestamps=timestamps, gt_poses=poses.copy(), name="t", source="test")


# ---------------------------------------------------------------------------------------------- keyframes


def test_select_keyframes_interval_is_a_cap_on_the_gap():
    times = np.array([0.0, 1.0, 2.9, 3.0, 4.0, 5.9, 6.5, 9.49, 9.5])
    # each keyframe the last scan within 3 s of the one before
    np.testing.assert_array_equal(select_keyframes(times, 3.0), [0, 3, 5, 6])
    # the last scan where the input is sparse at its end: 2.99 s after the scan before, beyond half the cap
    np.testing.assert_array_equal(select_keyframes(times[:-1], 3.0), [0, 3, 5, 6, 7])
    np.testing.assert_array_equal(select_keyframes(times[:5], 3.0), [0, 3])  # 1 s: within half the cap


def test_scans_sparser_than_the_time_cap_are_all_keyframes():
    times = np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(2.9, 3.0, size=29)])  # 30 scans 2.9-3.0 s apart
    np.testing.assert_array_equal(select_keyframes(times, 3.0), np.arange(30))


def test_ten_hz_sweeps_give_a_keyframe_every_3_s():
    times = 0.1 * np.arange(301)
    np.testing.assert_array_equal(select_keyframes(times, 3.0), np.arange(0, 300, 30))


def test_keyframes_follow_the_motion_whichever_cap_comes_first():
    times = 0.1 * np.arange(100)  # 10 s at 10 Hz, 1 m a sweep (a car), turning 10 degrees a sweep from sweep 50 on
    poses = np.tile(np.eye(4), (100, 1, 1))
    poses[:, 0, 3] = np.arange(100.0)
    poses[50:, :3, :3] = Rotation.from_euler("z", 10.0 * np.arange(50)[:, None], degrees=True).as_matrix()
    kept = select_keyframes(times, 3.0, poses=poses, distance_m=8.0, angle_deg=30.0)
    np.testing.assert_array_equal(kept[:6], [0, 8, 16, 24, 32, 40])  # 8 m apart
    assert np.all(np.diff(kept[kept >= 52]) == 3) and kept[-1] == 98  # 30 degrees apart
    np.testing.assert_array_equal(select_keyframes(times, 3.0, poses=poses), np.arange(0, 100, 30))


def test_the_range_sets_the_distance_cap_when_the_time_cap_is_on():
    assert keyframe_caps(3.0, 0.0, 0.0, 80.0) == (8.0, 30.0)  # a tenth of the range, 30 degrees
    assert keyframe_caps(3.0, 2.0, 10.0, 80.0) == (2.0, 10.0)  # as given
    assert keyframe_caps(0.0, 0.0, 0.0, 80.0) == (0.0, 0.0)  # a layout whose scans are keyframes: every scan


def test_select_keyframes_exact_spacing_keeps_all_even_at_epoch_times():
    times = 1650000000.1 + 3.0 * np.arange(10)
    np.testing.assert_array_equal(select_keyframes(times, 3.0), np.arange(10))


def test_select_keyframes_keeps_all_without_times_or_interval():
    np.testing.assert_array_equal(select_keyframes(np.array([0.0, 0.1, 0.2]), 0.0), [0, 1, 2])
    np.testing.assert_array_equal(select_keyframes(None, 3.0, num_scans=4), [0, 1, 2, 3])


# ---------------------------------------------------------------------------------------------- crop & voxel


def test_crop_range():
    points = np.array([[0.1, 0, 0], [0.5, 0, 0], [3, 4, 0], [80, 0, 0], [0, 0, 80.01]])
    np.testing.assert_array_equal(crop_range(points, 0.5, 80.0), points[1:4])


def test_voxel_downsample_one_point_per_voxel():
    rng = np.random.default_rng(0)
    # Tight clusters (0.2 m) around integer centres; the point at (-0.1, -0.1, -0.1) fixes the cloud's
    # minimum corner, so the voxel grid (Open3D puts it half a voxel below that corner) splits no cluster.
    centres = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 7.0, 2.0]])
    points = np.concatenate([c + rng.uniform(-0.1, 0.1, size=(50, 3)) for c in centres])
    points[0] = -0.1
    down = voxel_downsample(points, 1.0)
    assert down.shape == (3, 3)
    # each output is the centroid of its voxel's points
    expected = np.array([points[i * 50 : (i + 1) * 50].mean(axis=0) for i in range(3)])
    order = np.lexsort(down.T[::-1])
    np.testing.assert_allclose(down[order], expected[np.lexsort(expected.T[::-1])], atol=1e-9)
    np.testing.assert_array_equal(voxel_downsample(points, 0.0), points)


def test_preprocess_subsets_everything_and_logs(caplog):
    times = np.array([0.0, 1.0, 3.0, 4.0, 6.5])
    seq = make_sequence(timestamps=times)
    with caplog.at_level(logging.INFO, logger="neld_jax.data.preprocess"):
        out = preprocess(
            seq, KeyframeSettings(keyframe_interval_s=3.0, min_range=1.0, max_range=25.0, voxel_size=2.0, max_scans=2)
        )
    assert out.num_scans == 2
    np.testing.assert_array_equal(out.timestamps, [0.0, 3.0])
    np.testing.assert_array_equal(out.poses, seq.poses[[0, 2]])
    np.testing.assert_array_equal(out.gt_poses, seq.gt_poses[[0, 2]])
    for scan in out.scans:
        distances = np.linalg.norm(scan, axis=1)
        assert 0 < len(scan) < 400
        # voxel centroids of points in 1-25 m lie within that range up to the voxel diagonal
        assert distances.max() <= 25.0 + 2.0 * np.sqrt(3)
    messages = " ".join(r.getMessage() for r in caplog.records)
    assert "kept 2 of 5 scans" in messages
    assert "800 raw" in messages  # 2 kept scans of 400 points


def test_preprocess_scan_left_empty_is_an_error():
    seq = make_sequence(num_scans=2)
    seq.scans[1] = np.full((10, 3), 0.1)  # everything inside the 0.5 m minimum range
    with pytest.raises(DataError, match="test: scan 1 has no points left"):  # synthetic: no file to name
        preprocess(seq, KeyframeSettings(keyframe_interval_s=0.0))


def test_preprocess_scan_left_empty_names_its_file_and_time_after_keyframes(tmp_path):
    """The case to guard: after keyframe selection the index would point at the wrong scan; the file does not."""
    from neld_jax.data.generic import load_generic
    from neld_jax.synthetic.generator import write_generic

    times = np.array([0.0, 1.0, 3.0, 4.0, 6.0, 9.5])  # keyframes 0, 2 and 4
    src = make_sequence(num_scans=6, timestamps=times)
    src.scans[4] = np.random.default_rng(1).uniform(-0.2, 0.2, size=(500, 3))  # all within 0.5 m
    write_generic(src, tmp_path)
    seq = load_generic(tmp_path)
    with pytest.raises(
        DataError,
        match=re.escape(
            f"{tmp_path}: scans/000004.pcd (t=6.000000) has no points left within 0.5-80.0 m (it had 500 points, "
        ),
    ):
        preprocess(seq, KeyframeSettings(keyframe_interval_s=3.0))


# ---------------------------------------------------------------------------------------------- normalisation


def test_normalization_puts_points_and_origins_in_cube():
    seq = make_sequence()
    norm = fit_normalization(seq.scans, seq.poses, margin=0.9)
    largest = 0.0
    for scan, pose in zip(seq.scans, seq.poses):
        world = scan @ pose[:3, :3].T + pose[:3, 3]
        normalised = norm.points_to_normalized(world)
        assert np.abs(normalised).max() <= 0.9 + 1e-12
        largest = max(largest, np.abs(normalised).max())
    origins = norm.poses_to_normalized(seq.poses)[:, :3, 3]
    assert np.abs(origins).max() <= 0.9 + 1e-12
    assert largest == pytest.approx(0.9)  # the box touches the margin on its largest axis


def test_normalization_round_trips_and_is_consistent():
    seq = make_sequence()
    norm = fit_normalization(seq.scans, seq.poses)
    points = seq.scans[0] @ seq.poses[0, :3, :3].T + seq.poses[0, :3, 3]
    np.testing.assert_allclose(norm.points_to_world(norm.points_to_normalized(points)), points, atol=1e-10)
    normalised_poses = norm.poses_to_normalized(seq.poses)
    np.testing.assert_array_equal(normalised_poses[:, :3, :3], seq.poses[:, :3, :3])
    np.testing.assert_allclose(poses_to_world(norm, normalised_poses), seq.poses, atol=1e-10)
    # a point at range r along a ray lands at normalised range r * scale from the normalised origin
    p_sensor = seq.scans[0][0]
    r = np.linalg.norm(p_sensor)
    p_norm = normalised_poses[0, :3, :3] @ p_sensor * norm.scale + normalised_poses[0, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(p_norm - normalised_poses[0, :3, 3]), norm.ranges_to_normalized(r))
    np.testing.assert_allclose(norm.points_to_normalized(points[0]), p_norm, atol=1e-12)


def test_normalization_bad_record():
    with pytest.raises(DataError, match="invalid normalisation"):
        Normalization(scale=-1.0, offset=np.zeros(3))


# ---------------------------------------------------------------------------------------------- rays


def test_build_rays_directions_ranges_and_subsampling():
    seq = make_sequence(num_scans=3, points_per_scan=100)
    seq.scans[1][5] = 0.0  # a point at the origin has no direction and is dropped
    norm = fit_normalization(seq.scans, seq.poses)
    rays = build_rays(seq, norm)
    assert rays.num_rays == 299
    assert rays.directions.dtype == np.float32 and rays.ranges.dtype == np.float32
    assert rays.scan_index.dtype == np.int32
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=1), 1.0, atol=1e-6)
    first = seq.scans[0]
    np.testing.assert_allclose(
        rays.directions[:100] * rays.ranges[:100, None] / norm.scale, first, rtol=1e-5, atol=1e-4
    )
    np.testing.assert_array_equal(np.bincount(rays.scan_index), [100, 99, 100])

    sub = build_rays(seq, norm, max_rays_per_scan=40, seed=1)
    np.testing.assert_array_equal(np.bincount(sub.scan_index), [40, 40, 40])
    again = build_rays(seq, norm, max_rays_per_scan=40, seed=1)
    np.testing.assert_array_equal(sub.ranges, again.ranges)
