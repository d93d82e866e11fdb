"""Registration from no initial guess: FPFH features (Rusu et al., ICRA 2009) matched by Open3D's RANSAC. The
classical baseline's global loop closures, the odometry's recovery of a lost scan and its check (odometry_check.py)
start their ICP here."""

from __future__ import annotations

import numpy as np


def fpfh_features(cloud, voxel_m: float, radius_m: float):
    """An Open3D cloud (its own frame) -> (the cloud on a voxel_m grid with normals, its FPFH features within
    radius_m)."""
    import open3d as o3d

    coarse = cloud.voxel_down_sample(voxel_m)
    coarse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_m, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(
        coarse, o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=100)
    )
    return coarse, features


def ransac_alignment(
    source_features, target_features, voxel_m: float, iterations: int, seed: int, confidence: float = 0.999
) -> np.ndarray:
    """The transform [4, 4] mapping the source cloud into the target's frame that RANSAC finds from their
    (coarse cloud, FPFH features) (fpfh_features, both at voxel_m): three mutual feature matches a draw, checked by
    edge length and by distance (1.5 voxels), at most `iterations` draws (`confidence` stops it earlier; 1: never),
    Open3D's random draws seeded by `seed` (its threads still make it vary from run to run). Coarse: ICP refines
    it."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    (source_coarse, source_fpfh), (target_coarse, target_fpfh) = source_features, target_features
    distance = 1.5 * voxel_m
    o3d.utility.random.seed(seed)
    ransac = registration.registration_ransac_based_on_feature_matching(
        source_coarse,
        target_coarse,
        source_fpfh,
        target_fpfh,
        True,
        distance,
        registration.TransformationEstimationPointToPoint(False),
        3,
        [
            registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            registration.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        registration.RANSACConvergenceCriteria(iterations, confidence),
    )
    return np.asarray(ransac.transformation, dtype=np.float64)


def point_cloud(points: np.ndarray):
    """points [N, 3] -> an Open3D cloud."""
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


def refined_alignment(
    source, target, guess: np.ndarray, distances_m: tuple[float, ...], normal_radius_m: float
) -> tuple[np.ndarray, float]:
    """Open3D's point-to-plane ICP of the Open3D cloud source onto target (each in its own frame, target's normals
    estimated within normal_radius_m where it has none) from the transform guess [4, 4], pairing points within each
    of distances_m in turn (wide first: a coarse guess is off by a voxel or two) -> (the transform [4, 4] mapping
    source into target's frame, the share of source's points within the last distance of target's under it: Open3D's
    fitness; the guess and 0 for clouds of fewer than 3 points)."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    if len(source.points) < 3 or len(target.points) < 3:
        return np.asarray(guess, np.float64), 0.0
    if not target.has_normals():
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30))
    transform, fitness = np.asarray(guess, np.float64), 0.0
    for distance in distances_m:
        result = registration.registration_icp(
            source, target, distance, transform, registration.TransformationEstimationPointToPlane()
        )
        transform, fitness = np.asarray(result.transformation, np.float64), float(result.fitness)
    return transform, fitness


def fitness(source, target, transform: np.ndarray, distance_m: float) -> float:
    """The share of the Open3D cloud source's points within distance_m of target's under transform [4, 4] (source
    into target's frame): Open3D's fitness of a given alignment."""
    import open3d as o3d

    if len(source.points) == 0 or len(target.points) == 0:
        return 0.0
    return float(o3d.pipelines.registration.evaluate_registration(source, target, distance_m, transform).fitness)
