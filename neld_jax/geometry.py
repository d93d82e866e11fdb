"""Rigid transforms on numpy arrays, float64, for the edge (I/O, metrics, reports): the one place that moves
points by a 4x4 transform, inverts poses and measures rotation angles. (The jit-compiled maths has its own
versions in neld_jax.lie.)

Poses are 4x4 homogeneous matrices `T_world_sensor`: [..., 4, 4].
"""

from __future__ import annotations

import numpy as np


def transform_points(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform (rigid or similarity, `[[sR, t], [0, 1]]`) to points.

    points: [N, 3], transform: [4, 4] -> [N, 3] float64.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {points.shape}")
    transform = np.asarray(transform, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def cumulative_path(poses: np.ndarray) -> np.ndarray:
    """[S] metres travelled up to each pose of poses [S, 4, 4] (0 at the first)."""
    steps = np.linalg.norm(np.diff(np.asarray(poses)[:, :3, 3], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(steps)]


def invert_poses(poses: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms. poses: [..., 4, 4] -> [..., 4, 4]."""
    poses = np.asarray(poses, dtype=np.float64)
    rot_t = np.swapaxes(poses[..., :3, :3], -1, -2)
    inverse = np.zeros_like(poses)
    inverse[..., :3, :3] = rot_t
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, poses[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def rotation_angles_deg(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle of each matrix, robust near 0 and pi.

    rotations: [..., 3, 3] -> [...] degrees in [0, 180].
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    trace = np.trace(rotations, axis1=-2, axis2=-1)
    # |vee(R - R^T)| = 2 sin(theta); atan2 keeps precision where arccos of the trace would not.
    skew = rotations - np.swapaxes(rotations, -1, -2)
    sin2 = np.linalg.norm(np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1), axis=-1)
    return np.degrees(np.arctan2(sin2, trace - 1.0))


def nearest_rotations(matrices: np.ndarray) -> np.ndarray:
    """The rotation nearest to each nearly orthonormal matrix (SVD projection onto SO(3)): removes the round-off of
    an optimiser, of text files or of composing many transforms. matrices: [..., 3, 3] -> [..., 3, 3]."""
    u, _, vt = np.linalg.svd(np.asarray(matrices, dtype=np.float64))
    return u @ vt


def anchored_on_first(poses: np.ndarray, pose0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """poses [S, 4, 4] moved rigidly so that poses[0] becomes pose0 [4, 4] (the gauge: keyframe 0 keeps its start
    pose) -> (the moved poses [S, 4, 4], the rigid transform [4, 4] that moved them: pose0 poses[0]^-1)."""
    anchor = np.asarray(pose0, np.float64) @ np.linalg.inv(poses[0])
    return anchor @ poses, anchor


def with_up_axis_of(poses: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """poses tilted onto the reference's up axis: each rotation turned, about a horizontal axis, by the smallest
    angle that gives its sensor the world's up direction (+z) where the reference's sensor has it, so heading and
    position stay. For an input from an IMU-aided odometry, whose roll and pitch gravity keeps from drifting
    (docs/evaluation.md, "Keeping the input's tilt").

    poses, reference: [..., 4, 4] -> [..., 4, 4] with orthonormal rotations (re-orthonormalised: the result is
    composed with later registrations, and round-off would grow along a chain)."""
    poses = np.array(poses, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0])
    # Where the pose sends the direction that the reference sends to world up: the tilt to undo is from a to up.
    a = np.einsum("...ij,...kj,k->...i", poses[..., :3, :3], reference[..., :3, :3], up)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    axis = np.cross(a, up)  # |axis| = sin(angle)
    cos = a[..., 2][..., None, None]
    skew = np.zeros(a.shape[:-1] + (3, 3))
    skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -axis[..., 2], axis[..., 1], -axis[..., 0]
    skew = skew - np.swapaxes(skew, -1, -2)
    # Rodrigues' formula with an unnormalised axis; (1 - cos) / sin^2 = 1 / (1 + cos) holds also as sin -> 0.
    turn = np.eye(3) + skew + skew @ skew / (1.0 + cos)
    poses[..., :3, :3] = nearest_rotations(turn @ poses[..., :3, :3])
    return poses


def moved_enough(last: np.ndarray, pose: np.ndarray, distance_m: float, angle_deg: float) -> bool:
    """The spatial keyframe rule: pose [4, 4] lies at least distance_m from last [4, 4], or has turned at least
    angle_deg from it. A rule whose threshold is <= 0 is off (both off: False)."""
    relative = invert_poses(last) @ pose
    return bool(
        (distance_m > 0 and np.linalg.norm(relative[:3, 3]) >= distance_m)
        or (angle_deg > 0 and rotation_angles_deg(relative[:3, :3]) >= angle_deg)
    )


def register_scans(scans: list[np.ndarray], poses: np.ndarray) -> np.ndarray:
    """Transform each scan into the world frame and stack them: the raw map.

    scans: list of S arrays [N_i, 3] (sensor frame), poses: [S, 4, 4] sensor -> world
    -> points [sum N_i, 3] float64.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape [S, 4, 4], got {poses.shape}")
    if len(scans) != len(poses):
        raise ValueError(f"{len(scans)} scans but {len(poses)} poses")
    if not scans:
        return np.zeros((0, 3))
    return np.concatenate([transform_points(np.asarray(scan).reshape(-1, 3), pose) for scan, pose in zip(scans, poses)])
