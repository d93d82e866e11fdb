#!/usr/bin/env python
"""Speed of the jitted NeLD-BA train step, and this machine's float32 matmul rate for comparison.

    python benchmarks/train_step.py --preset=cpu                  # the CPU budget's step
    python benchmarks/train_step.py --preset=paper --stage=2      # the paper's step, last sample stage
    python benchmarks/train_step.py --preset=cpu --matmul_peak    # GFLOP/s of plain matmuls, same backend
    python benchmarks/train_step.py --preset=cpu --efficiency     # both, alternately: the step's share of the peak
    python benchmarks/train_step.py --preset=cpu --fit --steps 200  # train.fit's loop against the bare step
    python benchmarks/train_step.py --preset=cpu --viewer --steps 200 --repeats 6  # fit with the live view's hook
    python benchmarks/train_step.py --rays 256 --coarse 16 --fine 8 --width 64 --depth 2

Each run prints ONE JSON line on stdout (logs go to stderr). The train step is the trainer's own
(train.make_trainer and train.init_state over a plan of one cube, as a run builds them) on synthetic rays built in
memory (a few scans inside the normalisation cube looking at a sphere), so no dataset is needed.

Timing: the step is lowered and compiled once (compile_s), run once to warm up, then `--repeats` times
`--steps` consecutive steps are timed up to jax.block_until_ready; the reported rates use the median repeat.
The state is donated, as in the trainer, so every step feeds the previous step's output back in.

FLOP count (mlp_flops_per_step) covers the dense layers of the density MLP only, counted analytically from
the kernel shapes: a Dense layer with an [in, out] kernel costs 2 * in * out FLOPs per point forward (a
multiply and an add per weight); the backward pass costs twice that (one matmul of the same size for the
kernel gradient, one for the input gradient, which is needed because the pose gradient flows back through
the positions), so 3 * 2 * in * out in all. The MLP runs on every sample of every ray once per step (the fine
pass reuses the coarse densities), so

    mlp_flops_per_step = 3 * rays * (coarse + guided + fine) * sum_layers 2 * in * out.

achieved_gflops = mlp_flops_per_step * steps_per_s / 1e9; its fraction of `--matmul_peak`'s "gflops" is the
step's efficiency. xla_flops_per_step is XLA's own count for the whole compiled step (all ops, for reference).
On a machine shared with other jobs, compare the CPU-time rates instead (cpu_ms_per_step,
achieved_gflops_per_cpu_s against the peak's gflops_per_cpu_s): they count the work done, not the waiting.

--fit times `train.fit` (the fused loop: chunks of --log_every steps in one lax.scan each, with its logging)
against the bare step at the same sizes, alternately in this process for --repeats rounds. Each round runs fit
from a fresh state for --log_every + --steps steps (rounded up to whole chunks) and takes its rate from the
wall and CPU clocks between the first and the last chunk end (a checkpoint_fn hook, called once a chunk's
metrics are fetched), so the first chunk, which compiles, is left out; then it times the same number of bare
steps (one jitted call each, as in the default mode). "ratio" is the median of the rounds' fit / step rates of
wall time, "cpu_ratio" that of process CPU time (all threads; steadier where other jobs share the cores).

--viewer times train.fit with the hook a run with viz.live hands it (neld_jax.writing.viewer: run.rrd and a gRPC server
on a local port, the training curves and the keyframes' poses at every log) against fit without it, in the same
way, the order alternating between rounds; "slowdown" is the median of the rounds' plain / live rate less 1.

--profile_dir traces a few steps with jax.profiler.trace (open it in TensorBoard / XProf) and adds "profile" to
the JSON: thread-milliseconds per step by kind of XLA op (matmul, sin/cos, sort, gather, ...) and the top ops.
--dump_hlo writes the optimized HLO of the step, where those op names can be looked up.
"""

from __future__ import annotations

import functools
import glob
import json
import logging
import math
import os
import re
import statistics
import sys
import time
from typing import Callable, NamedTuple

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from absl import app, flags

from neld_jax.config import defaults, with_budget
from neld_jax.field.normalize import Normalization
from neld_jax.hugepages import reexec_with_huge_page_malloc
from neld_jax.training import submaps, train
from neld_jax.training.rays import RaySet, sphere_scene_rays

logger = logging.getLogger(__name__)

# Flag defaults are used as they are with --preset=none; a preset replaces every size flag that is not
# given on the command line. These defaults are the CPU budget's sizes without range-guided samples.
SIZE_FLAGS = ("rays", "coarse", "fine", "guided", "width", "depth", "skip_layers", "pos_freqs", "dir_freqs")
# model.matmul_dtype: taken from --matmul_dtype whatever the preset (the presets are all float32).

