"""Rosbags in, without ROS: one cloud topic and one odometry topic of a bag -> the generic layout.

    OUT/scans/000000.pcd ...   one cloud per kept message, in the cloud's own frame (header.frame_id)
    OUT/poses.txt              TUM, one line per scan: the odometry pose matched to that scan, at the scan's stamp
    OUT/import.json            what was read: bag, topics, the clouds' frame, tolerance, counts (kept, dropped)

Without odometry (odometry_topic='', or the default FAST-LIO2 topic absent from the bag), the clouds are raw
sweeps: no poses.txt is written (training makes the poses with KISS-ICP) and the layout keeps what the poses would
have carried, plus each point's time within its sweep:

    OUT/scans/<stamp>.pcd        named by the cloud's header stamp (%.9f seconds), the only place the stamp is kept
    OUT/point_times/<stamp>.npy  [N] float64 seconds after the stamp, in the order of the points in the .pcd (from
                                 the cloud's t / time / timestamp field; none written for clouds without one)

The times sit in their own folder because scans/ takes any .npy as a scan; a file per scan keeps memory flat
while importing and pairs with its scan by name (generic.load_generic reads them when every scan has one). The
points are rounded to float32 and filtered again before writing, so the .pcd reads back exactly these points.

Reads ROS1 .bag files and ROS2 bag folders with `rosbags.highlevel.AnyReader` (the `rosbags` package; no ROS
installation). The layout is the one `generic.load_generic` reads (docs/design.md, "Data on disk").

Clouds: sensor_msgs/PointCloud2; x, y, z are decoded from the message's own field table (offset, datatype,
endianness, point_step, row_step), so organised (height > 1, Ouster) and padded clouds read as well as dense
ones. Points with NaN/inf coordinates or exactly at (0, 0, 0) (no return) are skipped and counted.

Poses: nav_msgs/Odometry (pose.pose) or geometry_msgs/PoseStamped (pose), the pose of the cloud's frame in
the odometry's world frame (sensor -> world), matched to each cloud by header stamp: the nearest odometry
stamp within `tolerance_s` (DEFAULT_TOLERANCE_S). A cloud with no odometry stamp that close is never given a
neighbour's pose: the import stops with an error naming it (its message index and stamp), or, with
`drop_unmatched=True`, drops it and says how many were dropped.

Time conventions (each source states its own; the importer does not shift stamps unless told to):
  - FAST-LIO2 stamps /cloud_registered_body and /Odometry with the same `lidar_end_time` (the END of the
    scan), frames "body" (the IMU) and "camera_init" -> "body": laserMapping.cpp, publish_frame_body and
    publish_odometry (github.com/hku-mars/FAST_LIO, src/laserMapping.cpp). The stamps are equal, so a
    tolerance of 10 ms is generous; the body-frame clouds and the odometry describe the same frame. (Its PCD
    saving, pcd_save_en, accumulates world-frame points into scans_N.pcd, and its pos_log.txt holds time since
    start, rotation vector, position, ...: neither is per-scan clouds or TUM, hence recording the topics.)
  - Raw driver clouds (e.g. Ouster's /os_cloud_node/points) are stamped by the driver, commonly at the START
    of the sweep; against end-of-scan odometry use `time_offset_s` (+ one scan period, e.g. 0.1 s at 10 Hz).
    `time_offset_s` is added to every cloud stamp before matching, and the shifted stamp is written.

Keyframes at import time (optional): `stride` keeps every k-th matched cloud; `keyframe_distance_m` /
`keyframe_angle_deg` keep a cloud only when it moved or turned that far since the last kept one (the rule of
`preprocess.select_keyframes`, applied while reading, so the bag is read once and unkept clouds never hit the
disk). Training can still select keyframes later (config.data.keyframe_*).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from neld_jax.data.generic import POINT_TIMES_FOLDER
from neld_jax.data.poses import make_poses, write_tum
from neld_jax.data.scans import drop_invalid_points, valid_points, write_scan
from neld_jax.data.timing import nearest_times
from neld_jax.errors import DataError
from neld_jax.geometry import moved_enough

logger = logging.getLogger(__name__)

DEFAULT_CLOUD_TOPIC = "/cloud_registered_body"  # FAST-LIO2's undistorted scan in the IMU (body) frame
DEFAULT_ODOMETRY_TOPIC = "/Odometry"  # FAST-LIO2's odometry, camera_init -> body
DEFAULT_TOLERANCE_S = 0.01
CLOUD_TYPES = ("sensor_msgs/msg/PointCloud2",)
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped")
METADATA_FILE = "import.json"
_LISTED = 5

# sensor_msgs/PointField datatypes (INT8=1 ... FLOAT64=8) as numpy types.
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_INTEGER_TYPES = (1, 2, 3, 4, 5, 6)
# Per-point time fields of common drivers, in order of preference (cloud_point_times says how each is read).
TIME_FIELDS = ("t", "time", "timestamp")


# --------------------------------------------------------------------------------------------------
# Pure decoding
# --------------------------------------------------------------------------------------------------


def stamp_seconds(header) -> float:
    """A std_msgs/Header's stamp in seconds (rosbags names the fields sec/nanosec for ROS1 and ROS2)."""
    return int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9


