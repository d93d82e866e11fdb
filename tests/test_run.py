"""A whole run on a tiny synthetic sequence: outputs, kill-and-resume, command-line errors."""

import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from neld_jax import baseline, checkpoint, quality, run
from neld_jax.data.normalize import fit_normalization
from neld_jax.data.poses import read_kitti, read_tum
from neld_jax.errors import ConfigError, DataError

from conftest import make_tiny_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class _Killed(Exception):
    pass


def _run_killed_after_its_first_checkpoint(config, monkeypatch) -> None:
    """run.run(config), killed (an exception) right after it wrote its first checkpoint."""
    real_save = checkpoint.Checkpointer.save

    def save_then_die(self, state, metadata):
        real_save(self, state, metadata)
        raise _Killed()

    monkeypatch.setattr(checkpoint.Checkpointer, "save", save_then_die)
    with pytest.raises(_Killed):
        run.run(config, progress=False)
    monkeypatch.setattr(checkpoint.Checkpointer, "save", real_save)


def _free_gauge(config):
    config.train.fixed_scans = ()
    config.train.anchor_scan = 0
    return config


def test_run_writes_outputs_and_resumes_after_a_kill(tmp_path, monkeypatch):
    # Reference: an uninterrupted run.
    ref_cfg = _free_gauge(make_tiny_config(str(tmp_path / "ref"), steps=12))
    ref = run.run(ref_cfg, progress=False)
    assert ref["steps"] == 12

    out = tmp_path / "run"
    for name in ("poses_initial.txt", "poses_initial.kitti", "poses_optimized.txt", "poses_optimized.kitti",
                 "map_raw.ply", "map_rendered.ply", "metrics.json", "config.json"):
        assert (tmp_path / "ref" / name).is_file(), name
    t_opt, T_opt = read_tum(tmp_path / "ref" / "poses_optimized.txt")
    np.testing.assert_allclose(read_kitti(tmp_path / "ref" / "poses_optimized.kitti")[:, :3], T_opt[:, :3], atol=1e-6)
    # Every pose was free (the field holds the frame); the output is anchored so scan 0 keeps its initial pose.
    _, T_initial = read_tum(tmp_path / "ref" / "poses_initial.txt")
    np.testing.assert_allclose(T_opt[0], T_initial[0], atol=1e-6)
    assert np.abs(T_opt[1:] - T_initial[1:]).max() > 1e-6
    metrics = json.loads((tmp_path / "ref" / "metrics.json").read_text())
    assert metrics["run"]["steps"] == 12
    assert metrics["run"]["map_rays_rendered"] == metrics["run"]["map_rays"] > 0  # no time limit: every ray

    # A run killed right after its first checkpoint (step 5) ...
    _run_killed_after_its_first_checkpoint(_free_gauge(make_tiny_config(str(out), steps=12)), monkeypatch)
    assert checkpoint.Checkpointer(str(out / "checkpoints")).latest_step() == 5

    # ... and rerun with the same output_dir resumes there and ends at the same final step and poses.
    resumed = run.run(_free_gauge(make_tiny_config(str(out), steps=12)), progress=False)
    assert resumed["steps"] == 12
    _, T_resumed = read_tum(out / "poses_optimized.txt")
    np.testing.assert_allclose(T_resumed, T_opt, atol=1e-6)
    # The history and the training time continue across the resume instead of restarting.
    history = json.loads((out / "history.json").read_text())
    ref_history = json.loads((tmp_path / "ref" / "history.json").read_text())
    assert [h["step"] for h in history] == [h["step"] for h in ref_history] == list(range(1, 13))
    np.testing.assert_allclose([h["loss"] for h in history], [h["loss"] for h in ref_history], rtol=1e-5)
    elapsed = [h["elapsed_s"] for h in history]
    assert np.all(np.diff(elapsed) > 0), elapsed
    assert resumed["train_seconds"] >= round(elapsed[-1], 2) - 0.01

    # Data that changed under the same configuration (here: every initial pose shifted by 1 m, which moves the
    # normalisation; then one scan fewer) must not resume silently in another frame.
    real_load = run.load_and_prepare

    def load_changed(config, shift=1.0, drop=0):
        _, seq, _ = real_load(config)
        keep = slice(0, seq.num_scans - drop)
        poses = seq.poses[keep].copy()
        poses[:, 0, 3] += shift
        seq = dataclasses.replace(seq, scans=seq.scans[keep], poses=poses, timestamps=None, gt_poses=None,
                                  source_index=None)
        return seq, seq, fit_normalization(seq.scans, seq.poses, margin=config.data.normalization_margin)

    monkeypatch.setattr(run, "load_and_prepare", load_changed)
    with pytest.raises(DataError, match=r"checkpoints was written for other data \(normalisation scale"):
        run.run(_free_gauge(make_tiny_config(str(out), steps=12)), progress=False)
    monkeypatch.setattr(run, "load_and_prepare", lambda config: load_changed(config, shift=0.0, drop=1))
    with pytest.raises(DataError, match=r"checkpoints was written for other data \(4 scans, now 3"):
        run.run(_free_gauge(make_tiny_config(str(out), steps=12)), progress=False)


