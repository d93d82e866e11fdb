"""The config (neld_jax.config): the presets, the budgets, the recipe that follows the data, overrides, and a config
a person can hold."""

import os
import re

import pytest
from absl import flags
from ml_collections import config_flags

from neld_jax import config as config_module
from neld_jax.config import apply_overrides, count_fields, defaults, with_budget
from neld_jax.errors import ConfigError
from neld_jax.outputs import config_hash

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECORDED_LAYOUTS = ("generic.py", "fusionportable.py", "newer_college.py", "lio_keyframes.py", "hba.py", "kitti.py")
# What a layout's config may set: how to read it, where to write, how its ground truth is aligned
READING_FIELDS = {"data.format", "data.keyframe_interval_s", "output_dir", "eval.map_icp_m"}


def _parse(config_arg: str):
    """The config that `neld-train --config=<config_arg>` trains with (neld_jax.cli's parsing)."""
    argv = ["train.py", f"--config={os.path.join(REPO, 'configs', config_arg)}"]
    flag_values = flags.FlagValues()
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    return flag_values.config


def _leaves(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_a_config_a_person_can_hold():
    # At most 100 settings, each with a comment on the line that sets it.
    c = defaults()
    assert count_fields(c) <= 100
    source = open(os.path.join(REPO, "neld_jax", "config.py")).read()
    body = source[source.index("def defaults()"):source.index("def with_budget(")]
    for path in _leaves(c.to_dict()):
        if path.startswith("data.synthetic."):
            continue  # the generator's own fields (neld_jax.data.synthetic)
        line = re.search(rf"^\s*c\.{re.escape(path)} = .*$", body, re.M)
        assert line and "#" in line.group(0), path


def test_every_setting_is_read_by_the_package():
    # No dead settings: each field's name appears in the package outside config.py.
    package = os.path.join(REPO, "neld_jax")
    text = ""
    for folder, _, files in os.walk(package):
        for name in files:
            if name.endswith(".py") and name != "config.py":
                text += open(os.path.join(folder, name)).read()
    unread = [path for path in _leaves(defaults().to_dict()) if path.split(".")[-1] not in text]
    assert not unread, unread


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
    assert c.start.poses == "input" and c.max_minutes == 0
    assert c.to_dict() == with_budget(defaults(), "paper").to_dict() | {"data": c.data.to_dict(),
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
    assert cpu.max_minutes == 9.5  # training until 8 minutes, a minute for the map, 30 s for the crispness draws


def test_the_recipe_follows_the_data_not_the_layout():
    # Every recorded layout gets the same recipe at each budget; its config only says how to read it.
    for budget in ("cpu", "gpu", "paper"):
        recipes = {name: _leaves(_parse(f"{name}:{budget}").to_dict()) for name in RECORDED_LAYOUTS}
        reference = recipes["generic.py"]
        for name, recipe in recipes.items():
            differ = {path for path in reference if recipe[path] != reference[path]}
            assert differ <= READING_FIELDS, (name, budget, differ - READING_FIELDS)
    real, demo = _parse("generic.py:cpu"), _parse("demo.py:cpu")
    assert real.start.poses == "crisper" and demo.start.poses == "input"
    assert real.train.pose_lr_rot_init == 5e-6 and demo.train.pose_lr_rot_init == 1e-3
    assert real.data.max_range_m == 40 and real.loss.lambda_termination == 3.0
    assert real.submaps.lambda_termination == 1.0 and demo.submaps.lambda_termination == 0
    gpu = _parse("generic.py:gpu")
    assert gpu.start.poses == "crisper" and gpu.train.pose_lr_rot_init == 5e-6 and gpu.loss.lambda_termination == 1
    assert _parse("lio_keyframes.py:paper").start.poses == "input"  # the paper budget is the paper's


def test_no_budget_named_is_gpu_on_a_gpu_and_unchanged_on_a_cpu(monkeypatch):
    import jax

    assert jax.default_backend() == "cpu"
    assert _parse("generic.py").budget == "paper" and _parse("newer_college.py").budget == "paper"
    assert _parse("demo.py").budget == "cpu"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    for name in ("demo.py",) + RECORDED_LAYOUTS:
        assert _parse(name).budget == "gpu", name
    assert config_module.default_budget("cpu") == "gpu"


def test_budget_name_is_not_hashed_and_an_unknown_budget_is_an_error():
    a, b = with_budget(defaults(), "paper"), with_budget(defaults(), "paper")
    b.budget = "something else"
    assert config_hash(a) == config_hash(b)
    b.train.steps = 7
    assert config_hash(a) != config_hash(b)
    with pytest.raises(ConfigError, match="unknown budget 'tpu'"):
        with_budget(defaults(), "tpu")


def test_from_file_reads_a_config_with_its_budget():
    c = config_module.from_file(os.path.join(REPO, "configs", "demo.py:gpu"))
    assert c.budget == "gpu" and c.data.format == "synthetic"
    with pytest.raises(ConfigError, match="no such config file"):
        config_module.from_file(os.path.join(REPO, "configs", "nosuch.py"))


def test_overrides_parse_literals_and_bare_strings():
    c = apply_overrides(defaults(), ["train.steps=20", "start.poses=baseline", "sampling.coarse_stages=(16, 8)",
                                     "sampling.z_low_m=0.25"])
    assert c.train.steps == 20 and c.start.poses == "baseline"
    assert tuple(c.sampling.coarse_stages) == (16, 8) and c.sampling.z_low_m == 0.25


@pytest.mark.parametrize("item, message", [("train.stepz=3", "no field train.stepz"),
                                           ("nosuch.steps=3", "no field nosuch.steps"),
                                           ("train.steps", "expected KEY=VALUE")])
def test_bad_overrides_name_the_field(item, message):
    with pytest.raises(ConfigError, match=message):
        apply_overrides(defaults(), [item])