def cloud_fields(msg, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """A sensor_msgs/PointCloud2's scalar fields `names` -> {name: [height * width] array in the field's own
    numpy type} (every point, none dropped).

    Decoded by each field's offset and datatype within point_step, rows of row_step bytes (padding at the row
    end skipped), byte order from is_bigendian. Raises ValueError when a field is missing or not one number."""
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in names if name not in fields]
    if missing:
        raise ValueError(f"the cloud has no field {', '.join(missing)} (fields: {', '.join(fields) or 'none'})")
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for name in names:
        f = fields[name]
        if f.datatype not in POINTFIELD_TYPES or f.count != 1:
            raise ValueError(f"field {name} has datatype {f.datatype} and count {f.count}; expected one number")
        formats.append(order + POINTFIELD_TYPES[f.datatype])
    point_dtype = np.dtype(
        {
            "names": list(names),
            "formats": formats,
            "offsets": [fields[n].offset for n in names],
            "itemsize": int(msg.point_step),
        }
    )
    height, width = int(msg.height), int(msg.width)
    if height * width == 0:
        return {name: np.zeros(0, dtype=point_dtype[name].newbyteorder("=")) for name in names}
    raw = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    row_bytes = width * int(msg.point_step)
    if raw.size < (height - 1) * int(msg.row_step) + row_bytes:
        raise ValueError(f"the cloud's data holds {raw.size} bytes, fewer than its {height} x {width} points need")
    rows = np.lib.stride_tricks.as_strided(raw, shape=(height, row_bytes), strides=(int(msg.row_step), 1))
    points = np.ascontiguousarray(rows).reshape(-1).view(point_dtype)
    return {name: points[name].astype(point_dtype[name].newbyteorder("=")) for name in names}


def cloud_xyz(msg) -> np.ndarray:
    """A sensor_msgs/PointCloud2 -> its x, y, z as [height * width, 3] float64 (every point, none dropped).

    Decoded as cloud_fields does. Raises ValueError when x, y or z is missing or not scalar."""
    xyz = cloud_fields(msg, ("x", "y", "z"))
    return np.stack([xyz[n].astype(np.float64) for n in "xyz"], axis=1)


def time_field_of(msg) -> str:
    """The first of TIME_FIELDS that the cloud has, '' when none."""
    names = {f.name for f in msg.fields}
    return next((name for name in TIME_FIELDS if name in names), "")


def cloud_point_times(msg, stamp: float, name: str) -> np.ndarray:
    """The per-point times [height * width] float64 of field `name` (one of TIME_FIELDS), in seconds after
    `stamp` (the header stamp, seconds):
        t          Ouster driver: uint32 nanoseconds since the start of the sweep (a float `t`: seconds)
        time       Velodyne / Hesai drivers: float32 seconds relative to the header stamp
        timestamp  float64 absolute seconds: the stamp is subtracted
    Raises ValueError as cloud_fields does."""
    values = cloud_fields(msg, (name,))[name]
    datatype = next(f.datatype for f in msg.fields if f.name == name)
    if name == "timestamp":
        return values.astype(np.float64) - stamp
    if name == "t" and datatype in _INTEGER_TYPES:
        return values.astype(np.float64) * 1e-9
    return values.astype(np.float64)


def cloud_sweep(msg, stamp: float) -> tuple[np.ndarray, np.ndarray | None]:
    """A PointCloud2 as a raw sweep: x, y, z [N, 3] float64 and each point's time [N] in seconds after `stamp` from
    the first of TIME_FIELDS it has (None without one). Every point, none dropped; ValueError as cloud_fields."""
    time_name = time_field_of(msg)
    return cloud_xyz(msg), (cloud_point_times(msg, stamp, time_name) if time_name else None)


