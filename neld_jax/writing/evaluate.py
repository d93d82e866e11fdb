"""Evaluate a run against ground truth: pose errors, map errors, plots.

`evaluate` measures arrays (RunArtifacts: each method's trajectory and maps, the ground truth); the run hands it
what it has just written, from memory. `evaluate_run` is the same for a finished output folder (neld-evaluate,
neld-baseline): it reads what a run wrote into OUTPUT_DIR,

    poses_<method>.txt          TUM trajectories; <method> = initial, optimized, baseline, ...
    map_raw.ply                 raw map of "optimized"; map_raw_<method>.ply for any other method
    map_rendered.ply            rendered map of "optimized"; map_rendered_<method>.ply for others
    poses_gt.txt, map_gt.ply    ground truth, used when no explicit path is given

and merges its result into OUTPUT_DIR/metrics.json under "evaluation".

Per method: ATE (SE(3) Umeyama alignment, as evo) and RPE against the GT poses, then the map metrics of its maps
against the GT map -- raw maps with the paper's 1 m cutoff, rendered maps without -- after moving the maps into
the GT frame with the ATE alignment of that trajectory (the odometry frame is not the GT frame on real data),
optionally refined by Open3D point-to-point ICP of the raw map against the GT map (map_icp_m > 0: a GT map whose
frame differs a little from the GT trajectory's, as a survey map registered separately does; FusionPortable's own
map evaluation aligns maps by ICP too: github.com/JokerJohn/Cloud_Map_Evaluation, linked from
fusionportable_dataset_tools' README). Without GT poses the ICP starts from the identity. Plots go to
trajectory.png, pose_error.png and error_histogram.png.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from neld_jax.data.poses import read_kitti, read_newer_college_csv, read_tum
from neld_jax.data.scans import read_scan
from neld_jax.data.timing import DEFAULT_TIMESTAMP_TOLERANCE_S, match_by_timestamp
from neld_jax.errors import DataError
from neld_jax.geometry import invert_poses, transform_points
from neld_jax.judging import metrics
from neld_jax.writing import plots
from neld_jax.writing.export import write_json

logger = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"
GT_POSES_FILE = "poses_gt.txt"
GT_MAP_FILES = ("map_gt.ply", "map_gt.pcd")
METHOD_ORDER = ("initial", "baseline", "optimized")  # table rows first in this order, then the rest
PRIMARY_METHOD = "optimized"  # owns the unsuffixed map_raw.ply / map_rendered.ply


# ---------------------------------------------------------------------------------------------
# Finding and reading the files of a run
# ---------------------------------------------------------------------------------------------


def find_trajectories(output_dir: str | os.PathLike) -> dict[str, Path]:
    """{method: path} of every `poses_<method>.txt` in output_dir except the GT, in table order."""
    output_dir = Path(output_dir)
    found = {
        path.name[len("poses_") : -len(".txt")]: path
        for path in output_dir.glob("poses_*.txt")
        if path.name != GT_POSES_FILE
    }
    ordered = [name for name in METHOD_ORDER if name in found] + sorted(set(found) - set(METHOD_ORDER))
    return {name: found[name] for name in ordered}


def map_file_name(method: str, kind: str) -> str:
    """The name of a method's map of a kind ("raw" | "rendered") in an output folder."""
    return f"map_{kind}{'' if method == PRIMARY_METHOD else f'_{method}'}.ply"


def map_files(output_dir: str | os.PathLike, method: str) -> dict[str, Path]:
    """{"raw": path, "rendered": path} of the maps of a method that exist in output_dir."""
    candidates = {kind: Path(output_dir) / map_file_name(method, kind) for kind in ("raw", "rendered")}
    return {kind: path for kind, path in candidates.items() if path.is_file()}


