#!/usr/bin/env python
"""Which distance travelled KITTI's own sweeps side with: the raw map of every sweep (frames FIRST-100 of a KITTI
layout) under the ground truth and under the ground truth with its path scaled about its first pose (the same
rotations and shape, the distances 0.2 % shorter or longer), for several vertical-angle corrections of the HDL-64E
(data/kitti.py corrects 0.205 deg, as KISS-ICP does):

    python benchmarks/kitti_scale.py --root=<kitti00>/kitti/dataset/sequences/00 --offsets_deg=0.205,0,0.4 \\
        --out=benchmarks/results/kitti_scale_cpu.json

The margins are the truth's mean map entropy minus the scaled path's, over query draws (negative on every draw: the
truth's length is the crisper). Each sweep is cropped to 0.5-60 m and put on a 0.1 m grid.
"""

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

ROOT = flags.DEFINE_string(
    "root", None, "A KITTI sequence folder (velodyne/, times.txt, calib.txt; poses beside).", required=True
)
OFFSETS = flags.DEFINE_list("offsets_deg", ["0.205", "0", "0.4"], "Vertical-angle corrections to try [deg].")
SCALES = flags.DEFINE_list("scales", ["0.998", "1.002"], "Path scales compared with the truth's.")
FIRST = flags.DEFINE_integer("first", 15, "The first sweep used (KITTI 00's first 14 poses are a fill).")
DRAWS = flags.DEFINE_integer("draws", 4, "Query draws of the crispness margins.")


def scaled(poses, factor: float):
    """poses [S, 4, 4] with every position moved about the first pose's by factor: [S, 4, 4]."""
    out = poses.copy()
    out[:, :3, 3] = poses[0, :3, 3] + factor * (poses[:, :3, 3] - poses[0, :3, 3])
    return out


def main(argv):
    del argv
    import types

    import ml_collections
    import numpy as np

    from neld_jax.data import kitti
    from neld_jax.data.preprocess import crop_range, voxel_downsample
    from neld_jax.judging import judge

    seq = kitti.load(ml_collections.ConfigDict({"format": "kitti", "root": ROOT.value}))
    truth = seq.gt_poses[FIRST.value :]
    # the loader's sweeps carry its correction: undone here, then each offset applied
    raw = [
        kitti.corrected_elevations(np.asarray(seq.scans[i], np.float64), -kitti.VERTICAL_ANGLE_OFFSET_DEG)
        for i in range(FIRST.value, seq.num_scans)
    ]
    eval_cfg = {"crispness_radius_m": 0.3, "crispness_queries": 20_000, "crispness_draws": DRAWS.value}
    rows = []
    for offset in map(float, OFFSETS.value):
        scans = [voxel_downsample(crop_range(kitti.corrected_elevations(s, offset), 0.5, 60.0), 0.1) for s in raw]
        methods = {"truth": truth, **{f"x{float(f):g}": scaled(truth, float(f)) for f in SCALES.value}}
        first, _ = judge.compare_maps(scans, methods, 0.3, 20_000)
        margins = judge.crispness_margins(
            types.SimpleNamespace(scans=scans), methods, eval_cfg, against="truth", first_draw=first
        )
        rows.append(
            {
                "offset_deg": offset,
                "truth_entropy": round(first["truth"]["mean_map_entropy"], 4),
                "margins": {name: margins[name] for name in methods if name != "truth"},
            }
        )
        print(rows[-1], flush=True)
    harness.write(harness.OUT.value, {"root": ROOT.value, "first": FIRST.value, "sweeps": len(raw), "offsets": rows})


if __name__ == "__main__":
    harness.default_out(None)
    app.run(main)
