"""neld-make-synthetic (bin/make_synthetic.py): write the synthetic courtyard sequence of a config in the generic
layout (docs/design.md), with ground truth.

    neld-make-synthetic --config=configs/demo.py --root=/tmp/courtyard
    neld-train --config=configs/generic.py:cpu --config.data.root=/tmp/courtyard

The sequence is config.data.synthetic (seed, scans, beams, drift ...); override any of it on the command line,
e.g. --config.data.synthetic.seed=3 --config.data.synthetic.drift_trans_m=0.1.
"""

from absl import flags

from neld_jax.cli import main_with_config

ROOT = flags.DEFINE_string("root", None, "Folder to write the sequence to (scans/, poses.txt, gt_poses.txt, gt_map.pcd).")
flags.mark_flag_as_required("root")


def job(config) -> None:
    from neld_jax.data.synthetic import make_sequence, write_generic

    seq = make_sequence(config.data.synthetic)
    write_generic(seq, ROOT.value)
    print(f"wrote {seq.num_scans} scans with ground truth to {ROOT.value}")


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()
