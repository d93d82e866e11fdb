"""Shared fixtures: a tiny configuration that trains in seconds on a CPU, and whole runs made once for every test
that only reads their output folder."""

import fcntl
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

# Tests run on the CPU, whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Each run a test makes builds its jitted functions anew, so the in-memory cache misses and the same small train
# steps compile again and again: JAX's persistent compilation cache, shared by both xdist workers and by the runs and
# notebook kernels the tests start as subprocesses (they inherit the environment), compiles each program once.
os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR",
    os.path.join(tempfile.gettempdir(), f"neld_jax_tests_{os.getuid()}", "jax_compilation_cache"),
)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")
# The tests' programs are tiny: compiling them costs more than running them, and LLVM's optimisation of the CPU code
# is most of the compile (a tiny run: 45 s -> 32 s without it). What a program computes is the same.
# A test whose program computes much (the pose-recovery notebook's 900 steps) drops the flag: UNOPTIMISED_XLA_FLAGS.
UNOPTIMISED_XLA_FLAGS = "--xla_backend_optimization_level=0"
os.environ.setdefault("XLA_FLAGS", UNOPTIMISED_XLA_FLAGS)

from neld_jax.config import defaults  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def encoded_dim(in_dim: int, num_freqs: int) -> int:
    """Width of encoding.fourier_encode's output for `in_dim` inputs and `num_freqs` frequencies."""
    return in_dim * (1 + 2 * num_freqs)


def make_tiny_config(output_dir: str = "", steps: int = 20):
    c = defaults()
    c.output_dir = output_dir
    c.data.format = "synthetic"
    c.data.keyframe_interval_s = 0.0
    c.data.voxel_size_m = 0.2
    c.data.max_rays_per_scan = 256
    s = c.data.synthetic
    s.num_scans, s.num_beams, s.num_columns, s.gt_map_points = 4, 8, 64, 2000
    s.scene_size_m, s.trajectory_radius_m, s.max_range_m = 30.0, 5.0, 30.0
    c.model.width, c.model.depth, c.model.skip_layers = 16, 2, (1,)
    c.model.pos_freqs, c.model.dir_freqs = 8, 2
    c.sampling.coarse_stages, c.sampling.fine_stages = (8, 12), (4, 6)
    c.train.steps = steps
    c.train.batch_rays = 32
    c.train.c2f_end_fraction = 0.5
    c.train.field_lr_init, c.train.field_lr_final = 1e-3, 1e-4
    for k in ("rot", "trans"):
        c.train[f"pose_lr_{k}_init"], c.train[f"pose_lr_{k}_final"] = 1e-3, 1e-4
    c.train.checkpoint_every = 5
    c.train.log_every = 1
    c.mapping.num_coarse, c.mapping.num_fine = 8, 8
    c.mapping.max_rays_per_scan = 64
    c.mapping.voxel_size_m = 0.0
    c.mapping.min_opacity = 0.0  # a 12-step field is still mostly transparent
    return c


