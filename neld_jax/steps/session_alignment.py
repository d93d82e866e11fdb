"""Recordings of one place put in one frame: each recording after the first is placed in the first one's frame by
place recognition between the recordings' local maps (MapClosures, the loop detector of KISS-SLAM: BEV density
maps matched by ORB features), each candidate registered from no guess (FPFH + RANSAC, then ICP: MapClosures' own
2-D alignment was metres off on the synthetic courtyard) and kept by its overlap; where no local maps match, the
whole maps are registered so. A recording that matches no place of the first stops the run with one line naming it
and the best overlap found: a merged map is never written with a recording misplaced.

`load_sessions` is step 1 of a run for `data.root` naming several folders (neld_jax.data.sessions): each recording
loaded as one sequence would be, aligned, and joined into the one sequence the run trains on.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.baseline import BaselineSettings, TargetIndex, fpfh_features, global_registration, prepare_scan
from neld_jax.data import sessions as data_sessions
from neld_jax.errors import DataError
from neld_jax.geometry import invert_poses

logger = logging.getLogger(__name__)

LOCAL_MAP_SPACING_M = 1.0  # local maps are centred on keyframes at least this far apart along the route ...
LOCAL_MAP_HALF_WINDOW = 2  # ... each holds its keyframe with the 2 before and after it, in its frame ...
LOCAL_MAP_HALF_PATH_M = 5.0  # ... or with those within 5 m of route either side where they are more ...
MAX_LOCAL_MAP_HALF = 20  # ... but at most 20 either side
CANDIDATES_PER_MAP = 5  # MapClosures' best matches asked for per local map of a later recording ...
MAX_VERIFIED = 6  # ... of which the most inliers are registered, at most this many
ENOUGH_CLOSURES = 2  # verification stops once this many overlap enough
OVERLAP_DISTANCE_M = 0.3  # a point of one local map within this of the other's lies on it (register_scans' fit) ...
MIN_OVERLAP = 0.7  # ... and a closure between recordings has at least this share of its points on the other map
# The baseline's global registration (FPFH on a 0.5 m grid, RANSAC, ICP from 1 m down to 0.1 m) on a 0.2 m grid:
# local maps of five keyframes hold ~50k points, and the placing only has to be within the pose graph's reach.
ICP = BaselineSettings(voxel_size_m=0.2)


@dataclasses.dataclass(frozen=True)
class Closure:
    """A place seen by two recordings: keyframe `query` of the later one and keyframe `reference` of the first;
    transform [4, 4] maps the query keyframe's frame into the reference's; overlap: the share of the query's local
    map (or whole map) within OVERLAP_DISTANCE_M of the reference's after registration; inliers: MapClosures'
    feature matches."""

    query: int
    reference: int
    transform: np.ndarray
    overlap: float
    inliers: int  # 0: the whole maps registered (whole_map_closure)

    def record(self) -> dict:
        return {
            "keyframe": self.query,
            "first_keyframe": self.reference,
            "overlap": round(self.overlap, 4),
            "map_closures_inliers": self.inliers,
            "by": "local maps" if self.inliers else "whole maps",
        }


def local_map_centres(poses: np.ndarray, spacing_m: float = LOCAL_MAP_SPACING_M) -> np.ndarray:
    """[C] int64: the keyframes (poses [K, 4, 4], in order) whose local maps are matched: the first, then each
    one at least spacing_m of route after the last chosen."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    centres = [0]
    for k in range(1, len(poses)):
        if path[k] - path[centres[-1]] >= spacing_m:
            centres.append(k)
    return np.asarray(centres, np.int64)


