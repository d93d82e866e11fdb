"""A check of the LiDAR-only odometry (odometry.py) by evidence that does not share its failure: global registration
of pairs of consecutive scans from no guess.

Why. KISS-ICP guesses each scan from constant velocity and lets its ICP decide. Where that guess is far off (from
rest at the first scan; several metres a scan at 2 Hz) or the scene holds the motion weakly along one direction (a
street), its ICP settles short of the motion and the next guess inherits the shortfall: the path shrinks while
consecutive scans still overlap, which is all that odometry.py's lost-track rule sees. Measured on KITTI 00's first
101 sweeps thinned to 2 Hz (21 scans 2-5 m apart): KISS-ICP registering within 40 m kept 19 % of the path and ended
68.9 m off with no lost-track warning; within the sensor's 74.5 m (what odometry.py measures) 98 %.

What. CHECK_PAIRS pairs of consecutive scans evenly spaced over the recording (the first pair always among them),
the scans as they came (not deskewed) within KISS-ICP's ranges, scan i + 1 registered onto scan i by FPFH features
and RANSAC (feature_registration.py) from no guess on a grid FEATURE_VOXELS times KISS-ICP's voxel, then by
point-to-plane ICP on KISS-ICP's grid. A pair whose fitness (the share of scan i + 1's grid points within a voxel of
scan i's) is under MIN_FITNESS did not converge, and one that moved less than STILL_STEP_VOXELS voxels has a ratio
that is noise: neither carries evidence. From the others, the odometry's step length over the global step's: its
median (a step that slides throughout) and the ratio of their sums (the path over the sampled pairs: a few steps
that slid far) must lie within STEP_TOLERANCE either way, and no single pair may have slid (its ratio beyond
SLID_RATIO while its scans fit worse under the odometry's step than under the global one, SLID_FITNESS). Outside the
tolerance is evidence only where the scans say so: where in at least half of the pairs outside it the odometry's
step fits the scans as well as the global one, the global registration is no better evidence and the odometry's
steps are kept with a warning (16-beam synthetic sweeps 0.42 m apart: global steps 0.30-0.36 m where KISS-ICP's
0.41-0.45 m lay nearer the truth; FAST-LIO2's keyframes of HKU_1: 0.33 m against KISS-ICP's 0.77 m, which the
recording's own odometry confirmed), and along the path such a pair counts with the odometry's length. Where they
disagree, the odometry runs again with the converged global steps as KISS-ICP's motion guesses for those scans (its
constant-velocity model goes on from the step found) and is checked on the pairs between the first ones (the same
pairs in a recording of fewer than 2 x CHECK_PAIRS scans; their registrations are kept); if it still disagrees, the
load stops with one line naming the recording and the scans. One log line gives the evidence either way; with
fewer than MIN_EVIDENCE pairs of evidence (a sensor whose scans overlap little, a recording standing still) the
odometry goes on unchecked, with a warning.

Measured (2026-12-07, a 2-core Xeon VM with a benchmark running on both cores; 4-6 s for 20 pairs): KISS-ICP over
KITTI 00's first 101 sweeps (10 Hz, 0.4-1.0 m apart) 0.991-0.992 in the median (pairs 0.95-1.04), 0.990 along
the path (its path against the truth's: 0.984), 20 of 20 pairs converged (fitness 0.89-0.99); the same drive at
2 Hz 0.999 (0.99-1.01) and 0.998 (0.984), fitness 0.75 and over, and within 40 m 0.127 and 0.191 with 17 of 20 steps
slid, run again from the global steps 0.998 and 0.999: 98 % of the path, 2.05 m off at the end (2.08 m within
74.5 m), ATE 0.38 m against 23.4 m. Synthetic: the 10 m loop's 40 raw sweeps (0.22 m apart, voxel 0.4 m) 1.039 and
1.020 for seed 0 (0.77-1.18 a pair: KISS-ICP's own scatter on short steps), 1.086 and 1.082 for seed 1 (its path is
7.4 % long against the truth's), 1.009 and 1.013 at 0.6 m a sweep; the handheld walk (2 Hz, 40-50 degree turns)
1.002-1.004 and 0.983-0.993; rigid scans 1.7-2.2 m apart that KISS-ICP starts short (first steps 0.02-0.42 of the
global ones, paths 0.78-0.89 over the pairs) run again to 0.994-1.006 and 0.998-1.003 (ATE 1.15 -> 0.29 m,
2.12 -> 0.35 m). Global registration's steps against the truth: 1-9 mm on synthetic scans, 1-4 cm on KITTI's past
its first sweeps (where KITTI's ground truth disagrees with both); misregistered pairs (scans 26-85 m apart, a jump
into another place) 0.30-0.47 fitness; scans under the odometry's steps fit 0.96-1.04 of the global steps' fitness
where the steps agree, 0.32-0.80 where they slid.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable

import numpy as np

from neld_jax.data.preprocess import crop_range
from neld_jax.errors import DataError

logger = logging.getLogger(__name__)

CHECK_PAIRS = 20  # pairs of consecutive scans registered globally: 0.2-0.3 s each
# FPFH and RANSAC on a grid twice KISS-ICP's voxel: the same steps within 1 mm after ICP, 3.5 s instead of 10.7 s
# for 20 pairs of KITTI sweeps (the features and their matching dominate the cost).
FEATURE_VOXELS = 2.0
FEATURE_RADIUS_VOXELS = 5.0  # FPFH radius, in feature-grid voxels (the classical baseline's ratio)
RANSAC_ITERATIONS = 20_000  # at most (its 99.9 % confidence stops it earlier)
ICP_DISTANCES_VOXELS = (3.0, 1.0)  # ICP from RANSAC's pose pairs points this many KISS-ICP voxels apart, in turn
# Converged pairs of consecutive scans measured 0.75-0.99, misregistered ones 0.30-0.47 (module docstring).
MIN_FITNESS = 0.6
# A pair that moved less than this many voxels carries no evidence of the step's length: KISS-ICP's own scatter is
# about 0.05 m a step on the synthetic loop (an eighth of its voxel).
STILL_STEP_VOXELS = 0.25
MIN_EVIDENCE = 3  # pairs with evidence needed to decide
# The median and path ratios must lie within 1 / STEP_TOLERANCE .. STEP_TOLERANCE: measured within x1.086 of 1 where
# the odometry kept track (the furthest the synthetic loop whose path is 7.4 % long), 0.13 in the median and 0.19
# along the path where it slid throughout (KITTI at 2 Hz within 40 m; a real HDL-32E drive kept 57 % of its path).
# Steps that slid at the start only are SLID_RATIO's (the path over the pairs 0.78-0.89 there).
STEP_TOLERANCE = 1.15
# One pair slid when its ratio lies outside x SLID_RATIO and the odometry's step fits the two scans worse than the
# global one: its fitness under 0.9 x the global step's (measured 0.96-1.04 of it where the steps agree, 0.32-0.80
# where they slid).
SLID_RATIO = 2.0
SLID_FITNESS = 0.9
SHOWN_PAIRS = 3  # pairs named in the error line, the furthest first
MIN_POINTS = 10  # a scan with fewer points within the ranges has no features to match


@dataclasses.dataclass
class PairRegistration:
    """One pair's global registration, scan i + 1 onto scan i (it does not depend on the odometry)."""

    transform: np.ndarray  # [4, 4] scan i + 1 -> scan i
    fitness: float  # the share of scan i + 1's grid points within a voxel of scan i's under it
    source: object  # scan i + 1 on KISS-ICP's grid (an Open3D cloud, its sensor frame)
    target: object  # scan i on that grid
    seconds: float = 0.0  # what it cost


