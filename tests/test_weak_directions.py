"""Directions the geometry does not fix stay with the odometry: on a straight street between parallel walls a
registration keeps its guess's motion along the street and fixes the rest (baseline.icp.held_along_weak_directions);
in an open scene nothing is held. The baseline's poses keep the input's distance travelled unless their own give
a crisper map (baseline.distances)."""

import dataclasses

import numpy as np
import pytest

from neld_jax.baseline import BaselineSettings, multiscale_icp, prepare_clouds
from neld_jax.baseline.distances import keep_input_distances
from neld_jax.baseline.icp import TargetIndex, direction_shares
from neld_jax.geometry import cumulative_path
from neld_jax.synthetic.lidar import cast_scan, spinning_lidar_directions
from neld_jax.synthetic.scene import make_scene, raycasting_scene, street_meshes
from neld_jax.trajectory import window_scales, with_distances_of

HELD = BaselineSettings(voxel_size_m=0.2)
FREE = dataclasses.replace(HELD, min_direction_share=0.0)


def sensor_pose(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [x, y, 1.8]
    return pose


def scans_along(scene, poses) -> list[np.ndarray]:
    directions = spinning_lidar_directions(32, 15.0, -15.0, 512)
    rng = np.random.default_rng(0)
    return [cast_scan(scene, pose, directions, 40.0, 0.01, rng) for pose in poses]


@pytest.fixture(scope="module")
def street():
    poses = [sensor_pose(2.0 * k - 6.0) for k in range(6)]
    return scans_along(raycasting_scene(street_meshes()), poses), np.stack(poses)


@pytest.fixture(scope="module")
def courtyard():
    poses = [sensor_pose(-3.0 + 1.5 * k, 15.0, 0.1 * k) for k in range(4)]
    return scans_along(make_scene(0)[0], poses), np.stack(poses)


def shares_at(source, target, transform):
    points = np.asarray(source.points) @ transform[:3, :3].T + transform[:3, 3]
    nearest, _ = TargetIndex(target, 0.25).nearest(points, 0.25)
    paired = nearest >= 0
    return direction_shares(points[paired], np.asarray(target.normals)[nearest[paired]])


def test_direction_shares_find_the_street_and_not_the_courtyard(street, courtyard):
    for (scans, poses), weakest in ((street, "along"), (courtyard, None)):
        clouds = prepare_clouds(scans[:2], HELD)
        shares, vectors, _, _ = shares_at(clouds[1], clouds[0], np.linalg.inv(poses[0]) @ poses[1])
        if weakest == "along":
            assert shares[0] < HELD.min_direction_share
            assert abs(vectors[3, 0]) > 0.95  # the weakest direction: translation along x, the street
            assert shares[1] > HELD.min_direction_share
        else:
            assert shares[0] > 2 * HELD.min_direction_share


def test_registration_on_the_street_keeps_the_guess_along_it(street):
    scans, poses = street
    clouds = prepare_clouds(scans[:2], HELD)
    truth = np.linalg.inv(poses[0]) @ poses[1]
    guess = truth.copy()
    guess[:3, 3] += [0.3, 0.08, 0.0]  # an odometry 30 cm off along the street, 8 cm across it
    held, _ = multiscale_icp(clouds[1], clouds[0], guess, HELD)
    error = (np.linalg.inv(truth) @ held)[:3, 3]
    assert abs(error[0] - 0.3) < 0.01  # along the street: the guess's
    assert abs(error[1]) < 0.01 and abs(error[2]) < 0.01  # across and up: fixed by the walls and the ground


def test_nothing_is_held_in_an_open_scene(courtyard):
    scans, poses = courtyard
    clouds = prepare_clouds(scans[:2], HELD)
    guess = np.linalg.inv(poses[0]) @ poses[1]
    guess[:3, 3] += [0.2, -0.1, 0.0]
    held, _ = multiscale_icp(clouds[1], clouds[0], guess, HELD)
    free, _ = multiscale_icp(clouds[1], clouds[0], guess, FREE)
    np.testing.assert_array_equal(held, free)
    assert np.linalg.norm((np.linalg.inv(np.linalg.inv(poses[0]) @ poses[1]) @ held)[:3, 3]) < 0.02


def test_distances_of_the_reference_keep_the_directions():
    reference = np.tile(np.eye(4), (21, 1, 1))
    reference[:, 0, 3] = np.linspace(0.0, 40.0, 21)
    bent = reference.copy()
    bent[:, :3, 3] *= 0.99
    bent[10:, 1, 3] += 0.5  # a shape of its own: a step sideways
    np.testing.assert_allclose(window_scales(reference, reference, 10.0), 1.0)
    moved = with_distances_of(bent, reference, 10.0)
    assert cumulative_path(moved)[-1] == pytest.approx(cumulative_path(reference)[-1], rel=0.02)
    steps, moved_steps = np.diff(bent[:, :3, 3], axis=0), np.diff(moved[:, :3, 3], axis=0)
    cosines = (
        np.einsum("ij,ij->i", steps, moved_steps) / np.linalg.norm(steps, axis=1) / np.linalg.norm(moved_steps, axis=1)
    )
    np.testing.assert_allclose(cosines, 1.0)  # the same directions of travel
    np.testing.assert_array_equal(moved[:, :3, :3], bent[:, :3, :3])


def test_the_input_distances_unless_the_own_are_crisper(street, courtyard):
    # On the street no surface faces along it: a path 3 % short is as crisp as the true one, so the input's
    # distances (the truth here) are kept.
    scans, truth = street
    short = truth.copy()
    short[:, :3, 3] = truth[0, :3, 3] + 0.97 * (truth[:, :3, 3] - truth[0, :3, 3])
    settings = dataclasses.replace(HELD, distance_window_m=6.0, crispness_queries=3000)
    kept, record = keep_input_distances(scans, short, truth, settings)
    assert record["kept"] == "input"
    np.testing.assert_allclose(kept[:, :3, 3], truth[:, :3, 3], atol=1e-9)
    # In the courtyard the walls across the path see a 3 % longer input: the true distances are crisper and stay.
    scans, truth = courtyard
    longer = truth.copy()
    longer[:, :3, 3] = truth[0, :3, 3] + 1.03 * (truth[:, :3, 3] - truth[0, :3, 3])
    kept, record = keep_input_distances(scans, truth, longer, settings)
    assert record["kept"] == "own" and record["margin"] < 0
    np.testing.assert_array_equal(kept, truth)
    assert keep_input_distances(scans, truth, truth, settings) == (truth, None)  # nothing to compare
