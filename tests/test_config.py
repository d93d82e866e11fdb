"""The config (neld_jax.config): the presets, the budgets, the recipe that follows the data, overrides, and a config
a person can hold."""

import os

import pytest
from absl import flags
from ml_collections import config_flags

from neld_jax import config as config_module
from neld_jax.config import apply_overrides, count_fields, defaults, with_budget
from neld_jax.errors import ConfigError
from neld_jax.writing.outputs import config_hash

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
    # At most 100 settings, each declared once with a default its rule accepts and one line on what it does.
    c = defaults()
    assert count_fields(c) <= 100
    settings = config_module.SETTINGS
    names = [s.name for s in settings]
    assert len(set(names)) == len(names) and set(names) == set(config_module.leaves(c)) == set(config_module.RULES)
    groups = list(config_module.GROUPS)
    assert [s.group for s in settings] == sorted((s.group for s in settings), key=groups.index)  # in GROUPS' order
    for s in settings:
        assert s.rule.accepts(s.default), s.name
        assert s.why and "\n" not in s.why and s.why == s.why.strip(), s.name


def test_a_modules_settings_are_its_config_group():
    # The defaults a module owns are the config's: the baseline's settings, the judge's, the generator's.
    from neld_jax.baseline import BaselineSettings
    from neld_jax.synthetic.generator import synthetic_defaults

    c = defaults()
    assert BaselineSettings.from_config(c) == BaselineSettings()
    assert c.data.synthetic.to_dict() == synthetic_defaults().to_dict()


def test_the_settings_reference_in_the_docs_is_current():
    # docs/defaults.md's generated part is what `python -m neld_jax.config --docs` writes now.
    text = open(config_module.DOCS_PATH).read()
    assert text == config_module.with_settings_reference(text), "stale: run python -m neld_jax.config --docs"
    reference = config_module.settings_reference()
    assert all(f"| `{path}` |" in reference for path in config_module.RULES)
    assert "| `sampling.hierarchical` | str | `'before'` | one of before \\| nerf \\| none |" in reference
    assert text.index("## Every setting") < text.index(config_module.DOCS_BEGIN)


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
    assert c.to_dict() == with_budget(defaults(), "paper").to_dict() | {
        "data": c.data.to_dict(),
        "output_dir": c.output_dir,
    }


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
    assert cpu.max_minutes == 9.5  # training until 7.75 minutes, a minute for the map, 45 s for the draws and files


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


def test_no_budget_named_is_cpu_on_a_cpu_and_gpu_on_a_gpu(monkeypatch):
    # Every config in configs/ without an argument: the cpu budget on a CPU, whose clock ends the run within 10
    # minutes; the gpu budget where JAX's default backend is a GPU.
    import jax

    names = sorted(name for name in os.listdir(os.path.join(REPO, "configs")) if name.endswith(".py"))
    assert set(RECORDED_LAYOUTS) | {"demo.py"} <= set(names)
    assert jax.default_backend() == "cpu"
    for name in names:
        c = _parse(name)
        assert c.budget == "cpu" and 0 < c.max_minutes <= 10 and c.train.steps == 1500, name
        assert c.to_dict() == _parse(f"{name}:cpu").to_dict(), name
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    for name in names:
        assert _parse(name).budget == "gpu", name
    assert config_module.default_budget() == "gpu"


def test_a_long_run_without_a_time_limit_on_a_cpu_is_warned_about():
    # The paper's schedule on 2 cores: 160k steps at the measured 6.5 s a paper-size step, about 12 days.
    paper = config_module.recording("paper")
    assert config_module.cpu_training_hours(paper, cores=2) == pytest.approx(160_000 * 6.5 / 3600)
    warning = config_module.slow_run_warning(paper, "cpu", cores=2)
    assert "160000 steps" in warning and "about 12 days" in warning and "2 cores" in warning
    assert "\n" not in warning
    assert config_module.slow_run_warning(paper, "gpu", cores=2) == ""
    assert config_module.slow_run_warning(config_module.recording("cpu"), "cpu", cores=2) == ""  # max_minutes
    paper.max_minutes = 30.0  # a time limit compresses the schedule: nothing to warn about
    assert config_module.slow_run_warning(paper, "cpu", cores=2) == ""


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
    c = apply_overrides(
        defaults(),
        ["train.steps=20", "start.poses=baseline", "sampling.coarse_stages=(16, 8)", "sampling.z_low_m=0.25"],
    )
    assert c.train.steps == 20 and c.start.poses == "baseline"
    assert tuple(c.sampling.coarse_stages) == (16, 8) and c.sampling.z_low_m == 0.25


