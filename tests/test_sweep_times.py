"""Per-point times from azimuths (neld_jax.data.sweep_times): on the synthetic generator's raw sweeps, whose true
times are known, the derived times are the true ones; the Velodyne convention is KISS-ICP's; a generic folder of
sweeps without times gets them (one log line) and KISS-ICP's deskewed odometry from them matches the one from the
true times; keyframes, partial turns and sweeps with their own times are left as they are."""

import dataclasses
import logging
import shutil

import numpy as np
import pytest
from conftest import first_sweeps_of_the_loop, make_tiny_config

from neld_jax import metrics
from neld_jax.data import sweep_times
from neld_jax.data.formats import load_sequence
from neld_jax.data.generic import POINT_TIMES_FOLDER
from neld_jax.data.sweep_times import VELODYNE, SweepConvention, azimuth_times, turn_fractions, with_azimuth_times
from neld_jax.data.synthetic import write_generic

# 20 raw sweeps at 10 Hz, 2.1 m/s round a 10 m loop (0.2 m a sweep), 32 beams x 512 columns, 40 m range
SWEEPS = {"num_scans": 300, "trajectory_radius_m": 10.0, "max_range_m": 40.0, "gt_map_points": 0}
NUM_SWEEPS, RATE_HZ = 20, 10.0
SYNTHETIC_SENSOR = SweepConvention(start_azimuth_rad=0.0, clockwise=False)  # column c at azimuth 2 pi c / C
MIRROR_X = np.diag([-1.0, 1.0, 1.0])  # azimuth a -> pi - a: the synthetic head seen as a Velodyne's
# Derived times are exact but for rounding: a point's direction is its column's (range noise lies along the ray), so
# its azimuth is the column's to ~1e-15 rad, ~1e-17 s of a 0.1 s turn; 1 ns leaves room for any platform's atan2.
TIME_TOLERANCE_S = 1e-9


@pytest.fixture(scope="module")
def sweeps():
    """The first 20 sweeps of make_sequence(SWEEPS, rate_hz=RATE_HZ), the 300-sweep loop."""
    return first_sweeps_of_the_loop(NUM_SWEEPS, SWEEPS["num_scans"], rate_hz=RATE_HZ)


@pytest.fixture(scope="module")
def velodyne_sweeps(sweeps):
    """The same sweeps in a mirrored world: a head turning clockwise from behind, as a Velodyne's."""
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirrored = mirror @ sweeps.gt_poses @ mirror
    return dataclasses.replace(sweeps, scans=[scan @ MIRROR_X for scan in sweeps.scans], gt_poses=mirrored)


def _data(root):
    data = make_tiny_config().data
    data.format, data.root, data.max_range_m = "generic", str(root), 40.0
    return data


def test_derived_times_are_the_true_times_of_synthetic_sweeps(sweeps, velodyne_sweeps):
    assert sweep_times.sweep_period(sweeps.timestamps) == pytest.approx(1.0 / RATE_HZ)
    for scan, mirrored, true in zip(sweeps.scans, velodyne_sweeps.scans, sweeps.point_times):
        assert np.abs(azimuth_times(scan, 0.1, SYNTHETIC_SENSOR) - true).max() < TIME_TOLERANCE_S
        assert np.abs(azimuth_times(mirrored, 0.1, VELODYNE) - true).max() < TIME_TOLERANCE_S
    wrong = azimuth_times(sweeps.scans[0], 0.1, VELODYNE)
    assert np.abs(wrong - sweeps.point_times[0]).mean() > 0.02  # the convention matters


def test_the_velodyne_convention_is_kiss_icps_for_kitti_raw():
    from kiss_icp.datasets.kitti_raw import KITTIRawDataset

    points = np.random.default_rng(0).normal(size=(500, 3))
    np.testing.assert_allclose(turn_fractions(points, VELODYNE), KITTIRawDataset.get_timestamps(points), atol=1e-12)
    behind, left, front, right = turn_fractions(np.array([[-1.0, 0, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0]]), VELODYNE)
    assert (behind, left, front, right) == (0.0, 0.25, 0.5, 0.75)
    assert "behind the sensor, turning clockwise" in VELODYNE.describe()


def test_a_folder_of_sweeps_without_times_is_deskewed_by_derived_times(velodyne_sweeps, tmp_path, caplog):
    with_times, without = tmp_path / "with_times", tmp_path / "without"
    write_generic(velodyne_sweeps, with_times)  # scans/<stamp>.pcd + point_times/<stamp>.npy, gt_poses.txt
    shutil.copytree(with_times, without)
    shutil.rmtree(without / POINT_TIMES_FOLDER)
    caplog.set_level(logging.INFO)
    derived = load_sequence(_data(without))
    lines = [r.getMessage() for r in caplog.records if r.name == sweep_times.__name__]
    assert len(lines) == 1 and "derived from its azimuth, a sweep of 0.100 s (from the stamps)" in lines[0]
    true = load_sequence(_data(with_times))
    assert derived.poses_from == true.poses_from == "kiss_icp"
    # the times agree to TIME_TOLERANCE_S; the odometry's two passes use them as they are (measured: 4 mm apart)
    np.testing.assert_allclose(derived.poses, true.poses, atol=0.01)
    error_derived = metrics.ate(derived.poses, derived.gt_poses)["translation_rmse_m"]
    assert error_derived < 0.1 and error_derived == pytest.approx(
        metrics.ate(true.poses, true.gt_poses)["translation_rmse_m"], abs=3e-3)
    for a, b in zip(derived.scans[::5], true.scans[::5]):
        np.testing.assert_allclose(a, b, atol=0.01)  # the same points deskewed the same way (within 3 mm)


def test_keyframes_partial_turns_and_timed_sweeps_are_left_as_they_are(sweeps, caplog):
    caplog.set_level(logging.INFO)
    rigid = dataclasses.replace(sweeps, point_times=None)
    keyframes = dataclasses.replace(rigid, timestamps=3.0 * np.arange(NUM_SWEEPS))
    assert with_azimuth_times(keyframes).point_times is None
    assert "3.00 s apart, not consecutive sweeps" in caplog.text
    front_only = dataclasses.replace(rigid, scans=[scan[scan[:, 0] > 0] for scan in rigid.scans])
    assert with_azimuth_times(front_only).point_times is None
    assert "leave 181 deg of azimuth empty" in caplog.text  # 90 to 270 deg, and the column beside
    assert with_azimuth_times(sweeps).point_times is sweeps.point_times
    unstamped = with_azimuth_times(dataclasses.replace(rigid, timestamps=None), SYNTHETIC_SENSOR)
    assert "a sweep of 0.100 s (assumed: no stamps)" in caplog.text
    assert np.abs(unstamped.point_times[3] - sweeps.point_times[3]).max() < TIME_TOLERANCE_S
