"""The per-scan quality report of a run (scans_report.csv) and the outliers it names.

One row per INPUT scan: whether it was a keyframe, how many rays trained on it, the median |rendered -
measured| range of its rays after training, the correction of its pose from the input to the output (after
removing the rigid motion of the whole trajectory, so that it says how the scan moved against the others), the
part of it the bundle adjustment made (the refinement: from the poses training started from, the same when it
started from the input, only its own moves when it started from the classical baseline's), and the local
crispness of the map around its points before and after. A keyframe is flagged when its residual or its
refinement is an outlier among the keyframes: above median + 3 scaled MADs (1.4826 MAD, the robust standard
deviation), and also above a floor in absolute terms, so that a flag means a scan worth a look: a residual at
least 3 cm above the keyframes' median (RESIDUAL_FLOOR_M; on noise-free synthetic scans the residuals lie within
a few mm of each other, and the MAD rule alone flagged a scan 2 mm above the rest), a refinement of at least 1 cm
or 0.1 deg (REFINEMENT_FLOOR_*: NeLD-BA's moves off the classical baseline are a fraction of a millimetre on the
handheld sequences, and the outliers of those are not moves to distrust; the raw map's planes are 3-4 cm thick).
Flagged scans are the ones the bundle adjustment did not trust or moved most: look at them first. The baseline's
own corrections are not flagged: on Riverside02 its gates kept 42 % of its registrations, so its corrections fell in
two groups (a few mm and a few cm) and half the scans lay above median + 3 MADs (docs/evaluation.md, "Per-scan
report")."""

from __future__ import annotations

import csv
import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from neld_jax.geometry import invert_poses, rotation_angles_deg
from neld_jax.judging.metrics import similarity_matrix, umeyama_alignment

logger = logging.getLogger(__name__)

MAD_THRESHOLD = 3.0
RESIDUAL_FLOOR_M = 0.03  # a residual is flagged only this far above the keyframes' median or further
REFINEMENT_FLOOR_M = 0.01  # a refinement is flagged only from this size on (translation) ...
REFINEMENT_FLOOR_DEG = 0.1  # ... or this (rotation)
COLUMNS = (
    "scan",
    "file",
    "timestamp",
    "keyframe",
    "rays",
    "median_residual_m",
    "registration_residual_m",
    "correction_cm",
    "correction_deg",
    "refinement_cm",
    "refinement_deg",
    "entropy_before",
    "entropy_after",
    "flag",
)
LOCALIZATION_COLUMNS = ("scan", "file", "timestamp", "registration_residual_m", "fitness", "flag")