@dataclasses.dataclass
class StepCheck:
    """Global registration of P sampled pairs of consecutive scans against an odometry's steps."""

    pairs: np.ndarray  # [P] int: pair k registers scan pairs[k] + 1 to scan pairs[k]
    global_steps: np.ndarray  # [P, 4, 4] scan pairs[k] + 1 -> scan pairs[k], by global registration
    fitness: np.ndarray  # [P] the share of the later scan's grid points within a voxel of the earlier's under it
    odometry_steps: np.ndarray  # [P] metres the odometry moves between the two
    odometry_fitness: np.ndarray  # [P] that share under the odometry's step
    voxel_m: float  # KISS-ICP's voxel
    seconds: float  # what the global registration cost

    @property
    def converged(self) -> np.ndarray:
        """[P] bool: the pairs whose global registration converged (MIN_FITNESS)."""
        return self.fitness >= MIN_FITNESS

    @property
    def lengths(self) -> np.ndarray:
        """[P] metres of each global step."""
        return np.linalg.norm(self.global_steps[:, :3, 3], axis=1)

    @property
    def ratios(self) -> np.ndarray:
        """[P] the odometry's step length over the global step's; NaN for a pair without evidence."""
        evidence = self.converged & (self.lengths >= STILL_STEP_VOXELS * self.voxel_m)
        return np.where(evidence, self.odometry_steps / np.maximum(self.lengths, 1e-12), np.nan)

    @property
    def median_ratio(self) -> float | None:
        """The median of ratios over the pairs with evidence; None with fewer than MIN_EVIDENCE of them."""
        ratios = self.ratios[np.isfinite(self.ratios)]
        return float(np.median(ratios)) if len(ratios) >= MIN_EVIDENCE else None

    @property
    def path_ratio(self) -> float | None:
        """The odometry's path over the global registration's along the pairs with evidence (their summed step
        lengths): a few steps that slid far (from rest at the start) shorten it where the median stays; None as
        median_ratio. A pair whose odometry step fits its two scans about as well as the global one (SLID_FITNESS)
        counts with the odometry's length: the scans do not say which is right there (FAST-LIO2's handheld keyframes
        of HKU_1: global steps of 0.33 m where KISS-ICP's 0.77 m fitted as well and agreed with the recording's own
        odometry; counted, the path read 1.29 and a run again from those steps ended 0.167 m from that odometry
        instead of 0.116)."""
        ratios = self.ratios
        evidence = np.isfinite(ratios)
        if self.median_ratio is None:
            return None
        as_well = self.odometry_fitness >= SLID_FITNESS * self.fitness
        global_lengths = np.where(as_well, self.odometry_steps, self.lengths)
        return float(self.odometry_steps[evidence].sum() / global_lengths[evidence].sum())

    @property
    def slid(self) -> np.ndarray:
        """[P] bool: the pairs whose odometry step is off by more than x SLID_RATIO and fits the scans worse than
        the global step (SLID_FITNESS): one step that slid, whatever the others do."""
        ratios = np.where(np.isfinite(self.ratios), self.ratios, 1.0)
        return (np.abs(np.log(ratios)) > np.log(SLID_RATIO)) & (self.odometry_fitness < SLID_FITNESS * self.fitness)

    @property
    def within_tolerance(self) -> bool:
        """Whether the median and path ratios lie within STEP_TOLERANCE (True where nothing can be decided)."""
        if self.median_ratio is None:
            return True
        return all(1.0 / STEP_TOLERANCE <= ratio <= STEP_TOLERANCE for ratio in (self.median_ratio, self.path_ratio))

    @property
    def backed_by_the_scans(self) -> bool:
        """Whether the pairs whose steps disagree (outside STEP_TOLERANCE) fit their scans worse under the odometry's
        step than under the global one (SLID_FITNESS) in at least half of them: only then do the scans say that the
        odometry is wrong. Where both steps fit about as well, the global registration is no better evidence (16-beam
        sweeps 0.42 m apart: global steps 0.30-0.36 m where KISS-ICP's 0.41-0.45 m lay nearer the truth; HKU_1's
        keyframes: 0.33 m against KISS-ICP's 0.77 m, which agreed with the recording's own odometry)."""
        ratios = np.where(np.isfinite(self.ratios), self.ratios, 1.0)
        outside = np.abs(np.log(ratios)) > np.log(STEP_TOLERANCE)
        worse = self.odometry_fitness < SLID_FITNESS * self.fitness
        return bool(outside.any() and worse[outside].mean() >= 0.5)

    @property
    def agrees(self) -> bool:
        """Whether the odometry's steps agree, in the median, along the path and pair by pair (or nothing can be
        decided, or the scans fit its steps as well as the global ones)."""
        if self.slid.any():
            return False
        return self.within_tolerance or not self.backed_by_the_scans

    def summary(self) -> str:
        """The evidence in words (pairs checked, converged, moving, the median and path ratios, pairs that slid)."""
        ratios = self.ratios[np.isfinite(self.ratios)]
        said = (
            f"{len(self.pairs)} pairs of consecutive scans checked, {int(self.converged.sum())} converged "
            f"(fitness >= {MIN_FITNESS:g}), {len(ratios)} moving"
        )
        if self.median_ratio is None:
            return f"{said}: too few to decide (at least {MIN_EVIDENCE}), unchecked ({self.seconds:.1f} s)"
        unbacked = (
            ""
            if self.within_tolerance or self.backed_by_the_scans
            else ("; outside it, but the scans fit KISS-ICP's steps about as well as the global ones: kept")
        )
        return (
            f"{said}; KISS-ICP's step over the global step {self.median_ratio:.3f} in the median "
            f"({ratios.min():.2f}-{ratios.max():.2f}), its path over theirs {self.path_ratio:.3f} (both must lie "
            f"within x{STEP_TOLERANCE:g}), {int(self.slid.sum())} single steps slid{unbacked} "
            f"({self.seconds:.1f} s)"
        )

    def furthest(self, labels: list[str]) -> str:
        """The SHOWN_PAIRS pairs furthest outside the tolerance (or slid) in words, naming the scans (labels [S])."""
        log_ratios = np.abs(np.log(np.where(np.isfinite(self.ratios), self.ratios, 1.0)))
        outside = np.flatnonzero((log_ratios > np.log(STEP_TOLERANCE)) | self.slid)
        outside = outside[np.argsort(-log_ratios[outside], kind="stable")]
        named = [
            f"{labels[self.pairs[k]]} to {labels[self.pairs[k] + 1]}: {self.odometry_steps[k]:.2f} m against "
            f"{self.lengths[k]:.2f} m"
            for k in outside[:SHOWN_PAIRS]
        ]
        more = f" and {len(outside) - SHOWN_PAIRS} more pairs" if len(outside) > SHOWN_PAIRS else ""
        return "; ".join(named) + more


