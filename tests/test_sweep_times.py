"""Raw or deskewed, and per-point times from azimuths (neld_jax.frontend.sweep_times): scans without times are measured
(pairs registered rigidly and deskewed under each convention): the synthetic scene's rigid scans, and a handheld
walk's at 2 Hz without stamps, are deskewed already; its raw sweeps are raw, with the convention they were cast with
(mirrored or not); data.deskew overrides. On the raw sweeps, whose true times are known, the derived times are the
true ones; the Velodyne convention is KISS-ICP's; a generic folder of sweeps without times gets them (one log line)
and KISS-ICP's deskewed odometry from them matches the one from the true times, with stamps or without; partial
turns and sweeps with their own times are left as they are."""

import dataclasses
import logging
import re
import shutil

import numpy as np
import pytest
from conftest import first_sweeps_of_the_loop, make_tiny_config

from neld_jax import config as config_module
from neld_jax.data.generic import POINT_TIMES_FOLDER
from neld_jax.errors import ConfigError
from neld_jax.frontend import odometry, sweep_times
from neld_jax.frontend.sweep_times import (
    CONVENTIONS,
    VELODYNE,
    SweepConvention,
    azimuth_times,
    measured_deskew,
    turn_fractions,
    with_azimuth_times,
)
from neld_jax.judging import metrics
from neld_jax.steps.inputs import load_sequence
from neld_jax.synthetic.generator import make_sequence, write_generic

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


@pytest.fixture(scope="module")
def rigid_scans(sweeps):
    """The same scene scanned rigidly (deskewed, as a front-end writes its scans) at the sweeps' stamps and poses."""
    from neld_jax.synthetic.generator import (
        FOV_DEG,
        cast_scan,
        make_scene,
        spinning_lidar_directions,
        synthetic_defaults,
    )

    cfg = synthetic_defaults()
    scene, _ = make_scene(0, cfg.scene_size_m, path_radius_m=SWEEPS["trajectory_radius_m"])
    directions = spinning_lidar_directions(cfg.num_beams, FOV_DEG[1], FOV_DEG[0], cfg.num_columns)
    rng = np.random.default_rng(2)
    scans = [
        cast_scan(scene, pose, directions, SWEEPS["max_range_m"], cfg.range_noise_m, rng) for pose in sweeps.gt_poses
    ]
    return dataclasses.replace(sweeps, scans=scans, point_times=None)


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
    assert "are raw sweeps starting behind the sensor, turning clockwise seen from above (measured: " in lines[0]
    true = load_sequence(_data(with_times))
    assert derived.poses_from == true.poses_from == "kiss_icp"
    # the times agree to TIME_TOLERANCE_S; the odometry's two passes use them as they are (measured: 4 mm apart)
    np.testing.assert_allclose(derived.poses, true.poses, atol=0.01)
    error_derived = metrics.ate(derived.poses, derived.gt_poses)["translation_rmse_m"]
    assert error_derived < 0.1 and error_derived == pytest.approx(
        metrics.ate(true.poses, true.gt_poses)["translation_rmse_m"], abs=3e-3
    )
    for a, b in zip(derived.scans[::5], true.scans[::5]):
        np.testing.assert_allclose(a, b, atol=0.01)  # the same points deskewed the same way (within 3 mm)


def _sweep_times_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == sweep_times.__name__]


def test_rigid_scans_are_measured_deskewed_and_registered_as_they_are(rigid_scans, caplog):
    # Deskewing them under any convention bends them by the motion between two scans (0.2 m and 1.2 deg): every
    # hypothesis registers worse than rigid. Measured: x1.05-1.17 in the median over 5 pairs, x1.10-1.25 at most.
    evidence = measured_deskew(rigid_scans.scans, SWEEPS["max_range_m"])
    assert len(evidence.pairs) == 5 and evidence.winner() is None
    assert all(np.median(ratio) > 1.0 for ratio in evidence.ratios().values()), evidence.describe()
    caplog.set_level(logging.INFO)
    assert with_azimuth_times(rigid_scans).point_times is None
    lines = _sweep_times_lines(caplog)
    assert len(lines) == 1 and "are deskewed already: registered as they are (measured: RMS point-to-plane" in lines[0]


def test_a_handheld_walk_at_2_hz_without_stamps_is_deskewed_already(caplog):
    # A LiDAR-inertial odometry's deskewed scans: 2 Hz, 0.7 m and 40-50 degrees from scan to scan after 8 scans
    # looking ahead, no stamps. Assumed to be raw 10 Hz sweeps they would be bent by a whole turn's motion.
    walk = make_sequence({"route": "handheld", "num_scans": 16, "max_range_m": 40.0, "gt_map_points": 0})
    walk = dataclasses.replace(walk, timestamps=None)
    caplog.set_level(logging.INFO)
    assert with_azimuth_times(walk).point_times is None
    lines = _sweep_times_lines(caplog)
    assert len(lines) == 1 and "deskewed already" in lines[0]
    medians = [float(m) for m in re.findall(r"\(x(\d\.\d\d), x", lines[0])]
    assert len(medians) == 4 and min(medians) > 1.15, lines[0]  # measured x1.31-1.43


