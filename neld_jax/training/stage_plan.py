"""Every stage of a run sized before it starts: from the recording's size and the rates of its stages, the seconds
each stage needs to be complete (the odometry and the load, the classical baseline's chain, graph and a refinement
round over every keyframe, a floor of training steps, the rendered map's share, every other scan registered, a few
crispness draws and the last files) against the run's clock (neld_jax.training.budget).

`plan_stages` is the pure planner; `planned` makes the plan of a run once its scans are loaded, logs it in one line
with the rates it used, warns in one line when the recording cannot be completed within max_minutes (with the
max_minutes it needs), and hands the clock the planned reserves where the recording fits. The load's seconds are
measured (they have passed when the run plans); the other rates are rough constants, measured where each says, so a
plan is an estimate and the clock still stops each stage at its deadline.
"""

from __future__ import annotations

import dataclasses
import logging
import math

from neld_jax.training.budget import JUDGING_S, MIN_SHARE, REGISTRATION_S_PER_SCAN, WRITING_S, TimeBudget

logger = logging.getLogger(__name__)

# The front-end over a raw 64 x 1024 sweep (the range, KISS-ICP's two passes, the check by global registration):
# 0.27 s on the synthetic car's sweeps (Xeon, 2 cores, shared; benchmarks/RESULTS.md, "The front-end's pace"); scaled
# by a scan's points
ODOMETRY_S_PER_SWEEP, ODOMETRY_POINTS = 0.27, 64 * 1024
# The baseline on HKU_2's 266 keyframes of a few thousand points, idle EPYC: chain 59 s, pose graph 106 s, two
# refinement rounds 80 s (docs/evaluation.md); scaled by a keyframe's points over BASELINE_POINTS (a raw 64-beam
# sweep's chain link took 1.3 s, docs/evaluation.md)
CHAIN_S, GRAPH_S, ROUND_S, BASELINE_POINTS = 0.22, 0.40, 0.15, 10_000
# A training step of the cpu budget's field: 225 ms (EPYC, benchmarks/RESULTS.md, "The live view"); on an
# accelerator about a millisecond (875-1,130 steps/s on one H200, "The gpu budget on one H200")
TRAIN_S_PER_STEP = {"cpu": 0.225}
ACCELERATOR_S_PER_STEP = 0.001
# A crispness draw of three maps: 15 s on HKU_1's 1.5 M points (docs/evaluation.md); scaled by the keyframes' points
DRAW_S, DRAW_POINTS = 15.0, 1_500_000
# What a complete run needs at least: training steps (or train.steps where fewer), crispness draws
MIN_STEPS, MIN_DRAWS = 1000, 3
STAGES = ("load", "baseline", "training", "map", "registration", "judging")


@dataclasses.dataclass(frozen=True)
class Recording:
    """What a run works on: num_scans input scans, num_keyframes of them trained on, points_per_scan (a keyframe's
    mean); odometry: the front-end makes the poses (KISS-ICP); loaded_s: the load's measured seconds, the odometry
    included (None: forecast from the odometry's rate)."""

    num_scans: int
    num_keyframes: int
    points_per_scan: float
    odometry: bool = False
    loaded_s: float | None = None


@dataclasses.dataclass(frozen=True)
class Work:
    """What the run is asked to do: baseline: whether the classical baseline runs (start.poses other than input),
    with map_rounds refinement rounds; min_steps and min_draws: the floors of training and the crispness draws;
    render_s: the rendered map's share of the clock (mapping.max_seconds, as the clock has it)."""

    baseline: bool = False
    map_rounds: int = 2
    min_steps: int = MIN_STEPS
    min_draws: int = MIN_DRAWS
    render_s: float = 0.0


@dataclasses.dataclass(frozen=True)
class Rates:
    """Seconds a unit of each stage takes: a sweep of ODOMETRY_POINTS through the odometry, a keyframe of
    BASELINE_POINTS through the baseline's chain, its pose graph and one refinement round, a training step, a scan
    registered, a crispness draw of DRAW_POINTS; measured: which of them were measured in this run."""

    odometry_s: float = ODOMETRY_S_PER_SWEEP
    chain_s: float = CHAIN_S
    graph_s: float = GRAPH_S
    round_s: float = ROUND_S
    step_s: float = TRAIN_S_PER_STEP["cpu"]
    register_s: float = REGISTRATION_S_PER_SCAN
    draw_s: float = DRAW_S
    measured: tuple = ()

    @classmethod
    def for_backend(cls, backend: str) -> "Rates":
        return cls(step_s=TRAIN_S_PER_STEP.get(backend, ACCELERATOR_S_PER_STEP))

    def describe(self, recording: Recording, baseline: bool = True) -> str:
        """The rates as the plan of `recording` uses them (a keyframe's, a sweep's at its points), the baseline's
        where it runs."""
        scale = max(recording.points_per_scan / BASELINE_POINTS, 1.0)
        measured = "measured" if "odometry" in self.measured else f"{ODOMETRY_POINTS:,} points"
        text = f"odometry {self.odometry_s:.2f} s a sweep ({measured}), " if recording.odometry else ""
        if baseline:
            text += (
                f"the baseline {scale * self.chain_s:.2f} + {scale * self.graph_s:.2f} + "
                f"{scale * self.round_s:.2f} s a keyframe (chain, graph, a round), "
            )
        return (
            f"{text}{self.step_s:g} s a training step, {self.register_s:g} s a scan registered, {self.draw_s:g} s "
            f"a crispness draw of {DRAW_POINTS:,} points (rough constants where not measured: "
            "neld_jax.training.stage_plan)"
        )


