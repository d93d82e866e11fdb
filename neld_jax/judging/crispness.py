"""Map quality without ground truth: how crisp the raw map is under a set of poses.

Misregistered scans smear every surface into a thicker, fuzzier layer, so the spread of each map point's
neighbourhood measures registration. Two standard figures, both from the covariance S of the map points
within `radius` of a query point:
- mean map entropy (MME; Droeschel & Behnke 2018, the figure HBA reports): the mean over query points of the
  differential entropy of a Gaussian with covariance S, 0.5 ln det(2 pi e S). Lower is crisper; in nats, and
  -3.5 is a thin layer of a few cm.
- mean plane thickness: the mean over query points of sqrt(lambda_min(S)), the spread along the neighbourhood's
  normal, in metres.

Query points with fewer than `min_neighbors` neighbours (themselves included) are skipped and counted. Both
figures depend on the point density, so compare maps built from the same scans (before/after, or two
methods), never across sequences. Pure numpy + a SciPy KD-tree; see docs/evaluation.md.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

DEFAULT_RADIUS_M = 0.3
DEFAULT_MIN_NEIGHBORS = 5
DEFAULT_MAX_QUERIES = 10_000
DEFAULT_DRAWS = 5  # draws of the query points a comparison of two maps is judged over (eval.crispness_draws)
_EIGENVALUE_FLOOR = 1e-12  # m^2: collinear neighbourhoods would give ln(0); 1e-6 m is far below LiDAR noise


class Crispness(NamedTuple):
    """Per-query results (Q queries, NaN where skipped) and their means."""

    entropy: np.ndarray  # [Q] nats, 0.5 ln det(2 pi e S)
    thickness: np.ndarray  # [Q] metres, sqrt(lambda_min(S))
    query_index: np.ndarray  # [Q] int64 index of each query in the map's points

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.entropy)

    def summary(self) -> dict:
        valid = self.valid
        return {
            "mean_map_entropy": float(np.mean(self.entropy[valid])) if valid.any() else None,
            "mean_plane_thickness_m": float(np.mean(self.thickness[valid])) if valid.any() else None,
            "queries": int(len(self.entropy)),
            "queries_skipped": int((~valid).sum()),
        }


def neighbourhood_covariances(
    points: np.ndarray, queries: np.ndarray, radius: float, tree: cKDTree | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (1/n, not 1/(n-1)) of the points within `radius` of each query, with the query's own point.

    points: [N, 3], queries: [Q, 3] -> (covariances [Q, 3, 3], neighbour counts [Q] int64). tree: a cKDTree of
    points, built here when None (a second with the same map reuses it: about 1 s for a million points).
    """
    points = np.asarray(points, dtype=np.float64)
    queries = np.asarray(queries, dtype=np.float64)
    if len(queries) == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64)
    tree = cKDTree(points) if tree is None else tree
    neighbours = tree.query_ball_point(queries, radius, workers=-1, return_sorted=False)
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(neighbours))
    flat = np.fromiter((i for n in neighbours for i in n), dtype=np.int64, count=int(counts.sum()))
    owner = np.repeat(np.arange(len(queries)), counts)
    # Centre on the query point before summing, so large world coordinates do not cost precision.
    centred = points[flat] - queries[owner]
    n = np.maximum(counts, 1).astype(np.float64)
    q = len(queries)

    def per_query_sum(values):  # bincount is ~10x faster than np.add.at
        return np.bincount(owner, weights=values, minlength=q)

    mean = np.stack([per_query_sum(centred[:, a]) for a in range(3)], axis=-1) / n[:, None]
    second = np.stack(
        [np.stack([per_query_sum(centred[:, a] * centred[:, b]) for b in range(3)], axis=-1) for a in range(3)], axis=-2
    )
    covariances = second / n[:, None, None] - mean[:, :, None] * mean[:, None, :]
    return covariances, counts


