"""Each point's time within its sweep, from its azimuth, for spinning-LiDAR sweeps that carry no time field (most PCD
exports of a driver's clouds, KITTI-style .bin).

A spinning LiDAR measures a point when its head faces the point's azimuth, so the point's time after the sweep's
start is the fraction of a turn from the start azimuth, in the direction the head turns, times the sweep's period.
The times are seconds after the scan's stamp, taken as the sweep's start (as an Ouster stamps a sweep), in [0, T).

The convention (SweepConvention): the sweep starts and ends behind the sensor (azimuth pi in a frame with x
forward) and the head turns clockwise seen from above, as Velodyne heads spin and as KISS-ICP's own KITTI raw loader
(kiss_icp/datasets/kitti_raw.py) stamps the points. KITTI's raw readme says its HDL-64E turns counter-clockwise, and
a raw 64-beam city drive stores each ring anticlockwise from the front; deskewing that drive by either convention
left consecutive sweeps no crisper than not deskewing (docs/datasets.md, "Sweeps without point times"), so the data
did not decide. The synthetic generator's sensor turns anticlockwise from the front (SweepConvention(0.0, False)).

What it cannot know: a head whose lasers fire at azimuth offsets of their own (the HDL-64E's reach several degrees)
gives points measured together azimuths a little apart (a few ms at 10 Hz), and a point within that offset of the
seam is given the other end of the sweep. Scans that are deskewed already look the same as raw ones: which layouts
hold raw sweeps is the layout's knowledge (formats.load_sequence derives times for the generic layout only).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.scan_source import lazy
from neld_jax.data.sequence import Sequence

logger = logging.getLogger(__name__)

DEFAULT_PERIOD_S = 0.1  # a sweep's period when the scans have no stamps: 10 Hz, the common spinning rate
# Consecutive sweeps of a spinning LiDAR come 1/40 s (40 Hz) to 1/5 s (5 Hz) apart; stamps further apart are
# keyframes, whose sweep period the stamps do not tell.
MIN_PERIOD_S, MAX_PERIOD_S = 1.0 / 40.0, 1.0 / 5.0
# A sweep spans a full turn when no azimuth sector this wide is empty (a street or a room leaves none; a sensor
# looking through a window, or scans cropped to a camera's view, do).
MAX_AZIMUTH_GAP_DEG = 20.0
MAX_SCANS_LOOKED_AT = 200  # evenly spaced scans whose median gap decides: enough, and a long recording is not read


@dataclasses.dataclass(frozen=True)
class SweepConvention:
    """Where a sweep starts and which way the head turns.

    start_azimuth_rad: the azimuth (atan2(y, x) in the sensor frame) the sweep starts and ends at
    clockwise:         the head turns clockwise seen from above (+z), i.e. towards decreasing atan2(y, x)
    """

    start_azimuth_rad: float
    clockwise: bool

    def describe(self) -> str:
        """The convention in words, for the log."""
        where = {0.0: "in front of", 0.5: "left of", 1.0: "behind", -1.0: "behind", -0.5: "right of"}.get(
            round(float(np.angle(np.exp(1j * self.start_azimuth_rad))) / np.pi, 3),
            f"at azimuth {np.degrees(self.start_azimuth_rad):.0f} deg from")
        turning = "clockwise" if self.clockwise else "anticlockwise"
        return f"starting {where} the sensor, turning {turning} seen from above"


VELODYNE = SweepConvention(start_azimuth_rad=np.pi, clockwise=True)


def turn_fractions(points: np.ndarray, convention: SweepConvention) -> np.ndarray:
    """points [N, 3] (sensor frame, x forward, z up) -> [N] in [0, 1): how far through the turn each was measured."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    turned = (convention.start_azimuth_rad - azimuth) if convention.clockwise else (
        azimuth - convention.start_azimuth_rad)
    fraction = np.mod(turned, 2.0 * np.pi) / (2.0 * np.pi)
    return np.where(fraction >= 1.0, 0.0, fraction)  # mod of a tiny negative can round up to a full turn


def azimuth_times(points: np.ndarray, period_s: float, convention: SweepConvention) -> np.ndarray:
    """points [N, 3] -> [N] seconds after the sweep's start (turn_fractions x period_s), in [0, period_s)."""
    return turn_fractions(points, convention) * float(period_s)


def largest_azimuth_gap_deg(points: np.ndarray) -> float:
    """The widest azimuth sector in degrees that holds no point of points [N, 3] (360 for fewer than two)."""
    if len(points) < 2:
        return 360.0
    azimuth = np.sort(np.arctan2(points[:, 1], points[:, 0]))
    gaps = np.diff(np.r_[azimuth, azimuth[0] + 2.0 * np.pi])
    return float(np.degrees(gaps.max()))


def sweep_period(timestamps: np.ndarray | None) -> float | None:
    """The sweep period in seconds that stamps [S] imply: their median step, DEFAULT_PERIOD_S without stamps (or
    with one), None when the step is no spinning LiDAR's period (MIN_PERIOD_S..MAX_PERIOD_S: keyframes)."""
    if timestamps is None or len(timestamps) < 2:
        return DEFAULT_PERIOD_S
    period = float(np.median(np.diff(timestamps)))
    return period if MIN_PERIOD_S <= period <= MAX_PERIOD_S else None


def with_azimuth_times(seq: Sequence, convention: SweepConvention = VELODYNE) -> Sequence:
    """seq with point_times derived from the azimuths (azimuth_times) when it has none, its stamps are consecutive
    sweeps' (sweep_period) and its median scan spans a full turn (largest_azimuth_gap_deg at most
    MAX_AZIMUTH_GAP_DEG, over at most MAX_SCANS_LOOKED_AT scans evenly spaced); else seq as it is. Either way one log
    line says which and why. The times are derived from each scan when it is used (data.scan_source)."""
    where = seq.source or seq.name
    if seq.point_times is not None or not seq.scans:
        return seq
    period = sweep_period(seq.timestamps)
    if period is None:
        logger.info("%s: the scans carry no per-point times and are %.2f s apart, not consecutive sweeps: they are "
                    "registered as they are", where, float(np.median(np.diff(seq.timestamps))))
        return seq
    picked = np.unique(np.linspace(0, seq.num_scans - 1, min(seq.num_scans, MAX_SCANS_LOOKED_AT)).round().astype(int))
    gap = float(np.median([largest_azimuth_gap_deg(seq.scans[i]) for i in picked]))
    if gap > MAX_AZIMUTH_GAP_DEG:
        logger.info("%s: the scans carry no per-point times and leave %.0f deg of azimuth empty (a median scan), not "
                    "a spinning LiDAR's full turn: they are registered as they are", where, gap)
        return seq
    source = "from the stamps" if seq.timestamps is not None and len(seq.timestamps) > 1 else "assumed: no stamps"
    logger.info("%s: the scans carry no per-point times: each point's time is derived from its azimuth, a sweep of "
                "%.3f s (%s) %s (sensor frame x forward, z up)", where, period, source, convention.describe())
    times = lazy(seq.scans).map(lambda _, scan: azimuth_times(scan, period, convention))
    return dataclasses.replace(seq, point_times=times)
