"""Real recordings: the lio_keyframes layout (Scans/ + KITTI poses + times.txt), keyframe rules, every input scan
in the outputs, the per-scan report, pseudo ground truth, and a scene too large for one field."""

import json
import os
import subprocess
import sys

import ml_collections
import numpy as np
import pytest
from conftest import tiny_synthetic_sequence
from scipy.spatial.transform import Rotation

from neld_jax.data.layout import LoadOptions
from neld_jax.data.lio_keyframes import load_lio_keyframes
from neld_jax.data.poses import read_tum, write_kitti
from neld_jax.data.preprocess import select_keyframes
from neld_jax.data.scans import write_scan
from neld_jax.data.timing import read_times
from neld_jax.errors import DataError
from neld_jax.judging import report
from neld_jax.steps.inputs import load_sequence
from neld_jax.synthetic.pseudo_gt import with_drift

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _write_layout(root, seq, times=None, num_poses=None):
    (root / "Scans").mkdir(parents=True)
    for i, scan in enumerate(seq.scans):
        write_scan(root / "Scans" / f"{i:06d}.pcd", scan)
    write_kitti(root / "odom_poses.txt", seq.poses[: num_poses or seq.num_scans])
    times = seq.timestamps if times is None else times
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))


def test_lio_keyframes_layout_reads_scans_poses_and_stamps(tmp_path):
    seq = tiny_synthetic_sequence()
    _write_layout(tmp_path, seq, times=1.6e9 + np.array([0.1, 7.4, 7.8, 9.0]))
    loaded = load_lio_keyframes(tmp_path)
    assert loaded.num_scans == 4 and loaded.files == [f"Scans/{i:06d}.pcd" for i in range(4)]
    np.testing.assert_allclose(loaded.poses, seq.poses, atol=1e-6)
    np.testing.assert_allclose(loaded.timestamps, 1.6e9 + np.array([0.1, 7.4, 7.8, 9.0]))
    assert loaded.gt_poses is None
    via_config = load_sequence(
        ml_collections.ConfigDict(
            {"format": "lio_keyframes", "root": str(tmp_path), "initial_poses": "", "drop_unmatched_tail": False}
        )
    )
    np.testing.assert_allclose(via_config.poses, loaded.poses)


def test_lio_keyframes_count_mismatch_names_the_short_side(tmp_path):
    seq = tiny_synthetic_sequence()
    _write_layout(tmp_path, seq, num_poses=3)  # as new_Riverside02_bag_331: 332 scans and stamps, 331 poses
    with pytest.raises(DataError, match=r"odom_poses.txt has 3.*odom_poses.txt is short by 1.*drop_unmatched_tail"):
        load_lio_keyframes(tmp_path)
    dropped = load_lio_keyframes(tmp_path, LoadOptions(drop_unmatched_tail=True))
    assert dropped.num_scans == 3 and dropped.files[-1] == "Scans/000002.pcd" and len(dropped.timestamps) == 3
    with pytest.raises(DataError, match="optimized_poses.txt: pose file does not exist .found: odom_poses.txt"):
        load_lio_keyframes(tmp_path, pose_file="optimized_poses.txt")


def test_times_file_errors_name_the_line(tmp_path):
    path = tmp_path / "times.txt"
    path.write_text("1.0\n2.0\nabc\n")
    with pytest.raises(DataError, match=r"times.txt, line 3: not a timestamp"):
        read_times(path)
    path.write_text("1.0\n# comment\n2.0\n2.0\n")
    with pytest.raises(DataError, match=r"times.txt, lines 3 and 4: timestamps do not increase"):
        read_times(path)


