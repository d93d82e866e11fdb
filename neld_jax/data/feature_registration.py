"""Registration from no initial guess: FPFH features (Rusu et al., ICRA 2009) matched by Open3D's RANSAC. The
classical baseline's global loop closures and the odometry's recovery of a lost scan both start their ICP here."""

from __future__ import annotations

import numpy as np


def fpfh_features(cloud, voxel_m: float, radius_m: float):
    """An Open3D cloud (its own frame) -> (the cloud on a voxel_m grid with normals, its FPFH features within
    radius_m)."""
    import open3d as o3d

    coarse = cloud.voxel_down_sample(voxel_m)
    coarse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_m, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(
        coarse, o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=100))
    return coarse, features


def ransac_alignment(source_features, target_features, voxel_m: float, iterations: int, seed: int) -> np.ndarray:
    """The transform [4, 4] mapping the source cloud into the target's frame that RANSAC finds from their
    (coarse cloud, FPFH features) (fpfh_features, both at voxel_m): three mutual feature matches a draw, checked by
    edge length and by distance (1.5 voxels), at most `iterations` draws (99.9 % confidence stops it earlier),
    Open3D's random draws seeded by `seed`. Coarse: ICP refines it."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    (source_coarse, source_fpfh), (target_coarse, target_fpfh) = source_features, target_features
    distance = 1.5 * voxel_m
    o3d.utility.random.seed(seed)
    ransac = registration.registration_ransac_based_on_feature_matching(
        source_coarse, target_coarse, source_fpfh, target_fpfh, True, distance,
        registration.TransformationEstimationPointToPoint(False), 3,
        [registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         registration.CorrespondenceCheckerBasedOnDistance(distance)],
        registration.RANSACConvergenceCriteria(iterations, 0.999))
    return np.asarray(ransac.transformation, dtype=np.float64)
