"""benchmarks/real_gpu.py: prepare a finished run's sequence here, train it where open3d is missing, judge it here.

A tiny lio_keyframes sequence (synthetic scans written as PCD files) and a run folder written by hand stand for a
finished run; training runs in a subprocess whose imports of open3d fail, as on the GPU image."""

import json
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
from conftest import tiny_synthetic_sequence

from neld_jax.data.poses import read_kitti, write_kitti
from neld_jax.data.scans import write_scan
from neld_jax.synthetic.pseudo_gt import with_drift

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(REPO, "benchmarks", "real_gpu.py")
SIZES = [
    "--budget=cpu",
    "--set=train.steps=4",
    "--set=train.log_every=2",
    "--set=model.width=16",
    "--set=model.depth=2",
    "--set=model.skip_layers=()",
    "--set=train.batch_rays=32",
    "--set=data.max_rays_per_scan=64",
    "--set=eval.crispness_queries=300",
    "--set=eval.crispness_draws=2",
    "--set=start.poses='input'",
]
# Run a script with every import of open3d failing, as on a GPU image that lacks it.
WITHOUT_OPEN3D = """
import runpy, sys
class NoOpen3d:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'open3d':
            raise ImportError('no open3d here')
sys.meta_path.insert(0, NoOpen3d())
sys.argv = sys.argv[1:]
sys.path.insert(0, __import__('os').path.dirname(sys.argv[0]))  # as `python benchmarks/real_gpu.py` would
runpy.run_path(sys.argv[0], run_name='__main__')
"""


def _real_gpu(*args, without_open3d: bool = False):
    command = [sys.executable, "-c", WITHOUT_OPEN3D, SCRIPT] if without_open3d else [sys.executable, SCRIPT]
    return subprocess.run([*command, *args], capture_output=True, text=True, timeout=600, cwd=REPO)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """(sequence, run folder): 5 scans with drifted odometry, config.json naming them, the run's own answer."""
    from configs.lio_keyframes import get_config

    tmp = tmp_path_factory.mktemp("real_gpu")
    seq = tiny_synthetic_sequence(5)
    root, run_dir = tmp / "seq", tmp / "run"
    (root / "Scans").mkdir(parents=True)
    run_dir.mkdir()
    for i, scan in enumerate(seq.scans):
        write_scan(root / "Scans" / f"{i:06d}.pcd", scan)
    write_kitti(root / "odom_poses.txt", with_drift(seq, 0.05, 0.5, seed=0).poses)
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in seq.timestamps))
    config = get_config("cpu")
    config.data.root = str(root)
    (run_dir / "config.json").write_text(config.to_json_best_effort())
    write_kitti(run_dir / "poses_optimized.kitti", seq.poses)
    return seq, run_dir


def test_points_travel_within_a_twentieth_of_a_millimetre():
    sys.path.insert(0, os.path.join(REPO, "benchmarks"))
    import packed_points

    points = np.random.default_rng(0).uniform(-40.0, 40.0, (500, 3))
    packed = packed_points.pack_points(points)
    assert len(packed) < points.astype(np.float32).nbytes  # smaller than float32 even on random points
    assert np.abs(packed_points.unpack_points(packed) - points).max() <= 0.5 * packed_points.POINT_UNIT_M + 1e-12