def as_bag_paths(bag: str | os.PathLike | list) -> list[Path]:
    """A bag, or the list of the parts of one recording, as paths."""
    return [Path(p) for p in (bag if isinstance(bag, (list, tuple)) else [bag])]


def pose_matrix(msg, msgtype: str) -> np.ndarray:
    """nav_msgs/Odometry or geometry_msgs/PoseStamped -> its pose as a 4x4 (child frame -> header frame)."""
    pose = msg.pose.pose if msgtype == "nav_msgs/msg/Odometry" else msg.pose
    p, q = pose.position, pose.orientation
    return make_poses(np.array([[p.x, p.y, p.z]]), np.array([[q.x, q.y, q.z, q.w]]))[0]


def nearest_within(times: np.ndarray, query: float, tol: float) -> int | None:
    """Index of the time in `times` [P] nearest to `query`, or None when none is within `tol` seconds."""
    if times.size == 0:
        return None
    index, gap = nearest_times(np.array([query]), times)
    return int(index[0]) if gap[0] <= tol else None


# --------------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------------


@dataclass
class ImportResult:
    """What import_bag did (also written to OUT/import.json)."""

    bag: list[str]
    cloud_topic: str
    odometry_topic: str
    frame: str  # the clouds' header.frame_id: the frame the written scans are in
    odometry_frame: str  # the odometry's header.frame_id (the world frame of poses.txt)
    tolerance_s: float
    time_offset_s: float
    clouds_read: int = 0
    scans_written: int = 0
    dropped_unmatched: int = 0
    skipped_by_keyframe_rule: int = 0
    points_written: int = 0
    points_skipped: dict = field(default_factory=lambda: {"non-finite": 0, "zero": 0})
    point_times_written: int = 0  # scans with OUT/point_times/<stamp>.npy (raw sweeps, no odometry)
    note: str = ""


def list_topics(reader) -> str:
    """A bag's topics with their types, for messages: "/a (sensor_msgs/msg/PointCloud2), /b (...)"."""
    return ", ".join(f"{c.topic} ({c.msgtype})" for c in sorted(reader.connections, key=lambda c: c.topic)) or "none"


def topic_connections(reader, topic: str, types: tuple[str, ...], bag: str, what: str):
    """The reader's connections of `topic`; DataError naming the bag when it has none (listing its topics) or when
    one carries a type not in `types` (`what` names the kind of topic in the message)."""
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        raise DataError(f"{bag}: no {what} topic '{topic}' in the bag; it has: {list_topics(reader)}")
    bad = [c.msgtype for c in found if c.msgtype not in types]
    if bad:
        raise DataError(f"{bag}: topic '{topic}' carries {bad[0]}, not a {what} ({' or '.join(types)})")
    return found


def open_bag_reader(paths: list[Path]):
    """An opened rosbags AnyReader over paths (the parts of one recording); DataError naming a bag that is missing or
    cannot be read."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    for p in paths:
        if not p.exists():
            raise DataError(f"{p}: bag does not exist")
    # ROS1 bags carry their message definitions; the Noetic store is only the fallback AnyReader asks for.
    reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS1_NOETIC))
    try:
        reader.open()
    except AnyReaderError as exc:
        raise DataError(f"{', '.join(str(p) for p in paths)}: cannot read the bag ({exc})") from exc
    return reader


@dataclass(frozen=True)
class ImportSettings:
    """What import_bag reads and keeps (module docstring): the clouds of cloud_topic with the poses of
    odometry_topic ('' for none: raw sweeps), matched within tolerance_s after adding time_offset_s to each cloud
    stamp; drop_unmatched drops the clouds without a match instead of failing; every stride-th matched cloud is kept,
    and only once it moved keyframe_distance_m or turned keyframe_angle_deg since the last kept one (0: off)."""

    cloud_topic: str = DEFAULT_CLOUD_TOPIC
    odometry_topic: str = DEFAULT_ODOMETRY_TOPIC
    tolerance_s: float = DEFAULT_TOLERANCE_S
    time_offset_s: float = 0.0
    drop_unmatched: bool = False
    stride: int = 1
    keyframe_distance_m: float = 0.0
    keyframe_angle_deg: float = 0.0

    @property
    def keyframe_rule(self) -> bool:
        return self.keyframe_distance_m > 0 or self.keyframe_angle_deg > 0


class Odometry(NamedTuple):
    """An odometry topic's poses sorted by header stamp: times [P] seconds, poses [P, 4, 4] (the clouds' frame ->
    frame, the odometry's world frame)."""

    times: np.ndarray
    poses: np.ndarray
    frame: str