def test_spatial_keyframes_and_any_rule():
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, 0, 3] = [0.0, 0.4, 0.9, 1.0, 1.0, 1.0]
    poses[4:, :3, :3] = Rotation.from_euler("z", [[20.0], [50.0]], degrees=True).as_matrix()
    # Caps on the gap between neighbouring keyframes: each keyframe is the last scan within them of the one before.
    np.testing.assert_array_equal(select_keyframes(None, 0.0, poses=poses, distance_m=0.5), [0, 1, 2])
    np.testing.assert_array_equal(select_keyframes(None, 0.0, poses=poses, angle_deg=15.0), [0, 3, 4, 5])
    np.testing.assert_array_equal(
        select_keyframes(None, 0.0, poses=poses, distance_m=0.5, angle_deg=15.0), [0, 1, 2, 3, 4, 5]
    )
    times = np.arange(6) * 1.0
    np.testing.assert_array_equal(select_keyframes(times, 3.0, poses=poses, distance_m=0.5), [0, 1, 2])


def test_robust_outliers_and_report_rows():
    values = np.array([1.0, 1.1, 0.9, 1.05, 0.95, 5.0, np.nan])
    np.testing.assert_array_equal(report.robust_outliers(values), [0, 0, 0, 0, 0, 1, 0])
    assert not report.robust_outliers(np.ones(5)).any()  # no spread: nothing is an outlier
    T = np.tile(np.eye(4), (3, 1, 1))
    T_after = T.copy()
    T_after[1, :3, 3] = [0.03, 0.04, 0.0]
    T_after[1, :3, :3] = Rotation.from_euler("x", 2.0, degrees=True).as_matrix()
    metres, degrees = report.pose_corrections(T, T_after)
    np.testing.assert_allclose(metres, [0, 0.05, 0], atol=1e-12)
    np.testing.assert_allclose(degrees, [0, 2.0, 0], atol=1e-9)
    rows = report.scan_report(
        report.ScanList(3, np.array([0, 2]), ["a.pcd", "b.pcd", "c.pcd"]),
        report.KeyframeMeasures(
            np.array([10, 20]), np.array([0.1, 0.2]), np.array([-3.0, -3.1]), np.array([-3.2, -3.3])
        ),
        metres,
        degrees,
    )
    assert [r["keyframe"] for r in rows] == [1, 0, 1] and rows[1]["rays"] == 0 and rows[1]["entropy_after"] is None
    assert rows[2]["median_residual_m"] == pytest.approx(0.2) and rows[1]["correction_cm"] == pytest.approx(5.0)
    # Without a start of its own the refinement is the correction from the input (keyframes only)
    assert rows[0]["refinement_cm"] == 0.0 and rows[1]["refinement_cm"] is None


def test_the_report_flags_the_bundle_adjustments_own_moves_not_its_starts():
    # From the baseline's poses: the baseline moved 5 of 12 keyframes by cm (two groups; median + 3 MADs flags all
    # of the upper one), NeLD-BA moved every keyframe by 1-2 mm and keyframe 7 by 2 cm.
    keyframes = 12
    correction_m = np.where(np.arange(keyframes) < 7, 0.002, 0.04) + 0.001 * np.arange(keyframes) / keyframes
    refinement_m = 0.001 + 0.001 * np.arange(keyframes) / keyframes
    refinement_m[7] = 0.02
    flat, zeros = np.full(keyframes, 0.1), np.zeros(keyframes)
    scans = report.ScanList(keyframes, np.arange(keyframes))
    by_correction = report.scan_report(scans, report.KeyframeMeasures(flat, flat, flat, flat), correction_m, zeros)
    assert [r["scan"] for r in by_correction if r["flag"]] == [7, 8, 9, 10, 11]  # the start's upper group
    rows = report.scan_report(
        scans, report.KeyframeMeasures(flat, flat, flat, flat, refinement_m, zeros), correction_m, zeros
    )
    assert [r["scan"] for r in rows if r["flag"]] == [7] and rows[7]["flag"] == "refinement"
    assert rows[7]["refinement_cm"] == pytest.approx(2.0) and rows[7]["correction_cm"] == pytest.approx(
        4.0 + 0.0583, abs=1e-3
    )
    summary = report.summarize(rows)
    assert [f["scan"] for f in summary["flagged"]] == [7] and summary["flagged"][0]["refinement_cm"] == 2.0
    # An outlier among sub-millimetre moves is below the floor (REFINEMENT_FLOOR_M): not flagged
    tiny = report.scan_report(
        scans, report.KeyframeMeasures(flat, flat, flat, flat, refinement_m / 10, zeros), correction_m, zeros
    )
    assert not any(r["flag"] for r in tiny)