def pose_corrections(T_before: np.ndarray, T_after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Size of the change of each pose, in its own sensor frame: T_before^-1 T_after.

    T_before, T_after: [S, 4, 4] -> (translation [S] metres, rotation angle [S] degrees)."""
    delta = invert_poses(T_before) @ T_after
    return np.linalg.norm(delta[:, :3, 3], axis=1), rotation_angles_deg(delta[:, :3, :3])


def aligned_corrections(T_before: np.ndarray, T_after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How each scan moved against the others from T_before to T_after ([S, 4, 4] each): the rigid motion of the
    whole trajectory (the gauge) is removed first by aligning T_after to T_before (SE(3), with 3 scans or more).
    Returns (translation [S] metres, rotation [S] degrees)."""
    alignment = np.eye(4)
    if len(T_before) >= 3:
        rotation, translation, _ = umeyama_alignment(T_after[:, :3, 3], T_before[:, :3, 3])
        alignment = similarity_matrix(rotation, translation)
    return pose_corrections(T_before, alignment @ T_after)


def robust_outliers(values: np.ndarray, threshold: float = MAD_THRESHOLD, min_excess: float = 0.0) -> np.ndarray:
    """values: [N] (NaN ignored) -> bool [N], True where value > median + threshold * 1.4826 MAD and value >=
    median + min_excess (a floor in the values' own units).

    With a MAD of zero (most values equal) nothing is flagged: there is no spread to be an outlier of."""
    values = np.asarray(values, np.float64)
    finite = np.isfinite(values)
    flags = np.zeros(len(values), bool)
    if finite.sum() < 3:
        return flags
    median = np.median(values[finite])
    mad = 1.4826 * np.median(np.abs(values[finite] - median))
    if mad <= 0:
        return flags
    flags[finite] = (values[finite] > median + threshold * mad) & (values[finite] >= median + min_excess)
    return flags


@dataclasses.dataclass(frozen=True)
class ScanList:
    """The input scans a report lists: how many (S), which are keyframes (keyframe_index [K], into the S), their
    files ([S] names, or None) and timestamps ([S] seconds, or None)."""

    num_scans: int
    keyframe_index: np.ndarray
    files: list[str] | None = None
    timestamps: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class KeyframeMeasures:
    """What the run measured of each keyframe, [K] each: training rays, median range residual (m; NaN: none), local
    crispness before and after (mean entropy; None: not measured), and the bundle adjustment's own move from its
    start (m, deg; None: the correction's, as when training started from the input)."""

    rays: np.ndarray
    residual_m: np.ndarray
    entropy_before: np.ndarray | None = None
    entropy_after: np.ndarray | None = None
    refinement_m: np.ndarray | None = None
    refinement_deg: np.ndarray | None = None


def scan_report(
    scans: ScanList, measures: KeyframeMeasures, correction_m: np.ndarray, correction_deg: np.ndarray
) -> list[dict]:
    """Rows (dicts with COLUMNS) for every input scan; correction_m / correction_deg [S]: each scan's correction from
    the input (aligned_corrections).

    The flag names why a keyframe is an outlier ("residual", "refinement" or both, joined by '+'); a residual less
    than RESIDUAL_FLOOR_M above the median and a refinement under REFINEMENT_FLOOR_M and REFINEMENT_FLOOR_DEG are
    never flagged."""
    keyframe_index = np.asarray(scans.keyframe_index, np.int64)
    refinement_m, refinement_deg = measures.refinement_m, measures.refinement_deg
    if refinement_m is None or refinement_deg is None:
        refinement_m, refinement_deg = correction_m[keyframe_index], correction_deg[keyframe_index]
    residual_flags = robust_outliers(measures.residual_m, min_excess=RESIDUAL_FLOOR_M)
    refinement_flags = (robust_outliers(refinement_m) & (np.asarray(refinement_m) >= REFINEMENT_FLOOR_M)) | (
        robust_outliers(refinement_deg) & (np.asarray(refinement_deg) >= REFINEMENT_FLOOR_DEG)
    )
    kf_row = {int(s): k for k, s in enumerate(keyframe_index)}
    rows = []
    for s in range(scans.num_scans):
        k = kf_row.get(s)
        reasons = (
            []
            if k is None
            else ([r for r, f in (("residual", residual_flags[k]), ("refinement", refinement_flags[k])) if f])
        )
        rows.append(
            {
                "scan": s,
                "file": scans.files[s] if scans.files is not None else "",
                "timestamp": None if scans.timestamps is None else float(scans.timestamps[s]),
                "keyframe": int(k is not None),
                "rays": int(measures.rays[k]) if k is not None else 0,
                "median_residual_m": _value(measures.residual_m, k),
                "registration_residual_m": None,
                "correction_cm": float(100.0 * correction_m[s]),
                "correction_deg": float(correction_deg[s]),
                "refinement_cm": None if k is None else float(100.0 * refinement_m[k]),
                "refinement_deg": _value(refinement_deg, k),
                "entropy_before": _value(measures.entropy_before, k),
                "entropy_after": _value(measures.entropy_after, k),
                "flag": "+".join(reasons),
            }
        )
    return rows


def add_registration(rows: list[dict], residual_m: np.ndarray, flags: list[str]) -> list[dict]:
    """The registration of every input scan to the result (neld_jax.steps.registration) in the rows: its residual [S]
    (NaN: not registered, as the keyframes, which make the map) and, for a scan it refused, the flag
    "unregistered (<why>)" beside any other."""
    for row, residual, flag in zip(rows, residual_m, flags):
        row["registration_residual_m"] = float(residual) if np.isfinite(residual) else None
        if flag:
            row["flag"] = "+".join([r for r in (row["flag"], f"unregistered ({flag})") if r])
    return rows


def _value(per_keyframe: np.ndarray, k: int | None) -> float | None:
    if k is None or per_keyframe is None:
        return None
    value = float(per_keyframe[k])
    return value if np.isfinite(value) else None


def localization_rows(registration, files: list[str] | None, timestamps: np.ndarray | None) -> list[dict]:
    """Rows (LOCALIZATION_COLUMNS) of scans posed in a finished run's map (neld-localize): registration, a
    neld_jax.steps.registration.ScanRegistration of S scans; files [S] or None; timestamps [S] or None."""
    return [
        {
            "scan": s,
            "file": files[s] if files is not None else "",
            "timestamp": None if timestamps is None else float(timestamps[s]),
            "registration_residual_m": _value(registration.residual_m, s),
            "fitness": _value(registration.fitness, s),
            "flag": f"unregistered ({flag})" if flag else "",
        }
        for s, flag in enumerate(registration.flag)
    ]


def write_csv(path: str | os.PathLike, rows: list[dict], columns: tuple = COLUMNS) -> Path:
    path = Path(path)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({key: _format(row[key]) for key in columns})
    return path


def _format(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6f}"  # microseconds for stamps, micrometres for distances
    return str(value)


def summarize(rows: list[dict], max_listed: int = 10) -> dict:
    """{"num_scans", "num_keyframes", "flagged": [{"scan", "file", "flag", ...}]} for metrics.json and the log."""
    flagged = [row for row in rows if row["flag"]]
    for row in flagged[:max_listed]:
        logger.warning(
            "scan report: %s flagged (%s): median residual %s m, refinement %s (from the input: %.1f cm / %.2f deg)",
            row["file"] or f"scan {row['scan']}",
            row["flag"],
            "-" if row["median_residual_m"] is None else f"{row['median_residual_m']:.3f}",
            "-" if row["refinement_cm"] is None else f"{row['refinement_cm']:.2f} cm / {row['refinement_deg']:.3f} deg",
            row["correction_cm"],
            row["correction_deg"],
        )
    if len(flagged) > max_listed:
        logger.warning("scan report: %d more scans flagged (see scans_report.csv)", len(flagged) - max_listed)
    return {
        "num_scans": len(rows),
        "num_keyframes": int(sum(row["keyframe"] for row in rows)),
        "flagged": [
            {
                key: row[key]
                for key in (
                    "scan",
                    "file",
                    "flag",
                    "median_residual_m",
                    "registration_residual_m",
                    "correction_cm",
                    "correction_deg",
                    "refinement_cm",
                    "refinement_deg",
                )
            }
            for row in flagged
        ],
    }