def _train_cli(*args):
    return subprocess.run([sys.executable, os.path.join(REPO, "bin", "train.py"), *args],
                          capture_output=True, text=True, cwd=REPO, timeout=300)


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--config=configs/generic.py", "--config.data.root=/nonexistent/dir"], "/nonexistent/dir"),
        (["--config=configs/demo.py", "--config.train.no_such_field=3"], "no_such_field"),
        (["--config=configs/demo.py:tpu"], "unknown budget"),
    ],
)
def test_cli_bad_input_is_one_clear_line(args, expected, tmp_path):
    proc = _train_cli(*args, f"--config.output_dir={tmp_path}")
    assert proc.returncode != 0
    err = proc.stderr.strip().splitlines()
    assert "Traceback" not in proc.stderr, proc.stderr
    assert expected in err[-1], proc.stderr
    assert err[-1].startswith("error:"), proc.stderr


def test_cli_data_with_errors_is_one_clear_line(tmp_path):
    """A generic-layout folder with 2 scans but 3 poses: the error names both counts, no traceback."""
    from neld_jax.data.poses import write_tum
    from neld_jax.data.scans import write_scan

    root = tmp_path / "seq"
    rng = np.random.default_rng(0)
    for i in range(2):
        write_scan(root / "scans" / f"{i:06d}.pcd", rng.uniform(-5, 5, (100, 3)))
    write_tum(root / "poses.txt", np.arange(3.0), np.tile(np.eye(4), (3, 1, 1)))
    proc = _train_cli("--config=configs/generic.py:cpu", f"--config.data.root={root}",
                      f"--config.output_dir={tmp_path / 'out'}")
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error:") and "2" in last and "3" in last, proc.stderr


def _tiny_config_from_the_baseline(output_dir: str, steps: int):
    """A tiny run that starts from the classical baseline's poses (train.init_poses=baseline), no rendered map."""
    config = make_tiny_config(output_dir, steps=steps)
    config.train.init_poses = "baseline"
    config.baseline.window, config.baseline.voxel_size_m = 2, 0.2
    synthetic = config.data.synthetic  # dense enough scans for ICP, and a drift for it to undo
    synthetic.num_beams, synthetic.num_columns, synthetic.drift_trans_m, synthetic.drift_rot_deg = 32, 512, 0.15, 1.0
    config.mapping.enabled = False
    return config


