"""The baseline's scan-to-map chain (step 1 of neld_jax.baseline): each scan registered to the local map of the
scans before it, from the odometry's increment; and which of the two chains (the input's tilt kept, or free) goes
on."""

from __future__ import annotations

import logging
import time

import numpy as np
import open3d as o3d

from neld_jax.baseline.graph import fpfh_features, global_registration
from neld_jax.baseline.icp import correction_m, multiscale_icp
from neld_jax.baseline.segments import Segments
from neld_jax.baseline.settings import BaselineSettings, first_items, progress_bar
from neld_jax.geometry import with_up_axis_of
from neld_jax.judging import judge

logger = logging.getLogger(__name__)


def scan_to_map_chain(
    clouds: list,
    init_poses: np.ndarray,
    settings: BaselineSettings,
    keep_input_tilt: bool = False,
    deadline: float | None = None,
    progress: bool = False,
    segments: Segments = Segments(),
) -> tuple[np.ndarray | None, np.ndarray]:
    """Register each scan to the local map of the `settings.window` scans before it.

    clouds: S Open3D clouds (sensor frame, with normals); init_poses: [S, 4, 4] sensor -> world.
    Returns (poses [S, 4, 4] with poses[0] = init_poses[0], fitness [S] of each link, fitness[0] = 1); with
    keep_input_tilt every pose has its init_poses' up axis (geometry.with_up_axis_of). A link
    whose fitness is below settings.min_chain_fitness, or whose ICP moved the scan further than
    settings.max_link_correction_m where the global registration does not land on ICP's pose (_features_agree),
    keeps the odometry's increment; one warning per reason lists those scans.
    poses is None when the chain was given up (settings.chain_min_median_overlap, or the time.perf_counter() value
    `deadline` passed before its last link; one warning says which); fitness then holds the links registered
    before, NaN after. progress: a progress bar over the links. segments: recordings joined in one sequence; the
    chain restarts at each one's first scan (it keeps its input pose, fitness 1) and the local maps of a recording's
    scans hold only its own (neld_jax.baseline.segments).
    """
    poses = [np.asarray(init_poses[0], np.float64)]
    fitness = np.ones(len(clouds))
    kept = {"overlap": [], "slide": []}  # links that kept the odometry's increment, by reason: one warning each
    links = progress_bar(
        f"scan-to-map chain ({'the input' if keep_input_tilt else 'its own'} tilt)", progress, range(1, len(clouds))
    )
    for s in links:
        if _given_up(s, len(clouds), fitness, settings, deadline):
            fitness[s:] = np.nan
            break
        if s in segments.starts:  # a later recording: placed in the first one's frame, not linked to the one before
            poses.append(np.asarray(init_poses[s], np.float64))
            continue
        pose, fitness[s], reason = _link(clouds, poses, init_poses, s, settings, keep_input_tilt, segments.first_of(s))
        if reason is not None:
            kept[reason[0]].append(reason[1])
        poses.append(pose)
    links.close()
    _warn_kept(kept, settings)
    return (np.stack(poses) if len(poses) == len(clouds) else None), fitness


def _given_up(s: int, num_scans: int, fitness: np.ndarray, settings: BaselineSettings, deadline: float | None) -> bool:
    """Whether the chain stops before link s (fitness [S]: the links' so far): its links overlap too little
    (settings.chain_min_median_overlap) or the deadline passed; one warning says which."""
    if s - 1 >= max(settings.chain_check_links, 1) and np.median(fitness[1:s]) < settings.chain_min_median_overlap:
        logger.warning(
            "baseline: the first %d chain links overlap their local maps by %.2f%% (median; less "
            "than chain_min_median_overlap=%.0f%%: keyframes too far apart for scan-to-map ICP): the "
            "chain is given up, the pose graph skipped, and the multi-view refinement starts from the "
            "input poses: it sharpens the map locally, but drift the input poses gather along the "
            "route stays in the answer",
            s - 1,
            100 * np.median(fitness[1:s]),
            100 * settings.chain_min_median_overlap,
        )
        return True
    if deadline is not None and time.perf_counter() > deadline:
        # A half-registered chain cannot feed the pose graph, and the rounds would stop at once anyway.
        logger.warning(
            "baseline: the run's deadline passed after %d of the %d chain links: the chain is given up, "
            "the pose graph skipped, and the input poses are the baseline's start",
            s - 1,
            num_scans - 1,
        )
        return True
    return False


