"""The classical baseline: Open3D multiway registration (point-to-plane ICP + pose graph).

What a user reaches for before a neural method: starting from the initial (odometry) poses,
- odometry edges: point-to-plane ICP between neighbouring scans (s, s + 1);
- loop-closure edges: ICP between scans whose initial positions lie within `loop_radius_m` and that
  are not neighbours; these are "uncertain" edges that the optimiser may prune (line process);
- information matrices from `get_information_matrix_from_point_clouds`;
- a pose graph solved by Levenberg-Marquardt `global_optimization`, scan 0 held fixed.

Open3D pose-graph convention: node s holds T_world_scan[s]; an edge (source i, target j) holds
T_j^-1 T_i, the ICP transform that maps scan i's points into scan j's frame.

`multiway_registration` is the algorithm (arrays in, poses out); `run_baseline` is the effectful edge
behind bin/baseline.py (load and preprocess like the trainer, register, write, evaluate).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import ml_collections
import numpy as np
import open3d as o3d

from neld_jax.data.preprocess import load_preprocessed
from neld_jax.evaluate import GT_MAP_FILES, GT_POSES_FILE, evaluate_run
from neld_jax import quality
from neld_jax.export import write_json, write_point_cloud, write_poses, write_raw_map
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)


def _prepare_scan(points: np.ndarray, voxel_size: float, normal_radius: float) -> o3d.geometry.PointCloud:
    """points: [N, 3] sensor frame -> voxel-downsampled Open3D cloud with normals (for point-to-plane)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if voxel_size > 0:
        cloud = cloud.voxel_down_sample(voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    # Normals face the sensor (at the origin of the scan frame); ICP does not need it, but it is cheap.
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def candidate_pairs(positions: np.ndarray, loop_radius_m: float, max_loops_per_scan: int = 4
                    ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Scan pairs to register. positions: [S, 3] initial positions.

    Returns (odometry pairs [(s, s + 1)], loop pairs [(i, j)] with j > i + 1 and |p_i - p_j| < radius). Each
    scan i keeps at most `max_loops_per_scan` loop partners j > i + 1, the nearest ones: a dense trajectory
    (hundreds of keyframes a few metres apart) otherwise gives tens of thousands of pairs for little gain.
    """
    num_scans = len(positions)
    odometry = [(s, s + 1) for s in range(num_scans - 1)]
    distances = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
    loops = []
    for i in range(num_scans):
        partners = [j for j in range(i + 2, num_scans) if distances[i, j] < loop_radius_m]
        partners = sorted(partners, key=lambda j: (distances[i, j], j))[:max(max_loops_per_scan, 0)]
        loops.extend((i, j) for j in sorted(partners))
    return odometry, loops


def multiway_registration(scans: list[np.ndarray], init_poses: np.ndarray, voxel_size: float = 0.2,
                          max_corr_dist: float = 1.0, loop_radius_m: float = 10.0,
                          normal_radius_m: float | None = None, icp_iterations: int = 50,
                          min_loop_fitness: float = 0.3, edge_prune_threshold: float = 0.25) -> np.ndarray:
    """Refine poses with pairwise point-to-plane ICP and a pose graph (Open3D).

    scans: list of S arrays [N_i, 3] in the sensor frame; init_poses: [S, 4, 4] sensor -> world.
    voxel_size: downsampling before ICP (m); max_corr_dist: ICP / information correspondence
    distance (m); loop_radius_m: initial distance below which non-neighbouring scans are registered
    as loop closures; normal_radius_m: normal estimation radius (default 3 x voxel_size, at least
    0.5 m, since LiDAR scans are sparse); loop closures whose ICP fitness (overlap fraction) is below
    min_loop_fitness are not added. Returns refined poses [S, 4, 4], with pose 0 equal to init_poses[0].
    """
    init_poses = np.asarray(init_poses, dtype=np.float64)
    if init_poses.ndim != 3 or init_poses.shape[1:] != (4, 4):
        raise ValueError(f"init_poses must have shape [S, 4, 4], got {init_poses.shape}")
    if len(scans) != len(init_poses):
        raise ValueError(f"{len(scans)} scans but {len(init_poses)} initial poses")
    if len(scans) < 2:
        return init_poses.copy()
    normal_radius = normal_radius_m if normal_radius_m is not None else max(3.0 * voxel_size, 0.5)
    clouds = [_prepare_scan(scan, voxel_size, normal_radius) for scan in scans]
    odometry_pairs, loop_pairs = candidate_pairs(init_poses[:, :3, 3], loop_radius_m)
    logger.info("multiway registration: %d scans, %d odometry and %d loop-closure candidates",
                len(scans), len(odometry_pairs), len(loop_pairs))

    pose_graph = o3d.pipelines.registration.PoseGraph()
    for pose in init_poses:
        pose_graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=icp_iterations)
    point_to_plane = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    num_loops = 0
    edges = [(pair, False) for pair in odometry_pairs] + [(pair, True) for pair in loop_pairs]
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        for (source, target), is_loop in edges:
            initial_guess = np.linalg.inv(init_poses[target]) @ init_poses[source]
            icp = o3d.pipelines.registration.registration_icp(
                clouds[source], clouds[target], max_corr_dist, initial_guess, point_to_plane, criteria)
            if is_loop and icp.fitness < min_loop_fitness:
                continue
            if icp.fitness > 0:
                transform = icp.transformation
                information = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
                    clouds[source], clouds[target], max_corr_dist, transform)
            else:  # no overlap at all: keep the initial relative pose, weakly, so the graph stays connected
                logger.warning("multiway registration: scans %d and %d do not overlap within %.3g m; keeping "
                               "their initial relative pose", source, target, max_corr_dist)
                transform, information = initial_guess, np.eye(6)
            pose_graph.edges.append(o3d.pipelines.registration.PoseGraphEdge(
                source, target, transform, information, uncertain=is_loop))
            num_loops += int(is_loop)

        option = o3d.pipelines.registration.GlobalOptimizationOption(
            max_correspondence_distance=max_corr_dist, edge_prune_threshold=edge_prune_threshold,
            preference_loop_closure=1.0, reference_node=0)
        o3d.pipelines.registration.global_optimization(
            pose_graph, o3d.pipelines.registration.GlobalOptimizationLevenbergMarquardt(),
            o3d.pipelines.registration.GlobalOptimizationConvergenceCriteria(), option)
    logger.info("multiway registration: pose graph with %d odometry and %d loop-closure edges optimised",
                len(odometry_pairs), num_loops)

    optimized = np.stack([np.asarray(node.pose) for node in pose_graph.nodes])
    # Re-anchor exactly on scan 0 (the gauge), whatever the optimiser did with the reference node.
    anchor = init_poses[0] @ np.linalg.inv(optimized[0])
    optimized = anchor @ optimized
    # Remove the round-off that the optimiser leaves in the rotation blocks.
    u, _, vt = np.linalg.svd(optimized[:, :3, :3])
    optimized[:, :3, :3] = u @ vt
    return optimized


# ---------------------------------------------------------------------------------------------
# The command-line run (effects): load, register, write, evaluate
# ---------------------------------------------------------------------------------------------


def run_baseline(config: ml_collections.ConfigDict, voxel_size: float = 0.2, max_corr_dist: float = 1.0,
                 loop_radius_m: float = 10.0) -> dict:
    """Run the baseline on `config.data` and write its outputs into `config.output_dir`.

    config: the ml_collections ConfigDict of bin/train.py (uses config.data, config.output_dir and,
    when present, config.mapping.voxel_size_m and config.eval). Registers the keyframes and carries their
    corrections to every input scan (neld_jax.trajectory), as the trainer does. Writes poses_baseline.txt/.kitti,
    map_raw_baseline.ply and the raw-map crispness of "initial" and "baseline" into metrics.json; also
    poses_initial.txt/.kitti, map_raw_initial.ply, poses_gt.txt and map_gt.ply where they do not exist yet, so
    that the folder can be evaluated on its own.
    Returns {"seconds", "crispness": {method: summary}, "evaluation": evaluate_run's result or None}.
    """
    loaded, sequence = load_preprocessed(config.data)
    t0 = time.perf_counter()
    poses = multiway_registration(sequence.scans, sequence.poses, voxel_size=voxel_size,
                                  max_corr_dist=max_corr_dist, loop_radius_m=loop_radius_m)
    seconds = time.perf_counter() - t0
    poses_all = propagate_corrections(loaded.poses, sequence.loaded_index, poses, loaded.timestamps)

    output_dir = Path(config.output_dir)
    map_voxel = float(config.mapping.voxel_size_m) if "mapping" in config else 0.0
    write_poses(output_dir, "poses_baseline", loaded.timestamps, poses_all)
    write_raw_map(output_dir / "map_raw_baseline.ply", sequence.scans, poses, voxel_size=map_voxel)
    if not (output_dir / "poses_initial.txt").exists():
        write_poses(output_dir, "poses_initial", loaded.timestamps, loaded.poses)
    if not (output_dir / "map_raw_initial.ply").exists():
        write_raw_map(output_dir / "map_raw_initial.ply", sequence.scans, sequence.poses, voxel_size=map_voxel)
    if loaded.gt_poses is not None and not (output_dir / GT_POSES_FILE).exists():
        write_poses(output_dir, GT_POSES_FILE[:-len(".txt")], loaded.timestamps, loaded.gt_poses)
    if sequence.gt_map is not None and not any((output_dir / name).exists() for name in GT_MAP_FILES):
        write_point_cloud(output_dir / GT_MAP_FILES[0], sequence.gt_map)
    evaluation = config.get("eval", ml_collections.ConfigDict())
    crisp, _ = quality.map_crispness(sequence, {"initial": sequence.poses, "baseline": poses}, evaluation)
    crisp = quality.record_crispness(output_dir, crisp)
    write_json(output_dir / "metrics.json", {"baseline": {"seconds": round(seconds, 2), "voxel_size_m": voxel_size,
                                                          "max_corr_dist_m": max_corr_dist,
                                                          "loop_radius_m": loop_radius_m}})
    logger.info("baseline outputs written to %s (registration took %.1f s)", output_dir, seconds)

    result = None
    if sequence.gt_poses is not None or sequence.gt_map is not None:
        result = evaluate_run(output_dir, threshold=evaluation.get("f1_threshold_m", 0.2),
                              raw_cutoff=evaluation.get("raw_cutoff_m", 1.0),
                              map_icp_m=evaluation.get("map_icp_m", 0.0))
    return {"seconds": seconds, "crispness": crisp, "evaluation": result}
