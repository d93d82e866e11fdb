"""The run's one clock (neld_jax.training.budget.TimeBudget): training's share and floor, the baseline's deadline, the
map's seconds, the crispness draws' deadline, no limit at 0 minutes, and a resumed run's seconds."""

import pytest

from neld_jax.config import defaults, with_budget
from neld_jax.training.budget import JUDGING_S, WRITING_S, TimeBudget


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
