"""Every setting of a run, its default, and the named presets over them.

`defaults()` is the paper's configuration, one line of comment per field. A run is one of two recipes at one of
three budgets (docs/defaults.md says why each value is what it is):

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

`RULES` says what each field accepts (its type, range or choices) and `RELATIONS` what fields accept together;
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

from neld_jax.errors import ConfigError
from neld_jax.synthetic.generator import synthetic_defaults

BUDGETS = ("paper", "gpu", "cpu")
# (init, final) pose learning rates of poses that are already good: a recording's odometry, the baseline's poses
REFINE_POSE_LR = (5e-6, 2.5e-7)


def defaults() -> ml_collections.ConfigDict:
    """The paper's configuration (the "paper" budget)."""
    c = ml_collections.ConfigDict()
    c.output_dir = "outputs/run"  # where the run writes (a rerun resumes from its checkpoints)
    c.seed = 0  # the field's initialisation, the rays drawn, the batches
    c.budget = "paper"  # the budget the preset applied (paper | gpu | cpu); a record, not read by the run
    c.max_minutes = 0.0  # the whole run's wall-clock budget (neld_jax.training.budget); 0: none

    c.data = ml_collections.ConfigDict()
    c.data.format = "generic"  # one of neld_jax.data.FORMATS
    c.data.root = ""  # the sequence's folder
    c.data.initial_poses = ""  # "": the layout's poses; kiss_icp: KISS-ICP from the scans; lio_keyframes: a file
    c.data.drop_unmatched_tail = False  # drop up to 5 trailing scans without a pose or stamp instead of failing
    c.data.scans_in_world_frame = False  # the scans are registered already: move them into their sensors' frames
    c.data.invert_poses = False  # the poses file holds world -> sensor transforms
    c.data.keyframe_interval_s = 3.0  # keyframes at most this many seconds apart (<= 0: cap off) ...
    c.data.keyframe_distance_m = 0.0  # ... this far apart (0: a tenth of max_range_m with the time cap, else off) ...
    c.data.keyframe_angle_deg = 0.0  # ... and turned this far (0: 30 with the time cap, else off; all off: every scan)
    c.data.min_range_m = 0.5  # points nearer the sensor are dropped
    c.data.max_range_m = 80.0  # points further away are dropped
    c.data.deskew = "auto"  # scans without point times: auto (measured) | deskewed | raw | raw_<start>_<turning>
    c.data.voxel_size_m = 0.05  # each keyframe's points on this grid
    c.data.first_scan = 0  # keyframes from this input scan on ...
    c.data.max_scans = 0  # ... and at most this many (0: all): a long sequence in pieces
    c.data.max_rays_per_scan = 0  # training rays per keyframe, a random subset (0: every point)
    c.data.timestamp_tol_s = 0.05  # scans and poses match by time within this
    c.data.gt_poses_path = ""  # ground-truth trajectory (TUM, or Newer College .csv) in place of the layout's
    c.data.gt_map_path = ""  # ground-truth map (.pcd / .ply) in place of the layout's
    c.data.gt_from_scan = ()  # the scan frame's pose in the ground truth's body frame (tx ty tz qx qy qz qw)
    c.data.scan_frame = ""  # published extrinsic: fusionportable body_imu | ouster00; newer_college os_sensor | os_imu
    c.data.gt_time_offset_s = 0.0  # added to the scan stamps when matching ground truth
    c.data.synthetic = synthetic_defaults()  # the generated sequence (data.format="synthetic")

    c.model = ml_collections.ConfigDict()
    c.model.width = 512  # hidden layer width
    c.model.depth = 8  # hidden layers
    c.model.skip_layers = (4,)  # hidden layers that get the encoded position again
    c.model.pos_freqs = 15  # L of the position encoding
    c.model.dir_freqs = 4  # L of the view direction's encoding
    c.model.surrogate_gradient = True  # eq. 9 (ablation: False)
    c.model.matmul_dtype = "float32"  # float32 | bfloat16 (the hidden matmuls' inputs; parameters stay float32)

    c.sampling = ml_collections.ConfigDict()
    c.sampling.z_low_m = 0.3  # eq. 7's lower bound
    c.sampling.z_up_m = 200.0  # eq. 7's upper bound (beyond the cube: the cube bound decides)
    c.sampling.cube_bound = True  # samples only inside [-1, 1]^3 (ablation: False)
    c.sampling.hierarchical = "before"  # before (NeLD-BA) | nerf (ablation) | none (ablation)
    c.sampling.coarse_stages = (32, 48, 64)  # coarse samples per ray, one stage each (ramp over train.c2f_end_fraction)
    c.sampling.fine_stages = (16, 24, 32)  # fine samples per ray, one stage each
    c.sampling.guided_samples = 0  # coarse samples within 1 m of the measured range (0: the paper)

    c.loss = ml_collections.ConfigDict()
    c.loss.lambda_coarse = 0.1  # eq. 13
    c.loss.lambda_range = 1.0  # eq. 13
    c.loss.lambda_termination = 1.0  # eq. 13 (ablation: 0)

    c.train = ml_collections.ConfigDict()
    c.train.steps = 160_000  # optimiser steps
    c.train.batch_rays = 1024  # rays a step (over every submap)
    c.train.field_lr_init = 5e-5  # the field's Adam learning rate, decaying exponentially ...
    c.train.field_lr_final = 2e-5  # ... to this
    c.train.pose_lr_rot_init = 5e-5  # the poses' rotation learning rate ...
    c.train.pose_lr_rot_final = 2e-5  # ... decaying to this
    c.train.pose_lr_trans_init = 5e-5  # ... and translation learning rate
    c.train.pose_lr_trans_final = 2e-5  # ... decaying to this
    c.train.c2f_end_fraction = 0.75  # coarse-to-fine: every frequency active after this fraction of the steps
    c.train.pose_start_freq = 6  # k*: the poses move once this frequency is active
    c.train.fixed_scans = (0,)  # scans that never move (the gauge; (): every pose free, anchored on scan 0 after)
    c.train.checkpoint_every = 5000  # steps
    c.train.log_every = 100  # steps a device call runs (the log, the progress bar and the clock move in these)

    # Where training starts (neld_jax.steps.start): the input, the classical baseline's poses, or the crisper of the two.
    c.start = ml_collections.ConfigDict()
    c.start.poses = "input"  # input | baseline | crisper
    c.start.pose_lr_from_baseline = REFINE_POSE_LR  # from the baseline: pose learning rates at most these
    c.start.prior_from_baseline = 3000.0  # ... and a pull of each pose toward its start (0: none)

    # Submaps (neld_jax.training.submaps): a sequence larger than one cube is split into overlapping windows of keyframes.
    # The settings marked (M > 1) apply to a plan of several submaps only; one cube keeps the run's own.
    c.submaps = ml_collections.ConfigDict()
    c.submaps.enabled = "auto"  # auto (when one cube's finest detail exceeds max_detail_m) | on | off
    c.submaps.max_detail_m = 0.25  # the finest Fourier period one cube may have
    c.submaps.keyframes = 0  # keyframes a submap (0: the most whose cube keeps max_detail_m)
    c.submaps.overlap = 2  # keyframes neighbouring submaps share
    c.submaps.closure_radius_m = 10.0  # a revisit within this distance gets a submap of both visits (0: none)
    c.submaps.max_submaps = 0  # at most this many submaps (longer windows, coarser cubes; 0: no limit)
    c.submaps.width = 0  # (M > 1) each submap's field width (0: model.width)
    c.submaps.step_rays_factor = 1.0  # (M > 1) a step's rays over every submap, in units of train.batch_rays
    c.submaps.lambda_termination = 0.0  # (M > 1) the termination loss's weight (0: loss.lambda_termination)
    c.submaps.field_lr_from_steps = ()  # (M > 1) (N, f): a plan of N steps or more trains the fields at f x the rate

    c.mapping = ml_collections.ConfigDict()
    c.mapping.enabled = True  # render map_rendered.ply
    c.mapping.num_coarse = 128  # samples per ray of the rendered map (eq. 14)
    c.mapping.num_fine = 128  # ... coarse and fine
    c.mapping.max_rays_per_scan = 0  # rays per keyframe (0: every ray) ...
    c.mapping.max_rays = 0  # ... and over the sequence (0: no limit; each keyframe an equal share, >= 256)
    c.mapping.voxel_size_m = 0.05  # the written maps' grid (0: none)
    c.mapping.min_opacity = 0.5  # rays less opaque than this end nowhere
    c.mapping.max_seconds = 0.0  # the render's share of max_minutes (0: no limit)

    # The classical baseline (neld_jax.baseline): scan-to-map ICP, a loop-closed pose graph, multi-view refinement.
    c.baseline = ml_collections.ConfigDict()
    c.baseline.voxel_size_m = 0.1  # the scans' grid for ICP
    c.baseline.loop_radius_m = 10.0  # loop-closure candidates within this distance
    c.baseline.global_loops_per_scan = 1  # FPFH + RANSAC closures where ICP cannot reach (0: none)
    c.baseline.map_rounds = 2  # rounds of multi-view refinement (0: none)

    c.eval = ml_collections.ConfigDict()
    c.eval.map_icp_m = 0.0  # > 0: refine the ground-truth map's alignment by ICP at this distance
    c.eval.crispness_radius_m = 0.3  # the raw map's crispness: neighbourhood radius ...
    c.eval.crispness_queries = 10_000  # ... and query points
    c.eval.crispness_draws = 5  # draws of the query points that say how sure a comparison is (< 2: none)

    # Rerun (neld_jax.writing.viewer): the run's trajectories, maps and training, to look at in Rerun's viewer.
    c.viz = ml_collections.ConfigDict()
    c.viz.record = True  # write run.rrd in the output folder
    c.viz.live = False  # also serve the run on 127.0.0.1:9876 while it trains (`rerun rerun+http://...`)
    return c