def local_map_members(
    poses: np.ndarray, centre: int, half_window: int = LOCAL_MAP_HALF_WINDOW, half_path_m: float = LOCAL_MAP_HALF_PATH_M
) -> range:
    """Which keyframes make keyframe centre's local map (poses [K, 4, 4], in order): those within half_window of
    it, or within half_path_m of route of it where that holds more (dense keyframes), at most MAX_LOCAL_MAP_HALF
    either side."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    near = np.flatnonzero(np.abs(path - path[centre]) <= half_path_m)
    first = max(0, centre - MAX_LOCAL_MAP_HALF, min(centre - half_window, int(near[0])))
    last = min(len(poses) - 1, centre + MAX_LOCAL_MAP_HALF, max(centre + half_window, int(near[-1])))
    return range(first, last + 1)


def local_maps(scans: list[np.ndarray], poses: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The local maps of a recording's keyframes (scans: K arrays [N_i, 3], sensor frames; poses [K, 4, 4]) ->
    (their centres [C] (local_map_centres), C arrays [M_c, 3]: each centre's local_map_members in its frame)."""
    centres, maps = local_map_centres(poses), []
    for centre in centres:
        into_centre = invert_poses(poses[centre])
        parts = []
        for k in local_map_members(poses, int(centre)):
            relative = into_centre @ poses[k]
            parts.append(scans[k] @ relative[:3, :3].T + relative[:3, 3])
        maps.append(np.concatenate(parts))
    return centres, maps


def place_candidates(
    reference_maps: list[np.ndarray], query_maps: list[np.ndarray], per_map: int = CANDIDATES_PER_MAP
) -> list[tuple[int, int, int]]:
    """MapClosures' matches of each query local map among the reference ones -> [(query k, reference j, inliers)]
    (indices into the lists; at most per_map per query map), most inliers first. Every match is asked for: the
    query's own neighbours in its recording, added before it, match best and would fill a top k."""
    from map_closures.map_closures import MapClosures

    closures = MapClosures()
    for j, points in enumerate(reference_maps):
        closures.get_best_closure(j, points)  # adds map j to the database
    found, first = [], len(reference_maps)
    for k, points in enumerate(query_maps):
        matches = [
            (min(c.source_id, c.target_id), int(c.number_of_inliers))
            for c in closures.get_top_k_closures(first + k, points, first + k)
        ]
        across = sorted(((j, inliers) for j, inliers in matches if j < first), key=lambda m: -m[1])
        found.extend((k, j, inliers) for j, inliers in across[:per_map])
    return sorted(found, key=lambda c: -c[2])


def verify(query_map: np.ndarray, reference_map: np.ndarray) -> tuple[np.ndarray, float]:
    """Register query_map [N, 3] onto reference_map [M, 3] from no guess (FPFH + RANSAC, then ICP) -> (transform
    [4, 4] mapping the query map into the reference's frame, overlap: the share of the query's points within
    OVERLAP_DISTANCE_M of the reference's)."""
    source = prepare_scan(query_map, ICP.voxel_size_m, ICP.normal_radius_m)
    target = prepare_scan(reference_map, ICP.voxel_size_m, ICP.normal_radius_m)
    transform, _ = global_registration(source, target, fpfh_features(source, ICP), fpfh_features(target, ICP), ICP)
    points = np.asarray(source.points) @ transform[:3, :3].T + transform[:3, 3]
    nearest, _ = TargetIndex(target, OVERLAP_DISTANCE_M).nearest(points, OVERLAP_DISTANCE_M)
    return transform, float(np.mean(nearest >= 0))


def find_closures(reference: tuple[list, np.ndarray], query: tuple[list, np.ndarray]) -> list[Closure]:
    """The places a later recording shares with the first: reference and query are (keyframe scans, their poses
    [K, 4, 4] in the recording's own frame). MapClosures' candidates verified (verify) in order of inliers, at most
    MAX_VERIFIED, until ENOUGH_CLOSURES overlap MIN_OVERLAP, and where none does the whole maps
    (whole_map_closure) -> every closure tried, best overlap first."""
    (reference_centres, reference_maps), (query_centres, query_maps) = local_maps(*reference), local_maps(*query)
    candidates = place_candidates(reference_maps, query_maps)
    logger.info(
        "place recognition (MapClosures): %d candidate places between the recordings' %d and %d local maps",
        len(candidates),
        len(reference_maps),
        len(query_maps),
    )
    closures = []
    for k, j, inliers in candidates[:MAX_VERIFIED]:
        transform, overlap = verify(query_maps[k], reference_maps[j])
        closures.append(Closure(int(query_centres[k]), int(reference_centres[j]), transform, overlap, inliers))
        if sum(c.overlap >= MIN_OVERLAP for c in closures) >= ENOUGH_CLOSURES:
            break
    if not any(c.overlap >= MIN_OVERLAP for c in closures):
        closures.append(whole_map_closure(reference, query))
    return sorted(closures, key=lambda c: -c.overlap)


