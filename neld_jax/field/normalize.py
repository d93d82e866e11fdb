"""The similarity that maps the world into the unit cube [-1, 1]^3 where the field lives.

x_n = (x - offset) * scale. Rotations are unchanged; translations, points and ranges are mapped.
Every output of a run (poses, maps) is mapped back with the inverse before it is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neld_jax.errors import DataError

# The largest half-extent of the scans and sensor origins maps to this: room for the poses' corrections in the cube
NORMALIZATION_MARGIN = 0.9


@dataclass(frozen=True)
class Normalization:
    """scale: float (normalised units per metre); offset: [3] world point that maps to the origin."""

    scale: float
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        offset = np.asarray(self.offset, dtype=np.float64).reshape(3)
        object.__setattr__(self, "offset", offset)
        object.__setattr__(self, "scale", float(self.scale))
        if not np.isfinite(self.scale) or self.scale <= 0 or not np.all(np.isfinite(offset)):
            raise DataError(f"invalid normalisation: scale {self.scale}, offset {offset}")

    def points_to_normalized(self, points: np.ndarray) -> np.ndarray:
        """points: [..., 3] world (metres) -> [..., 3] normalised."""
        return (np.asarray(points, dtype=np.float64) - self.offset) * self.scale

    def points_to_world(self, points: np.ndarray) -> np.ndarray:
        """points: [..., 3] normalised -> [..., 3] world (metres)."""
        return np.asarray(points, dtype=np.float64) / self.scale + self.offset

    def poses_to_normalized(self, poses: np.ndarray) -> np.ndarray:
        """poses: [..., 4, 4] sensor -> world -> sensor -> normalised world (rotation unchanged)."""
        out = np.array(poses, dtype=np.float64, copy=True)
        out[..., :3, 3] = self.points_to_normalized(out[..., :3, 3])
        return out

    def ranges_to_normalized(self, ranges: np.ndarray) -> np.ndarray:
        """ranges: [...] metres -> [...] normalised units."""
        return np.asarray(ranges, dtype=np.float64) * self.scale

    def to_dict(self) -> dict:
        """JSON-able form, for the checkpoints' plan of cubes."""
        return {"scale": self.scale, "offset": [float(v) for v in self.offset]}


def fit_normalization(
    scans: list[np.ndarray], poses: np.ndarray, margin: float = NORMALIZATION_MARGIN
) -> Normalization:
    """Fit the normalisation to all scan points (in the world via the initial poses) and the sensor origins.

    scans: S arrays [N_i, 3] sensor frame; poses: [S, 4, 4] sensor -> world.
    offset = centre of the bounding box; scale maps the largest half-extent to `margin` (< 1 leaves room
    for pose corrections during optimisation)."""
    poses = np.asarray(poses, dtype=np.float64)
    if len(scans) != poses.shape[0]:
        raise DataError(f"fit_normalization: {poses.shape[0]} poses for {len(scans)} scans")
    if not 0 < margin <= 1:
        raise DataError(f"fit_normalization: margin must be in (0, 1], got {margin}")
    origins = poses[:, :3, 3]
    lower, upper = origins.min(axis=0), origins.max(axis=0)
    for scan, pose in zip(scans, poses):  # per scan, so the world-frame cloud is never held in full
        if len(scan) == 0:
            continue
        world = scan @ pose[:3, :3].T + pose[:3, 3]
        lower = np.minimum(lower, world.min(axis=0))
        upper = np.maximum(upper, world.max(axis=0))
    half_extent = float((upper - lower).max()) / 2.0
    if half_extent <= 0:
        raise DataError("fit_normalization: all points and sensor origins coincide; nothing to normalise")
    return Normalization(scale=margin / half_extent, offset=(lower + upper) / 2.0)
