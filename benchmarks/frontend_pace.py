#!/usr/bin/env python
"""The front-end's odometry against the sensor's pace: seconds per sweep and accuracy of KISS-ICP's settings.

    python benchmarks/frontend_pace.py --kitti=/work/data/kitti00/kitti/dataset/sequences/00 --car_seeds=0,1,2

For each sequence (KITTI odometry in its layout, read lazily as a run reads it; --car_scans raw sweeps of the
synthetic car of each of --car_seeds (peers.py's car:SEED), 64 x 1024 rays with per-point times, written once to
--work_dir in the generic layout) and each variant (VARIANTS: KISS-ICP's convergence criterion, its iteration cap,
its voxel rule, one pass or two over raw sweeps), the odometry (neld_jax.frontend.odometry's passes, without the
global-registration check) runs on the sweeps read from their files as it goes (`read_s_per_sweep`, reading
included) and, with --from_memory, again on the same sweeps held in memory (`odometry_s_per_sweep`). Then the ATE
(SE(3) alignment; KITTI from KITTI_FIRST_S on: its first ground truth poses are a constant-velocity fill), the
path-length ratio and the sweep-to-sweep error against the ground truth, and the CPU seconds (all threads; less
sensitive to a shared machine's load than the wall clock); the cars' spread over their seeds (min, mean, max) in
`cars_min_mean_max`. `front_end` rows time the whole front-end as a run calls it (scan_poses.with_scan_poses: the
range measured, the odometry, its check). Rigid scans (KITTI's are motion-compensated) are registered once whatever
the variant's passes.
"""

import contextlib
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

KITTI = flags.DEFINE_list(
    "kitti",
    ["/work/data/kitti00/kitti/dataset/sequences/00"],
    "KITTI sequence folders (velodyne/, times.txt, calib.txt; ground truth in ../../poses); empty: none.",
)
CAR_SCANS = flags.DEFINE_integer("car_scans", 300, "Raw sweeps of each synthetic car (0: none).")
CAR_SEEDS = flags.DEFINE_list("car_seeds", ["0"], "The synthetic cars' seeds: one sequence car:SEED each.")
FROM_MEMORY = flags.DEFINE_bool("from_memory", True, "Also run each variant on the sweeps held in memory.")
WORK_DIR = flags.DEFINE_string("work_dir", "/tmp/frontend_pace", "Where the car's sweeps are written (kept).")
ONLY = flags.DEFINE_list("variants", [], "Variant names to run (empty: all).")
FRONT_END = flags.DEFINE_bool("front_end", True, "Also time the whole front-end (check included).")

KITTI_FIRST_S = 1.55  # KITTI 00's frame 15's stamp: its ground truth before is a constant-velocity fill
CAR = {"route": "car", "route_length_m": 320.0, "num_beams": 64, "num_columns": 1024, "max_range_m": 80.0}  # peers.py's
# name: (passes over raw sweeps, KISS-ICP's convergence, its iteration cap, voxel per range, deskewing in one pass:
# "kiss_icp" (its own, by the last motion) or "none")
VARIANTS = {
    "2 passes": (2, 1e-3, 500, 0.01, None),
    "2 passes at most 10 iterations": (2, 1e-3, 10, 0.01, None),
    "1 pass KISS-ICP's deskewing": (1, 1e-3, 500, 0.01, "kiss_icp"),
    "1 pass KISS-ICP's deskewing at most 10 iterations": (1, 1e-3, 10, 0.01, "kiss_icp"),
    "1 pass not deskewed": (1, 1e-3, 500, 0.01, "none"),
}
FIELDS = ("passes", "convergence", "max_iterations", "voxel_per_range", "one_pass_deskew")


@contextlib.contextmanager
def kiss_icp_settings(convergence, iterations, voxel_per_range):
    """Within: every KISS-ICP the odometry makes has these settings."""
    from neld_jax.frontend import odometry

    real = odometry.kiss_icp_config

    def config(min_range_m, max_range_m, deskew):
        c = real(min_range_m, max_range_m, deskew)
        c.registration.convergence_criterion = float(convergence)
        c.registration.max_num_iterations = int(iterations)
        c.mapping.voxel_size = voxel_per_range * float(max_range_m)
        return c

    odometry.kiss_icp_config = config
    try:
        yield
    finally:
        odometry.kiss_icp_config = real


