"""LiDAR rays for training: one ray per scan point, in the sensor frame, with normalised ranges.

The ray of point p (sensor frame) has direction p / |p| and measured range |p| * scale. The trainer
turns it into a world ray with the current pose of its scan: origin t_s, direction R_s d.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from neld_jax.data.sequence import Sequence
from neld_jax.field.normalize import Normalization

logger = logging.getLogger(__name__)


@dataclass
class RaySet:
    """All training rays of a sequence, concatenated scan after scan.

    directions: [R, 3] float32 unit vectors in the SENSOR frame
    ranges:     [R] float32 measured ranges in NORMALISED units (metres * scale)
    scan_index: [R] int32 index of the scan each ray belongs to
    """

    directions: np.ndarray
    ranges: np.ndarray
    scan_index: np.ndarray

    @property
    def num_rays(self) -> int:
        return int(self.ranges.shape[0])


def build_rays(seq: Sequence, norm: Normalization, max_rays_per_scan: int | None = None, seed: int = 0) -> RaySet:
    """Rays of all scans of `seq` (normally preprocessed). Zero-length points are dropped (counted in the log).

    max_rays_per_scan: if set, each scan keeps a random subset of that many rays (seeded by `seed`)."""
    rng = np.random.default_rng(seed)
    directions, ranges, scan_index = [], [], []
    num_zero = 0
    for s, points in enumerate(seq.scans):
        lengths = np.linalg.norm(points, axis=1)
        valid = lengths > 0
        num_zero += int((~valid).sum())
        points, lengths = points[valid], lengths[valid]
        if max_rays_per_scan is not None and len(points) > max_rays_per_scan:
            chosen = np.sort(rng.choice(len(points), size=max_rays_per_scan, replace=False))
            points, lengths = points[chosen], lengths[chosen]
        directions.append((points / lengths[:, None]).astype(np.float32))
        ranges.append(norm.ranges_to_normalized(lengths).astype(np.float32))
        scan_index.append(np.full(len(points), s, dtype=np.int32))
    if num_zero:
        logger.warning("build_rays: dropped %d points at the sensor origin (no direction)", num_zero)
    rays = RaySet(
        directions=np.concatenate(directions) if directions else np.zeros((0, 3), np.float32),
        ranges=np.concatenate(ranges) if ranges else np.zeros((0,), np.float32),
        scan_index=np.concatenate(scan_index) if scan_index else np.zeros((0,), np.int32),
    )
    logger.info("build_rays: %d rays from %d scans", rays.num_rays, seq.num_scans)
    return rays


def rays_per_scan(max_rays_per_scan: int, max_rays: int, num_scans: int) -> int | None:
    """How many rays of each scan the rendered map casts: at most `max_rays_per_scan` (0: every ray), and with
    `max_rays` > 0 at most that many over the whole sequence (a floor of 256 a scan), so that the map's cost
    stops growing with the number of scans. None: every ray."""
    share = max(max_rays // max(num_scans, 1), 256) if max_rays > 0 else 0
    limits = [n for n in (max_rays_per_scan, share) if n > 0]
    return min(limits) if limits else None


def sphere_scene_rays(
    num_scans: int, rays_per_scan: int, seed: int = 0, radius: float = 0.8, spread: float = 0.3
) -> tuple[RaySet, np.ndarray]:
    """An analytic ray set for tests and benchmarks, already in the normalised frame: `num_scans` sensors at
    random poses within +-spread of the origin, each casting `rays_per_scan` random unit rays at a sphere of
    `radius` around the origin. Returns (RaySet with exact ranges, T_init [S, 4, 4] float64)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (num_scans, 1, 1))
    T[:, :3, 3] = rng.uniform(-spread, spread, (num_scans, 3))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.3, (num_scans, 3))).as_matrix()
    d = rng.normal(size=(num_scans * rays_per_scan, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scan = np.repeat(np.arange(num_scans), rays_per_scan)
    # Range from inside to the sphere: |o + r R d| = radius, the positive root.
    d_world = np.einsum("rij,rj->ri", T[scan, :3, :3], d)
    o = T[scan, :3, 3]
    b = np.sum(o * d_world, axis=1)
    r = -b + np.sqrt(b**2 - (np.sum(o * o, axis=1) - radius**2))
    rays = RaySet(directions=d.astype(np.float32), ranges=r.astype(np.float32), scan_index=scan.astype(np.int32))
    return rays, T