def import_bag(
    bag_paths: str | os.PathLike | list,
    out_dir: str | os.PathLike,
    settings: ImportSettings = ImportSettings(),
    progress: bool = True,
) -> ImportResult:
    """Write the clouds of settings.cloud_topic with their poses from settings.odometry_topic into out_dir (module
    docstring).

    bag_paths: a ROS1 .bag file, a ROS2 bag folder, or a list of them read as one recording. Raises DataError
    naming the bag for a missing topic (listing the topics the bag has), a topic of the wrong type, a cloud
    without x/y/z, or clouds without an odometry stamp within tolerance_s (unless drop_unmatched), and when
    out_dir already holds scans (a second import would mix two recordings). odometry_topic '' (or the default
    topic absent from the bag): the raw-sweep import, no poses (module docstring); a named odometry topic that
    is missing stays an error."""
    paths = as_bag_paths(bag_paths)
    bag = ", ".join(str(p) for p in paths)
    if settings.stride < 1:
        raise DataError(f"stride must be at least 1, got {settings.stride}")
    out = Path(out_dir)
    if (out / "scans").is_dir() and any((out / "scans").iterdir()):
        raise DataError(f"{out / 'scans'}: already holds scans; import into an empty folder")

    reader = open_bag_reader(paths)
    try:
        cloud_conns = topic_connections(reader, settings.cloud_topic, CLOUD_TYPES, bag, "cloud")
        if _as_raw_sweeps(reader, settings, bag):
            result = ImportResult(
                bag=[str(p) for p in paths],
                cloud_topic=settings.cloud_topic,
                odometry_topic="",
                frame="",
                odometry_frame="",
                tolerance_s=float(settings.tolerance_s),
                time_offset_s=float(settings.time_offset_s),
            )
            return _import_sweeps(reader, cloud_conns, out, result, settings.stride, progress)
        odometry = read_odometry(reader, settings.odometry_topic, bag)
        result = ImportResult(
            bag=[str(p) for p in paths],
            cloud_topic=settings.cloud_topic,
            odometry_topic=settings.odometry_topic,
            frame="",
            odometry_frame=odometry.frame,
            tolerance_s=float(settings.tolerance_s),
            time_offset_s=float(settings.time_offset_s),
        )
        kept_times, kept_poses, unmatched = _import_matched(
            reader, cloud_conns, out, result, settings, odometry, progress
        )
    finally:
        reader.close()

    if unmatched:
        _drop_unmatched(unmatched, result, settings, odometry, bag)
    if not kept_times:
        raise DataError(f"{bag}: no cloud on {settings.cloud_topic} was kept ({result.clouds_read} read)")
    write_tum(out / "poses.txt", np.asarray(kept_times), np.asarray(kept_poses))
    result.scans_written = len(kept_times)
    _note_matched(result, settings, bag)
    return _recorded(out, result)


def _as_raw_sweeps(reader, settings: ImportSettings, bag: str) -> bool:
    """Whether the bag is imported as raw sweeps: no odometry topic named, or the default one absent (logged); a
    keyframe rule then has no poses to measure (DataError)."""
    topic = settings.odometry_topic
    if topic and (topic != DEFAULT_ODOMETRY_TOPIC or any(c.topic == topic for c in reader.connections)):
        return False
    if settings.keyframe_rule:
        raise DataError(
            f"{bag}: no odometry topic, so --keyframe_distance_m / --keyframe_angle_deg have no "
            "poses to measure; use --stride, or select keyframes when training"
        )
    logger.warning(
        "%s: no odometry (%s): importing %s as raw sweeps without poses; training makes the poses from the "
        "scans with KISS-ICP",
        bag,
        f"no topic {topic}" if topic else "--odometry_topic=''",
        settings.cloud_topic,
    )
    return True


