"""Default hyper-parameters of NeLD-BA and the compute budgets.

The files in configs/ are thin: each calls `base_config()`, sets its data source and applies a budget with
`apply_budget`. Every field can be overridden on the command line (`--config.train.steps=2000`).

Units: distances that a user sets are in metres (`*_m`); the trainer converts them into the normalised
frame ([-1, 1]^3) with the scale of the fitted normalisation.
"""

from __future__ import annotations

import ml_collections

from neld_jax.data.synthetic import synthetic_defaults
from neld_jax.errors import ConfigError

BUDGETS = ("paper", "gpu", "cpu")
# (init, final) pose learning rates for poses that are already good (refine_odometry; train.pose_lr_from_baseline)
REFINE_POSE_LR = (5e-6, 2.5e-7)


def default_budget(cpu_default: str = "paper") -> str:
    """The budget of a config string that names none: "gpu" where JAX's default backend is a GPU, else
    `cpu_default` (the dataset configs: "paper"; the demo: "cpu"), so nothing changes on a CPU machine.

    The choice is kept in config.budget, which the run logs (the config is parsed before logging is set up).
    """
    import jax  # here, not at the top: the config module stays importable without initialising a backend

    return "gpu" if jax.default_backend() == "gpu" else cpu_default


def base_config() -> ml_collections.ConfigDict:
    """The paper's configuration (a GPU-sized run of 160k steps): the "paper" budget."""
    c = ml_collections.ConfigDict()
    c.output_dir = "outputs/run"
    c.seed = 0
    c.budget = "paper"  # which budget apply_budget applied (paper | gpu | cpu); informational, not hashed

    c.data = ml_collections.ConfigDict()
    c.data.format = "generic"  # generic | fusionportable | newer_college | lio_keyframes | hba | synthetic
    c.data.root = ""
    c.data.pose_file = ""  # lio_keyframes: the initial trajectory under root ("" = odom_poses.txt)
    c.data.drop_unmatched_tail = False  # drop up to 5 trailing scans that have no pose/stamp instead of failing
    # The scans are registered already (world frame, e.g. FAST-LIO2's /cloud_registered): move them into their
    # sensors' frames with the poses. Left False, scans that look registered are refused (neld_jax.data.frames).
    c.data.scans_in_world_frame = False
    # The poses file holds world -> sensor transforms: invert them. Left False, poses that look inverted are refused.
    c.data.invert_poses = False
    # Keyframes: a scan is kept when ANY enabled rule says so (<= 0 turns a rule off; all off keeps every scan).
    # Every input scan still gets a refined pose: the others take their keyframes' interpolated correction.
    c.data.keyframe_interval_s = 3.0
    c.data.keyframe_distance_m = 0.0
    c.data.keyframe_angle_deg = 0.0
    c.data.min_range_m = 0.5
    c.data.max_range_m = 80.0
    c.data.voxel_size_m = 0.05
    c.data.first_scan = 0  # keyframes from this input scan on (with max_scans: run a long sequence in pieces)
    c.data.max_scans = 0  # 0: all keyframes
    c.data.max_extent_m = 1000.0  # larger scenes are refused: one field's resolution falls with the cube's size
    c.data.max_rays_per_scan = 0  # 0: every point of the preprocessed scan is a training ray
    c.data.normalization_margin = 0.9  # largest half-extent of scans+origins maps to this (room for corrections)
    c.data.timestamp_tol_s = 0.05  # scan <-> pose matching by time (datasets.DEFAULT_TIMESTAMP_TOLERANCE_S)
    # Ground truth (neld_jax/data/ground_truth.py): explicit files replace what the layout has; a path that is set but
    # missing is an error. gt_from_scan: the scan frame's pose in the ground truth's body frame, (tx, ty, tz, qx, qy,
    # qz, qw); () = the dataset's published value for scan_frame ("" = the layout's own frame).
    c.data.gt_poses_path = ""  # TUM, or Newer College CSV (.csv)
    c.data.gt_map_path = ""  # .pcd / .ply, in the ground truth's world frame
    c.data.gt_from_scan = ()
    c.data.scan_frame = ""  # fusionportable: body_imu | ouster00; newer_college: os_sensor | os_imu
    c.data.gt_time_offset_s = 0.0  # added to scan stamps when matching GT (e.g. end-of-scan scans, start-of-scan GT)
    c.data.synthetic = synthetic_defaults()

    # Submaps (neld_jax.submaps, docs/method.md "Submaps"): a sequence that outgrows one cube is split into
    # overlapping windows of consecutive keyframes, each with its own cube and field, sharing one pose per keyframe.
    c.submaps = ml_collections.ConfigDict()
    c.submaps.enabled = "auto"  # auto: on when one cube's finest detail would exceed max_detail_m | on | off
    c.submaps.max_detail_m = 0.25  # finest Fourier period (2^(2-L) normalised units) one cube may have, metres
    c.submaps.keyframes = 0  # keyframes per submap; 0: the most whose cube keeps max_detail_m
    c.submaps.overlap = 2  # keyframes shared by neighbouring submaps (their poses tie the submaps together)
    # A revisit (keyframes 2+ windows apart, initial positions within this many metres) gets a submap holding
    # both visits, which ties the two ends of a loop together; 0: off.
    c.submaps.closure_radius_m = 10.0
    # rays per submap per step; 0: train.batch_rays x submaps.step_rays_factor shared among the submaps (>= 8 each)
    c.submaps.batch_rays = 0
    c.submaps.step_rays_factor = 1.0  # the rays of one step over all submaps, in units of train.batch_rays
    c.submaps.width = 0  # the MLP width of each submap's field; 0: model.width
    c.submaps.lambda_termination = 0.0  # the termination loss's weight in a submap run; 0: loss.lambda_termination
    # (N, f): a plan of N steps or more trains the submap fields at f x train.field_lr_*; (): at train.field_lr_*
    c.submaps.field_lr_from_steps = ()
    c.submaps.devices = 0  # devices the submaps are sharded over; 0: every visible device
    # At most this many submaps (0: no limit): a longer sequence gets longer windows, in larger cubes (coarser than
    # max_detail_m; the log says so). Unless submaps.keyframes is set.
    c.submaps.max_submaps = 0

    c.model = ml_collections.ConfigDict()
    c.model.width = 512
    c.model.depth = 8
    c.model.skip_layers = (4,)
    c.model.pos_freqs = 15
    c.model.dir_freqs = 4
    c.model.use_view_dirs = True
    c.model.density_activation = "softplus"
    c.model.surrogate_gradient = True  # ablation: False uses the exact Fourier gradient
    c.model.initial_density = 0.1  # the untrained field's density everywhere, approximately (normalised units)
    # float32 | bfloat16: the hidden layers' matmuls on bfloat16 inputs, float32 parameters and accumulation
    c.model.matmul_dtype = "float32"

    c.sampling = ml_collections.ConfigDict()
    c.sampling.z_low_m = 0.3  # eq. 7 lower bound; just below the 0.5 m minimum range
    c.sampling.z_up_m = 200.0  # eq. 7 upper bound; beyond the cube, so the cube bound decides
    c.sampling.cube_bound = True  # ablation: False samples in [z_low, z_up] whatever the cube
    c.sampling.hierarchical = "before"  # before (NeLD-BA) | nerf (vanilla NeRF) | none (coarse only)
    # Samples per ray ramp from the first to the last stage over `sample_ramp_fraction` of the steps, in
    # discrete stages so that the step compiles once per stage.
    c.sampling.coarse_stages = (32, 48, 64)
    c.sampling.fine_stages = (16, 24, 32)
    c.sampling.sample_ramp_fraction = 0.75  # 120k of 160k steps
    # Range-guided samples (CPU-budget option, 0 = the paper): this many of each ray's coarse samples are
    # placed uniformly within +-guided_width_m of the measured range, so the field sees the surface early.
    c.sampling.guided_samples = 0
    c.sampling.guided_width_m = 1.0
    # The expected range D_hat = sum h_i z_i reads each sample's own range (the paper). True: the middle of the
    # interval before each sample, unbiased for a sharp surface (rendering.composite; docs/method.md); measured no
    # better on the hard synthetic sequence (1500 and 6000 steps) nor on HKU_2 and Riverside02, so off.
    c.sampling.range_at_midpoint = False

    c.loss = ml_collections.ConfigDict()
    c.loss.lambda_coarse = 0.1
    c.loss.lambda_range = 1.0
    c.loss.lambda_termination = 1.0
    c.loss.termination = True  # ablation: False drops the termination loss

    c.train = ml_collections.ConfigDict()
    c.train.steps = 160_000
    c.train.batch_rays = 1024
    # 0: each step's rays uniform over all rays (the paper). N > 0: N scans a step, batch_rays // N rays each,
    # so each pose sampled gets a gradient averaged over several rays (sequences of hundreds of scans).
    c.train.scans_per_step = 0
    c.train.field_lr_init = 5e-5
    c.train.field_lr_final = 2e-5
    c.train.pose_lr_rot_init = 5e-5
    c.train.pose_lr_rot_final = 2e-5
    c.train.pose_lr_trans_init = 5e-5
    c.train.pose_lr_trans_final = 2e-5
    c.train.c2f_end_fraction = 0.75  # alpha ramps 0 -> pos_freqs over 120k of 160k steps (BARF)
    c.train.pose_start_freq = 6  # k*: poses start moving once this frequency is active
    c.train.pose_warmup_steps = 0  # extra: poses stay frozen at least this many steps (0 = only k*)
    # Pull each pose's correction xi back toward its start: weight * xi is added to the pose gradient before Adam (a
    # Gaussian prior, (weight / 2) |xi|^2 in normalised units and radians, beside the batch's mean loss). 0 = off.
    c.train.pose_prior_weight = 0.0
    # The rotation columns' (omega's) prior weight is pose_prior_weight times this; 1 = one weight for all six.
    # From the baseline, weight 10000 with factor 0.3 (rotation 3000) put the hard synthetic ATE below the
    # baseline's on every training seed with the rotation of 3000's, but HKU_2's and HKU_1's maps kept a third of
    # 3000's gain, as one weight of 10000 did (twentieth session; benchmarks/RESULTS.md): off by default.
    c.train.pose_prior_rot_factor = 1.0
    # Keep the trajectory's scale the start's: the pose steps are kept off the one mode that scales every position
    # about a point (docs/method.md, "Keeping the start's scale"). A LiDAR trajectory's scale is set by the metric
    # ranges; the field's rendering bias can shrink it (hard synthetic, from the baseline: by 2-4e-5, half of
    # NeLD-BA's ATE). The single cube and the submaps (whose shared rows are body-frame corrections: the mode is
    # then the world positions' spread seen in each scan's frame). On by default from the baseline's poses
    # (train.keep_scale_from_baseline).
    c.train.keep_start_scale = False
    c.train.fixed_scans = (0,)  # gauge: these scans never move during the optimisation (the paper's choice)
    # After training, re-express poses and maps so that this scan keeps its initial pose (-1: off). With scan 0
    # fixed this changes nothing; with fixed_scans=() (every pose free, the field holds the frame) it puts the
    # result back in the input's frame.
    c.train.anchor_scan = 0
    # Where training starts: "input" (the loaded odometry), "baseline" (the classical ICP + pose graph run
    # from it first; for starts that drifted beyond the field's basin of convergence) or "crisper" (the baseline
    # runs, and training starts from whichever of the two gives the crisper raw map; neld_jax.run.starting_poses).
    c.train.init_poses = "input"
    # (init, final) caps on the pose learning rates when training starts from the baseline's poses (init_poses
    # baseline, or crisper choosing it): they are registered to a few mm, and larger pose steps walk them away
    # (long synthetic route: ATE 0.0064 -> 0.0366 m at the cpu budget's 1e-3; docs/method.md "Which start").
    # refine_odometry's own rates; () = no cap.
    c.train.pose_lr_from_baseline = REFINE_POSE_LR
    # ... and the pose prior (train.pose_prior_weight) at least this from the baseline's poses: it holds each scan
    # near its registered start unless the rays keep pushing it, where the first pose steps, noise that Adam turns
    # into full-sized steps, blurred the map (docs/method.md, "A prior on the pose corrections"). With the start's
    # scale kept (below), 1500 steps from the baseline, weight 300 / 1000 / 3000: hard synthetic ATE 0.83 / 0.61 /
    # 0.51 mm (the baseline 0.54), HKU_2 -3.4928 / -3.4921 / -3.4910 (start -3.4901), main building -3.3947 / - /
    # -3.3954 (start -3.3945): 3000 is the weight at which NeLD-BA ties the baseline on ground truth (0.51-0.55 mm
    # over three training seeds) and stays crisper than it on the real sequences; 10000 is below the baseline on
    # every seed (0.50-0.52 mm) but keeps a third to two thirds of the real maps' gain and leaves quick-shack's a tie
    # (twentieth session). Not from the odometry: there it held back the field's corrections (HKU_2, weight 300:
    # -3.441 against -3.453 without). 0 = none.
    c.train.pose_prior_from_baseline = 3000.0
    # ... and (pose_prior_thin_map_m / t)^2 times that on the translation columns where the start's raw map is
    # thinner (mean plane thickness t, eval's crispness settings) than this, the rotation columns' weight unchanged
    # (neld_jax.run.pose_steps_for_start). A thin map comes from scans precise enough for ICP's translations to beat
    # what the field resolves: the synthetic sequences' baseline maps are 0.86-0.98 cm thin, and with 3000 from them
    # NeLD-BA's translations tied the baseline's (hard: 0.51-0.55 mm over three seeds against 0.54; with this rule
    # 0.50-0.53 over five), while FAST-LIO2 keyframe maps (3.2-4.4 cm on six real sequences) keep 3000, the weight
    # at which their maps gain most (twenty-third session; benchmarks/RESULTS.md). 0 = off.
    c.train.pose_prior_thin_map_m = 0.02
    # ... and train.keep_start_scale on: the baseline's scale is ICP's, metric to about 2e-5 (hard synthetic), while
    # the field shrank it by 2-4e-5 (hard synthetic from the baseline, weight 300: ATE 1.48 -> 0.83 mm with it, the
    # baseline 0.54). Not from the odometry: a drifted start's scale is part of its drift.
    c.train.keep_scale_from_baseline = True
    # A baseline trajectory that departs from the input's by more than this fraction of the path (largest position
    # difference after rigid alignment) is warned about, and init_poses=crisper keeps the input: the drift expected
    # of a LiDAR odometry (refine_odometry: 1 %). 0: no check (the input may have drifted arbitrarily).
    c.train.max_baseline_departure = 0.0
    c.train.baseline_departure_floor_m = 0.0  # but never less than this many metres (a short path's drift is in time)
    c.train.checkpoint_every = 5000
    c.train.log_every = 100
    # 0: no wall-clock limit; else training stops (and checkpoints) this long after the run started (loading and the
    # baseline count), but gets at least a quarter of it (neld_jax.run.training_seconds; train.fit alone: its own
    # time); steps that would not fit compress the schedule to those that do (train.run_chunks)
    c.train.max_minutes = 0.0

    c.mapping = ml_collections.ConfigDict()
    c.mapping.enabled = True
    c.mapping.num_coarse = 128
    c.mapping.num_fine = 128
    c.mapping.rays_per_batch = 4096
    c.mapping.max_rays_per_scan = 0  # 0: every preprocessed ray
    c.mapping.max_rays = 0  # > 0: at most this many rays over the sequence (each scan an equal share, >= 256)
    c.mapping.voxel_size_m = 0.05  # voxel grid on the written maps (0 = none)
    c.mapping.min_opacity = 0.5  # rendered points of rays whose opacity is below this are dropped
    # > 0: the render's time limit [s]; what it renders by then is a uniform sample of the rays (logged, metrics.json).
    # A run past train.max_minutes (training's floor) gives the overrun back from it (neld_jax.run.rendering_seconds)
    c.mapping.max_seconds = 0.0

    # The classical baseline (neld_jax.baseline.BaselineSettings: bin/baseline.py and train.init_poses=baseline).
    c.baseline = ml_collections.ConfigDict()
    c.baseline.voxel_size_m = 0.1
    c.baseline.window = 10  # scans in the local map of the scan-to-map chain
    c.baseline.icp_distances_m = (1.0, 0.5, 0.25, 0.1)  # multi-scale ICP of the chain, coarse first
    c.baseline.loop_icp_distances_m = (0.5, 0.25, 0.1)  # and of the loop closures (they start within dm)
    c.baseline.max_link_correction_m = 0.5  # chain links that ICP moves further from the odometry keep it
    c.baseline.loop_radius_m = 10.0  # loop-closure candidates, in the chain's frame
    c.baseline.max_loops_per_scan = 4
    c.baseline.min_loop_fitness = 0.3
    c.baseline.max_loop_correction_m = 0.2  # loop closures that move a scan further from the chain are dropped
    # Loops ICP cannot reach from the chain: FPFH + RANSAC for the nearest pair per scan (0: off), kept within
    # this fraction of the path between the two scans (the drift a LiDAR odometry builds up).
    c.baseline.global_loops_per_scan = 1
    c.baseline.loop_drift_fraction = 0.01
    c.baseline.map_rounds = 2  # rounds of multi-view refinement (each scan against the others' map); 0: none
    # ... started from the pose graph's poses or the input's, whichever gives the crisper raw map, never from a graph
    # bent away from the input (train.max_baseline_departure) | scans: the crisper unbent of the graph's and the
    # chain's, the input's only when both are bent | graph: always the graph's (neld_jax.run)
    c.baseline.refine_from = "crisper"
    # The input's roll and pitch are trusted (an IMU-aided odometry: gravity keeps them): the chain keeps each scan's
    # up axis from the input, and the refinement may start from the chain (neld_jax.baseline, keep_input_tilt).
    c.baseline.keep_input_tilt = False

    c.eval = ml_collections.ConfigDict()
    c.eval.f1_threshold_m = 0.2
    c.eval.raw_cutoff_m = 1.0
    c.eval.map_icp_m = 0.0  # > 0: refine the map alignment by ICP with this correspondence distance (evaluate.py)
    # Map crispness without ground truth (neld_jax.crispness): neighbourhood radius and number of query points.
    c.eval.crispness_radius_m = 0.3
    c.eval.crispness_queries = 10_000
    # Draws of those query points over which NeLD-BA's map is compared with each other method's (the margin in
    # metrics.json run.crispness_margin; docs/evaluation.md, "How sure a difference is"); 0 or 1: no margin.
    c.eval.crispness_draws = 5
    # ... and no draw after draw 0 starts once the run is this long past train.max_minutes + mapping.max_seconds
    # (neld_jax.run.margins_deadline); 0: no limit.
    c.eval.crispness_draws_max_seconds = 30.0
    return c


