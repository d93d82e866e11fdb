"""Writers of files in published layouts that only fixtures need (the package reads these layouts, never writes
them): a Newer College ground-truth CSV and a ROS1 .bag of Ouster-style PointCloud2 sweeps."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neld_jax.data.bags.rosbag_import import POINTFIELD_TYPES
from neld_jax.data.poses import rotation_to_quat

NEWER_COLLEGE_HEADER = "#sec,nsec,x,y,z,qx,qy,qz,qw"


def write_newer_college_csv(path: str | os.PathLike, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write timestamps: [S] and poses: [S, 4, 4] in the Newer College CSV layout (with header)."""
    path = Path(path)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    assert poses.shape == (len(timestamps), 4, 4), (timestamps.shape, poses.shape)
    quaternions = rotation_to_quat(poses[:, :3, :3])
    lines = [NEWER_COLLEGE_HEADER]
    for t, pose, q in zip(timestamps, poses, quaternions):
        sec = int(np.floor(t))
        nsec = int(round((t - sec) * 1e9))
        if nsec >= 1_000_000_000:
            sec, nsec = sec + 1, nsec - 1_000_000_000
        numbers = ",".join(repr(float(v)) for v in (*pose[:3, 3], *q))
        lines.append(f"{sec},{nsec},{numbers}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# The Ouster driver's point: x, y, z (padded to 16 bytes), intensity, t (ns since the sweep's start), reflectivity,
# ring, ambient, range; (name, offset, PointField datatype). 48 bytes a point with the driver's alignment.
OUSTER_FIELDS = (
    ("x", 0, 7),
    ("y", 4, 7),
    ("z", 8, 7),
    ("intensity", 16, 7),
    ("t", 20, 6),
    ("reflectivity", 24, 4),
    ("ring", 26, 4),
    ("ambient", 28, 4),
    ("range", 32, 6),
)
OUSTER_POINT_STEP = 48


def _ouster_cloud(store, stamp_ns: int, frame_id: str, points: np.ndarray, times: np.ndarray | None, rows: int):
    """One PointCloud2 of the Ouster layout; organised (height = rows) when rows divides the point count. No `t`
    field when times is None."""
    n = points.shape[0]
    height = rows if rows > 1 and n % rows == 0 else 1
    fields = [f for f in OUSTER_FIELDS if times is not None or f[0] != "t"]
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": ["<" + POINTFIELD_TYPES[f[2]] for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": OUSTER_POINT_STEP,
        }
    )
    data = np.zeros(n, dtype=dtype)
    for i, axis in enumerate("xyz"):
        data[axis] = points[:, i]
    if times is not None:
        data["t"] = np.round(np.asarray(times, dtype=np.float64) * 1e9).astype(np.uint32)
    data["ring"] = np.arange(n) % max(height, 1)
    with np.errstate(invalid="ignore", over="ignore"):
        distance = np.linalg.norm(points, axis=1)
    data["range"] = np.round(np.where(np.isfinite(distance), np.clip(distance, 0, 4e6), 0) * 1e3)  # mm, 0: none
    types = store.types
    point_field = types["sensor_msgs/msg/PointField"]
    header = types["std_msgs/msg/Header"](
        seq=0,
        stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame_id,
    )
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=height,
        width=n // height,
        fields=[point_field(name=name, offset=offset, datatype=datatype, count=1) for name, offset, datatype in fields],
        is_bigendian=False,
        point_step=OUSTER_POINT_STEP,
        row_step=OUSTER_POINT_STEP * (n // height),
        data=data.view(np.uint8).reshape(-1),
        is_dense=False,
    )


def write_lidar_bag(
    bag: str | os.PathLike, topic: str, frame_id: str, timestamps, scans, point_times=None, rows: int = 1
) -> Path:
    """Write a ROS1 .bag with one sensor_msgs/PointCloud2 per scan on `topic`, laid out as the Ouster driver's
    clouds (OUSTER_FIELDS), header stamp = bag time = the scan's timestamp.

    timestamps: [S] seconds; scans: S arrays [N_i, 3] (sensor frame; NaN or (0, 0, 0) points are written as
    they are); point_times: S arrays [N_i] seconds after the stamp (written as uint32 ns in `t`), or None for
    clouds without a time field; rows: the clouds' height when it divides N_i (organised clouds), else 1.
    Returns the bag's path (overwritten when it exists)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    bag = Path(bag)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    assert len(scans) == timestamps.shape[0] and (point_times is None or len(point_times) == len(scans))
    store = get_typestore(Stores.ROS1_NOETIC)
    bag.parent.mkdir(parents=True, exist_ok=True)
    if bag.exists():
        bag.unlink()
    msgtype = "sensor_msgs/msg/PointCloud2"
    with Writer(bag) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=store)
        for i in np.argsort(timestamps, kind="stable"):
            sec = int(np.floor(timestamps[i]))  # whole seconds apart: t * 1e9 alone loses ~100 ns to rounding
            stamp_ns = sec * 1_000_000_000 + int(np.rint((timestamps[i] - sec) * 1e9))
            points = np.asarray(scans[i], dtype=np.float64).reshape(-1, 3)
            times = None if point_times is None else point_times[i]
            msg = _ouster_cloud(store, stamp_ns, frame_id, points, times, rows)
            writer.write(connection, stamp_ns, store.serialize_ros1(msg, msgtype))
    return bag
