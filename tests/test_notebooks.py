"""Execute every notebook in notebooks/ (the committed .ipynb, as CI sees it) and fail on any cell error.

Plain `pytest` runs this (nbmake is not enabled in addopts, so the .ipynb files are not collected on
their own). It uses nbmake's runner (nbclient underneath) on a copy of the notebook in a temporary
folder, so a run leaves no outputs or files in the tree."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
TIMEOUT_S = 300  # per cell, generous: a cell of these notebooks takes seconds
MIN_IMAGES = {"tour_of_the_rig.ipynb": 3, "designer.ipynb": 5}  # notebooks whose point is their pictures


@pytest.fixture(autouse=True)
def _headless(monkeypatch):
    # the kernel inherits the environment: off-screen VTK, non-GUI matplotlib
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    monkeypatch.setenv("MPLBACKEND", "Agg")


def test_there_are_notebooks():
    assert NOTEBOOKS, "no notebooks/*.ipynb found"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path):
    pytest.importorskip("nbmake")
    from nbmake.nb_run import NotebookRun

    copy = tmp_path / path.name
    shutil.copy(path, copy)
    result = NotebookRun(copy, default_timeout=TIMEOUT_S).execute()
    err = result.error
    assert err is None, f"{path.name}: cell {err.failing_cell_index} failed:\n{err.trace}"
    code = [c for c in result.nb.cells if c.cell_type == "code"]
    assert code and all(c.get("execution_count") for c in code), "not every code cell ran"
    # a notebook that is about pictures must actually show them, not just run
    images = sum("image/png" in o.get("data", {}) for c in code for o in c.outputs)
    want = MIN_IMAGES.get(path.name, 0)
    assert images >= want, f"{path.name}: expected at least {want} images in its outputs, got {images}"