def fake_training_clock(monkeypatch, seconds_per_step: float = 1.0, compile_s: float = 5.0) -> list:
    """Make neld_jax.training.train's clock a fake one that only the fused chunks move: `seconds_per_step` a step, plus
    `compile_s` on each jitted chunk's first call. Returns the clock, [seconds]."""
    import types

    from neld_jax.training import train

    clock = [0.0]
    monkeypatch.setattr(train, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    real_jit_chunk = train.jit_chunk

    def timed_jit_chunk(body):
        chunk, calls = real_jit_chunk(body), []

        def timed(state, *args, num_steps, **kwargs):
            clock[0] += num_steps * seconds_per_step + (0.0 if calls else compile_s)
            calls.append(num_steps)
            return chunk(state, *args, num_steps=num_steps, **kwargs)

        return timed

    monkeypatch.setattr(train, "jit_chunk", timed_jit_chunk)
    return clock


def tiny_synthetic_sequence(num_scans: int = 4):
    """A synthetic Sequence of num_scans small scans (8 beams x 64 columns, 30 m scene, 5 m trajectory radius)."""
    import ml_collections

    from neld_jax.synthetic.generator import make_sequence

    cfg = ml_collections.ConfigDict(
        {
            "num_scans": num_scans,
            "num_beams": 8,
            "num_columns": 64,
            "gt_map_points": 1000,
            "scene_size_m": 30.0,
            "trajectory_radius_m": 5.0,
            "max_range_m": 30.0,
        }
    )
    return make_sequence(cfg)


def first_sweeps_of_the_loop(num_sweeps: int, loop_sweeps: int = 300, seed: int = 0, rate_hz: float = 10.0):
    """The first num_sweeps raw sweeps of make_sequence(SWEEPS, rate_hz) with SWEEPS = {"num_scans": loop_sweeps,
    "trajectory_radius_m": 10.0, "max_range_m": 40.0, "gt_map_points": 0, "seed": seed}, equal to them point for
    point, without casting the loop's other sweeps: a Sequence of raw sweeps (point_times, no poses) with ground truth.
    At the defaults 2.1 m/s round a 10 m loop (0.2 m a sweep), 32 beams x 512 columns."""
    import numpy as np

    from neld_jax.data.sequence import Sequence
    from neld_jax.synthetic.generator import (
        FOV_DEG,
        cast_sweep,
        loop_poses,
        make_scene,
        spinning_lidar_directions,
        synthetic_defaults,
    )

    cfg = synthetic_defaults()
    cfg.update({"trajectory_radius_m": 10.0, "max_range_m": 40.0, "seed": seed})
    scene, _ = make_scene(seed, cfg.scene_size_m, path_radius_m=cfg.trajectory_radius_m)
    directions = spinning_lidar_directions(cfg.num_beams, FOV_DEG[1], FOV_DEG[0], cfg.num_columns)
    rng = np.random.default_rng(seed + 2)  # make_sequence's stream: each sweep draws its noise in turn
    column_fraction = np.arange(cfg.num_columns) / cfg.num_columns
    scans, point_times = [], []
    for i in range(num_sweeps):
        column_poses = loop_poses((i + column_fraction) / loop_sweeps, cfg.trajectory_radius_m, seed)
        points, column = cast_sweep(scene, column_poses, directions, cfg.max_range_m, cfg.range_noise_m, rng)
        scans.append(points)
        point_times.append(column_fraction[column] / rate_hz)
    return Sequence(
        scans=scans,
        poses=None,
        timestamps=np.arange(num_sweeps) / rate_hz,
        gt_poses=loop_poses(np.arange(num_sweeps) / loop_sweeps, cfg.trajectory_radius_m, seed),
        name=f"synthetic_seed{seed}_{rate_hz:g}hz",
        source="synthetic",
        point_times=point_times,
    )


def similarity_scale(T_moved, T_start) -> float:
    """The Umeyama (similarity-alignment) scale of T_moved's positions [S, 4, 4] against T_start's, minus 1
    (float64): how much a pose update scales the route."""
    import numpy as np

    from neld_jax.judging.metrics import ate_errors

    return ate_errors(np.asarray(T_moved, np.float64), np.asarray(T_start, np.float64), "sim3")[3] - 1.0


def poses_to_world(norm, poses):
    """poses [..., 4, 4] in norm's (field.normalize.Normalization) normalised world -> metres in the world."""
    import numpy as np

    out = np.array(poses, dtype=np.float64, copy=True)
    out[..., :3, 3] = norm.points_to_world(out[..., :3, 3])
    return out


@pytest.fixture
def tiny_config(tmp_path):
    return make_tiny_config(str(tmp_path / "run"))


def made_once(tmp_path_factory, name: str, make) -> Path:
    """The folder <suite's temporary folder>/<name>, filled by make(folder) once for the whole test run: the
    pytest-xdist workers share it (a file lock; the first worker to ask makes it, the others wait and read it).
    Tests read the folder and never write into it."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the workers' folders sit side by side in the run's own folder
    folder, done = base / name, base / f"{name}.done"
    with open(base / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            make(folder)
            done.touch()
    return folder


def free_gauge_config(output_dir: str, steps: int = 12):
    """The tiny configuration with every pose free (no fixed scan: the field holds the frame)."""
    config = make_tiny_config(output_dir, steps=steps)
    config.train.fixed_scans = ()
    return config


@pytest.fixture(scope="session")
def free_gauge_run(tmp_path_factory) -> Path:
    """The output folder of one whole run (run.run) of free_gauge_config, 12 steps, the Rerun recording included."""
    from neld_jax import run

    return made_once(
        tmp_path_factory, "free_gauge_run", lambda folder: run.run(free_gauge_config(str(folder)), progress=False)
    )


def sphere_plan(
    num_scans: int = 3, per_scan: int = 64, seed: int = 0, window: int = 0, overlap: int = 1, num_devices: int = 1
):
    """The sphere scene (sensors within 0.2 of the origin looking at a sphere of radius 0.8; metres are the cube's
    units) as the trainer's data: one cube (window 0) or windows of `window` keyframes sharing `overlap`.
    Returns (rays, frames, plan, T [S, 4, 4]) with rays and frames on a mesh of the plan's size."""

    from neld_jax.field.normalize import Normalization
    from neld_jax.training import submaps, train
    from neld_jax.training.rays import sphere_scene_rays

    rays, T = sphere_scene_rays(num_scans, per_scan, seed, spread=0.2)
    if window:
        scans = [
            rays.directions[rays.scan_index == s] * rays.ranges[rays.scan_index == s, None] for s in range(num_scans)
        ]
        plan = submaps.plan_submaps(scans, T, window, overlap, 0.9, num_devices=num_devices)
    else:
        plan = submaps.one_cube_plan(num_scans, Normalization(1.0))
    mesh = train.make_mesh(submaps.mesh_size(plan, num_devices))
    device_rays, frames = train.device_data(submaps.submap_arrays(plan, rays, T), mesh)
    return device_rays, frames, plan, T


# The grid (baseline.voxel_size_m) on which the tests' runs over raw sweeps register every other scan: on the default
# 0.1 m that took half of such a run, and they assert the odometry and the outputs, not registration's precision.
COARSE_REGISTRATION_GRID_M = 0.4


def train_a_download_briefly(config_file: str, root, output_dir) -> subprocess.CompletedProcess:
    """bin/train.py on a dataset's download (root) in its own layout (configs/<config_file>, cpu budget), KISS-ICP
    making the poses, with a field and a schedule so small that it ends in seconds, and every other scan registered
    on COARSE_REGISTRATION_GRID_M; its output is captured."""
    return subprocess.run(
        [
            sys.executable,
            str(REPO / "bin" / "train.py"),
            f"--config={REPO / 'configs' / config_file}:cpu",
            f"--config.data.root={root}",
            f"--config.output_dir={output_dir}",
            "--config.data.max_range_m=40",
            "--config.data.keyframe_interval_s=1",
            "--config.data.max_rays_per_scan=256",
            "--config.train.steps=2",
            "--config.train.batch_rays=32",
            "--config.model.width=16",
            "--config.model.depth=2",
            "--config.model.skip_layers=(1,)",
            "--config.start.poses=input",
            "--config.mapping.enabled=False",
            "--config.viz.record=False",
            f"--config.baseline.voxel_size_m={COARSE_REGISTRATION_GRID_M}",
        ],
        check=False,
        capture_output=True,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        timeout=600,
    )
