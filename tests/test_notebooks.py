"""The walkthrough notebooks in notebooks/: the committed files are valid, executed and error-free,
match their sources in notebooks/build_notebooks.py, and run top to bottom in a fresh kernel."""

from __future__ import annotations

import importlib.util
import re
import sys
import time
import types

import pytest

from conftest import PROJECT_ROOT

nbformat = pytest.importorskip("nbformat", reason="pip install -e '.[test]' brings nbformat, nbclient and ipykernel")

NOTEBOOK_FOLDER = PROJECT_ROOT / "notebooks"
NAMES = ("quickstart", "custom_loss_kernel")
MAX_BYTES = 1_500_000
"""Committed notebooks keep their outputs (figures inline for GitHub) but stay under this size."""
CELL_TIMEOUT_S = 600

_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _builder() -> types.ModuleType:
    """notebooks/build_notebooks.py as a module (no __pycache__ written into notebooks/)."""
    spec = importlib.util.spec_from_file_location("build_notebooks", NOTEBOOK_FOLDER / "build_notebooks.py")
    module = importlib.util.module_from_spec(spec)
    previous, sys.dont_write_bytecode = sys.dont_write_bytecode, True
    try:
        spec.loader.exec_module(module)
    finally:
        sys.dont_write_bytecode = previous
    return module


def _read(name: str):
    return nbformat.read(NOTEBOOK_FOLDER / f"{name}.ipynb", as_version=nbformat.NO_CONVERT)


def _errors(nb) -> list[str]:
    """One line per error output of a code cell: cell number, exception and message."""
    found = []
    for number, cell in enumerate(nb.cells):
        for output in cell.get("outputs", []):
            if output.get("output_type") == "error":
                found.append(f"cell {number}: {output.get('ename')}: {_ANSI.sub('', output.get('evalue', ''))}")
    return found


def _notebook_folder_files() -> set[str]:
    """Everything under notebooks/, where a notebook run from there would leave its files."""
    return {str(p.relative_to(NOTEBOOK_FOLDER)) for p in NOTEBOOK_FOLDER.rglob("*")}


@pytest.mark.parametrize("name", NAMES)
def test_committed_notebook_is_valid_executed_and_small(name):
    path = NOTEBOOK_FOLDER / f"{name}.ipynb"
    nb = _read(name)
    assert nb.nbformat == 4
    nbformat.validate(nb)
    assert nb.metadata.kernelspec.name == "python3"
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert code, f"{path.name} has no code cells"
    assert not _errors(nb), f"{path.name} was committed with errors: {_errors(nb)}"
    unexecuted = [i for i, cell in enumerate(nb.cells) if cell.cell_type == "code" and cell.execution_count is None]
    assert not unexecuted, (f"{path.name}: cells {unexecuted} have no outputs; run python "
                            f"notebooks/build_notebooks.py --execute")
    figures = [o for cell in code for o in cell.outputs if "image/png" in o.get("data", {})]
    assert figures, f"{path.name} shows no inline figures"
    size = path.stat().st_size
    assert size < MAX_BYTES, f"{path.name} is {size / 1e6:.2f} MB; keep figures small (dpi, size)"


@pytest.mark.parametrize("name", NAMES)
def test_committed_notebook_matches_its_source(name):
    """The .ipynb files are generated: edit notebooks/build_notebooks.py, not the notebook."""
    built = _builder().build(name)
    committed = _read(name)
    expected = [(cell.cell_type, cell.source) for cell in built.cells]
    actual = [(cell.cell_type, cell.source) for cell in committed.cells]
    assert actual == expected, (
        f"notebooks/{name}.ipynb differs from its cells in notebooks/build_notebooks.py; "
        "edit the builder and run: python notebooks/build_notebooks.py --execute"
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_top_to_bottom(name, tmp_path):
    """Run the committed notebook in a fresh python3 kernel (this environment, WARP_CACHE_PATH
    included; inline matplotlib), in a temporary folder, and fail with the failing cell's error."""
    from nbclient.exceptions import CellExecutionError

    builder = _builder()
    nb = _read(name)
    before = _notebook_folder_files()
    started = time.perf_counter()
    try:
        builder.execute(nb, workdir=tmp_path, timeout=CELL_TIMEOUT_S)
    except CellExecutionError as error:
        pytest.fail(f"notebooks/{name}.ipynb failed:\n{_ANSI.sub('', str(error))}", pytrace=False)
    seconds = time.perf_counter() - started
    print(f"{name}.ipynb ran in {seconds:.1f} s")
    assert not _errors(nb)
    figures = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.outputs
               if "image/png" in o.get("data", {})]
    assert figures, "no inline figures: the kernel did not use matplotlib's inline backend"
    after = _notebook_folder_files()
    assert after == before, f"running {name}.ipynb wrote into notebooks/: {sorted(after - before)}"