@pytest.mark.parametrize(
    "item, message",
    [
        ("train.stepz=3", "no field train.stepz"),
        ("nosuch.steps=3", "no field nosuch.steps"),
        ("train.steps", "expected KEY=VALUE"),
    ],
)
def test_bad_overrides_name_the_field(item, message):
    with pytest.raises(ConfigError, match=message):
        apply_overrides(defaults(), [item])


def _valid(name: str = "generic.py:cpu"):
    c = _parse(name)
    c.unlock()
    c.data.root = "/data/seq" if c.data.format != "synthetic" else ""
    return c


def test_every_field_has_a_rule_and_every_shipped_config_passes():
    assert set(config_module.leaves(defaults())) == set(config_module.RULES)
    for path, _, _ in config_module.RELATIONS:
        assert path in config_module.RULES, path
    for name in ("demo.py",) + RECORDED_LAYOUTS:
        for budget in ("cpu", "gpu", "paper"):
            config_module.validate(_valid(f"{name}:{budget}"))


@pytest.mark.parametrize(
    "field, value, expected",
    [
        ("sampling.hierarchical", "nerff", "expected one of before | nerf | none"),
        ("submaps.enabled", "maybe", "expected one of auto | on | off"),
        ("train.fixed_scans", (0, 1.5), "expected a tuple of integers"),
        ("train.steps", 0, "expected an integer >= 1"),
        ("train.c2f_end_fraction", 1.5, "expected a number >= 0 and <= 1"),
        ("model.matmul_dtype", "float16", "expected one of float32 | bfloat16"),
        ("data.format", "kitti360", "expected one of generic | fusionportable"),
        ("data.gt_from_scan", (1.0, 2.0), "expected () or a tuple of 7 numbers"),
        ("start.pose_lr_from_baseline", (1e-5,), "expected () or a tuple of 2 numbers >= 0"),
        ("submaps.field_lr_from_steps", (6000, 0), "expected () or a tuple of 2 numbers > 0"),
        ("max_minutes", -1.0, "expected a number >= 0"),
        ("model.surrogate_gradient", 1, "expected True or False"),
        # what fields accept together
        ("data.max_range_m", 0.4, "expected more than data.min_range_m"),
        ("sampling.fine_stages", (16, 8), "expected as many stages as sampling.coarse_stages"),
        ("model.skip_layers", (4,), "expected hidden layers below model.depth"),
        ("data.scan_frame", "os_imu", "expected '' or a published frame of data.format"),
        ("data.initial_poses", "odom.txt", "a pose file's name only with data.format=lio_keyframes"),
        ("data.gt_from_scan", (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0), "with a unit quaternion"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_field_its_value_and_what_it_accepts(field, value, expected):
    c = _valid("fusionportable.py:cpu")
    *parents, leaf = field.split(".")
    node = c
    for part in parents:
        node = node[part]
    node.__dict__["_fields"][leaf] = value  # as a config file may set it, past the type check of ConfigDict
    with pytest.raises(ConfigError) as raised:
        config_module.validate(c)
    message = str(raised.value)
    assert message.startswith(f"{field} = {value!r}: ") and expected in message and "\n" not in message


def test_a_field_the_defaults_lack_and_fields_that_do_not_go_together_are_errors():
    c = _valid()
    c.train.stepz = 3  # a config file's typo
    with pytest.raises(ConfigError, match=r"^train.stepz = 3: the config has no such field"):
        config_module.validate(c)
    c = _valid()
    c.sampling.hierarchical = "nerf"
    c.sampling.coarse_stages, c.sampling.fine_stages = (2,), (16,)
    with pytest.raises(ConfigError, match=r"^sampling.coarse_stages = \(2,\): expected at least 3 samples"):
        config_module.validate(c)
    c = _parse("generic.py:cpu")
    with pytest.raises(ConfigError, match=r"^data.root = '': expected a folder"):
        config_module.validate(c)
    c = _valid()
    c.data.initial_poses, c.data.invert_poses = "kiss_icp", True
    with pytest.raises(
        ConfigError, match=r"^data.invert_poses = True: expected False with data.initial_poses=kiss_icp"
    ):
        config_module.validate(c)
