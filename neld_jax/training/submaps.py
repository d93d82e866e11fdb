"""The plan of cubes: one cube for a sequence it holds at the configured detail, else overlapping windows of
consecutive keyframes ("submaps"), each with its own cube and field, sharing one pose row per keyframe.

Pure numpy (no jax): the plan (which keyframes each cube holds, its normalisation), the rule that switches submaps
on, and the per-cube ray tensors the trainer stacks (neld_jax.training.train). docs/method.md ("Submaps") states the
conventions.

Windows, not spatial tiles: a scan's rays reach as far as its range, so a tile would have to clip scans (a ray
that ends in the next tile has no measured range inside its own) or hold every scan whose footprint touches
it: on the 600 m synthetic route a keyframe's box touches 2.0 cube-sized tiles on average against 1.14
windows (`tile_memberships`; benchmarks/RESULTS.md). A window holds whole scans, so every ray keeps its
measured range; the windows are equally long so that the submaps stack into one array without padding scans.

Shared pose, one row per keyframe: xi = (rho, omega) [S, 6] is a RIGHT correction in the scan's body frame,
T_s = T_init[s] @ Exp(xi_s) (metres / s_ref for rho). A normalisation x_n = s_m (x - o_m) keeps rotations and
scales translations, so in cube m the same correction is exactly Exp((s_m / s_ref) rho, omega) on the right
of the cube's normalised initial pose: `rho_factor[m] = s_m / s_ref` (1 for a single cube).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from neld_jax.errors import ConfigError
from neld_jax.field.normalize import NORMALIZATION_MARGIN, Normalization, fit_normalization

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SubmapPlan:
    """M submaps of W consecutive keyframes each, over S keyframes.

    members: [M, W] int64 keyframe indices of each submap (a keyframe in two windows appears in both rows);
    norms: M normalisations (each submap's own cube); ref_scale: s_ref, the unit of the shared rho (normalised
    units per metre); weight: [M] 1.0 for a real submap, 0.0 for padding (added so M divides the device count).
    """

    members: np.ndarray
    norms: tuple
    ref_scale: float
    weight: np.ndarray

    @property
    def num_submaps(self) -> int:
        return int(self.members.shape[0])

    @property
    def window(self) -> int:
        return int(self.members.shape[1])

    @property
    def scales(self) -> np.ndarray:
        return np.array([n.scale for n in self.norms], np.float64)

    @property
    def rho_factor(self) -> np.ndarray:
        """[M] s_m / s_ref: the shared rho in submap m's normalised units."""
        return self.scales / self.ref_scale

    def to_dict(self) -> dict:
        """JSON-able form, for checkpoints (a resume must train the same split)."""
        return {
            "members": self.members.tolist(),
            "norms": [n.to_dict() for n in self.norms],
            "ref_scale": self.ref_scale,
            "weight": self.weight.tolist(),
        }