def variant_poses(variant, scans, point_times, stamps, ranges):
    """The variant's odometry over scans [S] x [N_i, 3] (point_times [S] x [N_i] or None): poses [S, 4, 4] at the
    stamps [S], scan 0 at the identity."""
    import numpy as np

    from neld_jax.frontend import odometry

    passes, convergence, iterations, voxel, one_pass_deskew = variant
    labels = [str(i) for i in range(len(scans))]
    with kiss_icp_settings(convergence, iterations, voxel):
        if point_times is None:
            return odometry.kiss_icp_odometry(scans, None, labels, ranges, keep_sweeps=False)[0]
        if passes == 2:
            return odometry.two_pass_odometry(scans, point_times, stamps, labels, ranges)
        # one pass: KISS-ICP's own deskewing (its pose at the last point) or none (about the points' mean instant)
        times = point_times if one_pass_deskew == "kiss_icp" else None
        poses, _, _ = odometry.kiss_icp_odometry(scans, times, labels, ranges, keep_sweeps=False)
        if one_pass_deskew == "kiss_icp":
            offsets = np.array([float(np.max(point_times[i])) for i in range(len(scans))])
        else:
            offsets = np.array([float(np.mean(point_times[i])) for i in range(len(scans))])
        return odometry.poses_at_stamps(stamps, offsets, poses)


def accuracy(poses, gt, first: int) -> dict:
    from neld_jax.judging import metrics

    step = metrics.rpe(poses[first:], gt[first:])  # sweep to sweep: less at the mercy of one slip than the ATE
    return {
        "ate_m": round(metrics.ate(poses[first:], gt[first:])["translation_rmse_m"], 4),
        "path_ratio": round(float(metrics.path_length_ratio(poses[first:], gt[first:])), 4),
        "step_rmse_cm": round(100 * step["translation_rmse_m"], 3),
        "step_rmse_deg": round(step["rotation_rmse_deg"], 4),
    }


def load(name: str):
    """(data config, the Sequence as a run reads it (lazy), first frame evaluated) of "kitti:FOLDER" or "car:SEED"."""
    import numpy as np

    from neld_jax.config import from_file
    from neld_jax.data import formats

    kind, where = name.split(":", 1)
    if kind == "kitti":
        config = from_file(os.path.join(harness.REPO, "configs", "kitti.py"))
        config.data.root = where
        seq = formats.read_sequence(config.data)
        return config, seq, int(np.searchsorted(seq.timestamps, KITTI_FIRST_S - 1e-3))
    config = from_file(os.path.join(harness.REPO, "configs", "generic.py"))
    config.data.root = car_root(int(where))
    return config, formats.read_sequence(config.data), 0


def car_root(seed: int) -> str:
    """The car's raw sweeps (seed's) in the generic layout under --work_dir, written once."""
    import json

    from neld_jax.synthetic.generator import make_sequence, write_generic

    spec = {**CAR, "num_scans": CAR_SCANS.value, "seed": seed}
    root = os.path.join(WORK_DIR.value, f"car_{seed}_{CAR_SCANS.value}")
    marker = os.path.join(root, "spec.json")
    if not (os.path.exists(marker) and json.load(open(marker)) == spec):
        write_generic(make_sequence(spec), root)
        with open(marker, "w") as f:
            json.dump(spec, f)
    return root


def timed(function, *args) -> tuple:
    """(function(*args), wall seconds, CPU seconds of this process: all its threads, less sensitive to load)."""
    started, cpu = time.perf_counter(), time.process_time()
    out = function(*args)
    return out, time.perf_counter() - started, time.process_time() - cpu