def test_prepare_train_without_open3d_and_evaluate(finished_run, tmp_path):
    seq, run_dir = finished_run
    data, out, judged = tmp_path / "data", tmp_path / "out", tmp_path / "judged"
    out.mkdir()
    prepared = _real_gpu("--prepare", f"--run_dir={run_dir}", "--name=tiny", f"--data={data}", *SIZES)
    assert prepared.returncode == 0, prepared.stderr[-3000:]
    summary = json.loads(prepared.stdout.strip().splitlines()[-1])
    assert summary["keyframes"] == 5 and summary["start"] == "input" and summary["rays"] == 5 * 64

    # The prepared points are the rays a run draws (the same seeded subset), to the packing's rounding.
    from configs.lio_keyframes import get_config
    from neld_jax.config import apply_overrides
    from neld_jax.field.normalize import Normalization
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.training.rays import build_rays

    config = get_config("cpu")
    config.data.root = json.loads((run_dir / "config.json").read_text())["data"]["root"]
    config = apply_overrides(config, [s[len("--set=") :] for s in SIZES if s.startswith("--set=")])
    _, keyframes = load_keyframes(config.data)
    with open(data / "tiny.pkl", "rb") as f:
        d = pickle.load(f)
    sys.path.insert(0, os.path.join(REPO, "benchmarks"))
    import packed_points

    expected = build_rays(keyframes, Normalization(1.0), max_rays_per_scan=64, seed=config.seed)
    points = packed_points.unpack_points(d["points"])
    np.testing.assert_allclose(points, expected.directions * expected.ranges[:, None], atol=1e-4)
    assert d["counts"].tolist() == [64] * 5 and d["chosen"] == "input"

    trained = _real_gpu(f"--data={data}", f"--out_dir={out}", "--max_train_s=300", without_open3d=True)
    assert trained.returncode == 0, trained.stderr[-3000:]
    figures = json.loads((out / "real_gpu.json").read_text())
    assert [f["name"] for f in figures] == ["tiny"] and "error" not in figures[0], figures
    assert figures[0]["steps"] == figures[0]["schedule_steps"] == 4
    assert figures[0]["defaults_added"] == []
    # --set in training makes a variant of the prepared config, also of a field the code gained after the file
    # was prepared (the field gets its default first)
    older = tmp_path / "older"
    older.mkdir()
    del d["config"]["viz"]["record"]
    with open(older / "tiny.pkl", "wb") as f:
        pickle.dump(d, f)
    overrides = ["train.steps=2", "viz.record=False"]
    variant = _real_gpu(
        f"--data={older}",
        f"--out_dir={tmp_path / 'variant'}",
        "--max_train_s=300",
        *[f"--set={o}" for o in overrides],
        without_open3d=True,
    )
    assert variant.returncode == 0, variant.stderr[-3000:]
    varied = json.loads((tmp_path / "variant" / "real_gpu.json").read_text())[0]
    assert "error" not in varied, varied
    assert varied["steps"] == varied["schedule_steps"] == 2 and varied["overrides"] == overrides
    assert varied["defaults_added"] == ["viz.record"]

    judged_run = _real_gpu(
        "--evaluate", f"--run_dir={run_dir}", f"--trained={out / 'tiny_trained.npz'}", f"--out_dir={judged}", *SIZES
    )
    assert judged_run.returncode == 0, judged_run.stderr[-3000:]
    evaluation = json.loads((judged / "evaluation.json").read_text())
    assert evaluation["poses_optimized_lines"] == evaluation["num_input_scans"] == 5
    assert len(read_kitti(judged / "poses_optimized.kitti")) == 5
    # the run's own answer (the truth here) is crisper than the drifted odometry, on both draws
    versus = evaluation["optimized_minus"]
    assert set(versus) == {"initial", "run_optimized"} and len(versus["initial"]["per_draw"]) == 2
    truth_minus_drift = (
        evaluation["crispness"]["run_optimized"]["mean_map_entropy"]
        - evaluation["crispness"]["initial"]["mean_map_entropy"]
    )
    assert truth_minus_drift < 0


def test_prepare_names_a_run_of_another_sequence(finished_run, tmp_path):
    seq, run_dir = finished_run
    other = tmp_path / "other_run"
    other.mkdir()
    (other / "config.json").write_text((run_dir / "config.json").read_text())
    from neld_jax.steps.start import Start
    from neld_jax.training.train import PoseSteps

    Start(
        seq.poses[:3], "baseline", PoseSteps(), baseline_poses=seq.poses[:3], baseline_seconds=1.0, departure_m=0.0
    ).save(str(other), "0" * 12, seq.poses[:3])
    result = _real_gpu("--prepare", f"--run_dir={other}", f"--data={tmp_path}", *SIZES)
    assert result.returncode != 0 and "not this sequence's keyframes" in result.stderr
