#!/usr/bin/env python
"""NeLD-BA against its peers on the same raw sweeps: KISS-ICP (as its own pipeline runs it), KISS-SLAM (KISS-ICP with a
local-map pose graph and loop closures), the run's own odometry (its input: KISS-ICP twice, the sweeps deskewed along
the first pass; neld_jax.frontend.odometry), the classical baseline and NeLD-BA, in one table.

    pip install -e .[peers]      # kiss-slam; without it its row says "not installed" and the rest still runs
    python benchmarks/peers.py --sequences=synthetic10hz:0,synthetic10hz:1:20 --set=data.keyframe_interval_s=1.0 \\
        --work=outputs/peers --out=benchmarks/results/peers_cpu.json
    python benchmarks/peers.py --sequences= --roots=/data/seq1,/data/seq2 --config=configs/generic.py:cpu

Per sequence: one NeLD-BA run (neld_jax.run.run with --config and --set, fresh output folder), whose odometry
(data.initial_poses=kiss_icp) is its input and the classical baseline's; KISS-ICP and KISS-SLAM run on the same raw
sweeps as their own pipelines run them (deskewing by the points' times; their poses, at each sweep's last point's
instant as KISS-ICP gives them, interpolated to the sweeps' stamps), with --peer_range=own (the default) KISS-ICP's
own defaults (KISSConfig: 0-100 m, a 1 m voxel, a hundredth of the maximum range), with --peer_range=run the run's
data.min_range_m and data.max_range_m (the voxel a hundredth of it); the classical baseline from the run's
poses_baseline.txt (start.poses "crisper" runs it), or run here from the keyframes' odometry poses where the run did
not. Each method gives one pose per input sweep (TUM, at the sweeps' stamps). Columns (JSON keys of each row):
- the trajectory against the ground truth, where the sequence has it, over the input sweeps from --eval_from_scan on
  (KITTI 00: 15; the JSON's gt_path_m is the ground truth's path there): ATE translation RMSE [m] and rotation RMSE
  [deg] SE(3)-aligned as neld-evaluate aligns (ate_m, ate_rot_deg, ate_poses); the translation RMSE Sim(3)-aligned
  (ate_sim3_m) with the scale found (sim3_scale: above 1 when the path is too short); the path-length ratio, the
  estimate's path over the ground truth's (path_ratio, 1: the right length), which an aligned ATE hides; KITTI's
  relative error over --segments_m segments (the odometry devkit's measure, every --segment_step-th first frame):
  translation error over length [%] and rotation error over length [deg/m] averaged over the segments (kitti_t_pct,
  kitti_r_deg_per_m, kitti_segments);
- the raw map's crispness: mean map entropy and plane thickness of the run's keyframes (their KISS-ICP-deskewed
  scans) registered with each trajectory at the keyframes, on the same query points for every method
  (neld_jax.judging.judge, as neld-crispness; entropy, thickness_cm), and NeLD-BA's margin to each peer over
  eval.crispness_draws draws of the query points (neld_ba_margin, neld_ba_verdict): "every draw" (crisper on each),
  "a tie" (the draws disagree in sign) or "blurrier" (blurrier on each);
- the same for the raw map of EVERY input sweep (every_sweep_map: judge.EVERY_SCAN_POINTS random points of each, the
  sweeps as the run registers them) under each method's poses of every sweep;
- wall time [s] (wall_s): KISS-ICP's and KISS-SLAM's whole runs, the run's odometry, the baseline's registration,
  and NeLD-BA's whole run end to end (loading with the odometry, the baseline, training, rendering, judging).
Targets (entry["targets"]["peers"]), printed at the end: NeLD-BA's ATE below KISS-ICP's and KISS-SLAM's; its ATE over
KISS-ICP's (ate_over_kiss_icp), over the classical baseline's it started from (ate_over_baseline: what the neural part
adds) and over its odometry's (ate_over_odometry), also under the table; its path length over the odometry's
(path_scale_vs_odometry; path_scale_within_0.1pct: within 0.1 % of 1); its raw maps (the keyframes', every sweep's)
crisper than both peers on every draw; and the whole run within --minutes_limit minutes.

Sequences: `car:SEED` generates a car's 10 Hz scans along the synthetic courtyards' 320 m route with four corners
(--num_scans of a car driving it from rest, 11 m/s on the straights, slower round the corners: 300 drive 250 m; 64
beams x 1024 columns, 80 m range; raw sweeps with per-point times, up to 1.1 m of motion in each) with ground truth;
`synthetic10hz:SEED[:RADIUS_M]` generates raw 10 Hz sweeps with per-point times and ground truth
(neld_jax.synthetic.generator.make_sequence, rate_hz=10; --loop_scans sweeps round one loop of RADIUS_M (10 m: 63 m at
2.1 m/s; 20 m: 126 m at 4.2 m/s, longer than KISS-SLAM's 100 m local maps, so it can close the loop) at 40 m range,
the first --num_scans of them kept) into WORK/<name>/data in the generic layout without poses; `--roots` are
folders of raw full-rate sweeps as --config reads them (configs/generic.py, or a dataset's config for its layout as
downloaded), named by their folder. A sequence that fails records its one-line error, and the others still run.
"""

