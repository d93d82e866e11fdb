"""Every setting of a run, its default, and the named presets over them.

`SETTINGS` declares every field once: its name, default, what it accepts (a `Rule`: type, range or choices) and
what it does in one line. `defaults()` (the paper's configuration), `RULES` (what `validate` checks) and the
settings reference of docs/defaults.md (`python -m neld_jax.config --docs`) are made from it. Where a module owns a
default or a list of choices (the baseline's settings, the synthetic generator's, the formats, the start's choices),
the declaration imports it from there. A run is one of two recipes at one of three budgets (docs/defaults.md says
why each value is what it is):

- budgets: "paper" (the defaults as they are: 160k steps), "cpu" (within 10 minutes on 2 CPU cores) and "gpu" (the
  cpu recipe trained 20x longer, the paper's map); a config string that names none gets "gpu" where JAX's default
  backend is a GPU, else "cpu" (`default_budget`);
- recipes: `synthetic(budget)` for the generated demo sequence, whose odometry drifts far and whose poses move in
  large steps, and `recording(budget)` for every recorded sequence whatever layout it arrives in: on the cpu and
  gpu budgets small pose steps, points within 40 m, and training starts from the crisper of the input and the
  classical baseline (start.poses="crisper").

The files in configs/ only say how to read a layout: `get_config(budget)` picks the recipe, then sets data.format
and what the layout needs. Every field can be overridden on the command line (`--config.train.steps=2000`).
Distances are metres (`*_m`); the trainer converts them with the normalisation's scale.

`RULES` says what each field accepts and `RELATIONS` what fields accept together;
`validate` checks both once the config is resolved, before a run reads anything, and a bad value is one ConfigError
line naming the field, its value and what it accepts.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import math
import os

import ml_collections

from neld_jax.baseline.settings import BaselineSettings
from neld_jax.data.formats import KISS_ICP
from neld_jax.data.ground_truth import SCAN_FRAMES
from neld_jax.errors import ConfigError
from neld_jax.field.options import HIERARCHICAL, MATMUL_DTYPES
from neld_jax.frontend.sweep_times import DESKEW_CHOICES
from neld_jax.judging import crispness
from neld_jax.steps.choices import START_POSES
from neld_jax.steps.inputs import FORMATS
from neld_jax.synthetic.generator import MIN_RANGE_M, PATH_WOBBLE, synthetic_defaults

BUDGETS = ("paper", "gpu", "cpu")
# (init, final) pose learning rates of poses that are already good: a recording's odometry, the baseline's poses
REFINE_POSE_LR = (5e-6, 2.5e-7)


@dataclasses.dataclass(frozen=True)
class Rule:
    """What one field accepts. kind: "int", "float", "bool", "str", or "ints" / "floats" (a tuple of them, of a
    length in `lengths` when given); low / high: inclusive bounds of the number or of every element (low excluded
    when `above`); choices: the strings accepted (compared in lower case when `any_case`: its reader lowers it);
    nonempty: a tuple needs at least one element."""

    kind: str
    low: float | None = None
    high: float | None = None
    above: bool = False
    choices: tuple[str, ...] = ()
    any_case: bool = False
    lengths: tuple[int, ...] = ()
    nonempty: bool = False

    def accepts(self, value) -> bool:
        if self.kind in ("ints", "floats"):
            if not isinstance(value, (tuple, list)) or (self.nonempty and not value):
                return False
            return (not self.lengths or len(value) in self.lengths) and all(
                self._accepts_one(v, self.kind[:-1]) for v in value
            )
        return self._accepts_one(value, self.kind)

    def _accepts_one(self, value, kind: str) -> bool:
        if kind == "bool":
            return isinstance(value, bool)
        if kind == "str":
            text = value.lower() if self.any_case and isinstance(value, str) else value
            return isinstance(value, str) and (not self.choices or text in self.choices)
        if isinstance(value, bool) or not isinstance(value, int if kind == "int" else (int, float)):
            return False
        if not math.isfinite(value) or (self.high is not None and value > self.high):
            return False
        return self.low is None or (value > self.low if self.above else value >= self.low)

    def describe(self) -> str:
        """What the field accepts, in words: "an integer >= 1", "one of before | nerf | none", ..."""
        if self.kind == "bool":
            return "True or False"
        if self.kind == "str":
            return f"one of {' | '.join(c or repr(c) for c in self.choices)}" if self.choices else "a string"
        bounds = []
        if self.low is not None:
            bounds.append(f"{'>' if self.above else '>='} {self.low:g}")
        if self.high is not None:
            bounds.append(f"<= {self.high:g}")
        noun = {"int": "an integer", "float": "a number", "ints": "integers", "floats": "numbers"}[self.kind]
        what = f"{noun} {' and '.join(bounds)}".strip()
        if self.kind in ("int", "float"):
            return what
        counts = " or ".join(str(n) for n in self.lengths if n > 0)
        tuple_of = f"a {'non-empty ' if self.nonempty else ''}tuple of {counts + ' ' if counts else ''}{what}"
        return f"() or {tuple_of}" if 0 in self.lengths else tuple_of

    @property
    def type_name(self) -> str:
        """The field's Python type: "int", "float", "bool", "str", "tuple[int]" or "tuple[float]"."""
        return f"tuple[{self.kind[:-1]}]" if self.kind in ("ints", "floats") else self.kind


