"""The start policy (neld_jax.steps.start): the input or the baseline's poses, the pose steps from there, how far the
baseline departs, and the record a resume reads."""

import numpy as np
import pytest
from conftest import make_tiny_config, tiny_synthetic_sequence

from neld_jax.baseline import BaselineResult
from neld_jax.config import recording
from neld_jax.errors import ConfigError
from neld_jax.steps import start
from neld_jax.training.train import PoseSteps


def test_pose_steps_from_the_baseline_are_capped_held_and_keep_the_scale():
    config = make_tiny_config("unused", steps=4)
    config.train.pose_lr_rot_init, config.train.pose_lr_trans_init = 1e-3, 1e-6  # one above the cap, one below
    config.train.pose_lr_rot_final = config.train.pose_lr_trans_final = 1e-5
    config.start.pose_lr_from_baseline, config.start.prior_from_baseline = (5e-6, 2.5e-7), 300.0
    steps = start.pose_steps_from_baseline(config.start, config.train, thickness_m=0.05)
    assert steps.lr_rot == (5e-6, 2.5e-7) and steps.lr_trans == (1e-6, 2.5e-7)  # min(rate, cap)
    assert steps.prior_trans == steps.prior_rot == 300.0 and steps.keep_scale
    assert PoseSteps.from_config(config) == PoseSteps((1e-6, 1e-5), (1e-3, 1e-5))  # the input's: the config's own
    config.start.pose_lr_from_baseline = ()
    assert start.pose_steps_from_baseline(config.start, config.train, None).lr_rot == (1e-3, 1e-5)  # no cap
    config.start.pose_lr_from_baseline = (1e-6,)
    with pytest.raises(ConfigError, match="pose_lr_from_baseline"):
        start.pose_steps_from_baseline(config.start, config.train, None)


def test_the_translations_prior_is_heavier_from_a_thin_map():
    config = make_tiny_config("unused", steps=4)
    config.start.prior_from_baseline = 3000.0
    assert start.THIN_MAP_M == 0.02
    thin = start.pose_steps_from_baseline(config.start, config.train, thickness_m=0.01)
    assert thin.prior_trans == pytest.approx(4 * 3000.0) and thin.prior_rot == 3000.0  # (2 cm / 1 cm)^2
    for thickness in (0.03, None):  # a real keyframe map, or none measured: the weight as set
        kept = start.pose_steps_from_baseline(config.start, config.train, thickness_m=thickness)
        assert kept.prior_trans == kept.prior_rot == 3000.0
    config.start.prior_from_baseline = 0.0  # no prior to scale
    assert start.pose_steps_from_baseline(config.start, config.train, 0.01).prior_trans == 0.0


def test_trajectory_departure_ignores_a_rigid_motion_and_sees_a_bend():
    from scipy.spatial.transform import Rotation

    angle = np.linspace(0.0, np.pi / 2, 21)
    poses = np.tile(np.eye(4), (21, 1, 1))
    poses[:, :3, 3] = np.stack([20 * np.cos(angle), 20 * np.sin(angle), 0.1 * angle], axis=1)  # a 31 m arc
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = Rotation.from_euler("zx", (30, 5), degrees=True).as_matrix(), (5.0, -2.0, 1.0)
    departure, path = start.trajectory_departure(poses, moved @ poses)
    assert departure < 1e-9 and path == pytest.approx(10 * np.pi, rel=1e-2)
    bent = poses.copy()
    bent[:, 2, 3] += 0.03 * np.arange(21.0) ** 2  # rising 12 m by the end, 0.8 m of it left after alignment
    departure, _ = start.trajectory_departure(poses, bent)
    assert 0.5 < departure < 12.0


def test_the_input_start_runs_no_baseline_and_an_unknown_start_is_an_error(monkeypatch):
    seq = tiny_synthetic_sequence()
    config = make_tiny_config("unused")

    def no_baseline(*args, **kwargs):
        raise AssertionError("the baseline ran")

    monkeypatch.setattr(start, "register_sequence", no_baseline)
    chosen = start.choose_start(start.StartSettings.from_config(config), seq)
    assert chosen.chosen == "input" and chosen.poses is seq.poses and chosen.pose_steps == PoseSteps.from_config(config)
    assert chosen.record() == {"started_from": "input", "pose_steps": PoseSteps.from_config(config).to_dict()}
    config.start.poses = "maybe"
    with pytest.raises(ConfigError, match="start.poses"):
        start.choose_start(start.StartSettings.from_config(config), seq)
    config.start.poses, config.train.fixed_scans = "baseline", (seq.num_scans,)  # a keyframe the sequence lacks
    with pytest.raises(ConfigError, match=rf"train.fixed_scans = \({seq.num_scans},\): scan"):
        start.choose_start(start.StartSettings.from_config(config), seq)  # before the baseline runs


def test_the_crisper_start_is_the_one_with_the_crisper_map(monkeypatch):
    # "crisper": the baseline runs, and the start is the input or the baseline, whichever map is crisper (a tie
    # keeps the input); the pose steps follow the start.
    seq = tiny_synthetic_sequence()
    config = recording("cpu")
    import dataclasses

    truthful = dataclasses.replace(seq, poses=seq.gt_poses)  # an input crisper than a drifted baseline
    for data, baseline_poses, expected in ((seq, seq.gt_poses, "baseline"), (truthful, seq.poses, "input")):
        monkeypatch.setattr(
            start, "register_sequence", lambda scans, poses, settings, **kw: BaselineResult(baseline_poses)
        )
        chosen = start.choose_start(start.StartSettings.from_config(config), data)
        assert chosen.chosen == expected and chosen.baseline_poses is baseline_poses
        assert chosen.pose_steps.keep_scale == (expected == "baseline")
        assert set(chosen.judged[0]) == {"initial", "baseline"}
        assert chosen.record()["started_from"] == expected and chosen.departure_m >= 0
