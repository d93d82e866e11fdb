#!/usr/bin/env python
"""The ATE of each method of a peers.py result over stretches of the input sweeps, to see where a ground truth's own
errors weigh (KITTI 00's ground truth jumps 0.25 m over frames 38-46, where every LiDAR trajectory agrees on a
steady speed):

    python benchmarks/stretch_ate.py --peers=benchmarks/results/peers_kitti_cpu.json --stretches=15-37,47-100 \\
        --out=benchmarks/results/peers_kitti_stretches_cpu.json

For every sequence of the peers JSON with ground truth: its layout is loaded again with the recorded config (the
scans are not read: only the stamps and the ground truth are used), each method's poses file (the JSON's "poses")
is matched to the sweeps by stamp as peers.py matches them, and over each stretch FIRST-LAST (sweep indices,
inclusive) the SE(3)-aligned ATE, the Sim(3) scale and the path-length ratio are written.
"""

import os

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

PEERS = flags.DEFINE_string("peers", None, "A peers.py JSON file.", required=True)
STRETCHES = flags.DEFINE_list("stretches", ["15-37", "47-100"], "FIRST-LAST sweep indices, inclusive.")
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def stretch_figures(est, gt) -> dict:
    """est, gt: [K, 4, 4] matched poses -> {"ate_m", "sim3_scale", "path_ratio", "poses"}."""
    from neld_jax.judging import metrics

    return {
        "ate_m": round(metrics.ate(est, gt)["translation_rmse_m"], 4),
        "sim3_scale": round(metrics.ate(est, gt, align="sim3")["scale"], 5),
        "path_ratio": round(float(metrics.path_length_ratio(est, gt)), 5),
        "poses": len(est),
    }


def matched(path: str, loaded):
    """A TUM file's poses matched by stamp (within 0.01 s, as peers.py) to the input sweeps of `loaded`, every one of
    which has ground truth: (est [S, 4, 4], gt [S, 4, 4]) in sweep order; a ValueError where a sweep has no pose."""
    import numpy as np

    from neld_jax.data.poses import read_tum
    from neld_jax.writing.evaluate import match_poses

    stamps, poses = read_tum(path)
    est, gt, _ = match_poses(stamps, loaded.timestamps, len(poses), len(loaded.gt_poses), path, 0.01)
    if len(gt) != len(loaded.gt_poses):
        raise ValueError(f"{path}: poses for {len(gt)} of the {len(loaded.gt_poses)} sweeps with ground truth")
    order = np.argsort(gt)
    return poses[est[order]], loaded.gt_poses[gt[order]]


def main(argv):
    del argv
    from neld_jax.config import from_file
    from neld_jax.data.formats import FORMATS

    peers = harness.load(PEERS.value)
    stretches = [tuple(int(v) for v in item.split("-")) for item in STRETCHES.value]
    out = {"peers": PEERS.value, "stretches": STRETCHES.value, "sequences": []}
    for entry in peers["sequences"]:
        config = from_file(peers["config"] if os.path.isabs(peers["config"]) else os.path.join(REPO, peers["config"]))
        config.data.root = entry["root"]
        loaded = FORMATS[config.data.format](config.data)  # the layout alone: stamps and ground truth, no odometry
        if loaded.gt_poses is None:
            continue
        rows = {}
        for method, row in entry["methods"].items():
            if "poses" not in row:
                continue
            est, gt = matched(row["poses"], loaded)
            rows[method] = {f"{a}-{b}": stretch_figures(est[a : b + 1], gt[a : b + 1]) for a, b in stretches}
            print(entry["sequence"], method, rows[method], flush=True)
        out["sequences"].append({"sequence": entry["sequence"], "methods": rows})
    harness.write(harness.OUT.value, out)


if __name__ == "__main__":
    harness.default_out(None)  # no default here: the file must be named
    flags.mark_flag_as_required("out")
    app.run(main)
