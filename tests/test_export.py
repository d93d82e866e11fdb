"""Round trips of a run's outputs through the neld_jax.data readers."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax.data.poses import read_kitti, read_tum
from neld_jax.data.scans import read_scan
from neld_jax.errors import DataError
from neld_jax.geometry import register_scans
from neld_jax.writing import export


def _poses(num=5, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (num, 1, 1))
    poses[:, :3, :3] = Rotation.random(num, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-20, 20, (num, 3))
    return poses


def test_write_poses_round_trips_tum_and_kitti(tmp_path):
    poses = _poses()
    stamps = 1.7e9 + 0.1 * np.arange(len(poses))
    tum_path, kitti_path = export.write_poses(tmp_path / "out", "poses_optimized", stamps, poses)
    assert tum_path.name == "poses_optimized.txt" and kitti_path.name == "poses_optimized.kitti"
    read_stamps, read_poses = read_tum(tum_path)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6)
    np.testing.assert_allclose(read_poses, poses, atol=1e-12)
    np.testing.assert_allclose(read_kitti(kitti_path), poses, atol=1e-12)


def test_keyframe_poses_are_carried_to_every_input_scan_and_written(tmp_path):
    # Keyframes 0 and 2 of three scans moved by one rigid correction: the scan between them takes it too.
    from types import SimpleNamespace

    poses = _poses(3)
    loaded = SimpleNamespace(poses=poses, timestamps=np.array([10.0, 10.1, 10.2]))
    keyframes = SimpleNamespace(loaded_index=np.array([0, 2]))
    correction = _poses(1, seed=4)[0]
    written = export.write_keyframe_poses(tmp_path, "poses_baseline", loaded, keyframes, correction @ poses[[0, 2]])
    np.testing.assert_allclose(written, correction @ poses, atol=1e-9)
    stamps, read = read_tum(tmp_path / "poses_baseline.txt")
    np.testing.assert_allclose(stamps, loaded.timestamps, atol=1e-6)
    np.testing.assert_allclose(read, written, atol=1e-9)


def test_write_poses_without_timestamps_numbers_the_poses(tmp_path):
    export.write_poses(tmp_path, "poses_initial", None, _poses(3))
    stamps, _ = read_tum(tmp_path / "poses_initial.txt")
    np.testing.assert_array_equal(stamps, [0.0, 1.0, 2.0])


def test_register_scans_moves_each_scan_into_the_world():
    poses = _poses(2)
    scans = [np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]])]
    world = register_scans(scans, poses)
    assert world.shape == (3, 3)
    np.testing.assert_allclose(world[0], poses[0, :3, 0] + poses[0, :3, 3])
    np.testing.assert_allclose(world[1], poses[1, :3, 3])
    np.testing.assert_allclose(world[2], 2.0 * poses[1, :3, 1] + poses[1, :3, 3])
    with pytest.raises(ValueError, match="2 scans but 3 poses"):
        register_scans(scans, _poses(3))


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_write_point_cloud_round_trip(tmp_path, suffix):
    points = np.random.default_rng(0).uniform(-50, 50, (500, 3))
    path = export.write_point_cloud(tmp_path / f"map{suffix}", points)
    np.testing.assert_array_equal(read_scan(path), points)  # stored as float64


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_write_point_cloud_keeps_utm_sized_coordinates(tmp_path, suffix):
    # float32 spacing at 4e6 m is 0.25 m; a map in UTM coordinates must keep millimetres.
    points = np.array([[4e6 + 0.1234, -4e6 + 0.5678, 12.3456], [4e6 + 0.0004, 4e6 - 0.0007, -0.0009]])
    path = export.write_point_cloud(tmp_path / f"map{suffix}", points)
    assert np.abs(read_scan(path) - points).max() < 1e-3


def test_write_point_cloud_rejects_bad_input(tmp_path):
    with pytest.raises(DataError, match="map.xyz"):
        export.write_point_cloud(tmp_path / "map.xyz", np.zeros((3, 3)))
    with pytest.raises(DataError, match="NaN"):
        export.write_point_cloud(tmp_path / "map.ply", np.array([[0.0, np.nan, 0.0]]))


def test_write_raw_map_registers_and_downsamples(tmp_path):
    poses = _poses(2)
    scan = np.random.default_rng(1).uniform(0, 1, (2000, 3))
    full = export.write_raw_map(tmp_path / "full.ply", [scan, scan], poses)
    assert len(read_scan(tmp_path / "full.ply")) == 4000
    np.testing.assert_allclose(read_scan(tmp_path / "full.ply"), full, atol=1e-4)
    coarse = export.write_raw_map(tmp_path / "coarse.ply", [scan, scan], poses, voxel_size=0.5)
    assert 2 <= len(coarse) < 200
    assert len(read_scan(tmp_path / "coarse.ply")) == len(coarse)


def test_write_json_merges_and_converts(tmp_path):
    path = tmp_path / "metrics.json"
    export.write_json(path, {"run": {"steps": np.int64(10)}})
    export.write_json(
        path, {"evaluation": {"rmse": np.float32(0.5), "curve": np.arange(3), "bad": float("nan"), "where": tmp_path}}
    )
    data = json.loads(path.read_text())
    assert data["run"] == {"steps": 10}
    assert data["evaluation"] == {"rmse": 0.5, "curve": [0, 1, 2], "bad": None, "where": str(tmp_path)}
    export.write_json(path, {"run": {"steps": 20}})
    assert json.loads(path.read_text())["run"] == {"steps": 20}
    assert "evaluation" in json.loads(path.read_text())
    export.write_json(path, {"only": 1}, merge=False)
    assert json.loads(path.read_text()) == {"only": 1}
    assert not path.with_name("metrics.json.tmp").exists()


def test_write_json_refuses_to_merge_into_garbage(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("[1, 2")
    with pytest.raises(DataError, match="metrics.json"):
        export.write_json(path, {"a": 1})