def _integer(low=None, high=None) -> Rule:
    return Rule("int", low, high)


def _number(low=None, high=None, above=False) -> Rule:
    return Rule("float", low, high, above)


def _choice(*choices: str, any_case=False) -> Rule:
    return Rule("str", choices=choices, any_case=any_case)


FLAG, TEXT, POSITIVE, NON_NEGATIVE = Rule("bool"), Rule("str"), _number(0, above=True), _number(0)
COUNT, AT_LEAST_ONE = _integer(0), _integer(1)


@dataclasses.dataclass(frozen=True)
class Setting:
    """One field of the config: its dotted name, its default (a value `rule` accepts, of the type the ConfigDict
    keeps), what it accepts and, in one line, what it does (docs/defaults.md says why the value)."""

    name: str
    default: object
    rule: Rule
    why: str

    @property
    def group(self) -> str:
        """The group the field belongs to ("" for the run's own fields): "data.synthetic" for
        data.synthetic.seed."""
        return self.name.rpartition(".")[0]


# The groups, in order, and what each is for (a heading of docs/defaults.md's reference)
GROUPS = {
    "": "the run: where it writes, its seed and its clock",
    "data": "the sequence and its keyframes (neld_jax.steps.inputs, neld_jax.data)",
    "data.synthetic": 'the generated sequence, data.format="synthetic" (neld_jax.synthetic.generator owns the '
    "defaults)",
    "model": "the field (neld_jax.field.density)",
    "sampling": "the samples along a ray (neld_jax.field.sampling)",
    "loss": "the loss terms' weights (eq. 13)",
    "train": "the schedule and the steps of the field and the poses (neld_jax.training.train)",
    "start": "where training starts (neld_jax.steps.start): the input, the classical baseline's poses, or the "
    "crisper of the two",
    "submaps": "a sequence larger than one cube split into overlapping windows of keyframes "
    "(neld_jax.training.submaps); the fields marked (M > 1) apply to a plan of several submaps only",
    "mapping": "the rendered map (neld_jax.steps.mapping)",
    "baseline": "the classical baseline (neld_jax.baseline): scan-to-map ICP, a loop-closed pose graph, multi-view "
    "refinement; BaselineSettings owns these defaults and the baseline's other settings",
    "eval": "the judging of the result: the ground-truth map's alignment, the raw map's crispness",
    "viz": "Rerun (neld_jax.writing.viewer): the run's trajectories, maps and training in Rerun's viewer",
}

_BASELINE = BaselineSettings()
_SYNTHETIC = synthetic_defaults()

