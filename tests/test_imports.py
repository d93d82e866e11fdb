"""The core (maths, model, trainer, mapping) imports without the I/O stack, as on a GPU image without open3d.

Of neld_jax.data the core imports only what config.py and metrics.py take from it: the synthetic generator's
defaults (with the Sequence it returns) and the time matching, none of which imports open3d, scipy or matplotlib.
"""

import subprocess
import sys

BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ("open3d", "scipy", "matplotlib"):
            raise ImportError("blocked " + name)
sys.meta_path.insert(0, Block())
import neld_jax.train, neld_jax.model, neld_jax.mapping, neld_jax.checkpoint, neld_jax.metrics
light = {"neld_jax.data", "neld_jax.data.synthetic", "neld_jax.data.sequence", "neld_jax.data.timing"}
bad = [m for m in sys.modules if m.split(".")[0] in ("open3d", "scipy", "matplotlib")
       or (m.startswith("neld_jax.data") and m not in light)]
assert not bad, bad
print("ok")
"""


def test_core_imports_without_open3d_scipy_matplotlib():
    result = subprocess.run([sys.executable, "-c", BLOCKER], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]


RUN_WITHOUT_OPEN3D = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] == "open3d":
            raise ImportError("blocked " + name)
sys.meta_path.insert(0, Block())
import neld_jax.run, neld_jax.submap_run
assert callable(neld_jax.run.train_keyframes)
print("ok")
"""


def test_a_runs_training_step_imports_without_open3d():
    """run.train_keyframes is what benchmarks/real_gpu.py calls on a GPU image without open3d (docs/design.md)."""
    result = subprocess.run([sys.executable, "-c", RUN_WITHOUT_OPEN3D], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]
