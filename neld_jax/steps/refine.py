"""NeLD-BA on a sequence's keyframes: plan the cubes, stack their rays, train the field(s) and the poses (resuming
from the output folder's checkpoints), and bring the poses back into the world.

One path for one cube and for many: a sequence that one cube holds is a plan of one submap (neld_jax.training.submaps).
Needs no open3d: a GPU image without it runs this step alone (benchmarks/real_gpu.py).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from typing import Callable

import jax
import ml_collections
import numpy as np

from neld_jax.field.model import world_poses
from neld_jax.field.normalize import Normalization
from neld_jax.geometry import anchored_on_first
from neld_jax.training import submaps, train
from neld_jax.training.checkpoint import fit_resuming
from neld_jax.training.rays import build_rays

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Refined:
    """What training gave: the FitResult (its schedules: the plan that ran), the plan of cubes, the field module,
    and the keyframes' poses in the world [K, 4, 4]: `poses` anchored on keyframe 0 (it keeps its start pose; the
    outputs), `poses_in_field` as the fields see them (the rendered map's rays) and `anchor` [4, 4] the rigid
    transform from the one to the other (poses = anchor @ poses_in_field); rays_per_keyframe [K]: training rays."""

    result: train.FitResult
    plan: submaps.SubmapPlan
    field: object
    poses: np.ndarray
    poses_in_field: np.ndarray
    anchor: np.ndarray
    rays_per_keyframe: np.ndarray

    @property
    def alpha(self) -> float:
        """The coarse-to-fine window the fields were trained with."""
        return float(self.result.schedules.alpha(int(self.result.state.step)))


@dataclasses.dataclass(frozen=True)
class TrainingContext:
    """Where and how a run's training runs, besides what it trains: out_dir, whose checkpoints/ it resumes from and
    writes (a checkpoint of another config_hash, other keyframes or another plan is an error); max_seconds, its
    wall-clock limit (0: none); progress, a progress bar; on_log(entry, poses [K, 4, 4]), a viewer's hook that sees
    each history entry with the keyframes' poses of that step, anchored as the outputs are; on_checkpoint(), run
    before each checkpoint is saved (the run's clock, neld_jax.writing.output_folder.record_seconds)."""

    out_dir: str
    config_hash: str
    max_seconds: float = 0.0
    progress: bool = True
    on_log: Callable[[dict, np.ndarray], None] | None = None
    on_checkpoint: Callable[[], None] | None = None


@dataclasses.dataclass(frozen=True)
class TrainingSettings:
    """What training reads, each group as the config has it: train, model, sampling, submaps and loss (config.<group>),
    seed (config.seed) and max_rays_per_scan (config.data.max_rays_per_scan; 0: every ray). Built once at the edge
    (`from_config`)."""

    train: ml_collections.ConfigDict
    model: ml_collections.ConfigDict
    sampling: ml_collections.ConfigDict
    submaps: ml_collections.ConfigDict
    loss: ml_collections.ConfigDict
    seed: int
    max_rays_per_scan: int

    @classmethod
    def from_config(cls, config: ml_collections.ConfigDict) -> "TrainingSettings":
        """The groups of a run's config that training reads."""
        return cls(
            config.train,
            config.model,
            config.sampling,
            config.submaps,
            config.loss,
            config.seed,
            config.data.max_rays_per_scan,
        )

    def training_config(self) -> ml_collections.ConfigDict:
        """A config of these groups and the seed alone, the shape neld_jax.training's functions read (config.train,
        config.seed, ...): the groups themselves, not copies."""
        return ml_collections.ConfigDict(
            {
                "train": self.train,
                "model": self.model,
                "sampling": self.sampling,
                "submaps": self.submaps,
                "loss": self.loss,
                "seed": self.seed,
            }
        )


def refine_keyframes(
    settings: TrainingSettings,
    keyframes,
    start_poses: np.ndarray,
    pose_steps: train.PoseSteps,
    context: TrainingContext,
) -> Refined:
    """Train from the keyframes' start poses [K, 4, 4] (world) with `pose_steps` (settings: TrainingSettings),
    resuming from and checkpointing to context.out_dir/checkpoints, within context.max_seconds (`TrainingContext`)."""
    num_scans = keyframes.num_scans
    config = settings.training_config()
    plan = submaps.plan_from_config(
        dataclasses.replace(keyframes, poses=start_poses), config, num_devices=len(jax.devices())
    )
    rays_m = build_rays(
        keyframes, Normalization(1.0), max_rays_per_scan=(settings.max_rays_per_scan or None), seed=settings.seed
    )
    mesh = train.make_mesh(submaps.mesh_size(plan, len(jax.devices())))
    rays, frames = train.device_data(submaps.submap_arrays(plan, rays_m, start_poses), mesh)
    plan_of = functools.partial(
        train.make_trainer, config, num_scans, plan.num_submaps, pose_steps, start_poses, mesh=mesh
    )
    first = plan_of(int(config.train.steps))
    field_lr = first.schedules.field_lr
    logger.info(
        "%d keyframe(s) in %s, %d training rays (%d a step, fields %d wide, learning rate %g -> %g) on %d %s device(s)",
        num_scans,
        "one cube" if plan.num_submaps == 1 else f"{plan.num_submaps} submaps",
        rays_m.num_rays,
        first.batch_rays * plan.num_submaps,
        first.field.width,
        float(field_lr(0)),
        float(field_lr(first.schedules.total_steps)),
        mesh.size,
        jax.devices()[0].platform,
    )

    metadata = {
        "config_hash": context.config_hash,
        "num_scans": num_scans,
        "plan": plan.to_dict(),
        "pose_steps": pose_steps.to_dict(),
    }
    on_log = None if context.on_log is None else posed(context.on_log, start_poses, plan.ref_scale)
    data = train.TrainingData(rays, frames, plan.ref_scale)
    settings = train.FitSettings(context.max_seconds, context.progress, on_log)
    result = fit_resuming(
        os.path.join(context.out_dir, "checkpoints"),
        metadata,
        lambda: train.init_state(config, first, num_scans, plan.num_submaps),
        functools.partial(train.fit, config, plan_of, data, settings=settings),
        on_save=context.on_checkpoint,
    )
    poses_in_field = world_poses(start_poses, np.asarray(result.state.params["poses"]), plan.ref_scale)
    poses, anchor = anchored_on_first(poses_in_field, start_poses[0])
    return Refined(
        result, plan, first.field, poses, poses_in_field, anchor, np.bincount(rays_m.scan_index, minlength=num_scans)
    )


def posed(
    on_log: Callable[[dict, np.ndarray], None], start_poses: np.ndarray, ref_scale: float
) -> Callable[[dict, train.TrainState], None]:
    """train.fit's on_log(entry, state) that hands on_log(entry, poses [K, 4, 4]) the keyframes' poses of that step
    in the world, anchored as the outputs are."""

    def observe(entry: dict, state: train.TrainState) -> None:
        in_field = world_poses(start_poses, np.asarray(jax.device_get(state.params["poses"])), ref_scale)
        on_log(entry, anchored_on_first(in_field, start_poses[0])[0])

    return observe