# Every setting of the paper's configuration (the "paper" budget), in the order of `GROUPS`. Distances are metres.
SETTINGS = (
    Setting("output_dir", "outputs/run", TEXT, "where the run writes (a rerun resumes from its checkpoints)"),
    Setting("seed", 0, COUNT, "the field's initialisation, the rays drawn, the batches"),
    Setting(
        "budget",
        "paper",
        _choice(*BUDGETS, any_case=True),
        "the budget the preset applied; a record, not read by the run",
    ),
    Setting("max_minutes", 0.0, NON_NEGATIVE, "the whole run's wall-clock budget (neld_jax.training.budget); 0: none"),
    Setting("data.format", "generic", _choice(*FORMATS, any_case=True), "the layout the sequence arrives in"),
    Setting("data.root", "", TEXT, "the sequence's folder"),
    Setting(
        "data.initial_poses",
        "",
        TEXT,
        f'"": the layout\'s poses; {KISS_ICP}: KISS-ICP from the scans; lio_keyframes: a file',
    ),
    Setting(
        "data.drop_unmatched_tail",
        False,
        FLAG,
        "drop up to 5 trailing scans without a pose or stamp instead of failing",
    ),
    Setting(
        "data.scans_in_world_frame",
        False,
        FLAG,
        "the scans are registered already: move them into their sensors' frames",
    ),
    Setting("data.invert_poses", False, FLAG, "the poses file holds world -> sensor transforms"),
    Setting(
        "data.keyframe_interval_s", 3.0, _number(), "keyframes at most this many seconds apart (<= 0: cap off) ..."
    ),
    Setting(
        "data.keyframe_distance_m",
        0.0,
        _number(),
        "... this far apart (0: a tenth of max_range_m with the time cap, else off) ...",
    ),
    Setting(
        "data.keyframe_angle_deg",
        0.0,
        _number(),
        "... and turned this far (0: 30 with the time cap, else off; all off: every scan)",
    ),
    Setting("data.min_range_m", 0.5, NON_NEGATIVE, "points nearer the sensor are dropped"),
    Setting("data.max_range_m", 80.0, POSITIVE, "points further away are dropped"),
    Setting(
        "data.deskew",
        "auto",
        _choice(*DESKEW_CHOICES, any_case=True),
        "scans without point times: measured (auto), deskewed already, or raw sweeps (raw_<start>_<turning>)",
    ),
    Setting("data.voxel_size_m", 0.05, NON_NEGATIVE, "each keyframe's points on this grid"),
    Setting("data.first_scan", 0, COUNT, "keyframes from this input scan on ..."),
    Setting("data.max_scans", 0, COUNT, "... and at most this many (0: all): a long sequence in pieces"),
    Setting("data.max_rays_per_scan", 0, COUNT, "training rays per keyframe, a random subset (0: every point)"),
    Setting("data.timestamp_tol_s", 0.05, NON_NEGATIVE, "scans and poses match by time within this"),
    Setting(
        "data.gt_poses_path", "", TEXT, "ground-truth trajectory (TUM, or Newer College .csv) in place of the layout's"
    ),
    Setting("data.gt_map_path", "", TEXT, "ground-truth map (.pcd / .ply) in place of the layout's"),
    Setting(
        "data.gt_from_scan",
        (),
        Rule("floats", lengths=(0, 7)),
        "the scan frame's pose in the ground truth's body frame (tx ty tz qx qy qz qw)",
    ),
    Setting(
        "data.scan_frame",
        "",
        _choice("", *sorted({f for frames in SCAN_FRAMES.values() for f in frames})),
        "the published extrinsic of the ground truth (data.ground_truth.SCAN_FRAMES)",
    ),
    Setting("data.gt_time_offset_s", 0.0, _number(), "added to the scan stamps when matching ground truth"),
    Setting("data.synthetic.seed", _SYNTHETIC.seed, COUNT, "the scene, the drift and the noise drawn"),
    Setting(
        "data.synthetic.route",
        _SYNTHETIC.route,
        _choice("loop", "courtyards"),
        "a loop round one courtyard, or a route through several",
    ),
    Setting("data.synthetic.route_length_m", _SYNTHETIC.route_length_m, POSITIVE, "the courtyards route's length"),
    Setting("data.synthetic.num_scans", _SYNTHETIC.num_scans, AT_LEAST_ONE, "scans generated (each a keyframe)"),
    Setting("data.synthetic.scene_size_m", _SYNTHETIC.scene_size_m, POSITIVE, "the courtyard's width"),
    Setting("data.synthetic.trajectory_radius_m", _SYNTHETIC.trajectory_radius_m, POSITIVE, "the loop's radius"),
    Setting("data.synthetic.num_beams", _SYNTHETIC.num_beams, AT_LEAST_ONE, "the spinning LiDAR's rows ..."),
    Setting("data.synthetic.num_columns", _SYNTHETIC.num_columns, AT_LEAST_ONE, "... and columns"),
    Setting(
        "data.synthetic.max_range_m",
        _SYNTHETIC.max_range_m,
        _number(MIN_RANGE_M, above=True),
        "the LiDAR's reach (beyond its minimum range, synthetic.lidar.MIN_RANGE_M)",
    ),
    Setting("data.synthetic.range_noise_m", _SYNTHETIC.range_noise_m, NON_NEGATIVE, "the ranges' noise (sigma)"),
    Setting(
        "data.synthetic.drift_trans_m",
        _SYNTHETIC.drift_trans_m,
        NON_NEGATIVE,
        "the initial poses' random walk: translation a step ...",
    ),
    Setting("data.synthetic.drift_rot_deg", _SYNTHETIC.drift_rot_deg, NON_NEGATIVE, "... and rotation a step"),
    Setting("data.synthetic.gt_map_points", _SYNTHETIC.gt_map_points, COUNT, "points of the ground-truth map"),
    Setting("model.width", 512, _integer(2), "hidden layer width (the density head is width // 2 wide)"),
    Setting("model.depth", 8, AT_LEAST_ONE, "hidden layers"),
    Setting("model.skip_layers", (4,), Rule("ints", low=0), "hidden layers that get the encoded position again"),
    Setting("model.pos_freqs", 15, AT_LEAST_ONE, "L of the position encoding"),
    Setting("model.dir_freqs", 4, COUNT, "L of the view direction's encoding"),
    Setting("model.surrogate_gradient", True, FLAG, "eq. 9 (ablation: False)"),
    Setting(
        "model.matmul_dtype", "float32", _choice(*MATMUL_DTYPES), "the hidden matmuls' inputs (parameters stay float32)"
    ),
    Setting("sampling.z_low_m", 0.3, POSITIVE, "eq. 7's lower bound"),
    Setting("sampling.z_up_m", 200.0, POSITIVE, "eq. 7's upper bound (beyond the cube: the cube bound decides)"),
    Setting("sampling.cube_bound", True, FLAG, "samples only inside [-1, 1]^3 (ablation: False)"),
    Setting(
        "sampling.hierarchical",
        "before",
        _choice(*HIERARCHICAL),
        "before (NeLD-BA) | nerf (ablation) | none (ablation)",
    ),
    Setting(
        "sampling.coarse_stages",
        (32, 48, 64),
        Rule("ints", low=1, nonempty=True),
        "coarse samples per ray, one stage each (ramp over train.c2f_end_fraction)",
    ),
    Setting(
        "sampling.fine_stages", (16, 24, 32), Rule("ints", low=0, nonempty=True), "fine samples per ray, one stage each"
    ),
    Setting("sampling.guided_samples", 0, COUNT, "coarse samples within 1 m of the measured range (0: the paper)"),
    Setting("loss.lambda_coarse", 0.1, NON_NEGATIVE, "eq. 13"),
    Setting("loss.lambda_range", 1.0, NON_NEGATIVE, "eq. 13"),
    Setting("loss.lambda_termination", 1.0, NON_NEGATIVE, "eq. 13 (ablation: 0)"),
    Setting("train.steps", 160_000, AT_LEAST_ONE, "optimiser steps"),
    Setting("train.batch_rays", 1024, AT_LEAST_ONE, "rays a step (over every submap)"),
    Setting("train.field_lr_init", 5e-5, NON_NEGATIVE, "the field's Adam learning rate, decaying exponentially ..."),
    Setting("train.field_lr_final", 2e-5, NON_NEGATIVE, "... to this"),
    Setting("train.pose_lr_rot_init", 5e-5, NON_NEGATIVE, "the poses' rotation learning rate ..."),
    Setting("train.pose_lr_rot_final", 2e-5, NON_NEGATIVE, "... decaying to this"),
    Setting("train.pose_lr_trans_init", 5e-5, NON_NEGATIVE, "... and translation learning rate"),
    Setting("train.pose_lr_trans_final", 2e-5, NON_NEGATIVE, "... decaying to this"),
    Setting(
        "train.c2f_end_fraction",
        0.75,
        _number(0, 1),
        "coarse-to-fine: every frequency active after this fraction of the steps",
    ),
    Setting("train.pose_start_freq", 6, COUNT, "k*: the poses move once this frequency is active"),
    Setting(
        "train.fixed_scans",
        (0,),
        Rule("ints"),
        "scans that never move, negative from the last back (the gauge; (): every pose free, anchored on scan 0 after)",
    ),
    Setting("train.checkpoint_every", 5000, AT_LEAST_ONE, "steps"),
    Setting(
        "train.log_every",
        100,
        AT_LEAST_ONE,
        "steps a device call runs (the log, the progress bar and the clock move in these)",
    ),
    Setting("start.poses", "input", _choice(*START_POSES, any_case=True), "input | baseline | crisper"),
    Setting(
        "start.pose_lr_from_baseline",
        REFINE_POSE_LR,
        Rule("floats", low=0, lengths=(0, 2)),
        "from the baseline: pose learning rates at most these",
    ),
    Setting(
        "start.prior_from_baseline", 3000.0, NON_NEGATIVE, "... and a pull of each pose toward its start (0: none)"
    ),
    # submaps_wanted reads the flag's words too
    Setting(
        "submaps.enabled",
        "auto",
        _choice("auto", "on", "off", "true", "false", "1", "0", any_case=True),
        "auto (when one cube's finest detail exceeds max_detail_m) | on | off",
    ),
    Setting("submaps.max_detail_m", 0.25, POSITIVE, "the finest Fourier period one cube may have"),
    Setting("submaps.keyframes", 0, COUNT, "keyframes a submap (0: the most whose cube keeps max_detail_m)"),
    Setting("submaps.overlap", 2, COUNT, "keyframes neighbouring submaps share"),
    Setting(
        "submaps.closure_radius_m",
        10.0,
        NON_NEGATIVE,
        "a revisit within this distance gets a submap of both visits (0: none)",
    ),
    Setting("submaps.max_submaps", 0, COUNT, "at most this many submaps (longer windows, coarser cubes; 0: no limit)"),
    Setting("submaps.width", 0, COUNT, "(M > 1) each submap's field width (0: model.width)"),
    Setting(
        "submaps.step_rays_factor",
        1.0,
        POSITIVE,
        "(M > 1) a step's rays over every submap, in units of train.batch_rays",
    ),
    Setting(
        "submaps.lambda_termination",
        0.0,
        NON_NEGATIVE,
        "(M > 1) the termination loss's weight (0: loss.lambda_termination)",
    ),
    Setting(
        "submaps.field_lr_from_steps",
        (),
        Rule("floats", low=0, above=True, lengths=(0, 2)),
        "(M > 1) (N, f): a plan of N steps or more trains the fields at f x the rate",
    ),
    Setting("mapping.enabled", True, FLAG, "render map_rendered.ply"),
    Setting("mapping.num_coarse", 128, AT_LEAST_ONE, "samples per ray of the rendered map (eq. 14) ..."),
    Setting("mapping.num_fine", 128, COUNT, "... coarse and fine"),
    Setting("mapping.max_rays_per_scan", 0, COUNT, "rays per keyframe (0: every ray) ..."),
    Setting(
        "mapping.max_rays", 0, COUNT, "... and over the sequence (0: no limit; each keyframe an equal share, >= 256)"
    ),
    Setting("mapping.voxel_size_m", 0.05, NON_NEGATIVE, "the written maps' grid (0: none)"),
    Setting("mapping.min_opacity", 0.5, _number(0, 1), "rays less opaque than this end nowhere"),
    Setting("mapping.max_seconds", 0.0, NON_NEGATIVE, "the render's share of max_minutes (0: no limit)"),
    Setting("baseline.voxel_size_m", _BASELINE.voxel_size_m, NON_NEGATIVE, "the scans' grid for ICP"),
    Setting(
        "baseline.loop_radius_m", _BASELINE.loop_radius_m, NON_NEGATIVE, "loop-closure candidates within this distance"
    ),
    Setting(
        "baseline.global_loops_per_scan",
        _BASELINE.global_loops_per_scan,
        COUNT,
        "FPFH + RANSAC closures where ICP cannot reach (0: none)",
    ),
    Setting("baseline.map_rounds", _BASELINE.map_rounds, COUNT, "rounds of multi-view refinement (0: none)"),
    Setting(
        "eval.map_icp_m", 0.0, NON_NEGATIVE, "> 0: refine the ground-truth map's alignment by ICP at this distance"
    ),
    Setting(
        "eval.crispness_radius_m",
        crispness.DEFAULT_RADIUS_M,
        POSITIVE,
        "the raw map's crispness: neighbourhood radius ...",
    ),
    Setting("eval.crispness_queries", crispness.DEFAULT_MAX_QUERIES, AT_LEAST_ONE, "... and query points"),
    Setting(
        "eval.crispness_draws",
        crispness.DEFAULT_DRAWS,
        COUNT,
        "draws of the query points that say how sure a comparison is (< 2: none)",
    ),
    Setting("viz.record", True, FLAG, "write run.rrd in the output folder"),
    Setting("viz.live", False, FLAG, "also serve the run on 127.0.0.1:9876 while it trains (`rerun rerun+http://...`)"),
)