def test_run_from_the_baseline_fits_the_cube_to_its_poses(tmp_path, monkeypatch):
    # train.init_poses=baseline: the baseline's poses are written for every input scan, its map's crispness is
    # reported, and the normalisation cube is fitted to the poses training starts from (from a drifted start the
    # baseline moves scans by metres), not to the input's.
    fitted = []
    real_fit = run.fit_normalization

    def spy(scans, poses, margin):
        fitted.append(np.array(poses))
        return real_fit(scans, poses, margin=margin)

    monkeypatch.setattr(run, "fit_normalization", spy)
    spent = []  # what the run passes to the training guard: the baseline's seconds count
    real_training_seconds = run.training_seconds
    monkeypatch.setattr(run, "training_seconds", lambda c, s: spent.append(s) or real_training_seconds(c, s))
    # The run hands the baseline its deadline: one already past when the run starts stops the refinement rounds
    # before their first registration. It would give the chain up too (test_baseline); the chain here is let run,
    # so that the baseline moves the scans.
    monkeypatch.setattr(run, "baseline_deadline", lambda c, t_start: t_start - 1.0)
    chain_deadlines = []
    real_chain = baseline.scan_to_map_chain

    def chain_without_deadline(clouds, init_poses, settings, deadline=None, progress=False):
        chain_deadlines.append(deadline)
        return real_chain(clouds, init_poses, settings, progress=progress)

    monkeypatch.setattr(baseline, "scan_to_map_chain", chain_without_deadline)
    verdicts = []  # the margins the run's crispest verdict is given, and the verdict
    real_verdict = quality.warn_if_not_crispest

    def verdict_spy(summaries, refused=None, margins=None):
        verdicts.append((margins, real_verdict(summaries, refused, margins)))
        return verdicts[-1][1]

    monkeypatch.setattr(quality, "warn_if_not_crispest", verdict_spy)
    config = _tiny_config_from_the_baseline(str(tmp_path / "run"), steps=4)
    summary = run.run(config, progress=False)
    assert summary["started_from"] == "baseline" and summary["baseline_seconds"] > 0
    assert len(chain_deadlines) == 1 and chain_deadlines[0] < time.perf_counter()
    assert config.baseline.map_rounds > 0 and summary["baseline_rounds_done"] == 0
    assert spent[0] >= summary["baseline_seconds"]
    assert {"initial", "baseline", "optimized"} <= set(summary["crispness"])
    assert set(summary["crispness_margin"]) == {"initial", "baseline"}
    assert verdicts == [(summary["crispness_margin"], summary["crispest"])]  # judged over the query draws
    _, T_baseline = read_tum(tmp_path / "run" / "poses_baseline.txt")
    _, T_initial = read_tum(tmp_path / "run" / "poses_initial.txt")
    assert len(T_baseline) == len(T_initial) == 4
    assert np.abs(T_baseline[1:, :3, 3] - T_initial[1:, :3, 3]).max() > 1e-3  # the baseline did move the scans
    np.testing.assert_allclose(fitted[-1], T_baseline, atol=1e-5)
    # From the baseline's poses the pose steps are capped and the pose prior set, and config.json holds the
    # config as trained.
    trained = json.loads((tmp_path / "run" / "config.json").read_text())["train"]
    assert trained["pose_lr_trans_init"] == trained["pose_lr_rot_init"] == config.train.pose_lr_from_baseline[0]
    # The tiny synthetic map is thinner than train.pose_prior_thin_map_m: the translations' prior is heavier, the
    # rotations' stays pose_prior_from_baseline.
    assert trained["pose_prior_weight"] > config.train.pose_prior_from_baseline > config.train.pose_prior_weight
    assert trained["pose_prior_weight"] * trained["pose_prior_rot_factor"] == pytest.approx(
        config.train.pose_prior_from_baseline)
    assert trained["keep_start_scale"] and not config.train.keep_start_scale  # the baseline's scale kept
    assert config.train.pose_lr_trans_init > trained["pose_lr_trans_init"]  # the caller's config is not changed


def test_a_resumed_run_starts_from_the_baseline_poses_its_first_run_chose(tmp_path, monkeypatch):
    # The baseline's rounds stop at a wall-clock deadline, so a resume must not run it again: the checkpoint's pose
    # corrections are relative to the first run's start (start_poses.npz).
    import neld_jax.baseline

    _run_killed_after_its_first_checkpoint(_tiny_config_from_the_baseline(str(tmp_path / "run"), 12), monkeypatch)
    with np.load(tmp_path / "run" / run.START_FILE) as start_file:
        saved = dict(start_file)
    first_start = saved["poses"]

    def no_second_baseline(*args, **kwargs):
        raise AssertionError("the baseline ran again on resume")

    monkeypatch.setattr(neld_jax.baseline, "register_sequence", no_second_baseline)
    resumed = run.run(_tiny_config_from_the_baseline(str(tmp_path / "run"), 12), progress=False)
    assert resumed["steps"] == 12 and resumed["started_from"] == "baseline"
    _, T_baseline = read_tum(tmp_path / "run" / "poses_baseline.txt")
    np.testing.assert_allclose(T_baseline, first_start, atol=1e-6)
    # Another input (or another configuration) is not that run's: its start is chosen again.
    moved = np.array(saved["input_poses"])
    moved[:, 0, 3] += 0.01
    assert run.resumed_start(str(tmp_path / "run"), resumed["config_hash"], moved) is None
    assert run.resumed_start(str(tmp_path / "run"), "another hash", saved["input_poses"]) is None
    assert run.resumed_start(str(tmp_path / "run"), resumed["config_hash"], saved["input_poses"]) is not None


