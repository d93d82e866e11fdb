"""benchmarks/train_step.py: the JSON line of a tiny run, the FLOP count, the matmul mode, the HLO categories.

No timing assertions: only that the benchmark runs, reports what it promises, and counts FLOPs right.
"""

import functools
import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from conftest import COARSE_REGISTRATION_GRID_M

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # as `python benchmarks/x.py` would: the scripts import harness
import harness  # noqa: E402

SCRIPT = ROOT / "benchmarks" / "train_step.py"

TINY = [
    "--steps",
    "2",
    "--repeats",
    "1",
    "--rays",
    "16",
    "--coarse",
    "4",
    "--fine",
    "2",
    "--width",
    "8",
    "--depth",
    "1",
    "--scans",
    "2",
    "--rays_per_scan",
    "64",
]
STEP_KEYS = {
    "steps_per_s",
    "rays_per_s",
    "samples_per_s",
    "compile_s",
    "mlp_flops_per_step",
    "achieved_gflops",
    "device",
    "jax_version",
    "config",
    "cpu_ms_per_step",
    "xla_flops_per_step",
    "profile",
}


def _load_benchmark_module():
    spec = importlib.util.spec_from_file_location("benchmark_train_step", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench = _load_benchmark_module()


def test_tiny_run_prints_one_json_line_with_the_promised_keys(tmp_path):
    hlo_file = tmp_path / "step.hlo"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    args = TINY + ["--profile_dir", str(tmp_path / "trace"), "--profile_steps", "1", "--dump_hlo", str(hlo_file)]
    result = subprocess.run(
        [sys.executable, str(SCRIPT), *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    assert len(lines) == 1, result.stdout
    record = json.loads(lines[0])
    assert STEP_KEYS <= set(record), STEP_KEYS - set(record)
    assert record["benchmark"] == "train_step" and record["preset"] == "none"
    assert record["steps_per_s"] > 0 and record["compile_s"] > 0
    assert record["config"]["rays"] == 16 and record["config"]["samples_per_ray"] == 6
    assert record["config"]["skip_layers"] == []  # the default skip layer 2 does not exist at depth 1
    # Analytic count: pos 3 * (1 + 2 * 10) = 63 -> 8; density head (8 + 3 * (1 + 2 * 2)) = 23 -> 4; 4 -> 1
    # (the view direction is a 3-D unit vector).
    per_point = 2 * (63 * 8 + 23 * 4 + 4 * 1)
    assert record["mlp_flops_per_point_forward"] == per_point
    assert record["mlp_flops_per_step"] == 3 * 16 * 6 * per_point
    assert record["samples_per_s"] == pytest.approx(record["steps_per_s"] * 16 * 6)
    assert "ENTRY" in hlo_file.read_text()
    assert record["profile"]["thread_ms_per_step"] > 0
    assert "matmul" in record["profile"]["by_category_ms"]


def test_preset_fills_the_flags_and_a_given_flag_wins():
    config, sizes = bench.preset_sizes("cpu")
    assert (sizes["rays"], sizes["coarse"], sizes["guided"], sizes["fine"]) == (512, 32, 16, 16)
    assert (sizes["width"], sizes["depth"], sizes["pos_freqs"]) == (128, 4, 10)
    _, paper = bench.preset_sizes("paper", stage=2)
    assert (paper["width"], paper["depth"], paper["coarse"], paper["fine"]) == (512, 8, 64, 32)
    gpu_config, gpu = bench.preset_sizes("gpu")
    assert gpu == sizes and gpu_config.train.steps == 30_000  # the gpu budget: the cpu recipe, run longer
    configured = bench.configure(config, dict(sizes, depth=2, coarse=8), train_steps=5)
    assert configured.model.skip_layers == ()  # layer 2 is dropped at depth 2
    assert configured.sampling.coarse_stages == (8,) and configured.train.steps == 5
    assert config.model.depth == 4, "configure must not change the preset's config"


def test_mlp_flops_per_point_counts_every_dense_kernel():
    params = {"a": {"kernel": jnp.zeros((63, 128)), "bias": jnp.zeros(128)}, "b": {"kernel": jnp.zeros((128, 1))}}
    assert bench.mlp_flops_per_point(params) == 2 * (63 * 128 + 128 * 1)


def test_matmul_peak_reports_positive_rates():
    record = bench.benchmark_matmul_peak({"rays": 4, "coarse": 2, "guided": 0, "fine": 2, "width": 16}, [32], 1)
    assert record["benchmark"] == "matmul_peak" and record["config"]["points"] == 16
    assert set(record["square_gflops"]) == {"32"} and set(record["mlp_shaped_gflops"]) == {"16x16x16"}
    assert record["gflops"] == max([*record["square_gflops"].values(), *record["mlp_shaped_gflops"].values()]) > 0


def test_hlo_categories_find_the_matmul_and_the_sine():
    def f(a, b):
        return jnp.sin(a @ b) * 2.0

    a = jnp.ones((128, 64))
    compiled = jax.jit(f).lower(a, jnp.ones((64, 64))).compile()
    ops = bench.hlo_instruction_ops(compiled.as_text())
    categories = {bench.op_category(o) for o in ops.values()}
    assert "matmul" in categories and "sin/cos (encoding)" in categories
    # A sine on a handful of elements (a BARF window) does not make its fusion a sin/cos op.
    assert bench.op_category({"sine-small", "multiply"}) == "elementwise/other"
    assert bench._num_elements("f32[24576,30]{1,0}") == 24576 * 30 and bench._num_elements("f32[]") == 1


def test_efficiency_mode_times_step_and_peak_alternately():
    config, sizes = bench.preset_sizes("cpu")
    sizes = dict(sizes, rays=16, coarse=4, guided=0, fine=2, width=8, depth=1)
    record = bench.benchmark_efficiency(
        config, sizes, steps=1, repeats=3, square_sizes=[32], num_scans=2, rays_per_scan=64
    )
    assert record["benchmark"] == "efficiency" and len(record["rounds"]) == 3
    for r in record["rounds"]:
        assert set(r["matmul_gflops"]) == {"32", "96x8x8"}
        assert r["peak_gflops"] == max(r["matmul_gflops"].values()) > 0
        assert r["efficiency"] == pytest.approx(r["achieved_gflops"] / r["peak_gflops"])
    assert record["efficiency"] == sorted(r["efficiency"] for r in record["rounds"])[1]  # the median
    assert record["mlp_flops_per_step"] == 3 * 16 * 6 * 2 * (63 * 8 + 23 * 4 + 4 * 1)


def test_step_runner_starts_from_the_trainers_state():
    """The benchmark builds its state and step with train.make_trainer and train.init_state over one cube, as a run
    does: the same initial params as fit starts from."""
    import functools

    from neld_jax.training import train

    config, sizes = bench.preset_sizes("cpu")
    sizes = dict(sizes, rays=16, coarse=4, guided=0, fine=2, width=8, depth=1)
    runner = bench.StepRunner(config, sizes, train_steps=3, num_scans=2, rays_per_scan=64, seed=3)
    assert runner.config.seed == 3
    assert runner.frames.weight.shape == (1,) and runner.rays.directions.shape == (1, 2 * 64, 3)
    fit_config = runner.config.copy_and_resolve_references()
    fit_config.train.steps = 0  # fit returns the state it starts from
    plan_of = functools.partial(bench.trainer_for, fit_config, runner.cube)
    start = train.init_state(fit_config, plan_of(0), 2, 1)
    data = train.TrainingData(runner.rays, runner.frames, bench.SYNTHETIC_SCALE)
    fitted = train.fit(fit_config, plan_of, data, start, settings=train.FitSettings(progress=False)).state
    for expected in (fitted.params, train.init_state(runner.config, runner.trainer, 2, 1).params):
        assert jax.tree.structure(runner.state.params) == jax.tree.structure(expected)
        for a, b in zip(jax.tree.leaves(runner.state.params), jax.tree.leaves(expected)):
            assert jnp.array_equal(a, b)
    assert runner.state.params["fields"]["hidden_0"]["kernel"].shape == (1, 63, 8)  # one cube, stacked
    assert runner.state.params["poses"].shape == (2, 6)
    runner.run(1)


def test_fit_mode_times_fit_and_the_bare_step_alternately():
    config, sizes = bench.preset_sizes("cpu")
    sizes = dict(sizes, rays=16, coarse=4, guided=0, fine=2, width=8, depth=1)
    record = bench.benchmark_fit(config, sizes, steps=2, repeats=1, log_every=2, num_scans=2, rays_per_scan=64)
    assert record["benchmark"] == "fit" and len(record["rounds"]) == 1
    r = record["rounds"][0]
    assert record["config"]["fit_steps"] == 4 and record["config"]["timed_steps"] == 2  # first chunk not timed
    assert r["ratio"] == pytest.approx(r["fit_steps_per_s"] / r["step_steps_per_s"]) and r["ratio"] > 0
    assert r["cpu_ratio"] == pytest.approx(r["step_cpu_ms_per_step"] / r["fit_cpu_ms_per_step"]) and r["cpu_ratio"] > 0
    assert math.isfinite(r["fit_final_loss"])


def test_viewer_mode_times_fit_with_and_without_the_live_hook(monkeypatch):
    from neld_jax.writing import viewer

    monkeypatch.setattr(viewer, "LIVE_PORT", viewer.LIVE_PORT)  # the benchmark picks a free port; restore it after
    config, sizes = bench.preset_sizes("cpu")
    sizes = dict(sizes, rays=16, coarse=4, guided=0, fine=2, width=8, depth=1)
    record = bench.benchmark_viewer(config, sizes, steps=2, repeats=1, log_every=1, num_scans=2, rays_per_scan=64)
    assert record["benchmark"] == "viewer" and len(record["rounds"]) == 1
    r = record["rounds"][0]
    assert r["slowdown"] == pytest.approx(r["plain_steps_per_s"] / r["live_steps_per_s"] - 1.0)
    assert record["viewer_seconds"] > 0  # the hook ran: 3 logs in the live fit


@functools.lru_cache(maxsize=None)
def _gpu_suite_module():
    """benchmarks/gpu_suite.py, loaded once (its absl flags can be defined only once in a process)."""
    sys.modules.setdefault("train_step", bench)  # the suite imports it by name; its flags are defined once
    spec = importlib.util.spec_from_file_location("gpu_suite", ROOT / "benchmarks" / "gpu_suite.py")
    suite = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(suite)
    return suite


def test_gpu_suite_extrapolates_the_schedule_stage_by_stage():
    suite = _gpu_suite_module()
    out = suite.extrapolate_schedule((0, 60_000, 120_000), 160_000, [300.0, 200.0, 100.0])
    assert out["stage_steps"] == [60_000, 60_000, 40_000]
    assert out["total_s"] == pytest.approx(200 + 300 + 400)
    assert out["mean_steps_per_s"] == pytest.approx(160_000 / 900)
    with pytest.raises(FileNotFoundError, match="--prepare"):
        suite.load_demo(str(ROOT / "no_such_demo.npz"))


def test_gpu_suite_loads_the_prepared_demo_as_one_cube(tmp_path):
    """A prepared demo (rays in metres, start and ground-truth poses, the cube's normalisation) becomes the plan of
    one cube the trainer takes; the ATE of zero corrections is the start's."""
    import numpy as np

    from neld_jax.judging import metrics
    from neld_jax.training.rays import sphere_scene_rays

    suite = _gpu_suite_module()
    rays, T = sphere_scene_rays(3, 32, seed=0)  # normalised: taken as metres at scale 0.5 about (1, 2, 3)
    offset = np.array([1.0, 2.0, 3.0])
    poses, gt = T.copy(), T.copy()
    poses[:, :3, 3] = T[:, :3, 3] / 0.5 + offset
    gt[:, :3, 3] = poses[:, :3, 3] + np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, -0.03, 0.01]])
    path = tmp_path / "demo.npz"
    np.savez(
        path,
        directions=rays.directions,
        ranges_m=rays.ranges / 0.5,
        scan_index=rays.scan_index,
        poses=poses,
        gt_poses=gt,
        scale=0.5,
        offset=offset,
    )
    demo = suite.load_demo(str(path))
    assert demo.num_scans == 3 and demo.plan.num_submaps == 1 and demo.scale == 0.5
    assert demo.rays.directions.shape == (1, 96, 3)
    np.testing.assert_allclose(np.asarray(demo.rays.ranges)[0], rays.ranges, rtol=1e-6)  # back in the cube's units
    np.testing.assert_allclose(np.asarray(demo.frames.T_init)[0, :, :3, 3], T[:, :3, 3], atol=1e-6)
    zero = suite.ate_m(np.zeros((3, 6)), demo.start_poses, demo.gt_poses, demo.scale)
    assert zero["ate_m"] == pytest.approx(metrics.ate(poses, gt)["translation_rmse_m"]) and zero["ate_m"] > 0
    config = suite.demo_config("cpu")
    trainer = suite.demo_trainer(config, demo, total_steps=7)
    assert trainer.schedules.total_steps == 7 and trainer.batch_rays == config.train.batch_rays