FLAGS = flags.FLAGS
flags.DEFINE_enum(
    "preset",
    "none",
    ["cpu", "gpu", "paper", "none"],
    "cpu, gpu, paper: the sizes of with_budget(defaults(), preset) (paper: defaults() itself); none: the flags only.",
)
flags.DEFINE_integer("stage", 0, "Which sample-count stage of the preset (index into sampling.coarse_stages).")
flags.DEFINE_integer("rays", 512, "Rays per step (train.batch_rays).")
flags.DEFINE_integer("coarse", 32, "Stratified coarse samples per ray.")
flags.DEFINE_integer("fine", 16, "Fine (hierarchical) samples per ray.")
flags.DEFINE_integer("guided", 0, "Range-guided coarse samples per ray (sampling.guided_samples).")
flags.DEFINE_integer("width", 128, "MLP width.")
flags.DEFINE_integer("depth", 4, "Hidden layers of the MLP.")
flags.DEFINE_list("skip_layers", ["2"], "Hidden layers whose input gets the encoded position again.")
flags.DEFINE_integer("pos_freqs", 10, "Fourier frequencies of the position encoding.")
flags.DEFINE_integer("dir_freqs", 2, "Fourier frequencies of the view-direction encoding.")
flags.DEFINE_enum(
    "matmul_dtype",
    "float32",
    ["float32", "bfloat16"],
    "model.matmul_dtype: bfloat16 = the MLP's matmuls on bfloat16 inputs, float32 parameters and sums.",
)
flags.DEFINE_integer("steps", 20, "Timed steps per repeat.")
flags.DEFINE_integer("repeats", 5, "Timed repeats; the median is reported.")
flags.DEFINE_integer("scans", 8, "Scans in the synthetic ray set.")
flags.DEFINE_integer("rays_per_scan", 4096, "Rays per scan in the synthetic ray set.")
flags.DEFINE_integer("seed", 0, "Seed of the synthetic rays and the parameters.")
flags.DEFINE_bool("matmul_peak", False, "Measure float32 matmul GFLOP/s instead of the train step.")
flags.DEFINE_bool(
    "efficiency",
    False,
    "Time the step and the matmul peak alternately in this process and report "
    "the step's GFLOP/s as a fraction of the peak (median over --repeats rounds).",
)
flags.DEFINE_bool("fit", False, "Time train.fit (the fused loop) against the bare step, alternately (see --fit above).")
flags.DEFINE_bool("viewer", False, "Time train.fit with the live viewer's hook against fit without it (--viewer).")
flags.DEFINE_integer("log_every", 0, "--fit, --viewer: train.log_every, the steps per device call (0: the preset's).")
flags.DEFINE_list("matmul_sizes", ["256", "512", "1024", "2048"], "Square matmul sizes for --matmul_peak.")
flags.DEFINE_string("profile_dir", "", "If set, trace --profile_steps steps with jax.profiler.trace into it.")
flags.DEFINE_integer("profile_steps", 5, "Steps inside the profiler trace.")
flags.DEFINE_string("dump_hlo", "", "If set, write the optimized HLO text of the compiled step to this file.")

# Normalised units per metre of the synthetic set: a scene of ~70 m fills the cube (as the real loaders do).
SYNTHETIC_SCALE = 1.0 / 40.0


# ----------------------------------------------------------------------------------------------------------
# Pure helpers


def preset_sizes(preset: str, stage: int = 0) -> tuple[ml_collections.ConfigDict, dict]:
    """(config, sizes) of a preset: the config supplies everything the size flags do not (losses, sampling)."""
    config = with_budget(defaults(), preset)
    m, s = config.model, config.sampling
    sizes = {
        "rays": int(config.train.batch_rays),
        "coarse": int(s.coarse_stages[stage]),
        "fine": int(s.fine_stages[stage]),
        "guided": int(s.guided_samples),
        "width": int(m.width),
        "depth": int(m.depth),
        "skip_layers": tuple(int(k) for k in m.skip_layers),
        "pos_freqs": int(m.pos_freqs),
        "dir_freqs": int(m.dir_freqs),
        "matmul_dtype": str(m.matmul_dtype),
    }
    return config, sizes


def configure(config: ml_collections.ConfigDict, sizes: dict, train_steps: int) -> ml_collections.ConfigDict:
    """A copy of `config` with the benchmark's sizes written in (one sample stage)."""
    c = config.copy_and_resolve_references()
    c.model.width, c.model.depth = sizes["width"], sizes["depth"]
    c.model.skip_layers = tuple(k for k in sizes["skip_layers"] if k < sizes["depth"])
    c.model.pos_freqs, c.model.dir_freqs = sizes["pos_freqs"], sizes["dir_freqs"]
    c.model.matmul_dtype = sizes.get("matmul_dtype", "float32")
    c.sampling.coarse_stages, c.sampling.fine_stages = (sizes["coarse"],), (sizes["fine"],)
    c.sampling.guided_samples = sizes["guided"]
    c.train.batch_rays = sizes["rays"]
    c.train.steps = max(train_steps, 1)
    return c


class SyntheticCube(NamedTuple):
    """The in-memory training data of one cube: the trainer's (Rays, Frames) on a one-device mesh, and the start
    poses [S, 4, 4] in metres (world) that make_trainer takes."""

    rays: train.Rays
    frames: train.Frames
    start_poses: np.ndarray
    mesh: object


