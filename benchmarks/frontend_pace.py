#!/usr/bin/env python
"""The front-end's odometry against the sensor's pace: seconds per sweep and accuracy of KISS-ICP's settings.

    python benchmarks/frontend_pace.py --kitti=/work/data/kitti00/kitti/dataset/sequences/00 --car_scans=200

For each sequence (KITTI odometry in its layout, read lazily as a run reads it; --car_scans raw sweeps of the
synthetic car, 64 x 1024 rays with per-point times, written once to --work_dir in the generic layout) and each
variant (VARIANTS: KISS-ICP's convergence criterion, its iteration cap, its voxel rule, one pass or two over raw
sweeps), the odometry (neld_jax.frontend.odometry's passes, without the global-registration check) runs twice: on
the sweeps read from their files as it goes (`read_s_per_sweep`, reading included) and on the same sweeps held in
memory (`odometry_s_per_sweep`). Then the ATE (SE(3) alignment; KITTI from frame KITTI_FIRST on: its first ground
truth poses are a constant-velocity fill) and the path-length ratio against the ground truth. `front_end` rows time
the whole front-end as a run calls it (scan_poses.with_scan_poses: the range measured, the odometry, its check).
Rigid scans (KITTI's are motion-compensated) are registered once whatever the variant's passes.
"""

import contextlib
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

KITTI = flags.DEFINE_string(
    "kitti",
    "/work/data/kitti00/kitti/dataset/sequences/00",
    "A KITTI sequence folder (velodyne/, times.txt, calib.txt; ground truth in ../../poses); empty: none.",
)
CAR_SCANS = flags.DEFINE_integer("car_scans", 200, "Raw sweeps of the synthetic car (0: none).")
WORK_DIR = flags.DEFINE_string("work_dir", "/tmp/frontend_pace", "Where the car's sweeps are written (kept).")
ONLY = flags.DEFINE_list("variants", [], "Variant names to run (empty: all).")
FRONT_END = flags.DEFINE_bool("front_end", True, "Also time the whole front-end (check included).")

KITTI_FIRST = 15
CAR = {"route": "car", "num_beams": 64, "num_columns": 1024, "max_range_m": 80.0, "seed": 0}
CAR_SPEED_MPS = 11.0  # the route's length follows from the sweeps at 10 Hz
# name: (passes over raw sweeps, first pass's convergence, convergence, max iterations, voxel per range,
# deskewing in one pass: "kiss_icp" (its own, by the last motion) or "none")
VARIANTS = {
    "current (2 passes, 1e-3 then 1e-4)": (2, 1e-3, 1e-4, 500, 0.01, None),
    "2 passes, 1e-3": (2, 1e-3, 1e-3, 500, 0.01, None),
    "2 passes, 1e-3, 10 iterations": (2, 1e-3, 1e-3, 10, 0.01, None),
    "2 passes, 1e-3, voxel 1.5 % of range": (2, 1e-3, 1e-3, 500, 0.015, None),
    "1 pass, 1e-3, KISS-ICP's deskewing": (1, None, 1e-3, 500, 0.01, "kiss_icp"),
    "1 pass, 1e-3, not deskewed": (1, None, 1e-3, 500, 0.01, "none"),
}


@contextlib.contextmanager
def kiss_icp_settings(first_convergence, convergence, iterations, voxel_per_range):
    """Within: every KISS-ICP the odometry makes has these settings, the first one made (a first pass) its
    first_convergence where given."""
    from neld_jax.frontend import odometry

    real, made = odometry.kiss_icp_config, []

    def config(min_range_m, max_range_m, deskew):
        c = real(min_range_m, max_range_m, deskew)
        first = not made and first_convergence is not None
        made.append(1)
        c.registration.convergence_criterion = float(first_convergence if first else convergence)
        c.registration.max_num_iterations = int(iterations)
        c.mapping.voxel_size = voxel_per_range * float(max_range_m)
        return c

    saved = {name: getattr(odometry, name) for name in ("FIRST_PASS_CONVERGENCE",) if hasattr(odometry, name)}
    odometry.kiss_icp_config = config
    for name in saved:  # the code this was written against set the first pass's criterion itself
        setattr(odometry, name, first_convergence if first_convergence is not None else convergence)
    try:
        yield
    finally:
        odometry.kiss_icp_config = real
        for name, value in saved.items():
            setattr(odometry, name, value)


