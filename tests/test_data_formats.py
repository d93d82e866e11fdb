"""Scan and trajectory file formats: round trips and every bad-input case."""

import logging

import numpy as np
import pytest
from fixture_writers import write_newer_college_csv
from scipy.spatial.transform import Rotation

from neld_jax.data.poses import (
    quat_to_rotation,
    read_kitti,
    read_newer_college_csv,
    read_tum,
    rotation_to_quat,
    write_kitti,
    write_tum,
)
from neld_jax.data.scans import read_scan, write_scan
from neld_jax.errors import DataError


def random_points(n=200, seed=0):
    return np.random.default_rng(seed).uniform(-40.0, 40.0, size=(n, 3))


def random_poses(n=7, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=20.0, size=(n, 3))
    return poses


# ---------------------------------------------------------------------------------------------- scans


@pytest.mark.parametrize("ext, atol", [(".pcd", 1e-5), (".ply", 0.0), (".bin", 1e-5), (".npy", 0.0)])
def test_scan_round_trip(tmp_path, ext, atol):
    points = random_points()
    path = tmp_path / f"scan{ext}"
    write_scan(path, points)
    back = read_scan(path)
    assert back.dtype == np.float64 and back.shape == points.shape
    # .pcd and .bin store float32: relative precision ~6e-8 of 40 m
    np.testing.assert_allclose(back, points, rtol=0, atol=atol)


def test_npy_with_extra_columns_keeps_xyz(tmp_path):
    data = np.random.default_rng(1).normal(size=(10, 5))
    np.save(tmp_path / "scan.npy", data)
    np.testing.assert_array_equal(read_scan(tmp_path / "scan.npy"), data[:, :3])


def test_kitti_bin_reads_xyz_and_ignores_intensity(tmp_path):
    records = np.array([[1.0, 2.0, 3.0, 0.7], [4.0, 5.0, 6.0, 0.1]], dtype=np.float32)
    records.tofile(tmp_path / "000000.bin")
    np.testing.assert_array_equal(read_scan(tmp_path / "000000.bin"), records[:, :3])


def test_missing_scan_names_file(tmp_path):
    with pytest.raises(DataError, match="nothere.pcd.*does not exist"):
        read_scan(tmp_path / "nothere.pcd")


def test_unknown_extension_names_file(tmp_path):
    (tmp_path / "scan.xyz").write_text("1 2 3\n")
    with pytest.raises(DataError, match=r"scan\.xyz.*unknown scan file extension"):
        read_scan(tmp_path / "scan.xyz")
    with pytest.raises(DataError, match=r"scan\.xyz"):
        write_scan(tmp_path / "scan.xyz", random_points())


@pytest.mark.parametrize("name", ["bad.pcd", "bad.ply", "bad.npy"])
def test_unreadable_scan_names_file(tmp_path, name):
    (tmp_path / name).write_text("this is not a point cloud\n")
    with pytest.raises(DataError, match=name.replace(".", r"\.")):
        read_scan(tmp_path / name)


def test_truncated_bin_names_file(tmp_path):
    np.zeros(7, dtype=np.float32).tofile(tmp_path / "cut.bin")  # 28 bytes: not whole records
    with pytest.raises(DataError, match=r"cut\.bin.*multiple of 16"):
        read_scan(tmp_path / "cut.bin")


@pytest.mark.parametrize("ext", [".pcd", ".bin", ".npy"])
def test_empty_scan_names_file(tmp_path, ext):
    path = tmp_path / f"empty{ext}"
    path.write_bytes(b"")
    with pytest.raises(DataError, match=f"empty\\{ext}.*empty"):
        read_scan(path)


def test_npy_with_zero_points_is_an_error(tmp_path):
    np.save(tmp_path / "none.npy", np.zeros((0, 3)))
    with pytest.raises(DataError, match=r"none\.npy: scan file holds 0 points"):
        read_scan(tmp_path / "none.npy")


PCD_HEADER_0_POINTS = (
    "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\n"
    "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 0\nDATA ascii\n"
)
PLY_HEADER_0_POINTS = (
    "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
)


@pytest.mark.parametrize("name, text", [("zero.pcd", PCD_HEADER_0_POINTS), ("zero.ply", PLY_HEADER_0_POINTS)])
def test_point_cloud_with_zero_points_names_file(tmp_path, name, text):
    """A recorder that wrote a header but no point: one clear line, not Open3D's 'unable to parse header'."""
    (tmp_path / name).write_text(text)
    with pytest.raises(DataError, match=f"{name}: scan file holds 0 points"):
        read_scan(tmp_path / name)


