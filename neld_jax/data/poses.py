"""Trajectory files: TUM, KITTI and the Newer College ground-truth CSV.

All poses are 4x4 homogeneous matrices, sensor -> world, float64: `poses: [S, 4, 4]`.
Quaternions are in (qx, qy, qz, qw) order everywhere in this module.

Validation (each raises `DataError` naming the file and the line):
  wrong column count, non-numeric or non-finite values, a quaternion whose norm is off by more than
  1e-3 relative (smaller errors are normalised silently), a rotation block that is not a rotation
  (R^T R != I within 1e-4, or det(R) != +1), a file without any pose, and in timestamped files (TUM,
  Newer College CSV) two lines with the same timestamp (naming both lines): matching by time would be
  ambiguous, and trajectory evaluation (evo) associates by time.
Timestamps out of order are returned as they are, in file order: whoever matches the poses to scans
decides (layout.align_poses: fine by time, with a warning; an error by order).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from neld_jax.errors import DataError
from neld_jax.geometry import nearest_rotations

QUATERNION_NORM_TOLERANCE = 1e-3
ROTATION_TOLERANCE = 1e-4


# --------------------------------------------------------------------------------------------------
# Pure conversions
# --------------------------------------------------------------------------------------------------


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """q: [..., 4] (qx, qy, qz, qw), any non-zero norm -> rotation matrices [..., 3, 3] float64."""
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    if flat.shape[0] == 0:
        return np.zeros(q.shape[:-1] + (3, 3))
    return Rotation.from_quat(flat).as_matrix().reshape(q.shape[:-1] + (3, 3))


def rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """R: [..., 3, 3] rotation matrices -> unit quaternions [..., 4] (qx, qy, qz, qw) with qw >= 0."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    if flat.shape[0] == 0:
        return np.zeros(R.shape[:-2] + (4,))
    q = Rotation.from_matrix(flat).as_quat()
    q = np.where(q[:, 3:4] < 0.0, -q, q)  # one canonical sign, so files are reproducible
    return q.reshape(R.shape[:-2] + (4,))


def make_poses(translations: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """translations: [S, 3], quaternions: [S, 4] xyzw -> poses [S, 4, 4]."""
    translations = np.asarray(translations, dtype=np.float64)
    poses = np.tile(np.eye(4), (translations.shape[0], 1, 1))
    poses[:, :3, :3] = quat_to_rotation(quaternions)
    poses[:, :3, 3] = translations
    return poses


def rotation_error(R: np.ndarray) -> tuple[float, float]:
    """R: [3, 3] -> (max |R^T R - I|, det R): how far a matrix is from being a rotation."""
    orthogonality = float(np.abs(R.T @ R - np.eye(3)).max())
    return orthogonality, float(np.linalg.det(R))


def _is_rotation(R: np.ndarray) -> bool:
    orthogonality, det = rotation_error(R)
    return orthogonality <= ROTATION_TOLERANCE and abs(det - 1.0) <= ROTATION_TOLERANCE


# --------------------------------------------------------------------------------------------------
# Parsing helpers
# --------------------------------------------------------------------------------------------------


def _read_lines(path: Path, what: str) -> list[str]:
    if not path.is_file():
        raise DataError(f"{path}: {what} file does not exist")
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read {what} file ({exc})") from exc


def _parse_rows(
    path: Path, lines: list[str], num_columns: int, what: str, separator: str | None = None
) -> tuple[np.ndarray, list[int]]:
    """Parse numeric rows, skipping blank lines and '#' comments.

    Returns (values [S, num_columns] float64, 1-based line numbers [S])."""
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for line_number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(separator)] if separator else text.split()
        if len(fields) != num_columns:
            raise DataError(f"{path}, line {line_number}: expected {num_columns} columns ({what}), got {len(fields)}")
        try:
            values = [float(f) for f in fields]
        except ValueError as exc:
            raise DataError(f"{path}, line {line_number}: non-numeric value in '{text}'") from exc
        if not np.all(np.isfinite(values)):
            raise DataError(f"{path}, line {line_number}: NaN or infinite value in '{text}'")
        rows.append(values)
        line_numbers.append(line_number)
    if not rows:
        raise DataError(f"{path}: no poses found (file is empty)")
    return np.asarray(rows, dtype=np.float64), line_numbers


def _check_unique_times(path: Path, times: np.ndarray, line_numbers: list[int]) -> None:
    """times: [S] -> DataError naming both lines of the first timestamp that appears twice."""
    order = np.argsort(times, kind="stable")
    same = np.flatnonzero(np.diff(times[order]) == 0.0)
    if same.size:
        first, second = sorted((int(order[same[0]]), int(order[same[0] + 1])))
        raise DataError(
            f"{path}, lines {line_numbers[first]} and {line_numbers[second]}: the same timestamp "
            f"{times[first]:.9f} twice ({same.size} repeated timestamp(s) in the file); "
            "poses are matched and evaluated by time, so each timestamp must appear once"
        )


