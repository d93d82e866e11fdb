"""ATE / RPE against evo on the same TUM files; map metrics on sets with known answers."""

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax.data.poses import write_tum
from neld_jax.geometry import rotation_angles_deg, transform_points
from neld_jax.judging import metrics


def _random_trajectory(rng, num_poses=40):
    """A wiggly 3-D trajectory: [S, 4, 4]."""
    poses = np.tile(np.eye(4), (num_poses, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.1, (num_poses, 3)), axis=0)).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 1.0, (num_poses, 3)), axis=0)
    return poses


def _perturb(rng, poses, trans_sigma=0.1, rot_sigma_rad=0.02):
    noisy = poses.copy()
    noise = Rotation.from_rotvec(rng.normal(0, rot_sigma_rad, (len(poses), 3))).as_matrix()
    noisy[:, :3, :3] = noise @ poses[:, :3, :3]
    noisy[:, :3, 3] += rng.normal(0, trans_sigma, (len(poses), 3))
    return noisy


def _rigid(rng):
    transform = np.eye(4)
    transform[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    transform[:3, 3] = rng.uniform(-50, 50, 3)
    return transform


@pytest.fixture
def tum_pair(tmp_path):
    """GT and a noisy estimate in another frame, as TUM files, plus the arrays."""
    rng = np.random.default_rng(3)
    gt = _random_trajectory(rng)
    est = _rigid(rng) @ _perturb(rng, gt)
    stamps = 1000.0 + 0.1 * np.arange(len(gt))
    write_tum(tmp_path / "gt.txt", stamps, gt)
    write_tum(tmp_path / "est.txt", stamps, est)
    return tmp_path / "gt.txt", tmp_path / "est.txt", gt, est


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    rotation = Rotation.random(random_state=1).as_matrix()
    dst = 2.5 * src @ rotation.T + np.array([1.0, -2.0, 3.0])
    r, t, s = metrics.umeyama_alignment(src, dst, with_scale=True)
    np.testing.assert_allclose(r, rotation, atol=1e-10)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-10)
    assert s == pytest.approx(2.5)
    _, _, s_rigid = metrics.umeyama_alignment(src, dst, with_scale=False)
    assert s_rigid == 1.0


def test_ate_matches_evo(tum_pair):
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    gt_path, est_path, _, _ = tum_pair
    traj_ref = file_interface.read_tum_trajectory_file(str(gt_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est)
    traj_est_aligned = copy.deepcopy(traj_est)
    traj_est_aligned.align(traj_ref, correct_scale=False)

    ape_translation = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape_translation.process_data((traj_ref, traj_est_aligned))
    evo_stats = ape_translation.get_all_statistics()
    ape_rotation = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
    ape_rotation.process_data((traj_ref, traj_est_aligned))

    # Our side reads the same files through neld_jax's reader.
    from neld_jax.data.poses import read_tum

    stamps_gt, gt = read_tum(gt_path)
    stamps_est, est = read_tum(est_path)
    est_idx, gt_idx = metrics.associate_timestamps(stamps_est, stamps_gt)
    assert len(est_idx) == len(gt) == len(est)
    ours = metrics.ate(est[est_idx], gt[gt_idx], align="se3")

    assert ours["translation_rmse_m"] > 0.05  # the noise is really there
    assert ours["translation_rmse_m"] == pytest.approx(evo_stats["rmse"], abs=1e-6)
    assert ours["translation_mean_m"] == pytest.approx(evo_stats["mean"], abs=1e-6)
    assert ours["translation_median_m"] == pytest.approx(evo_stats["median"], abs=1e-6)
    assert ours["translation_max_m"] == pytest.approx(evo_stats["max"], abs=1e-6)
    assert ours["rotation_rmse_deg"] == pytest.approx(
        ape_rotation.get_statistic(evo_metrics.StatisticsType.rmse), abs=1e-6
    )


def test_sim3_ate_matches_evo(tum_pair):
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    gt_path, est_path, gt, est = tum_pair
    est_scaled = est.copy()
    est_scaled[:, :3, 3] *= 0.7
    write_tum(est_path.with_name("scaled.txt"), np.arange(len(gt)), est_scaled)
    traj_ref = file_interface.read_tum_trajectory_file(str(gt_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path.with_name("scaled.txt")))
    traj_est.align(traj_ref, correct_scale=True)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    ours = metrics.ate(est_scaled, gt, align="sim3")
    assert ours["scale"] == pytest.approx(1 / 0.7, rel=0.05)
    assert ours["translation_rmse_m"] == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.rmse), abs=1e-6)


