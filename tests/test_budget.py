"""The run's one clock (neld_jax.training.budget.TimeBudget): training's share and floor, the baseline's deadline, the
map's seconds, the crispness draws' deadline, no limit at 0 minutes, a resumed run's seconds; and the plan that sizes
every step before it starts (neld_jax.training.stage_plan)."""

import time

import numpy as np
import pytest

from neld_jax.config import defaults, with_budget
from neld_jax.training.budget import (
    JUDGING_S,
    MAX_REGISTRATION_SHARE,
    REGISTRATION_S_PER_SCAN,
    WRITING_S,
    TimeBudget,
)


def _at(budget: TimeBudget, elapsed: float, monkeypatch) -> TimeBudget:
    """The budget as seen `elapsed` seconds after its start."""
    import neld_jax.training.budget

    monkeypatch.setattr(neld_jax.training.budget.time, "perf_counter", lambda: budget.started + elapsed)
    return budget


def test_the_cpu_budget_trains_until_its_share_then_renders_and_judges(monkeypatch):
    config = with_budget(defaults(), "cpu")
    b = TimeBudget(60.0 * config.max_minutes, config.mapping.max_seconds, 100.0)
    assert b.training_share_s == 60.0 * 9.5 - 60.0 - JUDGING_S == 465.0
    assert _at(b, 0.0, monkeypatch).training_seconds() == 465.0
    assert _at(b, 200.0, monkeypatch).training_seconds() == 265.0  # a 200 s baseline counts
    assert _at(b, 400.0, monkeypatch).training_seconds() == 0.25 * 465.0  # but training gets at least a quarter
    assert b.baseline_deadline() == 100.0 + 0.75 * 465.0  # where only training's floor is left
    assert _at(b, 460.0, monkeypatch).render_seconds() == 60.0  # training ended on time: the map's whole share
    assert _at(b, 485.0, monkeypatch).render_seconds() == 40.0  # 20 s late: given back from the map
    assert _at(b, 545.0, monkeypatch).render_seconds() == 15.0  # at least a quarter of it
    assert b.judging_deadline() == pytest.approx(100.0 + 570.0 - WRITING_S)  # the last files get their seconds


def test_zero_minutes_is_no_limit(monkeypatch):
    b = TimeBudget(0.0, 60.0, 5.0)
    assert not b.limited and b.baseline_deadline() is None and b.judging_deadline() is None
    assert _at(b, 1e6, monkeypatch).training_seconds() == 0.0
    assert b.render_seconds() == 60.0  # the map's own limit stays
    assert TimeBudget(0.0, 0.0, 5.0).render_seconds() == 0.0
    assert TimeBudget(600.0, 0.0, 5.0).render_seconds() == 0.0  # a map without a limit stays without one
    assert "no time limit" in b.describe() and "training until" in TimeBudget(570.0, 60.0, 0.0).describe()


def test_registering_every_other_scan_is_kept_back_from_training(monkeypatch):
    from neld_jax.training.budget import MAX_REGISTRATION_SHARE, REGISTRATION_S_PER_SCAN

    b = TimeBudget(570.0, 60.0, 100.0).reserving_registration(100)
    assert b.registration_s == 100 * REGISTRATION_S_PER_SCAN
    assert b.training_share_s == 570.0 - 60.0 - b.registration_s - JUDGING_S
    assert _at(b, 0.0, monkeypatch).registration_deadline() == 100.0 + 570.0 - JUDGING_S  # up to the judging
    late = _at(b, 600.0, monkeypatch).registration_deadline()  # a run already past it: a quarter of the reserve
    assert late == pytest.approx(100.0 + 600.0 + 0.25 * b.registration_s)
    # Thousands of sweeps take at most their share of the budget; no limit reserves nothing.
    assert TimeBudget(570.0, 60.0, 0.0).reserving_registration(10_000).registration_s == MAX_REGISTRATION_SHARE * 570.0
    assert TimeBudget(0.0, 60.0, 0.0).reserving_registration(100).registration_s == 0.0
    assert TimeBudget(0.0, 60.0, 0.0).registration_deadline() is None


def test_a_resumed_runs_seconds_count_its_earlier_processes_and_leave_its_limits_alone(monkeypatch):
    fresh, resumed = TimeBudget(570.0, 60.0, 100.0), TimeBudget(570.0, 60.0, 100.0, earlier_s=300.0)
    assert _at(resumed, 20.0, monkeypatch).run_seconds() == pytest.approx(320.0)
    assert _at(fresh, 20.0, monkeypatch).run_seconds() == pytest.approx(20.0)
    assert resumed.training_seconds() == fresh.training_seconds() and resumed.render_seconds() == fresh.render_seconds()


def test_a_small_recording_fits_and_every_stage_gets_its_floor():
    from neld_jax.training.stage_plan import STAGES, Recording, Work, plan_stages

    work = Work(baseline=True, map_rounds=2, render_s=60.0)
    plan = plan_stages(Recording(num_scans=24, num_keyframes=24, points_per_scan=16_000, loaded_s=5.0), 570.0, work)
    assert plan.fits and plan.warning() is None and set(plan.seconds) == set(STAGES)
    assert all(plan.seconds[stage] >= plan.needed[stage] for stage in STAGES)  # every stage at least its floor
    assert plan.needed["training"] == work.min_steps * plan.rates.step_s and plan.needed["load"] == 5.0
    assert sum(plan.seconds.values()) == pytest.approx(570.0)  # training gets what is left
    assert plan.seconds["baseline"] > plan.needed["baseline"]  # room for every refinement round
    assert plan.record()["fits"] and plan.record()["planned_s"]["map"] == 60.0