def scan_bounds(scans: list[np.ndarray], poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World bounding box of each scan (its points and sensor origin via its pose): lower, upper [S, 3]."""
    lower, upper = [], []
    for scan, pose in zip(scans, np.asarray(poses, np.float64)):
        pts = np.vstack([scan @ pose[:3, :3].T + pose[:3, 3], pose[None, :3, 3]])
        lower.append(pts.min(axis=0))
        upper.append(pts.max(axis=0))
    return np.asarray(lower), np.asarray(upper)


def window_starts(num_scans: int, window: int, overlap: int) -> np.ndarray:
    """First keyframe of each window of `window` keyframes, consecutive windows sharing >= `overlap`.

    The last window ends at the last keyframe (it may share more than `overlap` with its neighbour)."""
    if window >= num_scans:
        return np.zeros(1, np.int64)
    stride = window - overlap
    if stride < 1:
        raise ConfigError(f"submaps.overlap ({overlap}) must be smaller than the window ({window} keyframes)")
    starts = list(range(0, num_scans - window, stride)) + [num_scans - window]
    return np.asarray(sorted(set(starts)), np.int64)


def max_window(lower: np.ndarray, upper: np.ndarray, max_extent: float, quantile: float = 0.0) -> int:
    """The longest run of consecutive scans whose union spans at most max_extent (largest box side), taken over
    the starting scans at `quantile`: 0 = every run of that length fits; 0.1 = nine in ten do (a fast stretch
    then gets larger cubes instead of shrinking every window). lower, upper: [S, 3] per-scan world boxes.
    Returns 0 when (at the quantile) a single scan is already larger; S when everything fits."""
    s = len(lower)
    lengths = []
    for a in range(s):
        lo, hi = lower[a].copy(), upper[a].copy()
        b = a
        while b < s:
            lo, hi = np.minimum(lo, lower[b]), np.maximum(hi, upper[b])
            if float((hi - lo).max()) > max_extent:
                break
            b += 1
        if b < s:  # runs that reach the end are cut by the sequence, not by the extent
            lengths.append(b - a)
    if not lengths:
        return s
    return int(np.quantile(np.asarray(lengths), quantile, method="lower"))


def single_cube_detail_m(extent_m: float, pos_freqs: int, margin: float) -> float:
    """The finest Fourier period in metres of one field whose cube holds a scene of extent_m.

    The period of frequency L - 1 is 2^(2 - L) normalised units; the largest half-extent maps to `margin`."""
    return 2.0 ** (2 - int(pos_freqs)) * (extent_m / 2.0) / margin


def max_submap_extent_m(max_detail_m: float, pos_freqs: int, margin: float) -> float:
    """The largest extent one cube may hold for its finest period to stay <= max_detail_m (inverse of above)."""
    return 2.0 * margin * max_detail_m * 2.0 ** (int(pos_freqs) - 2)


def submaps_wanted(config, extent_m: float) -> bool:
    """The switch: submaps.enabled "on"/"off", or "auto": on when one cube's finest detail at model.pos_freqs
    would be coarser than submaps.max_detail_m (the sequence outgrows one cube at the configured resolution)."""
    how = str(config.submaps.enabled).lower()
    if how in ("on", "true", "1"):
        return True
    if how in ("off", "false", "0"):
        return False
    if how != "auto":
        raise ConfigError(f"submaps.enabled: unknown value {config.submaps.enabled!r} (auto | on | off)")
    detail = single_cube_detail_m(extent_m, config.model.pos_freqs, NORMALIZATION_MARGIN)
    return detail > float(config.submaps.max_detail_m)


def closure_pairs(poses: np.ndarray, window: int, radius_m: float) -> list[tuple[int, int]]:
    """Revisits (i, j), i < j: keyframes at least 2 windows apart in the sequence whose initial positions are
    within radius_m. One pair per revisited stretch: a pair within a window of an accepted one (both ends) is
    skipped. radius_m <= 0: none."""
    if radius_m <= 0:
        return []
    t = np.asarray(poses, np.float64)[:, :3, 3]
    pairs: list[tuple[int, int]] = []
    for i in range(len(t)):
        far = np.arange(i + 2 * window, len(t))
        if far.size == 0:
            break
        d = np.linalg.norm(t[far] - t[i], axis=1)
        if d.min() > radius_m:
            continue
        j = int(far[np.argmin(d)])
        if all(abs(i - a) >= window or abs(j - b) >= window for a, b in pairs):
            pairs.append((i, j))
    return pairs


def closure_members(i: int, j: int, window: int, num_scans: int) -> np.ndarray:
    """The W keyframes [W] of a loop-closure submap: window // 2 around i and the rest around j (disjoint)."""
    h = window // 2
    a = int(np.clip(i - h // 2, 0, num_scans - h))
    b = int(np.clip(j - (window - h) // 2, 0, num_scans - (window - h)))
    return np.concatenate([np.arange(a, a + h), np.arange(b, b + window - h)])


def submap_members(poses: np.ndarray, window: int, overlap: int, closure_radius_m: float = 0.0) -> np.ndarray:
    """The keyframes [M, W] of each real submap of S keyframes (poses [S, 4, 4] initial): the windows of `window`
    (clipped to 1..S) consecutive keyframes, then one loop-closure submap per revisit (closure_pairs)."""
    s = len(poses)
    window = int(min(max(window, 1), s))
    members = window_starts(s, window, int(overlap))[:, None] + np.arange(window)[None, :]
    closures = [closure_members(i, j, window, s) for i, j in closure_pairs(poses, window, closure_radius_m)]
    return np.vstack([members] + [c[None] for c in closures]) if closures else members


def plan_submaps(
    scans: list[np.ndarray],
    poses: np.ndarray,
    window: int,
    overlap: int,
    margin: float,
    num_devices: int = 1,
    closure_radius_m: float = 0.0,
) -> SubmapPlan:
    """Split S keyframes (scans [N_i, 3] sensor frame, poses [S, 4, 4] initial) into windows of `window`.

    With closure_radius_m > 0, each revisit (closure_pairs) adds a submap holding both visits (closure_members),
    so that the field of that place ties the two ends of a loop together; windows alone tie only neighbours.
    Each submap gets its own normalisation fitted to its scans (fit_normalization with `margin`); s_ref is the
    median submap scale. M is padded up to a multiple of num_devices with weight-0 copies of the last submap."""
    members = submap_members(poses, window, overlap, closure_radius_m)
    norms = [fit_normalization([scans[i] for i in row], poses[row], margin=margin) for row in members]
    ref_scale = float(np.median([n.scale for n in norms]))
    weight = np.ones(len(members))
    pad = (-len(members)) % max(min(int(num_devices), len(members)), 1)
    if pad:
        members = np.vstack([members, np.repeat(members[-1:], pad, axis=0)])
        norms += [norms[-1]] * pad
        weight = np.concatenate([weight, np.zeros(pad)])
    return SubmapPlan(members=members, norms=tuple(norms), ref_scale=ref_scale, weight=weight)


def one_cube_plan(num_scans: int, norm: Normalization) -> SubmapPlan:
    """The plan of one cube, normalised by `norm`, holding every one of `num_scans` keyframes."""
    return SubmapPlan(members=np.arange(num_scans)[None], norms=(norm,), ref_scale=norm.scale, weight=np.ones(1))


def plan_from_config(seq, config, num_devices: int = 1) -> SubmapPlan:
    """The plan of a preprocessed sequence (seq.scans, seq.poses: the poses training starts from): one cube fitted to
    every keyframe when it holds them at submaps.max_detail_m (or submaps.enabled="off"), else windows. Logs how the
    sequence was split."""
    norm = fit_normalization(seq.scans, seq.poses, margin=NORMALIZATION_MARGIN)
    extent_m = 2.0 * NORMALIZATION_MARGIN / norm.scale
    if not submaps_wanted(config, extent_m):
        return one_cube_plan(seq.num_scans, norm)
    sc = config.submaps
    margin = NORMALIZATION_MARGIN
    max_extent = max_submap_extent_m(float(sc.max_detail_m), config.model.pos_freqs, margin)
    window = int(sc.keyframes)
    if window <= 0:
        lower, upper = scan_bounds(seq.scans, seq.poses)
        window = max_window(lower, upper, max_extent, quantile=0.1)
        if window < int(sc.overlap) + 1:
            largest = float((upper - lower).max())
            logger.warning(
                "%s: submaps of at most %.0f m (submaps.max_detail_m=%g at model.pos_freqs=%d) hold fewer than "
                "%d consecutive keyframes (one scan alone spans up to %.0f m): using %d, in larger cubes (lower "
                "data.max_range_m or set submaps.keyframes to choose)",
                seq.source or seq.name,
                max_extent,
                sc.max_detail_m,
                config.model.pos_freqs,
                int(sc.overlap) + 1,
                largest,
                int(sc.overlap) + 1,
            )
            window = int(sc.overlap) + 1
    closure_radius = float(sc.closure_radius_m)
    limit = int(sc.max_submaps)
    if limit > 0 and int(sc.keyframes) <= 0:
        wanted = window
        window = window_for_limit(seq.poses, window, int(sc.overlap), closure_radius, limit)
        if window > wanted:
            logger.info(
                "%s: windows of %d keyframes would make more than submaps.max_submaps=%d submaps; "
                "using %d keyframes a window, in larger cubes (coarser detail, below)",
                seq.source or seq.name,
                wanted,
                limit,
                window,
            )
    plan = plan_submaps(seq.scans, seq.poses, window, int(sc.overlap), margin, num_devices, closure_radius)
    logger.info(
        describe(
            plan,
            extent_m,
            single_cube_detail_m(extent_m, config.model.pos_freqs, margin),
            float(sc.max_detail_m),
            config.model.pos_freqs,
            margin,
        )
    )
    return plan


def count_submaps(poses: np.ndarray, window: int, overlap: int, closure_radius_m: float) -> int:
    """How many real submaps plan_submaps makes of S keyframes (poses [S, 4, 4]) with these windows."""
    return len(submap_members(poses, window, overlap, closure_radius_m))


def window_for_limit(poses: np.ndarray, window: int, overlap: int, closure_radius_m: float, limit: int) -> int:
    """The smallest window >= `window` whose plan has at most `limit` submaps (the whole sequence at worst).

    Every submap draws rays each step (train.batch_rays_per_cube), so their number sets what a step costs
    and how few rays each field sees: on 2 CPU cores, Riverside02's 0.25 m detail rule made 340 submaps of 3
    keyframes (2.4 s a step). Larger windows mean larger cubes, so coarser detail than submaps.max_detail_m."""
    s = len(poses)
    while window < s and count_submaps(poses, window, overlap, closure_radius_m) > limit:
        window += 1
    return window


def describe(
    plan: SubmapPlan, extent_m: float, detail_m: float, max_detail_m: float, pos_freqs: int, margin: float
) -> str:
    """The log line saying how the sequence was split."""
    real = plan.weight > 0
    sizes = 2.0 * margin / plan.scales[real]
    details = [single_cube_detail_m(e, pos_freqs, margin) for e in sizes]
    consecutive = np.all(np.diff(plan.members, axis=1) == 1, axis=1) & real
    closures = int(real.sum() - consecutive.sum())
    return (
        f"submaps: the keyframes span {extent_m:.0f} m, one cube's finest detail would be {detail_m:.2f} m "
        f"(> submaps.max_detail_m={max_detail_m:g}); split into {int(consecutive.sum())} submaps of {plan.window} "
        f"consecutive keyframes"
        + (f" and {closures} loop-closure submaps (two visits of one place)" if closures else "")
        + f" ({sizes.min():.0f}-{sizes.max():.0f} m cubes, finest detail "
        f"{min(details):.2f}-{max(details):.2f} m)"
        + (f", padded with {int((~real).sum())} empty submaps to fill the devices" if (~real).any() else "")
    )


def tile_memberships(lower: np.ndarray, upper: np.ndarray, tile_m: float) -> np.ndarray:
    """For comparison with windows: how many square x-y tiles of side tile_m each scan's box touches [S]."""
    lo = np.floor(lower[:, :2] / tile_m)
    hi = np.floor(upper[:, :2] / tile_m)
    return np.prod(hi - lo + 1, axis=1).astype(np.int64)


@dataclasses.dataclass
class SubmapArrays:
    """Per-submap tensors (numpy), stacked over M submaps, rays padded to R (the largest submap's count).

    directions [M, R, 3] float32 sensor frame; ranges [M, R] float32 in the submap's normalised units;
    scan_index [M, R] int32 local slot (0..W-1); num_rays [M] int32;
    T_init [M, W, 4, 4] float32 initial poses in each submap's normalised frame; scan_global [M, W] int32
    keyframe of each slot (a row of the shared poses); scale [M] float32 s_m (metres -> normalised);
    rho_factor [M] float32 s_m / s_ref; weight [M] float32."""

    directions: np.ndarray
    ranges: np.ndarray
    scan_index: np.ndarray
    num_rays: np.ndarray
    T_init: np.ndarray
    scan_global: np.ndarray
    scale: np.ndarray
    rho_factor: np.ndarray
    weight: np.ndarray


def submap_arrays(plan: SubmapPlan, rays_m, poses: np.ndarray) -> SubmapArrays:
    """Stack each submap's rays and frames. rays_m: a RaySet of all keyframes with ranges in METRES (scale 1)
    and rays grouped by scan; poses: [S, 4, 4] initial poses (world, metres), the ones training starts from."""
    scan_index = np.asarray(rays_m.scan_index)
    counts = np.bincount(scan_index, minlength=len(poses))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    m, w = plan.members.shape
    per = [int(counts[row].sum()) for row in plan.members]
    r = max(max(per), 1)
    out = SubmapArrays(
        directions=np.zeros((m, r, 3), np.float32),
        ranges=np.ones((m, r), np.float32),
        scan_index=np.zeros((m, r), np.int32),
        num_rays=np.asarray(per, np.int32),
        T_init=np.zeros((m, w, 4, 4), np.float32),
        scan_global=plan.members.astype(np.int32),
        scale=plan.scales.astype(np.float32),
        rho_factor=plan.rho_factor.astype(np.float32),
        weight=plan.weight.astype(np.float32),
    )
    for i, (row, norm) in enumerate(zip(plan.members, plan.norms)):
        at = 0
        for slot, s in enumerate(row):
            n = int(counts[s])
            sl = slice(starts[s], starts[s] + n)
            out.directions[i, at : at + n] = rays_m.directions[sl]
            out.ranges[i, at : at + n] = rays_m.ranges[sl] * norm.scale
            out.scan_index[i, at : at + n] = slot
            at += n
        # Padding rays (never drawn: the sampler draws below num_rays) repeat the first ray, harmless values.
        out.directions[i, at:] = out.directions[i, 0] if at else (1.0, 0.0, 0.0)
        out.T_init[i] = norm.poses_to_normalized(poses[row]).astype(np.float32)
    return out


def describe_membership(plan: SubmapPlan, num_scans: int) -> np.ndarray:
    """How many real submaps hold each keyframe [S] (1 or 2 with overlapping windows; never 0)."""
    count = np.zeros(num_scans, np.int64)
    for row, w in zip(plan.members, plan.weight):
        if w > 0:
            count[row] += 1
    return count


def mesh_size(plan: SubmapPlan, num_devices: int) -> int:
    """Devices the submap axis is sharded over: as many as given, never more than the real submaps."""
    return max(1, min(int(num_devices), int((plan.weight > 0).sum())))