# What each field accepts, by dotted name
RULES = {s.name: s.rule for s in SETTINGS}


def defaults() -> ml_collections.ConfigDict:
    """The paper's configuration (the "paper" budget): every field of `SETTINGS` at its default."""
    c = ml_collections.ConfigDict()
    for setting in SETTINGS:
        node = c
        *parents, leaf = setting.name.split(".")
        for part in parents:
            if part not in node:
                node[part] = ml_collections.ConfigDict()
            node = node[part]
        node[leaf] = setting.default
    return c


# The generated part of docs/defaults.md lies between these lines (`python -m neld_jax.config --docs` rewrites it)
DOCS_PATH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "defaults.md")
DOCS_BEGIN = "<!-- settings: generated by python -m neld_jax.config --docs -->"
DOCS_END = "<!-- end of generated settings -->"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def settings_reference() -> str:
    """The settings reference in Markdown: per group of `GROUPS`, a table of its fields (field, type, default,
    accepts, what it does), from `SETTINGS`."""
    parts = []
    for group, about in GROUPS.items():
        # bold lines, not headings: the hand-written sections of the same names keep their anchors
        parts += [
            f"**{group or 'The run'}**: {about}.",
            "",
            "| field | type | default | accepts | what it does |",
            "|---|---|---|---|---|",
        ]
        parts += [
            f"| `{s.name}` | {s.rule.type_name} | `{_cell(repr(s.default))}` | {_cell(s.rule.describe())} | "
            f"{_cell(s.why)} |"
            for s in SETTINGS
            if s.group == group
        ]
        parts.append("")
    return "\n".join(parts)


