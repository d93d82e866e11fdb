"""The gradient-check notebooks run from a clean kernel, and their claims (the assert cells at the end) hold.

Each notebook is executed with nbclient in a fresh "python3" kernel with notebooks/ as its working directory;
any cell that raises (a failing assert included) fails the test. The notebooks are kept in the repository
without outputs, which is checked too. Each takes well under two minutes on 2 CPU cores when the machine is
otherwise idle; the per-cell timeout leaves room for a busy machine.
"""

import os
from pathlib import Path

import nbformat
import pytest
from conftest import UNOPTIMISED_XLA_FLAGS
from nbclient import NotebookClient

NOTEBOOK_DIR = Path(__file__).resolve().parent.parent / "notebooks"
EXPECTED = ("surrogate_gradient.ipynb", "range_gradient.ipynb", "pose_recovery.ipynb")
CELL_TIMEOUT_S = 600
# Run with LLVM's optimisation (conftest turns it off for the suite's tiny programs): pose recovery trains 900 steps,
# which took 0.24 s each unoptimised against 0.09 s optimised (the compile 9.5 s against 16.5 s, three of them);
# the gradient notebooks are mostly compiles, and faster unoptimised (65 s against 87 s, 32 s against 40 s).
OPTIMISED = ("pose_recovery.ipynb",)


def _read(name: str) -> nbformat.NotebookNode:
    return nbformat.read(NOTEBOOK_DIR / name, as_version=4)


def test_every_notebook_is_listed_here():
    """A new notebook must be added to EXPECTED, so that it is executed below."""
    assert sorted(p.name for p in NOTEBOOK_DIR.glob("*.ipynb")) == sorted(EXPECTED)


@pytest.mark.parametrize("name", EXPECTED)
def test_notebook_is_saved_without_outputs_and_ends_with_asserts(name):
    nb = _read(name)
    nbformat.validate(nb)
    assert nb.cells[0].cell_type == "markdown", "a notebook starts by saying what it shows"
    code_cells = [cell for cell in nb.cells if cell.cell_type == "code"]
    for cell in code_cells:
        assert cell.outputs == [] and cell.execution_count is None, f"{name}: saved with outputs"
    assert "assert " in code_cells[-1].source, f"{name}: the last code cell must assert the notebook's claims"


@pytest.mark.parametrize("name", EXPECTED)
def test_notebook_runs_and_its_claims_hold(name, monkeypatch):
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")  # the kernel inherits the environment
    if name in OPTIMISED and os.environ.get("XLA_FLAGS") == UNOPTIMISED_XLA_FLAGS:  # flags of one's own are kept
        monkeypatch.delenv("XLA_FLAGS")
    nb = _read(name)
    client = NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    client.execute()  # raises CellExecutionError, naming the cell, if any cell fails
    code_cells = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert all(cell.execution_count is not None for cell in code_cells), f"{name}: not every cell ran"
    errors = [out for cell in code_cells for out in cell.outputs if out.output_type == "error"]
    assert not errors, errors