def crispness(
    points: np.ndarray,
    radius: float = DEFAULT_RADIUS_M,
    min_neighbors: int = DEFAULT_MIN_NEIGHBORS,
    max_queries: int = DEFAULT_MAX_QUERIES,
    seed: int = 0,
    query_index: np.ndarray | None = None,
    tree: cKDTree | None = None,
) -> Crispness:
    """MME and plane thickness of a map. points: [N, 3] metres.

    The queries are `query_index` (indices into points) if given, else a seeded random subset of at most
    `max_queries` points (all points when there are fewer): the same seed and map size pick the same points, so
    two registrations of the same scans are compared on the same query points. tree: a cKDTree of points, or None.
    """
    points = np.asarray(points, dtype=np.float64)
    if query_index is None:
        query_index = sample_queries(len(points), max_queries, seed)
    query_index = np.asarray(query_index, dtype=np.int64)
    covariances, counts = neighbourhood_covariances(points, points[query_index], radius, tree)
    eigenvalues = np.maximum(np.linalg.eigvalsh(covariances), _EIGENVALUE_FLOOR) if len(counts) else np.zeros((0, 3))
    entropy = 0.5 * np.sum(np.log(2.0 * math.pi * math.e * eigenvalues), axis=-1)
    thickness = np.sqrt(eigenvalues[:, 0]) if len(counts) else np.zeros(0)
    skipped = counts < min_neighbors
    entropy = np.where(skipped, np.nan, entropy)
    thickness = np.where(skipped, np.nan, thickness)
    return Crispness(entropy, thickness, query_index)


def entropy_over_query_draws(
    maps: dict[str, np.ndarray],
    seeds,
    max_queries: int = DEFAULT_MAX_QUERIES,
    radius: float = DEFAULT_RADIUS_M,
    deadline: float | None = None,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Mean map entropy of each map over several draws of the query points: {name: [D] nats}, D = len(seeds), or
    fewer when a time.perf_counter() `deadline` would pass: no draw starts that would end after it, judged by the
    draw before (each map's KD-tree is built once).

    maps: {name: [N, 3]} registrations of the same scans (the same points in the same order), so each draw
    queries the same points of every map and the differences between maps are paired. One draw of 10,000
    queries moves a sequence's entropy by about 0.01 nats, more than some differences between methods, and its
    pairing does not remove all of that: the spread of the paired difference over draws says whether a
    difference is resolved (docs/evaluation.md, "How sure a difference is"). progress: a progress bar over the
    draws (a minute on a real recording's maps)."""
    from tqdm.auto import tqdm  # an effect at the edge, off by default

    sizes = {len(points) for points in maps.values()}
    if len(sizes) > 1:
        raise ValueError(f"the maps must register the same points; their sizes differ: {sorted(sizes)}")
    num_points = sizes.pop() if sizes else 0
    trees: dict[str, cKDTree] = {}
    out = {name: [] for name in maps}
    draws = tqdm(seeds, desc="crispness over query draws", unit="draw", disable=not progress, dynamic_ncols=True)
    last_draw_s = 0.0
    for seed in draws:
        started = time.perf_counter()
        if deadline is not None and started + last_draw_s > deadline:  # it would end past the deadline
            break
        queries = sample_queries(num_points, max_queries, int(seed))
        for name, points in maps.items():
            if name not in trees:  # not setdefault: its default would build a tree every draw
                trees[name] = cKDTree(np.asarray(points, dtype=np.float64))
            tree = trees[name]
            entropy = crispness(points, radius=radius, query_index=queries, tree=tree).summary()["mean_map_entropy"]
            out[name].append(np.nan if entropy is None else entropy)
        last_draw_s = time.perf_counter() - started  # the first draw also builds the trees: an upper bound
    draws.close()
    return {name: np.asarray(values, dtype=np.float64) for name, values in out.items()}


def sample_queries(num_points: int, max_queries: int, seed: int = 0) -> np.ndarray:
    """Sorted indices [min(num_points, max_queries)] int64, a seeded random subset of range(num_points)."""
    if max_queries <= 0 or num_points <= max_queries:
        return np.arange(num_points, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(num_points, size=max_queries, replace=False))


def per_scan_means(
    values: np.ndarray, query_index: np.ndarray, scan_of_point: np.ndarray, num_scans: int
) -> np.ndarray:
    """Mean of per-query values [Q] over the queries that came from each scan (NaNs ignored) -> [S] (NaN if none).

    scan_of_point: [N] the scan each map point came from."""
    scan = np.asarray(scan_of_point)[query_index]
    valid = np.isfinite(values)
    sums = np.bincount(scan[valid], weights=values[valid], minlength=num_scans)
    counts = np.bincount(scan[valid], minlength=num_scans)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
