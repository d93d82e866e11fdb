"""The compute budgets of neld_jax.config: paper, gpu, cpu, and the default of a config that names none."""

import os

import pytest
from absl import flags
from ml_collections import config_flags

from neld_jax import config as config_module
from neld_jax.config import apply_budget, base_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _parse(config_arg: str):
    """The config that `bin/train.py --config=<config_arg>` trains with (neld_jax.cli's parsing)."""
    argv = ["train.py", f"--config={os.path.join(REPO, 'configs', config_arg)}"]
    flag_values = flags.FlagValues()
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    return flag_values.config


def test_paper_budget_is_the_papers_schedule():
    c = _parse("generic.py:paper")
    assert c.budget == "paper"
    assert c.train.steps == 160_000 and c.train.batch_rays == 1024
    assert (c.train.field_lr_init, c.train.field_lr_final) == (5e-5, 2e-5)
    for part in ("rot", "trans"):
        assert (c.train[f"pose_lr_{part}_init"], c.train[f"pose_lr_{part}_final"]) == (5e-5, 2e-5)
    assert tuple(c.train.fixed_scans) == (0,)
    assert (c.model.width, c.model.depth, c.model.pos_freqs) == (512, 8, 15)
    assert tuple(c.sampling.coarse_stages) == (32, 48, 64) and c.sampling.guided_samples == 0
    assert c.model.matmul_dtype == "float32"
    assert c.to_dict() == apply_budget(base_config(), "paper").to_dict() | {"data": c.data.to_dict(),
                                                                            "output_dir": c.output_dir}


def test_gpu_budget_is_the_cpu_recipe_run_longer():
    gpu, cpu = _parse("demo.py:gpu"), _parse("demo.py:cpu")
    assert gpu.budget == "gpu" and cpu.budget == "cpu"
    assert gpu.train.steps == 30_000 and gpu.train.log_every == 500 and cpu.train.steps == 1500
    assert gpu.model.to_dict() == cpu.model.to_dict() and gpu.sampling.to_dict() == cpu.sampling.to_dict()
    for name in ("batch_rays", "field_lr_init", "pose_lr_rot_init", "c2f_end_fraction", "fixed_scans"):
        assert gpu.train[name] == cpu.train[name], name
    assert (gpu.mapping.num_coarse, gpu.mapping.num_fine) == (128, 128)  # the paper's map
    assert gpu.mapping.max_seconds == 0 and cpu.mapping.max_seconds > 0  # every ray; on 2 cores, a time limit
    assert cpu.submaps.max_submaps == 32 and gpu.submaps.max_submaps == 0  # the cpu budget's step stays small
    # lio_keyframes: the gpu budget keeps the cpu budget's small pose steps for good odometry.
    assert _parse("lio_keyframes.py:gpu").train.pose_lr_rot_init == 5e-6
    # ... and both start from the crisper of the odometry and the classical baseline; the paper budget as given.
    assert _parse("lio_keyframes.py:gpu").train.init_poses == _parse("lio_keyframes.py:cpu").train.init_poses == "crisper"
    assert _parse("lio_keyframes.py:paper").train.init_poses == "input"
    # ... a pose prior only from the baseline's poses (neld_jax.run.pose_steps_for_start); the input's tilt kept
    lio_cpu = _parse("lio_keyframes.py:cpu")
    assert lio_cpu.train.pose_prior_weight == cpu.train.pose_prior_weight == 0
    assert lio_cpu.train.pose_prior_from_baseline == cpu.train.pose_prior_from_baseline > 0
    assert lio_cpu.baseline.keep_input_tilt and not cpu.baseline.keep_input_tilt
    # ... the termination loss 3x the paper's on the cpu budget only (the fog its 1500 steps leave), in one cube: the
    # submap fields of a drive keep the paper's weight; gpu and paper keep 1 everywhere.
    assert lio_cpu.loss.lambda_termination == 3 * cpu.loss.lambda_termination
    assert lio_cpu.submaps.lambda_termination == cpu.loss.lambda_termination == 1.0
    assert cpu.submaps.lambda_termination == 0  # elsewhere a submap run takes loss.lambda_termination
    assert _parse("lio_keyframes.py:gpu").loss.lambda_termination == gpu.loss.lambda_termination == 1.0
    assert _parse("lio_keyframes.py:paper").loss.lambda_termination == 1.0


def test_no_budget_named_is_gpu_on_a_gpu_and_unchanged_on_a_cpu(monkeypatch):
    import jax

    # On this (CPU) machine: the dataset configs are the paper's, the demo is the cpu budget, as before.
    assert jax.default_backend() == "cpu"
    assert _parse("generic.py").budget == "paper" and _parse("newer_college.py").budget == "paper"
    assert _parse("demo.py").budget == "cpu"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    for name in ("generic.py", "fusionportable.py", "newer_college.py", "lio_keyframes.py", "demo.py"):
        assert _parse(name).budget == "gpu", name
    assert config_module.default_budget("cpu") == "gpu"


def test_budget_name_is_not_hashed():
    from neld_jax.run import config_hash

    a = apply_budget(base_config(), "paper")
    b = apply_budget(base_config(), "paper")
    b.budget = "something else"
    assert config_hash(a) == config_hash(b)
    with pytest.raises(Exception, match="unknown budget 'tpu'"):
        apply_budget(base_config(), "tpu")
