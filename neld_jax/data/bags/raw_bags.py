"""Raw LiDAR sweeps straight from a rosbag: one sensor_msgs/PointCloud2 topic, every message a scan in the cloud's
own (sensor) frame, with each point's time within the sweep; no poses (load_sequence makes them from the scans).

    read_lidar_bag(bag, topic)             -> RawSweeps (stamps, scans, per-point times, frame, counts)
    sweeps_sequence(root, sweeps, options) -> Sequence with poses=None and the ground truth matched to the stamps

Per-point time comes from the cloud's own field table (rosbag_import.cloud_point_times: Ouster `t`, uint32 ns
since the sweep's start; Velodyne/Hesai `time`, float32 seconds relative; `timestamp`, float64 absolute seconds)
and is stored as seconds after the message's header stamp. A topic whose clouds have none of these gives point_times
None for the whole sequence (logged once): the scans are then taken as rigid.

Points with NaN/inf coordinates or exactly at (0, 0, 0) (no return: organised Ouster clouds hold many) are dropped
with their times and counted (scans.valid_points). A cloud left with no point is skipped and counted. Messages are
ordered by header stamp, so the parts of a split recording can be given in any order.

The PointCloud2 decoding is rosbag_import's (cloud_sweep); `rosbags` is imported inside the functions,
so the data layer imports without it.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neld_jax.data.bags.rosbag_import import (
    CLOUD_TYPES,
    TIME_FIELDS,
    as_bag_paths,
    cloud_sweep,
    list_topics,
    open_bag_reader,
    stamp_seconds,
    time_field_of,
    topic_connections,
)
from neld_jax.data.layout import LoadOptions, first_existing, matched_ground_truth
from neld_jax.data.scan_source import LazyScans
from neld_jax.data.scans import read_scan, valid_points
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)


@dataclass
class RawSweeps:
    """What read_lidar_bag read: S sweeps of one topic, in header-stamp order.

    timestamps:  [S] float64 header stamps, seconds
    scans:       S arrays [N_i, 3] float64, the cloud's frame, invalid points dropped: read again from the bag when
                 used (BagClouds), so that a long recording is never in memory whole
    point_times: S arrays [N_i] float64 seconds after the scan's stamp (read with the scans), or None (no time field)
    labels:      S names "<bag file>:<topic>#<index of the message in that bag's topic>"
    frame_id:    the clouds' header.frame_id (of the first cloud)
    time_field:  the field the times came from ('' when none)
    dropped:     points dropped: {'non-finite': ..., 'zero': ...}; empty_skipped: clouds with no valid point
    """

    bag: list[str]
    topic: str
    timestamps: np.ndarray
    scans: LazyScans | list
    point_times: LazyScans | list | None
    labels: list[str]
    frame_id: str = ""
    time_field: str = ""
    clouds_read: int = 0
    empty_skipped: int = 0
    dropped: dict = field(default_factory=lambda: {"non-finite": 0, "zero": 0})


class BagClouds(LazyScans):
    """The clouds of one topic read again from the bag(s) when used: item i is (points [N_i, 3] float64 without the
    invalid ones, per-point times [N_i] or None) of the message at entries[i] = (its connection's place among the
    topic's connections, its bag time in ns, its place among that connection's messages of that time). The bag is
    opened at the first access and kept open. Re-reading rather than a copy of the sweeps on disk: a bag indexes
    its messages by time, so one is found without reading the others, and nothing is written beside the data."""

    def __init__(self, paths: list[Path], topic: str, entries: list[tuple[int, int, int]]):
        super().__init__(len(entries))
        self.paths, self.topic, self.entries = paths, topic, entries
        self._reader, self._connections = None, None

    def _make(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        if self._reader is None:
            self._reader = open_bag_reader(self.paths)
            label = ", ".join(str(p) for p in self.paths)
            self._connections = topic_connections(self._reader, self.topic, CLOUD_TYPES, label, "cloud")
        which, bag_time, place = self.entries[i]
        found = (
            raw
            for _, _, raw in self._reader.messages(
                connections=[self._connections[which]], start=bag_time, stop=bag_time + 1
            )
        )
        raw = next(r for k, r in enumerate(found) if k == place)
        msg = self._reader.deserialize(raw, self._connections[which].msgtype)
        points, point_times = cloud_sweep(msg, stamp_seconds(msg.header))
        keep, counts = valid_points(points)
        if not counts["total"]:
            return points, point_times
        return points[keep], None if point_times is None else point_times[keep]

    def __del__(self):
        if self._reader is not None:
            self._reader.close()


# --------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------


def read_lidar_bag(bag: str | os.PathLike | list, topic: str) -> RawSweeps:
    """Every cloud of `topic` in `bag` (a ROS1 .bag, a ROS2 bag folder, or a list of the parts of one recording)
    as raw sweeps (module docstring). Each cloud is read once here, checked and counted, and read again from the bag
    when used (BagClouds). Raises DataError, one line naming the bag: a bag that does not exist or cannot be read,
    a missing topic (listing the bag's topics), a topic that is not PointCloud2, a cloud without x/y/z (naming the
    message), no cloud with a valid point."""
    paths = as_bag_paths(bag)
    label = ", ".join(str(p) for p in paths)
    sweeps = RawSweeps(
        bag=[str(p) for p in paths], topic=topic, timestamps=np.zeros(0), scans=[], point_times=None, labels=[]
    )
    reader = open_bag_reader(paths)
    try:
        stamps, entries, no_time_fields = _scan_clouds(reader, topic, paths, sweeps)
    finally:
        reader.close()
    if not entries:
        raise DataError(f"{label}: no cloud on {topic} has a valid point ({sweeps.clouds_read} read)")
    order = np.argsort(stamps, kind="stable")  # parts of a split recording, given in any order
    sweeps.timestamps = np.asarray(stamps, dtype=np.float64)[order]
    sweeps.labels = [sweeps.labels[i] for i in order]
    clouds = BagClouds(paths, topic, [entries[i] for i in order])
    sweeps.scans = clouds.map(lambda _, cloud: cloud[0])
    if no_time_fields:
        sweeps.time_field = ""
        logger.warning(
            "%s: the clouds on %s carry no per-point time (none of the fields %s; %s): the scans are taken as rigid",
            label,
            topic,
            ", ".join(TIME_FIELDS),
            no_time_fields,
        )
    else:
        sweeps.point_times = clouds.map(lambda _, cloud: cloud[1])
    dropped = sweeps.dropped["non-finite"] + sweeps.dropped["zero"]
    logger.info(
        "%s: read %d sweeps of %s (frame '%s', per-point time from '%s'); dropped %d points (%d NaN/infinite, "
        "%d at (0, 0, 0), i.e. no return) and %d clouds with no valid point; the sweeps are read again from "
        "the bag when used",
        label,
        len(entries),
        topic,
        sweeps.frame_id,
        sweeps.time_field or "none",
        dropped,
        sweeps.dropped["non-finite"],
        sweeps.dropped["zero"],
        sweeps.empty_skipped,
    )
    return sweeps


def _scan_clouds(reader, topic: str, paths: list[Path], sweeps: RawSweeps):
    """Read every cloud of topic once (checked, counted into sweeps: frame, time field, drops, labels), keeping none
    of its points. Returns (stamps [S], BagClouds entries [S], a description of a cloud without time fields or '')."""
    label = ", ".join(str(p) for p in paths)
    connections = topic_connections(reader, topic, CLOUD_TYPES, label, "cloud")
    stamps, entries, no_time_fields = [], [], ""
    per_bag: dict[str, int] = {}
    per_time: dict[tuple[int, int], int] = {}
    for conn, bag_time, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, conn.msgtype)
        stamp = stamp_seconds(msg.header)
        owner = Path(getattr(conn.owner, "path", paths[0])).name
        index = per_bag.get(owner, 0)
        per_bag[owner] = index + 1
        which = next(k for k, c in enumerate(connections) if c is conn)
        place = per_time.get((which, bag_time), 0)
        per_time[(which, bag_time)] = place + 1
        name = f"{owner}:{topic}#{index:06d}"
        sweeps.clouds_read += 1
        sweeps.frame_id = sweeps.frame_id or str(msg.header.frame_id)
        try:
            points, point_times = cloud_sweep(msg, stamp)
        except ValueError as exc:
            raise DataError(f"{label}: {name} (t={stamp:.6f}): {exc}") from None
        if point_times is None and not no_time_fields:
            no_time_fields = f"{name} has fields {', '.join(f.name for f in msg.fields)}"
        sweeps.time_field = sweeps.time_field or time_field_of(msg)
        keep, counts = valid_points(points)
        sweeps.dropped["non-finite"] += counts["non-finite"]
        sweeps.dropped["zero"] += counts["zero"]
        if not keep.any():
            sweeps.empty_skipped += 1
            continue
        stamps.append(stamp)
        entries.append((which, int(bag_time), place))
        sweeps.labels.append(name)
    return stamps, entries, no_time_fields


def bags_in(root: Path, preferred: str = "") -> list[Path]:
    """The bag(s) of a sequence folder: ROOT/<preferred> when it exists, else every ROOT/*.bag (the parts of one
    recording, sorted by name; read_lidar_bag orders their messages by stamp), else []."""
    if preferred and (root / preferred).is_file():
        return [root / preferred]
    return sorted(p for p in root.glob("*.bag") if p.is_file() and not p.name.startswith("."))


def pick_topic(bag: str | os.PathLike | list, candidates: tuple[str, ...]) -> str:
    """The first of `candidates` (topics, in order of preference) that the bag has; DataError naming the bag, the
    candidates and the topics it has when none."""
    paths = as_bag_paths(bag)
    reader = open_bag_reader(paths)
    try:
        present = {c.topic for c in reader.connections}
        found = next((topic for topic in candidates if topic in present), None)
        if found is None:
            raise DataError(
                f"{', '.join(str(p) for p in paths)}: no LiDAR topic ({' or '.join(candidates)}) in "
                f"the bag; it has: {list_topics(reader)}"
            )
        return found
    finally:
        reader.close()


def sweeps_sequence(root: Path, sweeps: RawSweeps, options: LoadOptions) -> Sequence:
    """The Sequence of raw sweeps: poses None, timestamps, point_times, files = the sweeps' labels, and the ground
    truth options.gt_poses_file (None: none) matched to the scan stamps as the folder loaders match it
    (layout.matched_ground_truth: nearest stamp within options.tol after adding options.gt_time_offset_s, then
    moved into the scan frame by options.gt_from_scan T_G_S [4, 4]). The GT map: options.gt_map_file, else
    ROOT/gt_map.pcd|ply when present. options (layout.LoadOptions) come with the format's defaults resolved."""
    gt_poses = None
    if options.gt_poses_file is not None:
        # The labels stand for files in the messages of the matching (a scan without ground truth is named).
        gt_poses = matched_ground_truth(
            root,
            [root / label for label in sweeps.labels],
            sweeps.timestamps,
            options.gt_poses_file,
            options.tol,
            options.gt_from_scan,
            options.gt_time_offset_s,
        )
    gt_map_file = options.gt_map_file or first_existing(root, ("gt_map.pcd", "gt_map.ply"))
    return Sequence(
        scans=sweeps.scans,
        poses=None,
        timestamps=sweeps.timestamps,
        gt_poses=gt_poses,
        gt_map=None if gt_map_file is None else read_scan(gt_map_file),
        name=root.name,
        source=str(root),
        files=sweeps.labels,
        point_times=sweeps.point_times,
    )