def test_the_report_flags_residuals_only_well_above_the_rest():
    keyframes = 24
    flat, zeros = np.full(keyframes, 0.1), np.zeros(keyframes)

    def flagged(residual_m):
        rows = report.scan_report(
            report.ScanList(keyframes, np.arange(keyframes)),
            report.KeyframeMeasures(flat, residual_m, flat, flat),
            zeros,
            zeros,
        )
        return [r["scan"] for r in rows if r["flag"]]

    # Noise-free synthetic scans (the demo): residuals 1.1-1.2 cm and one at 1.37 cm, above median + 3 MADs but
    # only 2 mm above the rest: not worth a look.
    clean = 0.011 + 0.001 * np.arange(keyframes) / keyframes
    clean[8] = 0.0137
    assert report.robust_outliers(clean)[8] and flagged(clean) == []
    # A real sequence's scans (median ~3 cm) with two genuine outliers 4 and 15 cm above it: both flagged, and
    # one just under the floor (2.5 cm above the median, far above the MAD rule) is not.
    real = 0.03 + 0.004 * np.arange(keyframes) / keyframes
    real[[3, 14, 20]] = [0.07, 0.18, 0.032 + report.RESIDUAL_FLOOR_M - 0.005]
    assert report.robust_outliers(real)[20] and flagged(real) == [3, 14]


def test_aligned_corrections_remove_the_trajectorys_rigid_motion():
    from neld_jax.judging.report import aligned_corrections

    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, 0, 3] = np.arange(4.0)
    moved = T.copy()
    moved[:, :3, 3] += [0.5, -0.2, 0.1]  # the whole trajectory shifted: no scan moved against the others
    moved[2, 1, 3] += 0.03
    metres, degrees = aligned_corrections(T, moved)
    assert metres[2] == pytest.approx(0.03 * 3 / 4, abs=2e-3) and metres.max() == metres[2]
    np.testing.assert_allclose(degrees, 0.0, atol=1e-6)


def test_pseudo_ground_truth_keeps_the_recording_as_gt():
    seq = tiny_synthetic_sequence(6)
    drifted = with_drift(seq, 0.05, 0.5, seed=0)
    np.testing.assert_array_equal(drifted.gt_poses, seq.poses)
    np.testing.assert_allclose(drifted.poses[0], seq.poses[0])
    assert np.abs(drifted.poses[1:, :3, 3] - seq.poses[1:, :3, 3]).max() > 0.01
    np.testing.assert_array_equal(with_drift(seq, 0.05, 0.5, seed=0).poses, drifted.poses)  # seeded


def _cli(script, *args):
    return subprocess.run(
        [sys.executable, os.path.join(REPO, "bin", script), *args],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NELD_JAX_HUGEPAGES": "0"},
    )


