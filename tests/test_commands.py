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
    assert set(SCRIPTS) == {"neld-train", "neld-baseline", "neld-evaluate", "neld-crispness", "neld-import-rosbag",
                            "neld-perturb", "neld-make-synthetic", "neld-localize"}
    for name, target in SCRIPTS.items():
        module, function = target.split(":")
        assert function == "main" and module == f"neld_jax.commands.{name[len('neld-'):].replace('-', '_')}"
        script = open(os.path.join(REPO, "bin", f"{module.rsplit('.', 1)[1]}.py")).read()
        assert f"from {module} import main" in script and "sys.path" not in script


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_prints_the_commands_usage(name):
    module = SCRIPTS[name].split(":")[0]
    done = subprocess.run([sys.executable, os.path.join(REPO, "bin", f"{module.rsplit('.', 1)[1]}.py"), "--help"],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "NELD_JAX_HUGEPAGES": "0"})
    assert done.returncode in (0, 1) and not done.stderr, done.stderr[-2000:]  # absl exits 1 after --help
    assert done.stdout.startswith(f"{name} (bin/"), done.stdout[:200]
