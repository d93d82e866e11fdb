#!/usr/bin/env python
"""Lay out KITTI odometry sweeps with ground truth for the benchmarks, from files as two public repositories keep
them (the sweeps of sequence 00, frames 0-100, are in github prime-slam/sova at commit acb45b8,
evaluation/kitti/clouds/NNNNNN.bin and evaluation/kitti/poses/calib.txt; the ground truth with its times in github
ouoz/egusa, poses/00.txt: a time column, then KITTI's 12 values of camera 0's pose):

    python benchmarks/kitti_layout.py --clouds=sova/evaluation/kitti/clouds \\
        --calib=sova/evaluation/kitti/poses/calib.txt --truth=egusa/poses/00.txt --out=/data/kitti00

writes three sequences under OUT:
    kitti/dataset/sequences/00/{velodyne/NNNNNN.bin, times.txt, calib.txt}, kitti/dataset/poses/00.txt
                       as KITTI ships them (configs/kitti.py reads ROOT = kitti/dataset/sequences/00)
    generic/scans/<time>.bin, generic/gt_poses.txt
                       the same sweeps in the generic layout with no poses, named by their times, the ground truth
                       moved into the LiDAR frame (TUM): what a user with a folder of sweeps has
    every5/dataset/sequences/00/..., every5/dataset/poses/00.txt
                       every --thin-th sweep (2 Hz, about 4 m apart), renumbered, in KITTI's layout

The sweeps are copied byte for byte. Nothing is downloaded here.
"""

import os
import shutil

import numpy as np
from absl import app, flags

CLOUDS = flags.DEFINE_string("clouds", None, "Folder of KITTI .bin sweeps NNNNNN.bin (frame numbers).", required=True)
CALIB = flags.DEFINE_string(
    "calib", None, "KITTI calib.txt of the sequence (its Tr: velodyne -> camera 0).", required=True
)
TRUTH = flags.DEFINE_string(
    "truth", None, "Ground truth with times: 'time r11 .. t3' (13 numbers) per frame.", required=True
)
FIRST = flags.DEFINE_integer("first", 0, "First frame.")
LAST = flags.DEFINE_integer("last", 100, "Last frame (included).")
THIN = flags.DEFINE_integer("thin", 5, "The thinned sequence keeps every THIN-th sweep.")
OUT = flags.DEFINE_string("out", None, "Folder the three sequences go in.", required=True)


def read_truth(path: str) -> tuple[np.ndarray, np.ndarray]:
    """'time + 12 values' rows -> (times [F], camera-0 poses [F, 4, 4]); ValueError naming the file otherwise."""
    rows = np.loadtxt(path, ndmin=2)
    if rows.shape[1] != 13:
        raise ValueError(f"{path}: expected 13 numbers a line (a time, then KITTI's 3x4 pose), got {rows.shape[1]}")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows[:, 1:].reshape(-1, 3, 4)
    return rows[:, 0], poses


def read_tr(path: str) -> np.ndarray:
    """calib.txt's Tr [4, 4] (velodyne -> camera 0)."""
    for line in open(path):
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            tr = np.eye(4)
            tr[:3, :4] = np.array(values.split(), np.float64).reshape(3, 4)
            return tr
    raise ValueError(f"{path}: no 'Tr:' line")


def kitti_rows(poses: np.ndarray) -> str:
    """[F, 4, 4] -> KITTI's text, 12 values a line."""
    return "".join(" ".join(f"{v:.9e}" for v in pose[:3, :4].reshape(-1)) + "\n" for pose in poses)


def write_kitti(root: str, frames: list[int], times: np.ndarray, camera_poses: np.ndarray) -> None:
    """ROOT/dataset/sequences/00/{velodyne, times.txt, calib.txt} and ROOT/dataset/poses/00.txt for these frames
    (renumbered from 0), their times made relative to the first kept one, the poses to the first kept camera."""
    sequence = os.path.join(root, "dataset", "sequences", "00")
    os.makedirs(os.path.join(sequence, "velodyne"), exist_ok=True)
    os.makedirs(os.path.join(root, "dataset", "poses"), exist_ok=True)
    for k, frame in enumerate(frames):
        shutil.copyfile(
            os.path.join(CLOUDS.value, f"{frame:06d}.bin"), os.path.join(sequence, "velodyne", f"{k:06d}.bin")
        )
    kept = times[frames] - times[frames[0]]
    with open(os.path.join(sequence, "times.txt"), "w") as f:
        f.writelines(f"{t:.6e}\n" for t in kept)
    shutil.copyfile(CALIB.value, os.path.join(sequence, "calib.txt"))
    relative = np.linalg.inv(camera_poses[frames[0]]) @ camera_poses[frames]
    with open(os.path.join(root, "dataset", "poses", "00.txt"), "w") as f:
        f.write(kitti_rows(relative))


def write_generic(root: str, frames: list[int], times: np.ndarray, camera_poses: np.ndarray, tr: np.ndarray) -> None:
    """ROOT/scans/<time>.bin (no poses) and ROOT/gt_poses.txt (TUM, the LiDAR frame, the first sweep at the
    identity)."""
    from scipy.spatial.transform import Rotation

    os.makedirs(os.path.join(root, "scans"), exist_ok=True)
    stamps = times[frames] - times[frames[0]]
    for frame, stamp in zip(frames, stamps):
        shutil.copyfile(os.path.join(CLOUDS.value, f"{frame:06d}.bin"), os.path.join(root, "scans", f"{stamp:.6f}.bin"))
    lidar = np.linalg.inv(tr) @ camera_poses[frames] @ tr
    lidar = np.linalg.inv(lidar[0]) @ lidar
    quaternions = Rotation.from_matrix(lidar[:, :3, :3]).as_quat()  # x y z w
    with open(os.path.join(root, "gt_poses.txt"), "w") as f:
        for stamp, pose, q in zip(stamps, lidar, quaternions):
            f.write(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q)) + "\n")


def main(argv):
    del argv
    times, camera_poses = read_truth(TRUTH.value)
    tr = read_tr(CALIB.value)
    frames = list(range(FIRST.value, LAST.value + 1))
    missing = [f for f in frames if not os.path.isfile(os.path.join(CLOUDS.value, f"{f:06d}.bin"))]
    if missing or LAST.value >= len(times):
        raise SystemExit(
            f"error: {CLOUDS.value}: frames {missing[:5]} missing, or {TRUTH.value} has only {len(times)} rows"
        )
    shutil.rmtree(OUT.value, ignore_errors=True)
    write_kitti(os.path.join(OUT.value, "kitti"), frames, times, camera_poses)
    write_generic(os.path.join(OUT.value, "generic"), frames, times, camera_poses, tr)
    write_kitti(os.path.join(OUT.value, f"every{THIN.value}"), frames[:: THIN.value], times, camera_poses)
    print(
        f"written: {OUT.value}/kitti, generic, every{THIN.value} ({len(frames)} sweeps, "
        f"{len(frames[:: THIN.value])} thinned)"
    )


if __name__ == "__main__":
    app.run(main)