def with_settings_reference(text: str) -> str:
    """text (docs/defaults.md) with what lies between DOCS_BEGIN and DOCS_END replaced by `settings_reference()`;
    a ConfigError where the markers are missing."""
    begin, end = text.find(DOCS_BEGIN), text.find(DOCS_END)
    if begin < 0 or end < begin:
        raise ConfigError(f"the settings reference's markers ({DOCS_BEGIN} ... {DOCS_END}) are missing")
    return f"{text[:begin]}{DOCS_BEGIN}\n\n{settings_reference()}\n{text[end:]}"


def _nerf_needs_three(c) -> bool:
    """NeRF's resampling (sampling.nerf_resample) needs at least 3 coarse samples a ray."""
    return c.sampling.hierarchical != "nerf" or min(c.sampling.coarse_stages) >= 3


def _unit_quaternion(values) -> bool:
    return not values or abs(math.sqrt(sum(float(q) ** 2 for q in values[3:])) - 1.0) <= 1e-3  # ground_truth


def _loop_fits(s) -> bool:
    """The loop route stays inside its courtyard: its radius wobbles by PATH_WOBBLE (synthetic.scene)."""
    return s.route != "loop" or s.trajectory_radius_m * (1 + PATH_WOBBLE) < s.scene_size_m / 2 - 1.0