def synthetic_rays(num_scans: int, rays_per_scan: int, seed: int = 0) -> SyntheticCube:
    """Rays of `num_scans` sensors inside the cube looking at a sphere of radius 0.8 around the origin, as one cube
    of SYNTHETIC_SCALE normalised units per metre (the sphere is 64 m across), placed as the trainer takes them."""
    rays, T = sphere_scene_rays(num_scans, rays_per_scan, seed)  # in the normalised frame
    rays_m = RaySet(rays.directions, (rays.ranges / SYNTHETIC_SCALE).astype(np.float32), rays.scan_index)
    T_m = np.array(T, np.float64)
    T_m[:, :3, 3] /= SYNTHETIC_SCALE
    mesh = train.make_mesh(1)
    arrays = submaps.submap_arrays(submaps.one_cube_plan(num_scans, Normalization(SYNTHETIC_SCALE)), rays_m, T_m)
    placed, frames = train.device_data(arrays, mesh)
    return SyntheticCube(placed, frames, T_m, mesh)


def trainer_for(
    config: ml_collections.ConfigDict, cube: SyntheticCube, total_steps: int | None = None
) -> train.Trainer:
    """train.make_trainer of one cube with the config's own pose steps, as a run from its input poses builds it."""
    return train.make_trainer(
        config,
        len(cube.start_poses),
        1,
        train.PoseSteps.from_config(config),
        cube.start_poses,
        total_steps=total_steps,
        mesh=cube.mesh,
    )


def points_per_step(sizes: dict) -> int:
    """Samples the MLP evaluates per step: rays * (coarse + guided + fine)."""
    return sizes["rays"] * (sizes["coarse"] + sizes["guided"] + sizes["fine"])


def mlp_shaped_matmul(sizes: dict) -> tuple[str, tuple[int, int, int]]:
    """(name, (m, k, n)) of the MLP's hidden-layer matmul: [points per step, width] @ [width, width]."""
    points, width = points_per_step(sizes), sizes["width"]
    return f"{points}x{width}x{width}", (points, width, width)


def mlp_flops_per_point(field_params) -> int:
    """Forward FLOPs of the MLP's dense layers for one point: sum over [in, out] kernels of 2 * in * out (kernels
    stacked over cubes, [M, in, out], count once per cube)."""
    kernels = [
        leaf
        for path, leaf in jax.tree_util.tree_leaves_with_path(field_params)
        if getattr(path[-1], "key", None) == "kernel"
    ]
    return int(sum(2 * math.prod(k.shape) for k in kernels))


def median_seconds(run: Callable[[], object], repeats: int) -> tuple[float, list[float], float]:
    """(median wall seconds, all wall seconds, median process CPU seconds) of `repeats` calls of run().

    run must block until its work is done. The CPU time sums all threads of this process: on a machine
    shared with other jobs it is a steadier measure of the work than the wall time (which includes waiting).
    """
    times, cpu_times = [], []
    for _ in range(max(repeats, 1)):
        t0, c0 = time.perf_counter(), time.process_time()
        run()
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    return statistics.median(times), times, statistics.median(cpu_times)


def device_info() -> dict:
    dev = jax.devices()[0]
    return {
        "device": f"{dev.platform}:{dev.device_kind}",
        "num_devices": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "jax_version": jax.__version__,
    }


def xla_flops(compiled) -> float | None:
    """XLA's FLOP estimate of a compiled executable (None where the backend gives none)."""
    try:
        cost = compiled.cost_analysis()
    except Exception:  # not every backend/version implements it; the benchmark works without
        return None
    if isinstance(cost, (list, tuple)):
        cost = cost[0] if cost else {}
    flops = (cost or {}).get("flops")
    return float(flops) if flops is not None else None


