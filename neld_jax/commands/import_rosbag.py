"""neld-import-rosbag (bin/import_rosbag.py): turn a rosbag (ROS1 .bag or ROS2 folder; no ROS needed) into the
generic layout that neld-train reads.

    # FAST-LIO2 recorded: body-frame clouds and odometry, both stamped at the end of the scan (the defaults)
    neld-import-rosbag --bag=fastlio_run.bag --out=/data/run
    neld-train --config=configs/generic.py:cpu --config.data.root=/data/run

    # other topics, every 2nd cloud, clouds stamped at the start of a 10 Hz sweep against end-of-scan odometry
    neld-import-rosbag --bag=rec.bag --out=/data/rec --cloud_topic=/os_cloud_node/points \\
        --odometry_topic=/odom --stride=2 --time_offset_s=0.1

    # raw driver sweeps, no odometry: scans named by stamp with their per-point times; training runs KISS-ICP
    neld-import-rosbag --bag=rec.bag --out=/data/rec --cloud_topic=/os_cloud_node/points --odometry_topic=''

Writes OUT/scans/NNNNNN.pcd (the clouds' own frame), OUT/poses.txt (TUM) and OUT/import.json (topics, frame,
counts); without odometry (--odometry_topic='' or no /Odometry in the bag) OUT/scans/<stamp>.pcd and
OUT/point_times/<stamp>.npy and no poses.txt. See neld_jax/data/bags/rosbag_import.py for the matching rule and the
time conventions.
"""

from absl import flags

from neld_jax.cli import main_with_flags
from neld_jax.data.bags import rosbag_import as ri

BAG = flags.DEFINE_multi_string(
    "bag", None, "ROS1 .bag file or ROS2 bag folder (repeat for a split recording).", required=True
)
OUT = flags.DEFINE_string("out", None, "Folder to write scans/, poses.txt and import.json to.", required=True)
CLOUD = flags.DEFINE_string("cloud_topic", ri.DEFAULT_CLOUD_TOPIC, "sensor_msgs/PointCloud2 topic.")
ODOM = flags.DEFINE_string(
    "odometry_topic",
    ri.DEFAULT_ODOMETRY_TOPIC,
    "nav_msgs/Odometry or geometry_msgs/PoseStamped topic (pose of the clouds' frame); "
    "'' for none (raw sweeps; training makes the poses with KISS-ICP).",
)
TOL = flags.DEFINE_float("tolerance_s", ri.DEFAULT_TOLERANCE_S, "Largest cloud-to-odometry stamp gap (seconds).")
OFFSET = flags.DEFINE_float("time_offset_s", 0.0, "Added to every cloud stamp before matching (seconds).")
DROP = flags.DEFINE_bool("drop_unmatched", False, "Drop clouds without odometry (counted) instead of failing.")
STRIDE = flags.DEFINE_integer("stride", 1, "Keep every k-th matched cloud.")
DIST = flags.DEFINE_float("keyframe_distance_m", 0.0, "Keep a cloud only after moving this far (0: off).")
ANGLE = flags.DEFINE_float("keyframe_angle_deg", 0.0, "... or after turning this far (0: off).")


def import_bag() -> int:
    settings = ri.ImportSettings(
        cloud_topic=CLOUD.value,
        odometry_topic=ODOM.value,
        tolerance_s=TOL.value,
        time_offset_s=OFFSET.value,
        drop_unmatched=DROP.value,
        stride=STRIDE.value,
        keyframe_distance_m=DIST.value,
        keyframe_angle_deg=ANGLE.value,
    )
    result = ri.import_bag(BAG.value, OUT.value, settings)
    if not result.odometry_topic:
        print(
            f"wrote {result.scans_written} raw sweeps of {result.clouds_read} clouds to {OUT.value} "
            f"({result.skipped_by_keyframe_rule} skipped by --stride), no poses"
        )
    else:
        print(
            f"wrote {result.scans_written} scans of {result.clouds_read} clouds to {OUT.value} "
            f"({result.dropped_unmatched} without odometry dropped, {result.skipped_by_keyframe_rule} skipped by "
            f"--stride/--keyframe_*)"
        )
    print(result.note)
    return 0


def main() -> None:
    main_with_flags(import_bag, doc=__doc__)


if __name__ == "__main__":
    main()