# What fields accept together: (the field named, what it accepts, the test on the config).
RELATIONS = (
    ("data.max_range_m", "more than data.min_range_m", lambda c: c.data.max_range_m > c.data.min_range_m),
    (
        "data.root",
        "a folder (data.format is not synthetic)",
        lambda c: bool(c.data.root) or c.data.format.lower() == "synthetic",
    ),
    (
        "data.initial_poses",
        f"'' or {KISS_ICP} (a pose file's name only with data.format=lio_keyframes)",
        lambda c: c.data.initial_poses in ("", KISS_ICP) or c.data.format.lower() == "lio_keyframes",
    ),
    (
        "data.scans_in_world_frame",
        f"False with data.initial_poses={KISS_ICP} (it needs the layout's own poses)",
        lambda c: not c.data.scans_in_world_frame or c.data.initial_poses != KISS_ICP,
    ),
    (
        "data.invert_poses",
        f"False with data.initial_poses={KISS_ICP} (it needs the layout's own poses)",
        lambda c: not c.data.invert_poses or c.data.initial_poses != KISS_ICP,
    ),
    (
        "data.scan_frame",
        "'' or a published frame of data.format (fusionportable: body_imu | ouster00; newer_college: "
        "os_sensor | os_imu)",
        lambda c: c.data.scan_frame in ("",) + SCAN_FRAMES.get(c.data.format.lower(), ()),
    ),
    (
        "data.gt_from_scan",
        "() or (tx, ty, tz, qx, qy, qz, qw) with a unit quaternion",
        lambda c: _unit_quaternion(c.data.gt_from_scan),
    ),
    (
        "data.synthetic.trajectory_radius_m",
        f"a loop inside the courtyard ({1 + PATH_WOBBLE:g} x the radius < data.synthetic.scene_size_m / 2 - 1)",
        lambda c: _loop_fits(c.data.synthetic),
    ),
    (
        "data.synthetic.route_length_m",
        "at least 100 with data.synthetic.route=courtyards",
        lambda c: c.data.synthetic.route != "courtyards" or c.data.synthetic.route_length_m >= 100,
    ),
    (
        "model.skip_layers",
        "hidden layers below model.depth",
        lambda c: all(k < c.model.depth for k in c.model.skip_layers),
    ),
    ("sampling.z_up_m", "more than sampling.z_low_m", lambda c: c.sampling.z_up_m > c.sampling.z_low_m),
    (
        "sampling.fine_stages",
        "as many stages as sampling.coarse_stages",
        lambda c: len(c.sampling.fine_stages) == len(c.sampling.coarse_stages),
    ),
    ("sampling.coarse_stages", "at least 3 samples a stage with sampling.hierarchical=nerf", _nerf_needs_three),
    (
        "mapping.num_coarse",
        "at least 3 with sampling.hierarchical=nerf",
        lambda c: c.sampling.hierarchical != "nerf" or c.mapping.num_coarse >= 3,
    ),
    (
        "submaps.overlap",
        "fewer than submaps.keyframes (when that is set)",
        lambda c: c.submaps.keyframes <= 0 or c.submaps.overlap < c.submaps.keyframes,
    ),
    (
        "train.fixed_scans",
        "keyframes below data.max_scans (when that is set)",
        lambda c: c.data.max_scans <= 0 or all(-c.data.max_scans <= s < c.data.max_scans for s in c.train.fixed_scans),
    ),
)


