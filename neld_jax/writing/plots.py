"""PNG figures of a run: trajectories from above, per-scan pose errors, map-error histograms.

Uses matplotlib's Agg backend (no display needed). Each function writes one file and returns its path.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: servers and CI have no display
import matplotlib.patches  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

logger = logging.getLogger(__name__)


def _save(fig: plt.Figure, path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    logger.info("wrote %s", path)
    return path


def plot_trajectories(
    path: str | os.PathLike, trajectories: dict[str, np.ndarray], gt: np.ndarray | None = None
) -> Path:
    """Top view (x-y) of each trajectory; trajectories: {name: poses [S, 4, 4]}, gt: [G, 4, 4] or None.

    Trajectories should already be in one frame (e.g. aligned to the ground truth).
    """
    fig, ax = plt.subplots(figsize=(6.5, 6.0))
    if gt is not None:
        gt = np.asarray(gt)
        ax.plot(gt[:, 0, 3], gt[:, 1, 3], "k--", linewidth=2.0, label="ground truth")
    for name, poses in trajectories.items():
        poses = np.asarray(poses)
        ax.plot(poses[:, 0, 3], poses[:, 1, 3], marker=".", markersize=4, linewidth=1.2, label=name)
    first = gt if gt is not None else next(iter(trajectories.values()), None)
    first = None if first is None else np.asarray(first)
    if first is not None and len(first):
        ax.plot(first[0, 0, 3], first[0, 1, 3], "g^", markersize=9, label="start")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectories (top view)")
    return _save(fig, path)


def plot_pose_errors(
    path: str | os.PathLike, per_scan_errors: dict[str, np.ndarray], ylabel: str = "translation error [m]"
) -> Path:
    """Error of each scan's pose, one line per method; per_scan_errors: {name: errors [S]}."""
    fig, ax = plt.subplots(figsize=(7.0, 3.8))
    for name, errors in per_scan_errors.items():
        errors = np.asarray(errors)
        ax.plot(np.arange(len(errors)), errors, marker=".", markersize=4, linewidth=1.2, label=name)
    ax.set_xlabel("scan")
    ax.set_ylabel(ylabel)
    ax.set_ylim(bottom=0.0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Per-scan pose error (after alignment)")
    return _save(fig, path)


def plot_error_histogram(
    path: str | os.PathLike, distances: dict[str, np.ndarray], threshold: float, max_distance: float | None = None
) -> Path:
    """Histogram of map-to-ground-truth distances per map; distances: {name: [N]} in metres.

    Distances beyond max_distance (default 5 x threshold) are gathered in the last bin, so outliers
    stay visible. The threshold is drawn as a vertical line.
    """
    max_distance = 5.0 * threshold if max_distance is None else max_distance
    bins = np.linspace(0.0, max_distance, 51)
    fig, ax = plt.subplots(figsize=(7.0, 3.8))
    for name, values in distances.items():
        values = np.asarray(values, dtype=np.float64)
        if len(values) == 0:
            continue
        ax.hist(
            np.minimum(values, max_distance),
            bins=bins,
            histtype="step",
            linewidth=1.5,
            weights=np.full(len(values), 100.0 / len(values)),
            label=f"{name} (n={len(values)})",
        )
    ax.axvline(threshold, color="k", linestyle="--", linewidth=1.0, label=f"threshold {threshold:g} m")
    ax.set_xlabel(f"distance to ground-truth map [m] (last bin: >= {max_distance:g})")
    ax.set_ylabel("points [%]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Map error histogram")
    return _save(fig, path)


def plot_scan_report(path: str | os.PathLike, rows: list[dict]) -> Path:
    """Per keyframe: median range residual, the bundle adjustment's refinement and the correction from the input,
    flagged scans in red (see neld_jax.judging.report)."""
    keyframes = [row for row in rows if row["keyframe"]]
    index = np.array([row["scan"] for row in keyframes])
    flagged = np.array([bool(row["flag"]) for row in keyframes], bool)

    def column(name):
        return np.array([np.nan if row.get(name) is None else row[name] for row in keyframes], np.float64)

    panels = (
        (column("median_residual_m"), "median range residual [m]"),
        (column("refinement_cm"), "NeLD-BA refinement [cm]"),
        (column("correction_cm"), "correction from input [cm]"),
    )
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 7.0), sharex=True)
    for ax, (values, label) in zip(axes, panels):
        ax.plot(index, values, ".", color="tab:blue", markersize=4)
        ax.plot(index[flagged], values[flagged], "o", color="tab:red", markersize=6, label="flagged")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("scan (input index)")
    if flagged.any():
        axes[0].legend(loc="best", fontsize=8)
    axes[0].set_title(f"Per-scan report: {int(flagged.sum())} of {len(keyframes)} keyframes flagged")
    return _save(fig, path)


