"""One bundle-adjustment run, read top to bottom: load, choose the start, train, render, register every scan,
judge (the answer: NeLD-BA's poses or, where they blurred it, the start's), write.

Each step is a function in the module of its idea; `bin/train.py` (neld-train) calls `run`. The viewer
(neld_jax.writing.viewer) records what each step made to run.rrd, and streams it with viz.live. The config is the
user's, written once to config.json and never changed; what the run decides (the start, the pose steps, a plan
compressed to the time) is recorded in metrics.json. One clock, config.max_minutes, is shared by the steps
(neld_jax.training.budget). A rerun with the same output_dir and configuration resumes from its last checkpoint and its
saved start, and its total_seconds counts the earlier processes' seconds too (output_folder.CLOCK_FILE); one of
another configuration stops before it writes anything (neld_jax.writing.output_folder).
"""

from __future__ import annotations

import dataclasses
import functools
import logging

import ml_collections

from neld_jax.judging import answer
from neld_jax.steps import mapping, refine, registration, start
from neld_jax.steps.session_alignment import load_sessions
from neld_jax.training import stage_plan
from neld_jax.training.budget import TimeBudget
from neld_jax.writing import output_folder, outputs, session_outputs
from neld_jax.writing.viewer import RunViewer

logger = logging.getLogger(__name__)


def run(config: ml_collections.ConfigDict, progress: bool = True, restart: bool = False) -> dict:
    """Run the bundle adjustment `config` describes; returns what it wrote to metrics.json. The output folder is
    checked first (a folder of another configuration is a ConfigError; restart=True deletes the earlier run's files
    instead); run.rrd is closed however the steps end, with the error that stopped them."""
    budget = TimeBudget.start(config)
    out_dir = output_folder.prepare(config, restart)
    budget = dataclasses.replace(budget, earlier_s=output_folder.earlier_seconds(out_dir))  # a resume's earlier runs
    with RunViewer.open(out_dir, config.viz) as viewer:
        summary = run_steps(config, out_dir, budget, viewer, progress)
    output_folder.record_seconds(out_dir, budget)
    logger.info("the steps took: %s", budget.clock.describe())
    return summary


def run_steps(
    config: ml_collections.ConfigDict, out_dir: str, budget: TimeBudget, viewer: RunViewer, progress: bool = True
) -> dict:
    """The steps of `run` in its prepared output folder."""
    config_hash = outputs.config_hash(config)

    # 1. Load every input scan and the keyframes trained on; several recordings joined (steps.session_alignment).
    loaded, keyframes, recordings = load_sessions(config.data, budget.total_s)
    # ... and every step's seconds planned from the recording's size, with one warning where it cannot fit.
    budget = stage_plan.planned(stage_plan.PlanSettings.from_config(config), loaded, keyframes, budget)
    budget.clock.lap("load")
    viewer.log_input(loaded, keyframes)

    # 2. Choose the start and its pose steps: the input's or the baseline's poses (steps.start); a resume keeps it.
    begin = start.Start.resumed(out_dir, config_hash, keyframes.poses)
    if begin is None:
        begin = start.choose_start(
            start.StartSettings.from_config(config), keyframes, budget.baseline_deadline(), progress, recordings
        )
        begin.save(out_dir, config_hash, keyframes.poses)
    budget.clock.lap("baseline")
    viewer.log_start(loaded, keyframes, begin)

    # 3. Train the field(s) and the poses (neld_jax.steps.refine: one cube, or submaps for a sequence larger than one).
    context = refine.TrainingContext(
        out_dir,
        config_hash,
        budget.training_seconds(),
        progress,
        viewer.training_hook(),
        functools.partial(output_folder.record_seconds, out_dir, budget),
    )
    refined = budget.clock.ended(
        "training",
        refine.refine_keyframes(
            refine.TrainingSettings.from_config(config), keyframes, begin.poses, begin.pose_steps, context
        ),
    )

    # 4. Render the map (neld_jax.steps.mapping; none with mapping.enabled off).
    render = budget.clock.ended(
        "map",
        mapping.rendered_map(
            config.mapping, config.sampling, refined, keyframes, config.seed + 1, budget.render_seconds(), progress
        ),
    )
    viewer.log_rendered(render)

    # 5. Register every other input scan to the keyframes' refined map, from its interpolated correction.
    settings = registration.RegistrationSettings.from_groups(config.data, config.baseline)
    registered = budget.clock.ended(
        "registration",
        registration.register_every_scan(
            loaded, keyframes, refined.poses, settings, progress, budget.registration_deadline()
        ),
    )
    # ... and the distance travelled checked against the input's on every scan's map (judging.answer).
    made = answer.keep_travel_of_input(
        outputs.RunSteps(loaded, keyframes, begin, refined, render, registered), config.eval
    )

    # 6. Judge the crispness; the answer: NeLD-BA's poses unless they blurred the start's (judging.answer); write
    #    poses, maps, per-scan report, metrics.json (writing.outputs), each recording's (writing.session_outputs).
    made, judged = answer.keep_the_better(made, outputs.judge_crispness(config.eval, made, budget, progress))
    written = outputs.write_outputs(out_dir, config.mapping, made)
    budget.clock.lap("judging")  # the distance check, the crispness draws and the poses and maps written
    T_all = written.trajectories["optimized"].poses
    viewer.log_outputs(keyframes, made.refined, T_all, recordings)
    sections = session_outputs.sections(recordings, keyframes, made.refined.poses, written, config.eval)
    summary, scan_rows = outputs.judge_run(out_dir, config, made, written, budget, judged, sections)
    session_outputs.write_session_files(out_dir, recordings, written, scan_rows)
    viewer.log_verdict(scan_rows, loaded, T_all)
    return summary