def leaves(c: ml_collections.ConfigDict, prefix: str = "") -> dict:
    """{dotted field name: value} of every setting of c."""
    out = {}
    for key, value in c.items():
        if isinstance(value, ml_collections.ConfigDict):
            out.update(leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def validate(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """c, once every field has a value its RULES entry accepts and every RELATIONS test holds; else a ConfigError
    of one line naming the first bad field, its value and what it accepts. An unknown field is an error too."""
    values = leaves(c)
    missing = sorted(set(RULES) - set(values))
    if missing:
        raise ConfigError(f"the config lacks the field(s) {', '.join(missing)}: build it from config.defaults()")
    for path, value in values.items():
        rule = RULES.get(path)
        if rule is None:
            raise ConfigError(f"{path} = {value!r}: the config has no such field (docs/defaults.md lists them)")
        if not rule.accepts(value):
            raise ConfigError(f"{path} = {value!r}: expected {rule.describe()}")
    for path, accepted, holds in RELATIONS:
        if not holds(c):
            raise ConfigError(f"{path} = {values[path]!r}: expected {accepted}")
    return c


def with_budget(c: ml_collections.ConfigDict, budget: str) -> ml_collections.ConfigDict:
    """Size the model, batch, steps and time for a budget ("" = `default_budget()`): paper leaves the defaults;
    cpu: within 10 minutes on 2 CPU cores (max_minutes = 9.5: the run's clock fits the schedule to it); gpu: the cpu
    recipe for 30k steps with the paper's map."""
    budget = (budget or default_budget()).strip().lower()
    if budget not in BUDGETS:
        raise ConfigError(f"unknown budget {budget!r} in the config string; choose one of {', '.join(BUDGETS)}")
    c.budget = budget
    if budget == "paper":
        return c
    c.model.update(width=128, depth=4, skip_layers=(2,), pos_freqs=10, dir_freqs=2)
    c.data.max_rays_per_scan = 8192
    c.sampling.update(coarse_stages=(32,), fine_stages=(16,), guided_samples=16)
    c.train.update(
        steps=1500,
        batch_rays=512,
        field_lr_init=5e-3,
        field_lr_final=5e-4,
        c2f_end_fraction=0.5,
        pose_lr_rot_init=1e-3,
        pose_lr_rot_final=1e-5,
        pose_lr_trans_init=1e-3,
        pose_lr_trans_final=1e-5,
        fixed_scans=(),
        checkpoint_every=500,
        log_every=25,
    )
    c.max_minutes = 9.5
    c.mapping.update(
        num_coarse=64, num_fine=64, max_rays_per_scan=2048, max_rays=262_144, voxel_size_m=0.1, max_seconds=60.0
    )
    c.submaps.update(max_submaps=32, width=64, step_rays_factor=3.0)
    c.data.synthetic.gt_map_points = 100_000
    if budget == "gpu":
        paper = defaults()
        c.train.update(steps=30_000, log_every=500, checkpoint_every=5000)
        c.submaps.update(max_submaps=0, width=paper.submaps.width, step_rays_factor=paper.submaps.step_rays_factor)
        c.mapping.update(paper.mapping)
    return c


def synthetic(budget: str = "") -> ml_collections.ConfigDict:
    """The generated demo sequence: data.format="synthetic", every generated scan a keyframe."""
    c = with_budget(defaults(), budget)
    c.data.format = "synthetic"
    c.data.keyframe_interval_s = 0.0  # the generator spaces its scans as keyframes
    return c


def recording(budget: str = "") -> ml_collections.ConfigDict:
    """A recorded sequence, whatever its layout: on the cpu and gpu budgets the recipe for real recordings
    (small pose steps, points within 40 m, the crisper start; on the cpu budget a heavier termination loss and a
    faster field in one cube); the paper budget is the paper's."""
    c = with_budget(defaults(), budget)
    if c.budget == "paper":
        return c
    c.train.update(
        pose_lr_rot_init=REFINE_POSE_LR[0],
        pose_lr_rot_final=REFINE_POSE_LR[1],
        pose_lr_trans_init=REFINE_POSE_LR[0],
        pose_lr_trans_final=REFINE_POSE_LR[1],
    )
    c.data.max_range_m = 40.0
    c.start.poses = "crisper"
    if c.budget == "cpu":
        c.loss.lambda_termination = 3.0
        c.train.update(field_lr_init=2e-2, field_lr_final=2e-3)
        c.submaps.update(lambda_termination=1.0, field_lr_from_steps=(6000, 0.25))
    return c


def default_budget() -> str:
    """The budget of a config string that names none: "gpu" where JAX's default backend is a GPU, else "cpu" (the
    paper's schedule is asked for by name: it would take weeks on a CPU)."""
    import jax  # here: importing the config does not start a backend

    return "gpu" if jax.default_backend() == "gpu" else "cpu"


# One training step of the paper's size (width 512, depth 8, 1024 rays x (64 + 32) samples at the last stage) on 2
# CPU cores: 6.5 s (benchmarks/RESULTS.md, "The paper's sizes on 2 cores": benchmarks/train_step.py --preset=paper
# --stage=2, Xeon, 2026-12-08; results/train_step_paper_cpu.json).
PAPER_CPU_STEP_S, PAPER_CPU_CORES = 6.5, 2
SLOW_RUN_HOURS = 1.0  # a CPU run without a time limit estimated longer than this is warned about


def cpu_training_hours(c: ml_collections.ConfigDict, cores: int | None = None) -> float:
    """About how long c's training takes on `cores` CPU cores (None: this machine's): the paper-size step's
    measured time scaled by the MLP work of a step (rays x samples x width^2 x depth, at the last sample stage) and
    by the cores, times train.steps. A lower bound for small models, whose step has overheads besides the MLP."""

    def work(rays, samples, width, depth):
        return rays * samples * width * width * depth

    s = c.sampling
    samples = s.coarse_stages[-1] + s.fine_stages[-1] + s.guided_samples
    ratio = work(c.train.batch_rays, samples, c.model.width, c.model.depth) / work(1024, 64 + 32, 512, 8)
    cores = cores or os.cpu_count() or PAPER_CPU_CORES
    return c.train.steps * PAPER_CPU_STEP_S * ratio * PAPER_CPU_CORES / cores / 3600.0


def slow_run_warning(c: ml_collections.ConfigDict, backend: str = "", cores: int | None = None) -> str:
    """A warning line when training c on `backend` ("cpu", "gpu"; "": JAX's default) without a time limit
    (max_minutes = 0) would take longer than SLOW_RUN_HOURS on a CPU (cpu_training_hours); "" otherwise."""
    if not backend:
        import jax  # here: importing the config does not start a backend

        backend = jax.default_backend()
    if backend != "cpu" or c.max_minutes > 0:
        return ""
    hours = cpu_training_hours(c, cores)
    if hours <= SLOW_RUN_HOURS:
        return ""
    took = f"{hours / 24:.0f} days" if hours >= 48 else f"{hours:.1f} hours"
    cpu_budget = "" if c.budget == "cpu" else "; the cpu budget (:cpu, the default on a CPU) ends within 10 minutes"
    return (
        f"the {c.budget} budget trains {c.train.steps} steps of a field {c.model.width} wide and {c.model.depth} "
        f"deep with no time limit (max_minutes=0): about {took} on this CPU's {cores or os.cpu_count()} cores"
        f"{cpu_budget}; --config.max_minutes=M fits the schedule to M minutes"
    )


def from_file(path: str, argument: str = "") -> ml_collections.ConfigDict:
    """The config of a configs/*.py file, as `--config=PATH[:ARGUMENT]` gives it (for benchmarks and notebooks)."""
    if ":" in os.path.basename(path) and not argument:
        path, argument = path.rsplit(":", 1)
    if not os.path.isfile(path):
        raise ConfigError(f"{path}: no such config file")
    spec = importlib.util.spec_from_file_location(f"neld_config_{os.path.basename(path)[:-3]}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.get_config(argument) if argument else module.get_config()


def apply_overrides(c: ml_collections.ConfigDict, items) -> ml_collections.ConfigDict:
    """Apply "KEY=VALUE" overrides (dotted keys, Python-literal values), as the benchmarks' --set flags give them.
    An unknown key is a ConfigError naming it, as bin/train.py's --config.KEY is."""
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"override {item!r}: expected KEY=VALUE")
        node = c
        *parents, leaf = key.split(".")
        try:
            for part in parents:
                node = node[part]
            if leaf not in node:
                raise KeyError(leaf)
        except KeyError:
            raise ConfigError(f"override {item!r}: the config has no field {key}") from None
        try:
            node[leaf] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            node[leaf] = value  # a bare string, e.g. start.poses=baseline
    return c


def count_fields(c: ml_collections.ConfigDict) -> int:
    """How many settings (leaves) a config holds."""
    return sum(count_fields(v) if isinstance(v, ml_collections.ConfigDict) else 1 for v in c.values())


def main(argv=None) -> int:
    """`python -m neld_jax.config --docs [PATH]`: rewrite the settings reference in docs/defaults.md (or PATH)."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m neld_jax.config", description=main.__doc__)
    parser.add_argument(
        "--docs",
        nargs="?",
        const=DOCS_PATH,
        default="",
        metavar="PATH",
        help="rewrite the generated settings reference of this file (default: docs/defaults.md)",
    )
    args = parser.parse_args(argv)
    if not args.docs:
        parser.print_help()
        return 2
    with open(args.docs) as f:
        text = f.read()
    with open(args.docs, "w") as f:
        f.write(with_settings_reference(text))
    print(f"wrote the settings reference of {args.docs}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