def _checked_quaternions(path: Path, quaternions: np.ndarray, line_numbers: list[int]) -> np.ndarray:
    """quaternions: [S, 4] -> normalised; a norm off by more than the tolerance is an error."""
    norms = np.linalg.norm(quaternions, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise DataError(
            f"{path}, line {line_numbers[i]}: quaternion norm {norms[i]:.6g} is not 1 "
            f"({bad.size} bad quaternion(s) in the file)"
        )
    return quaternions / norms[:, None]


def _check_pose_array(path: Path, poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise DataError(f"{path}: poses to write must have shape [S, 4, 4], got {poses.shape}")
    for row, pose in enumerate(poses):
        if not np.all(np.isfinite(pose)):
            raise DataError(f"{path}: pose {row} to write has NaN or infinite values")
        if not _is_rotation(pose[:3, :3]):
            orthogonality, det = rotation_error(pose[:3, :3])
            raise DataError(
                f"{path}: pose {row} to write is not a rotation (|R^T R - I| = {orthogonality:.3g}, det = {det:.6g})"
            )
    return poses


# --------------------------------------------------------------------------------------------------
# TUM: timestamp tx ty tz qx qy qz qw
# --------------------------------------------------------------------------------------------------


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory. Returns (timestamps [S] float64, poses [S, 4, 4] float64), in file order.

    A timestamp that appears on two lines is a DataError naming both."""
    path = Path(path)
    values, line_numbers = _parse_rows(path, _read_lines(path, "TUM pose"), 8, "timestamp tx ty tz qx qy qz qw")
    quaternions = _checked_quaternions(path, values[:, 4:8], line_numbers)
    _check_unique_times(path, values[:, 0], line_numbers)
    return values[:, 0].copy(), make_poses(values[:, 1:4], quaternions)


def _check_stamped_poses(path: Path, timestamps, poses) -> tuple[np.ndarray, np.ndarray]:
    """Validate what a writer is given: poses [S, 4, 4] and one timestamp per pose."""
    poses = _check_pose_array(path, poses)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if timestamps.shape[0] != poses.shape[0]:
        raise DataError(f"{path}: {timestamps.shape[0]} timestamps for {poses.shape[0]} poses")
    return timestamps, poses


def write_tum(path: str | os.PathLike, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write timestamps: [S] and poses: [S, 4, 4] as TUM ('%.9f' time, full-precision pose values)."""
    path = Path(path)
    timestamps, poses = _check_stamped_poses(path, timestamps, poses)
    quaternions = rotation_to_quat(poses[:, :3, :3])
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, pose, q in zip(timestamps, poses, quaternions):
        numbers = " ".join(repr(float(v)) for v in (*pose[:3, 3], *q))
        lines.append(f"{t:.9f} {numbers}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------------
# KITTI: 12 numbers per line, the row-major 3x4 matrix [R | t]
# --------------------------------------------------------------------------------------------------


def read_kitti(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI trajectory. Returns poses [S, 4, 4] float64."""
    path = Path(path)
    values, line_numbers = _parse_rows(path, _read_lines(path, "KITTI pose"), 12, "row-major 3x4 [R | t]")
    poses = np.tile(np.eye(4), (values.shape[0], 1, 1))
    poses[:, :3, :4] = values.reshape(-1, 3, 4)
    for i, pose in enumerate(poses):
        if not _is_rotation(pose[:3, :3]):
            orthogonality, det = rotation_error(pose[:3, :3])
            raise DataError(
                f"{path}, line {line_numbers[i]}: rotation block is not a rotation "
                f"(max |R^T R - I| = {orthogonality:.3g}, det = {det:.6g})"
            )
        pose[:3, :3] = nearest_rotations(pose[:3, :3])  # removes the rounding of text files
    return poses


def write_kitti(path: str | os.PathLike, poses: np.ndarray) -> None:
    """Write poses: [S, 4, 4] as KITTI (12 full-precision numbers per line)."""
    path = Path(path)
    poses = _check_pose_array(path, poses)
    lines = [" ".join(repr(float(v)) for v in pose[:3, :4].reshape(-1)) for pose in poses]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------------
# Newer College ground truth CSV: #sec,nsec,x,y,z,qx,qy,qz,qw
# --------------------------------------------------------------------------------------------------


def read_newer_college_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a Newer College CSV (header optional, with or without '#').

    Returns (timestamps [S] = sec + nsec * 1e-9, poses [S, 4, 4])."""
    path = Path(path)
    lines = _read_lines(path, "Newer College CSV")
    # A header without '#' ("sec,nsec,x,...") on the first non-blank line is skipped like a comment.
    for i, line in enumerate(lines):
        text = line.strip()
        if not text:
            continue
        if "sec" in text.lower() and not text.startswith("#"):
            lines = lines.copy()
            lines[i] = "#" + text
        break
    values, line_numbers = _parse_rows(path, lines, 9, "sec,nsec,x,y,z,qx,qy,qz,qw", separator=",")
    quaternions = _checked_quaternions(path, values[:, 5:9], line_numbers)
    timestamps = values[:, 0] + values[:, 1] * 1e-9
    _check_unique_times(path, timestamps, line_numbers)
    return timestamps, make_poses(values[:, 2:5], quaternions)


# --------------------------------------------------------------------------------------------------
# HBA pose.json: one pose per line, "tx ty tz qw qx qy qz" (whitespace), no timestamps
# --------------------------------------------------------------------------------------------------


def read_hba_poses(path: str | os.PathLike) -> np.ndarray:
    """Read HBA's pose.json (despite the name, plain text: 'tx ty tz qw qx qy qz' per line, scalar-first
    quaternion, no timestamps; github.com/hku-mars/HBA, include/mypcl.hpp read_pose / write_pose).

    Returns poses [S, 4, 4] (scan i <-> line i)."""
    path = Path(path)
    values, line_numbers = _parse_rows(path, _read_lines(path, "HBA pose"), 7, "tx ty tz qw qx qy qz")
    quaternions = _checked_quaternions(path, values[:, [4, 5, 6, 3]], line_numbers)
    return make_poses(values[:, :3], quaternions)