def test_train_on_the_layout_writes_every_input_scan_and_quality(tmp_path):
    """End to end through the CLI: 6 scans of which 3 are keyframes (distance rule), a pseudo ground truth from
    bin/perturb.py; every input scan gets a pose, the crispness and the per-scan report are written."""
    seq = tiny_synthetic_sequence(6)
    _write_layout(tmp_path / "rec", seq, times=np.arange(6) * 1.0)
    perturbed = _cli(
        "perturb.py",
        "--config=configs/lio_keyframes.py",
        f"--config.data.root={tmp_path / 'rec'}",
        f"--out={tmp_path / 'drift'}",
        "--trans_m=0.02",
        "--rot_deg=0.2",
    )
    assert perturbed.returncode == 0, perturbed.stderr[-2000:]
    assert "wrote 6 scans" in perturbed.stdout
    out = tmp_path / "out"
    args = [
        "--config=configs/generic.py:paper",
        f"--config.data.root={tmp_path / 'drift'}",
        f"--config.output_dir={out}",
        "--config.data.keyframe_interval_s=2.0",
        "--config.data.keyframe_angle_deg=360",  # 60 degrees a scan
        "--config.data.keyframe_distance_m=1000",
        "--config.model.width=16",
        "--config.model.depth=2",
        "--config.model.skip_layers=(1,)",
        "--config.model.pos_freqs=6",
        "--config.model.dir_freqs=2",
        "--config.sampling.coarse_stages=(8,)",
        "--config.sampling.fine_stages=(4,)",
        "--config.train.steps=12",
        "--config.train.batch_rays=32",
        "--config.train.log_every=4",
        "--config.data.max_rays_per_scan=128",
        "--config.mapping.num_coarse=8",
        "--config.mapping.num_fine=8",
        "--config.mapping.max_rays_per_scan=32",
        "--config.eval.crispness_queries=500",
        "--config.eval.crispness_radius_m=3.0",
    ]  # sparse 8-beam scans: a wide neighbourhood
    result = _cli("train.py", *args)
    assert result.returncode == 0, result.stderr[-3000:]
    said = result.stdout + result.stderr
    assert "3 keyframes of 6 input scans" in said or "on 3 keyframes of 6 input" in result.stdout
    stamps, poses = read_tum(out / "poses_optimized.txt")
    assert len(poses) == 6 and np.all(np.isfinite(poses))
    np.testing.assert_allclose(stamps, np.arange(6) * 1.0)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run"]["num_input_scans"] == 6 and metrics["run"]["num_scans"] == 3
    # twelve steps of a tiny field may blur the input's map: the input's poses are then the answer (test_answer.py)
    kept_start = {"neld_ba"} if metrics["run"]["answer"] == "input" else set()
    assert metrics["run"]["answer"] in ("neld_ba", "input")
    assert set(metrics["crispness"]) == {"initial", "optimized"} | kept_start
    assert metrics["crispness"]["optimized"]["mean_map_entropy"] is not None
    margin = metrics["run"]["crispness_margin"]  # eval.crispness_draws (5) draws of the query points
    assert set(margin) == {"initial"} | kept_start and len(margin["initial"]["per_draw"]) == 5
    assert metrics["evaluation"]["methods"]["optimized"]["num_poses"] == 6
    lines = (out / "scans_report.csv").read_text().strip().splitlines()
    assert lines[0].startswith("scan,file,timestamp,keyframe") and len(lines) == 7
    assert [line.split(",")[3] for line in lines[1:]] == ["1", "0", "1", "0", "1", "0"]
    assert (out / "map_topdown.png").stat().st_size > 10_000 and (out / "scans_report.png").is_file()
    assert "mean map entropy" in result.stdout


