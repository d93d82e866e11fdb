"""PNG figures of a run: trajectories from above, per-scan pose errors, map-error histograms.

Uses matplotlib's Agg backend (no display needed). Each function writes one file and returns its path.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: servers and CI have no display
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


def plot_trajectories(path: str | os.PathLike, trajectories: dict[str, np.ndarray],
                      gt: np.ndarray | None = None) -> Path:
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


def plot_pose_errors(path: str | os.PathLike, per_scan_errors: dict[str, np.ndarray],
                     ylabel: str = "translation error [m]") -> Path:
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


def plot_error_histogram(path: str | os.PathLike, distances: dict[str, np.ndarray],
                         threshold: float, max_distance: float | None = None) -> Path:
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
        ax.hist(np.minimum(values, max_distance), bins=bins, histtype="step", linewidth=1.5,
                weights=np.full(len(values), 100.0 / len(values)), label=f"{name} (n={len(values)})")
    ax.axvline(threshold, color="k", linestyle="--", linewidth=1.0, label=f"threshold {threshold:g} m")
    ax.set_xlabel(f"distance to ground-truth map [m] (last bin: >= {max_distance:g})")
    ax.set_ylabel("points [%]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Map error histogram")
    return _save(fig, path)