def test_rpe_matches_evo_all_pairs(tum_pair):
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    gt_path, est_path, gt, est = tum_pair
    traj_ref = file_interface.read_tum_trajectory_file(str(gt_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    for delta in (1, 3):
        rpe = evo_metrics.RPE(
            evo_metrics.PoseRelation.translation_part, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=True
        )
        rpe.process_data((traj_ref, traj_est))
        ours = metrics.rpe(est, gt, delta=delta)
        assert ours["num_pairs"] == len(gt) - delta
        assert ours["translation_rmse_m"] == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.rmse), abs=1e-6)


def test_sim3_scale_matches_evo_on_a_shortened_path(tum_pair):
    # A path 0.5 % short: Sim(3) finds the scale that stretches it back, as evo's alignment with correct_scale does
    from evo.core.trajectory import PosePath3D

    _, _, gt, est = tum_pair
    est_short = est.copy()
    est_short[:, :3, 3] *= 0.995
    traj_est = PosePath3D(poses_se3=list(est_short))
    _, _, evo_scale = traj_est.align(PosePath3D(poses_se3=list(gt)), correct_scale=True)
    ours = metrics.ate(est_short, gt, align="sim3")
    assert ours["scale"] == pytest.approx(evo_scale, rel=1e-9)
    assert ours["scale"] == pytest.approx(1 / 0.995, rel=0.01)


def test_path_length_matches_evo(tum_pair):
    from evo.core.trajectory import PosePath3D

    _, _, gt, est = tum_pair
    assert metrics.path_length(gt) == pytest.approx(PosePath3D(poses_se3=list(gt)).path_length, rel=1e-12)
    assert metrics.path_length_ratio(est, gt) == pytest.approx(
        PosePath3D(poses_se3=list(est)).path_length / PosePath3D(poses_se3=list(gt)).path_length, rel=1e-12
    )
    assert metrics.path_length(gt[:1]) == 0.0
    assert np.isnan(metrics.path_length_ratio(gt[:1], gt[:1]))


def _unit_step_trajectory(rng, num_poses=120):
    """Positions 1 m apart in random directions, a wandering orientation, and a noisy copy: ([S, 4, 4], [S, 4, 4])."""
    gt = np.tile(np.eye(4), (num_poses, 1, 1))
    gt[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (num_poses, 3)), axis=0)).as_matrix()
    steps = rng.normal(size=(num_poses - 1, 3))
    gt[1:, :3, 3] = np.cumsum(steps / np.linalg.norm(steps, axis=1, keepdims=True), axis=0)
    return gt, _perturb(rng, gt, trans_sigma=0.05, rot_sigma_rad=0.01)


def test_kitti_relative_error_matches_evo_rpe_in_meters():
    # With 1 m steps and lengths just under whole metres, the devkit's last frame (the first past L) is the one evo's
    # all-pairs RPE in metres picks (the nearest to L on the reference's path); evo's E is the inverse of the
    # devkit's, with the same translation norm and angle.
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PosePath3D

    gt, est = _unit_step_trajectory(np.random.default_rng(5))
    lengths = (9.9, 19.9, 29.9)
    ours = metrics.kitti_relative_error(est, gt, lengths, step=1)
    for length in lengths:
        mine = ours["per_length"][f"{length:g}"]
        for relation, key, factor in (
            (evo_metrics.PoseRelation.translation_part, "translation_pct", 100.0),
            (evo_metrics.PoseRelation.rotation_angle_deg, "rotation_deg_per_m", 1.0),
        ):
            rpe = evo_metrics.RPE(
                relation,
                delta=length,
                delta_unit=evo_metrics.Unit.meters,
                rel_delta_tol=0.02,
                all_pairs=True,
                pairs_from_reference=True,
            )
            rpe.process_data((PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))))
            assert mine["num_segments"] == len(rpe.error) == len(gt) - int(np.ceil(length))
            assert mine[key] == pytest.approx(factor * np.mean(rpe.error) / length, rel=1e-9)
    assert ours["num_segments"] == sum(v["num_segments"] for v in ours["per_length"].values())
    assert ours["translation_pct"] > 0.1 and ours["rotation_deg_per_m"] > 0.01  # the noise is really there