# ---------------------------------------------------------------------------------------------------------------
# What each field accepts. Choices repeat the constants of the modules that read them (tests/test_config.py checks
# that they agree): the config imports neither the loaders (Open3D) nor the model (Flax).
# ---------------------------------------------------------------------------------------------------------------

# neld_jax.steps.inputs.FORMATS
FORMATS = ("generic", "fusionportable", "newer_college", "lio_keyframes", "hba", "kitti", "synthetic")
START_POSES = ("input", "baseline", "crisper")  # neld_jax.steps.start.CHOICES
# data.scan_frame: the published frames of each format's ground truth (data.ground_truth.PUBLISHED_GT_FROM_SCAN)
SCAN_FRAMES = {"fusionportable": ("body_imu", "ouster00"), "newer_college": ("os_sensor", "os_imu")}
KISS_ICP = "kiss_icp"  # data.initial_poses that makes the poses from the scans (data.formats.KISS_ICP)


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
                self._accepts_one(v, self.kind[:-1]) for v in value)
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


def _integer(low=None, high=None) -> Rule:
    return Rule("int", low, high)


def _number(low=None, high=None, above=False) -> Rule:
    return Rule("float", low, high, above)


def _choice(*choices: str, any_case=False) -> Rule:
    return Rule("str", choices=choices, any_case=any_case)


