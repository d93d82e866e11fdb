"""The package's wings (docs/design.md, "Layout"): imports only go down and never in a circle; the field and
training import no I/O library; data imports neither the front-end nor the synthetic generator; no wing imports the
steps or the run; at most ten loose modules and no two modules of one name; the training step of a run needs no
open3d (a GPU image has none)."""

import ast
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(REPO, "neld_jax")

# The wings from the bottom: a module may import its own wing and the ones below, never one above. The loose
# modules of neld_jax/ are the foundations (errors, jsonable, geometry, lie, trajectory) and the edge (config, cli,
# hugepages, run); commands/ are the entry points.
LAYERS = [
    ("foundations", {"errors", "jsonable", "geometry", "lie", "trajectory"}),
    ("data", {"data"}),
    ("field", {"field"}),
    ("training", {"training"}),
    ("frontend", {"frontend"}),
    ("synthetic", {"synthetic"}),
    ("judging", {"judging"}),
    ("baseline", {"baseline"}),
    ("writing", {"writing"}),
    ("steps", {"steps"}),
    ("edge", {"config", "cli", "hugepages", "run", "commands"}),
]
LOOSE_AT_MOST = 10  # modules in neld_jax/ itself, __init__.py included
IO_LIBRARIES = ("open3d", "scipy", "matplotlib", "rosbags", "kiss_icp", "rerun", "map_closures")


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
    upward = [
        f"{a} ({LAYERS[_layer(a)][0]}) imports {b} ({LAYERS[_layer(b)][0]})"
        for a, targets in graph.items()
        if a != "neld_jax"
        for b in targets
        if b != "neld_jax" and _layer(b) > _layer(a)
    ]
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


def test_the_field_and_training_import_no_io_library():
    names = sorted(m for m in _modules() if m.split(".")[1:2] in (["field"], ["training"]))
    code = (
        f"import {', '.join(names)}\n"
        f"bad = [m for m in sys.modules if m.split('.')[0] in {IO_LIBRARIES!r}]\nassert not bad, bad\nprint('ok')"
    )
    result = _imports_without(IO_LIBRARIES, code)
    assert len(names) > 10 and result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]


def test_data_imports_neither_the_frontend_nor_the_synthetic_generator():
    modules = _modules()
    wrong = [
        f"{a} imports {b}"
        for a, path in modules.items()
        if a.startswith("neld_jax.data")
        for b in _imports(path, modules)
        if b.startswith(("neld_jax.frontend", "neld_jax.synthetic"))
    ]
    assert not wrong, wrong


def test_no_wing_imports_the_steps_or_the_run():
    modules = _modules()
    # the edge: the config offers the steps' choices (steps.choices, steps.inputs.FORMATS)
    edge = ("neld_jax.steps", "neld_jax.run", "neld_jax.commands", "neld_jax.cli", "neld_jax.config")
    wrong = [
        f"{a} imports {b}"
        for a, path in modules.items()
        if not a.startswith(edge)
        for b in _imports(path, modules)
        if b.startswith(("neld_jax.steps", "neld_jax.run"))
    ]
    assert not wrong, wrong


def test_few_loose_modules_and_no_two_modules_share_a_name():
    loose = [name for name in os.listdir(PACKAGE) if name.endswith(".py")]
    assert len(loose) <= LOOSE_AT_MOST, sorted(loose)
    names = [m.rsplit(".", 1)[-1] for m in _modules() if ".commands." not in m and m.count(".") >= 1]
    shared = sorted({n for n in names if names.count(n) > 1})
    assert not shared, shared


def test_the_training_step_of_a_run_imports_without_open3d():
    """refine.refine_keyframes is what a GPU image without open3d runs (benchmarks/real_gpu.py); the config too."""
    code = (
        "import neld_jax.steps.refine, neld_jax.config, neld_jax.steps.mapping\n"
        "assert callable(neld_jax.steps.refine.refine_keyframes)\n"
        "assert neld_jax.config.synthetic('cpu').budget == 'cpu'\n"
        "print('ok')"
    )
    result = _imports_without(("open3d",), code)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]
