"""neld_jax.geometry.with_up_axis_of: a pose tilted onto a reference's up axis, heading and position kept;
anchored_on_first: a trajectory moved rigidly onto its first pose's start."""

import numpy as np
from scipy.spatial.transform import Rotation

from neld_jax.geometry import anchored_on_first, rotation_angles_deg, with_up_axis_of


def _poses(count: int, seed: int, tilt_deg: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    euler = np.stack([rng.uniform(-180, 180, count), rng.normal(0, tilt_deg, count), rng.normal(0, tilt_deg, count)], 1)
    poses[:, :3, :3] = Rotation.from_euler("ZYX", euler, degrees=True).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 10.0, (count, 3))
    return poses


def test_the_result_has_the_references_up_axis_and_keeps_position_and_heading():
    poses, reference = _poses(64, 0, 20.0), _poses(64, 1, 20.0)
    levelled = with_up_axis_of(poses, reference)
    # The world's up, seen from the sensor (third row of R), is the reference's; positions do not move.
    np.testing.assert_allclose(levelled[:, 2, :3], reference[:, 2, :3], atol=1e-12)
    np.testing.assert_array_equal(levelled[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(
        np.einsum("sji,sjk->sik", levelled[:, :3, :3], levelled[:, :3, :3]), np.tile(np.eye(3), (64, 1, 1)), atol=1e-12
    )
    # The turn applied is about a horizontal axis (no heading change) and is the smallest one: the angle between
    # the two up axes.
    turn = levelled[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2)
    rotvec = Rotation.from_matrix(turn).as_rotvec()
    np.testing.assert_allclose(rotvec[:, 2], 0.0, atol=1e-12)
    between = np.degrees(np.arccos(np.clip(np.einsum("si,si->s", poses[:, 2, :3], reference[:, 2, :3]), -1, 1)))
    np.testing.assert_allclose(rotation_angles_deg(turn), between, atol=1e-9)
    assert between.max() > 10.0  # the case is not trivial


def test_a_pose_with_the_references_tilt_is_left_as_it_is_and_single_poses_work():
    poses = _poses(8, 2, 5.0)
    heading = np.eye(4)
    heading[:3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()  # turned about world up: same tilt
    np.testing.assert_allclose(with_up_axis_of(heading @ poses, poses), heading @ poses, atol=1e-12)
    np.testing.assert_allclose(with_up_axis_of(poses[3], poses[5]), with_up_axis_of(poses, poses[5])[3], atol=1e-12)


def test_a_trajectory_anchored_on_its_first_pose_keeps_its_shape():
    poses, start = _poses(5, seed=1, tilt_deg=10.0), _poses(1, seed=2, tilt_deg=10.0)[0]
    anchored, anchor = anchored_on_first(poses, start)
    np.testing.assert_allclose(anchored[0], start, atol=1e-12)  # the gauge
    np.testing.assert_allclose(anchored, anchor @ poses, atol=0)
    relative = np.linalg.inv(poses[:-1]) @ poses[1:]
    np.testing.assert_allclose(np.linalg.inv(anchored[:-1]) @ anchored[1:], relative, atol=1e-9)