FLAG, TEXT, POSITIVE, NON_NEGATIVE = Rule("bool"), Rule("str"), _number(0, above=True), _number(0)
COUNT, AT_LEAST_ONE = _integer(0), _integer(1)

RULES = {
    "output_dir": TEXT,
    "seed": COUNT,
    "budget": _choice(*BUDGETS, any_case=True),
    "max_minutes": NON_NEGATIVE,
    "data.format": _choice(*FORMATS, any_case=True),
    "data.root": TEXT,
    "data.initial_poses": TEXT,
    "data.drop_unmatched_tail": FLAG,
    "data.scans_in_world_frame": FLAG,
    "data.invert_poses": FLAG,
    "data.keyframe_interval_s": _number(),
    "data.keyframe_distance_m": _number(),
    "data.keyframe_angle_deg": _number(),
    "data.min_range_m": NON_NEGATIVE,
    "data.max_range_m": POSITIVE,
    "data.deskew": _choice("auto", "deskewed", "raw", "raw_behind_clockwise", "raw_behind_anticlockwise",
                           "raw_front_clockwise", "raw_front_anticlockwise",
                           any_case=True),  # sweep_times.DESKEW_CHOICES
    "data.voxel_size_m": NON_NEGATIVE,
    "data.first_scan": COUNT,
    "data.max_scans": COUNT,
    "data.max_rays_per_scan": COUNT,
    "data.timestamp_tol_s": NON_NEGATIVE,
    "data.gt_poses_path": TEXT,
    "data.gt_map_path": TEXT,
    "data.gt_from_scan": Rule("floats", lengths=(0, 7)),
    "data.scan_frame": _choice("", *sorted({f for frames in SCAN_FRAMES.values() for f in frames})),
    "data.gt_time_offset_s": _number(),
    "data.synthetic.seed": COUNT,
    "data.synthetic.route": _choice("loop", "courtyards"),
    "data.synthetic.route_length_m": POSITIVE,
    "data.synthetic.num_scans": AT_LEAST_ONE,
    "data.synthetic.scene_size_m": POSITIVE,
    "data.synthetic.trajectory_radius_m": POSITIVE,
    "data.synthetic.num_beams": AT_LEAST_ONE,
    "data.synthetic.num_columns": AT_LEAST_ONE,
    "data.synthetic.max_range_m": _number(0.5, above=True),  # data.synthetic.MIN_RANGE_M
    "data.synthetic.range_noise_m": NON_NEGATIVE,
    "data.synthetic.drift_trans_m": NON_NEGATIVE,
    "data.synthetic.drift_rot_deg": NON_NEGATIVE,
    "data.synthetic.gt_map_points": COUNT,
    "model.width": _integer(2),  # the density head is width // 2 wide
    "model.depth": AT_LEAST_ONE,
    "model.skip_layers": Rule("ints", low=0),
    "model.pos_freqs": AT_LEAST_ONE,
    "model.dir_freqs": COUNT,
    "model.surrogate_gradient": FLAG,
    "model.matmul_dtype": _choice("float32", "bfloat16"),  # field.MATMUL_DTYPES
    "sampling.z_low_m": POSITIVE,
    "sampling.z_up_m": POSITIVE,
    "sampling.cube_bound": FLAG,
    "sampling.hierarchical": _choice("before", "nerf", "none"),  # model.render_rays
    "sampling.coarse_stages": Rule("ints", low=1, nonempty=True),
    "sampling.fine_stages": Rule("ints", low=0, nonempty=True),
    "sampling.guided_samples": COUNT,
    "loss.lambda_coarse": NON_NEGATIVE,
    "loss.lambda_range": NON_NEGATIVE,
    "loss.lambda_termination": NON_NEGATIVE,
    "train.steps": AT_LEAST_ONE,
    "train.batch_rays": AT_LEAST_ONE,
    "train.field_lr_init": NON_NEGATIVE,
    "train.field_lr_final": NON_NEGATIVE,
    "train.pose_lr_rot_init": NON_NEGATIVE,
    "train.pose_lr_rot_final": NON_NEGATIVE,
    "train.pose_lr_trans_init": NON_NEGATIVE,
    "train.pose_lr_trans_final": NON_NEGATIVE,
    "train.c2f_end_fraction": _number(0, 1),
    "train.pose_start_freq": COUNT,
    "train.fixed_scans": Rule("ints"),  # negative: from the last keyframe back (train.fixed_rows)
    "train.checkpoint_every": AT_LEAST_ONE,
    "train.log_every": AT_LEAST_ONE,
    "start.poses": _choice(*START_POSES, any_case=True),
    "start.pose_lr_from_baseline": Rule("floats", low=0, lengths=(0, 2)),
    "start.prior_from_baseline": NON_NEGATIVE,
    "submaps.enabled": _choice("auto", "on", "off", "true", "false", "1", "0", any_case=True),  # submaps_wanted
    "submaps.max_detail_m": POSITIVE,
    "submaps.keyframes": COUNT,
    "submaps.overlap": COUNT,
    "submaps.closure_radius_m": NON_NEGATIVE,
    "submaps.max_submaps": COUNT,
    "submaps.width": COUNT,
    "submaps.step_rays_factor": POSITIVE,
    "submaps.lambda_termination": NON_NEGATIVE,
    "submaps.field_lr_from_steps": Rule("floats", low=0, above=True, lengths=(0, 2)),
    "mapping.enabled": FLAG,
    "mapping.num_coarse": AT_LEAST_ONE,
    "mapping.num_fine": COUNT,
    "mapping.max_rays_per_scan": COUNT,
    "mapping.max_rays": COUNT,
    "mapping.voxel_size_m": NON_NEGATIVE,
    "mapping.min_opacity": _number(0, 1),
    "mapping.max_seconds": NON_NEGATIVE,
    "baseline.voxel_size_m": NON_NEGATIVE,
    "baseline.loop_radius_m": NON_NEGATIVE,
    "baseline.global_loops_per_scan": COUNT,
    "baseline.map_rounds": COUNT,
    "eval.map_icp_m": NON_NEGATIVE,
    "eval.crispness_radius_m": POSITIVE,
    "eval.crispness_queries": AT_LEAST_ONE,
    "eval.crispness_draws": COUNT,
    "viz.record": FLAG,
    "viz.live": FLAG,
}


