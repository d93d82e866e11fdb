"""neld-make-synthetic (bin/make_synthetic.py): write the synthetic courtyard sequence of a config in the generic
layout (docs/design.md), with ground truth.

    neld-make-synthetic --config=configs/demo.py --root=/tmp/courtyard
    neld-train --config=configs/generic.py:cpu --config.data.root=/tmp/courtyard

The sequence is config.data.synthetic (seed, scans, beams, drift ...); override any of it on the command line,
e.g. --config.data.synthetic.seed=3 --config.data.synthetic.drift_trans_m=0.1. --rate_hz writes a LiDAR's raw
sweeps at that rate instead (the motion within each sweep, per-point times, no poses: the run makes them with
KISS-ICP), as a recording holds them:

    neld-make-synthetic --config=configs/demo.py --root=/tmp/sweeps --rate_hz=10 --config.data.synthetic.num_scans=300 \
        --config.data.synthetic.trajectory_radius_m=10 --config.data.synthetic.max_range_m=40

The routes "car" and "handheld" (data.synthetic.route) write scans named by their stamps, with ground truth and no
poses: a car's raw 10 Hz sweeps along the courtyards' route (from rest, 11 m/s on the straights, slower round the
corners; per-point times beside),
a handheld sensor's rigid 2 Hz scans turned 40-50 degrees from one to the next (--rate_hz sets another rate):

    neld-make-synthetic --config=configs/demo.py --root=/tmp/car --config.data.synthetic.route=car \
        --config.data.synthetic.num_beams=64 --config.data.synthetic.num_scans=400 \
        --config.data.synthetic.route_length_m=320 --config.data.synthetic.max_range_m=80

--session=K writes the K-th visit of the same courtyard (K = 0, 1, ...: another loop each, its own drift and noise,
the initial poses in its own frame with its first scan at the identity, the ground truth in the scene's frame shared
by every visit); several visits make one run (docs/sessions.md):

    neld-make-synthetic --config=configs/demo.py --root=/tmp/visit0 --session=0
    neld-make-synthetic --config=configs/demo.py --root=/tmp/visit1 --session=1
    neld-train --config=configs/generic.py:cpu --config.data.root=/tmp/visit0,/tmp/visit1
"""

from absl import flags

from neld_jax.cli import main_with_config

ROOT = flags.DEFINE_string(
    "root", None, "Folder to write the sequence to (scans/, poses.txt, gt_poses.txt, gt_map.pcd)."
)
flags.mark_flag_as_required("root")
RATE_HZ = flags.DEFINE_float(
    "rate_hz", 0.0, "Raw sweeps at this rate (0: one rigid scan every 3 s, with drifted initial poses)."
)
SESSION = flags.DEFINE_integer(
    "session",
    None,
    "Write the K-th visit of the scene (K >= 0): its own loop, drift and frame; ground truth in the scene's frame.",
)


def job(config) -> None:
    from neld_jax.synthetic.generator import make_sequence, write_generic

    seq = make_sequence(config.data.synthetic, rate_hz=RATE_HZ.value, session=SESSION.value)
    write_generic(seq, ROOT.value)
    if seq.point_times is not None:
        kind = f"raw {RATE_HZ.value:g} Hz sweeps (no poses)"
    else:
        kind = "scans" if seq.poses is not None else f"{config.data.synthetic.route} scans (no poses)"
    print(f"wrote {seq.num_scans} {kind} with ground truth to {ROOT.value}")


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()
