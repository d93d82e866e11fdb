"""The baseline's multi-view refinement (step 4 of neld_jax.baseline): rounds in which each scan is registered again
to the map of the other scans, and where those rounds start."""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from neld_jax.baseline.graph import passes_loop_gates
from neld_jax.baseline.icp import correction_m, multiscale_icp
from neld_jax.baseline.settings import BaselineSettings, progress_bar
from neld_jax.geometry import register_scans, transform_points
from neld_jax.judging import judge


def _world_map(clouds: list, poses: np.ndarray, scans, settings: BaselineSettings) -> o3d.geometry.PointCloud:
    """The scans `scans` (indices) in the world frame at poses [S, 4, 4], merged, voxel-downsampled, with normals
    estimated again (averaging the normals of overlapping scans would blur or cancel them)."""
    points = register_scans([np.asarray(clouds[k].points) for k in scans], poses[list(scans)])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if settings.voxel_size_m > 0:
        cloud = cloud.voxel_down_sample(settings.voxel_size_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=settings.normal_radius_m, max_nn=30))
    return cloud


@dataclasses.dataclass(frozen=True)
class Refinement:
    """What `refine_against_map` did: rounds_done, the rounds completed, with the fraction of the last one when a
    deadline stopped it (1.4: one round and 40 % of the scans of the second); rejected, the fraction of its
    registrations the gates rejected; stopped, whether the deadline stopped it before settings.map_rounds."""

    rounds_done: float
    rejected: float
    stopped: bool


def choose_refinement_start(
    graph: np.ndarray, chain: np.ndarray, scans: list[np.ndarray], settings: BaselineSettings
) -> tuple[str, dict]:
    """Where the multi-view refinement starts: the crisper of the graph's and the chain's poses [S, 4, 4] (a tie, or
    no judge, keeps the graph) -> ("graph" | "chain", {name: mean map entropy})."""
    summaries, _ = judge.compare_maps(
        scans, {"graph": graph, "chain": chain}, settings.crispness_radius_m, settings.crispness_queries
    )
    entropy = {name: summary["mean_map_entropy"] for name, summary in summaries.items()}
    crisper = judge.crispest(summaries)
    return ("chain" if crisper == "chain" and entropy["chain"] < entropy["graph"] else "graph"), entropy


def refine_against_map(
    clouds: list,
    poses: np.ndarray,
    settings: BaselineSettings,
    on_round: Callable[[int, np.ndarray], None] | None = None,
    deadline: float | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, Refinement]:
    """`settings.map_rounds` rounds of multi-view refinement (neld_jax.baseline, step 4); scan 0 stays.

    clouds: S Open3D clouds (sensor frame); poses: [S, 4, 4] sensor -> world. on_round(r, poses [S, 4, 4]), when
    given, sees a copy of the poses after each round r = 1 .. map_rounds (benchmarks/baseline_rounds.py).
    deadline: a time.perf_counter() value; no scan is registered after it (each registration moves one scan against
    the others' map, so the poses between two registrations are an answer too; neld_jax.run's `baseline_deadline`).
    progress: a progress bar over the scans of all rounds. Returns (poses [S, 4, 4], Refinement)."""
    poses = np.array(poses, dtype=np.float64)
    tried = rejected = 0
    bar = progress_bar(
        f"{settings.map_rounds} round(s) of multi-view refinement", progress, total=settings.map_rounds * len(clouds)
    )

    def report(rounds_done: float, stopped: bool) -> tuple[np.ndarray, Refinement]:
        bar.close()
        return poses, Refinement(round(rounds_done, 3), rejected / max(tried, 1), stopped)

    for round_index in range(1, settings.map_rounds + 1):
        visited = 0  # scans of this round registered, or skipped as the gauge, before a deadline
        for half in (0, 1):
            others = [k for k in range(len(clouds)) if k % 2 != half]
            if not others:
                continue
            if deadline is not None and time.perf_counter() > deadline:
                return report(round_index - 1 + visited / len(clouds), True)
            target = _MapTarget(_world_map(clouds, poses, others, settings))
            for s in range(half, len(clouds), 2):
                if deadline is not None and time.perf_counter() > deadline:
                    return report(round_index - 1 + visited / len(clouds), True)
                visited += 1
                bar.update()
                if s == 0:  # the gauge
                    continue
                tried += 1
                moved = target.register(clouds[s], poses[s], settings)
                if moved is None:
                    rejected += 1
                    continue
                poses[s] = moved
        if on_round is not None:
            on_round(round_index, poses.copy())
    return report(settings.map_rounds, False)


class _MapTarget:
    """The map of one half of the scans (an Open3D cloud with normals), with a KD-tree of its points, that the other
    half's scans register to."""

    def __init__(self, world: o3d.geometry.PointCloud):
        self.points, self.normals = np.asarray(world.points), np.asarray(world.normals)
        self.tree = cKDTree(self.points)

    def register(
        self, cloud: o3d.geometry.PointCloud, pose: np.ndarray, settings: BaselineSettings
    ) -> np.ndarray | None:
        """cloud (sensor frame) at pose [4, 4] registered to the map points near it -> its pose [4, 4], or None
        when too few map points are near or the loop closures' gates reject the result."""
        # The target: each scan point's nearest map points (one vectorised query; "missing" ones come back as index
        # len(points)).
        _, near = self.tree.query(
            transform_points(np.asarray(cloud.points), pose),
            k=settings.map_gather_points,
            distance_upper_bound=settings.map_gather_m,
        )
        near = np.unique(near[near < len(self.points)])
        if len(near) < 3:
            return None
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points[near]))
        target.normals = o3d.utility.Vector3dVector(self.normals[near])
        # sensor -> world; the map's normals were estimated again, their signs unknown
        map_icp = dataclasses.replace(settings, icp_distances_m=settings.map_icp_distances_m)
        transform, result = multiscale_icp(cloud, target, pose, map_icp, oriented=False)
        if not passes_loop_gates(result, correction_m(pose, transform), settings):
            return None
        return transform