def variant_poses(variant, scans, point_times, stamps, ranges):
    """The variant's odometry over scans [S] x [N_i, 3] (point_times [S] x [N_i] or None): poses [S, 4, 4] at the
    stamps [S], scan 0 at the identity."""
    import numpy as np

    from neld_jax.frontend import odometry

    passes, first, convergence, iterations, voxel, one_pass_deskew = variant
    labels = [str(i) for i in range(len(scans))]
    two_passes = passes == 2 and point_times is not None
    with kiss_icp_settings(first if two_passes else None, convergence, iterations, voxel):
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

    return {
        "ate_m": round(metrics.ate(poses[first:], gt[first:])["translation_rmse_m"], 4),
        "path_ratio": round(float(metrics.path_length_ratio(poses[first:], gt[first:])), 4),
    }


def load(name: str):
    """(data config, the Sequence as a run reads it (lazy), first frame evaluated)."""
    from neld_jax.config import from_file
    from neld_jax.data import formats

    if name == "kitti":
        config = from_file(os.path.join(harness.REPO, "configs", "kitti.py"))
        config.data.root, first = KITTI.value, KITTI_FIRST
    else:
        config = from_file(os.path.join(harness.REPO, "configs", "generic.py"))
        config.data.root, first = car_root(), 0
    return config, formats.read_sequence(config.data), first


def car_root() -> str:
    """The car's raw sweeps in the generic layout under --work_dir, written once."""
    import json

    from neld_jax.synthetic.generator import make_sequence, write_generic

    spec = {**CAR, "num_scans": CAR_SCANS.value, "route_length_m": max(100.0, CAR_SPEED_MPS * CAR_SCANS.value / 10)}
    root = os.path.join(WORK_DIR.value, f"car_{CAR_SCANS.value}")
    marker = os.path.join(root, "spec.json")
    if not (os.path.exists(marker) and json.load(open(marker)) == spec):
        write_generic(make_sequence(spec), root)
        with open(marker, "w") as f:
            json.dump(spec, f)
    return root


def timed(function, *args) -> tuple:
    started = time.perf_counter()
    out = function(*args)
    return out, time.perf_counter() - started


def sequence_rows(name: str, variants: dict) -> dict:
    import numpy as np

    from neld_jax.frontend import odometry, scan_poses

    config, seq, first = load(name)
    stamps = seq.timestamps
    ranges = (odometry.kiss_icp_default_ranges()[0], odometry.sensor_range_m(seq.scans))
    held, read_s = timed(lambda: [np.asarray(s, np.float64) for s in seq.scans])
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
        poses, with_reading = timed(variant_poses, variant, seq.scans, seq.point_times, stamps, ranges)
        again, alone = timed(variant_poses, variant, held, held_times, stamps, ranges)
        row = {
            "read_s_per_sweep": round(with_reading / seq.num_scans, 4),
            "odometry_s_per_sweep": round(alone / seq.num_scans, 4),
            **accuracy(poses, seq.gt_poses, first),
            "same_poses_from_memory": bool(np.allclose(poses, again, atol=1e-6)),
            "load_average": [round(v, 2) for v in os.getloadavg()],
        }
        out["variants"][label] = row
        print(name, label, row, flush=True)
    if FRONT_END.value:
        config.data.max_range_m = 1000.0  # the crop does not matter here: the odometry's own range does
        result, seconds = timed(scan_poses.with_scan_poses, seq, config.data, name != "kitti", False)
        out["front_end"] = {
            "s_per_sweep": round(seconds / seq.num_scans, 4),
            **accuracy(result.poses, seq.gt_poses, first),
            "load_average": [round(v, 2) for v in os.getloadavg()],
        }
        print(name, "front_end", out["front_end"], flush=True)
    return out


def main(argv):
    del argv
    variants = {k: v for k, v in VARIANTS.items() if not ONLY.value or k in ONLY.value}
    names = (["kitti"] if KITTI.value else []) + (["car"] if CAR_SCANS.value > 0 else [])
    out = {
        "variants": {
            k: dict(
                zip(
                    (
                        "passes",
                        "first_pass_convergence",
                        "convergence",
                        "max_iterations",
                        "voxel_per_range",
                        "one_pass_deskew",
                    ),
                    v,
                )
            )
            for k, v in variants.items()
        },
        "sequences": {},
    }
    stamped = harness.write(harness.OUT.value, out)
    for name in names:
        out["sequences"][name] = sequence_rows(name, variants)
        harness.write(harness.OUT.value, out, stamped=stamped)


if __name__ == "__main__":
    harness.default_out(os.path.join(harness.REPO, "benchmarks", "results", "frontend_pace_cpu.json"))
    app.run(main)