import contextlib
import json
import logging
import os
import shutil
import sys
import time
import traceback

import harness  # this folder's benchmarks/harness.py: --out, --set, the machine stamp and the JSON schema
import numpy as np
import real_targets  # this folder's benchmarks/real_targets.py: the targets' table
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SEQUENCES = flags.DEFINE_list(
    "sequences",
    ["synthetic10hz:0"],
    "Synthetic sequences: raw sweeps "
    "synthetic10hz:SEED[:RADIUS_M] (the loop's radius, default 10 m: a 63 m loop), or a "
    "car's scans car:SEED.",
)
ROOTS = flags.DEFINE_list("roots", [], "Folders of real raw full-rate sweeps (the layout --config reads).")
NUM_SCANS = flags.DEFINE_integer("num_scans", 300, "Synthetic: sweeps kept (the first of the loop's).")
LOOP_SCANS = flags.DEFINE_integer("loop_scans", 300, "Synthetic: sweeps round the whole loop (300: 2.1 m/s).")
GT_MAP_POINTS = flags.DEFINE_integer("gt_map_points", 50_000, "Synthetic: points of the ground-truth map.")
WORK = flags.DEFINE_string("work", "outputs/peers", "The sequences and the runs go below this.")
harness.default_out("outputs/peers/peers.json")  # --out: one entry per sequence
CONFIG = flags.DEFINE_string("config", "configs/generic.py:cpu", "The run's config, PATH[:BUDGET].")
OVERRIDES = harness.overrides_flag()
MAX_RANGE = flags.DEFINE_float(
    "max_range_m",
    0.0,
    "data.max_range_m of real roots (0: the config's); synthetic "
    "sequences use their generated range (40 m). --set wins over both.",
)
SLAM_SPLITTING = flags.DEFINE_float(
    "slam_splitting_m", 0.0, "KISS-SLAM's local_mapper.splitting_distance [m] (0: its own default, 100 m)."
)
MINUTES_LIMIT = flags.DEFINE_float("minutes_limit", 10.0, "The target for NeLD-BA's whole run [min].")
EVAL_FROM_SCAN = flags.DEFINE_integer(
    "eval_from_scan",
    0,
    "The trajectory figures (ATE, path length, KITTI's "
    "relative error) over the input sweeps from this index on (KITTI 00: 15, its "
    "ground truth of the first frames is a constant-velocity fill).",
)
PEER_RANGE = flags.DEFINE_enum(
    "peer_range",
    "own",
    ["own", "run"],
    "The ranges KISS-ICP and KISS-SLAM crop to: "
    "own (KISS-ICP's KISSConfig defaults, voxel a hundredth of its maximum range) or run "
    "(the run's data.min_range_m and data.max_range_m).",
)
SEGMENTS_M = flags.DEFINE_list(
    "segments_m",
    ["10", "20", "30", "40", "50"],
    "KITTI's relative error: the segment lengths [m] (the devkit's 100, ..., 800 m for whole sequences).",
)
SEGMENT_STEP = flags.DEFINE_integer(
    "segment_step", 1, "KITTI's relative error: frames between a segment's first frames (the devkit's 10)."
)

SYNTHETIC = {"trajectory_radius_m": 10.0, "max_range_m": 40.0}  # a 63 m loop by default
CAR = {"route": "car", "route_length_m": 320.0, "num_beams": 64, "num_columns": 1024, "max_range_m": 80.0}
RATE_HZ = 10.0
METHODS = ("kiss_icp", "kiss_slam", "odometry", "baseline", "neld_ba")
NOT_INSTALLED = "not installed (pip install neld-jax[peers])"


