"""A KITTI odometry download written from a synthetic sequence, for the tests: dataset/sequences/NN/{velodyne/*.bin,
times.txt, calib.txt} and dataset/poses/NN.txt, as the benchmark's archives unpack."""

from pathlib import Path

import numpy as np

from neld_jax.data.kitti import VERTICAL_ANGLE_OFFSET_DEG, corrected_elevations
from neld_jax.data.poses import write_kitti
from neld_jax.data.sequence import Sequence
from neld_jax.synthetic.generator import FOV_DEG, cast_scan, loop_poses, make_scene, spinning_lidar_directions

# Velodyne -> camera 0 of the benchmark's sequences 04-10 (x forward, y left, z up -> x right, y down, z forward)
VELODYNE_TO_CAMERA = np.array(
    [
        [-1.857739385241e-03, -9.999659513510e-01, -8.039975204516e-03, -4.784029760483e-03],
        [-6.481465826011e-03, 8.051860151134e-03, -9.999466081774e-01, -7.337429464231e-02],
        [9.999773098287e-01, -1.805528627661e-03, -6.496203536139e-03, -3.339968064433e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
PROJECTION = "7.18856e+02 0.0 6.071928e+02 0.0 0.0 7.18856e+02 1.852157e+02 0.0 0.0 0.0 1.0 0.0"


def write_kitti_download(base, seq, sequence: str = "07", times=None) -> Path:
    """Write seq (scans [S] x [N_i, 3] in the LiDAR frame, gt_poses [S, 4, 4] or None) under base/dataset as the
    benchmark lays it out; returns ROOT = base/dataset/sequences/<sequence>. The scans are written with the HDL-64E's
    elevation error put in (the loader takes it out again); the ground truth as camera 0's poses from the first
    camera-0 frame. times [S]: the stamps written (default: seq.timestamps less the first)."""
    root = Path(base) / "dataset" / "sequences" / sequence
    (root / "velodyne").mkdir(parents=True)
    for i, scan in enumerate(seq.scans):
        records = np.ones((len(scan), 4), dtype=np.float32)  # reflectance 1
        records[:, :3] = corrected_elevations(scan, -VERTICAL_ANGLE_OFFSET_DEG)
        records.tofile(root / "velodyne" / f"{i:06d}.bin")
    stamps = seq.timestamps - seq.timestamps[0] if times is None else np.asarray(times)
    (root / "times.txt").write_text("".join(f"{t:e}\n" for t in stamps))
    tr = " ".join(f"{v:.12e}" for v in VELODYNE_TO_CAMERA[:3].reshape(-1))
    (root / "calib.txt").write_text("".join(f"P{k}: {PROJECTION}\n" for k in range(4)) + f"Tr: {tr}\n")
    if seq.gt_poses is not None:
        lidar = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses
        write_kitti(
            Path(base) / "dataset" / "poses" / f"{sequence}.txt",
            VELODYNE_TO_CAMERA @ lidar @ np.linalg.inv(VELODYNE_TO_CAMERA),
        )
    return root


def rigid_scans(
    num_scans: int = 40, loop_scans: int = 300, radius_m: float = 10.0, max_range_m: float = 40.0, seed: int = 0
) -> Sequence:
    """The first num_scans of the synthetic loop cut into loop_scans steps (0.2 m apart at the defaults), each cast
    from one pose (rigid, as the benchmark's motion-compensated scans), stamped 0.1 s apart, with ground truth."""
    scene, _ = make_scene(seed, 60.0, path_radius_m=radius_m)
    gt_poses = loop_poses(np.arange(num_scans) / loop_scans, radius_m, seed)
    directions = spinning_lidar_directions(32, FOV_DEG[1], FOV_DEG[0], 512)
    rng = np.random.default_rng(seed + 2)
    scans = [cast_scan(scene, pose, directions, max_range_m, 0.01, rng) for pose in gt_poses]
    return Sequence(
        scans=scans,
        poses=None,
        timestamps=0.1 * np.arange(num_scans),
        gt_poses=gt_poses,
        name="rigid_scans",
        source="synthetic",
    )
