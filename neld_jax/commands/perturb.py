"""neld-perturb (bin/perturb.py): copy a real sequence into the generic layout with drifted initial poses and its
recorded poses as ground truth, so that pose recovery can be measured on real scans.

    neld-perturb --config=configs/lio_keyframes.py --config.data.root=/data/HKU_1_bag \\
        --out=/tmp/HKU_1_drift --trans_m=0.05 --rot_deg=0.5 --seed=0 [--keep_tilt]
    neld-train --config=configs/generic.py:cpu --config.data.root=/tmp/HKU_1_drift

Reads any format the config names (every input scan, before keyframe selection); writes OUT/scans/%06d.pcd,
OUT/poses.txt (drifted, TUM), OUT/gt_poses.txt (the recorded poses, TUM).
"""

from absl import flags

from neld_jax.cli import main_with_config

OUT = flags.DEFINE_string("out", None, "Folder to write the perturbed copy to (generic layout).")
TRANS_M = flags.DEFINE_float("trans_m", 0.05, "Drift per scan: translation sigma per axis [m].")
ROT_DEG = flags.DEFINE_float("rot_deg", 0.5, "Drift per scan: rotation-vector sigma per axis [deg].")
SEED = flags.DEFINE_integer("seed", 0, "Seed of the random walk.")
KEEP_TILT = flags.DEFINE_bool(
    "keep_tilt",
    False,
    "Drift in position and heading only, as an IMU-aided odometry "
    "drifts (gravity keeps roll and pitch); --rot_deg is then the heading's sigma.",
)
flags.mark_flag_as_required("out")


def job(config) -> None:
    from neld_jax.judging.metrics import ate
    from neld_jax.steps.inputs import load_sequence
    from neld_jax.synthetic.generator import write_generic
    from neld_jax.synthetic.pseudo_gt import with_drift

    seq = with_drift(load_sequence(config.data), TRANS_M.value, ROT_DEG.value, SEED.value, KEEP_TILT.value)
    write_generic(seq, OUT.value)
    error = ate(seq.poses, seq.gt_poses, align="se3")
    kind = " (position and heading only)" if KEEP_TILT.value else ""
    print(
        f"wrote {seq.num_scans} scans to {OUT.value}: drift {TRANS_M.value} m / {ROT_DEG.value} deg per scan{kind} "
        f"(seed {SEED.value}), initial ATE {error['translation_rmse_m']:.3f} m, "
        f"{error['rotation_rmse_deg']:.2f} deg after SE(3) alignment"
    )


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()