def _nerf_needs_three(c) -> bool:
    """NeRF's resampling (sampling.nerf_resample) needs at least 3 coarse samples a ray."""
    return c.sampling.hierarchical != "nerf" or min(c.sampling.coarse_stages) >= 3


def _unit_quaternion(values) -> bool:
    return not values or abs(math.sqrt(sum(float(q) ** 2 for q in values[3:])) - 1.0) <= 1e-3  # ground_truth


def _loop_fits(s) -> bool:
    """The loop route stays inside its courtyard (data.synthetic.PATH_WOBBLE = 0.08)."""
    return s.route != "loop" or s.trajectory_radius_m * 1.08 < s.scene_size_m / 2 - 1.0


# What fields accept together: (the field named, what it accepts, the test on the config).
RELATIONS = (
    ("data.max_range_m", "more than data.min_range_m", lambda c: c.data.max_range_m > c.data.min_range_m),
    ("data.root", "a folder (data.format is not synthetic)", lambda c: bool(c.data.root) or
     c.data.format.lower() == "synthetic"),
    ("data.initial_poses", f"'' or {KISS_ICP} (a pose file's name only with data.format=lio_keyframes)",
     lambda c: c.data.initial_poses in ("", KISS_ICP) or c.data.format.lower() == "lio_keyframes"),
    ("data.scans_in_world_frame", f"False with data.initial_poses={KISS_ICP} (it needs the layout's own poses)",
     lambda c: not c.data.scans_in_world_frame or c.data.initial_poses != KISS_ICP),
    ("data.invert_poses", f"False with data.initial_poses={KISS_ICP} (it needs the layout's own poses)",
     lambda c: not c.data.invert_poses or c.data.initial_poses != KISS_ICP),
    ("data.scan_frame", "'' or a published frame of data.format (fusionportable: body_imu | ouster00; newer_college: "
     "os_sensor | os_imu)", lambda c: c.data.scan_frame in ("",) + SCAN_FRAMES.get(c.data.format.lower(), ())),
    ("data.gt_from_scan", "() or (tx, ty, tz, qx, qy, qz, qw) with a unit quaternion",
     lambda c: _unit_quaternion(c.data.gt_from_scan)),
    ("data.synthetic.trajectory_radius_m", "a loop inside the courtyard (1.08 x the radius < "
     "data.synthetic.scene_size_m / 2 - 1)", lambda c: _loop_fits(c.data.synthetic)),
    ("data.synthetic.route_length_m", "at least 100 with data.synthetic.route=courtyards",
     lambda c: c.data.synthetic.route != "courtyards" or c.data.synthetic.route_length_m >= 100),
    ("model.skip_layers", "hidden layers below model.depth", lambda c: all(k < c.model.depth for k in
                                                                           c.model.skip_layers)),
    ("sampling.z_up_m", "more than sampling.z_low_m", lambda c: c.sampling.z_up_m > c.sampling.z_low_m),
    ("sampling.fine_stages", "as many stages as sampling.coarse_stages",
     lambda c: len(c.sampling.fine_stages) == len(c.sampling.coarse_stages)),
    ("sampling.coarse_stages", "at least 3 samples a stage with sampling.hierarchical=nerf", _nerf_needs_three),
    ("mapping.num_coarse", "at least 3 with sampling.hierarchical=nerf",
     lambda c: c.sampling.hierarchical != "nerf" or c.mapping.num_coarse >= 3),
    ("submaps.overlap", "fewer than submaps.keyframes (when that is set)",
     lambda c: c.submaps.keyframes <= 0 or c.submaps.overlap < c.submaps.keyframes),
    ("train.fixed_scans", "keyframes below data.max_scans (when that is set)",
     lambda c: c.data.max_scans <= 0 or all(-c.data.max_scans <= s < c.data.max_scans for s in c.train.fixed_scans)),
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
    c.train.update(steps=1500, batch_rays=512, field_lr_init=5e-3, field_lr_final=5e-4, c2f_end_fraction=0.5,
                   pose_lr_rot_init=1e-3, pose_lr_rot_final=1e-5, pose_lr_trans_init=1e-3, pose_lr_trans_final=1e-5,
                   fixed_scans=(), checkpoint_every=500, log_every=25)
    c.max_minutes = 9.5
    c.mapping.update(num_coarse=64, num_fine=64, max_rays_per_scan=2048, max_rays=262_144, voxel_size_m=0.1,
                     max_seconds=60.0)
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
    c.train.update(pose_lr_rot_init=REFINE_POSE_LR[0], pose_lr_rot_final=REFINE_POSE_LR[1],
                   pose_lr_trans_init=REFINE_POSE_LR[0], pose_lr_trans_final=REFINE_POSE_LR[1])
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
# CPU cores: 11.8 s (benchmarks/RESULTS.md, "The paper's sizes on 2 cores": benchmarks/train_step.py --preset=paper
# --stage=2, EPYC, 2026-11-27).
PAPER_CPU_STEP_S, PAPER_CPU_CORES = 11.8, 2
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
    return (f"the {c.budget} budget trains {c.train.steps} steps of a field {c.model.width} wide and {c.model.depth} "
            f"deep with no time limit (max_minutes=0): about {took} on this CPU's {cores or os.cpu_count()} cores"
            f"{cpu_budget}; --config.max_minutes=M fits the schedule to M minutes")


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
