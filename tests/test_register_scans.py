"""Every input scan registered to the result (neld_jax.steps.registration): scans between keyframes, moved off their
true poses by a known perturbation, come back to the truth; a scan of another scene is refused and keeps its guess;
the per-scan report carries the residual and the refusal."""

import dataclasses

import numpy as np
import pytest

from neld_jax import lie
from neld_jax.data.sequence import Sequence
from neld_jax.judging import report
from neld_jax.steps import registration
from neld_jax.synthetic.generator import make_sequence

SCENE = {
    "num_scans": 8,
    "num_beams": 16,
    "num_columns": 256,
    "gt_map_points": 1000,
    "scene_size_m": 40.0,
    "trajectory_radius_m": 6.0,
    "max_range_m": 30.0,
    "range_noise_m": 0.0,
}
KEYFRAMES = np.array([0, 2, 4, 6])


@pytest.fixture(scope="module")
def scene() -> Sequence:
    return make_sequence(SCENE)


def perturbed(poses: np.ndarray, seed: int, trans_m: float = 0.15, rot_deg: float = 1.5) -> np.ndarray:
    """poses [S, 4, 4] each moved by a right perturbation of trans_m and rot_deg in a random direction."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(len(poses), 2, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    xi = np.concatenate([trans_m * directions[:, 0], np.radians(rot_deg) * directions[:, 1]], axis=1)
    return poses @ lie.se3_exp_float64(xi)


def position_errors(T: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(T[:, :3, 3] - T_true[:, :3, 3], axis=1)


def test_perturbed_scans_between_keyframes_are_registered_back_to_the_truth(scene):
    settings = registration.RegistrationSettings(max_range_m=30.0)
    target = registration.map_cloud([scene.scans[k] for k in KEYFRAMES], scene.gt_poses[KEYFRAMES], settings)
    others = np.setdiff1d(np.arange(scene.num_scans), KEYFRAMES)
    guesses = perturbed(scene.gt_poses[others], seed=1)
    assert position_errors(guesses, scene.gt_poses[others]).min() > 0.14

    result = registration.register_to_map([scene.scans[s] for s in others], guesses, target, settings)

    assert result.registered.all(), result.flag
    assert position_errors(result.poses, scene.gt_poses[others]).max() < 0.02
    angles = np.degrees(
        np.linalg.norm(lie.se3_log_float64(np.linalg.inv(scene.gt_poses[others]) @ result.poses)[:, 3:], axis=1)
    )
    assert angles.max() < 0.2
    assert np.all(result.residual_m < 0.05) and np.all(result.fitness > 0.5)


def test_a_scan_of_another_scene_is_refused_and_keeps_its_guess(scene):
    settings = registration.RegistrationSettings(max_range_m=30.0)
    target = registration.map_cloud([scene.scans[k] for k in KEYFRAMES], scene.gt_poses[KEYFRAMES], settings)
    elsewhere = make_sequence({**SCENE, "seed": 7, "num_scans": 2})
    guesses = scene.gt_poses[[1]]

    result = registration.register_to_map(elsewhere.scans[:1], guesses, target, settings)

    assert result.flag[0] in (registration.POOR_FITNESS, registration.JUMP)
    assert not result.registered[0]
    np.testing.assert_array_equal(result.poses[0], guesses[0])


def test_too_few_points_are_refused(scene):
    settings = registration.RegistrationSettings(max_range_m=30.0)
    target = registration.map_cloud([scene.scans[0]], scene.gt_poses[:1], settings)
    result = registration.register_to_map([scene.scans[1][:20]], scene.gt_poses[1:2], target, settings)
    assert result.flag == [registration.TOO_FEW_POINTS] and np.isnan(result.residual_m[0])


def test_every_scan_but_the_keyframes_is_registered_from_its_interpolated_correction(scene):
    # The input: the truth with every scan between keyframes off by a perturbation, the keyframes exact.
    inputs = scene.gt_poses.copy()
    others = np.setdiff1d(np.arange(scene.num_scans), KEYFRAMES)
    inputs[others] = perturbed(scene.gt_poses[others], seed=2, trans_m=0.1, rot_deg=1.0)
    loaded = dataclasses.replace(scene, poses=inputs)
    keyframes = dataclasses.replace(
        scene,
        scans=[scene.scans[k] for k in KEYFRAMES],
        poses=inputs[KEYFRAMES],
        timestamps=scene.timestamps[KEYFRAMES],
        gt_poses=scene.gt_poses[KEYFRAMES],
        source_index=KEYFRAMES,
    )
    settings = registration.RegistrationSettings(max_range_m=30.0)

    result = registration.register_every_scan(loaded, keyframes, scene.gt_poses[KEYFRAMES], settings)

    np.testing.assert_array_equal(result.tried, np.isin(np.arange(scene.num_scans), others))
    np.testing.assert_array_equal(result.poses[KEYFRAMES], scene.gt_poses[KEYFRAMES])
    assert position_errors(result.poses, scene.gt_poses).max() < 0.02
    assert np.isnan(result.residual_m[KEYFRAMES]).all() and np.isfinite(result.residual_m[others]).all()


def test_the_report_carries_the_residual_and_the_refusal():
    rows = [{"flag": ""}, {"flag": "residual"}, {"flag": ""}]
    rows = report.add_registration(rows, np.array([np.nan, 0.01, 0.2]), ["", "", registration.POOR_FITNESS])
    assert [r["registration_residual_m"] for r in rows] == [None, 0.01, 0.2]
    assert [r["flag"] for r in rows] == ["", "residual", "unregistered (poor fitness)"]


def test_scans_past_the_deadline_keep_their_guesses_flagged_out_of_time(scene):
    settings = registration.RegistrationSettings(max_range_m=30.0)
    target = registration.map_cloud([scene.scans[k] for k in KEYFRAMES], scene.gt_poses[KEYFRAMES], settings)
    guesses = perturbed(scene.gt_poses[[1, 3]], seed=3)

    result = registration.register_to_map(
        [scene.scans[1], scene.scans[3]], guesses, target, settings, deadline=0.0
    )  # long past

    assert result.flag == [registration.OUT_OF_TIME] * 2 and not result.registered.any()
    np.testing.assert_array_equal(result.poses, guesses)


def test_scans_registered_together_get_the_poses_they_get_one_at_a_time(scene):
    settings = registration.RegistrationSettings(max_range_m=30.0)
    target = registration.map_cloud([scene.scans[k] for k in KEYFRAMES], scene.gt_poses[KEYFRAMES], settings)
    others = np.setdiff1d(np.arange(scene.num_scans), KEYFRAMES)
    scans = [scene.scans[s] for s in others] + [scene.scans[1][:20]]  # the last one too few points
    guesses = perturbed(scene.gt_poses[np.r_[others, 1]], seed=4)

    together = registration.register_to_map(scans, guesses, target, settings)
    alone = registration.register_to_map(scans, guesses, target, dataclasses.replace(settings, batch_scans=1))

    assert together.flag == alone.flag == [""] * len(others) + [registration.TOO_FEW_POINTS]
    np.testing.assert_allclose(together.poses, alone.poses, rtol=0, atol=1e-9)
    np.testing.assert_allclose(together.residual_m, alone.residual_m, rtol=0, atol=1e-9)
    assert position_errors(together.poses[:-1], scene.gt_poses[others]).max() < 0.02


def test_a_scan_slid_along_a_corridor_is_held_to_its_guess_along_it():
    # Two parallel walls and a floor: nothing fixes a move along the corridor (y), as along a straight street.
    rng = np.random.default_rng(0)
    walls = np.c_[np.where(np.arange(4000) % 2, 3.0, -3.0), rng.uniform(-20, 20, 4000), rng.uniform(0, 3, 4000)]
    floor = np.c_[rng.uniform(-3, 3, 4000), rng.uniform(-20, 20, 4000), np.zeros(4000)]
    settings = registration.RegistrationSettings(max_range_m=30.0)
    index = registration.map_index(registration.cloud_with_normals(np.vstack([walls, floor]), settings))
    scan = registration.prepare_scan(np.vstack([walls, floor]) - [0.0, 0.0, 1.5], settings)
    guess = np.eye(4)
    guess[2, 3] = 1.5
    slid = guess.copy()
    slid[1, 3] = 0.3  # what ICP's answer along the corridor may be: where its start and noise led it

    pose, _, fitness, flag = registration.judged(scan, guess, slid, index, settings)

    assert flag == "" and fitness > 0.9
    assert abs(pose[1, 3]) < 0.01 and np.abs(pose - guess).max() < 0.01