def read_trajectory(path: str | os.PathLike) -> tuple[np.ndarray | None, np.ndarray]:
    """Read a trajectory in any format the field uses, chosen by its content.

    TUM (8 columns), KITTI (12 columns, no timestamps) or Newer College CSV (.csv).
    Returns (timestamps [S] or None, poses [S, 4, 4]).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: trajectory file does not exist")
    if path.suffix.lower() == ".csv":
        return read_newer_college_csv(path)
    num_columns = 0
    with path.open() as lines:
        for line in lines:
            text = line.strip()
            if text and not text.startswith("#"):
                num_columns = len(text.split())
                break
    if num_columns == 12:
        return None, read_kitti(path)
    return read_tum(path)  # names the file and the column count if it is neither


def match_poses(
    stamps_est: np.ndarray | None,
    stamps_gt: np.ndarray | None,
    num_est: int,
    num_gt: int,
    what: str,
    max_time_diff: float = 0.01,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Pair estimated and GT poses: by timestamp where both have them, else by order.

    Timestamp matching is used when it pairs at least min(3, num_est) poses; otherwise equal counts
    fall back to order. Returns (est indices [K], gt indices [K], "timestamp" | "order").
    """
    if stamps_est is not None and stamps_gt is not None:
        est_idx, gt_idx = metrics.associate_timestamps(stamps_est, stamps_gt, max_time_diff)
        if len(est_idx) >= min(3, num_est) and len(est_idx) > 0:
            if len(est_idx) < num_est:
                logger.info(
                    "%s: %d of %d poses have a GT pose within %.3g s", what, len(est_idx), num_est, max_time_diff
                )
            return est_idx, gt_idx, "timestamp"
    if num_est == num_gt:
        if stamps_est is not None and stamps_gt is not None:
            logger.warning("%s: timestamps do not match the ground truth; matching %d poses by order", what, num_est)
        return np.arange(num_est), np.arange(num_gt), "order"
    raise DataError(
        f"{what}: cannot match {num_est} poses to {num_gt} ground-truth poses "
        f"(no common timestamps within {max_time_diff} s and the counts differ)"
    )


def _resolve_gt_map(output_dir: Path, gt_map_path: str | os.PathLike | None) -> Path | None:
    if gt_map_path:
        return Path(gt_map_path)
    return next((output_dir / name for name in GT_MAP_FILES if (output_dir / name).is_file()), None)


def read_artifacts(
    output_dir: str | os.PathLike,
    gt_poses_path: str | os.PathLike | None = None,
    gt_map_path: str | os.PathLike | None = None,
) -> tuple["RunArtifacts", dict[str, str | None]]:
    """What a finished run wrote into output_dir, as `evaluate` takes it (maps read only where a GT map is), and
    the ground truth's files ({"gt_poses", "gt_map"}: paths or None). gt_poses_path / gt_map_path default to
    OUTPUT_DIR/poses_gt.txt and OUTPUT_DIR/map_gt.ply when those exist."""
    output_dir = Path(output_dir)
    if not output_dir.is_dir():
        raise DataError(f"{output_dir}: output directory does not exist")
    trajectory_files = find_trajectories(output_dir)
    if not trajectory_files:
        raise DataError(
            f"{output_dir}: no trajectory to evaluate (expected poses_initial.txt, "
            "poses_optimized.txt or another poses_<method>.txt)"
        )
    if gt_poses_path is None and (output_dir / GT_POSES_FILE).is_file():
        gt_poses_path = output_dir / GT_POSES_FILE
    gt_map_file = _resolve_gt_map(output_dir, gt_map_path)
    logger.info(
        "evaluating %s: %s; GT poses %s; GT map %s",
        output_dir,
        ", ".join(trajectory_files),
        gt_poses_path or "none",
        gt_map_file or "none",
    )
    gt_map = read_scan(gt_map_file) if gt_map_file else None
    maps = (
        {}
        if gt_map is None
        else {
            name: {kind: read_scan(path) for kind, path in map_files(output_dir, name).items()}
            for name in trajectory_files
        }
    )
    artifacts = RunArtifacts(
        {name: Trajectory(*read_tum(path)) for name, path in trajectory_files.items()},
        maps,
        Trajectory(*read_trajectory(gt_poses_path)) if gt_poses_path else None,
        gt_map,
    )
    files = {
        "gt_poses": None if gt_poses_path is None else str(gt_poses_path),
        "gt_map": None if gt_map_file is None else str(gt_map_file),
    }
    return artifacts, files


