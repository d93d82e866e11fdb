"""The classical baseline (neld_jax.baseline) reduces the drift of a small synthetic sequence, its answer does not
depend on how far the start drifted, it decides from the scans whether to trust the input's tilt and where its
refinement starts; neld-baseline end to end."""

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from neld_jax import baseline
from neld_jax.baseline import (
    BaselineSettings,
    Segments,
    TargetIndex,
    anchored,
    candidate_pairs,
    loop_closed_graph,
    multiscale_icp,
    point_to_plane_icp,
    prepare_clouds,
    refine_against_map,
    register_sequence,
)
from neld_jax.data.preprocess import KeyframeSettings, preprocess
from neld_jax.geometry import invert_poses, rotation_angles_deg
from neld_jax.judging.metrics import ate
from neld_jax.synthetic.generator import make_sequence
from neld_jax.synthetic.pseudo_gt import with_drift

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def drifted_sequence():
    seq = make_sequence(
        dict(
            num_scans=6,
            num_beams=32,
            num_columns=512,
            gt_map_points=0,
            scene_size_m=40.0,
            trajectory_radius_m=8.0,
            max_range_m=30.0,
            drift_trans_m=0.15,
            drift_rot_deg=1.0,
        )
    )
    return preprocess(seq, KeyframeSettings(keyframe_interval_s=0.0, min_range=0.5, max_range=30.0, voxel_size=0.1))


SETTINGS = BaselineSettings(window=2, voxel_size_m=0.2)


@pytest.fixture(scope="module")
def registered(drifted_sequence):
    """register_sequence on the drifted sequence with SETTINGS, once for the tests that only read its result."""
    return register_sequence(drifted_sequence.scans, drifted_sequence.poses, SETTINGS)


def test_register_sequence_reduces_ate(drifted_sequence, registered):
    seq = drifted_sequence
    before = ate(seq.poses, seq.gt_poses)
    refined = registered.poses
    after = ate(refined, seq.gt_poses)
    assert before["translation_rmse_m"] > 0.1
    assert after["translation_rmse_m"] < 0.25 * before["translation_rmse_m"]
    assert after["rotation_rmse_deg"] < 0.25 * before["rotation_rmse_deg"]
    np.testing.assert_allclose(refined[0], seq.poses[0], atol=1e-9)  # the gauge scan does not move
    rotations = refined[:, :3, :3]
    np.testing.assert_allclose(
        np.einsum("sji,sjk->sik", rotations, rotations), np.tile(np.eye(3), (6, 1, 1)), atol=1e-10
    )


def test_progress_bars_follow_each_step_of_the_baseline_only_when_asked(drifted_sequence, registered, capsys):
    # Minutes of registrations on a real recording: bin/baseline.py and bin/train.py show a bar per step; the
    # library's default is quiet (test_register_sequence_repeats_bit_for_bit). The refinement's bar counts every
    # scan of every round.
    seq = drifted_sequence
    shown = register_sequence(seq.scans, seq.poses, SETTINGS, progress=True).poses
    err = capsys.readouterr().err
    np.testing.assert_array_equal(shown, registered.poses)
    rounds = SETTINGS.map_rounds * seq.num_scans
    assert "baseline: scan-to-map chain (the input tilt)" in err and "baseline: scan-to-map chain (its own tilt)" in err
    assert f"{seq.num_scans - 1}/{seq.num_scans - 1}" in err
    assert "baseline: loop closures" in err
    assert f"baseline: {SETTINGS.map_rounds} round(s) of multi-view refinement" in err and f"{rounds}/{rounds}" in err


def test_the_refinement_starts_from_the_crisper_of_the_graph_and_the_chain(drifted_sequence):
    # choose_refinement_start: the crisper raw map of the two (a tie keeps the graph); register_sequence reports it
    # and on_round sees that start as round 0, then every round.
    seq = drifted_sequence
    truth, drifted = seq.gt_poses, seq.poses
    assert baseline.choose_refinement_start(truth, drifted, seq.scans, SETTINGS)[0] == "graph"
    start, entropy = baseline.choose_refinement_start(drifted, truth, seq.scans, SETTINGS)
    assert start == "chain" and entropy["chain"] < entropy["graph"]
    assert baseline.choose_refinement_start(truth, truth, seq.scans, SETTINGS)[0] == "graph"  # a tie
    rounds = []
    result = register_sequence(seq.scans, seq.poses, SETTINGS, on_round=lambda r, poses: rounds.append((r, poses)))
    assert [r for r, _ in rounds] == list(range(SETTINGS.map_rounds + 1))
    assert result.refined_from in ("graph", "chain") and set(result.start_entropy) == {"graph", "chain"}
    assert result.report()["refined_from"] == result.refined_from and "poses" not in result.report()
    before = ate(seq.poses, seq.gt_poses)["translation_rmse_m"]
    assert ate(rounds[0][1], seq.gt_poses)["translation_rmse_m"] < 0.25 * before  # the rounds start from the scans


