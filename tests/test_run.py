"""A whole run on a tiny synthetic sequence (neld_jax.run): outputs, kill-and-resume, command-line errors, a start
from the classical baseline and its resume, the map's time limit."""

import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import free_gauge_config, make_tiny_config

from neld_jax import baseline, run
from neld_jax.data.poses import read_kitti, read_tum
from neld_jax.errors import ConfigError, DataError
from neld_jax.judging import judge
from neld_jax.steps import start
from neld_jax.training import budget, checkpoint, submaps
from neld_jax.writing import output_folder

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


def test_run_writes_outputs_and_resumes_after_a_kill(free_gauge_run, tmp_path, monkeypatch):
    # Reference: an uninterrupted run (conftest.free_gauge_run, 12 steps, every pose free).
    ref_dir = free_gauge_run
    metrics = json.loads((ref_dir / "metrics.json").read_text())
    assert metrics["run"]["steps"] == 12 and metrics["run"]["started_from"] == "input"

    out = tmp_path / "run"
    for name in (
        "poses_initial.txt",
        "poses_initial.kitti",
        "poses_optimized.txt",
        "poses_optimized.kitti",
        "map_raw.ply",
        "map_rendered.ply",
        "metrics.json",
        "config.json",
    ):
        assert (ref_dir / name).is_file(), name
    t_opt, T_opt = read_tum(ref_dir / "poses_optimized.txt")
    np.testing.assert_allclose(read_kitti(ref_dir / "poses_optimized.kitti")[:, :3], T_opt[:, :3], atol=1e-6)
    # Every pose was free (the field holds the frame); the output is anchored so scan 0 keeps its initial pose.
    _, T_initial = read_tum(ref_dir / "poses_initial.txt")
    np.testing.assert_allclose(T_opt[0], T_initial[0], atol=1e-6)
    assert np.abs(T_opt[1:] - T_initial[1:]).max() > 1e-6
    assert metrics["run"]["map_rays_rendered"] == metrics["run"]["map_rays"] > 0  # no time limit: every ray

    # A run killed right after its first checkpoint (step 5), its loading slowed by 2 s ...
    real_load = run.load_sessions
    monkeypatch.setattr(
        run, "load_sessions", lambda data_cfg, budget_s=0.0: time.sleep(2.0) or real_load(data_cfg, budget_s)
    )
    _run_killed_after_its_first_checkpoint(free_gauge_config(str(out)), monkeypatch)
    monkeypatch.setattr(run, "load_sessions", real_load)
    assert checkpoint.Checkpointer(str(out / "checkpoints")).latest_step() == 5
    assert output_folder.earlier_seconds(str(out)) >= 2.0

    # ... and rerun with the same output_dir resumes there and ends at the same final step and the same poses, bit
    # for bit: the key travels in the checkpointed state and the chunks are cut at the same steps.
    t0 = time.perf_counter()
    resumed = run.run(free_gauge_config(str(out)), progress=False)["run"]
    this_process_s = time.perf_counter() - t0
    assert resumed["steps"] == 12
    for name in ("poses_optimized.txt", "poses_optimized.kitti"):
        assert (out / name).read_bytes() == (ref_dir / name).read_bytes(), name
    # The history and the training time continue across the resume instead of restarting.
    history = json.loads((out / "history.json").read_text())
    ref_history = json.loads((ref_dir / "history.json").read_text())
    assert [h["step"] for h in history] == [h["step"] for h in ref_history] == list(range(1, 13))
    np.testing.assert_allclose([h["loss"] for h in history], [h["loss"] for h in ref_history], rtol=1e-5)
    elapsed = [h["elapsed_s"] for h in history]
    assert np.all(np.diff(elapsed) > 0), elapsed
    assert resumed["train_seconds"] >= round(elapsed[-1], 2) - 0.01
    # The run's whole time counts the killed process's seconds too (up to its checkpoint), not the last one's alone.
    assert resumed["total_seconds"] >= this_process_s + 1.5 and resumed["total_seconds"] >= resumed["train_seconds"]
    # Each step's seconds in this process, in the plan's stage names and order; together at most the process's own.
    stages = resumed["stage_seconds"]
    assert list(stages) == ["load", "baseline", "training", "map", "registration", "judging"]
    assert all(s >= 0 for s in stages.values()) and sum(stages.values()) <= this_process_s
    assert stages["training"] <= resumed["train_seconds"] + 1.0 and stages["training"] > 0

    # Data that changed under the same configuration (here: every initial pose shifted by 1 m, which moves the
    # cube; then one scan fewer) must not resume silently in another frame.
    def load_changed(data_cfg, budget_s=0.0, shift=1.0, drop=0):
        _, seq, _ = real_load(data_cfg)
        keep = slice(0, seq.num_scans - drop)
        poses = seq.poses[keep].copy()
        poses[:, 0, 3] += shift
        seq = dataclasses.replace(
            seq, scans=seq.scans[keep], poses=poses, timestamps=None, gt_poses=None, source_index=None
        )
        return seq, seq, None

    monkeypatch.setattr(run, "load_sessions", load_changed)
    with pytest.raises(DataError, match=r"checkpoints was written for other data \(another plan of cubes"):
        run.run(free_gauge_config(str(out)), progress=False)
    monkeypatch.setattr(run, "load_sessions", lambda data_cfg, budget_s=0.0: load_changed(data_cfg, shift=0.0, drop=1))
    with pytest.raises(DataError, match=r"checkpoints was written for other data \(4 keyframes, now 3"):
        run.run(free_gauge_config(str(out)), progress=False)
    # config.json holds the settings as given, once: the resumed run wrote the same
    assert json.loads((out / "config.json").read_text()) == json.loads((ref_dir / "config.json").read_text()) | {
        "output_dir": str(out)
    }