# ---------------------------------------------------------------------------------------------
# The evaluation
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Poses [S, 4, 4] and their timestamps [S] (None: matched to the ground truth by order)."""

    stamps: np.ndarray | None
    poses: np.ndarray


@dataclasses.dataclass(frozen=True)
class RunArtifacts:
    """What a run made, as evaluation measures it: each method's trajectory ({method: Trajectory}, in table order),
    its maps ({method: {"raw" | "rendered": points [N, 3]}}, a method's own frame) and the ground truth (a
    Trajectory, a map [M, 3]; None where there is none)."""

    trajectories: dict[str, Trajectory]
    maps: dict[str, dict[str, np.ndarray]]
    gt: Trajectory | None = None
    gt_map: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class EvalSettings:
    """threshold: F1 / inlier distance (m); raw_cutoff: Chamfer cutoff of raw maps (m); max_time_diff: pose matching
    by timestamp (s); map_icp_m: the ICP correspondence distance (m) that refines each method's map alignment (0: off,
    the trajectory alignment alone)."""

    threshold: float = 0.2
    raw_cutoff: float = 1.0
    max_time_diff: float = 0.01
    map_icp_m: float = 0.0


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """evaluate's answer: `result` (metrics.json's "evaluation" less where the files came from) and what the plots
    draw: each method's trajectory aligned to the GT ({method: [S, 4, 4]}), its ATE errors ({method: [K] m}), and
    each map's distances to the GT map ({"<method> <kind>": [N] m})."""

    result: dict[str, Any]
    aligned: dict[str, np.ndarray]
    pose_errors: dict[str, np.ndarray]
    map_distances: dict[str, np.ndarray]


def evaluate(artifacts: RunArtifacts, settings: EvalSettings = EvalSettings()) -> Evaluation:
    """Every method's pose errors against the GT poses and map errors against the GT map (module docstring).

    result: {"threshold_m", "raw_cutoff_m", "map_icp_m", "methods": {method: {"poses", "num_poses", ["matching",
    "matched_poses", "ate", "rpe"], ["raw_map", "rendered_map"]}}}; a map entry holds
    `metrics.map_metrics_from_distances` keys plus "file" (the map's name in an output folder), "aligned_to_gt" and
    "icp" (fitness, correction in m and deg; None without ICP)."""
    methods, aligned, pose_errors, map_distances = {}, {}, {}, {}
    for name, trajectory in artifacts.trajectories.items():
        entry, alignment, errors = _pose_entry(name, trajectory, artifacts.gt, settings)
        aligned[name] = trajectory.poses if alignment is None else alignment @ trajectory.poses
        if errors is not None:
            pose_errors[name] = errors
        if artifacts.gt_map is not None:
            for kind, (map_entry, distances) in _map_entries(
                name, artifacts.maps.get(name, {}), artifacts.gt_map, alignment, settings
            ).items():
                entry[f"{kind}_map"] = map_entry
                map_distances[f"{name} {kind}"] = distances
        methods[name] = entry
    result = {
        "threshold_m": float(settings.threshold),
        "raw_cutoff_m": float(settings.raw_cutoff),
        "map_icp_m": float(settings.map_icp_m),
        "methods": methods,
    }
    return Evaluation(result, aligned, pose_errors, map_distances)


def _pose_entry(
    name: str, trajectory: Trajectory, gt: Trajectory | None, settings: EvalSettings
) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """A method's entry with its pose errors (where there are GT poses), the SE(3) alignment to the GT [4, 4] and
    the translation errors [K] (None, None without GT poses)."""
    poses = trajectory.poses
    entry: dict[str, Any] = {"poses": f"poses_{name}.txt", "num_poses": int(len(poses))}
    if gt is None:
        return entry, None, None
    est_idx, gt_idx, how = match_poses(
        trajectory.stamps, gt.stamps, len(poses), len(gt.poses), f"poses_{name}", settings.max_time_diff
    )
    errors = metrics.ate_errors(poses[est_idx], gt.poses[gt_idx], "se3")
    entry.update(
        matching=how,
        matched_poses=int(len(est_idx)),
        ate=metrics.ate_summary(*errors, align="se3"),
        rpe=metrics.rpe(poses[est_idx], gt.poses[gt_idx], delta=1),
    )
    return entry, errors[2], errors[0]


def _map_entries(
    name: str, maps: dict[str, np.ndarray], gt_map: np.ndarray, alignment: np.ndarray | None, settings: EvalSettings
) -> dict[str, tuple[dict, np.ndarray]]:
    """{kind: (the map entry, its points' distances to the GT map [N])} of a method's maps ({kind: [N, 3]}), moved
    into the GT frame by its trajectory's alignment [4, 4] (None: the identity), refined by ICP with map_icp_m."""
    to_gt = np.eye(4) if alignment is None else alignment
    icp = None
    if settings.map_icp_m > 0 and maps:
        if alignment is None:
            logger.warning("%s: no GT poses to align the maps with; ICP starts from the odometry frame", name)
        reference = maps.get("raw", next(iter(maps.values())))
        icp = refine_map_alignment(transform_points(reference, to_gt), gt_map, settings.map_icp_m)
        to_gt = icp.pop("transform") @ to_gt
    entries = {}
    for kind, points in maps.items():
        points = transform_points(points, to_gt)
        est_to_gt = metrics.nearest_neighbor_distances(points, gt_map)
        gt_to_est = metrics.nearest_neighbor_distances(gt_map, points)
        # Raw maps keep outliers from misregistered scans: the paper cuts their distances at 1 m.
        cutoff = settings.raw_cutoff if kind == "raw" else None
        entries[kind] = (
            {
                "file": map_file_name(name, kind),
                "aligned_to_gt": alignment is not None or icp is not None,
                "icp": icp,
                **metrics.map_metrics_from_distances(est_to_gt, gt_to_est, settings.threshold, cutoff, "paper"),
            },
            est_to_gt,
        )
    return entries


