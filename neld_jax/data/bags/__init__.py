"""Rosbags without ROS (the `rosbags` library): raw sweeps read straight from a bag (`raw_bags`), and a bag's cloud
and odometry topics written as the generic layout (`rosbag_import`)."""