def test_the_chain_that_goes_on_keeps_the_input_tilt_unless_the_free_one_is_clearly_crisper(drifted_sequence):
    # choose_chain: a tie (within TILT_MARGIN) trusts the input's tilt; a free chain crisper by more wins.
    seq = drifted_sequence
    truth, drifted = seq.gt_poses, seq.poses
    chosen, entropy = baseline.choose_chain({"input tilt": drifted, "free": truth}, seq.scans, SETTINGS)
    assert chosen == "free" and entropy["free"] < entropy["input tilt"] - baseline.TILT_MARGIN
    assert baseline.choose_chain({"input tilt": truth, "free": drifted}, seq.scans, SETTINGS)[0] == "input tilt"
    assert baseline.choose_chain({"input tilt": truth, "free": truth}, seq.scans, SETTINGS)[0] == "input tilt"
    assert baseline.choose_chain({"input tilt": None, "free": truth}, seq.scans, SETTINGS) == ("free", {})
    # From a drift of position and heading only (an IMU-aided odometry's), the run trusts the input's tilt ...
    kept_tilt = with_drift(dataclasses.replace(seq, poses=truth), 0.15, 1.0, seed=3, keep_tilt=True)
    result = register_sequence(kept_tilt.scans, kept_tilt.poses, dataclasses.replace(SETTINGS, map_rounds=0))
    assert result.tilt == "input", result.chain_entropy
    # ... and from a drift that tilts the scans (a LiDAR-only odometry's), it finds its own
    tilted = with_drift(dataclasses.replace(seq, poses=truth), 0.05, 3.0, seed=3)
    result = register_sequence(tilted.scans, tilted.poses, dataclasses.replace(SETTINGS, map_rounds=0))
    assert result.tilt == "free", result.chain_entropy


def test_answer_does_not_depend_on_the_start(drifted_sequence, registered):
    # Two starts whose drift differs (a further random walk on top) give the same answer: every registration
    # starts from the odometry's increment, which both starts get within ICP's basin.
    seq = drifted_sequence
    further = with_drift(seq, 0.05, 0.5, seed=3)
    a = registered.poses
    b = register_sequence(seq.scans, further.poses, SETTINGS).poses
    apart_before = ate(further.poses, seq.poses)["translation_rmse_m"]
    apart_after = ate(b, a)["translation_rmse_m"]
    assert apart_before > 0.02
    assert apart_after < 0.1 * apart_before


def test_register_sequence_repeats_bit_for_bit_and_quietly(drifted_sequence, registered, capsys):
    # The same input and settings give the same poses: Open3D's ICP steps and information matrices sum over their
    # pairs in an order that changes from call to call (TBB), so the baseline sums them itself, in index order
    # (with Open3D's sums two runs on this sequence came out up to 1.4e-6 apart). The library's default shows no
    # progress bar.
    seq = drifted_sequence
    again = register_sequence(seq.scans, seq.poses, SETTINGS).poses
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(again, registered.poses)


def test_icp_steps_and_information_are_open3ds(drifted_sequence):
    # The fixed-order sums compute what Open3D's TransformationEstimationPointToPlane and
    # get_information_matrix_from_point_clouds compute, to round-off.
    from neld_jax.baseline import information, point_to_plane_step

    source, target = prepare_clouds(drifted_sequence.scans[1:3], SETTINGS)
    guess = invert_poses(drifted_sequence.poses[2]) @ drifted_sequence.poses[1]
    registration = o3d.pipelines.registration
    expected = registration.get_information_matrix_from_point_clouds(source, target, 0.25, guess)
    np.testing.assert_allclose(
        information(source, target, guess, SETTINGS), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max()
    )
    moved = np.asarray(source.points) @ guess[:3, :3].T + guess[:3, 3]
    nearest, _ = TargetIndex(target, 0.5).nearest(moved, 0.5)
    pairs = np.stack([np.flatnonzero(nearest >= 0), nearest[nearest >= 0]], axis=1).astype(np.int32)
    expected = registration.TransformationEstimationPointToPlane().compute_transformation(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(moved)), target, o3d.utility.Vector2iVector(pairs)
    )
    step = point_to_plane_step(
        moved[pairs[:, 0]], np.asarray(target.points)[pairs[:, 1]], np.asarray(target.normals)[pairs[:, 1]]
    )
    assert np.linalg.norm(expected[:3, 3]) > 0.01  # a real step
    np.testing.assert_allclose(step, expected, atol=1e-12)


def test_settings_from_config_checks_fields():
    from neld_jax.config import defaults

    config = defaults()
    config.baseline.window, config.eval.crispness_queries = 3, 500
    assert BaselineSettings.from_config(config) == BaselineSettings(window=3, crispness_queries=500)
    config.baseline.windwo = 3
    with pytest.raises(ValueError, match="unknown field"):
        BaselineSettings.from_config(config)


def test_candidate_pairs_are_neighbours_and_close_non_neighbours():
    positions = np.array([[0.0, 0, 0], [5.0, 0, 0], [10.0, 0, 0], [1.0, 0, 0]])
    odometry, loops = candidate_pairs(positions, loop_radius_m=6.0)
    assert odometry == [(0, 1), (1, 2), (2, 3)]
    assert loops == [(0, 3), (1, 3)]  # (0, 2) is 10 m apart
    # At most max_loops_per_scan partners per scan, the nearest ones.
    line = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    _, loops = candidate_pairs(line, loop_radius_m=100.0, max_loops_per_scan=2)
    assert [pair for pair in loops if pair[0] == 0] == [(0, 2), (0, 3)]
    assert len(loops) == 2 * 7 + 1  # scans 0-6 have two partners, scan 7 one (9), scans 8 and 9 none
    # Loop partners at least min_index_gap apart (the chain's window already ties closer scans).
    _, loops = candidate_pairs(line, loop_radius_m=100.0, max_loops_per_scan=1, min_index_gap=4)
    assert loops == [(i, i + 4) for i in range(6)]