def whole_map_closure(reference: tuple[list, np.ndarray], query: tuple[list, np.ndarray]) -> Closure:
    """Where no local maps match (MapClosures found HKU_2's two halves no candidate): the later recording's whole
    raw map registered to the first one's (verify), each in its keyframe 0's frame; a Closure between the two
    keyframes 0. Fits recordings whose own poses hold over their route (a LiDAR-inertial odometry's)."""
    maps = []
    for scans, poses in (reference, query):
        into_first = invert_poses(poses[0]) @ poses
        maps.append(np.concatenate([scan @ pose[:3, :3].T + pose[:3, 3] for scan, pose in zip(scans, into_first)]))
    transform, overlap = verify(maps[1], maps[0])
    logger.info("whole maps registered: overlap %.0f%%", 100 * overlap)
    return Closure(0, 0, transform, overlap, 0)


def frame_to_first(closure: Closure, reference_poses: np.ndarray, query_poses: np.ndarray) -> np.ndarray:
    """The later recording's frame -> the first one's [4, 4], from a closure and both recordings' keyframe poses
    [K, 4, 4] (each in its own frame)."""
    return reference_poses[closure.reference] @ closure.transform @ invert_poses(query_poses[closure.query])


def align_session(
    reference: tuple[list, np.ndarray], query: tuple[list, np.ndarray], name: str, first_name: str
) -> tuple[np.ndarray, list[Closure]]:
    """The later recording `name` in the first one's frame -> (its frame -> the first's [4, 4], the closures
    found, overlap at least MIN_OVERLAP, best first). A DataError naming it and the best overlap found when none
    overlaps enough."""
    closures = find_closures(reference, query)
    kept = [c for c in closures if c.overlap >= MIN_OVERLAP]
    if not kept:
        best = f"{closures[0].overlap:.0%}" if closures else "none (no candidate place)"
        raise DataError(
            f"data.root: recording {name} matches no place of {first_name} (best overlap {best}, at "
            f"least {MIN_OVERLAP:.0%} needed); is it a recording of the same place?"
        )
    transform = frame_to_first(kept[0], reference[1], query[1])
    logger.info(
        "recording %s placed in %s's frame: %d closures between them (best overlap %.0f%%)",
        name,
        first_name,
        len(kept),
        100 * kept[0].overlap,
    )
    return transform, kept


def load_sessions(data_cfg, budget_s: float = 0.0):
    """Step 1 of a run: data.root's recordings (data_cfg: config.data) -> (every input scan, the keyframes,
    neld_jax.data.sessions.Sessions or None), all in the first recording's frame. One folder: the sequence as
    neld_jax.steps.inputs.load_keyframes reads it, and None. budget_s: the run's seconds (0: no limit), for the
    front-end's forecast."""
    from neld_jax.steps.inputs import load_keyframes

    roots = data_sessions.session_roots(data_cfg.root)
    if len(roots) < 2:
        return (*load_keyframes(data_cfg, budget_s), None)
    names = data_sessions.session_names(roots)
    loaded, keyframes = [], []
    for root in roots:
        cfg = data_cfg.copy_and_resolve_references()
        cfg.root = root
        one_loaded, one_keyframes = load_keyframes(cfg, budget_s)
        loaded.append(one_loaded)
        keyframes.append(one_keyframes)
    to_first, closures = [np.eye(4)], [[]]
    first = (keyframes[0].scans, keyframes[0].poses)
    for r in range(1, len(roots)):
        transform, found = align_session(first, (keyframes[r].scans, keyframes[r].poses), names[r], names[0])
        to_first.append(transform)
        closures.append(found)
    joined_loaded, joined_keyframes, sessions = data_sessions.concatenate(loaded, keyframes, np.stack(to_first), names)
    records = [[closure.record() for closure in found] for found in closures]
    transforms = [[closure.transform for closure in found] for found in closures]
    return (
        joined_loaded,
        joined_keyframes,
        dataclasses.replace(sessions, closures=records, closure_transforms=transforms),
    )