@dataclasses.dataclass(frozen=True)
class Plan:
    """needed: {stage: the seconds it needs to be complete}; seconds: {stage: its planned seconds} (empty where the
    budget has no limit or the recording does not fit: the clock's fixed reserves apply); needed_s: the budget a
    complete run needs (training keeps at least MIN_SHARE of its share, as the clock gives it); total_s: the budget
    (0: no limit)."""

    recording: Recording
    work: Work
    rates: Rates
    needed: dict
    seconds: dict
    needed_s: float
    total_s: float

    @property
    def fits(self) -> bool:
        return self.total_s <= 0 or self.needed_s <= self.total_s

    @property
    def needed_minutes(self) -> float:
        """The max_minutes a complete run needs, rounded up to half a minute."""
        return math.ceil(self.needed_s / 30.0) / 2.0

    def describe(self) -> str:
        r = self.recording
        limit = "with no time limit" if self.total_s <= 0 else f"within max_minutes={self.total_s / 60:g}"
        shown = self.seconds or self.needed
        stages = ", ".join(
            f"{stage} {shown[stage]:.0f} s"
            + (f" ({shown[stage] / self.rates.step_s:,.0f} steps)" if stage == "training" else "")
            for stage in STAGES
            if shown[stage] > 0 or stage == "training"
        )
        least = f"{self.needed_s / 60:.1f} minutes at least"
        verdict = (
            f"fits: {least}"
            if self.seconds
            else f"each stage's least: {least}" + ("" if self.fits else ", does not fit")
        )
        return (
            f"the plan for {r.num_scans} scans ({r.num_keyframes} keyframes of {r.points_per_scan:,.0f} points) "
            f"{limit}: {stages} ({verdict}); at {self.rates.describe(r, self.work.baseline)}"
        )

    def warning(self) -> str | None:
        """One line where the recording cannot be completed within the budget, with the max_minutes it needs."""
        if self.fits:
            return None
        w, needed = self.work, self.needed
        complete = ["the baseline over every keyframe"] if needed["baseline"] > 0 else []
        complete += [f"{w.min_steps} training steps"] + (["every scan registered"] if needed["registration"] else [])
        return (
            f"the recording is too long for max_minutes={self.total_s / 60:g}: its {self.recording.num_scans} "
            f"scans need about {self.needed_s / 60:.1f} minutes to complete every stage ("
            f"{', '.join(complete)}, {w.min_draws} crispness draws); set max_minutes={self.needed_minutes:g} or "
            "more, or stages will be cut short at their deadlines"
        )

    def record(self) -> dict:
        """metrics.json's run.plan."""
        return {
            "fits": self.fits,
            "needs_max_minutes": self.needed_minutes,
            "needed_s": {k: round(v, 1) for k, v in self.needed.items()},
            "planned_s": {k: round(v, 1) for k, v in self.seconds.items()},
            "rates": dataclasses.asdict(self.rates),
        }


def needed_seconds(recording: Recording, work: Work, rates: Rates, rounds: int = 1) -> dict:
    """{stage: the seconds it needs to be complete}, the baseline with `rounds` refinement rounds (at most
    work.map_rounds)."""
    r = recording
    load = r.loaded_s
    if load is None:
        load = r.num_scans * rates.odometry_s * r.points_per_scan / ODOMETRY_POINTS if r.odometry else 0.0
    per_keyframe = rates.chain_s + rates.graph_s + min(rounds, work.map_rounds) * rates.round_s
    baseline = r.num_keyframes * per_keyframe * max(r.points_per_scan / BASELINE_POINTS, 1.0) if work.baseline else 0.0
    draw = rates.draw_s * r.num_keyframes * r.points_per_scan / DRAW_POINTS
    return {
        "load": load,
        "baseline": baseline,
        "training": work.min_steps * rates.step_s,
        "map": work.render_s,
        "registration": max(r.num_scans - r.num_keyframes, 0) * rates.register_s,
        "judging": max(JUDGING_S, work.min_draws * draw + WRITING_S),
    }