def read_odometry(reader, topic: str, bag: str) -> Odometry:
    """Every pose of the odometry `topic`, sorted by header stamp; DataError naming the bag when the topic is
    missing, of another type or empty."""
    pose_conns = topic_connections(reader, topic, POSE_TYPES, bag, "odometry")
    stamps, poses, odometry_frame = [], [], ""
    for conn, _, raw in reader.messages(connections=pose_conns):
        msg = reader.deserialize(raw, conn.msgtype)
        stamps.append(stamp_seconds(msg.header))
        poses.append(pose_matrix(msg, conn.msgtype))
        odometry_frame = odometry_frame or str(msg.header.frame_id)
    if not stamps:
        raise DataError(f"{bag}: odometry topic '{topic}' has no messages")
    order = np.argsort(stamps, kind="stable")
    return Odometry(np.asarray(stamps)[order], np.asarray(poses)[order], odometry_frame)


def _import_matched(
    reader, cloud_conns, out: Path, result: ImportResult, settings: ImportSettings, odometry: Odometry, progress: bool
) -> tuple[list, list, list]:
    """The clouds in bag order, each matched to the odometry, kept or not, and written at once to
    OUT/scans/NNNNNN.pcd (memory stays flat); result counts what was read, skipped and written. Returns the kept
    clouds' stamps and poses [4, 4] and the (message index, stamp) of each cloud without a match."""
    from tqdm import tqdm

    bag = ", ".join(result.bag)
    kept_times, kept_poses, unmatched = [], [], []
    matched_count = 0
    total = sum(c.msgcount for c in cloud_conns)
    messages = reader.messages(connections=cloud_conns)
    for conn, _, raw in tqdm(messages, total=total, desc="clouds", unit="msg", disable=not progress):
        msg = reader.deserialize(raw, conn.msgtype)
        index = result.clouds_read
        result.clouds_read += 1
        t = stamp_seconds(msg.header) + settings.time_offset_s
        result.frame = result.frame or str(msg.header.frame_id)
        match = nearest_within(odometry.times, t, settings.tolerance_s)
        if match is None:
            unmatched.append((index, t))
            continue
        matched_count += 1
        pose = odometry.poses[match]
        if (matched_count - 1) % settings.stride or (
            kept_poses
            and settings.keyframe_rule
            and not moved_enough(kept_poses[-1], pose, settings.keyframe_distance_m, settings.keyframe_angle_deg)
        ):
            result.skipped_by_keyframe_rule += 1
            continue
        try:
            points = cloud_xyz(msg)
        except ValueError as exc:
            raise DataError(f"{bag}: {settings.cloud_topic} message {index} (t={t:.6f}): {exc}") from None
        points, dropped = drop_invalid_points(points)
        result.points_skipped["non-finite"] += dropped["non-finite"]
        result.points_skipped["zero"] += dropped["zero"]
        if points.shape[0] == 0:
            logger.warning(
                "%s: %s message %d (t=%.6f) has no valid point; skipped", bag, settings.cloud_topic, index, t
            )
            continue
        write_scan(out / "scans" / f"{len(kept_times):06d}.pcd", points)
        result.points_written += int(points.shape[0])
        kept_times.append(t)
        kept_poses.append(pose)
    return kept_times, kept_poses, unmatched


def _drop_unmatched(
    unmatched: list, result: ImportResult, settings: ImportSettings, odometry: Odometry, bag: str
) -> None:
    """The clouds without an odometry stamp within tolerance_s ((message index, stamp) each): a DataError listing
    them, or with drop_unmatched a warning and their count in result."""
    listed = ", ".join(f"message {i} (t={t:.6f})" for i, t in unmatched[:_LISTED])
    more = f", ... ({len(unmatched)} in all)" if len(unmatched) > _LISTED else ""
    message = (
        f"{bag}: {len(unmatched)} of {result.clouds_read} clouds on {settings.cloud_topic} have no "
        f"{settings.odometry_topic} stamp within {settings.tolerance_s} s: {listed}{more} (odometry covers "
        f"t={odometry.times[0]:.6f} to t={odometry.times[-1]:.6f})"
    )
    if not settings.drop_unmatched:
        raise DataError(
            message + "; pass --drop_unmatched to drop them, or --tolerance_s / --time_offset_s "
            "if the stamps follow another convention"
        )
    logger.warning("%s; dropped them (--drop_unmatched)", message)
    result.dropped_unmatched = len(unmatched)


