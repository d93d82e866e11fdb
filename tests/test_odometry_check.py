"""The odometry checked by evidence that does not share its failure (neld_jax.frontend.odometry_check): sampled pairs of
consecutive scans registered globally from no guess agree with KISS-ICP's steps where it kept track; a path that
slid is found and named, run again from the global steps, and refused in one line where it still disagrees."""

import dataclasses
import logging
import re

import numpy as np
import pytest
from conftest import first_sweeps_of_the_loop

from neld_jax.errors import DataError
from neld_jax.frontend import odometry, odometry_check
from neld_jax.judging import metrics

NUM_SWEEPS = 40  # 10 Hz raw sweeps, 0.22 m apart round the 10 m loop, 32 beams, 40 m range
RANGES, VOXEL_M = (0.0, 40.0), 0.4  # KISS-ICP's registration of them: its 0 m, the sensor's 40 m, a hundredth


@pytest.fixture(scope="module")
def loop():
    """(the loop's first 40 raw sweeps with KISS-ICP's poses through the hook (the check passed), the sweeps as they
    came, {pair: global registration} for reuse)."""
    sweeps = first_sweeps_of_the_loop(NUM_SWEEPS)
    posed = odometry.with_kiss_icp_poses(sweeps, 0.5, 40.0, progress=False, odometry_range_m=RANGES[1])
    return posed, sweeps, {}


def _labels(count: int) -> list[str]:
    return [f"sweep {i:06d}" for i in range(count)]


def _shortened(poses: np.ndarray, scale: float) -> np.ndarray:
    """poses [S, 4, 4] with every step's translation scaled by `scale` (an odometry that slid)."""
    steps = np.linalg.inv(poses[:-1]) @ poses[1:]
    steps[:, :3, 3] *= scale
    out = [poses[0]]
    for step in steps:
        out.append(out[-1] @ step)
    return np.stack(out)


def test_the_loops_odometry_and_truth_agree_with_global_registration(loop):
    posed, sweeps, registered = loop
    truth = odometry_check.check_steps(sweeps.scans, sweeps.gt_poses, RANGES, VOXEL_M, registered=registered)
    assert truth.converged.all() and len(truth.pairs) == odometry_check.CHECK_PAIRS
    assert np.all(truth.fitness > 0.9)  # measured 0.96-0.99: misregistered pairs 0.30-0.47
    assert np.all(np.abs(truth.ratios - 1.0) < 0.04), truth.ratios  # 1-9 mm on 0.22 m steps
    assert np.all(truth.odometry_fitness > 0.95 * truth.fitness)
    kiss = odometry_check.check_steps(sweeps.scans, posed.poses, RANGES, VOXEL_M, registered=registered)
    # measured 1.039 in the median, 1.020 along the path: KISS-ICP's own scatter on short steps (0.77-1.18)
    assert kiss.agrees and abs(kiss.median_ratio - 1.0) < 0.07 and abs(kiss.path_ratio - 1.0) < 0.05
    assert not kiss.slid.any()
    true_moves = np.linalg.inv(sweeps.gt_poses[kiss.pairs]) @ sweeps.gt_poses[kiss.pairs + 1]
    true_steps = np.linalg.norm(true_moves[:, :3, 3], axis=1)
    np.testing.assert_allclose(kiss.ratios, kiss.odometry_steps / true_steps, atol=0.05)  # the truth's own ratios


def test_the_evidence_is_logged_in_one_line(loop, caplog):
    posed, sweeps, _ = loop
    rigid = dataclasses.replace(
        sweeps, scans=sweeps.scans[:8], point_times=None, timestamps=sweeps.timestamps[:8], gt_poses=sweeps.gt_poses[:8]
    )
    with caplog.at_level(logging.INFO, logger="neld_jax.frontend.odometry_check"):
        odometry.with_kiss_icp_poses(rigid, 0.5, 40.0, progress=False, odometry_range_m=RANGES[1])
    line = re.search(
        r"KISS-ICP's steps against global registration from no guess: 7 pairs of consecutive scans "
        r"checked, 7 converged \(fitness >= 0\.6\), 7 moving; KISS-ICP's step over the global step "
        r"(\d\.\d+) in the median",
        caplog.text,
    )
    # KISS-ICP's first steps from rest are short (0.72-0.90 of the true ones, measured the same within 0.01 here):
    # 0.885 in the median, within the tolerance
    assert line and 0.8 < float(line.group(1)) < odometry_check.STEP_TOLERANCE, caplog.text


