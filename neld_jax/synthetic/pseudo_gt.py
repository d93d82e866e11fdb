"""Pseudo ground truth from a real sequence: its recorded poses become the ground truth, and the initial poses
are the same trajectory with odometry-like drift added (a seeded random walk per scan, in metres and degrees),
so that pose recovery can be measured on real scans. The recorded poses are only as good as the odometry
(several cm on real data), so agreement between results and map crispness remain the sharper judges.
"""

from __future__ import annotations

import dataclasses

from neld_jax.data.sequence import Sequence
from neld_jax.synthetic.generator import add_odometry_drift


def with_drift(
    seq: Sequence, trans_sigma_m: float, rot_sigma_deg: float, seed: int = 0, keep_tilt: bool = False
) -> Sequence:
    """A copy of seq whose poses drift from the recorded ones, which become gt_poses.

    Step s adds translation ~ N(0, trans_sigma_m) per axis and a rotation vector ~ N(0, rot_sigma_deg) per axis
    to the relative motion from scan s-1 (synthetic.add_odometry_drift); scan 0 keeps its pose. keep_tilt: the
    drift of an IMU-aided odometry, in position and heading only (every scan keeps its recorded up axis)."""
    drifted = add_odometry_drift(seq.poses, trans_sigma_m, rot_sigma_deg, seed, keep_tilt=keep_tilt)
    kind = "_keeptilt" if keep_tilt else ""
    return dataclasses.replace(
        seq,
        poses=drifted,
        gt_poses=seq.poses.copy(),
        name=f"{seq.name}_drift{trans_sigma_m:g}m{rot_sigma_deg:g}deg{kind}_seed{seed}",
    )
