"""The code's shape: no function in neld_jax/ over MAX_STATEMENTS statements (its own, nested functions' apart, the
docstring not counted: what the formatter lays out over several lines is one statement) or MAX_LINES lines (its def
to its last line, as `ruff format` lays it out), or with more than MAX_PARAMETERS parameters (self and cls not
counted; *args and **kwargs one each), but the config's table of defaults. What travels together goes in a
dataclass."""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "neld_jax"
MAX_STATEMENTS = 45
MAX_LINES = 80
MAX_PARAMETERS = 8
EXEMPT = {"config.defaults"}  # one line a field: longer as the config grows, by design


def parameter_count(function: ast.FunctionDef | ast.AsyncFunctionDef, in_class: bool) -> int:
    a = function.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    if in_class and names and names[0] in ("self", "cls"):
        names = names[1:]
    return len(names) + (a.vararg is not None) + (a.kwarg is not None)


def statement_count(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """The function's own statements at any depth: its docstring and the bodies of functions nested in it left out."""
    body = function.body
    docstring = (
        body[0]
        if body
        and isinstance(body[0], ast.Expr)
        and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)
        else None
    )
    count, stack = 0, [s for s in body if s is not docstring]
    while stack:
        node = stack.pop()
        count += 1
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            stack += [child for child in ast.iter_child_nodes(node) if isinstance(child, ast.stmt)]
    return count


def oversized(source: str, module: str) -> list[tuple[str, int, str]]:
    """(qualified name, line, what is over) of each function of `source` over a limit; module names the file
    (data/layout), the qualified name is module.Class.function (nested functions under their parent)."""
    found = []

    def visit(node: ast.AST, prefix: str, in_class: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}.{child.name}", True)
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}.{child.name}"
                lines, parameters = child.end_lineno - child.lineno + 1, parameter_count(child, in_class)
                statements = statement_count(child)
                over = [f"{statements} statements (at most {MAX_STATEMENTS})"] if statements > MAX_STATEMENTS else []
                over += [f"{lines} lines (at most {MAX_LINES})"] if lines > MAX_LINES else []
                over += [f"{parameters} parameters (at most {MAX_PARAMETERS})"] if parameters > MAX_PARAMETERS else []
                if over:
                    found.append((name, child.lineno, ", ".join(over)))
                visit(child, name, False)
            else:
                visit(child, prefix, in_class)

    visit(ast.parse(source), module, False)
    return found


def package_oversized() -> list[tuple[str, str, int, str]]:
    """(qualified name, file, line, what is over) of every function in neld_jax/ over a limit."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = path.relative_to(PACKAGE).with_suffix("").as_posix()
        found += [
            (name, f"neld_jax/{module}.py", line, over) for name, line, over in oversized(path.read_text(), module)
        ]
    return found


def test_no_function_is_over_the_limits():
    over = [f"{file}:{line} {name}: {what}" for name, file, line, what in package_oversized() if name not in EXEMPT]
    assert not over, "functions over the limits (split them; group what travels together):\n" + "\n".join(over)


def test_the_check_names_the_line_the_function_and_the_count():
    long_body = "\n".join(f"    x{i} = {i}" for i in range(45))
    tall_call = "    return f(\n" + "".join(f"        {i},\n" for i in range(80)) + "    )\n"  # one statement, 83 lines
    source = (
        f"def short():\n    pass\n\n\ndef long():\n{long_body}\n    return 0\n\n\n"
        f"def tall():\n{tall_call}\n\n"
        "class Step:\n    def many(self, a, b, c, d, e, f, g, h):\n        pass\n\n"
        "    def more(self, a, b, c, d, e, f, g, *h, **i):\n        def inner(j):\n            pass\n"
    )
    assert oversized(source, "data/made_up") == [
        ("data/made_up.long", 5, "46 statements (at most 45)"),
        ("data/made_up.tall", 54, "83 lines (at most 80)"),
        ("data/made_up.Step.more", 143, "9 parameters (at most 8)"),
    ]