@pytest.mark.parametrize("mirrored, name", [(False, "front_anticlockwise"), (True, "behind_clockwise")])
def test_raw_sweeps_are_measured_raw_with_the_convention_they_were_cast_with(sweeps, velodyne_sweeps, mirrored, name):
    raw = velodyne_sweeps if mirrored else sweeps
    assert CONVENTIONS[name] == (VELODYNE if mirrored else SYNTHETIC_SENSOR)
    evidence = measured_deskew(raw.scans, SWEEPS["max_range_m"])
    ratios = evidence.ratios()
    assert evidence.winner() == name, evidence.describe()  # measured x0.86-0.88 in the median, x1.00-1.03 at most
    assert all(np.median(ratios[other]) > 1.0 for other in ratios if other != name)  # the other three bend them
    timeless = dataclasses.replace(raw, point_times=None)
    derived = with_azimuth_times(timeless, range_m=SWEEPS["max_range_m"])
    for i in (0, 7, NUM_SWEEPS - 1):
        assert np.abs(derived.point_times[i] - raw.point_times[i]).max() < TIME_TOLERANCE_S


def test_data_deskew_overrides_the_measurement(sweeps, rigid_scans, caplog):
    caplog.set_level(logging.INFO)
    timeless = dataclasses.replace(sweeps, point_times=None)
    assert with_azimuth_times(timeless, "deskewed").point_times is None
    assert "deskewed already: registered as they are (data.deskew=deskewed" in caplog.text
    given = with_azimuth_times(rigid_scans, "raw_front_anticlockwise")  # the user's word, whatever the data say
    expected = azimuth_times(rigid_scans.scans[3], 0.1, SYNTHETIC_SENSOR)
    assert np.abs(given.point_times[3] - expected).max() < TIME_TOLERANCE_S
    assert "anticlockwise seen from above (data.deskew=raw_front_anticlockwise): each point" in caplog.text
    forced = with_azimuth_times(rigid_scans, "raw")  # raw: the best convention even where rigid registers better
    assert forced.point_times is not None and "data.deskew=raw, the convention measured" in caplog.text
    with pytest.raises(ConfigError, match=r"^data\.deskew: unknown choice 'sideways' \(expected one of auto"):
        with_azimuth_times(timeless, "sideways")
    c = config_module.defaults()
    assert c.data.deskew == "auto"


def test_raw_sweeps_without_stamps_get_two_passes_at_an_assumed_period(velodyne_sweeps, caplog):
    # The period only scales time: the sweeps put 0.1 s apart give the poses their stamps give.
    caplog.set_level(logging.INFO)
    unstamped = dataclasses.replace(velodyne_sweeps, point_times=None, timestamps=None)
    derived = with_azimuth_times(unstamped, range_m=SWEEPS["max_range_m"])
    assert "a sweep of 0.100 s (assumed: no stamps)" in caplog.text
    ranges = dict(progress=False, odometry_range_m=SWEEPS["max_range_m"])
    posed = odometry.with_kiss_icp_poses(derived, 0.5, 40.0, unstamped_period_s=0.1, **ranges)
    assert "put 0.100 s apart for the odometry's two passes (assumed" in caplog.text
    stamped = odometry.with_kiss_icp_poses(velodyne_sweeps, 0.5, 40.0, **ranges)
    np.testing.assert_allclose(posed.poses, stamped.poses, atol=0.01)
    assert metrics.ate(posed.poses, velodyne_sweeps.gt_poses)["translation_rmse_m"] < 0.1


def test_partial_turns_and_timed_sweeps_are_left_as_they_are(sweeps, caplog):
    caplog.set_level(logging.INFO)
    rigid = dataclasses.replace(sweeps, point_times=None)
    front_only = dataclasses.replace(rigid, scans=[scan[scan[:, 0] > 0] for scan in rigid.scans])
    assert with_azimuth_times(front_only).point_times is None
    assert "leave 181 deg of azimuth empty" in caplog.text  # 90 to 270 deg, and the column beside
    assert with_azimuth_times(sweeps).point_times is sweeps.point_times
    assert sweep_times.sweep_period(None) == sweep_times.DEFAULT_PERIOD_S
    assert sweep_times.sweep_period(0.5 * np.arange(4)) == 0.5  # a raw sweep's period: the stamps' step
