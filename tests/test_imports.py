"""The package's layers (docs/design.md): imports only go down and never in a circle; the maths, the model and the
trainer import no I/O library; the training step of a run needs no open3d (a GPU image has none)."""

import ast
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(REPO, "neld_jax")

# From the bottom: a module may import its own layer and the ones below, never one above.
LAYERS = [
    ("foundations", {"errors", "jsonable", "geometry"}),
    ("maths", {"lie", "encoding", "sampling", "rendering", "losses"}),
    ("model", {"field", "model"}),
    ("trainer", {"train", "checkpoint"}),
    ("data", {"data"}),
    ("library", {"config", "submaps", "crispness", "metrics", "trajectory", "report", "judge", "baseline", "budget",
                 "session_alignment"}),
    ("steps", {"refine", "mapping", "start", "register_scans", "answer"}),
    ("edge", {"run", "outputs", "output_folder", "export", "evaluate", "plots", "viewer", "cli", "hugepages",
              "commands", "session_outputs"}),
]


def _modules() -> dict[str, str]:
    """{dotted name: path} of every module of the package."""
    found = {}
    for folder, _, files in os.walk(PACKAGE):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                relative = os.path.relpath(path, REPO)[:-3].replace(os.sep, ".")
                found[relative.removesuffix(".__init__")] = path
    return found


def _imports(path: str, modules: dict) -> set[str]:
    """The package modules a file imports, at its top or inside its functions."""
    tree = ast.parse(open(path).read())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        out |= {name for name in names if name in modules}
    return out


def _layer(module: str) -> int:
    top = module.split(".")[1] if module.count(".") else ""
    for index, (_, members) in enumerate(LAYERS):
        if top in members:
            return index
    raise AssertionError(f"{module} is in no layer of tests/test_imports.py: place it")


def test_imports_only_go_down_and_never_in_a_circle():
    modules = _modules()
    graph = {name: _imports(path, modules) - {name} for name, path in modules.items()}
    upward = [f"{a} ({LAYERS[_layer(a)][0]}) imports {b} ({LAYERS[_layer(b)][0]})"
              for a, targets in graph.items() if a != "neld_jax" for b in targets
              if b != "neld_jax" and _layer(b) > _layer(a)]
    assert not upward, upward
    # A circle: a module reachable from itself (packages' own __init__ aside)
    circles = []
    for start in graph:
        stack, seen = list(graph[start]), set()
        while stack:
            node = stack.pop()
            if node == start:
                circles.append(start)
                break
            if node not in seen:
                seen.add(node)
                stack.extend(graph.get(node, ()))
    assert not circles, circles


BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError("blocked " + name)
sys.meta_path.insert(0, Block())
"""


def _imports_without(blocked: tuple, code: str):
    script = f"BLOCKED = {blocked!r}\n" + BLOCKER + code
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)


def test_the_maths_model_and_trainer_import_no_io_library():
    code = ("import neld_jax.train, neld_jax.model, neld_jax.checkpoint, neld_jax.losses, neld_jax.sampling\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('open3d', 'scipy', 'matplotlib')]\n"
            "assert not bad, bad\nprint('ok')")
    result = _imports_without(("open3d", "scipy", "matplotlib"), code)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]


def test_the_training_step_of_a_run_imports_without_open3d():
    """refine.refine_keyframes is what a GPU image without open3d runs (benchmarks/real_gpu.py); the config too."""
    code = ("import neld_jax.refine, neld_jax.config, neld_jax.mapping\n"
            "assert callable(neld_jax.refine.refine_keyframes) and neld_jax.config.synthetic('cpu').budget == 'cpu'\n"
            "print('ok')")
    result = _imports_without(("open3d",), code)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]
