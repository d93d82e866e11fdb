"""The baseline on a sequence: the chains, the pose graph and the multi-view refinement in turn
(neld_jax.baseline), and what was decided on the way (BaselineResult)."""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable

import numpy as np
import open3d as o3d

from neld_jax.baseline.chain import choose_chain, scan_to_map_chain
from neld_jax.baseline.distances import keep_input_distances
from neld_jax.baseline.graph import loop_closed_graph
from neld_jax.baseline.icp import prepare_clouds
from neld_jax.baseline.multiview import choose_refinement_start, refine_against_map
from neld_jax.baseline.segments import Segments
from neld_jax.baseline.settings import BaselineSettings
from neld_jax.geometry import anchored_on_first, nearest_rotations

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class BaselineResult:
    """What `register_sequence` found and decided.

    poses: [S, 4, 4] with pose 0 equal to the input's and orthonormal rotations; tilt: the chain that went on,
    "input" (it keeps the input's up axis) | "free", None when both were given up; chain_entropy: {chain: mean map
    entropy of its raw map} ({} when fewer than two chains were held); chain_given_up; refined_from: where the
    multi-view refinement started, "graph" | "chain" | "input" (None: no rounds after a chain); start_entropy:
    {"graph" | "chain": entropy} when the two were compared; map_rounds_done: the rounds done (a fraction when the
    deadline stopped them; None: no rounds); stopped_at_deadline; distances: whose distances travelled the poses
    keep (distances.keep_input_distances' record; None: not compared); seconds: {step: seconds}."""

    poses: np.ndarray
    tilt: str | None = None
    chain_entropy: dict = dataclasses.field(default_factory=dict)
    chain_given_up: bool = False
    refined_from: str | None = None
    start_entropy: dict | None = None
    map_rounds_done: float | None = None
    stopped_at_deadline: bool | None = None
    distances: dict | None = None
    seconds: dict = dataclasses.field(default_factory=dict)

    def report(self) -> dict:
        """What was decided and done, as metrics.json records it: every field but the poses, those that did not
        apply left out (tilt always there); {} when nothing ran (fewer than two scans)."""
        if not self.seconds:
            return {}
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "poses"}
        return {name: value for name, value in fields.items() if value is not None or name == "tilt"}


def register_sequence(
    scans: list[np.ndarray],
    init_poses: np.ndarray,
    settings: BaselineSettings = BaselineSettings(),
    on_round: Callable[[int, np.ndarray], None] | None = None,
    deadline: float | None = None,
    progress: bool = False,
    segments: Segments = Segments(),
) -> BaselineResult:
    """The baseline: the scan-to-map chains (the input's tilt kept and free; the crisper goes on), the loop-closed
    pose graph, then the multi-view refinement from the crisper of the graph and the chain (neld_jax.baseline).

    scans: list of S arrays [N_i, 3] in the sensor frame; init_poses: [S, 4, 4] sensor -> world.
    on_round(r, poses [S, 4, 4]): `refine_against_map`'s, called with r = 0 and the poses the refinement starts
    from too; they are the poses returned up to the final re-anchoring on scan 0 (one rigid transform).
    deadline: a time.perf_counter() value after which the multi-view refinement registers no more scans
    (`refine_against_map`) and a chain not yet finished is given up (`scan_to_map_chain`); the pose graph always
    runs to the end. progress: progress bars over each step's registrations. segments: recordings joined in one
    sequence (neld_jax.baseline.segments): the chains restart at each later one's first scan, and the placing's links
    join the pose graph; none (one recording) changes nothing.
    """
    init_poses = np.asarray(init_poses, dtype=np.float64)
    if init_poses.ndim != 3 or init_poses.shape[1:] != (4, 4):
        raise ValueError(f"init_poses must have shape [S, 4, 4], got {init_poses.shape}")
    if len(scans) != len(init_poses):
        raise ValueError(f"{len(scans)} scans but {len(init_poses)} initial poses")
    if len(scans) < 2:
        return BaselineResult(init_poses.copy())
    segments.check(len(scans))
    _log_joined(segments)
    clouds = prepare_clouds(scans, settings)
    seconds = {}
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        t0 = time.perf_counter()
        chain, decided = _chosen_chain(clouds, scans, init_poses, settings, deadline, progress, segments)
        seconds["chains"] = time.perf_counter() - t0
        if chain is None:  # given up (scan_to_map_chain warned): no graph, the refinement starts from the input
            optimized = init_poses
            decided["refined_from"] = "input"
            logger.info("baseline: scan-to-map chain given up after %.1f s", seconds["chains"])
        else:
            t1 = time.perf_counter()
            optimized, loops = loop_closed_graph(clouds, chain, settings, progress, segments)
            seconds["graph"] = time.perf_counter() - t1
            logger.info(
                "baseline: pose graph with %d of %d loop-closure candidates (overlap >= %.0f%%), %d of them "
                "from %d global registrations%s, in %.1f s",
                loops.kept,
                loops.tried,
                100 * settings.min_loop_fitness,
                loops.global_kept,
                loops.global_tried,
                _between_recordings(loops) if segments.starts else "",
                seconds["graph"],
            )
        if settings.map_rounds > 0:
            t2 = time.perf_counter()
            # Joined recordings: from the graph, since the chain leaves each later one where its placing put it, and two
            # copies of a place further apart than the crispness radius look crisp (synthetic visits: docs/sessions.md).
            compared = None if segments.starts else chain
            if segments.starts and chain is not None:
                decided["refined_from"] = "graph"
            optimized = _refined(clouds, scans, optimized, compared, settings, (on_round, deadline, progress), decided)
            seconds["refinement"] = time.perf_counter() - t2
    # Re-anchor exactly on scan 0 (the gauge), whatever the optimiser did with the reference node.
    optimized = anchored(optimized, init_poses[0])
    if not segments.starts:  # joined recordings: the input's distance across a join is no measurement
        optimized, decided["distances"] = keep_input_distances(scans, optimized, init_poses, settings)
    return BaselineResult(optimized, seconds=seconds, **decided)


