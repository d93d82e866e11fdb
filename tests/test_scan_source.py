"""Scans read from disk when used (neld_jax.data.scan_source): the lazy view gives the points the eager reader gives,
KISS-ICP over the stream gives the poses it gives over a list, the registration of every scan reading each again
from disk gives the poses it gives from memory, and float32 keyframes move the registered poses by far less than
the registration's own error."""

import dataclasses

import numpy as np
import pytest

from neld_jax.data.generic import load_generic
from neld_jax.data.poses import write_tum
from neld_jax.data.preprocess import KeyframeSettings, preprocess
from neld_jax.data.scan_source import LazyScans, ScanFiles, is_lazy
from neld_jax.data.scans import read_scan, write_scan
from neld_jax.frontend import odometry
from neld_jax.steps import registration
from neld_jax.synthetic.generator import make_sequence

# 10 raw sweeps at 10 Hz round a 10 m loop, 16 beams x 256 columns: small, and moving enough to deskew
SWEEPS = {
    "num_scans": 150,
    "num_beams": 16,
    "num_columns": 256,
    "trajectory_radius_m": 10.0,
    "max_range_m": 30.0,
    "gt_map_points": 0,
}
NUM_SWEEPS, RANGES = 10, (0.5, 30.0)


@pytest.fixture(scope="module")
def sweeps():
    seq = make_sequence(SWEEPS, rate_hz=10.0)
    return dataclasses.replace(
        seq,
        scans=seq.scans[:NUM_SWEEPS],
        point_times=seq.point_times[:NUM_SWEEPS],
        timestamps=seq.timestamps[:NUM_SWEEPS],
        gt_poses=seq.gt_poses[:NUM_SWEEPS],
    )


@pytest.fixture(scope="module")
def on_disk(sweeps, tmp_path_factory):
    """The sweeps in the generic layout as float64 .npy (exactly the points in memory), with their point times and
    no poses: loaded lazily."""
    root = tmp_path_factory.mktemp("sweeps")
    for stamp, scan, times in zip(sweeps.timestamps, sweeps.scans, sweeps.point_times):
        write_scan(root / "scans" / f"{stamp:.9f}.npy", scan)
        (root / "point_times").mkdir(exist_ok=True)
        np.save(root / "point_times" / f"{stamp:.9f}.npy", times)
    write_tum(root / "gt_poses.txt", sweeps.timestamps, sweeps.gt_poses)
    return load_generic(root)


def test_the_lazy_view_reads_the_points_the_eager_reader_reads(tmp_path, sweeps):
    files = []
    for i, ext in enumerate((".pcd", ".ply", ".bin", ".npy")):
        files.append(tmp_path / f"{i:06d}{ext}")
        write_scan(files[-1], sweeps.scans[i])
    lazy = ScanFiles(files)
    assert len(lazy) == 4 and is_lazy(lazy)
    for i, f in enumerate(files):
        np.testing.assert_array_equal(lazy[i], read_scan(f))
    np.testing.assert_array_equal(lazy[-1], read_scan(files[-1]))
    assert [len(s) for s in lazy[1:3]] == [len(read_scan(f)) for f in files[1:3]]
    assert isinstance(lazy[[3, 0]], LazyScans) and len(lazy[[3, 0]][1]) == len(read_scan(files[0]))
    with pytest.raises(IndexError):
        lazy[4]


def test_a_folder_is_loaded_lazily_with_its_point_times(on_disk, sweeps):
    assert is_lazy(on_disk.scans) and is_lazy(on_disk.point_times) and on_disk.num_scans == NUM_SWEEPS
    for i in (0, 7, NUM_SWEEPS - 1):
        np.testing.assert_array_equal(on_disk.scans[i], sweeps.scans[i])
        np.testing.assert_array_equal(on_disk.point_times[i], sweeps.point_times[i])


def test_kiss_icp_over_the_stream_gives_the_poses_and_sweeps_of_the_list(on_disk, sweeps):
    from_disk = odometry.with_kiss_icp_poses(on_disk, *RANGES, progress=False)
    from_memory = odometry.with_kiss_icp_poses(sweeps, *RANGES, progress=False)
    np.testing.assert_allclose(from_disk.poses, from_memory.poses, rtol=0, atol=1e-9)
    assert is_lazy(from_disk.scans) and from_disk.point_times is None
    for i in (0, 5, NUM_SWEEPS - 1):  # deskewed along the trajectory when used, the same points
        np.testing.assert_allclose(from_disk.scans[i], from_memory.scans[i], rtol=0, atol=1e-9)


def test_a_rigid_stream_is_cropped_as_kiss_icp_crops_it(on_disk):
    rigid = dataclasses.replace(on_disk, point_times=None, timestamps=None)
    posed = odometry.with_kiss_icp_poses(rigid, 2.0, 20.0, progress=False)
    distances = np.linalg.norm(posed.scans[3], axis=1)
    assert is_lazy(posed.scans) and distances.min() >= 2.0 and distances.max() <= 20.0
    assert len(posed.scans[3]) < len(on_disk.scans[3])


def _registered(loaded, keyframes):
    settings = registration.RegistrationSettings(max_range_m=RANGES[1])
    return registration.register_every_scan(loaded, keyframes, keyframes.gt_poses, settings)


@pytest.fixture(scope="module")
def posed(on_disk):
    """(every sweep with KISS-ICP's poses, read from disk when used; the keyframes, float32; every other sweep
    registered to the keyframes' map, each read again from disk)."""
    loaded = odometry.with_kiss_icp_poses(on_disk, *RANGES, progress=False)
    keyframes = preprocess(loaded, KeyframeSettings(keyframe_interval_s=0.3, max_range=RANGES[1], voxel_size=0.1))
    return loaded, keyframes, _registered(loaded, keyframes)


def test_every_scan_registered_from_disk_gets_the_poses_it_gets_from_memory(posed):
    loaded, keyframes, from_disk = posed
    held = dataclasses.replace(loaded, scans=[np.array(scan) for scan in loaded.scans])
    assert 2 <= keyframes.num_scans < NUM_SWEEPS and keyframes.scans[0].dtype == np.float32
    assert from_disk.registered.sum() >= (NUM_SWEEPS - keyframes.num_scans) // 2
    np.testing.assert_array_equal(from_disk.poses, _registered(held, keyframes).poses)


def test_float32_keyframes_move_the_registered_poses_by_micrometres(posed):
    """A sensor-frame point within 30 m rounds to float32 by at most 30 m x 2^-24 ~ 2 um; ICP averages thousands of
    such independent roundings, so the poses may move by about that, against registration errors of centimetres
    (tests/test_register_scans.py: 2 cm). 0.1 mm and 0.005 deg leave room for a correspondence that flips."""
    loaded, keyframes, single = posed
    in_float64 = dataclasses.replace(keyframes, scans=[scan.astype(np.float64) for scan in keyframes.scans])
    double = _registered(loaded, in_float64)
    assert single.registered.sum() == double.registered.sum() > 0
    moved = np.linalg.norm(single.poses[:, :3, 3] - double.poses[:, :3, 3], axis=1)
    turned = np.degrees(
        np.arccos(
            np.clip(
                (np.trace(np.linalg.inv(single.poses[:, :3, :3]) @ double.poses[:, :3, :3], axis1=1, axis2=2) - 1) / 2,
                -1,
                1,
            )
        )
    )
    assert moved.max() < 1e-4 and turned.max() < 5e-3
