"""The notebooks: stored as tools/make_notebooks.py writes them, with their figures, and they run."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("make_notebooks", ROOT / "tools" / "make_notebooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_notebooks_exist() -> None:
    assert NOTEBOOKS, "no notebooks found"
    assert sorted(p.name for p in NOTEBOOKS) == sorted(_generator().NOTEBOOKS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_stored_cells_are_the_generators(path: Path) -> None:
    """A cell edited in the notebook but not in tools/make_notebooks.py (or the other way) fails."""
    stored = nbformat.read(path, as_version=4)
    made = _generator().NOTEBOOKS[path.name]()
    assert [(c.cell_type, c.source) for c in stored.cells] == [(c.cell_type, c.source) for c in made.cells], (
        f"{path.name} differs from its generator: python tools/make_notebooks.py --execute --only {path.name}"
    )


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_stored_with_their_figures(path: Path) -> None:
    """Every code cell ran (an execution count, no error) and the notebook shows at least one PNG."""
    nb = nbformat.read(path, as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.get("execution_count") for c in cells), f"{path.name} is stored unexecuted: python tools/make_notebooks.py --execute"
    outputs = [o for c in cells for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs), f"{path.name} shows no figure"


def test_unchanged_cells_keep_their_outputs() -> None:
    gen = _generator()
    old = gen.components()
    old.cells[1].outputs, old.cells[1].execution_count = [nbformat.v4.new_output("stream", text="kept")], 1
    old.cells[3].outputs = [nbformat.v4.new_output("stream", text="dropped")]
    new = gen.components()
    new.cells[3].source += "\n# changed"
    merged = gen.keep_outputs(new, old)
    assert merged.cells[1].outputs[0]["text"] == "kept"
    assert merged.cells[3].outputs == []


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("ADNERF_NOTEBOOK_SMALL", "1")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
