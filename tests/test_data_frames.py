"""Scans already registered (world frame) and poses that look inverted are refused with a line that names the fix,
or converted when data.scans_in_world_frame / data.invert_poses say so (neld_jax/data/frames.py)."""

import dataclasses

import ml_collections
import numpy as np
import pytest
from conftest import tiny_synthetic_sequence

from neld_jax.data import frames
from neld_jax.errors import DataError
from neld_jax.geometry import transform_points
from neld_jax.steps.inputs import load_sequence
from neld_jax.synthetic.generator import write_generic


def _registered(seq):
    return [transform_points(scan, pose) for scan, pose in zip(seq.scans, seq.poses)]


def test_votes_tell_sensor_from_world_frame_and_the_move_back_is_exact():
    seq = tiny_synthetic_sequence(30)
    voters, share = frames.world_frame_votes(seq.scans, seq.poses)
    assert voters == 30 and share < 0.5
    world = _registered(seq)
    voters, share = frames.world_frame_votes(world, seq.poses)
    assert voters == 30 and share > frames.WORLD_SHARE
    for back, scan in zip(frames.to_sensor_frame(world, seq.poses), seq.scans):
        np.testing.assert_allclose(back, scan, atol=1e-9)
    # Poses all near the origin (a scan taken in place) decide nothing.
    still = seq.poses.copy()
    still[:, :3, 3] *= 0.1
    assert frames.world_frame_votes(seq.scans, still)[0] == 0


def _config(root, **extra):
    return ml_collections.ConfigDict({"format": "generic", "root": str(root), **extra})


def test_load_refuses_registered_scans_and_moves_them_when_told(tmp_path):
    seq = tiny_synthetic_sequence(30)
    write_generic(dataclasses.replace(seq, scans=_registered(seq)), tmp_path / "world")
    with pytest.raises(DataError, match=r"world: the scans look registered already .*scans_in_world_frame=True"):
        load_sequence(_config(tmp_path / "world"))
    moved = load_sequence(_config(tmp_path / "world", scans_in_world_frame=True))
    for back, scan in zip(moved.scans, seq.scans):  # PCD stores float32 coordinates
        np.testing.assert_allclose(back, scan, atol=1e-4)
    write_generic(seq, tmp_path / "sensor")
    loaded = load_sequence(_config(tmp_path / "sensor"))
    np.testing.assert_allclose(loaded.scans[3], seq.scans[3], atol=1e-4)


def test_inverted_poses_are_refused_and_inverted_when_told(tmp_path):
    seq = tiny_synthetic_sequence(30)
    frames.check_pose_direction(seq, "as generated")  # sensor -> world: passes
    inverted = dataclasses.replace(seq, poses=np.linalg.inv(seq.poses))
    with pytest.raises(DataError, match=r"inverted: the poses look inverted \(world -> sensor\).*invert_poses=True"):
        frames.check_pose_direction(inverted, "inverted")
    write_generic(inverted, tmp_path / "inverted")
    with pytest.raises(DataError, match="inverted: the poses look inverted"):
        load_sequence(_config(tmp_path / "inverted"))
    loaded = load_sequence(_config(tmp_path / "inverted", invert_poses=True))
    np.testing.assert_allclose(loaded.poses, seq.poses, atol=1e-6)
    # Too few pairs that moved to tell: nothing decided.
    still = dataclasses.replace(inverted, poses=np.tile(np.eye(4), (seq.num_scans, 1, 1)))
    frames.check_pose_direction(still, "still")