# Profile summary: the categories of HLO work, tested in this order on the ops of an instruction (a fusion's
# ops are those of the computation it calls). The first match names the instruction's category. A sine or
# cosine on fewer than SMALL_OP_ELEMENTS elements (the BARF window's) does not make a fusion "sin/cos".
OP_CATEGORIES = (
    ("matmul", ("dot", "convolution")),
    ("sin/cos (encoding)", ("sine", "cosine")),
    ("sort", ("sort",)),
    ("gather/scatter", ("gather", "scatter", "dynamic-slice", "dynamic-update-slice")),
    ("exp/log/expm1", ("exponential", "exponential-minus-one", "log", "log-plus-one")),
    ("reduce/cumsum", ("reduce", "reduce-window")),
    ("concatenate/copy/transpose", ("concatenate", "copy", "transpose", "pad", "slice")),
)
SMALL_OP_ELEMENTS = 4096
# "%name = f32[24576,30]{1,0} cosine(%x), ..." -> name, result shape, opcode
_HLO_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%(\S+) = (.*?) ([a-z][a-z0-9\-]*)\(")


def _num_elements(shape: str) -> int:
    """Elements of an HLO result shape such as 'f32[24576,30]{1,0}' (a scalar: 1; a tuple: its first array)."""
    dims = re.search(r"\[([0-9,]*)\]", shape)
    if dims is None:
        return 1
    return math.prod(int(d) for d in dims.group(1).split(",") if d)


def hlo_instruction_ops(hlo_text: str) -> dict[str, set]:
    """Optimized HLO text -> {instruction name: set of HLO opcodes it runs (a fusion: its callee's ops)}."""
    computations: dict[str, list] = {}
    current = None
    for line in hlo_text.splitlines():
        header = re.match(r"^(?:ENTRY )?%(\S+) .*\{\s*$", line)
        if header:
            current = computations.setdefault(header.group(1), [])
        elif line.strip() == "}":
            current = None
        elif current is not None:
            current.append(line)
    ops: dict[str, set] = {}
    for lines in computations.values():
        for line in lines:
            m = _HLO_INSTRUCTION.match(line)
            if not m:
                continue
            name, _, opcode = m.groups()
            callee = re.search(r"calls=%([\w.\-]+)", line)
            if callee and callee.group(1) in computations:
                body = [b.groups() for b in map(_HLO_INSTRUCTION.match, computations[callee.group(1)]) if b]
                ops[name] = {_sized_opcode(op, shape) for _, shape, op in body}
            else:
                ops[name] = {_sized_opcode(opcode, m.group(2))}
    return ops


def _sized_opcode(opcode: str, shape: str) -> str:
    """The opcode, with '-small' appended to a sine/cosine on few elements (so it does not name the category)."""
    if opcode in ("sine", "cosine") and _num_elements(shape) < SMALL_OP_ELEMENTS:
        return opcode + "-small"
    return opcode


def op_category(opcodes: set) -> str:
    for category, members in OP_CATEGORIES:
        if opcodes & set(members):
            return category
    return "elementwise/other"


def summarize_profile(xplane_path: str, hlo_text: str, num_steps: int, top: int = 15) -> dict:
    """Thread-milliseconds per step by op category, from a jax.profiler trace of `num_steps` steps.

    Every XLA op event of the host plane counts with its duration; ops that run on both CPU threads at
    once count twice, so the total can exceed the wall time (total / wall ~ threads kept busy).
    """
    ops = hlo_instruction_ops(hlo_text)
    by_op: dict[str, float] = {}
    plane = jax.profiler.ProfileData.from_file(xplane_path).find_plane_with_name("/host:CPU")
    for line in plane.lines:
        for event in line.events:
            hlo_op = dict(event.stats).get("hlo_op")
            if hlo_op:
                by_op[hlo_op] = by_op.get(hlo_op, 0.0) + event.duration_ns / 1e6 / num_steps
    by_category: dict[str, float] = {}
    for name, ms in by_op.items():
        category = op_category(ops.get(name, set()))
        by_category[category] = by_category.get(category, 0.0) + ms
    total = sum(by_op.values())
    ranked = sorted(by_op.items(), key=lambda kv: -kv[1])[:top]
    return {
        "thread_ms_per_step": total,
        "by_category_ms": dict(sorted(((k, round(v, 2)) for k, v in by_category.items()), key=lambda kv: -kv[1])),
        "top_ops_ms": [[name, round(ms, 2), op_category(ops.get(name, set()))] for name, ms in ranked],
    }


# ----------------------------------------------------------------------------------------------------------
# Benchmarks (effects: compile, run, time)


class StepRunner:
    """The trainer's step at `sizes` (train.make_trainer / train.init_state over one cube, as a run builds them),
    jitted and compiled once, on in-memory synthetic rays.

    run(n) runs n consecutive steps (the state is donated, as in the trainer's chunks, so each step's output feeds
    the next) and blocks until they are done; it returns the last step's metrics.
    """

    def __init__(
        self,
        config: ml_collections.ConfigDict,
        sizes: dict,
        train_steps: int,
        num_scans: int = 8,
        rays_per_scan: int = 4096,
        seed: int = 0,
    ):
        self.sizes = sizes
        self.config = configure(config, sizes, train_steps=train_steps)
        self.config.seed = seed
        self.cube = synthetic_rays(num_scans, rays_per_scan, seed)
        self.rays, self.frames = self.cube.rays, self.cube.frames
        self.trainer = trainer_for(self.config, self.cube)
        self.state = train.init_state(self.config, self.trainer, num_scans, 1)
        step = jax.jit(self.trainer.step, static_argnames=("sampler",), donate_argnums=(0,))
        t0 = time.perf_counter()
        self.compiled = step.lower(self.state, self.rays, self.frames, sampler=self.trainer.sampler(0)).compile()
        self.compile_s = time.perf_counter() - t0
        self.mlp_flops_per_point = mlp_flops_per_point(self.state.params["fields"])  # kernel shapes never change

    def run(self, n: int):
        state, metrics = self.state, None
        for _ in range(n):
            state, metrics = self.compiled(state, self.rays, self.frames)  # donated: feed the newest one back
        jax.block_until_ready((state, metrics))
        self.state = state
        return metrics

    def mlp_flops_per_step(self) -> int:
        """3 * points per step * forward FLOPs per point (see the module docstring)."""
        return 3 * points_per_step(self.sizes) * self.mlp_flops_per_point


def benchmark_train_step(
    config: ml_collections.ConfigDict,
    sizes: dict,
    steps: int,
    repeats: int,
    num_scans: int = 8,
    rays_per_scan: int = 4096,
    seed: int = 0,
    profile_dir: str = "",
    profile_steps: int = 5,
    dump_hlo: str = "",
) -> dict:
    """Compile, warm up and time the trainer's jitted step at `sizes`; returns the JSON-ready record."""
    runner = StepRunner(config, sizes, steps * repeats + profile_steps + 1, num_scans, rays_per_scan, seed)
    if dump_hlo:
        with open(dump_hlo, "w") as f:
            f.write(runner.compiled.as_text())
        logger.info("optimized HLO written to %s", dump_hlo)

    t0 = time.perf_counter()
    metrics = runner.run(1)
    warmup_s = time.perf_counter() - t0
    loss = float(metrics["loss"])
    median_s, times, median_cpu_s = median_seconds(lambda: runner.run(steps), repeats)

    profile = None
    if profile_dir:
        with jax.profiler.trace(profile_dir):
            runner.run(profile_steps)
        logger.info("profile of %d steps written under %s", profile_steps, profile_dir)
        traces = sorted(
            glob.glob(os.path.join(profile_dir, "plugins", "profile", "*", "*.xplane.pb")), key=os.path.getmtime
        )
        if traces:
            profile = summarize_profile(traces[-1], runner.compiled.as_text(), profile_steps)

    steps_per_s = steps / median_s
    samples_per_ray = sizes["coarse"] + sizes["guided"] + sizes["fine"]
    mlp_flops_step = runner.mlp_flops_per_step()
    return {
        "benchmark": "train_step",
        "steps_per_s": steps_per_s,
        "step_ms": 1e3 / steps_per_s,
        "cpu_ms_per_step": 1e3 * median_cpu_s / steps,  # all threads; ~ step_ms * threads kept busy
        "rays_per_s": steps_per_s * sizes["rays"],
        "samples_per_s": steps_per_s * points_per_step(sizes),
        "compile_s": runner.compile_s,
        "warmup_step_s": warmup_s,
        "mlp_flops_per_point_forward": runner.mlp_flops_per_point,
        "mlp_flops_per_step": mlp_flops_step,
        "achieved_gflops": mlp_flops_step * steps_per_s / 1e9,
        "achieved_gflops_per_cpu_s": mlp_flops_step * steps / median_cpu_s / 1e9,
        "xla_flops_per_step": xla_flops(runner.compiled),
        "repeat_s": times,
        "loss_after_warmup": loss,
        "profile": profile,
        **device_info(),
        "config": {
            **sizes,
            "skip_layers": list(runner.config.model.skip_layers),
            "samples_per_ray": samples_per_ray,
            "steps": steps,
            "repeats": repeats,
            "scans": num_scans,
            "rays_per_scan": rays_per_scan,
            "hierarchical": str(runner.config.sampling.hierarchical),
        },
    }


def benchmark_efficiency(
    config: ml_collections.ConfigDict,
    sizes: dict,
    steps: int,
    repeats: int,
    square_sizes: list[int],
    num_scans: int = 8,
    rays_per_scan: int = 4096,
    seed: int = 0,
) -> dict:
    """The step's GFLOP/s as a fraction of the matmul peak, both timed in this process, alternately.

    Each of `repeats` rounds times `steps` train steps, then each peak matmul (the square `square_sizes` and
    the MLP-shaped one); a round's efficiency is its step rate over its best matmul rate. Alternating makes
    the ratio robust to the machine's speed drifting (shared or throttled cores) between the two measurements.
    """
    runner = StepRunner(config, sizes, steps * repeats + 2, num_scans, rays_per_scan, seed)
    runner.run(1)  # warm-up
    mlp_name, mlp_shape = mlp_shaped_matmul(sizes)
    shapes = {**{str(n): (n, n, n) for n in square_sizes}, mlp_name: mlp_shape}
    matmuls = {name: MatmulTimer(*shape) for name, shape in shapes.items()}
    flops = runner.mlp_flops_per_step()
    rounds = []
    for _ in range(max(repeats, 1)):
        step_s, _, _ = median_seconds(lambda: runner.run(steps), 1)
        rates = {name: timer.gflops() for name, timer in matmuls.items()}
        achieved, peak = flops * steps / step_s / 1e9, max(rates.values())
        rounds.append(
            {"achieved_gflops": achieved, "peak_gflops": peak, "matmul_gflops": rates, "efficiency": achieved / peak}
        )
    median = lambda key: statistics.median(r[key] for r in rounds)  # noqa: E731
    return {
        "benchmark": "efficiency",
        "efficiency": median("efficiency"),
        "achieved_gflops": median("achieved_gflops"),
        "peak_gflops": median("peak_gflops"),
        "step_ms": flops / median("achieved_gflops") / 1e6,
        "mlp_flops_per_step": flops,
        "rounds": rounds,
        "compile_s": runner.compile_s,
        **device_info(),
        "config": {
            **sizes,
            "skip_layers": list(runner.config.model.skip_layers),
            "steps": steps,
            "repeats": repeats,
            "square_sizes": list(square_sizes),
        },
    }


def fit_setup(
    config: ml_collections.ConfigDict,
    sizes: dict,
    steps: int,
    repeats: int,
    log_every: int,
    num_scans: int,
    rays_per_scan: int,
    seed: int,
):
    """(runner, the fit config, plan_of, fit_steps, timed_steps) for timing train.fit in chunks of log_every steps
    (the first chunk compiles and is not timed)."""
    log_every = max(int(log_every), 1)
    chunks = max(1, math.ceil(steps / log_every))
    fit_steps = log_every * (chunks + 1)
    timed_steps = log_every * chunks
    runner = StepRunner(config, sizes, timed_steps * repeats + 2, num_scans, rays_per_scan, seed)
    runner.run(1)  # warm-up
    fit_config = configure(config, sizes, train_steps=fit_steps)
    fit_config.seed = seed
    fit_config.train.log_every = log_every
    fit_config.train.checkpoint_every = log_every  # the hook below runs at every chunk end; no chunk is cut
    fit_config.max_minutes = 0.0
    fit_config.train.pose_start_freq = 0  # poses move from step 0: every chunk is log_every steps long
    return runner, fit_config, functools.partial(trainer_for, fit_config, runner.cube), fit_steps, timed_steps


def timed_fit(
    fit_config: ml_collections.ConfigDict,
    plan_of: Callable,
    runner: "StepRunner",
    fit_steps: int,
    on_log: Callable | None = None,
) -> dict:
    """One train.fit from a fresh state; its rate from the wall and CPU clocks between the first and the last chunk
    end (a checkpoint_fn hook, called once a chunk's metrics are fetched and on_log has run)."""
    marks = []  # (step, wall s, process CPU s) at each chunk end

    def mark(state, history, seconds):
        marks.append((int(state.step), time.perf_counter(), time.process_time()))

    state = train.init_state(fit_config, plan_of(fit_steps), len(runner.cube.start_poses), 1)
    t0 = time.perf_counter()
    result = train.fit(
        fit_config,
        plan_of,
        train.TrainingData(runner.rays, runner.frames, SYNTHETIC_SCALE),
        state,
        checkpoint_fn=mark,
        settings=train.FitSettings(progress=False, on_log=on_log),
    )
    (first_step, first_wall, first_cpu), (last_step, last_wall, last_cpu) = marks[0], marks[-1]
    return {
        "steps_per_s": (last_step - first_step) / (last_wall - first_wall),
        "cpu_ms_per_step": 1e3 * (last_cpu - first_cpu) / (last_step - first_step),
        "total_s": time.perf_counter() - t0,
        "final_loss": result.history[-1]["loss"],
    }


def benchmark_fit(
    config: ml_collections.ConfigDict,
    sizes: dict,
    steps: int,
    repeats: int,
    log_every: int,
    num_scans: int = 8,
    rays_per_scan: int = 4096,
    seed: int = 0,
) -> dict:
    """Steps/s of train.fit against the bare jitted step at `sizes`, alternately (module docstring, --fit)."""
    runner, fit_config, plan_of, fit_steps, timed_steps = fit_setup(
        config, sizes, steps, repeats, log_every, num_scans, rays_per_scan, seed
    )
    rounds = []
    for _ in range(max(repeats, 1)):
        fitted = timed_fit(fit_config, plan_of, runner, fit_steps)
        step_s, _, step_cpu_s = median_seconds(lambda: runner.run(timed_steps), 1)
        step_rate, step_cpu_ms = timed_steps / step_s, 1e3 * step_cpu_s / timed_steps
        rounds.append(
            {
                "fit_steps_per_s": fitted["steps_per_s"],
                "step_steps_per_s": step_rate,
                "ratio": fitted["steps_per_s"] / step_rate,
                "fit_cpu_ms_per_step": fitted["cpu_ms_per_step"],
                "step_cpu_ms_per_step": step_cpu_ms,
                "cpu_ratio": step_cpu_ms / fitted["cpu_ms_per_step"],
                "fit_total_s": fitted["total_s"],
                "fit_final_loss": fitted["final_loss"],
            }
        )
    median = lambda key: statistics.median(r[key] for r in rounds)  # noqa: E731
    return {
        "benchmark": "fit",
        "ratio": median("ratio"),
        "cpu_ratio": median("cpu_ratio"),  # step CPU time / fit CPU time per step: steadier on a shared machine
        "fit_steps_per_s": median("fit_steps_per_s"),
        "step_steps_per_s": median("step_steps_per_s"),
        "fit_step_ms": 1e3 / median("fit_steps_per_s"),
        "step_ms": 1e3 / median("step_steps_per_s"),
        "fit_cpu_ms_per_step": median("fit_cpu_ms_per_step"),
        "step_cpu_ms_per_step": median("step_cpu_ms_per_step"),
        "rounds": rounds,
        "compile_s": runner.compile_s,
        **device_info(),
        "config": {
            **sizes,
            "skip_layers": list(runner.config.model.skip_layers),
            "log_every": log_every,
            "fit_steps": fit_steps,
            "timed_steps": timed_steps,
            "repeats": repeats,
            "scans": len(runner.cube.start_poses),
            "rays_per_scan": rays_per_scan,
        },
    }


def benchmark_viewer(
    config: ml_collections.ConfigDict,
    sizes: dict,
    steps: int,
    repeats: int,
    log_every: int,
    num_scans: int = 8,
    rays_per_scan: int = 4096,
    seed: int = 0,
) -> dict:
    """Steps/s of train.fit with the live viewer's hook against fit without it, alternately (--viewer): the hook a
    run with viz.live gets (neld_jax.writing.viewer: run.rrd and a gRPC server on a free local port; the training curves
    and the keyframes' poses at every log, as neld_jax.steps.refine hands them over)."""
    import socket
    import tempfile

    from neld_jax.steps.refine import posed
    from neld_jax.writing import viewer

    runner, fit_config, plan_of, fit_steps, timed_steps = fit_setup(
        config, sizes, steps, repeats, log_every, num_scans, rays_per_scan, seed
    )
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        viewer.LIVE_PORT = s.getsockname()[1]
    fit_config.viz.live = True
    start_poses = runner.cube.start_poses
    rounds = []
    with tempfile.TemporaryDirectory() as folder:
        live = viewer.RunViewer.open(folder, fit_config.viz)
        on_log = posed(live.training_hook(), start_poses, SYNTHETIC_SCALE)  # the hook a run hands fit
        for r in range(max(repeats, 1)):
            order = (None, on_log) if r % 2 == 0 else (on_log, None)
            timed = {("live" if h else "plain"): timed_fit(fit_config, plan_of, runner, fit_steps, h) for h in order}
            rounds.append(
                {
                    "plain_steps_per_s": timed["plain"]["steps_per_s"],
                    "live_steps_per_s": timed["live"]["steps_per_s"],
                    "slowdown": timed["plain"]["steps_per_s"] / timed["live"]["steps_per_s"] - 1.0,
                    "plain_cpu_ms_per_step": timed["plain"]["cpu_ms_per_step"],
                    "live_cpu_ms_per_step": timed["live"]["cpu_ms_per_step"],
                }
            )
        live.close()
    median = lambda key: statistics.median(r[key] for r in rounds)  # noqa: E731
    return {
        "benchmark": "viewer",
        "slowdown": median("slowdown"),  # wall time a step with the live hook, over one without, less 1
        "slowdown_per_round": [r["slowdown"] for r in rounds],
        "plain_step_ms": 1e3 / median("plain_steps_per_s"),
        "live_step_ms": 1e3 / median("live_steps_per_s"),
        "viewer_seconds": live.seconds,
        "rounds": rounds,
        **device_info(),
        "config": {
            **sizes,
            "log_every": log_every,
            "fit_steps": fit_steps,
            "timed_steps": timed_steps,
            "repeats": repeats,
            "scans": len(start_poses),
            "rays_per_scan": rays_per_scan,
        },
    }


class MatmulTimer:
    """A jitted [m, k] @ [k, n] on random inputs (float32, or bfloat16 inputs with float32 sums); gflops() times
    a batch of calls lasting ~min_seconds."""

    def __init__(self, m: int, k: int, n: int, seed: int = 0, min_seconds: float = 0.05, dtype: str = "float32"):
        key_a, key_b = jax.random.split(jax.random.PRNGKey(seed))
        self.a = jax.random.normal(key_a, (m, k), jnp.float32).astype(dtype)
        self.b = jax.random.normal(key_b, (k, n), jnp.float32).astype(dtype)
        self.flops = 2.0 * m * k * n
        self.matmul = jax.jit(lambda a, b: jnp.matmul(a, b, preferred_element_type=jnp.float32))
        jax.block_until_ready(self.matmul(self.a, self.b))  # compile and warm up
        t0 = time.perf_counter()
        jax.block_until_ready(self.matmul(self.a, self.b))
        self.calls = max(1, int(min_seconds / max(time.perf_counter() - t0, 1e-6)))

    def run(self):
        out = None
        for _ in range(self.calls):
            out = self.matmul(self.a, self.b)
        jax.block_until_ready(out)

    def gflops(self, repeats: int = 1) -> float:
        return self.rates(repeats)[0]

    def rates(self, repeats: int) -> tuple[float, float]:
        """(GFLOP/s, GFLOP per CPU second), medians of `repeats` batches."""
        median_s, _, median_cpu_s = median_seconds(self.run, repeats)
        return self.flops * self.calls / median_s / 1e9, self.flops * self.calls / median_cpu_s / 1e9


def matmul_gflops(
    m: int, k: int, n: int, repeats: int, min_seconds: float = 0.05, seed: int = 0, dtype: str = "float32"
) -> tuple[float, float]:
    """(GFLOP/s, GFLOP per CPU second) of a jitted [m, k] @ [k, n] (2 m k n FLOPs), medians of `repeats` batches
    of calls lasting >= min_seconds each."""
    return MatmulTimer(m, k, n, seed, min_seconds, dtype).rates(repeats)


def benchmark_matmul_peak(sizes: dict, square_sizes: list[int], repeats: int, dtype: str = "float32") -> dict:
    """Matmul GFLOP/s (float32, or bfloat16 inputs with float32 sums): square n x n matmuls and the MLP's
    [points, width] @ [width, width] matmul."""
    mlp_name, mlp_shape = mlp_shaped_matmul(sizes)
    square = {str(n): matmul_gflops(n, n, n, repeats, dtype=dtype) for n in square_sizes}
    mlp_shaped = {mlp_name: matmul_gflops(*mlp_shape, repeats, dtype=dtype)}
    rates = [*square.values(), *mlp_shaped.values()]
    return {
        "benchmark": "matmul_peak",
        "gflops": max(wall for wall, _ in rates),
        "gflops_per_cpu_s": max(cpu for _, cpu in rates),
        "square_gflops": {n: wall for n, (wall, _) in square.items()},
        "mlp_shaped_gflops": {s: wall for s, (wall, _) in mlp_shaped.items()},
        "square_gflops_per_cpu_s": {n: cpu for n, (_, cpu) in square.items()},
        "mlp_shaped_gflops_per_cpu_s": {s: cpu for s, (_, cpu) in mlp_shaped.items()},
        **device_info(),
        "config": {"dtype": dtype, "repeats": repeats, "points": mlp_shape[0], "width": mlp_shape[1]},
    }


# ----------------------------------------------------------------------------------------------------------


def resolve_sizes() -> tuple[ml_collections.ConfigDict, dict]:
    """The preset's config and sizes, with every size flag given on the command line taking precedence."""
    preset = "cpu" if FLAGS.preset == "none" else FLAGS.preset
    preset_config = with_budget(defaults(), preset)
    stages = len(preset_config.sampling.coarse_stages)
    if not 0 <= FLAGS.stage < stages:
        raise app.UsageError(f"--stage={FLAGS.stage}: the {preset} preset has stages 0..{stages - 1}")
    config, sizes = preset_sizes(preset, FLAGS.stage)
    for name in SIZE_FLAGS:
        if FLAGS.preset == "none" or FLAGS[name].present:
            value = FLAGS[name].value
            sizes[name] = tuple(int(v) for v in value) if name == "skip_layers" else int(value)
    sizes["matmul_dtype"] = FLAGS.matmul_dtype
    for name in ("rays", "coarse", "width", "depth", "steps", "repeats", "scans", "rays_per_scan"):
        value = sizes[name] if name in sizes else FLAGS[name].value
        if value < 1:
            raise app.UsageError(f"--{name} must be at least 1, got {value}")
    for name in ("fine", "guided", "pos_freqs", "dir_freqs"):
        if sizes[name] < 0:
            raise app.UsageError(f"--{name} must not be negative, got {sizes[name]}")
    return config, sizes


def main(argv):
    del argv
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    config, sizes = resolve_sizes()
    if FLAGS.matmul_peak + FLAGS.efficiency + FLAGS.fit + FLAGS.viewer > 1:
        raise app.UsageError("--matmul_peak, --efficiency, --fit and --viewer are different modes: give one")
    if FLAGS.fit or FLAGS.viewer:
        preset = "cpu" if FLAGS.preset == "none" else FLAGS.preset
        log_every = FLAGS.log_every or int(preset_sizes(preset)[0].train.log_every)
        record = (benchmark_viewer if FLAGS.viewer else benchmark_fit)(
            config, sizes, FLAGS.steps, FLAGS.repeats, log_every, FLAGS.scans, FLAGS.rays_per_scan, FLAGS.seed
        )
    elif FLAGS.matmul_peak:
        record = benchmark_matmul_peak(sizes, [int(n) for n in FLAGS.matmul_sizes], FLAGS.repeats, FLAGS.matmul_dtype)
    elif FLAGS.efficiency:
        record = benchmark_efficiency(
            config,
            sizes,
            FLAGS.steps,
            FLAGS.repeats,
            [int(n) for n in FLAGS.matmul_sizes],
            FLAGS.scans,
            FLAGS.rays_per_scan,
            FLAGS.seed,
        )
    else:
        record = benchmark_train_step(
            config,
            sizes,
            FLAGS.steps,
            FLAGS.repeats,
            FLAGS.scans,
            FLAGS.rays_per_scan,
            FLAGS.seed,
            FLAGS.profile_dir,
            FLAGS.profile_steps,
            FLAGS.dump_hlo,
        )
    record["preset"] = FLAGS.preset
    print(json.dumps(record), flush=True)  # the one line of stdout a caller parses
    harness.write(FLAGS.out, record)


if __name__ == "__main__":
    reexec_with_huge_page_malloc()  # ~25% faster CPU steps: see neld_jax/hugepages.py
    app.run(main)