def sampled_pairs(num_scans: int, between: bool = False) -> np.ndarray:
    """[P] the first scan of CHECK_PAIRS pairs of consecutive scans evenly spaced over num_scans (the first pair
    always among them: KISS-ICP starts it from no motion); between: the pairs halfway between those instead."""
    if num_scans < 2:
        return np.zeros(0, dtype=np.int64)
    count = min(CHECK_PAIRS, num_scans - 1)
    positions = np.linspace(0, num_scans - 2, count)
    if between:  # a short recording's pairs are all sampled already: the same ones
        positions = np.floor(positions + 0.5 * (num_scans - 2) / max(count - 1, 1))
    return np.unique(np.clip(np.round(positions), 0, num_scans - 2).astype(np.int64))


def global_step(source: np.ndarray, target: np.ndarray, voxel_m: float) -> PairRegistration:
    """source [N, 3] (a scan in its sensor frame) registered onto target [M, 3] (its own) by FPFH features and
    RANSAC from no guess on a FEATURE_VOXELS x voxel_m grid, then point-to-plane ICP on the voxel_m grid."""
    from neld_jax.frontend.feature_registration import fpfh_features, point_cloud, ransac_alignment, refined_alignment

    started = time.perf_counter()
    grids = [point_cloud(points).voxel_down_sample(voxel_m) for points in (source, target)]
    feature_voxel = FEATURE_VOXELS * voxel_m
    if min(len(points) for points in (source, target)) < MIN_POINTS:  # nothing to match: no evidence
        return PairRegistration(np.eye(4), 0.0, *grids, time.perf_counter() - started)
    features = [
        fpfh_features(point_cloud(points), feature_voxel, FEATURE_RADIUS_VOXELS * feature_voxel)
        for points in (source, target)
    ]
    guess = ransac_alignment(*features, feature_voxel, RANSAC_ITERATIONS, seed=0)
    distances = tuple(d * voxel_m for d in ICP_DISTANCES_VOXELS)
    transform, fitness = refined_alignment(*grids, guess, distances, 2 * voxel_m)
    return PairRegistration(transform, fitness, *grids, time.perf_counter() - started)