def budget_needed(needed: dict) -> float:
    """The budget in which every stage gets what `needed` says: training its floor, and at least MIN_SHARE of its
    share (the clock stops the baseline where only that is left)."""
    before = needed["load"] + needed["baseline"]
    after = needed["map"] + needed["registration"] + needed["judging"]
    return max(before + needed["training"] + after, before / (1.0 - MIN_SHARE) + after)


def plan_stages(recording: Recording, total_s: float, work: Work = Work(), rates: Rates = Rates()) -> Plan:
    """The plan of a run on `recording` within total_s seconds (0: no limit): each stage's least seconds and, where
    they fit, its planned seconds: the baseline's every round where they fit too, training the rest."""
    needed = needed_seconds(recording, work, rates)
    needed_s = budget_needed(needed)
    seconds = {}
    if 0 < needed_s <= total_s:
        whole = needed_seconds(recording, work, rates, rounds=work.map_rounds)
        seconds = dict(whole if budget_needed(whole) <= total_s else needed)
        seconds["training"] = total_s - sum(v for stage, v in seconds.items() if stage != "training")
    return Plan(recording, work, rates, needed, seconds, needed_s, total_s)


@dataclasses.dataclass(frozen=True)
class PlanSettings:
    """What the plan reads of a run's config: the work asked (Work), the budget's name and jax's backend (the
    training step's rate)."""

    work: Work
    budget_name: str
    backend: str

    @classmethod
    def from_config(cls, config) -> "PlanSettings":
        import jax

        work = Work(
            baseline=str(config.start.poses).lower() != "input",
            map_rounds=int(config.baseline.map_rounds),
            min_steps=min(MIN_STEPS, int(config.train.steps)),
            min_draws=min(MIN_DRAWS, int(config.eval.crispness_draws)),
        )
        return cls(work, str(config.budget), jax.default_backend())


def front_end_forecast(num_scans: int, points_per_scan: float, total_s: float, where: str = "") -> float:
    """Before the front-end runs (the longest part of loading raw sweeps): its seconds forecast from
    ODOMETRY_S_PER_SWEEP for num_scans scans of points_per_scan points, logged in one line, with a warning where it
    alone would take more than half of a limited budget total_s (0: none), naming the max_minutes that leaves the
    other stages the rest. Returns the forecast seconds."""
    forecast = num_scans * ODOMETRY_S_PER_SWEEP * points_per_scan / ODOMETRY_POINTS
    logger.info(
        "%sthe front-end over %d scans of about %.0f points: about %.0f s (a rough %.2f s a %d-point sweep on 2 CPU "
        "cores: neld_jax.training.stage_plan)",
        where,
        num_scans,
        points_per_scan,
        forecast,
        ODOMETRY_S_PER_SWEEP,
        ODOMETRY_POINTS,
    )
    if total_s > 0 and forecast > 0.5 * total_s:
        needs = math.ceil(2 * 2 * forecast / 60.0) / 2  # the front-end at most half of it, in half minutes
        logger.warning(
            "%sthe recording is too long for max_minutes=%g: the front-end alone needs about %.1f minutes of it; set "
            "max_minutes=%g or more, or stages will be cut short at their deadlines (the plan after loading says "
            "what each needs)",
            where,
            total_s / 60.0,
            forecast / 60.0,
            needs,
        )
    return forecast


def planned(settings: PlanSettings, loaded, keyframes, budget: TimeBudget) -> TimeBudget:
    """The run's clock once its scans are loaded (loaded: every input scan, keyframes: those trained on; sequences),
    with the registration's reserve and the plan: logged in one line, a warning where the recording cannot be
    completed in time; where it fits, the registration and the judging keep what the plan gives them."""
    budget = budget.reserving_registration(loaded.num_scans - keyframes.num_scans)
    logger.info("budget %s on jax's %s backend: %s", settings.budget_name, settings.backend, budget.describe())
    points = sum(len(scan) for scan in keyframes.scans) / max(keyframes.num_scans, 1)
    odometry, loaded_s = loaded.poses_from == "kiss_icp", budget.elapsed()
    rates = Rates.for_backend(settings.backend)
    if odometry:  # the load was mostly the odometry: its rate, measured
        rates = dataclasses.replace(rates, odometry_s=loaded_s / max(loaded.num_scans, 1), measured=("odometry",))
    recording = Recording(loaded.num_scans, keyframes.num_scans, points, odometry, loaded_s)
    plan = plan_stages(recording, budget.total_s, dataclasses.replace(settings.work, render_s=budget.render_s), rates)
    logger.info("%s", plan.describe())
    if plan.warning():
        logger.warning("%s", plan.warning())
    if plan.seconds:  # it fits: the registration and the judging get their planned seconds, not the fixed reserves
        budget = dataclasses.replace(
            budget, registration_s=plan.seconds["registration"], judging_s=plan.seconds["judging"]
        )
    return dataclasses.replace(budget, plan=plan)
