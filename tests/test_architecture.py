"""The package's layering (docs/architecture.md): lower folders never import higher ones, so a
stage can be read, tested and changed without the jobs above it; and no module imports itself
through others (an import circle), imports inside functions included, type-checking-only ones
not."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "aperture_fab"

#: Folder (or top-level module) -> the folders it must not import, at any depth of the file.
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "config": ("optimize", "fabrication", "validation", "report", "pipeline", "sweep", "cli"),
    "optics": ("optimize", "fabrication", "validation", "report", "pipeline", "sweep", "cli"),
    "io": ("optimize", "validation", "report", "pipeline", "sweep", "cli"),
    "fabrication": ("optimize", "validation", "report", "pipeline", "sweep", "cli"),
    "optimize": ("validation", "report", "pipeline", "sweep", "cli"),
    # Judging apart from drawing: validation computes the verdicts and figures' data, report/
    # draws them (the page, the figures, the assembly sheet).
    "validation": ("report", "pipeline", "sweep", "cli"),
    "report": ("pipeline", "sweep", "cli"),
    "metrics": ("optics", "optimize", "fabrication", "validation", "report", "pipeline", "sweep",
                "cli"),
    "pipeline": ("sweep", "cli"),
    "sweep": ("cli",),
    # The error classes that carry their exit status: importable from anywhere, importing nothing.
    "errors": ("config", "optics", "io", "fabrication", "optimize", "validation", "report",
               "pipeline", "sweep", "cli", "metrics", "measure", "targets"),
}


#: Modules of a forbidden folder that a folder may import all the same: the process catalog
#: is data (the config types its [process] table with it) and imports nothing of the package
#: but its error classes.
ALLOWED: dict[str, tuple[str, ...]] = {"config": ("aperture_fab.fabrication.process",)}


def imported_packages(path: Path, allowed: tuple[str, ...] = ()) -> set[str]:
    """The aperture_fab sub-packages or modules a file imports (first name after the package),
    imports of the modules in `allowed` left out."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        for name in names:
            parts = name.split(".")
            if parts[0] == "aperture_fab" and len(parts) > 1 and name not in allowed:
                found.add(parts[1])
    return found


def files_of(unit: str) -> list[Path]:
    folder = PACKAGE / unit
    return sorted(folder.rglob("*.py")) if folder.is_dir() else [PACKAGE / f"{unit}.py"]


@pytest.mark.parametrize("unit", sorted(FORBIDDEN))
def test_lower_layers_do_not_import_higher_ones(unit: str) -> None:
    files = files_of(unit)
    assert files and all(f.is_file() for f in files)
    allowed = ALLOWED.get(unit, ())
    broken = {f.relative_to(PACKAGE).as_posix():
              sorted(imported_packages(f, allowed) & set(FORBIDDEN[unit])) for f in files}
    assert not {f: bad for f, bad in broken.items() if bad}


@pytest.mark.parametrize("module", sorted({m for ms in ALLOWED.values() for m in ms}))
def test_allowed_modules_import_only_the_error_classes(module: str) -> None:
    path = PACKAGE.parent / (module.replace(".", "/") + ".py")
    assert imported_packages(path) <= {"errors"}


def test_the_checker_sees_imports_inside_functions(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from aperture_fab.pipeline.design_job import design\n"
                      "import aperture_fab.optics.scene\n")
    assert imported_packages(source) == {"pipeline", "optics"}


def module_name(path: Path, root: Path = PACKAGE) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_only(tree: ast.AST) -> set[int]:
    """ids of the nodes under `if TYPE_CHECKING:`."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                skip.update(id(n) for n in ast.walk(sub))
    return skip


def imported_modules(path: Path, modules: set[str], root: Path = PACKAGE) -> set[str]:
    """The package's modules a file imports: `from a.b import c` names module a.b.c where
    that is one, else a.b (its __init__); relative imports resolved."""
    name = module_name(path, root)
    tree = ast.parse(path.read_text())
    skip = _type_checking_only(tree)
    here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = here[:len(here) - (node.level - 1)]
                base = ".".join([*parent, *([base] if base else [])])
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in modules else base)
    return {m for m in found if m in modules and m != name}


def import_circles(root: Path = PACKAGE) -> list[list[str]]:
    """The strongly connected groups (two modules or more) of the import graph (Tarjan)."""
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    graph = {m: imported_modules(p, set(files), root) for m, p in files.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def test_no_import_circles() -> None:
    assert import_circles() == []


def test_the_circle_finder_sees_circles_through_functions_but_not_type_checking(
        tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from pkg.b import f\n")
    (package / "b.py").write_text("def f():\n    from pkg import c\n")
    (package / "c.py").write_text("from . import a\n")
    (package / "d.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                  "    from pkg.e import x\n")
    (package / "e.py").write_text("from pkg.d import y\n")
    assert import_circles(package) == [["pkg.a", "pkg.b", "pkg.c"]]


#: The functions a design run may hand the whole config to (tools/config_stops.py, measured
#: 2026-11-28: 8 stops; 22 before issue 19; 9 since 2026-11-29, when `design` became the
#: choice between lattices over `_design_on`, the design on one): the stages below take what
#: they need from it.
CONFIG_STOPS_MAX = 9


@pytest.mark.slow
def test_the_config_stops_at_few_functions(tmp_path: Path, marker_png: Path) -> None:
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "config_stops", PACKAGE.parent / "tools" / "config_stops.py")
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    config_calls, settings_calls = tool.trace_design(marker_png, tmp_path / "out")
    assert "pipeline/design_job.py:run_design" in config_calls  # the trace saw the run
    assert settings_calls  # and the stages that take their own settings
    assert len(config_calls) <= CONFIG_STOPS_MAX, sorted(config_calls)
