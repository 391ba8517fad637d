"""The tutorials: each runs top to bottom (from the notebooks folder, so that it finds
the repository's problem files; slow), and — in the default run — each code cell
compiles and every jaxtissue name it imports or uses is public."""

import ast
import pathlib

import nbformat
import pytest

import jaxtissue as jt

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"
NAMES = sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))


def _code(name):
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    return [c.source for c in nb.cells if c.cell_type == "code"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_cells_compile_and_use_the_public_api(name):
    modules = {"jt": jt}
    for source in _code(name):
        tree = ast.parse(source)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxtissue"):
                module = __import__(node.module, fromlist=["_"])
                for alias in node.names:
                    assert not alias.name.startswith("_") and hasattr(module, alias.name), (name, node.module, alias.name)
                    modules[alias.asname or alias.name] = getattr(module, alias.name)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules:
                owner = modules[node.value.id]
                if hasattr(owner, "__file__"):  # a jaxtissue module: the name must exist and be public
                    assert not node.attr.startswith("_") and hasattr(owner, node.attr), (name, node.value.id, node.attr)


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs(name):
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
