"""Execute the notebooks in smoke mode (JAXMESH_SMOKE=1: small inputs)."""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("JAXMESH_SMOKE", "1")
    monkeypatch.setenv("JAXMESH_NOTEBOOK_OUT", str(tmp_path))
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    assert (tmp_path / "rve2d.vtu").exists() and (tmp_path / "rve3d.msh").exists()
    assert os.path.getsize(tmp_path / "rve2d.png") > 10_000
