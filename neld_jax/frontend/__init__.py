"""The front-end: every decision about scans that come without poses, made from the data. KISS-ICP's odometry
within the sensor's measured range (`odometry`), whether raw sweeps want deskewing and how they were timed
(`sweep_times`), the odometry checked by global registration (`odometry_check`), and FPFH + RANSAC registration
from no guess (`feature_registration`), which the baseline and the session alignment use too."""
