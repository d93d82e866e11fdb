"""Fixtures: FusionPortable and Newer College 2021 sequences as downloaded (raw LiDAR bags and the dataset's ground
truth file, in the download's folders), written from sensor-frame sweeps and ground truth, so that loading them
(fusionportable.load_fusionportable, newer_college.load_newer_college) gives back what was written.

The ground truth is given as poses of the SENSOR frame [S, 4, 4] (sensor -> world) at the scan stamps and written
as the dataset's body frame G: T_world_G = T_world_S @ inv(T_G_S), with the T_G_S that the loader applies
(ground_truth.published_offset), so the loader's T_world_G @ T_G_S is the sensor pose again.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from fixture_writers import write_lidar_bag, write_newer_college_csv

from neld_jax.data import fusionportable, newer_college
from neld_jax.data.ground_truth import published_offset
from neld_jax.data.poses import write_tum
from neld_jax.geometry import invert_poses


def _gt_body(gt_poses: np.ndarray, release: str, frame: str) -> np.ndarray:
    """Sensor-frame ground truth [S, 4, 4] -> the dataset's body frame G (module docstring)."""
    return np.asarray(gt_poses, dtype=np.float64) @ invert_poses(published_offset(release, frame))


def write_fusionportable_download(
    root: str | os.PathLike, sequence_name: str, timestamps, scans, point_times, gt_poses, rows: int = 1
) -> Path:
    """Write ROOT/sensor_data/handheld/<sequence>/<sequence>.bag (the Ouster's sweeps on
    fusionportable.LIDAR_TOPICS[0], frame ouster00) and ROOT/groundtruth/traj/<sequence>.txt (TUM).

    timestamps: [S] seconds; scans: S arrays [N_i, 3] sensor frame; point_times: S arrays [N_i] seconds after
    the stamp, or None; gt_poses: [S, 4, 4] sensor -> world at the stamps, or None (no ground truth written).
    Returns the sequence folder (the data.root to load)."""
    root = Path(root)
    folder = root / "sensor_data" / "handheld" / sequence_name
    write_lidar_bag(
        folder / f"{sequence_name}.bag",
        fusionportable.LIDAR_TOPICS[0],
        fusionportable.LIDAR_FRAME,
        timestamps,
        scans,
        point_times,
        rows=rows,
    )
    if gt_poses is not None:
        write_tum(
            root / "groundtruth" / "traj" / f"{sequence_name}.txt",
            np.asarray(timestamps, dtype=np.float64),
            _gt_body(gt_poses, "fusionportable", fusionportable.LIDAR_FRAME),
        )
    return folder


def write_newer_college_download(
    root: str | os.PathLike,
    name: str,
    timestamps,
    scans,
    point_times,
    gt_poses,
    parts: int = 1,
    rows: int = 1,
    start: str = "2021-07-01-10-37-38",
) -> Path:
    """Write a Newer College 2021 sequence `name` (e.g. quad-easy) into the folder ROOT: its bag
    <start>-<name>.bag, or `parts` bags <start>_<k>-<name>.bag of consecutive sweeps (newer_college.LIDAR_TOPIC,
    frame os_sensor), and gt-nc-<name>.csv (sec,nsec,x,y,z,qx,qy,qz,qw, the base frame).

    Arguments as write_fusionportable_download. Returns ROOT (the data.root to load)."""
    root = Path(root)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    chunks = np.array_split(np.arange(len(scans)), max(parts, 1))
    for k, chunk in enumerate(chunks):
        bag = root / (f"{start}-{name}.bag" if parts <= 1 else f"{start}_{k}-{name}.bag")
        write_lidar_bag(
            bag,
            newer_college.LIDAR_TOPIC,
            newer_college.LIDAR_FRAME,
            timestamps[chunk],
            [scans[i] for i in chunk],
            None if point_times is None else [point_times[i] for i in chunk],
            rows=rows,
        )
    if gt_poses is not None:
        write_newer_college_csv(
            root / f"gt-nc-{name}.csv", timestamps, _gt_body(gt_poses, "newer_college_2021", newer_college.LIDAR_FRAME)
        )
    return root