def evaluation_record(
    output_dir: str | os.PathLike,
    artifacts: RunArtifacts,
    settings: EvalSettings,
    gt_files: dict[str, str | None],
    write_plots: bool = True,
) -> dict[str, Any]:
    """`evaluate` of a run's artifacts, with its plots written into output_dir (write_plots): the "evaluation"
    section of metrics.json, {"output_dir", "gt_poses", "gt_map" (gt_files: where the ground truth came from),
    "threshold_m", "raw_cutoff_m", "map_icp_m", "methods", "plots"}."""
    evaluation = evaluate(artifacts, settings)
    plots_written = []
    if write_plots:
        plots_written = _write_plots(
            Path(output_dir), evaluation, None if artifacts.gt is None else artifacts.gt.poses, settings
        )
    return {
        "output_dir": str(output_dir),
        "gt_poses": gt_files.get("gt_poses"),
        "gt_map": gt_files.get("gt_map"),
        **evaluation.result,
        "plots": plots_written,
    }


def evaluate_run(
    output_dir: str | os.PathLike,
    gt_poses_path: str | os.PathLike | None = None,
    gt_map_path: str | os.PathLike | None = None,
    threshold: float = 0.2,
    raw_cutoff: float = 1.0,
    max_time_diff: float = 0.01,
    write_plots: bool = True,
    map_icp_m: float = 0.0,
) -> dict[str, Any]:
    """Evaluate every trajectory and map of a finished output folder (read_artifacts; the settings: EvalSettings),
    write the plots, and merge the result into its metrics.json under "evaluation" (the folder's other sections
    stay). Returns evaluation_record's answer."""
    artifacts, gt_files = read_artifacts(output_dir, gt_poses_path, gt_map_path)
    settings = EvalSettings(threshold, raw_cutoff, max_time_diff, map_icp_m)
    result = evaluation_record(output_dir, artifacts, settings, gt_files, write_plots)
    write_json(Path(output_dir) / METRICS_FILE, {"evaluation": result}, merge=True)
    return result


def refine_map_alignment(points: np.ndarray, gt_map: np.ndarray, max_distance: float) -> dict[str, Any]:
    """Open3D point-to-point ICP of points [N, 3] onto gt_map [M, 3] (both in the GT frame already, roughly),
    with correspondences up to max_distance metres; both are thinned on a max_distance / 10 voxel grid first.

    Returns {"transform": [4, 4] correction (points -> GT), "max_distance_m", "fitness" (share of points with a
    correspondence), "correction_m", "correction_deg"}."""
    import open3d as o3d

    from neld_jax.geometry import rotation_angles_deg

    voxel = max_distance / 10.0
    source, target = (
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, dtype=np.float64))).voxel_down_sample(voxel)
        for p in (points, gt_map)
    )
    result = o3d.pipelines.registration.registration_icp(
        source,
        target,
        max_distance,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=100),
    )
    transform = np.asarray(result.transformation, dtype=np.float64)
    return {
        "transform": transform,
        "max_distance_m": float(max_distance),
        "fitness": float(result.fitness),
        "correction_m": float(np.linalg.norm(transform[:3, 3])),
        "correction_deg": float(rotation_angles_deg(transform[:3, :3])),
    }


def _write_plots(
    output_dir: Path, evaluation: Evaluation, gt_poses: np.ndarray | None, settings: EvalSettings
) -> list[str]:
    written = [plots.plot_trajectories(output_dir / "trajectory.png", evaluation.aligned, gt_poses)]
    if evaluation.pose_errors:
        written.append(plots.plot_pose_errors(output_dir / "pose_error.png", evaluation.pose_errors))
    if evaluation.map_distances:
        written.append(
            plots.plot_error_histogram(
                output_dir / "error_histogram.png",
                evaluation.map_distances,
                settings.threshold,
                max_distance=max(settings.raw_cutoff, 2.0 * settings.threshold),
            )
        )
    return [path.name for path in written]