def test_a_straight_path_one_percent_short():
    # 0.99 of the ground truth's 60 m path in 1/64 m steps (exact in binary): the path-length ratio 0.99, KITTI's
    # translation error 1 % (the segment runs to the first frame past L: at most a step longer), no rotation error;
    # Sim(3) stretches it back
    gt = np.tile(np.eye(4), (3841, 1, 1))
    gt[:, 0, 3] = np.arange(3841) / 64
    est = gt.copy()
    est[:, :3, 3] *= 0.99
    assert metrics.path_length_ratio(est, gt) == pytest.approx(0.99, rel=1e-12)
    kitti = metrics.kitti_relative_error(est, gt, lengths_m=(10, 20, 30, 40, 50), step=10)
    assert kitti["translation_pct"] == pytest.approx(1.0, rel=1e-3)
    assert kitti["rotation_deg_per_m"] == pytest.approx(0.0, abs=1e-9)
    # the first frames 0, 10, ..., 630: from 640 on (10 m), less than 50 m of path remain
    assert kitti["per_length"]["50"]["num_segments"] == 64
    assert metrics.ate(est, gt, align="sim3")["translation_rmse_m"] < 1e-9
    assert metrics.ate(est, gt, align="se3")["translation_rmse_m"] > 0.05


def test_kitti_segments_follow_the_devkit():
    # 0.5 m steps: the last frame is the first whose path from the first exceeds L strictly (10.5 m for L = 10);
    # first frames every `step`; a segment past the end is left out; a constant yaw drift gives angle / L.
    num = 41
    gt = np.tile(np.eye(4), (num, 1, 1))
    gt[:, 0, 3] = 0.5 * np.arange(num)
    est = gt.copy()
    est[:, :3, :3] = Rotation.from_euler("z", 0.01 * np.arange(num)[:, None], degrees=True).as_matrix()
    segments = metrics.kitti_segment_errors(est, gt, lengths_m=(10.0, 19.0), step=10)
    np.testing.assert_array_equal(segments["first"], [0, 0, 10])
    np.testing.assert_array_equal(segments["last"], [21, 39, 31])
    np.testing.assert_allclose(segments["rotation_deg"], [0.21, 0.39, 0.21], atol=1e-9)
    kitti = metrics.kitti_relative_error(est, gt, lengths_m=(10.0, 19.0), step=10)
    assert kitti["rotation_deg_per_m"] == pytest.approx(np.mean([0.021, 0.39 / 19, 0.021]))
    assert kitti["per_length"]["19"]["num_segments"] == 1
    assert np.isnan(metrics.kitti_relative_error(est, gt, lengths_m=(100.0,))["translation_pct"])
    with pytest.raises(ValueError, match="step"):
        metrics.kitti_segment_errors(est, gt, step=0)


def test_ate_zero_for_rigidly_moved_copy_only_with_alignment():
    rng = np.random.default_rng(1)
    gt = _random_trajectory(rng, 20)
    moved = _rigid(rng) @ gt
    aligned = metrics.ate(moved, gt, align="se3")
    assert aligned["translation_rmse_m"] < 1e-9
    assert aligned["rotation_rmse_deg"] < 1e-6
    # The alignment found is the inverse of the transform applied.
    np.testing.assert_allclose(np.array(aligned["alignment"]) @ moved[0], gt[0], atol=1e-9)
    unaligned = metrics.ate(moved, gt, align="none")
    assert unaligned["translation_rmse_m"] > 1.0
    assert unaligned["rotation_rmse_deg"] > 1.0


def test_ate_rejects_mismatched_inputs():
    with pytest.raises(ValueError, match="matched"):
        metrics.ate(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (4, 1, 1)))
    with pytest.raises(ValueError, match="align"):
        metrics.ate(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), align="bogus")


def test_collinear_trajectory_falls_back_to_translation():
    gt = np.tile(np.eye(4), (5, 1, 1))
    gt[:, 0, 3] = np.arange(5.0)
    shifted = gt.copy()
    shifted[:, :3, 3] += [1.0, 2.0, 3.0]
    result = metrics.ate(shifted, gt)
    assert result["translation_rmse_m"] < 1e-12


def test_associate_timestamps_nearest_within_tolerance():
    est_idx, gt_idx = metrics.associate_timestamps(
        np.array([0.0, 1.0, 2.004, 5.0]), np.array([0.001, 0.5, 1.0, 2.0, 3.0]), max_diff=0.01
    )
    np.testing.assert_array_equal(est_idx, [0, 1, 2])
    np.testing.assert_array_equal(gt_idx, [0, 2, 3])