def _train_cli(*args):
    return subprocess.run(
        [sys.executable, os.path.join(REPO, "bin", "train.py"), *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )


def test_cli_unknown_budget_is_one_clear_line(tmp_path):
    # A missing data folder and an unknown field: tests/test_commands.py
    proc = _train_cli("--config=configs/demo.py:tpu", f"--config.output_dir={tmp_path}")
    assert proc.returncode != 0
    err = proc.stderr.strip().splitlines()
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "unknown budget" in err[-1], proc.stderr
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
    proc = _train_cli(
        "--config=configs/generic.py:cpu", f"--config.data.root={root}", f"--config.output_dir={tmp_path / 'out'}"
    )
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error:") and "2" in last and "3" in last, proc.stderr


def _tiny_config_from_the_baseline(output_dir: str, steps: int):
    """A tiny run that starts from the classical baseline's poses (start.poses=baseline), no rendered map."""
    config = make_tiny_config(output_dir, steps=steps)
    config.start.poses = "baseline"
    config.baseline.window, config.baseline.voxel_size_m = 2, 0.2
    synthetic = config.data.synthetic  # dense enough scans for ICP, and a drift for it to undo
    synthetic.num_beams, synthetic.num_columns, synthetic.drift_trans_m, synthetic.drift_rot_deg = 32, 512, 0.15, 1.0
    config.mapping.enabled = False
    return config


def test_run_from_the_baseline_fits_the_cube_to_its_poses(tmp_path, monkeypatch):
    # start.poses=baseline: the baseline's poses are written for every input scan, its map's crispness is reported,
    # the cube is fitted to the poses training starts from (from a drifted start the baseline moves scans by metres),
    # and the pose steps from there are recorded (config.json stays the user's).
    planned = []
    real_plan = submaps.plan_from_config
    monkeypatch.setattr(
        run.refine.submaps,
        "plan_from_config",
        lambda seq, config, num_devices=1: planned.append(np.array(seq.poses)) or real_plan(seq, config, num_devices),
    )
    # The run hands the baseline its deadline: one already past stops the refinement rounds before their first
    # registration. It would give the chains up too (test_baseline); the chains here run, so the scans move.
    monkeypatch.setattr(budget.TimeBudget, "baseline_deadline", lambda self: self.started - 1.0)
    chain_deadlines = []
    real_chain = baseline.scan_to_map_chain

    def chain_without_deadline(
        clouds, init_poses, settings, keep_input_tilt=False, deadline=None, progress=False, segments=baseline.Segments()
    ):
        chain_deadlines.append(deadline)
        return real_chain(clouds, init_poses, settings, keep_input_tilt, None, progress, segments)

    monkeypatch.setattr(baseline.pipeline, "scan_to_map_chain", chain_without_deadline)
    verdicts = []  # the margins the run's crispest verdict is given, and the verdict
    real_verdict = judge.warn_if_not_crispest

    def verdict_spy(summaries, margins=None):
        verdicts.append((margins, real_verdict(summaries, margins)))
        return verdicts[-1][1]

    monkeypatch.setattr(judge, "warn_if_not_crispest", verdict_spy)
    config = _tiny_config_from_the_baseline(str(tmp_path / "run"), steps=4)
    summary = run.run(config, progress=False)
    r = summary["run"]
    assert r["started_from"] == "baseline" and r["baseline_seconds"] > 0 and r["baseline_tilt"] in ("input", "free")
    assert len(chain_deadlines) == 2 and all(d < time.perf_counter() for d in chain_deadlines)  # two chains: tilt
    assert config.baseline.map_rounds > 0 and r["baseline_rounds_done"] == 0
    assert {"initial", "baseline", "optimized"} <= set(summary["crispness"])
    # four steps of a tiny field may blur the baseline's map: the baseline's poses are then the answer (test_answer)
    kept_start = {"neld_ba"} if r["answer"] == "baseline" else set()
    assert r["answer"] in ("neld_ba", "baseline") and set(r["crispness_margin"]) == {"initial", "baseline"} | kept_start
    assert verdicts == [(r["crispness_margin"], r["crispest"])]  # judged over the query draws
    _, T_baseline = read_tum(tmp_path / "run" / "poses_baseline.txt")
    _, T_initial = read_tum(tmp_path / "run" / "poses_initial.txt")
    assert len(T_baseline) == len(T_initial) == 4
    assert np.abs(T_baseline[1:, :3, 3] - T_initial[1:, :3, 3]).max() > 1e-3  # the baseline did move the scans
    np.testing.assert_allclose(planned[-1], T_baseline, atol=1e-5)
    # From the baseline's poses the pose steps are capped, a prior set (heavier on the translations: the tiny
    # synthetic map is thinner than start.THIN_MAP_M) and the scale kept; the config is the user's.
    steps = r["pose_steps"]
    assert tuple(steps["lr_trans"]) == tuple(steps["lr_rot"]) == tuple(config.start.pose_lr_from_baseline)
    assert steps["prior_trans"] > steps["prior_rot"] == config.start.prior_from_baseline and steps["keep_scale"]
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["train"]["pose_lr_trans_init"] == config.train.pose_lr_trans_init > steps["lr_trans"][0]


def test_a_resumed_run_starts_from_the_baseline_poses_its_first_run_chose(tmp_path, monkeypatch):
    # The baseline's rounds stop at a wall-clock deadline, so a resume must not run it again: the checkpoint's pose
    # corrections are relative to the first run's start (start_poses.npz).
    _run_killed_after_its_first_checkpoint(_tiny_config_from_the_baseline(str(tmp_path / "run"), 12), monkeypatch)
    with np.load(tmp_path / "run" / start.FILE) as start_file:
        saved = dict(start_file)
    first_start = saved["poses"]

    def no_second_baseline(*args, **kwargs):
        raise AssertionError("the baseline ran again on resume")

    monkeypatch.setattr(start, "register_sequence", no_second_baseline)
    resumed = run.run(_tiny_config_from_the_baseline(str(tmp_path / "run"), 12), progress=False)["run"]
    assert resumed["steps"] == 12 and resumed["started_from"] == "baseline"
    _, T_baseline = read_tum(tmp_path / "run" / "poses_baseline.txt")
    np.testing.assert_allclose(T_baseline, first_start, atol=1e-6)
    # Another input (or another configuration) is not that run's: an error before anything runs, not a second
    # baseline overwriting the saved start.
    moved = np.array(saved["input_poses"])
    moved[:, 0, 3] += 0.01
    with pytest.raises(DataError, match="start_poses.npz was saved for other input poses"):
        start.Start.resumed(str(tmp_path / "run"), resumed["config_hash"], moved)
    with pytest.raises(ConfigError, match="start_poses.npz was saved under another configuration"):
        start.Start.resumed(str(tmp_path / "run"), "another hash", saved["input_poses"])
    again = start.Start.resumed(str(tmp_path / "run"), resumed["config_hash"], saved["input_poses"])
    assert again is not None and again.pose_steps.keep_scale and again.chosen == "baseline"


def test_the_run_renders_its_map_within_the_time_its_budget_gives(tmp_path, monkeypatch):
    # The run asks the budget for the map's limit when the map starts, and the render keeps to it: a limit that has
    # already passed renders the first piece of the rays alone (a uniform sample, metrics.json).
    from neld_jax.steps import mapping

    asked = []
    monkeypatch.setattr(budget.TimeBudget, "render_seconds", lambda self: asked.append(self.elapsed()) or 1e-9)
    monkeypatch.setattr(mapping, "RAYS_PER_BATCH", 64)  # the tiny map's rays make several batches
    config = make_tiny_config(str(tmp_path / "run"), steps=4)
    config.submaps.enabled = "off"
    summary = run.run(config, progress=False)["run"]
    assert len(asked) == 1 and asked[0] > 0
    assert summary["map_rays_rendered"] == 64 < summary["map_rays"]


def test_run_reads_as_its_named_steps():
    # run.run_steps is the pipeline: load, choose the start, train, render, register every scan, judge and keep the
    # better answer, write, each a call into its module.
    import ast
    import inspect

    from test_code_shape import statement_count

    tree = ast.parse(inspect.getsource(run.run_steps))
    calls = [
        ast.unparse(node.func)
        for node in sorted(
            (n for n in ast.walk(tree) if isinstance(n, ast.Call)), key=lambda n: (n.lineno, n.col_offset)
        )
    ]
    order = [
        "load_sessions",
        "start.choose_start",
        "refine.refine_keyframes",
        "mapping.rendered_map",
        "registration.register_every_scan",
        "answer.keep_travel_of_input",
        "answer.keep_the_better",
        "outputs.judge_crispness",
        "outputs.write_outputs",
        "outputs.judge_run",
    ]
    positions = [calls.index(name) for name in order]
    assert positions == sorted(positions), calls
    assert statement_count(tree.body[0]) < 30  # read top to bottom: one call a step


def test_no_step_takes_the_whole_config():
    # A step receives the groups it reads (config.data, ...) or a settings dataclass built from them at the edge: a
    # parameter named config in neld_jax.steps is the whole config coming back. The settings' from_config builders
    # are that edge (run.py, commands/ call them).
    import importlib
    import inspect
    import pkgutil

    import neld_jax.steps

    taking = []
    for info in pkgutil.iter_modules(neld_jax.steps.__path__):
        module = importlib.import_module(f"neld_jax.steps.{info.name}")
        for name, value in vars(module).items():
            if getattr(value, "__module__", None) != module.__name__ or name.startswith("_"):
                continue
            members = [(name, value)] if inspect.isfunction(value) else []
            if inspect.isclass(value):
                members = [
                    (f"{name}.{key}", getattr(value, key))
                    for key in vars(value)
                    if not key.startswith("_") and key != "from_config" and callable(getattr(value, key))
                ]
            taking += [
                f"{module.__name__}.{qualified}"
                for qualified, function in members
                if "config" in inspect.signature(function).parameters
            ]
    assert not taking, f"steps that take the whole config: {taking}"


def _folder_state(folder) -> dict:
    """{relative path: (bytes, mtime in ns)} of every file under folder."""
    return {
        str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _quick_config(output_dir: str, steps: int = 4):
    """A tiny run of one sample-count stage (one compile) without a rendered map."""
    config = make_tiny_config(output_dir, steps=steps)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.mapping.enabled = False
    return config


def test_a_rerun_resumes_its_own_configuration_refuses_another_and_restarts_when_asked(tmp_path, caplog):
    out = tmp_path / "run"
    first = run.run(_quick_config(str(out)), progress=False)
    # metrics.json is the run's alone: a rerun rewrites it whole, inheriting no section of an earlier one.
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"run", "scans_report", "crispness", "evaluation"} == set(first)
    (out / "metrics.json").write_text(
        json.dumps({**metrics, "baseline": {"seconds": 1.0}, "crispness": {**metrics["crispness"], "stale": {}}})
    )
    config_bytes = (out / "config.json").read_bytes()
    again = run.run(_quick_config(str(out)), progress=False)  # the same configuration: it resumes (at its end)
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == set(again) == set(first) and "stale" not in metrics["crispness"]
    assert metrics["run"]["steps"] == 4 and (out / "config.json").read_bytes() == config_bytes
    assert again["run"]["total_seconds"] > first["run"]["total_seconds"]  # the first process's seconds and its own

    # Another configuration: one ConfigError naming each field that differs, old -> new, before anything is written.
    before = _folder_state(out)
    changed = _quick_config(str(out), steps=6)
    changed.seed = 3
    changed.viz.record = False  # where the run writes and how it is watched is not compared
    with pytest.raises(ConfigError) as refused:
        run.run(changed, progress=False)
    line = str(refused.value)
    assert "\n" not in line and str(out / "config.json") in line and "new output_dir" in line and "--restart" in line
    assert "seed: 0 -> 3" in line and "train.steps: 4 -> 6" in line and "viz" not in line
    assert _folder_state(out) == before

    # neld-train: the same refusal is one line on stderr, and the folder is still as it was.
    proc = _train_cli("--config=configs/demo.py", f"--config.output_dir={out}")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: {out / 'config.json'} holds another configuration")
    assert _folder_state(out) == before

    # --restart: the earlier run's files go (the log names them; other files stay), and the run starts over.
    (out / "notes.txt").write_text("mine")
    with caplog.at_level("WARNING", logger="neld_jax.writing.output_folder"):
        restarted = run.run(changed, progress=False, restart=True)["run"]
    assert "--restart: deleting" in caplog.text and "checkpoints/" in caplog.text and "metrics.json" in caplog.text
    assert output_folder.CLOCK_FILE in caplog.text  # the run starts its clock over too
    assert "notes.txt" not in caplog.text and (out / "notes.txt").read_text() == "mine"
    assert restarted["steps"] == 6 and not (out / "run.rrd").exists()
    assert json.loads((out / "config.json").read_text())["seed"] == 3


def test_config_differences_name_dotted_fields_old_and_new():
    saved = {
        "seed": 0,
        "output_dir": "/a",
        "viz": {"record": True},
        "train": {"steps": 4, "fixed_scans": [0]},
        "data": {"root": "/x"},
    }
    now = {
        "seed": 0,
        "output_dir": "/b",
        "viz": {"record": False},
        "train": {"steps": 8, "fixed_scans": []},
        "data": {"root": "/x", "added": 1.5},
    }
    assert output_folder.config_differences(saved, now) == [
        "data.added: (absent) -> 1.5",
        "train.fixed_scans: [0] -> []",
        "train.steps: 4 -> 8",
    ]
    assert output_folder.config_differences(saved, saved) == []
    many = output_folder.refusal("/r/config.json", [f"f{i}: 0 -> 1" for i in range(9)])
    assert "f5: 0 -> 1" in many and "f6" not in many and "and 3 more" in many