def variant_row(variant, seq, held, held_times, ranges, first) -> dict:
    import numpy as np

    poses, with_reading, cpu = timed(variant_poses, variant, seq.scans, seq.point_times, seq.timestamps, ranges)
    row = {
        "read_s_per_sweep": round(with_reading / seq.num_scans, 4),
        "read_cpu_s_per_sweep": round(cpu / seq.num_scans, 4),
        **accuracy(poses, seq.gt_poses, first),
    }
    if FROM_MEMORY.value:
        again, alone, _ = timed(variant_poses, variant, held, held_times, seq.timestamps, ranges)
        row["odometry_s_per_sweep"] = round(alone / seq.num_scans, 4)
        row["same_poses_from_memory"] = bool(np.allclose(poses, again, atol=1e-6))
    return {**row, "load_average": [round(v, 2) for v in os.getloadavg()]}


def sequence_rows(name: str, variants: dict) -> dict:
    import numpy as np

    from neld_jax.frontend import odometry, scan_poses

    config, seq, first = load(name)
    ranges = (odometry.kiss_icp_default_ranges()[0], odometry.sensor_range_m(seq.scans))
    held, read_s, _ = timed(lambda: [np.asarray(s, np.float64) for s in seq.scans])
    held_times = None if seq.point_times is None else [np.asarray(t, np.float64) for t in seq.point_times]
    out = {
        "sweeps": seq.num_scans,
        "points_per_sweep": int(np.mean([len(s) for s in held])),
        "raw_sweeps": seq.point_times is not None,
        "registration_range_m": round(ranges[1], 2),
        "read_s_per_sweep": round(read_s / seq.num_scans, 4),
        "evaluated_from": first,
        "variants": {},
    }
    print(name, {k: v for k, v in out.items() if k != "variants"}, flush=True)
    for label, variant in variants.items():
        if seq.point_times is None and variant[0] == 1:
            continue  # rigid scans: one pass whatever the variant
        out["variants"][label] = variant_row(
            variant, seq, held if FROM_MEMORY.value else None, held_times, ranges, first
        )
        print(name, label, out["variants"][label], flush=True)
    if FRONT_END.value:
        config.data.max_range_m = 1000.0  # the crop does not matter here: the odometry's own range does
        result, seconds, cpu = timed(scan_poses.with_scan_poses, seq, config.data, not name.startswith("kitti"), False)
        out["front_end"] = {
            "s_per_sweep": round(seconds / seq.num_scans, 4),
            "cpu_s_per_sweep": round(cpu / seq.num_scans, 4),
            **accuracy(result.poses, seq.gt_poses, first),
            "load_average": [round(v, 2) for v in os.getloadavg()],
        }
        print(name, "front_end", out["front_end"], flush=True)
    return out


def spread(sequences: dict) -> dict:
    """{variant: {measure: [min, mean, max] over the cars' seeds}} of the car:SEED sequences' rows."""
    import numpy as np

    cars = [rows for name, rows in sequences.items() if name.startswith("car:")]
    out = {}
    for label in cars[0]["variants"] if cars else []:
        got = [rows["variants"][label] for rows in cars if label in rows["variants"]]
        out[label] = {
            key: [round(float(f(np.array([row[key] for row in got]))), 4) for f in (np.min, np.mean, np.max)]
            for key in (
                "ate_m",
                "path_ratio",
                "step_rmse_cm",
                "step_rmse_deg",
                "read_s_per_sweep",
                "read_cpu_s_per_sweep",
            )
        }
    return out


def main(argv):
    del argv
    variants = {k: v for k, v in VARIANTS.items() if not ONLY.value or k in ONLY.value}
    names = [f"kitti:{folder}" for folder in KITTI.value]
    names += [f"car:{seed}" for seed in CAR_SEEDS.value] if CAR_SCANS.value > 0 else []
    out = {"variants": {k: dict(zip(FIELDS, v)) for k, v in variants.items()}, "sequences": {}}
    stamped = harness.write(harness.OUT.value, out)
    for name in names:
        out["sequences"][name] = sequence_rows(name, variants)
        out["cars_min_mean_max"] = spread(out["sequences"])
        harness.write(harness.OUT.value, out, stamped=stamped)


if __name__ == "__main__":
    harness.default_out(os.path.join(harness.REPO, "benchmarks", "results", "frontend_pace_cpu.json"))
    app.run(main)
