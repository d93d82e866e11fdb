#!/usr/bin/env python
"""Every GPU measurement in one process, within a time budget, into one JSON file.

    python benchmarks/gpu_suite.py --prepare              # here (open3d needed): the demo's rays and poses
    bash benchmarks/gpu_suite.sh                          # on the GPU machine (installs .whl/ if needed)
    python benchmarks/gpu_suite.py --smoke                # the same path end to end on tiny sizes, any backend

A GPU image may lack open3d (and ml-collections, which gpu_suite.sh installs from .whl/), so the demo sequence
is generated here by `--prepare` into .gpu_data/demo.npz (the keyframes' rays in metres, initial and ground-truth
poses, the normalisation of its one cube) and the suite trains on it with neld_jax.training.train alone, as a plan of
one cube (train.make_trainer, train.init_state, train.fit: the path a run takes).

Sections, in order of priority (each is skipped once --budget_s is spent; a failing one records its error
and the next runs):
- step_per_stage: the paper-size step at each sample-count stage (train_step.benchmark_train_step).
- matmul_peak: float32 and bfloat16 matmul peaks at the paper's MLP shape and squares.
- fit_vs_step: train.fit's fused loop against the bare step, at the paper's stage 0 and the gpu budget's size.
- demo_gpu: the demo with the gpu budget: ATE every checkpoint_every steps against the training seconds.
- paper_schedule: the paper budget's fit steps/s in each stage (runs from each stage's first step, stopped after
  a few seconds of chunks), extrapolated to the whole 160k-step schedule.
- render_map: the rendered map of every demo ray at the paper's 128 + 128 samples, for a few batch sizes.
- bfloat16: the paper-size step with model.matmul_dtype=bfloat16, and the demo's ATE with it.
- torch_peer: benchmarks/torch_peer.py at the paper's last stage on CUDA (eager, TF32, torch.compile), when
  torch is installed.
Output: $OUT/gpu_suite.json (OUT defaults to benchmarks/results/), rewritten after every section.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import subprocess
import sys
import time
import traceback
from typing import NamedTuple

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
import numpy as np
import train_step as ts  # this folder's benchmarks/train_step.py (its flags are defined too; the suite sets sizes)
from absl import app, flags

from neld_jax.hugepages import reexec_with_huge_page_malloc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

logger = logging.getLogger("gpu_suite")
FLAGS = flags.FLAGS
flags.DEFINE_bool("smoke", False, "Tiny sizes and steps everywhere: checks the whole path on any backend in minutes.")
flags.DEFINE_bool("prepare", False, "Write the demo's rays and poses to --data (needs open3d) and exit.")
flags.DEFINE_string("data", os.path.join(ROOT, ".gpu_data", "demo.npz"), "The prepared demo (--prepare).")
flags.DEFINE_float("budget_s", 450.0, "Start no section after this many seconds.")
flags.DEFINE_list("sections", [], "Run only these sections (default: all).")
# --out (benchmarks/harness.py, through train_step): the JSON file; default gpu_suite[_smoke].json in $OUT, else in
# benchmarks/results/.

SECTIONS = (
    "step_per_stage",
    "matmul_peak",
    "fit_vs_step",
    "demo_gpu",
    "paper_schedule",
    "render_map",
    "bfloat16",
    "torch_peer",
)
TINY = {"rays": 16, "width": 8, "depth": 2, "skip_layers": (1,), "pos_freqs": 4, "dir_freqs": 2}


# ----------------------------------------------------------------------------------------------------------
# Pure helpers


def extrapolate_schedule(stage_starts: tuple, total: int, rates: list) -> dict:
    """Seconds of a whole schedule from steps/s per stage: sum over stages of (steps in the stage) / rate."""
    ends = list(stage_starts[1:]) + [total]
    steps = [end - start for start, end in zip(stage_starts, ends)]
    seconds = [n / r for n, r in zip(steps, rates)]
    return {
        "stage_steps": steps,
        "stage_seconds": seconds,
        "total_s": sum(seconds),
        "mean_steps_per_s": total / sum(seconds),
    }


def ate_m(poses: np.ndarray, start_poses: np.ndarray, gt_poses: np.ndarray, ref_scale: float) -> dict:
    """ATE (SE(3)-aligned, neld_jax.judging.metrics) of the corrected poses: poses [S, 6] (rho in units of ref_scale per
    metre) on the start poses [S, 4, 4] (metres), against the ground truth [S, 4, 4] (metres)."""
    from neld_jax.field.model import world_poses
    from neld_jax.judging import metrics

    result = metrics.ate(world_poses(start_poses, np.asarray(poses), ref_scale), gt_poses)
    return {"ate_m": result["translation_rmse_m"], "rot_deg": result["rotation_rmse_deg"]}


# ----------------------------------------------------------------------------------------------------------
# The demo's data


def demo_config(budget: str):
    """configs/demo.py at `budget`."""
    from neld_jax.config import from_file

    return from_file(os.path.join(ROOT, "configs", "demo.py"), budget)


def prepare(path: str, smoke: bool) -> dict:
    """Generate the demo sequence (configs/demo.py, gpu budget's rays per scan) and save what training needs: the
    keyframes' rays in metres, their initial and ground-truth poses, and the normalisation of one cube around them."""
    from neld_jax.field.normalize import NORMALIZATION_MARGIN, Normalization, fit_normalization
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.training.rays import build_rays

    config = demo_config("gpu")
    if smoke:
        s = config.data.synthetic
        s.num_scans, s.num_beams, s.num_columns, s.gt_map_points = 4, 8, 64, 2000
        s.scene_size_m, s.trajectory_radius_m, s.max_range_m = 30.0, 5.0, 30.0
        config.data.max_rays_per_scan = 256
    _, keyframes = load_keyframes(config.data)
    norm = fit_normalization(keyframes.scans, keyframes.poses, NORMALIZATION_MARGIN)
    rays = build_rays(
        keyframes, Normalization(1.0), max_rays_per_scan=(config.data.max_rays_per_scan or None), seed=config.seed
    )
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(
        path,
        directions=rays.directions,
        ranges_m=rays.ranges,
        scan_index=rays.scan_index,
        poses=keyframes.poses,
        gt_poses=keyframes.gt_poses,
        scale=norm.scale,
        offset=norm.offset,
    )
    return {"path": path, "num_scans": keyframes.num_scans, "num_rays": int(rays.num_rays), "scale": float(norm.scale)}


class Demo(NamedTuple):
    """The prepared demo as the trainer takes it: rays (RaySet, metres), the one cube's (Rays, Frames) on a
    one-device mesh, the start and ground-truth poses [S, 4, 4] (metres) and the cube's scale."""

    rays_m: object
    rays: object
    frames: object
    start_poses: np.ndarray
    gt_poses: np.ndarray
    scale: float
    plan: object
    mesh: object

    @property
    def num_scans(self) -> int:
        return len(self.start_poses)


def load_demo(path: str) -> Demo:
    """The prepared demo (`prepare`) as a plan of one cube, placed on one device."""
    from neld_jax.field.normalize import Normalization
    from neld_jax.training import submaps, train
    from neld_jax.training.rays import RaySet

    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no prepared demo; run `python benchmarks/gpu_suite.py --prepare` first")
    d = np.load(path)
    if "ranges_m" not in d:
        raise FileNotFoundError(
            f"{path}: a demo prepared in another layout; run `python benchmarks/gpu_suite.py --prepare` again"
        )
    rays_m = RaySet(d["directions"], d["ranges_m"], d["scan_index"])
    scale = float(d["scale"])
    num_scans = len(d["poses"])
    plan = submaps.one_cube_plan(num_scans, Normalization(scale, d["offset"]))
    mesh = train.make_mesh(1)
    rays, frames = train.device_data(submaps.submap_arrays(plan, rays_m, d["poses"]), mesh)
    return Demo(rays_m, rays, frames, d["poses"], d["gt_poses"], scale, plan, mesh)


def demo_trainer(config, demo: Demo, total_steps: int | None = None):
    """train.make_trainer of the demo's one cube with the config's own pose steps (a run from the input poses)."""
    from neld_jax.training import train

    return train.make_trainer(
        config,
        demo.num_scans,
        1,
        train.PoseSteps.from_config(config),
        demo.start_poses,
        total_steps=total_steps,
        mesh=demo.mesh,
    )


class _Enough(Exception):
    """Raised from fit's checkpoint hook once a measurement has the chunks it needs."""


# ----------------------------------------------------------------------------------------------------------
# Sections


class Suite:
    def __init__(self, out_path: str, smoke: bool, budget_s: float, data: str):
        self.out_path, self.smoke, self.budget_s, self.data = out_path, smoke, budget_s, data
        self.t0 = time.perf_counter()
        self.record = {"benchmark": "gpu_suite", "smoke": smoke, **ts.device_info(), "sections": {}}
        self.stamped = None  # the record's schema around it, stamped at the first write
        self._demo = None

    def demo(self):
        if self._demo is None:
            self._demo = load_demo(self.data)
        return self._demo

    def sizes(self, preset: str, stage: int = 0) -> tuple:
        config, sizes = ts.preset_sizes(preset, stage)
        if self.smoke:
            sizes.update(
                TINY,
                coarse=max(2, sizes["coarse"] // 8),
                fine=max(1, sizes["fine"] // 8),
                guided=min(sizes["guided"], 2),
            )
        return config, sizes

    def config(self, budget: str):
        config = demo_config(budget)
        if self.smoke:
            config.model.width, config.model.depth, config.model.skip_layers = 8, 2, (1,)
            config.model.pos_freqs, config.model.dir_freqs = 4, 2
            config.train.batch_rays = 16
            config.mapping.num_coarse, config.mapping.num_fine = 8, 8
        return config

    def run(self, names):
        for name in names:
            elapsed = time.perf_counter() - self.t0
            if elapsed > self.budget_s:
                skipped = f"time budget spent ({elapsed:.0f} of {self.budget_s:.0f} s)"
                self.record["sections"][name] = {"skipped": skipped}
                continue
            logger.info("section %s (%.0f s in)", name, elapsed)
            t = time.perf_counter()
            try:
                result = getattr(self, name)()
            except Exception as e:  # one failing measurement must not cost the others
                result = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()[-3000:]}
                logger.error("section %s failed: %s", name, e)
            result["section_s"] = time.perf_counter() - t
            self.record["sections"][name] = result
            self.record["elapsed_s"] = time.perf_counter() - self.t0
            self.stamped = harness.write(self.out_path, self.record, stamped=self.stamped)
        return self.record

    def step_per_stage(self):
        steps, repeats = (2, 1) if self.smoke else (50, 3)
        out = {}
        for stage in range(3):
            config, sizes = self.sizes("paper", stage)
            r = ts.benchmark_train_step(config, sizes, steps, repeats)
            out[f"stage{stage}"] = {
                k: r[k]
                for k in (
                    "steps_per_s",
                    "step_ms",
                    "achieved_gflops",
                    "compile_s",
                    "mlp_flops_per_step",
                    "xla_flops_per_step",
                    "config",
                )
            }
        return out

    def matmul_peak(self):
        _, sizes = self.sizes("paper", 2)
        squares, repeats = ([64], 1) if self.smoke else ([1024, 2048, 4096, 8192], 3)
        out = {dtype: ts.benchmark_matmul_peak(sizes, squares, repeats, dtype) for dtype in ("float32", "bfloat16")}
        stage2 = self.record["sections"].get("step_per_stage", {}).get("stage2")
        if stage2:
            out["stage2_step_fraction_of_float32_peak"] = stage2["achieved_gflops"] / out["float32"]["gflops"]
        return out

    def fit_vs_step(self):
        out = {}
        for preset, steps, log_every in (("paper", 400, 100), ("gpu", 5000, 500)):
            if self.smoke:
                steps, log_every = 4, 2
            config, sizes = self.sizes(preset)
            out[preset] = ts.benchmark_fit(config, sizes, steps, 1 if self.smoke else 2, log_every)
        return out

    def _demo_run(self, budget: str, matmul_dtype: str = "float32"):
        import functools

        from neld_jax.training import train

        demo = self.demo()
        config = self.config(budget)
        config.model.matmul_dtype = matmul_dtype
        if self.smoke:
            config.train.steps, config.train.log_every, config.train.checkpoint_every = 20, 5, 10
        probes = []

        def probe(state, history, seconds):  # at every checkpoint step and the end: the ATE so far
            probes.append(
                {
                    "step": int(state.step),
                    "train_s": seconds,
                    **ate_m(np.asarray(state.params["poses"]), demo.start_poses, demo.gt_poses, demo.scale),
                }
            )

        plan_of = functools.partial(demo_trainer, config, demo)
        state = train.init_state(config, plan_of(), demo.num_scans, 1)
        result = train.fit(
            config,
            plan_of,
            train.TrainingData(demo.rays, demo.frames, demo.scale),
            state,
            checkpoint_fn=probe,
            settings=train.FitSettings(progress=False),
        )
        initial = ate_m(np.zeros((demo.num_scans, 6), np.float32), demo.start_poses, demo.gt_poses, demo.scale)
        final = probes[-1]
        return {
            "budget": budget,
            "matmul_dtype": matmul_dtype,
            "steps": int(result.state.step),
            "train_s": result.train_seconds,
            "first_chunk_s": result.history[0]["elapsed_s"],
            "initial_ate_m": initial["ate_m"],
            "final_ate_m": final["ate_m"],
            "ate_fraction_of_initial": final["ate_m"] / initial["ate_m"],
            "probes": probes,
            "target": "ATE <= 0.01 x initial within 30 s of training",
        }

    def demo_gpu(self):
        return self._demo_run("gpu")

    def paper_schedule(self):
        import functools

        import jax
        import jax.numpy as jnp

        from neld_jax.training import train

        demo = self.demo()
        config = self.config("paper")
        if self.smoke:
            config.train.log_every = 10
        config.train.checkpoint_every = config.train.log_every  # the hook below sees every chunk end
        plan_of = functools.partial(demo_trainer, config, demo)
        schedules = plan_of().schedules
        stage_steps = self.record["sections"].get("step_per_stage", {})
        rates = []
        per_stage = []
        for i, start in enumerate(schedules.stage_starts):
            # Chunks for 1.5x the step's compile time (measured above) plus 12 s (smoke: 6 s), and two at least:
            # the first chunk compiles and is not counted; fit is stopped from its hook, so that its plan stays the
            # whole schedule's (a time limit of its own would compress it).
            compile_s = stage_steps.get(f"stage{i}", {}).get("compile_s", 5.0 if self.smoke else 30.0)
            allowed_s = 1.5 * compile_s + (6.0 if self.smoke else 12.0)
            state = train.init_state(config, plan_of(), demo.num_scans, 1)
            # at the stage's first step, placed as the step's output is (another placement would compile again)
            state = state.replace(step=jax.device_put(jnp.asarray(start, jnp.int32), state.step.sharding))
            marks = []  # (step, seconds) at each chunk end

            def mark(state, history, seconds, marks=marks):
                marks.append((int(state.step), time.perf_counter()))
                if len(marks) >= 2 and marks[-1][1] - t > allowed_s:
                    raise _Enough

            t = time.perf_counter()
            try:
                train.fit(
                    config,
                    plan_of,
                    train.TrainingData(demo.rays, demo.frames, demo.scale),
                    state,
                    checkpoint_fn=mark,
                    settings=train.FitSettings(progress=False),
                )
            except _Enough:
                pass
            if len(marks) < 2:
                raise RuntimeError(f"stage {i}: only {len(marks)} chunk ran (the schedule ended)")
            (first_step, first_t), (last_step, last_t) = marks[0], marks[-1]
            rate = (last_step - first_step) / max(last_t - first_t, 1e-9)
            rates.append(rate)
            per_stage.append(
                {
                    "start": start,
                    "steps_run": last_step - start,
                    "steps_per_s": rate,
                    "samples": schedules.samples(start),
                    "wall_s": time.perf_counter() - t,
                }
            )
        return {
            "stages": per_stage,
            **extrapolate_schedule(schedules.stage_starts, schedules.total_steps, rates),
            "target": "the 160k-step schedule in <= 600 s (>= 270 steps/s)",
        }

    def render_map(self):
        from neld_jax.steps import mapping, refine
        from neld_jax.training import train

        demo = self.demo()
        out = {}
        for budget in ("gpu", "paper"):
            config = self.config(budget)
            trainer = demo_trainer(config, demo)
            state = train.init_state(config, trainer, demo.num_scans, 1)
            total = trainer.schedules.total_steps  # every frequency active, as after training
            result = train.FitResult(state.replace(step=state.step + total), [], False, 0.0, trainer.schedules)
            refined = refine.Refined(
                result,
                demo.plan,
                trainer.field,
                demo.start_poses,
                demo.start_poses,
                np.eye(4),
                np.bincount(demo.rays_m.scan_index, minlength=demo.num_scans),
            )
            sampler = train.sampler_settings(config.sampling, config.mapping.num_coarse, config.mapping.num_fine)
            rows = []
            # A [rays x 256 samples, width] float32 activation is 4 GiB at 8192 rays and width 512.
            default_batch = mapping.RAYS_PER_BATCH
            for batch in (64,) if self.smoke else (4096, 16384, 32768):

                def render():
                    return mapping.render_map(refined, demo.rays_m, sampler, min_opacity=0.0)

                mapping.RAYS_PER_BATCH = batch  # the rays a device call renders (a constant of the module)
                try:
                    t = time.perf_counter()
                    render()  # compiles
                    first_s = time.perf_counter() - t
                    t = time.perf_counter()
                    render()
                    seconds = time.perf_counter() - t
                except Exception as e:  # out of memory at this batch size: keep the others
                    rows.append({"rays_per_batch": batch, "error": f"{type(e).__name__}: {str(e)[:300]}"})
                    continue
                finally:
                    mapping.RAYS_PER_BATCH = default_batch
                rows.append(
                    {
                        "rays_per_batch": batch,
                        "seconds": seconds,
                        "rays_per_s": demo.rays_m.num_rays / seconds,
                        "first_call_s": first_s,
                    }
                )
            out[budget] = {
                "width": config.model.width,
                "depth": config.model.depth,
                "rays": demo.rays_m.num_rays,
                "samples": [sampler.num_coarse, sampler.num_fine],
                "batches": rows,
            }
        return out

    def bfloat16(self):
        steps, repeats = (2, 1) if self.smoke else (50, 3)
        config, sizes = self.sizes("paper", 2)
        out = {"step_stage2": {}}
        for dtype in ("float32", "bfloat16"):
            r = ts.benchmark_train_step(config, dict(sizes, matmul_dtype=dtype), steps, repeats)
            out["step_stage2"][dtype] = {k: r[k] for k in ("steps_per_s", "step_ms", "achieved_gflops")}
        out["demo_gpu_bfloat16"] = self._demo_run("gpu", "bfloat16")
        return out

    def torch_peer(self):
        if importlib.util.find_spec("torch") is None:
            return {"skipped": "torch is not installed"}
        import torch

        cuda = torch.cuda.is_available()
        args = [
            sys.executable,
            os.path.join(ROOT, "benchmarks", "torch_peer.py"),
            "--torch_device=" + ("cuda" if cuda else "cpu"),
            "--torch_modes=" + ("eager,tf32,compile" if cuda else "eager"),
        ]
        args += (
            [
                "--preset=none",
                "--steps=2",
                "--repeats=1",
                "--rays=16",
                "--coarse=4",
                "--fine=2",
                "--width=8",
                "--depth=2",
                "--skip_layers=1",
                "--scans=2",
                "--rays_per_scan=64",
            ]
            if self.smoke
            else ["--preset=paper", "--stage=2", "--steps=20", "--repeats=3"]
        )
        left = max(60.0, self.budget_s + 150 - (time.perf_counter() - self.t0))
        # The peer's process runs a JAX step too: JAX there and here must leave the GPU's memory to torch.
        env = dict(os.environ, XLA_PYTHON_CLIENT_MEM_FRACTION="0.25")
        proc = subprocess.run(args, capture_output=True, text=True, timeout=left, cwd=ROOT, env=env)
        if proc.returncode != 0:
            return {"error": proc.stderr[-3000:]}
        return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv):
    del argv
    logging.basicConfig(
        level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )
    logging.getLogger("neld_jax.training.train").setLevel(logging.WARNING)
    if FLAGS.prepare:
        print(json.dumps(prepare(FLAGS.data, FLAGS.smoke)), flush=True)
        return
    names = FLAGS.sections or list(SECTIONS)
    unknown = set(names) - set(SECTIONS)
    if unknown:
        raise app.UsageError(f"unknown --sections {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    out_dir = os.environ.get("OUT") or os.path.join(ROOT, "benchmarks", "results")
    out_path = FLAGS.out or os.path.join(out_dir, "gpu_suite_smoke.json" if FLAGS.smoke else "gpu_suite.json")
    record = Suite(out_path, FLAGS.smoke, FLAGS.budget_s, FLAGS.data).run(names)
    summary = {
        name: ("error" if "error" in r else "skipped" if "skipped" in r else "ok")
        for name, r in record["sections"].items()
    }
    print(json.dumps({"out": out_path, "elapsed_s": record.get("elapsed_s"), "sections": summary}), flush=True)


if __name__ == "__main__":
    reexec_with_huge_page_malloc()
    app.run(main)