# ---------------------------------------------------------------------------------------------
# The terminal table
# ---------------------------------------------------------------------------------------------

_COLUMNS = (  # header, path into a method entry, scale for display, format
    ("ATE RMSE [m]", ("ate", "translation_rmse_m"), 1.0, "{:.4f}"),
    ("ATE mean [m]", ("ate", "translation_mean_m"), 1.0, "{:.4f}"),
    ("rot RMSE [deg]", ("ate", "rotation_rmse_deg"), 1.0, "{:.3f}"),
    ("RPE [m]", ("rpe", "translation_rmse_m"), 1.0, "{:.4f}"),
    ("raw L1-CD [cm]", ("raw_map", "chamfer_l1_m"), 100.0, "{:.2f}"),
    ("rend. L1-CD [cm]", ("rendered_map", "chamfer_l1_m"), 100.0, "{:.2f}"),
    ("rend. F1 [%]", ("rendered_map", "f1"), 100.0, "{:.2f}"),
    ("rend. inlier RMSE [cm]", ("rendered_map", "inlier_rmse_m"), 100.0, "{:.2f}"),
)


def format_table(result: dict[str, Any]) -> str:
    """A plain-text table of `evaluate_run`'s result: one row per method, "-" where not measured."""
    methods = result.get("methods", {})
    columns = [
        column for column in _COLUMNS if any(_lookup(entry, column[1]) is not None for entry in methods.values())
    ]
    header = ["method", "poses"] + [column[0] for column in columns]
    rows = []
    for name, entry in methods.items():
        row = [name, str(entry.get("num_poses", "-"))]
        for _, keys, scale, fmt in columns:
            value = _lookup(entry, keys)
            row.append("-" if value is None else fmt.format(value * scale))
        rows.append(row)
    widths = [max(len(line[i]) for line in [header] + rows) for i in range(len(header))]

    def _line(cells: list[str]) -> str:
        return "  ".join(
            cell.ljust(width) if i == 0 else cell.rjust(width) for i, (cell, width) in enumerate(zip(cells, widths))
        )

    lines = [_line(header), "  ".join("-" * width for width in widths)] + [_line(row) for row in rows]
    notes = []
    if result.get("gt_poses") is None:
        notes.append("no ground-truth poses: pose errors not measured")
    if result.get("gt_map") is None:
        notes.append("no ground-truth map: map errors not measured")
    elif columns and any(column[1][0] == "raw_map" for column in columns):
        notes.append(
            f"raw-map L1-CD drops distances beyond {result.get('raw_cutoff_m', 1.0):g} m; "
            f"F1 at {result.get('threshold_m', 0.2):g} m"
        )
    return "\n".join(lines + [f"({note})" for note in notes])


def _lookup(entry: dict[str, Any], keys: tuple[str, ...]) -> float | None:
    value: Any = entry
    for key in keys:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return float(value)


def trajectory_at_keyframes(
    path, loaded, keyframes, tol: float = DEFAULT_TIMESTAMP_TOLERANCE_S, invert: bool = False
) -> np.ndarray:
    """The poses [K, 4, 4] a trajectory file (TUM, KITTI or Newer College CSV, in the convention of the sequence's own
    pose file; invert: world -> sensor, as data.invert_poses) gives the keyframes of the input scans `loaded`: by
    time when the file and the scans have timestamps (every keyframe needs a pose within `tol` s), else by order, one
    pose per input scan or one per keyframe. A file that fits neither is one DataError naming it."""
    stamps, poses = read_trajectory(path)
    poses = invert_poses(poses) if invert else poses
    index = keyframes.loaded_index
    if stamps is not None and loaded.timestamps is not None:
        labels = None if loaded.files is None else [loaded.files[i] for i in index]
        return poses[match_by_timestamp(loaded.timestamps[index], stamps, tol=tol, what=str(path), scan_labels=labels)]
    if len(poses) == loaded.num_scans:
        return poses[index]
    if len(poses) == keyframes.num_scans:
        return poses
    why = "has no timestamps" if stamps is None else "has timestamps but the scans have none"
    raise DataError(
        f"{path}: {len(poses)} poses for {loaded.num_scans} input scans ({keyframes.num_scans} "
        f"keyframes); the file {why}, so it must hold one pose per input scan or per keyframe, in order"
    )
