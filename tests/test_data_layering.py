"""neld_jax.data is a lower layer: its modules import no other neld_jax module but errors and geometry, no
leading-underscore name of another module, and none imports itself back through the others (lazy imports in
functions count too). Read from the source with ast, so nothing is imported."""

import ast
from pathlib import Path

import neld_jax

PACKAGE = Path(neld_jax.__file__).resolve().parent
DATA = PACKAGE / "data"
ALLOWED_OUTSIDE = {"neld_jax.errors", "neld_jax.geometry"}


def _module_name(path):
    relative = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = relative.parts[:-1] if relative.name == "__init__" else relative.parts
    return ".".join(parts)


def _neld_imports(path):
    """(imported module, names taken from it) for every neld_jax import in the file, at any depth."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names if alias.name.split(".")[0] == "neld_jax"]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "neld_jax":
            names = [alias.name for alias in node.names]
            # `from neld_jax.data import generic` imports the module neld_jax.data.generic
            submodules = [n for n in names if (PACKAGE.parent / node.module.replace(".", "/") / f"{n}.py").is_file()]
            found += [(f"{node.module}.{n}", []) for n in submodules]
            rest = [n for n in names if n not in submodules]
            if rest:
                found.append((node.module, rest))
    return found


def _graph():
    return {_module_name(path): _neld_imports(path) for path in sorted(DATA.rglob("*.py"))}


def test_data_imports_nothing_above_it_and_no_private_names():
    graph = _graph()
    outside = {
        (m, target)
        for m, imports in graph.items()
        for target, _ in imports
        if not target.startswith("neld_jax.data") and target not in ALLOWED_OUTSIDE
    }
    assert not outside, f"neld_jax.data imports from a higher layer: {sorted(outside)}"
    private = {
        (m, target, name)
        for m, imports in graph.items()
        for target, names in imports
        for name in names
        if name.startswith("_")
    }
    assert not private, f"private names imported across modules: {sorted(private)}"


def test_no_import_cycle_inside_data():
    graph = _graph()
    edges = {m: {t for t, _ in imports if t in graph and t != "neld_jax.data"} for m, imports in graph.items()}
    state = {}

    def visit(module, path):
        state[module] = "open"
        for target in sorted(edges[module]):
            assert state.get(target) != "open", "import cycle: " + " -> ".join(path + [module, target])
            if target not in state:
                visit(target, path + [module])
        state[module] = "done"

    for module in sorted(edges):
        if module not in state:
            visit(module, [])


def test_every_format_is_a_module_with_a_load():
    from neld_jax.data import formats

    for name, load in formats.FORMATS.items():
        assert load.__module__ == f"neld_jax.data.{name}" and load.__name__ == "load", name
    assert set(formats.GT_SEARCHED) == set(formats.FORMATS)
