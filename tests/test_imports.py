"""The core (maths, model, trainer, mapping) imports without the I/O stack, as on a GPU image without open3d."""

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
bad = [m for m in sys.modules if m.split(".")[0] in ("open3d", "scipy", "matplotlib") or m.startswith("neld_jax.data")]
assert not bad, bad
print("ok")
"""


def test_core_imports_without_open3d_scipy_matplotlib():
    result = subprocess.run([sys.executable, "-c", BLOCKER], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]