def test_training_time_counts_from_the_run_start_with_a_floor():
    config = make_tiny_config("unused", steps=4)
    config.train.max_minutes = 8.0
    assert run.training_seconds(config, 0.0) == 480.0
    assert run.training_seconds(config, 200.0) == 280.0  # the baseline's 200 s count
    assert run.training_seconds(config, 400.0) == 120.0  # but training gets at least a quarter
    config.train.max_minutes = 0.0
    assert run.training_seconds(config, 400.0) == 0.0  # no limit


def test_the_baseline_refines_until_only_trainings_floor_is_left():
    config = make_tiny_config("unused", steps=4)
    config.train.max_minutes = 8.0
    assert run.baseline_deadline(config, 100.0) == 100.0 + 360.0  # 8 minutes less training's quarter
    assert run.training_seconds(config, 360.0) == 120.0  # a baseline stopped there leaves training its floor
    config.train.max_minutes = 0.0
    assert run.baseline_deadline(config, 100.0) is None  # no limit


def test_rendering_time_gives_back_what_the_run_overran_with_a_floor():
    config = make_tiny_config("unused", steps=4)
    config.train.max_minutes, config.mapping.max_seconds = 8.0, 60.0
    assert run.rendering_seconds(config, 470.0) == 60.0  # training ended on time: the whole limit
    assert run.rendering_seconds(config, 500.0) == 40.0  # 20 s past the 8 minutes (training's floor)
    assert run.rendering_seconds(config, 560.0) == 15.0  # but the map gets at least a quarter
    config.mapping.max_seconds = 0.0
    assert run.rendering_seconds(config, 560.0) == 0.0  # no limit stays none
    config.train.max_minutes, config.mapping.max_seconds = 0.0, 60.0
    assert run.rendering_seconds(config, 560.0) == 60.0  # no run clock: the map's own limit


def test_the_run_renders_its_map_within_the_time_rendering_seconds_gives(tmp_path, monkeypatch):
    # The run asks rendering_seconds for the map's limit at the time the map starts, and the render keeps to it:
    # a limit that has already passed renders the first piece of the rays alone (a uniform sample, metrics.json).
    asked = []
    monkeypatch.setattr(run, "rendering_seconds", lambda config, elapsed_s: asked.append(elapsed_s) or 1e-9)
    config = make_tiny_config(str(tmp_path / "run"), steps=4)
    summary = run.run(config, progress=False)
    assert len(asked) == 1 and asked[0] > 0
    assert 0 < summary["map_rays_rendered"] <= config.mapping.rays_per_batch < summary["map_rays"]


def test_trajectory_departure_ignores_a_rigid_motion_and_sees_a_bend():
    from scipy.spatial.transform import Rotation

    angle = np.linspace(0.0, np.pi / 2, 21)
    poses = np.tile(np.eye(4), (21, 1, 1))
    poses[:, :3, 3] = np.stack([20 * np.cos(angle), 20 * np.sin(angle), 0.1 * angle], axis=1)  # a 31 m arc
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = Rotation.from_euler("zx", (30, 5), degrees=True).as_matrix(), (5.0, -2.0, 1.0)
    departure, path = run.trajectory_departure(poses, moved @ poses)
    assert departure < 1e-9 and path == pytest.approx(10 * np.pi, rel=1e-2)
    bent = poses.copy()
    bent[:, 2, 3] += 0.03 * np.arange(21.0) ** 2  # rising 12 m by the end, 0.8 m of it left after alignment
    departure, _ = run.trajectory_departure(poses, bent)
    assert 0.5 < departure < 12.0
    # departure_check: bent beyond the share of the path allowed; max_baseline_departure=0 switches the check off
    config = make_tiny_config("unused")
    config.train.max_baseline_departure, config.train.baseline_departure_floor_m = 0.01, 0.1
    is_bent, _, _, allowed_m = run.departure_check(config, poses, bent)
    assert is_bent and allowed_m > 0.1
    config.train.max_baseline_departure = 0.0
    is_bent, checked_m, _, allowed_m = run.departure_check(config, poses, bent)
    assert not is_bent and checked_m == pytest.approx(departure) and allowed_m == np.inf


