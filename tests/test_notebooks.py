"""Every notebook executes from top to bottom (they must never rot).

The notebooks share one stage cache for the session (as one user's cache would be): the seed
notebooks reuse the helsinki-medical maps the earlier notebooks computed, which keeps each one
within its 60 s budget in the suite; a notebook run alone computes them itself."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.fixture(scope="module")
def notebook_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("notebook-cache")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch, notebook_cache):
    monkeypatch.setenv("SKYROUTE_CACHE_DIR", str(notebook_cache))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors, errors
    assert sum(1 for c in nb.cells if c.cell_type == "code") >= 3
