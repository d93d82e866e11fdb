"""Every setting of a run, its default, and the named presets over them.

`defaults()` is the paper's configuration, one line of comment per field. A run is one of two recipes at one of
three budgets (docs/defaults.md says why each value is what it is):

- budgets: "paper" (the defaults as they are: 160k steps), "cpu" (about 10 minutes on 2 CPU cores) and "gpu" (the
  cpu recipe trained 20x longer, the paper's map);
- recipes: `synthetic(budget)` for the generated demo sequence, whose odometry drifts far and whose poses move in
  large steps, and `recording(budget)` for every recorded sequence whatever layout it arrives in: on the cpu and
  gpu budgets small pose steps, points within 40 m, and training starts from the crisper of the input and the
  classical baseline (start.poses="crisper").

The files in configs/ only say how to read a layout: `get_config(budget)` picks the recipe, then sets data.format
and what the layout needs. Every field can be overridden on the command line (`--config.train.steps=2000`).
Distances are metres (`*_m`); the trainer converts them with the normalisation's scale.
"""

from __future__ import annotations

import ast
import importlib.util
import os

import ml_collections

from neld_jax.data.synthetic import synthetic_defaults
from neld_jax.errors import ConfigError

BUDGETS = ("paper", "gpu", "cpu")
# (init, final) pose learning rates of poses that are already good: a recording's odometry, the baseline's poses
REFINE_POSE_LR = (5e-6, 2.5e-7)


def defaults() -> ml_collections.ConfigDict:
    """The paper's configuration (the "paper" budget)."""
    c = ml_collections.ConfigDict()
    c.output_dir = "outputs/run"  # where the run writes (a rerun resumes from its checkpoints)
    c.seed = 0  # the field's initialisation, the rays drawn, the batches
    c.budget = "paper"  # the budget the preset applied (paper | gpu | cpu); a record, not read by the run
    c.max_minutes = 0.0  # the whole run's wall-clock budget (neld_jax.budget); 0: none

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
    c.data.voxel_size_m = 0.05  # each keyframe's points on this grid
    c.data.first_scan = 0  # keyframes from this input scan on ...
    c.data.max_scans = 0  # ... and at most this many (0: all): a long sequence in pieces
    c.data.max_rays_per_scan = 0  # training rays per keyframe, a random subset (0: every point)
    c.data.timestamp_tol_s = 0.05  # scans and poses match by time within this
    c.data.gt_poses_path = ""  # ground-truth trajectory (TUM, or Newer College .csv) in place of the layout's
    c.data.gt_map_path = ""  # ground-truth map (.pcd / .ply) in place of the layout's
    c.data.gt_from_scan = ()  # the scan frame's pose in the ground truth's body frame (tx ty tz qx qy qz qw)
    c.data.scan_frame = ""  # which published extrinsic: fusionportable body_imu | ouster00; newer_college os_sensor | os_imu
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

    # Where training starts (neld_jax.start): the input, the classical baseline's poses, or the crisper of the two.
    c.start = ml_collections.ConfigDict()
    c.start.poses = "input"  # input | baseline | crisper
    c.start.pose_lr_from_baseline = REFINE_POSE_LR  # from the baseline: pose learning rates at most these
    c.start.prior_from_baseline = 3000.0  # ... and a pull of each pose toward its start (0: none)
    c.start.thin_map_m = 0.02  # ... heavier on the translations where the start's map is thinner than this

    # Submaps (neld_jax.submaps): a sequence larger than one cube is split into overlapping windows of keyframes.
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

    # Rerun (neld_jax.viewer): the run's trajectories, maps and training, to look at in Rerun's viewer.
    c.viz = ml_collections.ConfigDict()
    c.viz.record = True  # write run.rrd in the output folder
    c.viz.live = False  # also serve the run on 127.0.0.1:9876 while it trains (`rerun rerun+http://...`)
    return c


def with_budget(c: ml_collections.ConfigDict, budget: str) -> ml_collections.ConfigDict:
    """Size the model, batch, steps and time for a budget ("" = `default_budget()`): paper leaves the defaults;
    cpu: about 10 minutes on 2 CPU cores for ~24 keyframes; gpu: the cpu recipe for 30k steps with the paper's map."""
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
    c = with_budget(defaults(), budget or default_budget("cpu"))
    c.data.format = "synthetic"
    c.data.keyframe_interval_s = 0.0  # the generator spaces its scans as keyframes
    return c


def recording(budget: str = "") -> ml_collections.ConfigDict:
    """A recorded sequence, whatever its layout: on the cpu and gpu budgets the recipe for real recordings
    (small pose steps, points within 40 m, the crisper start; on the cpu budget a heavier termination loss and a
    faster field in one cube); the paper budget is the paper's."""
    c = with_budget(defaults(), budget or default_budget("paper"))
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


def default_budget(cpu_default: str = "paper") -> str:
    """The budget of a config string that names none: "gpu" where JAX's default backend is a GPU, else
    `cpu_default`."""
    import jax  # here: importing the config does not start a backend

    return "gpu" if jax.default_backend() == "gpu" else cpu_default


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
