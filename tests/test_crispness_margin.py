"""benchmarks/crispness_margin.py on a run folder written by hand: a lio_keyframes sequence (tiny synthetic scans),
config.json, and KITTI poses where the start is the truth with drift and the answer is the truth."""

import json
import os
import subprocess
import sys

import numpy as np
from conftest import tiny_synthetic_sequence

from neld_jax.data.poses import write_kitti
from neld_jax.data.scans import write_scan
from neld_jax.lie import se3_exp_float64, se3_log_float64
from neld_jax.synthetic.pseudo_gt import with_drift

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _write_run(tmp_path, num_scans: int = 4):
    """The sequence in tmp_path/seq, a run folder tmp_path/run with its config.json; returns (sequence, run folder)."""
    from configs.lio_keyframes import get_config

    seq = tiny_synthetic_sequence(num_scans)
    root, run_dir = tmp_path / "seq", tmp_path / "run"
    (root / "Scans").mkdir(parents=True)
    run_dir.mkdir()
    for i, scan in enumerate(seq.scans):
        write_scan(root / "Scans" / f"{i:06d}.pcd", scan)
    write_kitti(root / "odom_poses.txt", seq.poses)
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in seq.timestamps))
    config = get_config("cpu")
    config.data.root = str(root)
    (run_dir / "config.json").write_text(config.to_json_best_effort())
    return seq, run_dir


def _margin(*args):
    return subprocess.run(
        [sys.executable, os.path.join(REPO, "benchmarks", "crispness_margin.py"), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_margin_pairs_the_maps_on_every_draw(tmp_path):
    seq, run_dir = _write_run(tmp_path)
    write_kitti(run_dir / "poses_initial.kitti", with_drift(seq, 0.05, 0.5, seed=0).poses)
    write_kitti(run_dir / "poses_optimized.kitti", seq.poses)
    out = tmp_path / "margin.json"
    result = _margin(f"--run_dir={run_dir}", "--draws=3", "--queries=300", f"--out={out}")
    assert result.returncode == 0, result.stderr[-2000:]
    margin = json.loads(out.read_text())["results"]  # the payload of the benchmarks' schema (benchmarks/harness.py)
    assert margin["draws"] == 3 and margin["queries"] == 300 and set(margin["optimized_minus"]) == {"initial"}
    versus = margin["optimized_minus"]["initial"]
    # the truth's map is crisper than the drifted one's on every draw, and the three draws differ
    assert all(d < 0 for d in versus["per_draw"]) and versus["all_draws_agree"]
    assert len(set(versus["per_draw"])) == 3
    assert "against the initial poses'" in result.stdout and "crisper on every one of 3 draws" in result.stdout


def test_margin_names_a_folder_without_an_answer(tmp_path):
    _, run_dir = _write_run(tmp_path, num_scans=3)
    result = _margin(f"--run_dir={run_dir}")
    assert result.returncode != 0 and "no poses_optimized.kitti" in result.stderr


def test_mean_of_seeds_judges_the_mean_correction(tmp_path):
    """Two "seeds" that land on either side of the truth (the truth's correction from the drifted start, plus and
    minus 2 cm / 0.3 deg of noise) are judged, with --mean_of, as the truth itself: the same margin on every draw
    as a run whose answer is the truth."""
    seq, run_dir = _write_run(tmp_path)
    start = with_drift(seq, 0.05, 0.5, seed=0).poses
    truth_xi = se3_log_float64(np.linalg.inv(start) @ seq.poses)
    noise = np.random.default_rng(0).normal(0, 1, truth_xi.shape) * np.r_[0.02, 0.02, 0.02, 0.005, 0.005, 0.005]
    other = tmp_path / "other_seed"
    other.mkdir()
    for folder, answer in ((run_dir, truth_xi + noise), (other, truth_xi - noise)):
        write_kitti(folder / "poses_initial.kitti", start)
        write_kitti(folder / "poses_optimized.kitti", start @ se3_exp_float64(answer))
    truth_dir = tmp_path / "truth"
    truth_dir.mkdir()
    (truth_dir / "config.json").write_text((run_dir / "config.json").read_text())
    write_kitti(truth_dir / "poses_initial.kitti", start)
    write_kitti(truth_dir / "poses_optimized.kitti", seq.poses)
    margins = []
    for args in ([f"--run_dir={run_dir}", f"--mean_of={other}"], [f"--run_dir={truth_dir}"]):
        out = tmp_path / f"margin{len(margins)}.json"
        result = _margin(*args, "--draws=2", "--queries=300", f"--out={out}")
        assert result.returncode == 0, result.stderr[-2000:]
        margins.append(json.loads(out.read_text())["results"])
    assert margins[0]["mean_of"] == [str(other)]
    np.testing.assert_allclose(
        margins[0]["optimized_minus"]["initial"]["per_draw"],
        margins[1]["optimized_minus"]["initial"]["per_draw"],
        atol=1e-6,
    )
    assert all(d < 0 for d in margins[0]["optimized_minus"]["initial"]["per_draw"])


def test_mean_of_refuses_a_run_from_another_start(tmp_path):
    """Corrections from two different starts have no common origin: a --mean_of run whose poses_initial.kitti
    differ from this run's is refused with one line naming it, as is one that wrote none."""
    seq, run_dir = _write_run(tmp_path, num_scans=3)
    write_kitti(run_dir / "poses_initial.kitti", with_drift(seq, 0.05, 0.5, seed=0).poses)
    write_kitti(run_dir / "poses_optimized.kitti", seq.poses)
    elsewhere, no_start = tmp_path / "elsewhere", tmp_path / "no_start"
    for folder in (elsewhere, no_start):
        folder.mkdir()
        write_kitti(folder / "poses_optimized.kitti", seq.poses)
    write_kitti(elsewhere / "poses_initial.kitti", with_drift(seq, 0.05, 0.5, seed=1).poses)
    for other, message in ((elsewhere, "differ from"), (no_start, "no poses_initial.kitti")):
        result = _margin(f"--run_dir={run_dir}", f"--mean_of={other}", "--draws=1", "--queries=100")
        assert result.returncode != 0
        last_line = result.stderr.strip().splitlines()[-1]
        assert last_line.startswith(str(other)) and message in last_line, result.stderr[-1000:]