def detail_window(maps_xy: list[np.ndarray], lo_xy: np.ndarray, hi_xy: np.ndarray, side: float) -> tuple[float, float]:
    """Lower-left corner (x, y) of the side x side square inside [lo_xy, hi_xy] where the first and the last map
    differ most; maps_xy: [[N_k, 2]] points seen from above.

    Each map becomes a histogram of 1/64-of-the-side cells, normalised by its point count; the window maximises
    the summed absolute difference (where the poses moved the map most, sharpened or blurred alike), found with
    a summed-area table, and is centred on that difference within it."""
    cell = side / 64.0
    shape = np.maximum(np.ceil((hi_xy - lo_xy) / cell).astype(int), 64)
    edges = [lo_xy[axis] + cell * np.arange(shape[axis] + 1) for axis in range(2)]
    histograms = []
    for points in (maps_xy[0], maps_xy[-1]):
        counts = np.histogram2d(points[:, 0], points[:, 1], bins=edges)[0]
        histograms.append(counts / max(len(points), 1))
    difference = np.abs(histograms[0] - histograms[1])
    table = np.zeros((shape[0] + 1, shape[1] + 1))
    table[1:, 1:] = difference.cumsum(0).cumsum(1)
    window = table[64:, 64:] - table[:-64, 64:] - table[64:, :-64] + table[:-64, :-64]  # [nx - 63, ny - 63]
    i, j = np.unravel_index(np.argmax(window), window.shape)
    # Windows that hold the same change tie; centre the first one on its difference's centroid instead of leaving
    # the change at its edge.
    for _ in range(4):  # a few mean-shift steps
        block = difference[i : i + 64, j : j + 64]
        if block.sum() <= 0:
            break
        ci, cj = np.array([np.arange(64) @ block.sum(1), np.arange(64) @ block.sum(0)]) / block.sum()
        i = int(np.clip(round(i + ci - 31.5), 0, window.shape[0] - 1))
        j = int(np.clip(round(j + cj - 31.5), 0, window.shape[1] - 1))
    return float(edges[0][i]), float(edges[1][j])


def plot_map_topdown(
    path: str | os.PathLike, maps: dict[str, np.ndarray], max_points: int = 400_000, seed: int = 0
) -> Path:
    """Raw maps seen from above on the same axes, and below them a close-up of each where the first and the last
    map differ most; maps: {title: points [N, 3]}.

    Points are drawn small and translucent, coloured by height, so a misregistered wall shows as a double or
    blurred line. Maps wider than tall (a drive) are stacked, each the figure's width; others sit side by side.
    The close-up is a square of a fifth of the map's longer side (8 m at least, the shorter side at most; its
    outline is drawn on the maps), where a centimetre-level change is visible, which a whole route at screen
    resolution cannot show. At most max_points per map and per close-up (a seeded random subset)."""
    rng = np.random.default_rng(seed)
    items = [(title, np.asarray(points)) for title, points in maps.items() if len(points)]
    if not items:
        fig, _ = plt.subplots(figsize=(6.0, 6.0))
        return _save(fig, path)
    count = len(items)
    everything = np.concatenate([points for _, points in items])
    low, high = np.percentile(everything[:, 2], [2, 98])
    # The 0.5-99.5 percentiles, not min/max: a few far returns would shrink the map to a corner.
    lo_xy, hi_xy = np.percentile(everything[:, :2], 0.5, axis=0), np.percentile(everything[:, :2], 99.5, axis=0)
    pad = 0.03 * (hi_xy - lo_xy)
    lo_xy, hi_xy = lo_xy - pad, hi_xy + pad
    width, height = np.maximum(hi_xy - lo_xy, 1e-3)
    side = float(min(max(0.2 * max(width, height), 8.0), min(width, height)))
    corner = np.array(detail_window([points[:, :2] for _, points in items], lo_xy, hi_xy, side))

    stacked = width > 1.3 * height
    if stacked:  # one row per map at the figure's full width, then the close-ups side by side
        overview_h = float(np.clip(11.0 * height / width, 0.5, 5.0)) + 0.9  # + title and x labels
        fig = plt.figure(figsize=(12.0, count * overview_h + 12.0 / count + 0.8))
        grid = fig.add_gridspec(count + 1, count, height_ratios=[overview_h] * count + [12.0 / count + 0.8])
        overviews = [fig.add_subplot(grid[row, :]) for row in range(count)]
    else:
        overview_h = float(np.clip(5.5 * height / width, 2.5, 9.0)) + 0.8
        fig = plt.figure(figsize=(6.0 * count, overview_h + 6.0))
        grid = fig.add_gridspec(2, count, height_ratios=[overview_h, 6.0])
        overviews = [fig.add_subplot(grid[0, column]) for column in range(count)]
    details = [fig.add_subplot(grid[-1, column]) for column in range(count)]

    def draw(ax, points, size, title, lo, hi):
        if len(points) > max_points:
            points = points[rng.choice(len(points), max_points, replace=False)]
        ax.scatter(
            points[:, 0],
            points[:, 1],
            c=np.clip(points[:, 2], low, high),
            s=size,
            alpha=0.4,
            cmap="viridis",
            linewidths=0,
            rasterized=True,
        )
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")

    for overview, detail, (title, points) in zip(overviews, details, items):
        draw(overview, points, 0.05, title, lo_xy, hi_xy)
        overview.add_patch(matplotlib.patches.Rectangle(corner, side, side, fill=False, edgecolor="red", linewidth=1.0))
        inside = np.all((points[:, :2] >= corner) & (points[:, :2] <= corner + side), axis=1)
        draw(detail, points[inside], 0.4, f"{title}: close-up ({side:.0f} m)", corner, corner + side)
    fig.set_dpi(150)
    return _save(fig, path)