def written_once(spec: dict, root: str, write) -> None:
    """write(root) makes the sequence that `spec` describes in root, unless root already holds it (its
    peers_sequence.json equals spec); otherwise root is emptied first and the spec recorded after."""
    marker = os.path.join(root, "peers_sequence.json")
    if os.path.exists(marker):
        with open(marker) as f:
            if json.load(f) == spec:
                return
    shutil.rmtree(root, ignore_errors=True)
    write(root)
    with open(marker, "w") as f:
        json.dump(spec, f)


def make_synthetic(seed: int, radius_m: float, root: str) -> None:
    """The first NUM_SCANS of LOOP_SCANS raw 10 Hz sweeps round the loop of radius_m, in the generic layout (no
    poses.txt); kept when root already holds the same sequence."""
    import dataclasses

    from neld_jax.synthetic.generator import make_sequence, write_generic

    spec = {
        **SYNTHETIC,
        "trajectory_radius_m": radius_m,
        "num_scans": LOOP_SCANS.value,
        "gt_map_points": GT_MAP_POINTS.value,
        "seed": seed,
        "kept": NUM_SCANS.value,
        "rate_hz": RATE_HZ,
    }

    def write(folder):
        seq = make_sequence({k: v for k, v in spec.items() if k not in ("kept", "rate_hz")}, rate_hz=RATE_HZ)
        n = min(NUM_SCANS.value, seq.num_scans)
        seq = dataclasses.replace(
            seq,
            scans=seq.scans[:n],
            point_times=seq.point_times[:n],
            timestamps=seq.timestamps[:n],
            gt_poses=seq.gt_poses[:n],
        )
        write_generic(seq, folder)

    written_once(spec, root, write)


def make_car(seed: int, root: str) -> None:
    """NUM_SCANS of a car's 10 Hz scans along the courtyards' route (CAR), in the generic layout (no poses.txt); kept
    when root already holds the same sequence."""
    from neld_jax.synthetic.generator import make_sequence, write_generic

    spec = {**CAR, "num_scans": NUM_SCANS.value, "gt_map_points": GT_MAP_POINTS.value, "seed": seed}
    written_once(spec, root, lambda folder: write_generic(make_sequence(spec), folder))


def run_config(root: str, out_dir: str, range_m: float | None):
    """--config for one sequence: the scans' own KISS-ICP odometry as the input, the range (a synthetic sequence's
    range_m, or --max_range_m), --set last."""
    from neld_jax.config import apply_overrides, from_file

    path = CONFIG.value if os.path.isabs(CONFIG.value) else os.path.join(REPO, CONFIG.value)
    c = from_file(path)
    c.data.root = root
    c.output_dir = out_dir
    c.data.initial_poses = "kiss_icp"
    if range_m is not None:
        c.data.max_range_m = range_m
    elif MAX_RANGE.value > 0:
        c.data.max_range_m = MAX_RANGE.value
    return apply_overrides(c, OVERRIDES.value)


@contextlib.contextmanager
def watching_the_run(seen: dict):
    """Within: neld_jax.run's load_sessions and the odometry it calls are wrapped, so that `seen` gets the loaded
    sequence and keyframes ("loaded", "keyframes"), the raw sweeps KISS-ICP read ("raw": the layout's Sequence) and
    the odometry's wall time ("odometry_s"), without loading or registering the scans twice."""
    from neld_jax import run as run_module
    from neld_jax.frontend import odometry

    real_load, real_odometry = run_module.load_sessions, odometry.with_kiss_icp_poses

    def load_sessions(*args, **kwargs):
        out = real_load(*args, **kwargs)
        seen["loaded"], seen["keyframes"] = out[:2]
        return out

    def with_kiss_icp_poses(seq, *args, **kwargs):
        seen["raw"] = seq
        t0 = time.perf_counter()
        out = real_odometry(seq, *args, **kwargs)
        seen["odometry_s"] = time.perf_counter() - t0
        return out

    run_module.load_sessions, odometry.with_kiss_icp_poses = load_sessions, with_kiss_icp_poses
    try:
        yield seen
    finally:
        run_module.load_sessions, odometry.with_kiss_icp_poses = real_load, real_odometry


