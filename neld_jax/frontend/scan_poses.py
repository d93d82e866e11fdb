"""The front-end's decisions in order, for a sequence read without poses: the sensor's range measured from the
scans (odometry.registration_range_m), then whether raw sweeps want deskewing (sweep_times.with_azimuth_times, in
the layouts that may hold raw sweeps or when data.deskew says), then KISS-ICP's odometry, checked by global
registration (odometry.with_kiss_icp_poses). Each decision is logged with its evidence."""

from __future__ import annotations

from neld_jax.data.sequence import Sequence
from neld_jax.frontend import odometry, sweep_times


def with_scan_poses(seq: Sequence, data_cfg, may_be_raw_sweeps: bool, progress: bool = True) -> Sequence:
    """seq (poses None) with KISS-ICP's poses, registered within the sensor's range; its scans cropped to the
    field's data.min_range_m..max_range_m. Scans without per-point times are raw sweeps or deskewed as data.deskew
    says ("auto": measured where may_be_raw_sweeps, else registered as they are)."""
    range_m = odometry.registration_range_m(seq)
    deskew = str(data_cfg.get("deskew", sweep_times.AUTO)).lower()
    period = None
    if seq.point_times is None and (may_be_raw_sweeps or deskew != sweep_times.AUTO):
        seq = sweep_times.with_azimuth_times(seq, deskew, range_m)
        period = sweep_times.DEFAULT_PERIOD_S if seq.point_times is not None else None  # used without stamps
    return odometry.with_kiss_icp_poses(
        seq, data_cfg.min_range_m, data_cfg.max_range_m, progress, odometry_range_m=range_m, unstamped_period_s=period
    )
