"""The input layout of HBA (hierarchical LiDAR bundle adjustment, github.com/hku-mars/HBA), the classical LiDAR BA
the paper compares with:

    ROOT/pcd/0.pcd, 1.pcd, ...   one scan per pose, in the frame whose pose pose.json gives (HBA transforms each
                                 point by its scan's pose: source/hba.cpp, cut_voxel); names may be zero-padded
                                 (HBA's pcd_name_fill_num, e.g. 00000.pcd), as long as they are 0, 1, 2, ...
    ROOT/pose.json               one pose per line, 'tx ty tz qw qx qy qz' (poses.read_hba_poses), no stamps

Scans and poses correspond by index (HBA loads pcd/<i>.pcd for pose i). There are no timestamps, so keyframes can
only be chosen by distance/angle (config.data.keyframe_distance_m / keyframe_angle_deg), and a ground truth given
with data.gt_poses_path is matched by order. Note that HBA overwrites ROOT/pose.json with its own result.
"""

from __future__ import annotations

import os

from neld_jax.data.layout import (
    LoadOptions,
    align_poses,
    build_sequence,
    check_root,
    config_root,
    list_scans,
    load_options,
    with_explicit_ground_truth,
)
from neld_jax.data.poses import read_hba_poses
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

SCAN_FOLDER = "pcd"
POSE_FILE = "pose.json"


def load_hba(root: str | os.PathLike, options: LoadOptions = LoadOptions()) -> Sequence:
    """Load the layout of this module's docstring (scans, poses; no stamps; the layout has no ground truth), with
    the settings of options (layout.LoadOptions): options.gt_poses_file / gt_map_file, when set, give the ground
    truth (matched by order: the layout has no stamps; layout.with_explicit_ground_truth); scan_frame is not read.

    A scan name that is not an index, an index missing from 0..S-1, or a pose count other than the scan count
    is a DataError naming the file (options.drop_unmatched_tail: see layout.align_poses)."""
    root = check_root(root)
    files = [f for f in list_scans(root / SCAN_FOLDER)]
    indexed = {}
    for f in files:
        if f.suffix.lower() != ".pcd" or not f.stem.isdigit():
            raise DataError(f"{f}: HBA scans are named by their index (0.pcd, 1.pcd, ... or zero-padded)")
        if int(f.stem) in indexed:
            raise DataError(f"{f}: the same index as {indexed[int(f.stem)].name}")
        indexed[int(f.stem)] = f
    missing = sorted(set(range(len(indexed))) - set(indexed))
    if missing:
        raise DataError(
            f"{root / SCAN_FOLDER}: scan index {missing[0]} is missing ({len(indexed)} scans, highest "
            f"index {max(indexed)}); HBA reads pcd/<i>.pcd for pose i"
        )
    files = [indexed[i] for i in range(len(indexed))]
    pose_file = root / POSE_FILE
    poses = read_hba_poses(pose_file)
    aligned = align_poses(
        poses, None, pose_file, files, None, drop_unmatched_tail=options.drop_unmatched_tail, root=root
    )
    files = [files[i] for i in aligned.scan_indices]
    seq = build_sequence(root, files, aligned.poses, None, None, pose_file)
    return with_explicit_ground_truth(seq, root, options)


def load(data_cfg) -> Sequence:
    """data.format = 'hba': load_hba(data.root) with layout.load_options (data.drop_unmatched_tail,
    data.gt_poses_path / gt_map_path ...)."""
    return load_hba(config_root(data_cfg, "hba"), load_options(data_cfg))