@contextlib.contextmanager
def stdout_to_stderr():
    """KISS-SLAM's pose-graph optimiser (g2o) prints every iteration to the process's stdout: send it to stderr."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def kiss_icp_poses(raw, min_range_m: float, max_range_m: float):
    """KISS-ICP alone (its KissICP as its own pipeline drives it: its deskewing by raw.point_times where there are,
    no check of the track) over the raw sweeps of Sequence `raw` (time order). Returns (poses [S, 4, 4] sensor ->
    world at the sweeps' stamps, scan 0 at the identity; seconds)."""
    from kiss_icp.kiss_icp import KissICP

    from neld_jax.frontend.odometry import kiss_icp_config

    t0 = time.perf_counter()
    odometry, poses = KissICP(kiss_icp_config(min_range_m, max_range_m, deskew=raw.point_times is not None)), []
    for i, scan in enumerate(raw.scans):
        times = np.zeros(0) if raw.point_times is None else np.asarray(raw.point_times[i], np.float64)
        odometry.register_frame(np.asarray(scan, np.float64), times)
        poses.append(np.array(odometry.last_pose, np.float64))
    seconds = time.perf_counter() - t0
    return at_the_stamps(raw, np.stack(poses)), seconds


def at_the_stamps(raw, poses: np.ndarray) -> np.ndarray:
    """KISS-ICP's (or KISS-SLAM's) poses [S, 4, 4] of the sweeps of Sequence `raw` moved to the sweeps' stamps (where
    deskewed, a pose is the sensor's at its sweep's last point), scan 0 at the identity."""
    from neld_jax.frontend.odometry import last_point_offsets, poses_at_stamps

    if raw.point_times is not None and raw.timestamps is not None and raw.num_scans >= 2:
        poses = poses_at_stamps(raw.timestamps, last_point_offsets(raw.point_times), poses)
    return np.linalg.inv(poses[0]) @ poses


def kiss_slam_poses(raw, min_range_m: float, max_range_m: float, splitting_m: float = 0.0):
    """KISS-SLAM (its KissSLAM class, as its own pipeline drives it) over the raw sweeps of Sequence `raw` (time
    order), deskewing by raw.point_times where there are. Returns (poses [S, 4, 4] sensor -> world at the sweeps'
    stamps, scan 0 at the identity; seconds; {"local_maps", "closures"}). ImportError without kiss-slam."""
    import numpy as np
    from kiss_slam.config import KissSLAMConfig
    from kiss_slam.slam import KissSLAM

    from neld_jax.frontend.odometry import VOXELS_PER_RANGE

    config = KissSLAMConfig()  # its defaults; the range-derived voxel as its load_config derives it
    config.odometry.preprocessing.min_range = float(min_range_m)
    config.odometry.preprocessing.max_range = float(max_range_m)
    config.odometry.preprocessing.deskew = raw.point_times is not None
    config.odometry.mapping.voxel_size = VOXELS_PER_RANGE * float(max_range_m)
    config.occupancy_mapper.max_range = float(max_range_m)
    if splitting_m > 0:
        config.local_mapper.splitting_distance = float(splitting_m)
    t0 = time.perf_counter()
    with stdout_to_stderr():
        slam = KissSLAM(config)
        for i, scan in enumerate(raw.scans):
            times = np.zeros(0) if raw.point_times is None else np.asarray(raw.point_times[i], np.float64)
            slam.process_scan(np.asarray(scan, np.float64), times)
        # what kiss_slam.pipeline.SlamPipeline._run_pipeline does after the last scan
        slam.generate_new_node()
        slam.local_map_graph.erase_last_local_map()
        poses, _ = slam.fine_grained_optimization()
    seconds = time.perf_counter() - t0
    poses = np.array(poses, np.float64)
    if len(poses) != raw.num_scans:
        raise RuntimeError(f"KISS-SLAM gave {len(poses)} poses for {raw.num_scans} sweeps")
    poses = at_the_stamps(raw, poses)
    info = {"local_maps": len(list(slam.local_map_graph.local_maps())), "closures": len(slam.closures)}
    return poses, seconds, info


def run_baseline_here(config, loaded, keyframes, path_dir: str):
    """The classical baseline from the keyframes' poses (as neld-baseline), its poses of every input sweep written to
    path_dir/poses_baseline.txt. Returns its registration seconds."""
    from neld_jax.baseline import BaselineSettings, register_sequence
    from neld_jax.writing.export import write_keyframe_poses

    t0 = time.perf_counter()
    poses = register_sequence(keyframes.scans, keyframes.poses, BaselineSettings.from_config(config)).poses
    seconds = time.perf_counter() - t0
    write_keyframe_poses(path_dir, "poses_baseline", loaded, keyframes, poses)
    return seconds


def peer_ranges(config, mode: str) -> dict:
    """The ranges KISS-ICP and KISS-SLAM run with: mode "own", KISS-ICP's KISSConfig defaults (KISS-SLAM's odometry
    has the same); "run", the run's data.min_range_m and data.max_range_m. Returns {"mode", "min_range_m",
    "max_range_m", "voxel_m"} (the voxel a hundredth of the maximum range, as their pipelines derive it)."""
    from neld_jax.frontend.odometry import VOXELS_PER_RANGE

    if mode == "own":
        from kiss_icp.config import KISSConfig

        ranges = KISSConfig().data.min_range, KISSConfig().data.max_range
    elif mode == "run":
        ranges = config.data.min_range_m, config.data.max_range_m
    else:
        raise ValueError(f"peer range mode must be own or run, got {mode!r}")
    return {
        "mode": mode,
        "min_range_m": float(ranges[0]),
        "max_range_m": float(ranges[1]),
        "voxel_m": VOXELS_PER_RANGE * float(ranges[1]),
    }


def run_peers(seen: dict, ranges: dict, out: str, rows: dict, files: dict, name: str) -> None:
    """KISS-ICP and KISS-SLAM over the raw sweeps the run read (seen["raw"]) with `ranges` (peer_ranges): their poses
    written below out, their files into `files`, wall time (or why not) into their rows."""
    from neld_jax.writing.export import write_poses

    if "raw" not in seen:
        rows["kiss_icp"]["status"] = "not run: the layout gave the run its poses"
        rows["kiss_slam"]["status"] = "not run: the layout gave the run its poses"
        return
    limits = ranges["min_range_m"], ranges["max_range_m"]
    poses, seconds = kiss_icp_poses(seen["raw"], *limits)
    files["kiss_icp"] = str(
        write_poses(os.path.join(out, "kiss_icp"), "poses_kiss_icp", seen["raw"].timestamps, poses)[0]
    )
    rows["kiss_icp"]["wall_s"] = round(seconds, 1)
    try:
        poses, seconds, info = kiss_slam_poses(seen["raw"], *limits, SLAM_SPLITTING.value)
        files["kiss_slam"] = str(
            write_poses(os.path.join(out, "kiss_slam"), "poses_kiss_slam", seen["raw"].timestamps, poses)[0]
        )
        rows["kiss_slam"].update(wall_s=round(seconds, 1), **info)
    except ImportError:
        rows["kiss_slam"]["status"] = NOT_INSTALLED
    except Exception as e:  # its row says why; the others still compare
        rows["kiss_slam"]["status"] = f"failed: {type(e).__name__}: {e}"
        logging.error("KISS-SLAM failed on %s:\n%s", name, traceback.format_exc())


def trajectory_figures(est: np.ndarray, gt: np.ndarray, lengths_m, step: int = 1) -> dict:
    """One method's trajectory figures against the ground truth, est and gt: [S, 4, 4] matched poses in time order.
    Returns ate_m / ate_rot_deg (translation / rotation RMSE, SE(3)-aligned), ate_poses, ate_sim3_m and sim3_scale
    (Sim(3)-aligned, the scale that takes the estimate to the ground truth: above 1 for a shortened path),
    path_ratio (the estimate's path length over the ground truth's), and KITTI's relative error over segments of
    lengths_m [m] from every step-th frame: kitti_t_pct (%), kitti_r_deg_per_m, kitti_segments."""
    from neld_jax.judging import metrics

    rigid, similar = metrics.ate(est, gt, align="se3"), metrics.ate(est, gt, align="sim3")
    kitti = metrics.kitti_relative_error(est, gt, lengths_m, step)

    def rounded(value, digits):  # NaN (no segment fits) is None in the JSON
        return None if not np.isfinite(value) else round(float(value), digits)

    return {
        "ate_m": round(rigid["translation_rmse_m"], 4),
        "ate_rot_deg": round(rigid["rotation_rmse_deg"], 3),
        "ate_poses": len(est),
        "ate_sim3_m": round(similar["translation_rmse_m"], 4),
        "sim3_scale": round(similar["scale"], 6),
        "path_ratio": rounded(metrics.path_length_ratio(est, gt), 6),
        "kitti_t_pct": rounded(kitti["translation_pct"], 4),
        "kitti_r_deg_per_m": rounded(kitti["rotation_deg_per_m"], 5),
        "kitti_segments": kitti["num_segments"],
    }


def evaluated_poses(path: str, loaded, from_scan: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A TUM file's poses matched by stamp to the input sweeps of `loaded` that have ground truth, from sweep index
    from_scan on, in time order: (est [K, 4, 4], gt [K, 4, 4]); a ValueError when fewer than 3 are left."""
    from neld_jax.data.poses import read_tum
    from neld_jax.writing.evaluate import match_poses

    stamps, poses = read_tum(path)
    est, gt, _ = match_poses(stamps, loaded.timestamps, len(poses), len(loaded.gt_poses), path, 0.01)
    keep = gt >= from_scan
    order = np.argsort(gt[keep], kind="stable")
    est, gt = est[keep][order], gt[keep][order]
    if len(est) < 3:
        raise ValueError(f"{path}: {len(est)} poses with ground truth from sweep {from_scan} on (at least 3)")
    return poses[est], loaded.gt_poses[gt]


def run_sequence(name: str, root: str, range_m: float | None) -> dict:
    from neld_jax.judging.metrics import path_length
    from neld_jax.run import run

    out = os.path.join(WORK.value, name)
    run_dir = os.path.join(out, "neld_ba")
    shutil.rmtree(run_dir, ignore_errors=True)  # a fresh run, not a resumed one
    config = run_config(root, run_dir, range_m)
    seen = {}
    t0 = time.perf_counter()
    with watching_the_run(seen):
        summary = run(config, progress=False)
    neld_s = time.perf_counter() - t0
    r = summary["run"]
    loaded, keyframes = seen["loaded"], seen["keyframes"]
    ranges = peer_ranges(config, PEER_RANGE.value)
    entry = {
        "sequence": name,
        "root": root,
        "input_scans": loaded.num_scans,
        "keyframes": keyframes.num_scans,
        "steps": r["steps"],
        "started_from": r.get("started_from"),
        "peer_range": ranges,
        "eval_from_scan": EVAL_FROM_SCAN.value,
        "methods": {},
    }
    rows = {m: {"method": m} for m in METHODS}
    files = {
        "odometry": os.path.join(run_dir, "poses_odometry.txt"),
        "neld_ba": os.path.join(run_dir, "poses_optimized.txt"),
    }
    if not os.path.exists(files["odometry"]):  # the input came from the layout's own poses after all
        files["odometry"] = os.path.join(run_dir, "poses_initial.txt")
        rows["odometry"]["note"] = "the layout's poses, not the run's odometry"
    rows["odometry"]["wall_s"] = None if "odometry_s" not in seen else round(seen["odometry_s"], 1)
    rows["neld_ba"]["wall_s"] = round(neld_s, 1)
    run_peers(seen, ranges, out, rows, files, name)

    files["baseline"] = os.path.join(run_dir, "poses_baseline.txt")
    if os.path.exists(files["baseline"]):
        rows["baseline"]["wall_s"] = r.get("baseline_seconds")
    else:  # the run started from its input without the baseline: run it here from the same keyframes
        baseline_dir = os.path.join(out, "baseline")
        rows["baseline"]["wall_s"] = round(run_baseline_here(config, loaded, keyframes, baseline_dir), 1)
        files["baseline"] = os.path.join(baseline_dir, "poses_baseline.txt")
        rows["baseline"]["note"] = "run by the benchmark (the run did not)"

    methods = [m for m in METHODS if m in files]
    if loaded.gt_poses is not None:  # every sweep's pose from --eval_from_scan on, matched as neld-evaluate does
        lengths = [float(v) for v in SEGMENTS_M.value]
        for m in methods:
            est, gt = evaluated_poses(files[m], loaded, EVAL_FROM_SCAN.value)
            rows[m].update(trajectory_figures(est, gt, lengths, SEGMENT_STEP.value))
        entry["gt_path_m"] = round(path_length(loaded.gt_poses[EVAL_FROM_SCAN.value :]), 3)
    crispness_rows(config, loaded, keyframes, files, rows, methods)
    entry["methods"] = rows
    entry["targets"] = {"peers": real_targets.peer_target_verdicts(entry, MINUTES_LIMIT.value)}
    return entry


def crispness_rows(config, loaded, keyframes, files: dict, rows: dict, methods: list) -> None:
    """Into each method's row: the keyframes' raw map under its trajectory (entropy, thickness_cm, NeLD-BA's margin
    and verdict, on the same query draws), the raw map of every sweep (every_sweep_map) and its poses' file."""
    from neld_jax.judging import judge
    from neld_jax.writing.evaluate import trajectory_at_keyframes

    at_keyframes = {
        m: trajectory_at_keyframes(files[m], loaded, keyframes, tol=float(config.data.timestamp_tol_s)) for m in methods
    }
    crisp, _ = judge.map_crispness(keyframes, at_keyframes, config.eval)
    margins = judge.crispness_margins(keyframes, at_keyframes, config.eval, against="neld_ba", first_draw=crisp)
    every = every_sweep_crispness(loaded, {m: poses_of_every_sweep(files[m], loaded) for m in methods}, config.eval)
    for m in methods:
        s = crisp[m]
        rows[m]["every_sweep_map"] = every[m]
        rows[m].update(
            entropy=None if s["mean_map_entropy"] is None else round(s["mean_map_entropy"], 4),
            thickness_cm=None if s["mean_plane_thickness_m"] is None else round(100 * s["mean_plane_thickness_m"], 3),
        )
        if m in margins:
            rows[m].update(
                neld_ba_margin=margins[m]["mean"],
                neld_ba_margin_per_draw=margins[m]["per_draw"],
                neld_ba_verdict=real_targets.margin_verdict(margins[m]),
            )
        rows[m]["poses"] = files[m]


def poses_of_every_sweep(path: str, loaded):
    """The poses [S, 4, 4] a TUM file gives every input sweep of `loaded`: by stamp where both have stamps (each
    sweep's nearest within 0.01 s), else one pose a sweep in order; a sweep without one is a DataError."""
    from neld_jax.data.poses import read_tum
    from neld_jax.errors import DataError
    from neld_jax.writing.evaluate import match_poses

    stamps, poses = read_tum(path)
    est, at, _ = match_poses(stamps, loaded.timestamps, len(poses), loaded.num_scans, path, 0.01)
    if len(at) != loaded.num_scans:
        raise DataError(f"{path}: poses for {len(at)} of the {loaded.num_scans} input sweeps")
    out = np.empty((loaded.num_scans, 4, 4))
    out[at] = poses[est]
    return out


def every_sweep_crispness(loaded, methods: dict, eval_cfg) -> dict:
    """The raw map of EVERY input sweep (as the run registers them: deskewed along its odometry; judge.
    every_scan_crispness's points of each) under each method's poses [S, 4, 4]: {method: {"entropy",
    "thickness_cm", and beside NeLD-BA's: "neld_ba_margin" (its paired margin over eval.crispness_draws draws,
    negative: NeLD-BA crisper), "neld_ba_margin_per_draw", "neld_ba_verdict"}}."""
    from neld_jax.judging import judge

    crisp, margins = judge.every_scan_crispness(loaded.scans, methods, eval_cfg, against="neld_ba")
    out = {}
    for m, summary in crisp.items():
        out[m] = {
            "entropy": summary["mean_map_entropy"],
            "thickness_cm": None
            if summary["mean_plane_thickness_m"] is None
            else round(100 * summary["mean_plane_thickness_m"], 3),
        }
        if m in margins:
            out[m].update(
                neld_ba_margin=margins[m]["mean"],
                neld_ba_margin_per_draw=margins[m]["per_draw"],
                neld_ba_verdict=real_targets.margin_verdict(margins[m]),
            )
    return out


TABLE_COLUMNS = (  # (header, row key, format) of the trajectory's columns
    ("ATE m", "ate_m", "8.4f"),
    ("ATE deg", "ate_rot_deg", "8.3f"),
    ("Sim3 m", "ate_sim3_m", "8.4f"),
    ("scale", "sim3_scale", "8.5f"),
    ("path", "path_ratio", "8.5f"),
    ("KITTI %", "kitti_t_pct", "8.3f"),
    ("deg/m", "kitti_r_deg_per_m", "8.5f"),
)


def format_table(entry: dict) -> str:
    """The sequence's rows: method, the trajectory's figures (TABLE_COLUMNS), crispness, NeLD-BA's margin, wall time
    (or why a row is empty); then NeLD-BA's ATE over each other method's and its path over the odometry's."""

    def cell(value, fmt):
        return "-" if value is None else format(value, fmt)

    def margin(row):
        return "" if "neld_ba_margin" not in row else f"{row['neld_ba_margin']:+.4f} {row['neld_ba_verdict']}"

    scored = "" if not entry.get("eval_from_scan") else f", scored from sweep {entry['eval_from_scan']}"
    lines = [
        f"{entry['sequence']}: {entry['input_scans']} sweeps, {entry['keyframes']} keyframes{scored}",
        (
            f"{'method':<10} " + " ".join(f"{h:>8}" for h, _, _ in TABLE_COLUMNS) + f" {'entropy':>8} "
            f"{'thick cm':>8} {'NeLD-BA margin':>22} {'wall s':>7} {'every sweep: entropy':>20} "
            f"{'NeLD-BA margin':>22}"
        ),
    ]
    for m in METHODS:
        row = entry["methods"][m]
        if "status" in row:
            lines.append(f"{m:<10} {row['status']}")
            continue
        every = row.get("every_sweep_map", {})
        lines.append(
            f"{m:<10} "
            + " ".join(cell(row.get(key), fmt).rjust(8) for _, key, fmt in TABLE_COLUMNS)
            + f" {cell(row.get('entropy'), '8.4f')} {cell(row.get('thickness_cm'), '8.3f')} "
            f"{margin(row):>22} {cell(row.get('wall_s'), '7.1f')} {cell(every.get('entropy'), '20.4f')} "
            f"{margin(every):>22}"
        )
    targets = entry.get("targets", {}).get("peers", {})
    over = ", ".join(f"{m} {cell(targets.get(f'ate_over_{m}'), '.4f')}" for m in ("kiss_icp", "odometry", "baseline"))
    lines.append(
        f"NeLD-BA's ATE over: {over}; its path over the odometry's: "
        f"{cell(targets.get('path_scale_vs_odometry'), '.6f')}"
    )
    return "\n".join(lines)


def sequences() -> list[tuple[str, str, tuple | None]]:
    """(name, root, how to make it: (make_synthetic | make_car, its arguments, data.max_range_m) or None for a real
    root) of every --sequences and --roots item."""
    out = []
    for item in SEQUENCES.value:
        kind, seed, radius = (item.split(":") + [""])[:3]
        if kind == "car" and seed.isdigit() and radius == "":
            name = f"car_{seed}_{NUM_SCANS.value}"
            out.append((name, os.path.join(WORK.value, name, "data"), (make_car, (int(seed),), CAR["max_range_m"])))
            continue
        if kind != "synthetic10hz" or not seed.isdigit() or not (radius == "" or radius.replace(".", "", 1).isdigit()):
            raise app.UsageError(f"--sequences item {item!r}: expected synthetic10hz:SEED[:RADIUS_M] or car:SEED")
        radius_m = float(radius or SYNTHETIC["trajectory_radius_m"])
        name = f"synthetic10hz_{seed}_r{radius_m:g}_{NUM_SCANS.value}"
        out.append(
            (
                name,
                os.path.join(WORK.value, name, "data"),
                (make_synthetic, (int(seed), radius_m), SYNTHETIC["max_range_m"]),
            )
        )
    for root in ROOTS.value:
        out.append((os.path.basename(os.path.normpath(root)), root, None))
    return out


def main(argv):
    del argv
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        lengths = [float(v) for v in SEGMENTS_M.value]
    except ValueError as e:
        raise app.UsageError(f"--segments_m: {e}") from e
    if not lengths or min(lengths) <= 0 or SEGMENT_STEP.value < 1 or EVAL_FROM_SCAN.value < 0:
        raise app.UsageError("--segments_m needs positive lengths, --segment_step >= 1, --eval_from_scan >= 0")
    todo = sequences()
    results, stamped = [], None
    for name, root, synthetic in todo:
        try:
            if synthetic:
                make, arguments, _ = synthetic
                make(*arguments, root)
            entry = run_sequence(name, root, None if synthetic is None else synthetic[2])
            print(format_table(entry), flush=True)
        except Exception as e:  # one line per failed sequence; the others still run
            entry = {"sequence": name, "error": f"{type(e).__name__}: {e}"}
            logging.error("%s failed:\n%s", name, traceback.format_exc())
        results.append(entry)
        stamped = harness.write(
            harness.OUT.value,
            {
                "config": CONFIG.value,
                "overrides": OVERRIDES.value,
                "num_scans": NUM_SCANS.value,
                "slam_splitting_m": SLAM_SPLITTING.value or None,
                "peer_range": PEER_RANGE.value,
                "eval_from_scan": EVAL_FROM_SCAN.value,
                "segments_m": [float(v) for v in SEGMENTS_M.value],
                "segment_step": SEGMENT_STEP.value,
                "sequences": results,
            },
            stamped=stamped,
        )
    print(
        f"targets (NeLD-BA's ATE below KISS-ICP's and KISS-SLAM's and over theirs, the baseline's and the "
        f"odometry's, its path within 0.1 % of the odometry's, its raw map crisper than both peers on every draw, "
        f"the whole run within {MINUTES_LIMIT.value:g} minutes):\n" + real_targets.format_targets(results),
        flush=True,
    )
    print(f"written to {harness.OUT.value}", flush=True)


if __name__ == "__main__":
    reexec_with_huge_page_malloc()
    app.run(main)