def registering_pairs(pairs: np.ndarray, ranges: tuple[float, float], voxel_m: float, registered: dict) -> Callable:
    """seen(i, scan [N_i, 3]) for an odometry that reads the scans once, in order: each of the pairs (scan pairs[k] +
    1 onto scan pairs[k]) not yet in registered is registered into it (global_step, within ranges (min, max) m on
    voxel_m) as soon as its second scan is seen, so that check_steps reads no scan again. Holds one scan at most."""
    wanted = {int(i) for i in pairs} - set(registered)
    held = {}  # {i: scan i within the ranges} while pair i waits for scan i + 1

    def seen(i: int, scan: np.ndarray) -> None:
        cropped = crop_range(np.asarray(scan, np.float64), *ranges) if i in wanted or i - 1 in wanted else None
        if i - 1 in held:
            registered[i - 1] = global_step(cropped, held.pop(i - 1), voxel_m)
        if i in wanted:
            held[i] = cropped

    return seen


def check_steps(
    scans,
    poses: np.ndarray,
    ranges: tuple[float, float],
    voxel_m: float,
    pairs: np.ndarray | None = None,
    registered: dict | None = None,
) -> StepCheck:
    """The odometry's poses [S, 4, 4] (sensor -> world, one a scan) against global registration of the scans
    [S] x [N_i, 3] (sensor frame, as the odometry registered them, a list or a LazyScans; within ranges (min, max) m,
    KISS-ICP's voxel voxel_m) for the pairs (scan pairs[k] + 1 to scan pairs[k]; None: sampled_pairs).
    registered: {pair: PairRegistration} already found (they do not depend on the odometry), filled with the new
    ones."""
    from neld_jax.frontend.feature_registration import fitness

    pairs = sampled_pairs(len(poses)) if pairs is None else np.asarray(pairs, np.int64)
    registered = {} if registered is None else registered
    earlier = {id(pair) for pair in registered.values()}  # registered before this call (as the odometry read them)
    started = time.perf_counter()
    for i in pairs:
        if int(i) not in registered:
            later, earlier = (crop_range(np.asarray(scans[j], np.float64), *ranges) for j in (i + 1, i))
            registered[int(i)] = global_step(later, earlier, voxel_m)
    found = [registered[int(i)] for i in pairs]
    increments = np.linalg.inv(poses[pairs]) @ poses[pairs + 1]  # [P, 4, 4] scan i + 1 -> scan i
    return StepCheck(
        pairs=pairs,
        global_steps=np.array([pair.transform for pair in found]).reshape(-1, 4, 4),
        fitness=np.array([pair.fitness for pair in found], np.float64),
        odometry_steps=np.linalg.norm(increments[:, :3, 3], axis=1),
        odometry_fitness=np.array(
            [fitness(pair.source, pair.target, increment, voxel_m) for pair, increment in zip(found, increments)],
            np.float64,
        ),
        voxel_m=float(voxel_m),
        seconds=time.perf_counter() - started + sum(pair.seconds for pair in found if id(pair) in earlier),
    )


