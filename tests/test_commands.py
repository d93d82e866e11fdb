"""The installed commands (pyproject.toml [project.scripts]) and the bin/ scripts are the same entry points, and
each prints its own usage."""

import os
import subprocess
import sys
import tomllib

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
    SCRIPTS = tomllib.load(f)["project"]["scripts"]


def test_every_command_has_its_bin_script():
    assert set(SCRIPTS) == {
        "neld-train",
        "neld-baseline",
        "neld-evaluate",
        "neld-crispness",
        "neld-import-rosbag",
        "neld-perturb",
        "neld-make-synthetic",
        "neld-localize",
    }
    for name, target in SCRIPTS.items():
        module, function = target.split(":")
        assert function == "main" and module == f"neld_jax.commands.{name[len('neld-') :].replace('-', '_')}"
        script = open(os.path.join(REPO, "bin", f"{module.rsplit('.', 1)[1]}.py")).read()
        assert f"from {module} import main" in script and "sys.path" not in script


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_prints_the_commands_usage(name):
    module = SCRIPTS[name].split(":")[0]
    done = subprocess.run(
        [sys.executable, os.path.join(REPO, "bin", f"{module.rsplit('.', 1)[1]}.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "NELD_JAX_HUGEPAGES": "0"},
    )
    assert done.returncode in (0, 1) and not done.stderr, done.stderr[-2000:]  # absl exits 1 after --help
    assert done.stdout.startswith(f"{name} (bin/"), done.stdout[:200]


def _train(*args, tmp_path, **env):
    """neld-train with args: (exit code, stderr)."""
    done = subprocess.run(
        [sys.executable, os.path.join(REPO, "bin", "train.py"), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ, "NELD_JAX_HUGEPAGES": "0", "NELD_TRACEBACK": "", **env},
    )
    return done.returncode, done.stderr


def test_a_bad_field_is_one_line_before_anything_is_read(tmp_path):
    # The sequence folder does not exist: the field's error comes first, so nothing was read.
    code, err = _train(
        f"--config={REPO}/configs/generic.py",
        f"--config.data.root={tmp_path}/missing",
        "--config.sampling.hierarchical=nerff",
        f"--config.output_dir={tmp_path}/out",
        tmp_path=tmp_path,
    )
    assert code == 1 and err == "error: sampling.hierarchical = 'nerff': expected one of before | nerf | none\n", err
    assert not (tmp_path / "out").exists()
    code, err = _train(f"--config={REPO}/configs/generic.py", "--config.train.stepz=3", tmp_path=tmp_path)
    assert code == 1 and err.startswith("error: --config.train.stepz: the config has no field train.stepz"), err
    assert err.count("\n") == 1


@pytest.mark.parametrize(
    "body, line, kind",
    [
        (
            "from neld_jax import config\n\ndef get_config(budget=''):\n    c = config.recording(budget)\n"
            "    c.train.steps = 1 / 0\n    return c\n",
            5,
            "ZeroDivisionError: division by zero",
        ),
        ("def get_config(budget=''):\n    return {\n\n", 2, "SyntaxError: "),
    ],
    ids=["raises", "syntax_error"],
)
def test_an_error_in_the_users_config_file_names_its_file_and_line(tmp_path, body, line, kind):
    mine = tmp_path / "my.py"
    mine.write_text(body)
    code, err = _train(f"--config={mine}", tmp_path=tmp_path)
    assert code == 1 and err.startswith(f"error: {mine}:{line}: {kind}") and err.count("\n") == 1, err
    code, err = _train(f"--config={mine}", tmp_path=tmp_path, NELD_TRACEBACK="1")
    assert code != 0 and "Traceback (most recent call last)" in err and f'File "{mine}", line {line}' in err, err


def test_the_papers_schedule_on_a_cpu_is_warned_about_with_its_time(tmp_path):
    code, err = _train(
        f"--config={REPO}/configs/generic.py:paper",
        f"--config.data.root={tmp_path}/missing",
        f"--config.output_dir={tmp_path}/out",
        tmp_path=tmp_path,
    )
    warning = next(line for line in err.splitlines() if "WARNING" in line)
    assert "the paper budget trains 160000 steps" in warning and "days on this CPU's" in warning, err
    assert code == 1 and err.splitlines()[-1].startswith("error: ") and "missing" in err.splitlines()[-1], err
