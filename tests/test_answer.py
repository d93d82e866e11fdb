"""The run's answer (neld_jax.judging.answer): NeLD-BA's poses unless they blurred the start's raw map on every query
draw; then the start's poses, and NeLD-BA's written beside them."""

import dataclasses
import json
import logging

import numpy as np
import pytest
from conftest import make_tiny_config

from neld_jax import run
from neld_jax.data.poses import read_tum
from neld_jax.judging import answer
from neld_jax.lie import se3_exp_float64


def _margin(per_draw):
    per_draw = np.asarray(per_draw, dtype=np.float64)
    return {
        "per_draw": per_draw.tolist(),
        "mean": float(per_draw.mean()),
        "std": float(per_draw.std(ddof=1)),
        "all_draws_agree": bool((per_draw > 0).all() or (per_draw < 0).all()),
    }


@pytest.mark.parametrize(
    "per_draw, chosen, blurred",
    [
        ([0.02, 0.01, 0.03], "baseline", True),  # blurrier than the start on every draw
        ([0.02, -0.01, 0.03], "baseline", False),  # the draws disagree: a tie keeps NeLD-BA's
        ([-0.02, -0.01, -0.03], "baseline", False),  # crisper
        ([0.02, 0.01, 0.03], "input", False),  # blurrier than the baseline, but training started from the input
    ],
)
def test_the_start_is_kept_only_where_every_draw_says_it_was_crisper(per_draw, chosen, blurred):
    margins = {"baseline": _margin(per_draw), "initial": _margin([-0.5, -0.4, -0.6])}
    assert answer.blurred_the_start(margins, chosen) is blurred
    assert not answer.blurred_the_start({}, chosen)  # no draws: nothing to judge by


def test_the_start_as_answer_moves_the_figures_and_the_margins_to_it():
    crisp = {
        "initial": {"mean_map_entropy": -2.0},
        "baseline": {"mean_map_entropy": -3.0},
        "optimized": {"mean_map_entropy": -2.9},
    }
    per_scan = {name: np.full(3, s["mean_map_entropy"]) for name, s in crisp.items()}
    margins = {"initial": _margin([-0.9, -0.8]), "baseline": _margin([0.1, 0.05])}  # optimized minus each
    crisp2, per_scan2, margins2 = answer.start_as_answer((crisp, per_scan, margins), "baseline")
    assert crisp2["optimized"] == crisp["baseline"] and crisp2["neld_ba"] == crisp["optimized"]
    np.testing.assert_array_equal(per_scan2["optimized"], per_scan["baseline"])
    np.testing.assert_array_equal(per_scan2["neld_ba"], per_scan["optimized"])
    # the answer (the baseline's poses) minus each: initial (-0.9 - 0.1, -0.8 - 0.05), NeLD-BA's, itself
    np.testing.assert_allclose(margins2["initial"]["per_draw"], [-1.0, -0.85])
    np.testing.assert_allclose(margins2["neld_ba"]["per_draw"], [-0.1, -0.05])
    assert margins2["baseline"]["per_draw"] == [0.0, 0.0] and not margins2["baseline"]["all_draws_agree"]


def _blurred(poses: np.ndarray) -> np.ndarray:
    """poses [K, 4, 4] with every keyframe but the first moved by 0.4 m and 4 degrees, in turn one way and the other."""
    moved = np.array(poses)
    for k in range(1, len(moved)):
        sign = 1.0 if k % 2 else -1.0
        twist = sign * np.array([0.4, -0.3, 0.1, 0.0, 0.0, np.deg2rad(4.0)])  # (translation, rotation)
        moved[k] = moved[k] @ se3_exp_float64(twist)
    return moved


