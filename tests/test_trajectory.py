"""Every input scan gets a refined pose: keyframe corrections interpolated on SE(3)."""

import numpy as np
from scipy.spatial.transform import Rotation

from neld_jax.trajectory import propagate_corrections


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.5, (n, 3))).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(0, 1.0, (n, 3)), axis=0)
    return T


def test_keyframes_exact_and_a_common_correction_reaches_every_scan():
    T_in = _poses(10)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    G[:3, 3] = [1.0, 2.0, -0.5]
    keyframes = np.array([1, 4, 8])
    refined = propagate_corrections(T_in, keyframes, G @ T_in[keyframes])
    np.testing.assert_allclose(refined, G @ T_in, atol=1e-12)  # same correction everywhere: exact everywhere


def test_interpolation_halfway_in_time_and_ends_clamped():
    T_in = np.tile(np.eye(4), (5, 1, 1))
    T_in[:, 0, 3] = np.arange(5.0)
    keyframes = np.array([1, 3])
    C_b = np.eye(4)
    C_b[:3, :3] = Rotation.from_rotvec([0, 0, 0.4]).as_matrix()
    C_b[:3, 3] = [0.0, 0.2, 0.0]
    refined_kf = np.stack([T_in[1], C_b @ T_in[3]])
    times = np.array([0.0, 1.0, 1.5, 3.0, 4.0])  # scan 2 is a quarter of the way from keyframe 1 to 3 in time
    refined = propagate_corrections(T_in, keyframes, refined_kf, times)
    expected_rot = Rotation.from_rotvec([0, 0, 0.1]).as_matrix()
    C_2 = refined[2] @ np.linalg.inv(T_in[2])
    np.testing.assert_allclose(C_2[:3, :3], expected_rot, atol=1e-12)
    np.testing.assert_allclose(refined[0], T_in[0], atol=1e-12)  # before the first keyframe: its (identity) correction
    np.testing.assert_allclose(refined[4], C_b @ T_in[4], atol=1e-12)  # after the last: its correction
    by_index = propagate_corrections(T_in, keyframes, refined_kf)  # halfway by index
    C_2 = by_index[2] @ np.linalg.inv(T_in[2])
    np.testing.assert_allclose(C_2[:3, :3], Rotation.from_rotvec([0, 0, 0.2]).as_matrix(), atol=1e-12)
