"""Synthetic LiDAR sequences with exact ground truth (Open3D ray casting): the scenes (`scene`), the routes
(`routes`), the spinning sensor (`lidar`), the generator and its defaults (`generator`), and drifted copies of real
sequences as pseudo ground truth (`pseudo_gt`)."""
