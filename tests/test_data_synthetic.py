"""The synthetic sequence: determinism, scans on the scene surfaces, drift, GT map, generic round trip."""

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from neld_jax.data.generic import load_generic
from neld_jax.data.preprocess import select_keyframes
from neld_jax.errors import ConfigError
from neld_jax.synthetic.generator import (
    add_odometry_drift,
    car_drive,
    cast_scan,
    make_scene,
    make_scene_meshes,
    make_sequence,
    smooth_trajectory,
    spinning_lidar_directions,
    synthetic_defaults,
    write_generic,
)

SMALL = {"num_scans": 4, "num_beams": 16, "num_columns": 128, "gt_map_points": 5000}


@pytest.fixture(scope="module")
def small_sequence():
    return make_sequence(SMALL)


def test_scene_is_deterministic_and_seeded():
    a = make_scene_meshes(3, 60.0)
    b = make_scene_meshes(3, 60.0)
    c = make_scene_meshes(4, 60.0)
    assert len(a) == len(b) and len(a) > 20
    for ma, mb in zip(a, b):
        np.testing.assert_array_equal(np.asarray(ma.vertices), np.asarray(mb.vertices))
    assert len(a) != len(c) or any(
        not np.array_equal(np.asarray(x.vertices), np.asarray(y.vertices)) for x, y in zip(a, c)
    )