def test_a_path_that_slid_is_found_and_its_scans_named(loop):
    # every 4th sweep (0.9 m apart) with KISS-ICP's steps shortened to 0.4: 0.5 m short, more than a voxel, so the
    # scans fit the shortened steps worse than the global ones and say that the odometry slid
    posed, sweeps, _ = loop
    scans, slid = sweeps.scans[::4], _shortened(posed.poses[::4], 0.4)
    check = odometry_check.check_steps(scans, slid, RANGES, VOXEL_M)
    assert check.backed_by_the_scans and not check.agrees and 0.35 < check.median_ratio < 0.45, check.median_ratio
    assert re.match(r"sweep \d{6} to sweep \d{6}: 0\.\d\d m against 0\.\d\d m", check.furthest(_labels(10)))
    # the same steps only 0.9 x as long lie within the tolerance; 0.6 x as long on the 0.2 m steps between
    # consecutive sweeps are 0.09 m short, well within a voxel: the scans fit them as well, and they are kept
    assert odometry_check.check_steps(scans, _shortened(posed.poses[::4], 0.9), RANGES, VOXEL_M).within_tolerance
    short = odometry_check.check_steps(sweeps.scans, _shortened(posed.poses, 0.6), RANGES, VOXEL_M, registered=loop[2])
    assert not short.within_tolerance and not short.backed_by_the_scans and short.agrees
    assert "the scans fit KISS-ICP's steps about as well as the global ones: kept" in short.summary()
    # run again, it slides again: one line naming the recording and the scans
    with pytest.raises(
        DataError,
        match=r"^the loop: KISS-ICP's steps are [34]\d% of what global registration "
        r"\(FPFH features and RANSAC, then ICP, from no guess\) finds between "
        r"consecutive scans in the median and its path \d+% of theirs over 9 pairs "
        r"\(sweep 0000\d\d to sweep 0000\d\d: 0\.\d\d m against 0\.\d\d m; ",
    ) as error:
        odometry_check.checked_odometry(scans, lambda guesses, seen: (slid,), _labels(10), RANGES, VOXEL_M, "the loop")
    assert "\n" not in str(error.value)


def test_one_step_far_off_is_found_where_the_median_is_not(loop):
    # the first step 5x as long (1.1 m, 2.2 voxels too far), the rest KISS-ICP's: its scans fit worse under it
    posed, sweeps, registered = loop
    jumped = posed.poses.copy()
    jumped[1:] = _shortened(posed.poses[:2], 5.0)[1] @ np.linalg.inv(posed.poses[1]) @ posed.poses[1:]
    check = odometry_check.check_steps(sweeps.scans, jumped, RANGES, VOXEL_M, registered=registered)
    assert abs(check.median_ratio - 1.0) < 0.1  # the other 19 steps are KISS-ICP's
    assert check.slid.tolist() == [True] + [False] * (len(check.pairs) - 1) and not check.agrees
    assert check.odometry_fitness[0] < 0.9 * check.fitness[0]


def test_kiss_icp_that_slid_from_rest_is_run_again_from_the_global_steps(caplog):
    # 12 sweeps 1.7 m apart (the loop in 40 sweeps, taken as rigid scans): KISS-ICP starts from no motion and its
    # first step stops at a third of the way (measured 0.50 m against 1.60 m): the path is 15 % short, 1.15 m ATE
    fast = dataclasses.replace(first_sweeps_of_the_loop(12, 40), point_times=None)
    alone, _, _ = odometry.kiss_icp_odometry(fast.scans, None, _labels(12), RANGES, keep_sweeps=False)
    with caplog.at_level(logging.INFO, logger="neld_jax.frontend.odometry_check"):
        posed = odometry.with_kiss_icp_poses(fast, 0.5, 40.0, progress=False, odometry_range_m=RANGES[1])
    assert re.search(
        r"disagree with global registration .* 1 single steps slid .*\); scan 0 \(t=0\.000000\) to "
        r"scan 1 \(t=0\.100000\): 0\.\d\d m against 1\.\d\d m",
        caplog.text,
    ), caplog.text
    assert "KISS-ICP run again from the global steps; its steps against global registration: 11 pairs" in caplog.text
    errors = [metrics.ate(poses, fast.gt_poses)["translation_rmse_m"] for poses in (alone, posed.poses)]
    assert errors[0] > 0.8 and errors[1] < 0.5 * errors[0], errors  # measured 1.15 and 0.29 m


def test_pairs_that_did_not_converge_carry_no_evidence(loop):
    _, sweeps, _ = loop
    elsewhere = first_sweeps_of_the_loop(6, seed=7)  # another courtyard
    scans = [sweeps.scans[4], elsewhere.scans[5], sweeps.scans[5], sweeps.scans[6]]
    check = odometry_check.check_steps(scans, sweeps.gt_poses[3:7], RANGES, VOXEL_M)
    assert check.converged.tolist() == [False, False, True], check.fitness  # measured 0.33 against 0.9+
    assert check.median_ratio is None and check.agrees and "too few to decide" in check.summary()


def test_the_sample_spans_the_recording_and_the_second_lies_between():
    first, between = odometry_check.sampled_pairs(101), odometry_check.sampled_pairs(101, between=True)
    assert len(first) == odometry_check.CHECK_PAIRS and first[0] == 0 and first[-1] == 99
    assert not set(first[:-1]) & set(between) and np.all(np.diff(between) > 0)
    assert (
        odometry_check.sampled_pairs(12).tolist()
        == list(range(11))
        == odometry_check.sampled_pairs(12, between=True).tolist()
    )  # a short recording: every pair, both times
    assert len(odometry_check.sampled_pairs(1)) == 0
