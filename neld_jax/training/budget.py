"""The run's wall clock: one budget (config.max_minutes) shared by its steps, so that a run ends on time however
long its classical baseline or its map took (docs/design.md, "One run, top to bottom").

The budget runs from the run's start. After training it keeps back `mapping.max_seconds` for the rendered map,
REGISTRATION_S_PER_SCAN for each input scan that is not a keyframe (registered to the result after training; at
most MAX_REGISTRATION_SHARE of the budget) and JUDGING_S for the crispness margins and the last files; training
ends where that reserve begins, but always gets at least MIN_SHARE of its share of the budget, however long the
baseline took before it; the baseline's multi-view refinement stops where only that floor would be left. A step
that overran its share is paid back by the next (the render gets its seconds less the overrun, at least MIN_SHARE
of them). A budget of 0 minutes has no limits. Where the run's plan (neld_jax.training.stage_plan) finds that the
recording fits, the registration and the judging keep back what it planned for them instead of the fixed reserves.
"""

from __future__ import annotations

import dataclasses
import time

# Kept back at the end of the run for the crispness margins' query draws (a 1.5 M-point map: 15 s a draw of three
# maps) and, after them, WRITING_S for the figures and files written last (map_topdown.png of two 400k-point maps
# took 14 s on 2 cores)
JUDGING_S = 45.0
WRITING_S = 15.0
# The floor of training's and of the render's share, whatever the steps before them took
MIN_SHARE = 0.25
# Kept back for each input scan registered to the result after training (neld_jax.steps.registration), and the most of
# the budget that may go to it; scans past its deadline keep their interpolated poses, flagged. Measured: 0.045 s a
# KITTI sweep and 0.031 s a synthetic one, read from disk to judged, on 2 busy cores (benchmarks/RESULTS.md, "Every
# input scan"); twice that kept back, for the map's KD-tree and a slower machine
REGISTRATION_S_PER_SCAN = 0.1
MAX_REGISTRATION_SHARE = 0.3


@dataclasses.dataclass
class StageClock:
    """Each step's wall seconds in this process, by the plan's stage names (stage_plan: load, baseline, training,
    map, registration, judging), so that a run says where its time went (metrics.json run.stage_seconds)."""

    last: float = dataclasses.field(default_factory=time.perf_counter)
    seconds: dict = dataclasses.field(default_factory=dict)

    def lap(self, stage: str) -> None:
        """The seconds since the last lap (or the clock's start) are stage's."""
        now = time.perf_counter()
        self.seconds[stage] = round(now - self.last, 2)
        self.last = now

    def ended(self, stage: str, result):
        """result, a step's, once its seconds are recorded as stage's (lap): `made = clock.ended("map", step(...))`."""
        self.lap(stage)
        return result

    def describe(self) -> str:
        return ", ".join(f"{stage} {seconds:.0f} s" for stage, seconds in self.seconds.items())


@dataclasses.dataclass(frozen=True)
class TimeBudget:
    """total_s: the whole run's seconds (0: no limit); render_s: the rendered map's share (0: no limit);
    started: time.perf_counter() at the run's start; registration_s: kept back for registering every other input
    scan (reserving_registration); earlier_s: the seconds earlier processes of a resumed run took, counted in
    run_seconds alone (each process gets the whole budget, as training gets its share afresh on resume); judging_s:
    kept back for the crispness draws and the last files; plan: the run's stage_plan.Plan (None: not planned)."""

    total_s: float
    render_s: float
    started: float
    registration_s: float = 0.0
    earlier_s: float = 0.0
    judging_s: float = JUDGING_S
    plan: object = dataclasses.field(default=None, compare=False)
    clock: StageClock = dataclasses.field(default_factory=StageClock, compare=False)

    @classmethod
    def start(cls, config) -> "TimeBudget":
        """The budget of config.max_minutes and config.mapping.max_seconds, starting now."""
        return cls(60.0 * float(config.max_minutes), float(config.mapping.max_seconds), time.perf_counter())

    def reserving_registration(self, num_scans: int) -> "TimeBudget":
        """This budget keeping back REGISTRATION_S_PER_SCAN for each of num_scans scans to register after training
        (at most MAX_REGISTRATION_SHARE of the whole)."""
        reserve = min(REGISTRATION_S_PER_SCAN * num_scans, MAX_REGISTRATION_SHARE * self.total_s)
        return dataclasses.replace(self, registration_s=reserve if self.limited else 0.0)

    @property
    def limited(self) -> bool:
        return self.total_s > 0

    @property
    def training_share_s(self) -> float:
        """The seconds up to the end of training: the budget less the reserve for the map, the registration of every
        other scan and the judging."""
        return max(self.total_s - max(self.render_s, 0.0) - self.registration_s - self.judging_s, 0.0)

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def run_seconds(self) -> float:
        """The run's seconds so far, over every process of a resumed run (metrics.json's total_seconds)."""
        return self.earlier_s + self.elapsed()

    def baseline_deadline(self) -> float | None:
        """A time.perf_counter() value after which the baseline's refinement registers no more scans: where training
        would be left its floor. None: no limit."""
        if not self.limited:
            return None
        return self.started + (1.0 - MIN_SHARE) * self.training_share_s

    def training_seconds(self) -> float:
        """Seconds training may take from now: up to the reserve, at least MIN_SHARE of its share (0: no limit)."""
        if not self.limited:
            return 0.0
        share = self.training_share_s
        return max(share - self.elapsed(), MIN_SHARE * share)

    def render_seconds(self) -> float:
        """Seconds the rendered map may take from now: its share less what the run is past the end of training, at
        least MIN_SHARE of it (0: no limit)."""
        if not self.limited or self.render_s <= 0:
            return max(self.render_s, 0.0)
        overrun = max(self.elapsed() - self.training_share_s, 0.0)
        return max(self.render_s - overrun, MIN_SHARE * self.render_s)

    def registration_deadline(self) -> float | None:
        """A time.perf_counter() value after which no more scans are registered to the result: where the judging's
        reserve begins, but at least MIN_SHARE of the registration's reserve from now (None: no limit)."""
        if not self.limited:
            return None
        return max(self.started + self.total_s - self.judging_s, time.perf_counter() + MIN_SHARE * self.registration_s)

    def judging_deadline(self) -> float | None:
        """A time.perf_counter() value by which the query draws end, WRITING_S before the budget's end (None: no
        limit)."""
        return self.started + self.total_s - WRITING_S if self.limited else None

    def describe(self) -> str:
        if not self.limited:
            return "no time limit (max_minutes=0)"
        return (
            f"{self.total_s / 60:g} minutes: training until {self.training_share_s / 60:.1f} min, then "
            f"{self.render_s:g} s for the rendered map, {self.registration_s:.0f} s for registering every other "
            f"scan and {self.judging_s:.0f} s for the crispness draws and the last files"
        )
