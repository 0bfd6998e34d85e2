"""The notebooks run end to end at a small size (their SMALL switch), in a fresh kernel each."""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_the_five_notebooks_are_there_without_outputs():
    assert [p.name[:2] for p in NOTEBOOKS] == ["01", "02", "03", "04", "05"]
    for p in NOTEBOOKS:
        nb = nbformat.read(p, as_version=4)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{p.name}: outputs are not stripped"


def test_the_documentations_copies_hold_the_same_code_with_outputs():
    """docs/notebooks/ (tools/render_notebooks.py): each notebook executed, its code unchanged."""
    for p in NOTEBOOKS:
        shown = Path(__file__).parent.parent / "docs" / "notebooks" / p.name
        assert shown.is_file(), f"{shown}: missing (run tools/render_notebooks.py)"
        src = [c.source for c in nbformat.read(p, as_version=4).cells]
        nb = nbformat.read(shown, as_version=4)
        assert [c.source for c in nb.cells] == src, (
            f"{shown.name}: its cells differ from {p} (run tools/render_notebooks.py)"
        )
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(c.execution_count is not None for c in code), f"{shown.name}: not executed"
        assert not [o for c in code for o in c.outputs if o.output_type == "error"], f"{shown.name}: an error"
        assert any(o.output_type == "display_data" for c in code for o in c.outputs), f"{shown.name}: no figure"


# each runs in a fresh kernel that compiles its own calibration: the slow tier
@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    # the kernels inherit the tests' persistent compilation cache (conftest): the calibration
    # of the same small scene compiles once
    monkeypatch.setenv("SLCV_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    assert os.listdir(tmp_path), "the notebook wrote nothing"
