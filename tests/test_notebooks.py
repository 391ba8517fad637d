"""The tutorials run top to bottom with the public API (from the notebooks folder, so
that they find the repository's problem files)."""

import pathlib

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"
slow = pytest.mark.slow


@pytest.mark.parametrize("name", [
    "01_static_culture.ipynb",
    pytest.param("02_static_vs_flex.ipynb", marks=slow),
    pytest.param("03_calibration.ipynb", marks=slow),
    pytest.param("04_protocol_optimisation.ipynb", marks=slow),
    "05_sweeps_and_sensitivity.ipynb",
])
def test_notebook_runs(name):
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