def test_entropy_trajectory_benchmark_follows_the_poses(tmp_path):
    """benchmarks/entropy_trajectory.py: the map's entropy before the poses start equals the start's, and moves
    once they do; one record per --every steps and one at the end."""
    _write_layout(tmp_path / "seq", tiny_synthetic_sequence(num_scans=4))
    out = tmp_path / "trajectory.json"
    tiny = [
        "model.width=16",
        "model.depth=2",
        "model.skip_layers=(1,)",
        "model.pos_freqs=6",
        "model.dir_freqs=2",
        "sampling.coarse_stages=(8,)",
        "sampling.fine_stages=(4,)",
        "sampling.guided_samples=4",
        "train.steps=8",
        "train.batch_rays=64",
        "train.log_every=4",
        "data.max_rays_per_scan=128",
        "eval.crispness_queries=300",
        "eval.crispness_radius_m=3.0",
        "train.pose_lr_trans_init=1e-3",
        "train.pose_lr_rot_init=1e-3",
    ]
    proc = subprocess.run(
        [
            sys.executable,
            os.path.join(REPO, "benchmarks", "entropy_trajectory.py"),
            f"--root={tmp_path / 'seq'}",
            "--every=4",
            f"--out={out}",
            *[f"--set={s}" for s in tiny],
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())["results"]  # the payload of the benchmarks' schema (benchmarks/harness.py)
    records = result["records"]
    assert [r["step"] for r in records] == [0, 4, 8] and result["scans"] == 4
    # Poses start with frequency 6 of 6, at step 4 (c2f over half the steps): frozen until then.
    assert records[1]["mean_map_entropy"] == records[0]["mean_map_entropy"]
    assert records[1]["pose_trans_mean_m"] == 0.0 < records[2]["pose_trans_mean_m"]
    assert records[2]["mean_map_entropy"] != records[0]["mean_map_entropy"]


def _loaded_and_keyframes(root, keyframe_interval_s=0.0):
    from configs.lio_keyframes import get_config
    from neld_jax.steps.inputs import load_keyframes

    data = get_config("cpu").data
    data.root, data.keyframe_interval_s = str(root), keyframe_interval_s
    data.keyframe_angle_deg, data.keyframe_distance_m = 360.0, 1000.0  # the time cap alone: 60 degrees a scan
    return load_keyframes(data)


def test_another_trajectory_is_matched_to_the_keyframes_by_time_or_by_order(tmp_path):
    from neld_jax.data.poses import write_tum
    from neld_jax.writing.evaluate import trajectory_at_keyframes

    seq = tiny_synthetic_sequence(6)
    _write_layout(tmp_path / "rec", seq, times=np.arange(6) * 1.0)
    loaded, keyframes = _loaded_and_keyframes(tmp_path / "rec", keyframe_interval_s=2.0)
    np.testing.assert_array_equal(keyframes.loaded_index, [0, 2, 4])
    other = seq.gt_poses
    order = np.array([3, 0, 5, 1, 4, 2])  # by time, the file's order does not matter
    write_tum(tmp_path / "other.txt", np.arange(6)[order] + 0.01, other[order])
    np.testing.assert_allclose(trajectory_at_keyframes(tmp_path / "other.txt", loaded, keyframes), other[[0, 2, 4]])
    write_kitti(tmp_path / "all.kitti", other)  # by order: one pose per input scan ...
    np.testing.assert_allclose(
        trajectory_at_keyframes(tmp_path / "all.kitti", loaded, keyframes), other[[0, 2, 4]], atol=1e-6
    )
    write_kitti(tmp_path / "keyframes.kitti", other[[0, 2, 4]])  # ... or one per keyframe
    np.testing.assert_allclose(
        trajectory_at_keyframes(tmp_path / "keyframes.kitti", loaded, keyframes), other[[0, 2, 4]], atol=1e-6
    )
    np.testing.assert_allclose(
        trajectory_at_keyframes(tmp_path / "all.kitti", loaded, keyframes, invert=True),
        np.linalg.inv(other[[0, 2, 4]]),
        atol=1e-6,
    )
    write_kitti(tmp_path / "short.kitti", other[:5])
    with pytest.raises(
        DataError,
        match=r"short.kitti: 5 poses for 6 input scans \(3 keyframes\); the file has no "
        r"timestamps, so it must hold one pose per input scan or per keyframe",
    ):
        trajectory_at_keyframes(tmp_path / "short.kitti", loaded, keyframes)
    write_tum(tmp_path / "late.txt", np.arange(6) + 0.5, other)
    with pytest.raises(DataError, match=r"late.txt: 3 of 3 scans have no pose within 0.05 s \(first: Scans/0+.pcd"):
        trajectory_at_keyframes(tmp_path / "late.txt", loaded, keyframes)


def test_judging_trajectories_finds_the_true_poses_crisper_on_every_draw():
    from neld_jax.judging.judge import judge_trajectories, margins_against

    seq = tiny_synthetic_sequence(6)
    eval_cfg = ml_collections.ConfigDict({"crispness_radius_m": 3.0, "crispness_queries": 800, "crispness_draws": 3})
    verdict = judge_trajectories(seq, {"drifted": seq.poses, "true": seq.gt_poses}, eval_cfg)
    assert verdict["crispest"] == "true"
    margin = verdict["margins"]["drifted"]
    assert len(margin["per_draw"]) == 3 and margin["all_draws_agree"] and margin["mean"] < 0
    crisp = verdict["crispness"]
    assert crisp["true"]["mean_map_entropy"] < crisp["drifted"]["mean_map_entropy"]
    # re-referenced to another method: new minus other, per draw
    margins = {"b": {"per_draw": [-0.1, -0.3]}, "c": {"per_draw": [0.2, 0.1]}}
    moved = margins_against(margins, "a", "c")
    np.testing.assert_allclose(moved["a"]["per_draw"], [-0.2, -0.1])  # c - a
    np.testing.assert_allclose(moved["b"]["per_draw"], [-0.3, -0.4])  # c - b = (a - b) - (a - c)
    assert moved["b"]["all_draws_agree"] and set(moved) == {"a", "b"}


def test_crispness_cli_judges_files_against_the_input_and_refuses_a_bad_one(tmp_path):
    from neld_jax.data.poses import write_tum

    seq = tiny_synthetic_sequence(4)
    _write_layout(tmp_path / "rec", seq)
    write_kitti(tmp_path / "true.kitti", seq.gt_poses)
    common = [
        "--config=configs/lio_keyframes.py:cpu",
        f"--config.data.root={tmp_path / 'rec'}",
        "--config.eval.crispness_radius_m=3.0",
        "--config.eval.crispness_queries=800",
    ]
    run = tmp_path / "run"  # a run's output folder stands for its answer, poses_optimized.txt
    run.mkdir()
    write_tum(run / "poses_optimized.txt", seq.timestamps, seq.poses)
    result = _cli(
        "crispness.py", *common, f"--poses={tmp_path / 'true.kitti'},run={run}", f"--out={tmp_path / 'j.json'}"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "crispest: true" in result.stdout and "against the input poses' map" in result.stdout
    rows = [line.split() for line in result.stdout.splitlines() if line.split()[:1] in (["input"], ["true"], ["run"])]
    assert [row[0] for row in rows] == ["input", "true", "run"]  # in the order given, four decimals of entropy
    assert all(len(row[1].split(".")[1]) == 4 and len(row[2].split(".")[1]) == 3 for row in rows)
    judged = json.loads((tmp_path / "j.json").read_text())
    assert judged["crispest"] == "true" and judged["keyframes"] == 4
    assert set(judged["crispness"]) == {"input", "true", "run"}  # the run's answer here: the input's own poses
    assert judged["crispness"]["run"]["mean_map_entropy"] == pytest.approx(
        judged["crispness"]["input"]["mean_map_entropy"], abs=1e-6
    )
    assert len(judged["margins"]["input"]["per_draw"]) == 5
    write_kitti(tmp_path / "short.kitti", seq.gt_poses[:3])
    bad = _cli("crispness.py", *common, f"--poses=other={tmp_path / 'short.kitti'}")
    assert bad.returncode == 1
    assert bad.stderr.strip().splitlines()[-1].startswith(f"error: {tmp_path / 'short.kitti'}: 3 poses for 4 input")
    named_twice = _cli("crispness.py", *common, f"--poses=input={tmp_path / 'true.kitti'}")
    assert named_twice.returncode == 1 and "the name 'input' is the sequence's own poses" in named_twice.stderr
    missing = _cli("crispness.py", *common, f"--poses=other={tmp_path / 'none.txt'}")
    assert missing.returncode == 1 and "none.txt: trajectory file does not exist (--poses other)" in missing.stderr