def _note_matched(result: ImportResult, settings: ImportSettings, bag: str) -> None:
    """result.note of an import with poses: the frames of scans/ and poses.txt; a warning when the clouds are in
    the odometry's world frame (registered already, which training refuses unless told)."""
    offset = settings.time_offset_s
    result.note = (
        f"scans/ are in frame '{result.frame}' (the clouds' header.frame_id); poses.txt holds the pose of "
        f"that frame in '{result.odometry_frame}' from {result.odometry_topic}, one line per scan, at the "
        f"scan's stamp{'' if not offset else f' + {offset} s'}"
    )
    if result.frame and result.frame == result.odometry_frame:
        # FAST-LIO2's /cloud_registered: the clouds are registered already, which training refuses unless told
        result.note += (
            f"; the clouds' frame is the odometry's world frame, so the scans are registered already: "
            f"train with --config.data.scans_in_world_frame=True, or import {DEFAULT_CLOUD_TOPIC}"
        )
        logger.warning(
            "%s: %s is in '%s', the odometry's world frame: the scans are registered already "
            "(data.scans_in_world_frame=True moves them into the sensor frame for training)",
            bag,
            result.cloud_topic,
            result.frame,
        )


def _import_sweeps(reader, cloud_conns, out: Path, result: ImportResult, stride: int, progress: bool) -> ImportResult:
    """The raw-sweep import (module docstring): every stride-th cloud to OUT/scans/<stamp>.pcd with its point
    times to OUT/point_times/<stamp>.npy; no poses.txt. Returns result filled in (also written to import.json)."""
    from tqdm import tqdm

    bag = ", ".join(result.bag)
    total = sum(c.msgcount for c in cloud_conns)
    no_time, written = "", set()
    for conn, _, raw in tqdm(
        reader.messages(connections=cloud_conns), total=total, desc="clouds", unit="msg", disable=not progress
    ):
        index = result.clouds_read
        result.clouds_read += 1
        if index % stride:
            result.skipped_by_keyframe_rule += 1
            continue
        msg = reader.deserialize(raw, conn.msgtype)
        stamp = stamp_seconds(msg.header)
        t = stamp + result.time_offset_s
        result.frame = result.frame or str(msg.header.frame_id)
        try:
            points, times = cloud_sweep(msg, stamp)
        except ValueError as exc:
            raise DataError(f"{bag}: {result.cloud_topic} message {index} (t={t:.6f}): {exc}") from None
        # rounded to float32 as the .pcd stores them, then filtered: the file reads back exactly these points
        points = points.astype(np.float32).astype(np.float64)
        keep, dropped = valid_points(points)
        result.points_skipped["non-finite"] += dropped["non-finite"]
        result.points_skipped["zero"] += dropped["zero"]
        if not keep.any():
            logger.warning("%s: %s message %d (t=%.6f) has no valid point; skipped", bag, result.cloud_topic, index, t)
            continue
        name = f"{t:.9f}"
        if name in written:
            logger.warning(
                "%s: %s message %d has the stamp t=%s of an earlier cloud; skipped",
                bag,
                result.cloud_topic,
                index,
                name,
            )
            continue
        written.add(name)
        write_scan(out / "scans" / f"{name}.pcd", points[keep])
        result.points_written += int(keep.sum())
        result.scans_written += 1
        if times is None:
            no_time = no_time or f"message {index} has fields {', '.join(f.name for f in msg.fields)}"
            continue
        (out / POINT_TIMES_FOLDER).mkdir(parents=True, exist_ok=True)
        np.save(out / POINT_TIMES_FOLDER / f"{name}.npy", times[keep])
        result.point_times_written += 1
    if not result.scans_written:
        raise DataError(f"{bag}: no cloud on {result.cloud_topic} was kept ({result.clouds_read} read)")
    if no_time:
        logger.warning(
            "%s: some clouds on %s carry no per-point time (none of %s; %s): the scans will be taken as rigid",
            bag,
            result.cloud_topic,
            ", ".join(TIME_FIELDS),
            no_time,
        )
    result.note = (
        f"scans/ are raw sweeps in frame '{result.frame}' (the clouds' header.frame_id), named by their "
        f"stamp{'' if not result.time_offset_s else f' + {result.time_offset_s} s'}; "
        f"{result.point_times_written} have their point times in {POINT_TIMES_FOLDER}/; no poses.txt: "
        "training makes the poses with KISS-ICP"
    )
    return _recorded(out, result)


def _recorded(out: Path, result: ImportResult) -> ImportResult:
    """result, after writing it to OUT/import.json and logging what was written."""
    (out / METADATA_FILE).write_text(json.dumps(asdict(result), indent=2) + "\n")
    logger.info("wrote %d scans (%d points) to %s; %s", result.scans_written, result.points_written, out, result.note)
    return result