def _ate_change_module():
    spec = importlib.util.spec_from_file_location("benchmark_ate_change", ROOT / "benchmarks" / "ate_change.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ate_change_terms_split_a_moves_effect_on_the_ate():
    # benchmarks/ate_change.py: a move orthogonal to the baseline's error raises the ATE at second order only, one
    # against it lowers the ATE, and a rigid motion of the whole trajectory is no move at all.
    import numpy as np

    ate_change = _ate_change_module()
    rng = np.random.default_rng(0)
    n = 200
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    error = rng.normal(scale=0.03, size=(n, 3))
    error -= error.mean(0)  # no translation for the alignment to take out
    baseline = gt.copy()
    baseline[:, :3, 3] += error
    orthogonal = np.cross(error, rng.normal(size=(n, 3)))
    orthogonal *= 0.002 / np.sqrt(np.mean(np.sum(orthogonal**2, axis=1)))  # 2 mm rms, e_i . d_i = 0 for every pose
    moved = baseline.copy()
    moved[:, :3, 3] += orthogonal
    terms = ate_change.ate_change_terms(baseline, moved, gt)
    assert terms["change_mm"] > 0 and abs(terms["correlation"]) < 0.05
    assert terms["move_rms_mm"] == pytest.approx(2.0, rel=0.05)
    assert terms["change_mm"] == pytest.approx(terms["uncorrelated_change_mm"], rel=0.3)
    assert terms["change_mm"] <= terms["bound_change_mm"] + 1e-9
    toward = baseline.copy()
    toward[:, :3, 3] -= 0.5 * error  # halfway back to the ground truth
    terms = ate_change.ate_change_terms(baseline, toward, gt)
    assert terms["correlation"] < -0.99 and terms["change_mm"] < -0.4 * terms["ate_baseline_mm"]
    assert terms["correlation_rotation_p"] < 0.01
    rigid = np.eye(4)
    rigid[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    rigid[:3, 3] = [5.0, -2.0, 1.0]
    terms = ate_change.ate_change_terms(baseline, rigid @ baseline, gt)
    assert terms["move_rms_mm"] < 1e-6 and abs(terms["change_mm"]) < 1e-6


def test_ate_change_rotation_null_widens_the_chance_level_for_smooth_signals():
    # Smooth (random-walk) error and move drawn independently: their correlation is chance, and the random-rotation
    # null says so where 1 / sqrt(3 N) would not; a move back toward the input shows in toward_input_correlation.
    import numpy as np

    ate_change = _ate_change_module()
    rng = np.random.default_rng(1)
    n = 300

    def walk(scale):
        steps = np.cumsum(rng.normal(scale=scale, size=(n, 3)), axis=0)
        return steps - steps.mean(0)

    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    correlations, ps = [], []
    for _ in range(8):
        baseline = gt.copy()
        baseline[:, :3, 3] += walk(0.003)
        moved = baseline.copy()
        moved[:, :3, 3] += walk(0.0001)
        terms = ate_change.ate_change_terms(baseline, moved, gt)
        correlations.append(terms["correlation"])
        ps.append(terms["correlation_rotation_p"])
        assert terms["correlation_rotation_sd"] > 2.0 * terms["chance_correlation"]  # fewer independent values
    assert np.max(np.abs(correlations)) > 1.0 / np.sqrt(3 * n)  # the naive level would call some of them real
    assert np.median(ps) > 0.1
    initial = gt.copy()
    initial[:, :3, 3] += walk(0.02)  # the drifted start
    back = baseline.copy()
    back[:, :3, 3] += 0.02 * (initial[:, :3, 3] - baseline[:, :3, 3])  # a fiftieth of the way back to it
    terms = ate_change.ate_change_terms(baseline, back, gt, initial)
    assert terms["toward_input_correlation"] > 0.5 and terms["toward_input_rotation_p"] < 0.05
    assert "toward_input_correlation" not in ate_change.ate_change_terms(baseline, back, gt)


def _real_targets_module():
    spec = importlib.util.spec_from_file_location("benchmark_real_targets", ROOT / "benchmarks" / "real_targets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _margin(*per_draw):
    return {
        "per_draw": list(per_draw),
        "mean": sum(per_draw) / len(per_draw),
        "all_draws_agree": all(d < 0 for d in per_draw) or all(d > 0 for d in per_draw),
    }


def test_real_targets_read_the_targets_off_an_entry():
    # benchmarks/real_targets.py: each target of a real_data.py entry passes on good figures and fails when one
    # figure crosses its line; missing figures give None, not a verdict.
    targets = _real_targets_module()
    entry = {
        "sequence": "seq",
        "recorded": {
            "crisper": {
                "scans": 3,
                "pose_lines": 3,
                "wall_s": 550.0,
                "crispness": {
                    "initial": {"entropy": -3.40},
                    "baseline": {"entropy": -3.50},
                    "optimized": {"entropy": -3.51},
                },
                "crispness_margin": {"baseline": _margin(-0.002, -0.001, -0.003)},
            }
        },
        "drift": {
            "ate_vs_odometry_m": {"initial": 1.0, "baseline": 0.0365, "optimized": 0.0364},
            "optimized_apart_from_recorded_m": 0.0022,
            "crispness": {"initial": {"entropy": -2.2}, "optimized": {"entropy": -3.51}},
            "crispness_margin": {"baseline": _margin(-0.002, 0.001, -0.003)},
        },
    }
    got = targets.target_verdicts(entry, "crisper", minutes_limit=10)
    assert got == {
        "recorded": {
            "within_minutes": True,
            "every_scan_a_pose": True,
            "crisper_than_odometry": True,
            "crisper_than_baseline": "every draw",
        },
        "drift": {
            "within_2cm_of_recorded_answer": True,
            "as_crisp_as_odometry": True,
            "ate_at_or_below_baseline": True,
            "crisper_than_baseline": "a tie",
        },
    }
    entry["recorded"]["crisper"].update(
        wall_s=601.0, pose_lines=2, crispness_margin={"baseline": _margin(0.001, 0.002, 0.001)}
    )
    entry["recorded"]["crisper"]["crispness"]["optimized"]["entropy"] = -3.40  # equal is not crisper
    entry["drift"].update(
        optimized_apart_from_recorded_m=0.021,
        ate_vs_odometry_m={"initial": 1.0, "baseline": 0.0365, "optimized": 0.0366},
    )
    entry["drift"]["crispness"]["optimized"]["entropy"] = -3.39  # blurrier than the recorded odometry's -3.40
    entry["drift"]["ate_change_vs_odometry"] = {"ate_baseline_mm": 36.44, "ate_optimized_mm": 36.45}
    entry["drift"]["ate_vs_odometry_m"]["optimized"] = 0.0364  # rounded: the split's own figures decide
    got = targets.target_verdicts(entry, "crisper", minutes_limit=10)
    assert got["recorded"] == {
        "within_minutes": False,
        "every_scan_a_pose": False,
        "crisper_than_odometry": False,
        "crisper_than_baseline": "blurrier",
    }
    assert got["drift"]["within_2cm_of_recorded_answer"] is False
    assert got["drift"]["as_crisp_as_odometry"] is False
    assert got["drift"]["ate_at_or_below_baseline"] is False
    del entry["drift"]["optimized_apart_from_recorded_m"], entry["drift"]["crispness_margin"]
    got = targets.target_verdicts(entry, "crisper")
    assert got["drift"]["within_2cm_of_recorded_answer"] is None and got["drift"]["crisper_than_baseline"] is None
    assert targets.target_verdicts(entry, "input").keys() == {"drift"}  # no recorded run from that start
    entry["drift"]["every_scan_map"] = {"margin": {"initial": _margin(-0.3, -0.2), "baseline": _margin(0.01, -0.01)}}
    got = targets.target_verdicts(entry, "crisper")
    assert got["drift"]["every_scan_map_crisper_than_odometry"] == "every draw"
    assert got["drift"]["every_scan_map_crisper_than_baseline"] == "a tie"
    entry["targets"] = got
    table = targets.format_targets([entry, {"sequence": "big", "error": "DataError: too wide"}])
    assert "seq (recorded): within_minutes NO, every_scan_a_pose NO" in table
    assert "big: failed: DataError: too wide" in table.splitlines()[-1]


def _peer_entry(**neld):
    """An entry of benchmarks/peers.py with every method's figures; neld overrides NeLD-BA's row."""
    rows = {
        m: {
            "ate_m": ate,
            "path_ratio": ratio,
            "wall_s": 10.0,
            "neld_ba_verdict": "every draw",
            "every_sweep_map": {"neld_ba_verdict": "a tie"},
        }
        for m, ate, ratio in (
            ("kiss_icp", 0.20, 0.9950),
            ("kiss_slam", 0.25, 0.9940),
            ("odometry", 0.10, 0.9953),
            ("baseline", 0.08, 0.9951),
            ("neld_ba", 0.06, 0.9945),
        )
    }
    rows["neld_ba"].update({"wall_s": 500.0, **neld})
    return {"sequence": "kitti00", "methods": rows}


def test_peer_targets_read_neld_ba_against_its_start_and_its_peers():
    # NeLD-BA's ATE over each other method's, and its path length over its odometry's (the ratio of their path ratios)
    # within 0.1 %: 0.9945 / 0.9953 is 0.08 % short; 0.9935 / 0.9953, 0.18 % short, misses it
    targets = _real_targets_module()
    got = targets.peer_target_verdicts(_peer_entry(), minutes_limit=10)
    assert got["ate_over_kiss_icp"] == 0.3 and got["ate_over_baseline"] == 0.75 and got["ate_over_odometry"] == 0.6
    assert got["path_scale_vs_odometry"] == pytest.approx(0.9945 / 0.9953, abs=1e-6)
    assert got["path_scale_within_0.1pct"] is True and got["ate_below_kiss_icp"] and got["ate_below_kiss_slam"]
    assert got["crisper_than_kiss_icp"] == "every draw" and got["every_sweep_map_crisper_than_kiss_slam"] == "a tie"
    assert got["within_minutes"] is True
    got = targets.peer_target_verdicts(_peer_entry(path_ratio=0.9935, ate_m=0.3, wall_s=601.0))
    assert got["path_scale_within_0.1pct"] is False and got["ate_below_kiss_icp"] is False
    assert got["ate_over_baseline"] == 3.75 and got["within_minutes"] is False
    got = targets.peer_target_verdicts(_peer_entry(path_ratio=None, ate_m=None))  # no ground truth
    assert got["path_scale_vs_odometry"] is None and got["path_scale_within_0.1pct"] is None
    assert got["ate_over_baseline"] is None and got["ate_below_kiss_icp"] is None
    assert "kitti00 (peers): ate_below_kiss_icp None" in targets.format_targets(
        [{**_peer_entry(), "targets": {"peers": got}}]
    )


def test_peers_compares_the_methods_on_the_same_sweeps(tmp_path):
    # benchmarks/peers.py on 30 raw 10 Hz sweeps with a tiny model: a row per method (KISS-ICP and KISS-SLAM as their
    # own pipelines run them, the run's own odometry, the baseline, NeLD-BA) with its ATE, crispness and wall
    # time, NeLD-BA's margin to each peer, and the targets. KISS-SLAM is an optional extra (neld-jax[peers]): where it
    # is missing its row says so and the others still compare.
    out = tmp_path / "peers.json"
    tiny = [
        "data.keyframe_interval_s=0.5",
        "data.max_rays_per_scan=256",
        "train.steps=2",
        "train.batch_rays=32",
        "model.width=16",
        "model.depth=2",
        "model.skip_layers=(1,)",
        "mapping.enabled=False",
        "viz.record=False",
        "eval.crispness_queries=2000",
        "eval.crispness_draws=3",
        f"baseline.voxel_size_m={COARSE_REGISTRATION_GRID_M}",
    ]
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "peers.py"),
            "--sequences=synthetic10hz:0",
            "--num_scans=30",
            "--gt_map_points=2000",
            f"--work={tmp_path / 'work'}",
            f"--out={out}",
            "--eval_from_scan=5",
            "--segments_m=1,2",
            *[f"--set={s}" for s in tiny],
        ],
        cwd=ROOT,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    record = json.loads(out.read_text())  # the benchmarks' schema (benchmarks/harness.py) around the payload
    assert set(record) == set(harness.SCHEMA_KEYS) and record["benchmark"] == "peers"
    assert record["command"].startswith("python benchmarks/peers.py --sequences=synthetic10hz:0 --num_scans=30")
    assert record["machine"]["cores"] >= 1 and record["machine"]["date_utc"].endswith("UTC")
    (entry,) = harness.load(str(out))["sequences"]
    assert "error" not in entry, entry.get("error")
    assert entry["input_scans"] == 30 and entry["keyframes"] == 6
    rows = entry["methods"]
    assert set(rows) == {"kiss_icp", "kiss_slam", "odometry", "baseline", "neld_ba"}
    slam_installed = importlib.util.find_spec("kiss_slam") is not None
    measured = ["kiss_icp", "odometry", "baseline", "neld_ba"] + (["kiss_slam"] if slam_installed else [])
    if not slam_installed:
        assert rows["kiss_slam"]["status"] == "not installed (pip install neld-jax[peers])"
    for name in measured:
        row = rows[name]
        assert row["ate_poses"] == 25 and 0 <= row["ate_m"] < 1.0 and row["ate_rot_deg"] >= 0, (name, row)
        # Sim(3) fits at least as well as SE(3); a path length and KITTI's relative error over 1 and 2 m segments
        assert row["ate_sim3_m"] <= row["ate_m"] + 1e-4 and 0.5 < row["sim3_scale"] < 2.0, (name, row)
        assert 0.5 < row["path_ratio"] < 2.0 and row["kitti_segments"] > 0, (name, row)
        assert row["kitti_t_pct"] >= 0 and row["kitti_r_deg_per_m"] >= 0, (name, row)
        assert math.isfinite(row["entropy"]) and row["thickness_cm"] > 0 and row["wall_s"] >= 0, (name, row)
        every = row["every_sweep_map"]  # every sweep's points, not only the keyframes'
        assert math.isfinite(every["entropy"]) and every["thickness_cm"] > 0, (name, every)
        if name != "neld_ba":
            for verdict in (row, every):
                assert len(verdict["neld_ba_margin_per_draw"]) == 3
                assert verdict["neld_ba_verdict"] in ("every draw", "a tie", "blurrier")
    assert rows["neld_ba"]["wall_s"] >= rows["odometry"]["wall_s"]  # the whole run holds its odometry
    assert rows["kiss_icp"]["poses"] != rows["odometry"]["poses"]  # KISS-ICP alone, not the run's two passes
    # KISS-ICP and KISS-SLAM with KISS-ICP's own defaults (--peer_range=own), not the run's 40 m
    assert entry["peer_range"] == {"mode": "own", "min_range_m": 0.0, "max_range_m": 100.0, "voxel_m": 1.0}
    assert entry["eval_from_scan"] == 5 and entry["gt_path_m"] > 2.0
    peers = entry["targets"]["peers"]
    for method in ("kiss_icp", "baseline", "odometry"):
        assert peers[f"ate_over_{method}"] == pytest.approx(rows["neld_ba"]["ate_m"] / rows[method]["ate_m"], rel=1e-3)
    assert peers["path_scale_vs_odometry"] == pytest.approx(
        rows["neld_ba"]["path_ratio"] / rows["odometry"]["path_ratio"], abs=1e-6
    )
    assert set(peers) == {
        "ate_below_kiss_icp",
        "ate_below_kiss_slam",
        "ate_over_kiss_icp",
        "ate_over_baseline",
        "ate_over_odometry",
        "path_scale_vs_odometry",
        "path_scale_within_0.1pct",
        "crisper_than_kiss_icp",
        "crisper_than_kiss_slam",
        "every_sweep_map_crisper_than_kiss_icp",
        "every_sweep_map_crisper_than_kiss_slam",
        "within_minutes",
    }
    assert entry["targets"]["peers"]["within_minutes"] is True
    assert "kiss_icp" in result.stdout and "targets" in result.stdout and "iteration=" not in result.stdout
    assert "Sim3 m" in result.stdout and "KITTI %" in result.stdout and "NeLD-BA's ATE over: kiss_icp" in result.stdout