@pytest.mark.parametrize("ext", [".pcd", ".npy", ".bin"])
def test_zero_points_dropped_with_count(tmp_path, ext, caplog):
    """(0, 0, 0) is how many drivers write 'no return'; a few are dropped quietly, many with a warning."""
    points = random_points(20)
    points[:4] = 0.0
    points[4] = [0.0, 0.0, 1e-3]  # near the origin is a measurement; only exactly (0, 0, 0) goes
    write_scan(tmp_path / f"few{ext}", points)
    with caplog.at_level(logging.DEBUG, logger="neld_jax.data.scans"):
        back = read_scan(tmp_path / f"few{ext}")
    assert back.shape == (16, 3) and back.any(axis=1).all()
    (record,) = [r for r in caplog.records if f"few{ext}" in r.getMessage()]
    assert record.levelno == logging.DEBUG and "dropped 4 of 20" in record.getMessage()
    assert "0 with NaN or infinite coordinates, 4 at (0, 0, 0)" in record.getMessage()

    points[:15] = 0.0
    write_scan(tmp_path / f"many{ext}", points)
    caplog.clear()
    with caplog.at_level(logging.DEBUG, logger="neld_jax.data.scans"):
        assert read_scan(tmp_path / f"many{ext}").shape == (5, 3)
    (record,) = [r for r in caplog.records if f"many{ext}" in r.getMessage()]
    assert record.levelno == logging.WARNING and "dropped 15 of 20" in record.getMessage()


def test_all_zero_or_infinite_scan_is_an_error(tmp_path):
    points = np.zeros((6, 3))
    points[:2] = np.inf
    np.save(tmp_path / "noreturn.npy", points)
    with pytest.raises(
        DataError,
        match=r"noreturn\.npy: scan has no valid points \(all 6 points were NaN or "
        r"infinite \(2\) or at \(0, 0, 0\) \(4\)",
    ):
        read_scan(tmp_path / "noreturn.npy")


def test_npy_wrong_shape_names_file(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros((10, 2)))
    with pytest.raises(DataError, match=r"flat\.npy.*shape"):
        read_scan(tmp_path / "flat.npy")


@pytest.mark.parametrize("ext", [".pcd", ".npy", ".bin"])
def test_nan_points_dropped_with_count(tmp_path, ext, caplog):
    points = random_points(20)
    points[3, 0] = np.nan
    points[7, 2] = np.inf
    points[11, 1] = -np.inf
    path = tmp_path / f"nan{ext}"
    write_scan(path, points)
    with caplog.at_level(logging.WARNING, logger="neld_jax.data.scans"):
        back = read_scan(path)
    assert back.shape == (17, 3)
    assert np.isfinite(back).all()
    assert any("dropped 3 of 20" in r.getMessage() and f"nan{ext}" in r.getMessage() for r in caplog.records)


def test_all_nan_scan_is_an_error(tmp_path):
    np.save(tmp_path / "allnan.npy", np.full((5, 3), np.nan))
    with pytest.raises(DataError, match=r"allnan\.npy.*all 5 points were NaN"):
        read_scan(tmp_path / "allnan.npy")


# ---------------------------------------------------------------------------------------------- poses


