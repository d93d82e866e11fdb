"""Whether scans that carry no time field (most PCD exports of a driver's clouds, KITTI-style .bin, a LiDAR-inertial
odometry's deskewed scans) are raw sweeps at all, measured on the data, and if they are, each point's time within its
sweep from its azimuth.

A spinning LiDAR measures a point when its head faces the point's azimuth, so the point's time after the sweep's
start is the fraction of a turn from the start azimuth, in the direction the head turns, times the sweep's period.
The times are seconds after the scan's stamp, taken as the sweep's start (as an Ouster stamps a sweep), in [0, T).
Which way a head turns and where its sweep starts (SweepConvention) differ between sensors: Velodyne heads turn
clockwise seen from above from behind the sensor, as KISS-ICP's own KITTI raw loader (kiss_icp/datasets/kitti_raw.py)
stamps the points; KITTI's raw readme says its HDL-64E turns counter-clockwise; the synthetic generator's sensor
turns anticlockwise from the front.

Raw or deskewed. Deskewed scans look like raw ones, and deskewing them again bends each by the motion between two
scans: handheld scans deskewed by a LiDAR-inertial odometry (2 Hz, no stamps) made KISS-ICP lose track at scan 30
once deskewed at an assumed 10 Hz, and registered as they are it followed them. So the data decides
(measured_deskew): up to EVIDENCE_PAIRS pairs of consecutive scans, those that turn most of CANDIDATE_PAIRS spread
over the recording (a sweep's skew shows where the sensor turns; a straight drive's shows on few surfaces), each
registered rigidly (point-to-plane ICP from no motion, or from FPFH + RANSAC where that does not hold), then again
with both scans deskewed under each convention of CONVENTIONS, the motion during a sweep taken as the pair's
registered motion (for consecutive sweeps that is one sweep's motion, whatever the period). A hypothesis's residual is
the RMS point-to-plane distance after ICP, truncated at two voxels. A convention wins when its residual is at most
1 - MARGIN times the rigid one in the median over the pairs and more than 1 + MARGIN times it on none; otherwise,
and on a tie, the scans are registered as they are (deskewing what was deskewed already is the damage). The stamps
are not what decides: keyframes 0.2-1 s apart may hold raw sweeps or deskewed scans alike. data.deskew overrides
the decision (DESKEW_CHOICES).

What it cannot know: a head whose lasers fire at azimuth offsets of their own (the HDL-64E's reach several degrees)
gives points measured together azimuths a little apart (a few ms at 10 Hz), and a point within that offset of the
seam is given the other end of the sweep. Scans covering part of a turn are left as they are.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.data.scan_source import lazy
from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError
from neld_jax.frontend import odometry

logger = logging.getLogger(__name__)

DEFAULT_PERIOD_S = 0.1  # a raw sweep's period when the scans have no stamps: 10 Hz, the common spinning rate
# A sweep spans a full turn when no azimuth sector this wide is empty (a street or a room leaves none; a sensor
# looking through a window, or scans cropped to a camera's view, do).
MAX_AZIMUTH_GAP_DEG = 20.0
MAX_SCANS_LOOKED_AT = 200  # evenly spaced scans whose median gap decides: enough, and a long recording is not read
CANDIDATE_PAIRS = 10  # consecutive pairs spread over the recording, registered rigidly ...
EVIDENCE_PAIRS = 5  # ... of which those that turn most decide between the hypotheses
MIN_EVIDENCE_PAIRS = 2  # fewer registered pairs decide nothing: the scans are registered as they are
MARGIN = 0.05  # a convention must lower the rigid residual by this share (median over pairs) and raise it on none
MIN_FITNESS = 0.5  # a pair whose rigid registration leaves fewer of its points within two voxels is no evidence
RANSAC_ITERATIONS = 20_000  # at most, for a pair that ICP from no motion does not hold (the odometry's recovery's)
FEATURE_RADIUS_VOXELS = 5.0  # FPFH radius, in voxels (the odometry's recovery's)
AUTO, DESKEWED, RAW = "auto", "deskewed", "raw"


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
            f"at azimuth {np.degrees(self.start_azimuth_rad):.0f} deg from",
        )
        turning = "clockwise" if self.clockwise else "anticlockwise"
        return f"starting {where} the sensor, turning {turning} seen from above"


VELODYNE = SweepConvention(start_azimuth_rad=np.pi, clockwise=True)
# The hypotheses the data decides between (and data.deskew's "raw_<name>" names)
CONVENTIONS = {
    "behind_clockwise": VELODYNE,
    "behind_anticlockwise": SweepConvention(np.pi, False),
    "front_clockwise": SweepConvention(0.0, True),
    "front_anticlockwise": SweepConvention(0.0, False),
}
DESKEW_CHOICES = (AUTO, DESKEWED, RAW) + tuple(f"{RAW}_{name}" for name in CONVENTIONS)


@dataclasses.dataclass(frozen=True)
class DeskewEvidence:
    """What measured_deskew measured: pairs [P] (the first scan of each pair), residuals {"rigid" or a CONVENTIONS
    name: [P] RMS point-to-plane residuals in metres}; no pair when none could be registered."""

    pairs: tuple[int, ...]
    residuals: dict[str, np.ndarray]

    def ratios(self) -> dict[str, np.ndarray]:
        """{convention name: [P] its residuals over the rigid ones}."""
        return {
            name: r / np.maximum(self.residuals["rigid"], 1e-12)
            for name, r in self.residuals.items()
            if name != "rigid"
        }

    def winner(self, margin: float = MARGIN) -> str | None:
        """The convention that registers clearly better than rigid (module docstring; margin 0: the best of them,
        whatever rigid gives, from any pair), None on a tie or with fewer than MIN_EVIDENCE_PAIRS pairs."""
        if not self.pairs or (margin > 0 and len(self.pairs) < MIN_EVIDENCE_PAIRS):
            return None
        ratios = self.ratios()
        best = min(ratios, key=lambda name: float(np.median(ratios[name])))
        clear = np.median(ratios[best]) <= 1.0 - margin and np.max(ratios[best]) <= 1.0 + margin
        return best if margin <= 0 or clear else None

    def describe(self) -> str:
        """The evidence in words, for the log line."""
        if not self.pairs:
            return "no pair of consecutive scans could be registered"
        rigid = float(np.median(self.residuals["rigid"]))
        ratios = self.ratios()
        each = ", ".join(
            f"{name.replace('_', ' ')} {100 * np.median(self.residuals[name]):.2f} cm "
            f"(x{np.median(ratios[name]):.2f}, x{np.max(ratios[name]):.2f} at most)"
            for name in ratios
        )
        return (
            f"RMS point-to-plane residuals after ICP of {len(self.pairs)} pairs of consecutive scans (first "
            f"scans {', '.join(map(str, self.pairs))}), medians: rigid {100 * rigid:.2f} cm, {each}"
        )


def turn_fractions(points: np.ndarray, convention: SweepConvention) -> np.ndarray:
    """points [N, 3] (sensor frame, x forward, z up) -> [N] in [0, 1): how far through the turn each was measured."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    turned = (
        (convention.start_azimuth_rad - azimuth) if convention.clockwise else (azimuth - convention.start_azimuth_rad)
    )
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


