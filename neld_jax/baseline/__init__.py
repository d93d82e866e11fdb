"""The classical baseline: Open3D scan-to-map ICP, then a pose graph with loop closures.

What a user reaches for before a neural method, built the way LiDAR odometry back-ends are (docs/evaluation.md,
"The classical baseline"), starting from the initial (odometry) poses:
1. a scan-to-map chain: each scan is registered by multi-scale point-to-plane ICP to a local map of the
   `window` scans before it (already registered), from the odometry's increment as the initial guess. Scan to
   map is far more accurate than scan to scan on sparse keyframes (a few thousand points each), and every
   registration starts from the odometry's relative motion only, so the chain does not depend on how far the
   odometry drifted overall (measured on real keyframes: two starts 1.5 m apart give chains 1 cm apart); a link
   that moves the scan more than `max_link_correction_m` from that increment keeps the increment, and a chain
   whose links overlap their local maps too little is given up (`chain_min_median_overlap`: keyframes too far
   apart for ICP; steps 2 and 3 are skipped and step 4 starts from the input). At their coarse
   scales the ICPs here pair points only where their normals agree (`point_to_plane_icp`: thin walls). With
   `keep_input_tilt` (an IMU-aided odometry's input) every link keeps the input's up axis, so that the links' pitch
   errors do not bow the route (docs/evaluation.md, "Keeping the input's tilt"). Whether the input's tilt is to be
   trusted, the data decides: the chain runs twice, keeping the input's up axis and free, and the one whose raw map
   is crisper goes on (a tie keeps the input's tilt: an IMU-aided odometry's roll and pitch do not drift, a
   LiDAR-only odometry's do, and then the chain that keeps them blurs the map; `choose_chain`);
2. a pose graph on the chain's poses: one edge per consecutive pair (the chain's relative pose), and
   loop-closure edges between scans at least `window` apart that lie within `loop_radius_m` IN THE CHAIN'S
   FRAME (candidates found in a drifted frame are wrong or far off), each registered by multi-scale ICP
   (`loop_icp_distances_m`, without the chain's coarsest scale) and kept only when its fitness (overlap
   fraction) reaches `min_loop_fitness` and it moves the scan by at most `max_loop_correction_m` from where the
   chain puts it; loop edges are "uncertain", so the line process may prune them. Where ICP found too little
   overlap, or moved the scan further than that, and no closure joins the same two stretches of the route, the
   chain may have drifted beyond ICP's reach or its gate: the nearest such pair per scan is registered again from
   FPFH features + RANSAC (`global_registration`) and kept, as a certain edge, within the drift a LiDAR odometry can
   build up over the path between the two scans (`loop_drift_fraction`), and, where ICP had moved the scan, only
   where both registrations agree (a slide along a corridor depends on where ICP started);
3. Levenberg-Marquardt `global_optimization`, scan 0 held fixed;
4. `map_rounds` rounds of multi-view refinement: each scan is registered again, by point-to-plane ICP at
   `map_icp_distances_m`, to the map of the OTHER scans (voxel-downsampled, normals re-estimated). A round has two
   halves, the even scans against the odd scans' map, then the odd against the even, so that no scan meets its own
   points and one map (one KD-tree) serves half the scans. The gates of the loop closures apply. This is what makes
   the map crisp: the chain and the graph only align scans in pairs or to a few neighbours, and their errors of
   about a centimetre per link add up (measured on real keyframes: docs/evaluation.md). The rounds start from the
   crisper of the graph's and the chain's poses (a tie keeps the graph's), the input's only where the chain was
   given up: the rounds keep their start's route-long shape, and the input's is its drift (docs/evaluation.md,
   "Where the refinement starts");
5. the distance travelled: the poses take the input's distances over every `distance_window_m` window (their own
   rotations and directions of travel) unless their own give a crisper raw map on every query draw (`distances`).
Every ICP of these steps leaves its guess's motion along a direction that its pairs fix with less than
`min_direction_share` of their normal energy (along a straight street between parallel walls: icp.direction_shares,
`held_along_weak_directions`; docs/evaluation.md, "Weak directions and the distance travelled").

The modules, one step each: `settings` (BaselineSettings), `icp` (the ICP kernels: prepared scans, the target
index, point-to-plane ICP and its step, the information matrix; their sums in a fixed order, so that the same input
gives the same poses bit for bit), `chain` (step 1), `graph` (steps 2 and 3, the global registration among them),
`refine` (step 4), `distances` (step 5), `segments` (recordings joined in one sequence: where the chain restarts,
the links between them) and `sequence` (`register_sequence`: arrays in, a BaselineResult out). Its command-line
edge is neld_jax.commands.baseline.
"""

import importlib

# Each public name and the module it lives in: a name is imported when first used, so that
# `import neld_jax.baseline.settings` (the config reads BaselineSettings' defaults) does not load Open3D.
_HOMES = {
    "chain": ("TILT_MARGIN", "choose_chain", "scan_to_map_chain"),
    "graph": ("LoopClosures", "candidate_pairs", "fpfh_features", "global_registration", "loop_closed_graph"),
    "icp": (
        "IcpResult",
        "TargetIndex",
        "correction_m",
        "information",
        "multiscale_icp",
        "point_to_plane_icp",
        "point_to_plane_step",
        "prepare_clouds",
        "prepare_scan",
    ),
    "multiview": ("Refinement", "choose_refinement_start", "refine_against_map"),
    "pipeline": ("BaselineResult", "anchored", "register_sequence"),
    "segments": ("Segments",),
    "settings": ("BaselineSettings",),
}
_MODULE_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = sorted(_MODULE_OF)


_MODULES = (*_HOMES, "distances")


def __getattr__(name: str):
    """A public name, or a module of the package (`baseline.chain`), imported on first use."""
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name not in _MODULE_OF:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_MODULE_OF[name]}"), name)
    globals()[name] = value  # the next use finds it without this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
