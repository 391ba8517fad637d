"""The codebase's own rules, checked from its source: the package's imports form no
cycle, no private name (`_name`, or a private module) is used outside its module, and
every citation of the model document points at a section that exists."""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxtissue"


def module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def package_of(name: str, path: pathlib.Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def imports(path: pathlib.Path):
    """(importing module, imported module, names) for every import in a file of the
    package, function-level ones included, relative ones resolved."""
    name = module_name(path)
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield name, alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = package_of(name, path).split(".")
                anchor = ".".join(package[: len(package) - node.level + 1])
                base = f"{anchor}.{base}" if node.module else anchor
            yield name, base, tuple(a.name for a in node.names)


def dependencies():
    """The package's import graph: module -> modules it imports (a name imported from
    a package that is itself a module counts as that module)."""
    graph = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        for _, target, names in imports(path):
            if not target.startswith("jaxtissue"):
                continue
            submodules = [f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES]
            if submodules:
                graph[module].update(submodules)
            if len(submodules) < len(names) or not names:
                assert target in MODULES, f"{module} imports {target}, which is not a module of the package"
                graph[module].add(target)
    return graph


def test_the_package_imports_without_cycles():
    graph = dependencies()
    assert "jaxtissue.numerics" in graph["jaxtissue.simulate"]  # the graph sees imports
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_numerics_and_plots_import_no_model_or_study():
    graph = dependencies()
    for module, deps in graph.items():
        if module.startswith("jaxtissue.numerics"):
            assert all(d.startswith("jaxtissue.numerics") or d == "jaxtissue._custom_types" for d in deps), (module, deps)
    assert not any(d.startswith("jaxtissue.studies") for d in graph["jaxtissue.plots"])


def test_the_workflows_load_on_first_use():
    """`import jaxtissue` (and so every command) does not import `jaxtissue.studies`; its
    modules still come as attributes (`jt.calibration`, `from jaxtissue import sweep`)."""
    graph = dependencies()
    assert not any(d.startswith("jaxtissue.studies") for d in graph["jaxtissue"] | graph["jaxtissue.studies"])
    import jaxtissue as jt
    from jaxtissue import sweep

    assert jt.calibration.__name__ == "jaxtissue.studies.calibration" and sweep is jt.studies.sweep
    assert {"studies", "posterior"} <= set(dir(jt)) and "sweep_dask" in dir(jt.studies)
    with pytest.raises(AttributeError, match="no_such_workflow"):
        jt.no_such_workflow


def test_the_solvers_libraries_load_on_first_use():
    """`import jaxtissue` and the command line leave diffrax, optimistix and lineax
    unimported until a run is traced (a run loaded as a saved program never needs them);
    the numerics built on them still come from `jaxtissue.numerics`."""
    import subprocess
    import sys

    code = ("import sys, jaxtissue, jaxtissue.cli; "
            "print(*(m in sys.modules for m in ('diffrax', 'optimistix', 'lineax'))); "
            "from jaxtissue.numerics import ROS34PW2, LevenbergMarquardt; "
            "print(ROS34PW2.__module__, LevenbergMarquardt.__module__, 'diffrax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout.splitlines()
    assert out == ["False False False", "jaxtissue.numerics._rosenbrock jaxtissue.numerics._least_squares True"]
    import jaxtissue.numerics as numerics

    assert {"ROS34PW2", "quantise", "Stacked"} <= set(dir(numerics))
    with pytest.raises(AttributeError, match="no_such_solver"):
        numerics.no_such_solver


def _python_files():
    for folder in ("jaxtissue", "tests", "benchmarks", "calibrate"):
        yield from (ROOT / folder).rglob("*.py")


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_is_used_outside_its_module():
    bad = []
    for path in _python_files():
        tree = ast.parse(path.read_text())
        own = module_name(path) if path.is_relative_to(PACKAGE) else None
        own_package = package_of(own, path) if own else None
        aliases = set()  # local names bound to jaxtissue modules
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                if isinstance(node, ast.ImportFrom):
                    module = node.module or ""
                    if node.level and own:
                        package = own_package.split(".")
                        anchor = ".".join(package[: len(package) - node.level + 1])
                        module = f"{anchor}.{module}" if node.module else anchor
                    if not module.startswith("jaxtissue"):
                        continue
                    parts = module.split(".")
                    private_part = next((i for i, p in enumerate(parts) if _private(p)), None)
                    if private_part is not None and not (own_package or "").startswith(".".join(parts[:private_part])):
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: imports private module {module}")
                    for alias in node.names:
                        if _private(alias.name) and module != own:
                            bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: imports {alias.name} from {module}")
                        if f"{module}.{alias.name}" in MODULES:
                            aliases.add(alias.asname or alias.name)
                else:
                    for alias in node.names:
                        if alias.name.startswith("jaxtissue"):
                            aliases.add(alias.asname or alias.name.split(".")[0])
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _private(node.attr):
                base = node.value
                while isinstance(base, ast.Attribute):
                    base = base.value
                if isinstance(base, ast.Name) and base.id in aliases:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: uses {node.attr} of {base.id}")
    assert not bad, "\n".join(bad)


def test_the_model_document_is_cited_by_its_own_sections():
    sections = set(re.findall(r"^## (§\d+)", (ROOT / "docs" / "model.md").read_text(), flags=re.M))
    assert {f"§{k}" for k in range(1, 9)} <= sections
    cited, missing = 0, []
    for path in [*_python_files(), *ROOT.glob("*.md"), *(ROOT / "docs").glob("*.md"), *(ROOT / "benchmarks").glob("*.md"),
                 *(ROOT / "notebooks").glob("*.ipynb"), *ROOT.glob("*/*.toml")]:
        text = path.read_text()
        assert "MODEL" ".md" not in text, f"{path.relative_to(ROOT)} cites a document outside the repository"
        for match in re.finditer(r"docs/model\.md (§\d+(?:, §\d+)*)", text):
            for section in re.findall(r"§\d+", match.group(1)):
                cited += 1
                if section not in sections:
                    missing.append(f"{path.relative_to(ROOT)}: {section}")
    assert cited > 20 and not missing, missing


def test_readme_is_a_short_user_page():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.encode()) <= 12 * 1024
    first = [line for line in readme.splitlines() if line.startswith("python3 -m venv")]
    assert "jaxtissue reproduce" in first[0] and "pytest" in first[1]
    assert first[1].split("&& ", 1)[1] in (ROOT / ".ci" / "run").read_text()