def test_a_recording_too_long_for_its_budget_is_told_up_front_with_the_budget_it_needs(caplog):
    import logging
    import types

    from neld_jax.training import stage_plan

    # 1,000 raw 64 x 1024 sweeps on the cpu budget: the odometry alone took 438 s of the 570 (benchmarks/RESULTS.md)
    plan = stage_plan.plan_stages(
        stage_plan.Recording(1000, 34, 40_000, odometry=True), 570.0, stage_plan.Work(baseline=True, render_s=60.0)
    )
    assert not plan.fits and plan.seconds == {} and plan.needed_minutes > 9.5
    # forecast from the odometry's rate
    assert plan.needed["load"] == pytest.approx(1000 * stage_plan.ODOMETRY_S_PER_SWEEP * 40_000 / 65_536)
    assert stage_plan.plan_stages(plan.recording, 60.0 * plan.needed_minutes, plan.work).fits  # what it says suffices
    # The run logs it once, after loading: the plan and one warning that names the max_minutes it needs.
    scans = types.SimpleNamespace(num_scans=1000, poses_from="kiss_icp")
    keyframes = types.SimpleNamespace(num_scans=34, scans=[np.zeros((40_000, 3))] * 34)
    settings = stage_plan.PlanSettings(stage_plan.Work(baseline=True), "cpu", "cpu")
    with caplog.at_level(logging.INFO, logger=stage_plan.__name__):
        budget = stage_plan.planned(settings, scans, keyframes, TimeBudget(570.0, 60.0, time.perf_counter() - 438.0))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "too long for max_minutes=9.5" in warnings[0]
    assert f"set max_minutes={budget.plan.needed_minutes:g} or more" in warnings[0]
    assert any("odometry 0.44 s a sweep (measured)" in r.getMessage() for r in caplog.records)
    fixed = min(REGISTRATION_S_PER_SCAN * (1000 - 34), MAX_REGISTRATION_SHARE * 570.0)
    assert budget.judging_s == JUDGING_S and budget.registration_s == fixed  # the fixed reserves, as before


def test_a_recording_that_fits_hands_the_clock_its_planned_reserves():
    import types

    from neld_jax.training import stage_plan

    scans = types.SimpleNamespace(num_scans=5000, poses_from="")
    keyframes = types.SimpleNamespace(num_scans=100, scans=[np.zeros((10_000, 3))] * 100)
    settings = stage_plan.PlanSettings(stage_plan.Work(), "cpu", "cpu")
    budget = stage_plan.planned(settings, scans, keyframes, TimeBudget(1200.0, 60.0, time.perf_counter()))
    # every scan's registration, past the fixed reserve's cap (MAX_REGISTRATION_SHARE of the budget)
    assert budget.plan.fits and budget.registration_s == 4900 * REGISTRATION_S_PER_SCAN > MAX_REGISTRATION_SHARE * 1200
    assert budget.judging_s == budget.plan.seconds["judging"] >= JUDGING_S


def test_an_unlimited_budget_plans_no_limits(caplog):
    import logging
    import types

    from neld_jax.training import stage_plan

    plan = stage_plan.plan_stages(stage_plan.Recording(1000, 34, 40_000, odometry=True), 0.0)
    assert plan.fits and plan.seconds == {} and plan.warning() is None and plan.needed_s > 0
    scans = types.SimpleNamespace(num_scans=1000, poses_from="kiss_icp")
    keyframes = types.SimpleNamespace(num_scans=34, scans=[np.zeros((40_000, 3))] * 34)
    with caplog.at_level(logging.INFO, logger=stage_plan.__name__):
        budget = stage_plan.planned(
            stage_plan.PlanSettings(stage_plan.Work(), "paper", "cpu"),
            scans,
            keyframes,
            TimeBudget(0.0, 0.0, time.perf_counter()),
        )
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert budget.registration_s == 0.0 and budget.judging_s == JUDGING_S and budget.baseline_deadline() is None
    assert any("with no time limit" in r.getMessage() for r in caplog.records)


def test_a_front_end_too_long_for_the_budget_is_told_before_it_runs(caplog):
    import logging

    from neld_jax.training import stage_plan

    sweep = stage_plan.ODOMETRY_POINTS
    with caplog.at_level(logging.INFO, logger=stage_plan.__name__):
        forecast = stage_plan.front_end_forecast(1000, sweep, 570.0, "/data/drive: ")
    assert forecast == pytest.approx(1000 * stage_plan.ODOMETRY_S_PER_SWEEP)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    # 270 s of 570 is under half: 2,000 sweeps are not
    assert warnings == []
    caplog.clear()
    with caplog.at_level(logging.INFO, logger=stage_plan.__name__):
        stage_plan.front_end_forecast(2000, sweep, 570.0, "/data/drive: ")
        stage_plan.front_end_forecast(2000, sweep, 0.0)  # no limit: a forecast, no warning
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and warnings[0].startswith("/data/drive: the recording is too long for max_minutes=9.5")
    assert "set max_minutes=18 or more" in warnings[0]  # 540 s of front-end at most half of it
