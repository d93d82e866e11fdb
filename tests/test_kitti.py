"""The KITTI odometry layout as downloaded (neld_jax.data.kitti): the scans with the HDL-64E's elevation correction,
the stamps, the ground truth moved from camera 0 into the LiDAR frame, KISS-ICP's poses, one clear line for each kind
of broken download, and a run through bin/train.py."""

import numpy as np
import pytest
from conftest import make_tiny_config, train_a_download_briefly
from kitti_layout import VELODYNE_TO_CAMERA, rigid_scans, write_kitti_download

from neld_jax.data.kitti import camera_to_lidar, corrected_elevations, load_kitti, read_calibration
from neld_jax.data.poses import read_tum
from neld_jax.errors import DataError
from neld_jax.judging import metrics
from neld_jax.steps.inputs import load_sequence


@pytest.fixture(scope="module")
def scans():
    return rigid_scans()


@pytest.fixture(scope="module")
def download(scans, tmp_path_factory):
    return write_kitti_download(tmp_path_factory.mktemp("kitti"), scans)


def _data(root, **overrides):
    data = make_tiny_config().data
    data.format, data.root, data.max_range_m = "kitti", str(root), 40.0
    data.update(overrides)
    return data


def test_the_elevation_correction_is_kiss_icps():
    from kiss_icp.pybind import kiss_icp_pybind

    points = np.random.default_rng(0).normal(size=(200, 3)) * [20.0, 20.0, 2.0]
    reference = np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(points)))
    np.testing.assert_allclose(corrected_elevations(points), reference, atol=1e-9)
    np.testing.assert_array_equal(corrected_elevations(np.array([[0.0, 0.0, 3.0]])), [[0.0, 0.0, 3.0]])


def test_ground_truth_moves_from_camera_0_into_the_lidar_frame():
    lidar = np.eye(4)
    lidar[:3, 3] = [2.0, 0.5, 0.1]  # 2 m forward in the LiDAR frame is 2 m along the camera's z
    camera = VELODYNE_TO_CAMERA @ lidar @ np.linalg.inv(VELODYNE_TO_CAMERA)
    assert camera[2, 3] == pytest.approx(2.0, abs=0.02)
    np.testing.assert_allclose(camera_to_lidar(camera[None], VELODYNE_TO_CAMERA)[0], lidar, atol=1e-12)


def test_the_download_loads_scans_stamps_and_ground_truth(scans, download):
    seq = load_kitti(download)
    assert seq.poses is None and seq.point_times is None and seq.num_scans == scans.num_scans
    assert seq.files[0] == "velodyne/000000.bin"
    np.testing.assert_allclose(seq.timestamps, scans.timestamps, atol=1e-6)
    for loaded, written in zip(seq.scans[:3], scans.scans[:3]):
        np.testing.assert_allclose(loaded, written, atol=2e-5)  # float32 records, the correction undone
    np.testing.assert_allclose(seq.gt_poses, np.linalg.inv(scans.gt_poses[0]) @ scans.gt_poses, atol=1e-9)


def test_a_download_gets_kiss_icp_poses_without_deskewing(scans, download, caplog):
    caplog.set_level("INFO")
    seq = load_sequence(_data(download))
    assert seq.poses_from == "kiss_icp" and seq.point_times is None
    assert "rigid scans" in caplog.text and "derived from its azimuth" not in caplog.text
    assert metrics.ate(seq.poses, seq.gt_poses)["translation_rmse_m"] < 0.1


def test_a_broken_download_is_one_line_naming_the_file(scans, tmp_path):
    few = type(scans)(scans=scans.scans[:3], poses=None, timestamps=scans.timestamps[:3], gt_poses=scans.gt_poses[:3])
    root = write_kitti_download(tmp_path / "a", few)
    calib = (root / "calib.txt").read_text()

    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DataError, match=r"times.txt has 2 stamps but .*velodyne has 3 scans"):
        load_kitti(root)
    (root / "times.txt").write_text("0.0\n0.1\n0.2\n")

    (root / "calib.txt").write_text(calib.replace("Tr:", "Tv:"))
    with pytest.raises(DataError, match=r"calib.txt: no 'Tr:' line"):
        load_kitti(root)
    (root / "calib.txt").write_text(calib.rsplit(" ", 1)[0] + "\n")
    with pytest.raises(DataError, match=r"calib.txt, line 5: 'Tr:' must hold 12 finite numbers"):
        load_kitti(root)
    (root / "calib.txt").write_text(calib.replace("Tr: -1.857739385241e-03", "Tr: 5.0"))
    with pytest.raises(DataError, match=r"is not a rotation"):
        load_kitti(root)
    (root / "calib.txt").write_text("P0 1 2 3\n")
    with pytest.raises(DataError, match=r"calib.txt, line 1: expected '<key>: <numbers>'"):
        read_calibration(root / "calib.txt")
    (root / "calib.txt").unlink()
    with pytest.raises(DataError, match=r"calib.txt: calibration file does not exist"):
        load_kitti(root)
    (root / "calib.txt").write_text(calib)

    with open(root / "velodyne" / "000001.bin", "ab") as f:
        f.write(b"\0" * 5)
    with pytest.raises(DataError, match=r"000001.bin: KITTI .bin size \d+ bytes is not a multiple of 16"):
        load_kitti(root)

    with pytest.raises(DataError, match=r"no velodyne/ folder"):
        load_kitti(root.parent)


def test_a_download_without_ground_truth_needs_no_calibration(scans, tmp_path):
    few = type(scans)(scans=scans.scans[:2], poses=None, timestamps=scans.timestamps[:2])
    root = write_kitti_download(tmp_path, few, sequence="11")
    (root / "calib.txt").unlink()
    seq = load_kitti(root)
    assert seq.gt_poses is None and seq.num_scans == 2


def test_a_download_runs_through_the_command(scans, tmp_path):
    half = type(scans)(
        scans=scans.scans[:20], poses=None, timestamps=scans.timestamps[:20], gt_poses=scans.gt_poses[:20]
    )
    download = write_kitti_download(tmp_path / "download", half)
    out = tmp_path / "run"
    done = train_a_download_briefly("kitti.py", download, out)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "making the initial poses from the 20 scans with KISS-ICP" in done.stderr
    _, odometry_poses = read_tum(out / "poses_odometry.txt")
    _, gt = read_tum(out / "poses_gt.txt")
    assert len(odometry_poses) == len(gt) == 20
    assert metrics.ate(odometry_poses, gt)["translation_rmse_m"] < 0.1