def sweep_period(timestamps: np.ndarray | None) -> float:
    """A raw sweep's period in seconds from stamps [S]: their median step (consecutive sweeps), DEFAULT_PERIOD_S
    without stamps (or with one)."""
    if timestamps is None or len(timestamps) < 2:
        return DEFAULT_PERIOD_S
    return float(np.median(np.diff(timestamps)))


def deskewed_by(points: np.ndarray, fractions: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """A raw sweep's points [N, 3], each measured at fractions [N] of the sweep, moved into the sensor frame at the
    sweep's start, the sensor moving by motion [4, 4] (the frame at the sweep's end in the one at its start) at
    constant velocity: rotation by slerp, translation linearly (odometry.interpolate_poses). [N, 3]."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_matrix(motion[:3, :3]).as_rotvec()
    return Rotation.from_rotvec(fractions[:, None] * turn).apply(points) + fractions[:, None] * motion[:3, 3]


def _cloud(points: np.ndarray, voxel_m: float, normals: bool = False):
    """An Open3D cloud of points [N, 3] on a voxel_m grid (with normals within two voxels when asked)."""
    import open3d as o3d

    from neld_jax.frontend.feature_registration import point_cloud

    cloud = point_cloud(points).voxel_down_sample(voxel_m)
    if normals:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel_m, max_nn=30))
    return cloud


def _icp(source, target, start: np.ndarray, distances: list[float]) -> np.ndarray:
    """Point-to-plane ICP (feature_registration.refined_alignment) of the cloud source to target (with normals) from
    start [4, 4], pairing points within each of distances [m] in turn: the pose [4, 4] of source's frame in
    target's."""
    from neld_jax.frontend.feature_registration import refined_alignment

    return refined_alignment(source, target, start, tuple(distances), normal_radius_m=0.0)[0]


def _residual(source, target, pose: np.ndarray, voxel_m: float) -> tuple[float, float]:
    """(RMS point-to-plane distance [m] of the cloud source at pose [4, 4] to target (with normals), each distance
    truncated at two voxels, a point without a neighbour within them counting as two voxels; the share of source's
    points that have one)."""
    from scipy.spatial import cKDTree

    points = np.asarray(source.points) @ pose[:3, :3].T + pose[:3, 3]
    target_points, target_normals = np.asarray(target.points), np.asarray(target.normals)
    cap = 2.0 * voxel_m
    nearest, index = cKDTree(target_points).query(points, distance_upper_bound=cap)
    found = np.isfinite(nearest)
    distance = np.full(len(points), cap)
    offsets = points[found] - target_points[index[found]]
    distance[found] = np.minimum(np.abs(np.einsum("ij,ij->i", offsets, target_normals[index[found]])), cap)
    return float(np.sqrt(np.mean(distance**2))), float(np.mean(found))


def rigid_pair(a: np.ndarray, b: np.ndarray, voxel_m: float) -> tuple[np.ndarray, float, float]:
    """Scan b [M, 3] registered rigidly to scan a [N, 3] (both sensor frames) on a voxel_m grid: (b's pose [4, 4] in
    a's frame, its residual [m] and fitness, _residual). ICP from no motion; where that leaves less than MIN_FITNESS,
    also from FPFH + RANSAC (a turn too large for ICP), the better kept."""
    from neld_jax.frontend.feature_registration import fpfh_features, ransac_alignment

    source, target = _cloud(b, voxel_m), _cloud(a, voxel_m, normals=True)
    pose = _icp(source, target, np.eye(4), [4.0 * voxel_m, 2.0 * voxel_m, voxel_m])
    residual, fitness = _residual(source, target, pose, voxel_m)
    if fitness < MIN_FITNESS:
        radius = FEATURE_RADIUS_VOXELS * voxel_m
        start = ransac_alignment(
            fpfh_features(_cloud(b, voxel_m), voxel_m, radius),
            fpfh_features(_cloud(a, voxel_m), voxel_m, radius),
            voxel_m,
            RANSAC_ITERATIONS,
            0,
        )
        featured = _icp(source, target, start, [2.0 * voxel_m, voxel_m])
        other = _residual(source, target, featured, voxel_m)
        if other[1] > fitness:
            pose, (residual, fitness) = featured, other
    return pose, residual, fitness


def deskewed_residual(
    a: np.ndarray, b: np.ndarray, convention: SweepConvention, motion: np.ndarray, voxel_m: float
) -> float:
    """The residual [m] (_residual) of scan b [M, 3] registered to scan a [N, 3], both deskewed as raw sweeps of
    `convention` (deskewed_by) with the sensor moving by the pair's motion [4, 4] (b's pose in a's frame, rigid_pair)
    in each sweep; the motion registered again from the deskewed scans, twice."""
    fractions_a, fractions_b = turn_fractions(a, convention), turn_fractions(b, convention)
    for _ in range(2):
        source = _cloud(deskewed_by(b, fractions_b, motion), voxel_m)
        target = _cloud(deskewed_by(a, fractions_a, motion), voxel_m, normals=True)
        motion = _icp(source, target, motion, [2.0 * voxel_m, voxel_m])
    return _residual(source, target, motion, voxel_m)[0]


def measured_deskew(scans, range_m: float) -> DeskewEvidence:
    """The evidence (module docstring, "Raw or deskewed") from scans [S] x [N_i, 3] (sensor frame, time order; a list
    or a LazyScans), their points within range_m [m] on a grid of a hundredth of it (KISS-ICP's voxel)."""
    voxel = odometry.VOXELS_PER_RANGE * range_m

    def read(i: int) -> np.ndarray:
        points = np.asarray(scans[i], np.float64)
        return points[np.linalg.norm(points, axis=1) <= range_m]

    firsts = np.unique(np.linspace(0, len(scans) - 2, min(len(scans) - 1, CANDIDATE_PAIRS)).round().astype(int))
    registered = []  # (turn [rad], first scan, scans, motion, residual)
    for i in firsts if len(scans) >= 2 else []:
        a, b = read(i), read(i + 1)
        motion, residual, fitness = rigid_pair(a, b, voxel)
        if fitness >= MIN_FITNESS:
            turn = float(np.arccos(np.clip((np.trace(motion[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
            registered.append((turn, int(i), (a, b), motion, residual))
    chosen = sorted(sorted(registered, key=lambda pair: -pair[0])[:EVIDENCE_PAIRS], key=lambda pair: pair[1])
    residuals = {"rigid": np.array([pair[4] for pair in chosen])}
    for name, convention in CONVENTIONS.items():
        residuals[name] = np.array(
            [deskewed_residual(*scans_ab, convention, motion, voxel) for _, _, scans_ab, motion, _ in chosen]
        )
    return DeskewEvidence(tuple(pair[1] for pair in chosen), residuals)


def deskew_decision(seq: Sequence, deskew: str, range_m: float) -> tuple[SweepConvention | None, str]:
    """(the convention seq's scans are raw sweeps of, None to register them as they are; why, for the log) under
    data.deskew = `deskew` (DESKEW_CHOICES): auto measures (measured_deskew, within range_m [m]); raw measures which
    convention and takes the best even on a tie (VELODYNE without evidence); deskewed and raw_<convention> decide."""
    if deskew == DESKEWED:
        return None, "data.deskew=deskewed"
    if deskew.startswith(f"{RAW}_"):
        return CONVENTIONS[deskew[len(RAW) + 1 :]], f"data.deskew={deskew}"
    evidence = measured_deskew(seq.scans, range_m)
    name = evidence.winner(margin=0.0 if deskew == RAW else MARGIN)
    if deskew == RAW:
        how = "measured" if name else "assumed: Velodyne's"
        return CONVENTIONS[name or "behind_clockwise"], f"data.deskew=raw, the convention {how}; {evidence.describe()}"
    return (CONVENTIONS[name] if name else None), f"measured: {evidence.describe()}; data.deskew overrides"


def with_azimuth_times(seq: Sequence, deskew: str = AUTO, range_m: float = 0.0) -> Sequence:
    """seq with point_times derived from the azimuths (azimuth_times) when it has none and its scans are raw sweeps
    (deskew_decision under data.deskew = `deskew`; range_m [m]: the points the measurement registers, 0: the
    sensor's range, odometry.sensor_range_m), at the stamps' period (sweep_period); else seq as it is. Under auto,
    scans whose median leaves more than MAX_AZIMUTH_GAP_DEG of azimuth empty (over at most MAX_SCANS_LOOKED_AT scans
    evenly spaced) are no full turns and are left as they are. One log line says which and why, with the evidence.
    The times are derived from each scan when it is used (data.scan_source)."""
    where = seq.source or seq.name
    if seq.point_times is not None or not seq.scans:
        return seq
    if deskew not in DESKEW_CHOICES:
        raise ConfigError(f"data.deskew: unknown choice '{deskew}' (expected one of {' | '.join(DESKEW_CHOICES)})")
    if deskew == AUTO:
        picked = np.unique(
            np.linspace(0, seq.num_scans - 1, min(seq.num_scans, MAX_SCANS_LOOKED_AT)).round().astype(int)
        )
        gap = float(np.median([largest_azimuth_gap_deg(seq.scans[i]) for i in picked]))
        if gap > MAX_AZIMUTH_GAP_DEG:
            logger.info(
                "%s: the scans carry no per-point times and leave %.0f deg of azimuth empty (a median scan), "
                "not a spinning LiDAR's full turn: they are registered as they are",
                where,
                gap,
            )
            return seq
    convention, why = deskew_decision(seq, deskew, range_m or odometry.sensor_range_m(seq.scans))
    if convention is None:
        logger.info(
            "%s: the scans carry no per-point times and are deskewed already: registered as they are (%s)", where, why
        )
        return seq
    period = sweep_period(seq.timestamps)
    source = "from the stamps" if seq.timestamps is not None and len(seq.timestamps) > 1 else "assumed: no stamps"
    logger.info(
        "%s: the scans carry no per-point times and are raw sweeps %s (%s): each point's time is derived "
        "from its azimuth, a sweep of %.3f s (%s) (sensor frame x forward, z up)",
        where,
        convention.describe(),
        why,
        period,
        source,
    )
    times = lazy(seq.scans).map(lambda _, scan: azimuth_times(scan, period, convention))
    return dataclasses.replace(seq, point_times=times)