def test_single_scan_is_returned_unchanged():
    poses = np.eye(4)[None]
    result = register_sequence([np.zeros((10, 3))], poses)
    np.testing.assert_array_equal(result.poses, poses)
    assert result.report() == {}


def test_cli_writes_baseline_outputs_and_table(tmp_path):
    out = tmp_path / "run"
    args = [
        sys.executable,
        str(REPO / "bin" / "baseline.py"),
        f"--config={REPO / 'configs' / 'demo.py'}",
        f"--config.output_dir={out}",
        "--config.data.voxel_size_m=0.2",
        "--config.data.synthetic.num_scans=4",
        "--config.data.synthetic.num_beams=16",
        "--config.data.synthetic.num_columns=256",
        "--config.data.synthetic.gt_map_points=5000",
        "--config.data.synthetic.scene_size_m=30.0",
        "--config.data.synthetic.trajectory_radius_m=5.0",
        "--config.data.synthetic.max_range_m=30.0",
        "--config.mapping.voxel_size_m=0.0",
    ]
    done = subprocess.run(args, capture_output=True, text=True, env=dict(os.environ, JAX_PLATFORMS="cpu"), timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    for name in (
        "poses_baseline.txt",
        "poses_baseline.kitti",
        "map_raw_baseline.ply",
        "poses_initial.txt",
        "map_raw_initial.ply",
        "poses_gt.txt",
        "map_gt.ply",
        "metrics.json",
    ):
        assert (out / name).is_file(), name
    assert "baseline" in done.stdout and "initial" in done.stdout
    evaluation = json.loads((out / "metrics.json").read_text())["evaluation"]
    assert set(evaluation["methods"]) == {"initial", "baseline"}
    assert evaluation["methods"]["baseline"]["raw_map"]["num_est"] > 0

    bad = subprocess.run(
        args[:2]
        + [
            f"--config={REPO / 'configs' / 'generic.py'}",
            f"--config.data.root={tmp_path / 'no_such_sequence'}",
            f"--config.output_dir={tmp_path / 'bad'}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 1
    assert bad.stderr.startswith("error: ") and "Traceback" not in bad.stderr


def test_training_starts_from_the_baseline_of_config_baseline(drifted_sequence, registered):
    # start.poses=baseline: the run registers first, with config.baseline's settings, and trains from the result;
    # "input" trains from the loaded poses.
    from neld_jax.config import defaults
    from neld_jax.steps.start import StartSettings, choose_start

    config = defaults()
    config.baseline.window, config.baseline.voxel_size_m = SETTINGS.window, SETTINGS.voxel_size_m
    config.start.poses = "baseline"
    chosen = choose_start(StartSettings.from_config(config), drifted_sequence)
    assert chosen.baseline_seconds > 0 and chosen.chosen == "baseline" and chosen.pose_steps.keep_scale
    assert chosen.baseline_report["refined_from"] in ("graph", "chain")
    assert BaselineSettings.from_config(config) == SETTINGS
    np.testing.assert_array_equal(chosen.poses, registered.poses)
    config.start.poses = "input"
    chosen = choose_start(StartSettings.from_config(config), drifted_sequence)
    assert chosen.baseline_seconds is None and chosen.poses is drifted_sequence.poses and chosen.chosen == "input"


def test_a_chain_that_keeps_the_input_tilt_gives_every_scan_the_inputs_up_axis(drifted_sequence):
    # An input that drifted in position and heading only (an IMU-aided odometry): the chain that keeps the input's
    # tilt gives its scans the input's up axes exactly and undoes the drift as the free one does.
    truth = drifted_sequence.gt_poses
    kept_tilt = with_drift(dataclasses.replace(drifted_sequence, poses=truth), 0.15, 1.0, seed=3, keep_tilt=True)
    np.testing.assert_allclose(kept_tilt.poses[:, 2, :3], truth[:, 2, :3], atol=1e-12)
    clouds = prepare_clouds(kept_tilt.scans, SETTINGS)
    chain, _ = baseline.scan_to_map_chain(clouds, kept_tilt.poses, SETTINGS, keep_input_tilt=True)
    free, _ = baseline.scan_to_map_chain(clouds, kept_tilt.poses, SETTINGS)
    np.testing.assert_allclose(chain[:, 2, :3], kept_tilt.poses[:, 2, :3], atol=1e-9)
    assert np.abs(free[:, 2, :3] - kept_tilt.poses[:, 2, :3]).max() > 1e-6  # ICP alone tilts them a little
    before = ate(kept_tilt.poses, truth)["translation_rmse_m"]
    assert before > 0.1 and ate(chain, truth)["translation_rmse_m"] < 0.25 * before


def test_chain_keeps_the_odometry_increment_when_icp_slides_far(drifted_sequence, monkeypatch, caplog):
    # A link whose ICP result lies further than max_link_correction_m from the odometry's increment (with a good
    # overlap, as in a corridor) keeps the increment. ICP is replaced by one that slides 2 m along x.
    seq = drifted_sequence
    clouds = prepare_clouds(seq.scans, SETTINGS)
    slide = np.eye(4)
    slide[0, 3] = 2.0

    class Result:
        fitness = 0.9

    monkeypatch.setattr(
        baseline.chain, "multiscale_icp", lambda source, target, guess, settings: (guess @ slide, Result())
    )
    chain, fitness = baseline.scan_to_map_chain(clouds, seq.poses, SETTINGS)
    np.testing.assert_allclose(chain, seq.poses, atol=1e-9)  # every link kept the odometry's increment
    warned = [r.getMessage() for r in caplog.records if "max_link_correction_m" in r.getMessage()]
    assert len(warned) == 1 and f"moved {len(clouds) - 1} scan(s)" in warned[0]  # one line for all of them
    chain, _ = baseline.scan_to_map_chain(clouds, seq.poses, dataclasses.replace(SETTINGS, max_link_correction_m=3.0))
    np.testing.assert_allclose(
        np.linalg.inv(seq.poses[0]) @ chain[1], np.linalg.inv(seq.poses[0]) @ seq.poses[1] @ slide, atol=1e-9
    )  # under a looser bound the slide is taken


def test_a_link_icp_moves_far_is_kept_where_the_features_find_the_same_pose(drifted_sequence, monkeypatch):
    # The odometry's first increment 0.8 m wrong (every later pose moved with it: an odometry's first second at
    # speed): ICP from it finds the true link, past max_link_correction_m (0.5 m), and the global registration, from
    # no start, lands on the same pose, so the link is ICP's. Where the features disagree, the increment stays.
    seq = drifted_sequence
    clouds = prepare_clouds(seq.scans, SETTINGS)
    start = seq.gt_poses.copy()
    start[1:, 0, 3] += 0.8
    chain, _ = baseline.scan_to_map_chain(clouds, start, SETTINGS)
    link = np.linalg.inv(chain[0]) @ chain[1]
    truth = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses[1]
    assert np.linalg.norm(link[:3, 3] - truth[:3, 3]) < 0.05
    monkeypatch.setattr(baseline.chain, "_features_agree", lambda *args: False)
    kept, _ = baseline.scan_to_map_chain(clouds, start, SETTINGS)
    np.testing.assert_allclose(np.linalg.inv(kept[0]) @ kept[1], np.linalg.inv(start[0]) @ start[1], atol=1e-9)


def test_a_chain_whose_links_overlap_too_little_is_given_up(drifted_sequence, monkeypatch, caplog):
    # Keyframes too far apart for ICP (MulRan Riverside02): once the links' median overlap falls below
    # chain_min_median_overlap, the chain stops, the pose graph is skipped and the refinement starts from the input.
    seq = drifted_sequence
    clouds = prepare_clouds(seq.scans, SETTINGS)

    class Result:
        fitness = 0.2  # enough for a link (min_chain_fitness), too little for a chain

    monkeypatch.setattr(baseline.chain, "multiscale_icp", lambda source, target, guess, settings: (guess, Result()))
    settings = dataclasses.replace(SETTINGS, chain_check_links=2, map_rounds=0)
    chain, fitness = baseline.scan_to_map_chain(clouds, seq.poses, settings)
    assert chain is None and np.all(fitness[1:3] == 0.2) and np.all(np.isnan(fitness[3:]))  # checked at link 2
    warned = [r.getMessage() for r in caplog.records if "the first 2 chain links overlap" in r.getMessage()]
    assert len(warned) == 1 and "by 20.00%" in warned[0]
    assert "drift the input poses gather along the route stays in the answer" in warned[0]  # the user is told
    switched_off = dataclasses.replace(settings, chain_min_median_overlap=0)
    kept_on, _ = baseline.scan_to_map_chain(clouds, seq.poses, switched_off)
    np.testing.assert_allclose(kept_on, seq.poses, atol=1e-9)  # 0 switches the rule off
    Result.fitness = settings.chain_min_median_overlap
    assert baseline.scan_to_map_chain(clouds, seq.poses, settings)[0] is not None  # at the threshold: kept

    def not_called(*args):
        raise AssertionError("no pose graph without a chain")

    Result.fitness = 0.2
    monkeypatch.setattr(baseline.pipeline, "loop_closed_graph", not_called)
    result = register_sequence(seq.scans, seq.poses, settings)
    np.testing.assert_allclose(result.poses, seq.poses, atol=1e-9)  # no rounds here: the input as it came
    assert result.chain_given_up and result.refined_from == "input" and result.chain_entropy == {}
    assert result.tilt is None and result.report()["tilt"] is None  # no chain went on


def test_a_chain_still_running_at_the_deadline_is_given_up(drifted_sequence, monkeypatch, caplog):
    # A sequence too long for the run's clock: the chain stops between two links once the deadline has passed,
    # the pose graph is skipped and (no time left for the rounds) the input is the baseline's answer.
    seq = drifted_sequence
    clouds = prepare_clouds(seq.scans, SETTINGS)
    clock = iter(range(1000))
    with mock.patch.object(time, "perf_counter", lambda: float(next(clock))):
        chain, fitness = baseline.scan_to_map_chain(clouds, seq.poses, SETTINGS, deadline=1.5)
    # The clock ticks before each link (0, 1, 2): links 1 and 2 were registered when it passed.
    assert chain is None and np.all(np.isfinite(fitness[:3])) and np.all(np.isnan(fitness[3:]))
    assert any("deadline passed after 2 of the 5 chain links" in r.getMessage() for r in caplog.records)
    assert baseline.scan_to_map_chain(clouds, seq.poses, SETTINGS, deadline=time.perf_counter() + 600)[0] is not None

    def not_called(*args):
        raise AssertionError("no pose graph without a chain")

    monkeypatch.setattr(baseline.pipeline, "loop_closed_graph", not_called)
    result = register_sequence(
        seq.scans, seq.poses, dataclasses.replace(SETTINGS, map_rounds=2), deadline=time.perf_counter() - 1.0
    )
    np.testing.assert_allclose(result.poses, seq.poses, atol=1e-9)
    assert result.chain_given_up and result.refined_from == "input"
    assert result.map_rounds_done == 0 and result.stopped_at_deadline


def _two_recordings(seq):
    """The drifted sequence as two recordings joined: scans 0-2 under the input's drift, scans 3-5 placed in the first
    one's frame 0.36 m off the truth (as a placing against the first recording's drifted input puts them), their
    own steps exact -> (the joined input poses [6, 4, 4], the truth in the input's frame [6, 4, 4])."""
    truth = anchored(seq.gt_poses, seq.poses[0])
    off = np.eye(4)
    off[:3, 3] = [0.3, -0.2, 0.0]
    return np.concatenate([seq.poses[:3], off @ truth[3:]]), truth


def test_the_chain_restarts_at_a_later_recordings_first_scan(drifted_sequence):
    # Run on, the chain places scan 3 from scan 2 by the input's step and registers it to the first recording's
    # map: the second recording takes on the first one's correction. Restarted, scan 3 keeps its input pose, and
    # scans 4 and 5 register to the second recording's own scans only.
    seq = drifted_sequence
    init, _ = _two_recordings(seq)
    clouds = prepare_clouds(seq.scans, SETTINGS)
    restarted, fitness = baseline.scan_to_map_chain(clouds, init, SETTINGS, segments=Segments(starts=(3,)))
    run_on, _ = baseline.scan_to_map_chain(clouds, init, SETTINGS)
    np.testing.assert_array_equal(restarted[3], init[3])
    np.testing.assert_array_equal(restarted[:3], run_on[:3])  # the first recording's chain as before
    assert fitness[3] == 1.0
    departure_m = np.linalg.norm(restarted[3:, :3, 3] - init[3:, :3, 3], axis=1)
    assert departure_m.max() < 0.02  # its own steps, not the first recording's correction
    angles = rotation_angles_deg(np.einsum("sji,sjk->sik", init[3:, :3, :3], restarted[3:, :3, :3]))
    assert angles.max() < 0.2
    carried_m = np.linalg.norm(run_on[3:, :3, 3] - init[3:, :3, 3], axis=1)
    assert carried_m.min() > 0.1  # what the restart prevents


def test_the_placings_links_join_the_recordings_in_the_pose_graph(drifted_sequence):
    # The chain restarted in the second recording, 0.36 m off the first's: beyond the loop gates (0.2 m), so no
    # loop closure joins them, but the placing's links (the true relative poses here) pull the second recording
    # onto the first, and the chain's step into scan 3 (no measurement) does not hold it back.
    seq = drifted_sequence
    chain, truth = _two_recordings(seq)
    chain[:3] = truth[:3]
    clouds = prepare_clouds(seq.scans, SETTINGS)
    links = tuple((i, j, np.linalg.inv(truth[j]) @ truth[i]) for i, j in ((3, 1), (5, 0)))
    linked, loops = loop_closed_graph(clouds, chain, SETTINGS, segments=Segments((3,), links))
    unlinked, _ = loop_closed_graph(clouds, chain, SETTINGS)
    assert loops.linked == loops.links_in_final_graph == 2  # no closure joins the recordings: the links stay
    assert np.linalg.norm(linked[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.03
    assert np.linalg.norm(unlinked[3:, :3, 3] - truth[3:, :3, 3], axis=1).min() > 0.1


def test_over_joined_recordings_the_refinement_starts_from_the_graph(drifted_sequence):
    seq = drifted_sequence
    init, _ = _two_recordings(seq)
    result = register_sequence(
        seq.scans, init, dataclasses.replace(SETTINGS, map_rounds=1), segments=Segments(starts=(3,))
    )
    assert result.refined_from == "graph" and result.start_entropy is None


def test_one_recording_gives_the_baselines_poses_bit_for_bit(drifted_sequence, registered):
    seq = drifted_sequence
    one = register_sequence(seq.scans, seq.poses, SETTINGS, segments=Segments())
    np.testing.assert_array_equal(one.poses, registered.poses)
    with pytest.raises(ValueError, match="segment starts must ascend"):
        register_sequence(seq.scans, seq.poses, SETTINGS, segments=Segments(starts=(0,)))


def test_multi_view_refinement_pulls_a_scan_onto_the_others_map_and_gates_a_far_one(drifted_sequence):
    # The scans lie where they were taken, but scan 2 is pushed off by 10 cm and 0.6 degrees and scan 3 by 1 m
    # (beyond max_loop_correction_m): the rounds bring scan 2 back onto the others' map, leave scan 3 where it
    # was, and keep the gauge scan 0 and the well-placed scans where they are.
    seq = drifted_sequence
    start = seq.gt_poses.copy()
    angle = np.radians(0.6)
    nudge = np.eye(4)
    nudge[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    nudge[:3, 3] = [0.06, -0.06, 0.05]
    start[2] = start[2] @ nudge
    start[3, 0, 3] += 1.0
    settings = dataclasses.replace(SETTINGS, map_rounds=2)
    clouds = prepare_clouds(seq.scans, settings)
    seen = []
    refined, refinement = refine_against_map(clouds, start, settings, on_round=lambda r, poses: seen.append((r, poses)))
    # on_round sees each round's poses (copies), the last of them the result
    assert [r for r, _ in seen] == [1, 2]
    np.testing.assert_array_equal(seen[-1][1], refined)
    assert seen[0][1] is not refined and not np.allclose(seen[0][1][2], start[2])

    def errors(poses):
        """-> (translation errors [S] m, rotation errors [S] deg) against the truth."""
        relative = invert_poses(seq.gt_poses) @ poses
        return np.linalg.norm(relative[:, :3, 3], axis=1), rotation_angles_deg(relative[:, :3, :3])

    (t_before, r_before), (t_after, r_after) = errors(start), errors(refined)
    assert t_before[2] > 0.09 and r_before[2] > 0.55
    assert t_after[2] < 0.25 * t_before[2] and r_after[2] < 0.25 * r_before[2]
    assert np.all(t_after[[1, 4, 5]] < 0.02) and np.all(r_after[[1, 4, 5]] < 0.1)
    np.testing.assert_array_equal(refined[0], start[0])  # the gauge scan
    np.testing.assert_array_equal(refined[3], start[3])  # gated: ICP would move it by about 1 m
    assert refinement.rejected >= 2 / 10  # scan 3 in both rounds, of 5 registrations a round
    assert refinement.rounds_done == 2 and not refinement.stopped


def test_a_deadline_stops_the_refinement_between_two_registrations(drifted_sequence):
    # neld_jax.run keeps a run's time by the baseline's deadline: the poses when it passes are the answer. One
    # already past registers nothing; one that passes during the rounds leaves the scans registered so far moved.
    seq = drifted_sequence
    start = seq.gt_poses.copy()
    start[2, :3, 3] += [0.06, -0.06, 0.05]
    settings = dataclasses.replace(SETTINGS, map_rounds=2)
    clouds = prepare_clouds(seq.scans, settings)
    untouched, stopped = refine_against_map(clouds, start, settings, deadline=time.perf_counter() - 1.0)
    np.testing.assert_array_equal(untouched, start)
    assert stopped.stopped and stopped.rounds_done == 0
    clock = iter(range(1000))
    with mock.patch.object(time, "perf_counter", lambda: float(next(clock))):
        part_way, stopped = refine_against_map(clouds, start, settings, deadline=2.5)
    # The clock ticks before the even half (0) and before each of its scans (1, 2, 3: scans 0, 2, 4): the gauge and
    # scan 2 were visited when the deadline passed, 2 of the 6 scans of round 1; only scan 2 moved.
    assert stopped.stopped and stopped.rounds_done == pytest.approx(2 / 6, abs=1e-3)
    assert not np.allclose(part_way[2], start[2])
    np.testing.assert_array_equal(np.delete(part_way, 2, axis=0), np.delete(start, 2, axis=0))


def _plane_points(origin, u, v, size_u, size_v, spacing=0.1):
    """Points [N, 3] on origin + a u + b v, a in [0, size_u], b in [0, size_v], on a grid."""
    a, b = np.meshgrid(np.arange(0, size_u, spacing), np.arange(0, size_v, spacing), indexing="ij")
    return np.asarray(origin) + a.reshape(-1, 1) * np.asarray(u) + b.reshape(-1, 1) * np.asarray(v)


def _cloud(parts):
    """parts: [(points [N, 3], normal [3])] -> an Open3D cloud with those normals."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate([p for p, _ in parts])))
    cloud.normals = o3d.utility.Vector3dVector(np.concatenate([np.tile(n, (len(p), 1)) for p, n in parts]))
    return cloud


def test_icp_does_not_pair_the_two_faces_of_a_thin_wall():
    # A floor, a side wall and a far wall fix the pose. The target saw the FRONT face of a 0.3 m thick wall (normal
    # towards -x), the source, from the other side, its BACK face (normal +x): the same pose for both, but the
    # plain nearest-neighbour pairing (Open3D's ICP) pulls the back face onto the front face and slides the scan
    # along x. Pairing only compatible normals keeps the true pose.
    floor = (_plane_points([-6, -4, 0], [1, 0, 0], [0, 1, 0], 12, 8, 0.25), [0, 0, 1])
    side = (_plane_points([-6, -4, 0], [1, 0, 0], [0, 0, 1], 12, 3, 0.25), [0, 1, 0])
    far = (_plane_points([-6, -4, 0], [0, 1, 0], [0, 0, 1], 8, 3, 0.5), [1, 0, 0])
    front = (_plane_points([5.0, -4, 0], [0, 1, 0], [0, 0, 1], 8, 3), [-1, 0, 0])
    back = (_plane_points([5.3, -4, 0], [0, 1, 0], [0, 0, 1], 8, 3), [1, 0, 0])
    target, source = _cloud([floor, side, far, front]), _cloud([floor, side, far, back])
    settings = BaselineSettings(icp_distances_m=(1.0, 0.5, 0.25, 0.1))

    transform, result = multiscale_icp(source, target, np.eye(4), settings)
    assert np.linalg.norm(transform[:3, 3]) < 0.01
    assert result.fitness < 1.0  # the back face has no partner within 0.1 m: Open3D's fitness definition
    plain = np.eye(4)
    for distance in settings.icp_distances_m:
        plain = o3d.pipelines.registration.registration_icp(
            source,
            target,
            distance,
            plain,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30),
        ).transformation
    assert plain[0, 3] < -0.1  # what the normal check prevents

    # Map normals of unknown sign (oriented=False) pair by |cosine|: a flipped target still registers, and a
    # nudge of 5 cm along x is undone.
    flipped = o3d.geometry.PointCloud(target)
    flipped.normals = o3d.utility.Vector3dVector(-np.asarray(target.normals))
    nudge = np.eye(4)
    nudge[0, 3] = 0.05
    result = point_to_plane_icp(source, flipped, nudge, 0.25, 30, 0.5, oriented=False)
    assert np.linalg.norm(result.transformation[:3, 3]) < 0.01 and result.num_correspondences > 0


@pytest.fixture(scope="module")
def short_courtyard_route():
    seq = make_sequence(
        dict(
            route="courtyards",
            route_length_m=100.0,
            num_scans=34,
            num_beams=32,
            num_columns=512,
            gt_map_points=0,
            max_range_m=30.0,
            drift_trans_m=0.0,
            drift_rot_deg=0.0,
        )
    )
    return preprocess(seq, KeyframeSettings(keyframe_interval_s=0.0, min_range=0.5, max_range=30.0, voxel_size=0.1))


def test_global_registration_closes_a_loop_beyond_icps_reach(short_courtyard_route):
    # A chain that drifted linearly to 2.5 m at the loop's end (the truth with a growing offset; 2.5 % of the path,
    # so the drift allowance is raised to 3 %). On this short route the end scans overlap the first ones by 20-30 %
    # only, so closures need 20 %. ICP from the chain cannot reach some pairs (overlap 8-9 %), FPFH + RANSAC can, and
    # its closure pulls the graph back; without the global stage the graph keeps the drift.
    seq = short_courtyard_route
    num_scans = seq.num_scans
    chain = seq.gt_poses.copy()
    chain[:, :3, 3] += np.linspace(0.0, 1.0, num_scans)[:, None] * np.array([2.0, 1.5, 0.0])
    settings = BaselineSettings(window=10, map_rounds=0, loop_drift_fraction=0.03, min_loop_fitness=0.2)
    clouds = prepare_clouds(seq.scans, settings)

    poses, loops = loop_closed_graph(clouds, chain, settings)
    drifted = ate(chain, seq.gt_poses)["translation_rmse_m"]
    assert drifted > 0.5 and loops.tried > 0 and loops.global_tried >= loops.global_kept >= 1
    assert ate(poses, seq.gt_poses)["translation_rmse_m"] < 0.2 * drifted

    poses, loops = loop_closed_graph(clouds, chain, dataclasses.replace(settings, global_loops_per_scan=0))
    assert loops.global_tried == loops.global_kept == 0
    assert ate(poses, seq.gt_poses)["translation_rmse_m"] > 0.5 * drifted


def test_a_loop_icp_moves_past_its_gate_closes_where_the_features_find_the_same_pose(short_courtyard_route):
    # A chain that drifted linearly to 0.6 m at the loop's end (0.6 % of the path, within the 1 % allowance): ICP from
    # it finds the first scans again with a good overlap but moves the last ones past max_loop_correction_m (0.2 m).
    # The global registration, from no guess, finds the same poses: those closures are kept and pull the graph back.
    # Where ICP had landed elsewhere (a slide: here ICP's poses moved by 0.5 m), the same closures are refused.
    from neld_jax.baseline import graph

    seq = short_courtyard_route
    chain = seq.gt_poses.copy()
    chain[:, :3, 3] += np.linspace(0.0, 1.0, seq.num_scans)[:, None] * np.array([0.48, 0.36, 0.0])
    settings = BaselineSettings(window=10, map_rounds=0, min_loop_fitness=0.2)
    clouds = prepare_clouds(seq.scans, settings)
    poses, loops = loop_closed_graph(clouds, chain, settings)
    drifted = ate(chain, seq.gt_poses)["translation_rmse_m"]
    assert drifted > 0.1 and loops.global_tried >= loops.global_kept >= 1, loops
    assert ate(poses, seq.gt_poses)["translation_rmse_m"] < 0.3 * drifted

    positions = chain[:, :3, 3]
    path_m = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    _, pairs = candidate_pairs(positions, settings.loop_radius_m, settings.max_loops_per_scan, settings.window)
    _, _, moved = graph._icp_closures(clouds, chain, pairs, path_m, settings)
    assert moved, "no ICP closure moved past the gate with a good overlap"
    agreed = graph._global_closures(clouds, chain, list(moved), path_m, settings, moved)
    slid = {pair: transform @ _shifted(0.5) for pair, transform in moved.items()}
    assert agreed and not graph._global_closures(clouds, chain, list(moved), path_m, settings, slid)


def _shifted(metres: float) -> np.ndarray:
    shift = np.eye(4)
    shift[0, 3] = metres
    return shift


def test_loop_closures_between_linked_recordings_pass_the_loop_gates(short_courtyard_route):
    # The route's second half a recording of its own, restarted 0.85 m off the first: the closures
    # where the route comes back to its start join the two recordings but lie beyond the loop gates; once the
    # placing's links (two relative poses at the join, 3 cm and 0.3 degree off, as a placing on local maps errs)
    # have brought the recordings together, they pass them, and the graph keeps the closures, not the links
    # (with the links kept too: 9 mm).
    seq = short_courtyard_route
    half = seq.num_scans // 2
    off = np.eye(4)
    off[:3, 3] = [0.6, 0.6, 0.0]
    chain = np.concatenate([seq.gt_poses[:half], off @ seq.gt_poses[half:]])
    settings = BaselineSettings(window=10, map_rounds=0, min_loop_fitness=0.2, global_loops_per_scan=0)
    clouds = prepare_clouds(seq.scans, settings)
    link_error = np.eye(4)
    link_error[:3, :3] = Rotation.from_euler("z", 0.3, degrees=True).as_matrix()
    link_error[:3, 3] = [0.018, -0.024, 0.0]
    links = tuple(
        (i, j, link_error @ np.linalg.inv(seq.gt_poses[j]) @ seq.gt_poses[i])
        for i, j in ((half, half - 1), (half + 1, half - 2))
    )
    _, unlinked = loop_closed_graph(clouds, chain, settings, segments=Segments((half,)))
    poses, linked = loop_closed_graph(clouds, chain, settings, segments=Segments((half,), links))
    assert unlinked.across_tried > 0 and unlinked.across_kept == 0
    assert linked.across_kept >= 1 and linked.linked == 2 and linked.links_in_final_graph == 0
    assert ate(poses, seq.gt_poses)["translation_rmse_m"] < 0.005


@pytest.mark.parametrize("num_targets, max_distance", [(2_000, 0.5), (2_000, 1.0), (20_000, 0.5)])
def test_target_index_finds_the_nearest_point_within_the_distance(num_targets, max_distance):
    # Each of the search kinds (radius search for small targets and short distances, nearest search otherwise)
    # against scipy's KD-tree: the same nearest point, -1 beyond the distance.
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    targets = rng.uniform(-5.0, 5.0, (num_targets, 3))
    queries = rng.uniform(-5.5, 5.5, (500, 3))
    index = TargetIndex(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(targets)), max_distance)
    for distance in (max_distance, 0.1):
        nearest, squared = index.nearest(queries, distance)
        expected_distance, expected = cKDTree(targets).query(queries, distance_upper_bound=distance)
        found = np.isfinite(expected_distance)
        np.testing.assert_array_equal(nearest >= 0, found)
        np.testing.assert_array_equal(nearest[found], expected[found])
        np.testing.assert_allclose(np.sqrt(squared[found]), expected_distance[found], atol=1e-9)


def test_a_large_scan_registers_a_subsample_at_all_but_the_finest_scale():
    # A raw 64-beam sweep (tens of thousands of points) registers every k-th point at the coarse scales, the finest
    # scale every point; a keyframe of a few thousand points registers as it is.
    from neld_jax.baseline.icp import COARSE_SOURCE_POINTS, coarse_source

    rng = np.random.default_rng(0)
    small = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-5, 5, (COARSE_SOURCE_POINTS, 3))))
    assert coarse_source(small) is small
    large = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-5, 5, (3 * COARSE_SOURCE_POINTS + 1, 3))))
    sub = coarse_source(large)
    assert len(sub.points) <= COARSE_SOURCE_POINTS and len(sub.points) > COARSE_SOURCE_POINTS // 2
    np.testing.assert_array_equal(np.asarray(sub.points), np.asarray(large.points)[::4])  # every 4th, in order
    # ... and the pose is found as with every point: a dense room (about 40,000 points) nudged by 0.3 m and 2 degrees
    floor = (_plane_points([-6, -4, 0], [1, 0, 0], [0, 1, 0], 12, 8, 0.05), [0, 0, 1])
    side = (_plane_points([-6, -4, 0], [1, 0, 0], [0, 0, 1], 12, 3, 0.1), [0, 1, 0])
    far = (_plane_points([-6, -4, 0], [0, 1, 0], [0, 0, 1], 8, 3, 0.1), [1, 0, 0])
    room = _cloud([floor, side, far])
    assert len(room.points) > 3 * COARSE_SOURCE_POINTS
    angle = np.radians(2.0)
    nudge = np.eye(4)
    nudge[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    nudge[:3, 3] = [0.3, -0.2, 0.1]
    transform, result = multiscale_icp(room, room, nudge, BaselineSettings())
    np.testing.assert_allclose(transform, np.eye(4), atol=1e-6)
    assert result.fitness == 1.0