def test_pose_steps_are_capped_only_from_the_baseline():
    config = make_tiny_config("unused", steps=4)
    config.train.pose_lr_rot_init, config.train.pose_lr_trans_init = 1e-3, 1e-6  # one above the cap, one below
    config.train.pose_lr_rot_final = config.train.pose_lr_trans_final = 1e-5
    config.train.pose_lr_from_baseline = (5e-6, 2.5e-7)
    config.train.pose_prior_weight, config.train.pose_prior_from_baseline = 0.0, 300.0
    assert run.pose_steps_for_start(config, "input") is config  # from the odometry: no cap, prior or scale kept
    capped = run.pose_steps_for_start(config, "baseline")
    assert capped.train.keep_start_scale and not config.train.keep_start_scale
    assert capped.train.pose_lr_rot_init == 5e-6 and capped.train.pose_lr_trans_init == 1e-6  # min(rate, cap)
    assert capped.train.pose_lr_rot_final == capped.train.pose_lr_trans_final == 2.5e-7
    assert capped.train.pose_prior_weight == 300.0 and config.train.pose_prior_weight == 0.0
    assert capped.train.field_lr_init == config.train.field_lr_init and config.train.pose_lr_rot_init == 1e-3
    config.train.pose_prior_weight = 1000.0  # a stronger prior asked for is kept
    assert run.pose_steps_for_start(config, "baseline").train.pose_prior_weight == 1000.0
    config.train.pose_lr_from_baseline, config.train.pose_prior_from_baseline = (), 0.0
    config.train.keep_scale_from_baseline = False
    assert run.pose_steps_for_start(config, "baseline") is config
    config.train.pose_lr_from_baseline = (1e-6,)
    with pytest.raises(ConfigError, match="pose_lr_from_baseline"):
        run.pose_steps_for_start(config, "baseline")


def test_the_translations_prior_is_heavier_from_a_thin_map():
    config = make_tiny_config("unused", steps=4)
    config.train.pose_prior_weight, config.train.pose_prior_from_baseline = 0.0, 3000.0
    config.train.pose_prior_thin_map_m, config.train.pose_prior_rot_factor = 0.02, 0.5
    thin = run.pose_steps_for_start(config, "baseline", start_thickness_m=0.01)
    assert thin.train.pose_prior_weight == pytest.approx(4 * 3000.0)  # (2 cm / 1 cm)^2
    assert thin.train.pose_prior_weight * thin.train.pose_prior_rot_factor == pytest.approx(1500.0)  # rotations kept
    for thickness in (0.03, None):  # a real keyframe map, or none measured: the weight as set
        kept = run.pose_steps_for_start(config, "baseline", start_thickness_m=thickness)
        assert kept.train.pose_prior_weight == 3000.0 and kept.train.pose_prior_rot_factor == 0.5
    assert run.pose_steps_for_start(config, "input", start_thickness_m=0.01) is config  # from the odometry: no prior
    config.train.pose_prior_thin_map_m = 0.0  # off
    assert run.pose_steps_for_start(config, "baseline", start_thickness_m=0.01).train.pose_prior_weight == 3000.0
    config.train.pose_prior_thin_map_m, config.train.pose_prior_from_baseline = 0.02, 0.0  # no prior to scale
    assert run.pose_steps_for_start(config, "baseline", start_thickness_m=0.01).train.pose_prior_weight == 0.0


def test_the_margins_deadline_follows_the_runs_clock():
    from neld_jax.config import apply_budget, base_config

    config = apply_budget(base_config(), "cpu")
    limit = 60.0 * config.train.max_minutes + config.mapping.max_seconds + config.eval.crispness_draws_max_seconds
    assert run.margins_deadline(config, 100.0) == pytest.approx(100.0 + limit)
    config.eval.crispness_draws_max_seconds = 0.0
    assert run.margins_deadline(config, 100.0) is None
    config.eval.crispness_draws_max_seconds, config.train.max_minutes = 30.0, 0.0
    assert run.margins_deadline(config, 100.0) is None