def test_quaternion_conversions_round_trip():
    R = Rotation.random(50, random_state=3).as_matrix().reshape(5, 10, 3, 3)
    q = rotation_to_quat(R)
    assert q.shape == (5, 10, 4)
    assert np.all(q[..., 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotation(q), R, atol=1e-12)
    # xyzw order: 90 degrees about z
    np.testing.assert_allclose(
        quat_to_rotation([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )


def test_tum_round_trip(tmp_path):
    poses = random_poses()
    times = 1650000000.0 + np.arange(7) * 0.1 + 0.123456789
    write_tum(tmp_path / "poses.txt", times, poses)
    back_times, back_poses = read_tum(tmp_path / "poses.txt")
    np.testing.assert_allclose(back_times, times, rtol=0, atol=1e-6)  # float64 spacing at 1.65e9 s
    np.testing.assert_allclose(back_poses, poses, rtol=0, atol=1e-12)
    first = [ln for ln in (tmp_path / "poses.txt").read_text().splitlines() if not ln.startswith("#")][0]
    assert first.split()[0] == f"{times[0]:.9f}"


def test_kitti_round_trip(tmp_path):
    poses = random_poses(seed=4)
    write_kitti(tmp_path / "poses.kitti", poses)
    lines = (tmp_path / "poses.kitti").read_text().splitlines()
    assert len(lines) == 7 and all(len(ln.split()) == 12 for ln in lines)
    np.testing.assert_allclose(read_kitti(tmp_path / "poses.kitti"), poses, rtol=0, atol=1e-12)


def test_newer_college_csv_round_trip(tmp_path):
    poses = random_poses(seed=5)
    times = 1583836591.0 + np.arange(7) * 0.25 + 0.182590976
    write_newer_college_csv(tmp_path / "registered_poses.csv", times, poses)
    assert (tmp_path / "registered_poses.csv").read_text().startswith("#sec,nsec,x,y,z,qx,qy,qz,qw\n")
    back_times, back_poses = read_newer_college_csv(tmp_path / "registered_poses.csv")
    np.testing.assert_allclose(back_times, times, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back_poses, poses, rtol=0, atol=1e-12)


@pytest.mark.parametrize("header", ["#sec,nsec,x,y,z,qx,qy,qz,qw\n", "sec,nsec,x,y,z,qx,qy,qz,qw\n", ""])
def test_newer_college_csv_header_optional(tmp_path, header):
    (tmp_path / "gt.csv").write_text(header + "100,500000000,1,2,3,0,0,0,1\n101,0,4,5,6,0,0,1,0\n")
    times, poses = read_newer_college_csv(tmp_path / "gt.csv")
    np.testing.assert_allclose(times, [100.5, 101.0])
    np.testing.assert_allclose(poses[1, :3, 3], [4, 5, 6])
    np.testing.assert_allclose(poses[1, :3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_tum_slightly_off_quaternion_is_normalised(tmp_path):
    (tmp_path / "p.txt").write_text("0.0 1 2 3 0 0 0 1.0005\n")
    _, poses = read_tum(tmp_path / "p.txt")
    np.testing.assert_allclose(poses[0, :3, :3], np.eye(3), atol=1e-12)


def test_tum_bad_quaternion_names_file_and_line(tmp_path):
    (tmp_path / "p.txt").write_text("# header\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1.1\n")
    with pytest.raises(DataError, match=r"p\.txt, line 3: quaternion norm"):
        read_tum(tmp_path / "p.txt")


def test_tum_wrong_column_count_names_line(tmp_path):
    (tmp_path / "p.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"p\.txt, line 2: expected 8 columns.*got 7"):
        read_tum(tmp_path / "p.txt")


def test_tum_non_numeric_names_line(tmp_path):
    (tmp_path / "p.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0 zero 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"p\.txt, line 2: non-numeric"):
        read_tum(tmp_path / "p.txt")


@pytest.mark.parametrize(
    "reader, lines",
    [
        (read_tum, ["# t x y z qx qy qz qw", "0.5 0 0 0 0 0 0 1", "1.0 0 0 0 0 0 0 1", "0.5 1 0 0 0 0 0 1"]),
        (
            read_newer_college_csv,
            [
                "#sec,nsec,x,y,z,qx,qy,qz,qw",
                "0,500000000,0,0,0,0,0,0,1",
                "1,0,0,0,0,0,0,0,1",
                "0,500000000,1,0,0,0,0,0,1",
            ],
        ),
    ],
)
def test_duplicate_timestamp_names_file_and_both_lines(tmp_path, reader, lines):
    (tmp_path / "p.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"p\.txt, lines 2 and 4: the same timestamp 0\.500000000 twice"):
        reader(tmp_path / "p.txt")


def test_unsorted_timestamps_are_read_in_file_order(tmp_path):
    """The reader keeps file order; layout.align_poses decides (error by order, warning by time)."""
    (tmp_path / "p.txt").write_text("2.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    times, poses = read_tum(tmp_path / "p.txt")
    np.testing.assert_array_equal(times, [2.0, 1.0])
    np.testing.assert_array_equal(poses[:, 0, 3], [0.0, 1.0])


def test_tum_nan_value_names_line(tmp_path):
    (tmp_path / "p.txt").write_text("0.0 nan 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"p\.txt, line 1: NaN"):
        read_tum(tmp_path / "p.txt")


@pytest.mark.parametrize("reader", [read_tum, read_kitti, read_newer_college_csv])
def test_empty_pose_file_names_file(tmp_path, reader):
    (tmp_path / "empty.txt").write_text("# only a comment\n\n")
    with pytest.raises(DataError, match=r"empty\.txt.*empty"):
        reader(tmp_path / "empty.txt")


@pytest.mark.parametrize("reader", [read_tum, read_kitti, read_newer_college_csv])
def test_missing_pose_file_names_file(tmp_path, reader):
    with pytest.raises(DataError, match=r"gone\.txt.*does not exist"):
        reader(tmp_path / "gone.txt")


def test_kitti_non_rotation_names_line(tmp_path):
    good = "1 0 0 0 0 1 0 0 0 0 1 0"
    scaled = "2 0 0 0 0 1 0 0 0 0 1 0"  # not orthonormal
    (tmp_path / "k.txt").write_text(f"{good}\n{scaled}\n")
    with pytest.raises(DataError, match=r"k\.txt, line 2: rotation block is not a rotation"):
        read_kitti(tmp_path / "k.txt")


def test_kitti_reflection_names_line(tmp_path):
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 -1 0\n")  # det = -1
    with pytest.raises(DataError, match=r"k\.txt, line 1: .*det = -1"):
        read_kitti(tmp_path / "k.txt")


def test_kitti_wrong_column_count(tmp_path):
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"k\.txt, line 1: expected 12 columns"):
        read_kitti(tmp_path / "k.txt")


def test_writing_a_non_rotation_names_file_and_row(tmp_path):
    poses = random_poses(3)
    poses[2, :3, :3] *= 1.5
    with pytest.raises(DataError, match=r"bad\.txt: pose 2"):
        write_tum(tmp_path / "bad.txt", np.arange(3.0), poses)
