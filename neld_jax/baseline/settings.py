"""The classical baseline's settings (config.baseline), and what every step of it shares: a progress bar and the
one-line list of the scans a step warns about."""

from __future__ import annotations

import dataclasses

from neld_jax.judging import crispness


@dataclasses.dataclass(frozen=True)
class BaselineSettings:
    """The baseline's settings; metres unless named otherwise. The config's baseline group exposes voxel_size_m,
    loop_radius_m, global_loops_per_scan and map_rounds with the defaults given here (neld_jax.config declares them
    from these), and its eval group the judge's crispness settings (judging.crispness's defaults)."""

    voxel_size_m: float = 0.1  # scans are downsampled to this grid before ICP
    normal_radius_m: float = 0.5  # normal estimation radius (LiDAR scans are sparse: at least 0.5 m)
    window: int = 10  # scans in the local map of the scan-to-map chain; loop closures are at least this far apart
    icp_distances_m: tuple = (1.0, 0.5, 0.25, 0.1)  # correspondence distances of the multi-scale ICP, coarse first
    icp_iterations: int = 30  # per scale
    # At the ICP scales above normal_check_above_m, points pair only where their normals agree this well (cosine):
    # at thin walls seen from both sides Open3D's plain nearest-neighbour pairs slide scans by the wall's thickness
    # (point_to_plane_icp). The finer scales pair as Open3D does: their distances do not reach across a wall, and
    # the check there cost accuracy (hard synthetic: 0.52 -> 1.0-1.1 mm ATE with it at every scale, cosine 0-0.5).
    min_normal_cos: float = 0.5
    normal_check_above_m: float = 0.25
    min_chain_fitness: float = 0.1  # below this overlap a chain link keeps the odometry's increment (and warns)
    # Scan-to-map ICP between keyframes that overlap their local map this little neither holds nor can be checked: on
    # MulRan Riverside02 (keyframes 7-8 m apart on roads, median overlap 19-20 %) the links slid by up to 8.6 m or
    # kept the odometry's increment (87-200 of the links), the chains bent 27 and 61 m and the run refused them after
    # 158-273 s of ICP; the handheld sequences' chains overlap 74-79 % (median) and keep no link. From
    # chain_check_links links on, once the links' median overlap falls below chain_min_median_overlap, the chain is
    # given up, the pose graph skipped, and the refinement starts from the input (what the run's refinement_start
    # chose there anyway). 0.4 lies midway between Riverside02's median over its first 30 links (16 and 31 %) and the
    # lowest running median of the handheld and long synthetic chains (52-77 %). 0 switches it off.
    chain_min_median_overlap: float = 0.4
    chain_check_links: int = 30
    # A chain link whose ICP result moves the scan more than this from the odometry's increment keeps the increment
    # (and warns): in corridors and stairwells ICP slides along the free axis with a good overlap (measured on
    # HKU_2: two links jumped 0.84 and 1.9 m between keyframes 0.2 m apart; docs/evaluation.md), unless the global
    # registration (FPFH + RANSAC, no start) lands within max_loop_correction_m of ICP's pose: then the increment was
    # wrong, not ICP (KISS-ICP's first second at speed, 0.54 m off on the 20 m synthetic loop).
    max_link_correction_m: float = 0.5
    loop_radius_m: float = 10.0  # loop-closure candidates: scans closer than this in the chain's frame
    max_loops_per_scan: int = 4  # the nearest candidates only: dense trajectories give thousands of pairs
    min_loop_fitness: float = 0.3  # loop closures that overlap less are not added
    # Loop closures start from the chain, which is within dm of them, and corrections above max_loop_correction_m are
    # dropped anyway: the 1 m scale only cost time (HKU_2: 1018 candidates in 57 s instead of about 180 s, map as
    # crisp: entropy -3.408 against -3.405).
    loop_icp_distances_m: tuple = (0.5, 0.25, 0.1)
    # Loop closures whose ICP result moves scan i more than this from where the chain puts it (relative to j) are
    # not added: in corridors ICP slides along the free axis and still overlaps well (docs/evaluation.md).
    max_loop_correction_m: float = 0.2
    # A loop candidate whose ICP from the chain overlaps less than min_loop_fitness (the chain drifted beyond ICP's
    # basin: 4.5 m at the long synthetic route's loop), over a path long enough for loop_drift_fraction of it to
    # exceed max_loop_correction_m, and with no kept closure between the same stretches of the route, is registered
    # again from FPFH features + RANSAC, then multi-scale ICP (global_icp_distances_m), for at most
    # global_loops_per_scan of each scan's candidates, the nearest. Such a closure is kept when it overlaps at least
    # min_loop_fitness and moves the scan at most max_loop_correction_m + loop_drift_fraction x the chain's path
    # between the two scans (the drift a LiDAR odometry builds up, about 1 % of the distance travelled). A candidate
    # whose ICP overlapped well but moved the scan past max_loop_correction_m over such a path (a slide in a corridor,
    # or drift: the synthetic car's 320 m loop came back 1.03 m off) is registered globally too, and kept only where
    # the global pose lies within max_loop_correction_m of ICP's: a slide depends on ICP's start, drift does not.
    # 0 switches it off.
    global_loops_per_scan: int = 1
    global_voxel_m: float = 0.5  # the features' grid: coarser than ICP's, for speed and repeatable neighbourhoods
    global_feature_radius_m: float = 2.5  # FPFH radius (5 voxels)
    global_icp_distances_m: tuple = (1.0, 0.5, 0.25, 0.1)
    loop_drift_fraction: float = 0.01
    global_seed: int = 0  # RANSAC's random draws (Open3D's global seed), for repeatable runs
    # RANSAC stops at 99.9 % confidence or after this many draws: pairs that share no surface (most candidates that
    # failed ICP on real data: rooms either side of a wall) run to the cap.
    global_ransac_iterations: int = 20000
    # A registration does not move a scan from its guess (the odometry's increment, the chain's pose) along a direction
    # that its pairs fix with less than this share of their normal energy (icp.direction_shares). Measured: 0.008-0.014
    # along a synthetic straight street between parallel walls; the weakest direction of KITTI 00's keyframes (the
    # roll about the road) 0.038-0.09, the synthetic courtyard's 0.09, the long route's gates 0.10-0.23. 0: off.
    min_direction_share: float = 0.02
    # The baseline's poses keep the input's distance travelled over every window this long unless their own distances
    # give a crisper raw map on every query draw (baseline/distances.py: registration shortened KITTI's straight road
    # by 0.2 % where the odometry kept its length). 0 switches it off.
    distance_window_m: float = 50.0
    information_distance_m: float = 0.25  # correspondence distance of the information matrices and the pruning
    edge_prune_threshold: float = 0.25
    # Multi-view refinement after the graph (module docstring, step 4); 0 switches it off. On HKU_2 the rounds took
    # the map's entropy -3.405 -> -3.480 -> -3.491 -> -3.493, about 40-65 s each on 2 cores (docs/evaluation.md).
    map_rounds: int = 2
    map_icp_distances_m: tuple = (0.25, 0.1)
    # The ICP target: the map_gather_points map points nearest to each scan point and within map_gather_m of it
    # (one KD-tree query); 16 points at the 0.1 m grid cover a plane to about 0.2 m around each scan point.
    map_gather_points: int = 16
    map_gather_m: float = 0.5
    # The judge of the choices above (which chain, where the rounds start): the raw map's mean map entropy at this
    # radius over this many query points (the run's eval.crispness_radius_m / crispness_queries)
    crispness_radius_m: float = crispness.DEFAULT_RADIUS_M
    crispness_queries: int = crispness.DEFAULT_MAX_QUERIES
    crispness_draws: int = crispness.DEFAULT_DRAWS

    @classmethod
    def from_config(cls, config) -> "BaselineSettings":
        """From a run's config: config.baseline's fields and the judge's (config.eval's crispness settings); the
        rest keep their defaults."""
        return cls.from_groups(config.baseline, config.eval)

    @classmethod
    def from_groups(cls, baseline_cfg, eval_cfg) -> "BaselineSettings":
        """baseline_cfg (config.baseline): its fields; eval_cfg (config.eval): the judge's crispness settings; the
        rest keep their defaults."""
        fields = dict(baseline_cfg)
        unknown = set(fields) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"config.baseline: unknown field(s) {sorted(unknown)}")
        return cls(
            **fields,
            crispness_radius_m=float(eval_cfg.crispness_radius_m),
            crispness_queries=int(eval_cfg.crispness_queries),
            crispness_draws=int(eval_cfg.crispness_draws),
        )


def progress_bar(what: str, progress: bool, iterable=None, total: int | None = None):
    """A tqdm bar over the scans or pairs of one step of the baseline (minutes on real recordings), off unless
    `progress`."""
    from tqdm.auto import tqdm  # an effect at the edge, as train.fit's bar

    return tqdm(
        iterable, total=total, desc=f"baseline: {what}", unit=" registrations", disable=not progress, dynamic_ncols=True
    )


def first_items(items: list[str], count: int = 12) -> str:
    """The first `count` items, comma-separated, and how many more (for one log line)."""
    more = f" and {len(items) - count} more" if len(items) > count else ""
    return ", ".join(items[:count]) + more