def test_lidar_directions():
    d = spinning_lidar_directions(num_beams=4, fov_up_deg=10.0, fov_down_deg=-20.0, num_columns=8)
    assert d.shape == (32, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    elevation = np.rad2deg(np.arcsin(d[:, 2])).reshape(4, 8)
    np.testing.assert_allclose(elevation[:, 0], [-20, -10, 0, 10], atol=1e-9)
    np.testing.assert_allclose(elevation, elevation[:, :1].repeat(8, axis=1), atol=1e-9)


def test_trajectory_is_smooth_level_and_follows_motion():
    poses = smooth_trajectory(36, 15.0, seed=2)
    np.testing.assert_allclose(np.linalg.det(poses[:, :3, :3]), 1.0, atol=1e-12)
    assert np.all(np.abs(poses[:, 2, 3] - 1.8) < 0.2)
    radii = np.linalg.norm(poses[:, :2, 3], axis=1)
    assert np.all((radii > 13.0) & (radii < 17.0))
    steps = np.diff(poses[:, :3, 3], axis=0)
    forward = poses[:-1, :3, 0]  # the sensor x axis points roughly along the motion
    cosines = np.sum(steps * forward, axis=1) / np.linalg.norm(steps, axis=1)
    assert cosines.min() > 0.9
    assert np.all(np.abs(poses[:, 2, 2]) > np.cos(np.deg2rad(5)))  # small roll and pitch


def test_drift_starts_exact_and_grows_with_length():
    gt = smooth_trajectory(40, 15.0, seed=0)
    errors = np.array(
        [np.linalg.norm(add_odometry_drift(gt, 0.05, 0.5, seed)[:, :3, 3] - gt[:, :3, 3], axis=1) for seed in range(30)]
    )
    assert np.all(errors[:, 0] == 0.0)
    mean = errors.mean(axis=0)
    assert mean[1] > 0.0
    assert mean[30:].mean() > 2.0 * mean[1:10].mean()
    # the relative motions of the drifted trajectory stay close to the true ones
    init = add_odometry_drift(gt, 0.05, 0.5, 0)
    rel_gt = np.linalg.inv(gt[:-1]) @ gt[1:]
    rel_init = np.linalg.inv(init[:-1]) @ init[1:]
    assert np.abs(rel_gt[:, :3, 3] - rel_init[:, :3, 3]).max() < 0.3


def test_drift_that_keeps_the_tilt_moves_position_and_heading_only():
    # The drift of an IMU-aided odometry: every scan keeps its true up axis; positions and headings drift as much as
    # in the six-axis walk, and the six-axis walk is what it always was (the same formula, the same draws).
    gt = smooth_trajectory(40, 15.0, seed=0)
    kept = add_odometry_drift(gt, 0.05, 0.5, 0, keep_tilt=True)
    free = add_odometry_drift(gt, 0.05, 0.5, 0)
    np.testing.assert_array_equal(kept[0], gt[0])
    np.testing.assert_allclose(kept[:, 2, :3], gt[:, 2, :3], atol=1e-12)  # up, seen from each sensor
    assert np.abs(free[:, 2, :3] - gt[:, 2, :3]).max() > 1e-3  # the six-axis walk tilts the scans
    assert np.linalg.norm(kept[:, :3, 3] - gt[:, :3, 3], axis=1)[-1] > 0.05
    heading = lambda poses: np.arctan2(poses[:, 1, 0], poses[:, 0, 0])  # noqa: E731
    assert np.degrees(np.abs(heading(kept) - heading(gt))).max() > 0.5
    rng = np.random.default_rng(0)
    rotation_noise, translation_noise = rng.normal(0, np.deg2rad(0.5), (39, 3)), rng.normal(0, 0.05, (39, 3))
    expected = gt.copy()
    for s in range(1, 40):
        noise = np.eye(4)
        noise[:3, :3], noise[:3, 3] = Rotation.from_rotvec(rotation_noise[s - 1]).as_matrix(), translation_noise[s - 1]
        expected[s] = expected[s - 1] @ np.linalg.inv(gt[s - 1]) @ gt[s] @ noise
    np.testing.assert_allclose(free, expected, atol=1e-9)


def test_sequence_is_deterministic(small_sequence):
    again = make_sequence(SMALL)
    for a, b in zip(small_sequence.scans, again.scans):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(small_sequence.poses, again.poses)
    np.testing.assert_array_equal(small_sequence.gt_map, again.gt_map)
    other = make_sequence({**SMALL, "seed": 1})
    assert not np.array_equal(other.gt_poses, small_sequence.gt_poses)


def test_sequence_fields(small_sequence):
    seq = small_sequence
    assert seq.num_scans == 4 and seq.source == "synthetic"
    assert seq.gt_map.shape == (5000, 3)
    np.testing.assert_array_equal(seq.poses[0], seq.gt_poses[0])
    assert not np.allclose(seq.poses[1:], seq.gt_poses[1:])
    # keyframe selection at the paper's 3 s keeps every synthetic scan
    np.testing.assert_array_equal(select_keyframes(seq.timestamps, 3.0), np.arange(4))
    for scan in seq.scans:
        ranges = np.linalg.norm(scan, axis=1)
        assert 1000 < len(scan) <= 16 * 128
        assert ranges.min() >= 0.5 and ranges.max() <= 60.0


def test_scans_lie_on_the_scene_surfaces():
    cfg = {**SMALL, "range_noise_m": 0.0, "gt_map_points": 2000}
    seq = make_sequence(cfg)
    scene, meshes = make_scene(0, 60.0, path_radius_m=15.0)
    for scan, gt_pose, init_pose in zip(seq.scans, seq.gt_poses, seq.poses):
        world = scan @ gt_pose[:3, :3].T + gt_pose[:3, 3]
        distances = scene.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        assert distances.max() < 2e-3
    # with the drifted poses, the late scans do not fit the scene
    last = seq.scans[-1] @ seq.poses[-1, :3, :3].T + seq.poses[-1, :3, 3]
    assert np.median(scene.compute_distance(o3d.core.Tensor(last.astype(np.float32))).numpy()) > 0.01
    gt_map_distances = scene.compute_distance(o3d.core.Tensor(seq.gt_map.astype(np.float32))).numpy()
    assert gt_map_distances.max() < 1e-3


def test_range_noise_has_the_configured_spread():
    scene, _ = make_scene(0, 60.0)
    pose = smooth_trajectory(4, 15.0, seed=0)[0]
    directions = spinning_lidar_directions(16, 15.0, -15.0, 256)
    clean = cast_scan(scene, pose, directions, 60.0, 0.0, np.random.default_rng(0))
    noisy = cast_scan(scene, pose, directions, 60.0, 0.05, np.random.default_rng(0))
    # same rays hit (noise of 5 cm rarely crosses the range limits), ranges differ by ~N(0, 0.05)
    n = min(len(clean), len(noisy))
    assert abs(len(clean) - len(noisy)) < 20
    difference = np.linalg.norm(noisy[:n], axis=1) - np.linalg.norm(clean[:n], axis=1)
    assert 0.03 < np.median(np.abs(difference)) / 0.6745 < 0.07


def test_gt_map_covers_what_the_scans_see(small_sequence):
    seq = small_sequence
    tree = cKDTree(seq.gt_map)
    world = np.concatenate([s @ T[:3, :3].T + T[:3, 3] for s, T in zip(seq.scans, seq.gt_poses)])
    # most observed points have a GT map point nearby (5000 map points: ~1 m spacing on the ground)
    distances, _ = tree.query(world)
    assert np.median(distances) < 1.5


def test_generic_round_trip(tmp_path, small_sequence):
    seq = small_sequence
    write_generic(seq, tmp_path)
    assert sorted(p.name for p in (tmp_path / "scans").iterdir()) == [f"{i:06d}.pcd" for i in range(4)]
    back = load_generic(tmp_path)
    assert back.num_scans == seq.num_scans
    for a, b in zip(back.scans, seq.scans):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)  # PCD stores float32
    np.testing.assert_allclose(back.poses, seq.poses, atol=1e-12)
    np.testing.assert_allclose(back.gt_poses, seq.gt_poses, atol=1e-12)
    np.testing.assert_allclose(back.timestamps, seq.timestamps, atol=1e-9)
    np.testing.assert_allclose(back.gt_map, seq.gt_map, rtol=0, atol=1e-5)