def test_a_run_whose_training_blurred_its_start_answers_with_the_start(tmp_path, monkeypatch, caplog):
    # Training that moves the poses away from a crisp start (a stand-in for a field that fitted the wrong thing):
    # poses_optimized and map_raw.ply are the start's, NeLD-BA's poses are written as poses_neld_ba, metrics.json
    # says whose the answer is, and the log says why.
    real_refine = run.refine.refine_keyframes

    def refine_then_blur(settings, keyframes, start_poses, pose_steps, context):
        refined = real_refine(settings, keyframes, start_poses, pose_steps, context)
        return dataclasses.replace(refined, poses=_blurred(refined.poses))

    monkeypatch.setattr(run.refine, "refine_keyframes", refine_then_blur)
    config = make_tiny_config(str(tmp_path / "run"), steps=4)
    config.data.synthetic.num_beams, config.data.synthetic.num_columns = 16, 256  # a map with surfaces to judge
    config.mapping.enabled = False
    with caplog.at_level(logging.WARNING, logger="neld_jax.judging.answer"):
        summary = run.run(config, progress=False)
    r = summary["run"]
    assert r["started_from"] == "input" and r["answer"] == "input"
    assert "blurrier than the input poses training started from" in caplog.text
    _, T_initial = read_tum(tmp_path / "run" / "poses_initial.txt")
    _, T_answer = read_tum(tmp_path / "run" / "poses_optimized.txt")
    _, T_neld_ba = read_tum(tmp_path / "run" / "poses_neld_ba.txt")
    np.testing.assert_allclose(T_answer, T_initial, atol=1e-6)
    moved_m = np.linalg.norm(T_neld_ba[1:, :3, 3] - T_initial[1:, :3, 3], axis=1)
    assert moved_m.min() > 0.3  # NeLD-BA's blurred poses, kept
    assert summary["crispness"]["optimized"] == summary["crispness"]["initial"]
    assert summary["crispness"]["neld_ba"]["mean_map_entropy"] > summary["crispness"]["initial"]["mean_map_entropy"]
    margins = r["crispness_margin"]
    assert margins["neld_ba"]["mean"] < 0 and margins["neld_ba"]["all_draws_agree"]  # the answer is the crisper
    assert not margins["initial"]["all_draws_agree"]  # against itself: a tie
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert set(metrics["evaluation"]["methods"]) >= {"initial", "optimized", "neld_ba"}


def _scaled(poses: np.ndarray, factor: float) -> np.ndarray:
    scaled = poses.copy()
    scaled[:, :3, 3] = poses[0, :3, 3] + factor * (poses[:, :3, 3] - poses[0, :3, 3])
    return scaled


EVERY_SCAN = {"crispness_radius_m": 0.3, "crispness_queries": 3000, "crispness_draws": 3}


def test_a_path_shortened_where_no_scan_can_tell_takes_the_input_distances():
    """On a straight street no surface faces along it: a crisper keyframe map could have shortened the path 3 %, every
    scan's map cannot tell, and the input's distances (the truth here) are the answer's."""
    from test_weak_directions import scans_along, sensor_pose

    from neld_jax.synthetic.scene import raycasting_scene, street_meshes

    truth = np.stack([sensor_pose(2.0 * k - 6.0) for k in range(6)])
    scans = scans_along(raycasting_scene(street_meshes()), truth)
    kept, record = answer.keep_input_travel(scans, _scaled(truth, 0.97), truth, EVERY_SCAN)
    assert record["kept"] == "input" and record["largest_window_change"] > answer.ODOMETRY_DRIFT
    assert record["path_ratio"] == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(kept[:, :3, 3], truth[:, :3, 3], atol=1e-9)


def test_distances_the_scans_confirm_or_within_an_odometry_drift_stay():
    from test_weak_directions import scans_along, sensor_pose

    from neld_jax.synthetic.scene import make_scene

    truth = np.stack([sensor_pose(-3.0 + 1.5 * k, 15.0, 0.1 * k) for k in range(4)])
    scans = scans_along(make_scene(0)[0], truth)
    # The input drifted 3 % long; the walls across the path see it: the answer's true distances are crisper.
    kept, record = answer.keep_input_travel(scans, truth, _scaled(truth, 1.03), EVERY_SCAN)
    assert record["kept"] == "own" and record["margin"] < 0
    np.testing.assert_array_equal(kept, truth)
    # Within what an odometry drifts: nothing judged, nothing moved.
    kept, record = answer.keep_input_travel(scans, truth, _scaled(truth, 1.0 + answer.ODOMETRY_DRIFT / 2), EVERY_SCAN)
    assert record["kept"] is None and record["margin"] is None and record["steps_beyond"] == 0.0
    np.testing.assert_array_equal(kept, truth)


def test_the_kept_travel_reaches_every_output_of_the_run():
    """keep_travel_of_input on a run's steps: the input's distances become the every-scan poses and the keyframes'."""
    from test_weak_directions import scans_along, sensor_pose

    from neld_jax.synthetic.scene import raycasting_scene, street_meshes
    from neld_jax.writing.outputs import RunSteps

    truth = np.stack([sensor_pose(2.0 * k - 6.0) for k in range(6)])
    scans = scans_along(raycasting_scene(street_meshes()), truth)
    loaded = dataclasses.make_dataclass("Loaded", ["scans", "poses", "timestamps", "num_scans"])(scans, truth, None, 6)
    keyframes = dataclasses.make_dataclass("Keyframes", ["loaded_index"])(np.array([0, 5]))
    refined = dataclasses.make_dataclass("Refined", ["poses"])(_scaled(truth, 0.97)[[0, 5]])
    made = RunSteps(loaded, keyframes, None, refined)
    checked = answer.keep_travel_of_input(made, EVERY_SCAN)
    assert checked.travelled["kept"] == "input"
    np.testing.assert_allclose(checked.every_scan_poses()[:, :3, 3], truth[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(checked.refined.poses, checked.every_scan_poses()[[0, 5]])