def _log_joined(segments: Segments) -> None:
    """One log line for recordings joined in one sequence (none: nothing)."""
    if segments.starts:
        logger.info(
            "baseline: %d recordings joined: the chain restarts from the input pose at scan(s) %s (each later "
            "recording's first, placed in the first one's frame), and %d links from the placing join them in "
            "the pose graph",
            len(segments.starts) + 1,
            ", ".join(map(str, segments.starts)),
            len(segments.links),
        )


def _chosen_chain(
    clouds: list,
    scans: list[np.ndarray],
    init_poses: np.ndarray,
    settings: BaselineSettings,
    deadline: float | None,
    progress: bool,
    segments: Segments,
) -> tuple[np.ndarray | None, dict]:
    """Both chains (the input's tilt kept, free) and the one that goes on -> (its poses [S, 4, 4], None when given
    up; {"tilt", "chain_entropy", "chain_given_up"} for BaselineResult)."""
    t0 = time.perf_counter()
    chains, fitness = {}, {}
    for name, keep_tilt in (("input tilt", True), ("free", False)):
        chains[name], fitness[name] = scan_to_map_chain(
            clouds, init_poses, settings, keep_tilt, deadline, progress, segments
        )
    chosen, entropy = choose_chain(chains, scans, settings)
    chain = chains[chosen]
    if chain is not None:
        logger.info(
            "baseline: the chain %s (raw-map entropy: %s; median overlap %.0f%%), %.1f s for both",
            "keeps the input's tilt" if chosen == "input tilt" else "finds its own tilt: the input's drifted",
            _entropy_text(entropy) or "one chain held",
            100 * np.nanmedian(fitness[chosen][1:]),
            time.perf_counter() - t0,
        )
    tilt = None if chain is None else ("input" if chosen == "input tilt" else "free")
    return chain, {"tilt": tilt, "chain_entropy": entropy, "chain_given_up": chain is None}


def _refined(
    clouds: list,
    scans: list[np.ndarray],
    optimized: np.ndarray,
    chain: np.ndarray | None,
    settings: BaselineSettings,
    hooks: tuple,
    decided: dict,
) -> np.ndarray:
    """The multi-view refinement from the crisper of the graph's poses `optimized` [S, 4, 4] and the chain [S, 4, 4]
    (the input's when chain is None) -> its poses [S, 4, 4]. hooks: (on_round, deadline, progress) of
    register_sequence; decided: BaselineResult's fields so far, updated with where the rounds started and how many
    were done."""
    on_round, deadline, progress = hooks
    # The graph's poses carry round-off in the rotations; re-orthonormalise before moving clouds with them.
    optimized = _orthonormal(optimized)
    if chain is not None:
        start, entropy = choose_refinement_start(optimized, _orthonormal(chain), scans, settings)
        decided.update(refined_from=start, start_entropy=entropy)
        logger.info(
            "baseline: the multi-view refinement starts from the %s's poses (raw-map entropy: %s)",
            start,
            _entropy_text(entropy),
        )
        optimized = _orthonormal(chain) if start == "chain" else optimized
    if on_round is not None:
        on_round(0, optimized.copy())
    t0 = time.perf_counter()
    optimized, refinement = refine_against_map(clouds, optimized, settings, on_round, deadline, progress)
    logger.info(
        "baseline: %g round(s) of multi-view refinement in %.1f s (%.0f%% of the registrations rejected by the gates)",
        refinement.rounds_done,
        time.perf_counter() - t0,
        100 * refinement.rejected,
    )
    decided.update(map_rounds_done=refinement.rounds_done, stopped_at_deadline=refinement.stopped)
    return optimized


def _between_recordings(loops) -> str:
    """The pose graph's joins between recordings, for the log (loops: graph.LoopClosures)."""
    return (
        f"; between recordings {loops.across_kept} of {loops.across_tried} ICP candidates kept (with the global "
        f"closures) and {loops.linked} links from the placing ({loops.links_in_final_graph} of them left in the "
        "final graph: a recording joined by a closure keeps the closures)"
    )


def _entropy_text(entropy: dict) -> str:
    return ", ".join(f"{name} {'-' if value is None else f'{value:.3f}'}" for name, value in entropy.items())


def anchored(poses: np.ndarray, pose0: np.ndarray) -> np.ndarray:
    """poses [S, 4, 4] moved rigidly so that poses[0] is pose0 [4, 4] exactly (the gauge), rotations
    re-orthonormalised."""
    return _orthonormal(anchored_on_first(poses, pose0)[0])


def _orthonormal(poses: np.ndarray) -> np.ndarray:
    """poses [S, 4, 4] with the nearest rotations in their rotation blocks (removes an optimiser's round-off)."""
    poses = np.array(poses, dtype=np.float64)
    poses[:, :3, :3] = nearest_rotations(poses[:, :3, :3])
    return poses