def _link(
    clouds: list,
    poses: list,
    init_poses: np.ndarray,
    s: int,
    settings: BaselineSettings,
    keep_input_tilt: bool,
    first: int = 0,
) -> tuple[np.ndarray, float, tuple[str, str] | None]:
    """Scan s registered to the local map of the scans before it at poses (s of them, [4, 4]), from scan `first` (its
    recording's first) on -> (its pose [4, 4], the link's fitness, None or (why it kept the odometry's increment:
    "overlap" | "slide", the scan for the log))."""
    guess = poses[s - 1] @ np.linalg.inv(init_poses[s - 1]) @ init_poses[s]  # the odometry's increment
    if keep_input_tilt:
        guess = with_up_axis_of(guess, init_poses[s])
    local_map = o3d.geometry.PointCloud()
    for k in range(max(first, s - settings.window), s):
        local_map += o3d.geometry.PointCloud(clouds[k]).transform(poses[k])  # normals rotate along
    transform, result = multiscale_icp(clouds[s], local_map, guess, settings)
    moved_m = correction_m(guess, transform)
    reason = None
    if result.fitness < settings.min_chain_fitness:
        reason = ("overlap", f"{s} ({100 * result.fitness:.1f}%)")
        transform = guess
    elif moved_m > settings.max_link_correction_m and not _features_agree(clouds[s], local_map, transform, settings):
        reason = ("slide", f"{s} ({moved_m:.2f} m)")
        transform = guess
    pose = with_up_axis_of(transform, init_poses[s]) if keep_input_tilt else transform
    return pose, result.fitness, reason


def _features_agree(scan, local_map, transform: np.ndarray, settings: BaselineSettings) -> bool:
    """Whether the global registration (FPFH + RANSAC, then ICP: graph.global_registration) of the scan (sensor frame)
    onto its local map (world frame) lands within max_loop_correction_m of ICP's pose `transform` [4, 4]. ICP that
    slid along a corridor landed where its start led it, and the features, which need no start, do not follow it;
    an odometry increment that was wrong (KISS-ICP's first second at speed: 0.54 m on the 20 m synthetic loop) is
    corrected alike by both."""
    found, _ = global_registration(
        scan, local_map, fpfh_features(scan, settings), fpfh_features(local_map, settings), settings
    )
    return correction_m(transform, found) <= settings.max_loop_correction_m


def _warn_kept(kept: dict, settings: BaselineSettings) -> None:
    """One warning per reason a link kept the odometry's increment (kept: {"overlap" | "slide": [scan text]})."""
    if kept["overlap"]:
        logger.warning(
            "baseline: %d scan(s) overlap the map of the %d scans before them by less than "
            "min_chain_fitness=%.0f%% and keep the odometry's increment: %s",
            len(kept["overlap"]),
            settings.window,
            100 * settings.min_chain_fitness,
            first_items(kept["overlap"]),
        )
    if kept["slide"]:
        logger.warning(
            "baseline: ICP moved %d scan(s) further than max_link_correction_m=%.2g m from the odometry's "
            "increment, where the global registration put them elsewhere (a slide along a featureless "
            "direction?); they keep the increment: %s",
            len(kept["slide"]),
            settings.max_link_correction_m,
            first_items(kept["slide"]),
        )


# A chain that keeps the input's tilt is kept unless the free chain's raw map is crisper by more than this (mean map
# entropy, nats). Measured (docs/evaluation.md, "Keeping the input's tilt"): with an IMU-aided odometry's tilt the free
# chain came out crisper by 0.012-0.030 on three real sequences, while keeping the tilt gave the better route; with
# a tilt that drifted 0.2-0.5 deg a keyframe the chain that keeps it was blurrier by 0.68-0.78.
TILT_MARGIN = 0.1


def choose_chain(chains: dict, scans: list[np.ndarray], settings: BaselineSettings) -> tuple[str, dict]:
    """Which chain goes on: {"input tilt": poses, "free": poses} (None: given up) -> (the name, {name: mean map
    entropy of its raw map}). The free chain wins only when crisper by more than TILT_MARGIN."""
    held = {name: poses for name, poses in chains.items() if poses is not None}
    if len(held) < 2:
        return next(iter(held), "free"), {}
    summaries, _ = judge.compare_maps(scans, held, settings.crispness_radius_m, settings.crispness_queries)
    entropy = {name: summary["mean_map_entropy"] for name, summary in summaries.items()}
    tilt, free = entropy["input tilt"], entropy["free"]
    chosen = "free" if tilt is not None and free is not None and free < tilt - TILT_MARGIN else "input tilt"
    return chosen, entropy
