"""Shared fixtures: a tiny configuration that trains in seconds on a CPU."""

import os

import pytest

# Tests run on the CPU, whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")

from neld_jax.config import base_config  # noqa: E402


def make_tiny_config(output_dir: str = "", steps: int = 20):
    c = base_config()
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
    c.sampling.sample_ramp_fraction = 0.5
    c.train.steps = steps
    c.train.batch_rays = 32
    c.train.c2f_end_fraction = 0.5
    c.train.field_lr_init, c.train.field_lr_final = 1e-3, 1e-4
    for k in ("rot", "trans"):
        c.train[f"pose_lr_{k}_init"], c.train[f"pose_lr_{k}_final"] = 1e-3, 1e-4
    c.train.checkpoint_every = 5
    c.train.log_every = 1
    c.mapping.num_coarse, c.mapping.num_fine = 8, 8
    c.mapping.rays_per_batch = 128
    c.mapping.max_rays_per_scan = 64
    c.mapping.voxel_size_m = 0.0
    c.mapping.min_opacity = 0.0  # a 12-step field is still mostly transparent
    return c


@pytest.fixture
def tiny_config(tmp_path):
    return make_tiny_config(str(tmp_path / "run"))