def refine_odometry(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Settings for real recordings whose initial poses are already good (LIO output such as FAST-LIO2, or the
    classical baseline's), on the cpu and gpu budgets: pose steps 200x smaller (5e-6 -> 2.5e-7 normalised units),
    points within 40 m, and training starts from the crisper of the odometry and the classical baseline
    (train.init_poses=crisper; from the baseline with a prior holding each pose near it,
    train.pose_prior_from_baseline); on the cpu budget, a termination loss three times the paper's weight in one
    cube (submap runs keep the paper's) and four times the budget's field learning rate.

    Measured on real sequences (benchmarks/RESULTS.md): with the cpu budget's pose learning rate (1e-3) the
    field, which resolves a few cm at this size, walked good poses away (HKU_1 mean map entropy -3.403 ->
    -3.380). At 1e-4 the maps came out slightly crisper, but two runs from the same start with different seeds
    lay 2.6 cm apart: a pose sees about two rays a step, and the first pose steps, at the highest rate, move
    every scan by a few cm of noise that the field then learns and the decayed rate never undoes. At 2e-5 the
    two starts of the drift test lie 0.9 cm apart (2.3 cm at 1e-4) and the map is crisper still. The 40 m
    crop shrinks the cube, so the same field resolves finer detail. The field refines within a few cm and does
    not undo a blurrier start: from the recorded odometry it beat the baseline where the odometry was the crisper
    start (HKU_2, HKU main building) and lost where the baseline was (Hilti quick-shack), so the run judges the
    two starts by their maps' entropy first (docs/method.md, "Which start"). Since the baseline's multi-view
    refinement (2026-12-01) the baseline is the crisper start on HKU_2 and the main building too, and the
    field, which moves it by about a centimetre, leaves it slightly blurrier (HKU_2: -3.490 -> -3.475); the
    run then says which poses file gives the crispest map (quality.warn_if_not_crispest). Measured every 250
    steps from that start (HKU_2, HKU_1), the map blurs within 50 steps of the poses starting (-3.490 -> -3.410)
    and then recovers part of the way; how far it blurs follows the pose step and nothing else tried (a ramp of
    the rate, a later start, 16 scans a step, Adam b1 0.99), so the steps are 4x smaller again: HKU_2 -3.475 ->
    -3.486, HKU_1 -3.514 -> -3.523 (its start: -3.528). The field does not yet place a scan as finely as the
    baseline's ICP against every other scan (docs/method.md, "Pose steps on real recordings").
    """
    for part in ("rot", "trans"):
        c.train[f"pose_lr_{part}_init"], c.train[f"pose_lr_{part}_final"] = REFINE_POSE_LR
    c.data.max_range_m = 40.0
    c.train.init_poses = "crisper"
    # On MulRan Riverside02 (2.6 km, sparse outdoor scans overlapping 19 % at the chain's 0.1 m scale) the
    # baseline's chain bent the route by up to 33.7 m (1.28 % of the path) and still gave the crisper local map;
    # on HKU_1 and HKU_2 it departs 0.25 % and 0.11 % (docs/method.md, "Which start").
    c.train.max_baseline_departure = 0.01
    # ... and at least 1 m: Hilti quick-shack walks 7 m in a room, and its baseline (0.27 m from FAST-LIO2's poses,
    # 3.7 % of that path) gives a far crisper map (-3.246 against -3.180); Riverside02's bend is 33.7 m.
    c.train.baseline_departure_floor_m = 1.0
    if c.budget == "cpu":
        # The cpu budget's 1500 steps leave a fog in front of real surfaces, which the termination loss (-ln h of the
        # first sample beyond the range) clears; three times the paper's weight moves the poses about twice as far and
        # made the map crisper against the baseline than at 1 on the four handheld sequences, each of two seeds (1.1-2.3x
        # the margin; HKU_1 and HKU_2 about 2x; docs/method.md, "The termination loss's weight on the cpu budget").
        # The gpu budget's 30k steps clear the fog anyway: it keeps 1.
        c.loss.lambda_termination = 3.0
        # ... in one cube. The submap fields of a drive keep the paper's weight: over Riverside02's two parts the
        # heavier one lost more on the first (+0.0014 -> +0.0040 / +0.0055) than it gained on the second (-0.0043 ->
        # -0.0052 / -0.0047); its harm there is the scans' vertical scan-to-scan moves (docs/method.md, same item).
        c.submaps.lambda_termination = 1.0
        # Four times the cpu budget's field learning rate (5e-3 -> 2e-2, decaying to 2e-3), in one cube and in submaps:
        # in 1500 steps the fields fit real keyframes coarsely (Riverside02's submaps: 0.77 m of median range
        # residual), and the higher rate fits them closer. The fixed-step protocol from the baseline's poses, margin
        # at 1x -> 4x: HKU_2 -0.0022 -> -0.0030 (two seeds), HKU_1 -0.0013 -> -0.0016, Riverside02 281 +0.0015 ->
        # +0.0004 (two and three seeds), 331 -0.0043 -> -0.0048, quick-shack -0.00005 -> -0.00003 (the same map
        # either way); twenty-third and twenty-fourth sessions, docs/method.md "The field's learning rate on real
        # recordings". The gpu budget keeps its 5e-3.
        c.train.field_lr_init, c.train.field_lr_final = 2e-2, 2e-3
        # ... but a drive's submap fields trained four times longer want the budget's own rate again: at 6000 steps
        # 1x beat 4x on both Riverside02 parts (281: -0.0012 against -0.0003; 331: -0.0126 against -0.0113, NeLD-BA's
        # map minus the baseline's over five draws), while one cube kept 4x ahead (HKU_2, HKU_1, the main building);
        # at 3000 steps 4x still led 2x on the 281 part (-0.0001 against +0.0005), and 1x at 4500 on both parts (281:
        # -0.0002 against +0.0002; 331: -0.0109 against -0.0099; twenty-sixth to twenty-eighth sessions,
        # docs/method.md "The field's learning rate on real recordings").
        c.submaps.field_lr_from_steps = (6000, 0.25)
    return c


def apply_budget(c: ml_collections.ConfigDict, budget: str) -> ml_collections.ConfigDict:
    """Size the model, batch and steps for a compute budget ("" = `default_budget()`).

    paper: exactly the paper's configuration and schedule (base_config as is: 160k steps, 1024 rays, learning
    rates 5e-5 -> 2e-5, scan 0 fixed; docs/method.md, "Optimisation"). About 1.5 h on an RTX 4060 in the paper.
    cpu: about 10 minutes on 2 CPU cores for ~24 scans; a smaller MLP, fewer steps, and the CPU options
    that make the bundle adjustment converge within 1% of the paper's step count (see README).
    gpu: the cpu budget's recipe (model, samples, learning rates, every pose free) run 20x longer, 30k steps,
    in chunks of 500 steps a device call, with the paper's map (128 + 128 samples, every ray). Chosen from the
    measurements on one H200 (issue 13; benchmarks/RESULTS.md): that recipe reached ATE 0.0017 m (0.012x the
    initial 0.137 m) on the demo in 36,446 steps and 33 s, while the paper-size model with the same recipe
    needed 106 s for 0.0022 m (7,147 steps) and the paper's own recipe had not converged at that step count.
    The small model is launch-bound on a GPU (0.66 ms a step), so the fused loop runs it at about the step's
    rate: on one H200 (eighteenth session) 30k steps took 27-34 s on the real handheld sequences and 57-101 s with
    Riverside02's 172-279 submaps, and from the classical baseline's poses every real map but one came out crisper
    than the baseline's on every query draw (quick-shack: a tie); on the hard synthetic sequence the ATE ended about at
    the baseline's (0.53-0.60 mm over three training seeds against 0.54; benchmarks/RESULTS.md).
    """
    budget = (budget or default_budget()).strip().lower()
    if budget not in BUDGETS:
        raise ConfigError(f"unknown budget {budget!r} in the config string; choose one of {', '.join(BUDGETS)}")
    c.budget = budget
    if budget == "paper":
        return c
    c.model.width = 128
    c.model.depth = 4
    c.model.skip_layers = (2,)
    c.model.pos_freqs = 10
    c.model.dir_freqs = 2
    c.data.max_rays_per_scan = 8192
    c.sampling.coarse_stages = (32,)
    c.sampling.fine_stages = (16,)
    c.sampling.guided_samples = 16
    c.sampling.guided_width_m = 1.0
    c.train.steps = 1500
    c.train.batch_rays = 512
    c.train.field_lr_init = 5e-3
    c.train.field_lr_final = 5e-4
    c.train.pose_lr_rot_init = 1e-3
    c.train.pose_lr_rot_final = 1e-5
    c.train.pose_lr_trans_init = 1e-3
    c.train.pose_lr_trans_final = 1e-5
    c.train.c2f_end_fraction = 0.5
    c.train.pose_start_freq = 6
    # Every pose free, the field holds the frame, the result is anchored on scan 0 afterwards. Fixing scan 0
    # during training leaves it behind the others, which follow the field that the drifted majority built:
    # measured on the demo, ATE 0.031 m with scan 0 fixed against 0.0027 m free (benchmarks/RESULTS.md).
    c.train.fixed_scans = ()
    c.train.anchor_scan = 0
    c.train.checkpoint_every = 500
    c.train.log_every = 25
    c.train.max_minutes = 8.0  # a guard: the whole run (with the baseline and the map) stays within about 10 minutes
    c.mapping.num_coarse = 64
    c.mapping.num_fine = 64
    c.mapping.max_rays_per_scan = 2048
    # Sequences of hundreds of keyframes: the map's rays stop growing at 2^18 (HKU_2's 266 scans x 2048 rays
    # took 160 s to render on 2 cores, as long as half the training).
    c.mapping.max_rays = 262_144
    # The render is outside train.max_minutes: 75 s for these 2^18 rays on an idle machine, 160 s in a slow spell
    # of the same VM (HKU_1, 2026-12-02), which took that run to 11.2 minutes. A limit keeps the run's 10.
    c.mapping.max_seconds = 60.0
    c.mapping.voxel_size_m = 0.1
    # A step's rays are shared among the submaps; beyond 32 each field sees too few and a step costs more than the
    # single cube's (Riverside02's 0.25 m rule: 340 submaps, 2.4 s a step on 2 cores).
    c.submaps.max_submaps = 32
    # Narrower submap fields, each drawing three times the rays (1536 a step over the submaps: Riverside02's 31
    # submaps 49 each instead of 16) for 1.3-1.4x the step: the fields fit better (median range residual 1.03 ->
    # 0.78-0.90 m), both Riverside02 parts' maps came out crisper end to end (by 0.0010 / 0.0025) and the shortened
    # synthetic long route's ATE fell from 0.324 to 0.223 m (benchmarks/RESULTS.md, fifteenth session). The single
    # cube keeps model.width.
    c.submaps.width = 64
    c.submaps.step_rays_factor = 3.0
    c.data.synthetic.gt_map_points = 100_000
    if budget == "gpu":
        c.train.steps = 30_000
        c.train.log_every = 500  # K: steps per device call of the fused loop
        c.train.checkpoint_every = 5000
        # A GPU runs hundreds of submaps' rays a step: Riverside02's 279 submaps at 286 steps/s on one H200
        c.submaps.max_submaps = 0
        paper = base_config()
        # The cpu budget's trade of the submap fields' width for rays (31 submaps 64 wide, 3x the rays) lost to this
        # rule on Riverside02's 281 part at 30k steps: -0.0020 against -0.0035 to the baseline's entropy (H200)
        c.submaps.width, c.submaps.step_rays_factor = paper.submaps.width, paper.submaps.step_rays_factor
        # the paper's map: 128 + 128 samples per ray, every ray, 5 cm voxels
        for field in ("num_coarse", "num_fine", "max_rays_per_scan", "max_rays", "voxel_size_m", "max_seconds"):
            c.mapping[field] = paper.mapping[field]
    return c


def with_train(c: ml_collections.ConfigDict, **fields) -> ml_collections.ConfigDict:
    """c itself when its train fields already hold `fields`, else a copy with them set (c is left as it is)."""
    if all(key in c.train and c.train[key] == value for key, value in fields.items()):
        return c
    changed = ml_collections.ConfigDict(c.to_dict())
    for key, value in fields.items():
        changed.train[key] = value
    return changed


def apply_overrides(c: ml_collections.ConfigDict, items) -> ml_collections.ConfigDict:
    """Apply "KEY=VALUE" overrides (dotted keys, Python-literal values) as the benchmarks' --set flags give them.

    An unknown key raises ConfigError naming it, as bin/train.py's --config.KEY does."""
    import ast

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
            node[leaf] = value  # a bare string, e.g. train.init_poses=baseline
    return c

