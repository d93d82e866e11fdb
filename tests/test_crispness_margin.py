"""benchmarks/crispness_margin.py on a run folder written by hand: a lio_keyframes sequence (tiny synthetic scans),
config.json, and KITTI poses where the start is the truth with drift and the answer is the truth."""

import json
import os
import subprocess
import sys

from conftest import tiny_synthetic_sequence
from neld_jax.data.poses import write_kitti
from neld_jax.data.pseudo_gt import with_drift
from neld_jax.data.scans import write_scan

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
    return subprocess.run([sys.executable, os.path.join(REPO, "benchmarks", "crispness_margin.py"), *args],
                          capture_output=True, text=True, timeout=300)


def test_margin_pairs_the_maps_on_every_draw(tmp_path):
    seq, run_dir = _write_run(tmp_path)
    write_kitti(run_dir / "poses_initial.kitti", with_drift(seq, 0.05, 0.5, seed=0).poses)
    write_kitti(run_dir / "poses_optimized.kitti", seq.poses)
    out = tmp_path / "margin.json"
    result = _margin(f"--run_dir={run_dir}", "--draws=3", "--queries=300", f"--out={out}")
    assert result.returncode == 0, result.stderr[-2000:]
    margin = json.loads(out.read_text())
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
