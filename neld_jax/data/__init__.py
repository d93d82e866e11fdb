"""Data handling: scan and trajectory formats, dataset loaders, preprocessing, the normalisation into the
unit cube, training rays, and a synthetic sequence with exact ground truth.

Typical use:
    seq = load_sequence(cfg.data)                      # Sequence, sensor-frame scans + initial poses
    seq = preprocess(seq, keyframe_interval_s=3.0, min_range=0.5, max_range=80.0, voxel_size=0.05)
    norm = fit_normalization(seq.scans, seq.poses)     # world -> [-1, 1]^3
    rays = build_rays(seq, norm)                       # RaySet: directions, normalised ranges, scan index
"""

from neld_jax.data.datasets import (
    Alignment,
    align_poses,
    load_fusionportable,
    load_generic,
    load_newer_college,
    load_sequence,
)
from neld_jax.data.normalize import Normalization, fit_normalization
from neld_jax.data.poses import (
    quat_to_rotation,
    read_kitti,
    read_newer_college_csv,
    read_tum,
    rotation_to_quat,
    write_kitti,
    write_newer_college_csv,
    write_tum,
)
from neld_jax.data.preprocess import crop_range, preprocess, select_keyframes, voxel_downsample
from neld_jax.data.rays import RaySet, build_rays, sample_ray_indices
from neld_jax.data.scans import read_scan, write_scan
from neld_jax.data.sequence import Sequence, check_pose_jumps, match_by_timestamp
from neld_jax.data.synthetic import default_synthetic_config, make_sequence, write_generic

__all__ = [
    "Alignment",
    "Normalization",
    "RaySet",
    "Sequence",
    "align_poses",
    "build_rays",
    "check_pose_jumps",
    "crop_range",
    "default_synthetic_config",
    "fit_normalization",
    "load_fusionportable",
    "load_generic",
    "load_newer_college",
    "load_sequence",
    "make_sequence",
    "match_by_timestamp",
    "preprocess",
    "quat_to_rotation",
    "read_kitti",
    "read_newer_college_csv",
    "read_scan",
    "read_tum",
    "rotation_to_quat",
    "sample_ray_indices",
    "select_keyframes",
    "voxel_downsample",
    "write_generic",
    "write_kitti",
    "write_newer_college_csv",
    "write_scan",
    "write_tum",
]