def motion_guesses(check: StepCheck) -> dict[int, np.ndarray]:
    """{scan i + 1: the global step [4, 4] from scan i} for the pairs whose global registration converged: where
    KISS-ICP's constant-velocity model starts when it runs again."""
    return {int(i) + 1: step for i, step, ok in zip(check.pairs, check.global_steps, check.converged) if ok}


def checked_odometry(
    scans,
    odometry: Callable[[dict, Callable], tuple],
    labels: list[str],
    ranges: tuple[float, float],
    voxel_m: float,
    where: str,
) -> tuple:
    """odometry({}, seen) (a tuple whose first item is the poses [S, 4, 4] of the scans [S] x [N_i, 3]; it calls
    seen(i, scan i) as it reads each scan, and the pairs are registered from that read: registering_pairs), checked
    by check_steps (ranges (min, max) m and voxel_m: KISS-ICP's). Where its steps disagree with the global ones, it
    is run again as odometry(motion_guesses, seen) and checked on the pairs between the first ones; that result is
    returned if it agrees, else a DataError names the recording (where) and the scans (labels [S]). Logs the
    evidence."""
    registered = {}
    result = odometry({}, registering_pairs(sampled_pairs(len(scans)), ranges, voxel_m, registered))
    check = check_steps(scans, result[0], ranges, voxel_m, registered=registered)
    if check.agrees:
        log = logger.info if check.median_ratio is not None and check.within_tolerance else logger.warning
        log("%s: KISS-ICP's steps against global registration from no guess: %s", where, check.summary())
        return result
    logger.warning(
        "%s: KISS-ICP's steps disagree with global registration from no guess (%s; %s): running it "
        "again from the global steps of %d pairs",
        where,
        check.summary(),
        check.furthest(labels),
        len(motion_guesses(check)),
    )
    between = sampled_pairs(len(scans), between=True)
    repaired = odometry(motion_guesses(check), registering_pairs(between, ranges, voxel_m, registered))
    again = check_steps(scans, repaired[0], ranges, voxel_m, between, registered)
    if again.agrees:
        log = logger.info if again.median_ratio is not None else logger.warning
        log(
            "%s: KISS-ICP run again from the global steps; its steps against global registration: %s",
            where,
            again.summary(),
        )
        return repaired
    raise DataError(
        f"{where}: KISS-ICP's steps are {again.median_ratio:.0%} of what global registration (FPFH features and "
        f"RANSAC, then ICP, from no guess) finds between consecutive scans in the median and its path "
        f"{again.path_ratio:.0%} of theirs over {int(np.isfinite(again.ratios).sum())} pairs "
        f"({again.furthest(labels)}), after running again from the global steps ({check.median_ratio:.0%} and "
        f"{check.path_ratio:.0%} before): the odometry slid along the scene; give the sequence its poses (poses.txt, "
        "an odometry topic)"
    )