def test_config_defaults_and_errors():
    from neld_jax.config import defaults as base_config

    cfg = synthetic_defaults()
    assert base_config().data.synthetic.to_dict() == cfg.to_dict()  # the config takes the generator's defaults
    assert cfg.num_scans == 24 and cfg.num_beams == 32 and cfg.num_columns == 512
    assert cfg.gt_map_points == 200000 and cfg.drift_rot_deg == 0.5
    assert base_config().data.synthetic.gt_map_points == 200000  # the cpu and gpu budgets sample half as many
    with pytest.raises(ConfigError, match="unknown field 'beams'"):
        make_sequence({"beams": 3})
    with pytest.raises(ConfigError, match="trajectory_radius_m"):
        make_sequence({"trajectory_radius_m": 40.0})
    with pytest.raises(ConfigError, match="unknown field 'fov_down_deg'"):  # the field of view is the generator's own
        make_sequence({"fov_down_deg": 20.0})


def test_a_handheld_walk_turns_40_to_50_degrees_between_scans_at_2_hz():
    seq = make_sequence({**SMALL, "route": "handheld", "num_scans": 14, "gt_map_points": 0})
    assert seq.poses is None and seq.point_times is None and seq.name == "synthetic_seed0_handheld_2hz"
    np.testing.assert_allclose(np.diff(seq.timestamps), 0.5)
    relative = np.einsum("sji,sjk->sik", seq.gt_poses[:-1, :3, :3], seq.gt_poses[1:, :3, :3])
    turns = np.rad2deg(np.linalg.norm(Rotation.from_matrix(relative).as_rotvec(), axis=1))
    assert np.all(turns[:7] < 6.0)  # the first 8 scans look ahead along the loop
    assert np.all((turns[7:] > 39.0) & (turns[7:] < 51.0)), turns  # then 40-50 degrees (roll and pitch aside)
    steps = np.linalg.norm(np.diff(seq.gt_poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.7, atol=0.1)  # walking, 1.4 m/s


def test_a_car_route_is_long_with_turns_at_10_hz(tmp_path):
    cfg = {
        **SMALL,
        "route": "car",
        "num_scans": 400,
        "route_length_m": 320.0,
        "num_beams": 4,
        "num_columns": 32,
        "gt_map_points": 0,
    }
    seq = make_sequence(cfg)
    assert seq.poses is None and seq.name == "synthetic_seed0_car_10hz"
    np.testing.assert_allclose(np.diff(seq.timestamps), 0.1)
    path = np.linalg.norm(np.diff(seq.gt_poses[:, :3, 3], axis=0), axis=1)
    assert path.sum() > 300.0 and np.all(path < 1.12)  # 11 m/s at most
    assert path[:5].sum() < 0.35 and path[90:130].min() > 1.0  # from rest (2.5 m/s^2), cruising on the second straight
    heading = np.unwrap(np.arctan2(seq.gt_poses[:, 1, 0], seq.gt_poses[:, 0, 0]))
    assert abs(heading[-1] - heading[0]) > np.deg2rad(340)  # four corners round a closed route
    # as a car drives: its yaw rate builds up over the corner (KITTI 00's frames 0-100 change it by at most 0.27 deg
    # a sweep from one sweep to the next), the corners no faster than 3 m/s^2 sideways allows, no jump in speed
    turn = np.diff(heading)
    assert np.abs(np.diff(turn)).max() < np.deg2rad(0.35) and np.abs(turn).max() > np.deg2rad(2.5)
    assert np.max(np.abs(turn[1:]) * 10 * (path[1:] + path[:-1]) / 2 * 10) < 3.2  # m/s^2 sideways
    assert np.abs(np.diff(path)).max() * 100 < 2.6  # m/s^2
    # raw sweeps: each point's time within its sweep, the car's motion while the head turns in them
    assert all(0.0 <= t.min() and t.max() < 0.1 for t in seq.point_times)
    columns, _ = car_drive(400, 320.0, 0, 10.0, np.array([0.0, 0.999]))
    within = np.linalg.norm(columns[:, 1, :3, 3] - columns[:, 0, :3, 3], axis=1)
    assert within[0] < 0.02 and within[60:].min() > 0.5  # from rest, then 0.55-1.1 m within each sweep
    np.testing.assert_allclose(columns[:, 0], seq.gt_poses, atol=1e-12)  # the ground truth at the sweeps' stamps
    write_generic(seq, tmp_path)  # no poses.txt: the scans carry their stamps in their names, point_times/ beside
    back = load_generic(tmp_path)
    assert back.poses is None and back.num_scans == 400 and not (tmp_path / "poses.txt").exists()
    np.testing.assert_allclose(back.point_times[7], seq.point_times[7], atol=1e-6)
    np.testing.assert_allclose(back.timestamps, seq.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.gt_poses, seq.gt_poses, atol=1e-6)