def test_rotation_angle_small_and_large():
    angles = np.array([1e-7, 0.3, np.pi - 1e-6])
    rotations = Rotation.from_rotvec(angles[:, None] * np.array([0.0, 0.6, 0.8])).as_matrix()
    np.testing.assert_allclose(rotation_angles_deg(rotations), np.degrees(angles), rtol=1e-6)


# ------------------------------------------------------------------------------------ map metrics


def _grid(step=0.1, size=20):
    """A planar grid of points 10 cm apart: [size^2, 3]."""
    u, v = np.meshgrid(np.arange(size) * step, np.arange(size) * step)
    return np.stack([u.ravel(), v.ravel(), np.zeros(size * size)], axis=1)


def _map_metrics(est_points, gt_points, **settings) -> dict:
    """metrics.map_metrics_from_distances of two maps [N, 3], [M, 3] (the evaluation's nearest neighbours)."""
    return metrics.map_metrics_from_distances(
        metrics.nearest_neighbor_distances(est_points, gt_points),
        metrics.nearest_neighbor_distances(gt_points, est_points),
        **settings,
    )


def test_identical_maps():
    points = _grid()
    result = _map_metrics(points, points, threshold=0.2)
    assert result["chamfer_l1_m"] == 0.0
    assert result["f1"] == 1.0 and result["precision"] == 1.0 and result["recall"] == 1.0
    assert result["inlier_rmse_m"] == 0.0
    assert result["num_est"] == result["num_gt"] == len(points)


def test_shifted_copy_chamfer_is_the_shift():
    points = _grid()
    shift = 0.05  # out of the plane, so every nearest neighbour is the shifted twin
    result = _map_metrics(points + [0, 0, shift], points, threshold=0.2)
    assert result["chamfer_l1_m"] == pytest.approx(shift)
    assert result["accuracy_m"] == pytest.approx(shift) and result["completeness_m"] == pytest.approx(shift)
    assert result["f1"] == 1.0
    assert result["inlier_rmse_m"] == pytest.approx(shift)
    beyond = _map_metrics(points + [0, 0, 0.3], points, threshold=0.2)
    assert beyond["f1"] == 0.0 and beyond["num_inliers"] == 0
    assert _map_metrics(points + [0, 0, shift], points, mode="sum")["chamfer_l1_m"] == pytest.approx(2 * shift)


def test_subset_is_accurate_but_incomplete():
    gt = _grid()
    est = gt[gt[:, 0] < 0.95]  # the left half
    result = _map_metrics(est, gt, threshold=0.2)
    assert result["accuracy_m"] == 0.0
    assert result["completeness_m"] > 0.1
    assert result["precision"] == 1.0 and result["recall"] < 1.0
    assert result["chamfer_l1_m"] == pytest.approx(0.5 * result["completeness_m"])


def test_cutoff_drops_or_clips_outliers_by_mode():
    gt = _grid()
    outliers = np.array([[0.5, 0.5, 5.0], [0.5, 0.5, 3.0]])  # 5 m and 3 m above the plane
    est = np.concatenate([gt, outliers])
    num = len(est)
    no_cutoff = _map_metrics(est, gt, cutoff=None)
    assert no_cutoff["accuracy_m"] == pytest.approx(8.0 / num)
    paper = _map_metrics(est, gt, cutoff=1.0, mode="paper")
    assert paper["accuracy_m"] == 0.0  # outliers dropped
    assert paper["num_est_within_cutoff"] == num - 2
    assert paper["chamfer_l1_m"] == 0.0
    clip = _map_metrics(est, gt, cutoff=1.0, mode="clip")
    assert clip["accuracy_m"] == pytest.approx(2.0 / num)  # each outlier counts 1 m
    assert clip["chamfer_l1_m"] == pytest.approx(1.0 / num)
    summed = _map_metrics(est, gt, cutoff=1.0, mode="sum")
    assert summed["chamfer_l1_m"] == 0.0
    # F1 does not depend on the cutoff convention.
    assert paper["precision"] == clip["precision"] == pytest.approx((num - 2) / num)
    with pytest.raises(ValueError, match="mode"):
        _map_metrics(est, gt, mode="bogus")


def test_transform_points_applies_the_transform():
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    transform[:3, 3] = [1.0, 0.0, 0.0]
    np.testing.assert_allclose(transform_points(np.array([[1.0, 0.0, 0.0]]), transform), [[1.0, 1.0, 0.0]], atol=1e-12)
