"""The package's layering (docs/architecture.md): lower folders never import higher ones, so a
stage can be read, tested and changed without the jobs above it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "aperture_fab"

#: Folder (or top-level module) -> the folders it must not import, at any depth of the file.
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "config": ("optimize", "fabrication", "validation", "pipeline", "sweep", "cli"),
    "optics": ("optimize", "fabrication", "validation", "pipeline", "sweep", "cli"),
    "io": ("optimize", "validation", "pipeline", "sweep", "cli"),
    "fabrication": ("optimize", "validation", "pipeline", "sweep", "cli"),
    "optimize": ("validation", "pipeline", "sweep", "cli"),
    "validation": ("pipeline", "sweep", "cli"),
    "metrics": ("optics", "optimize", "fabrication", "validation", "pipeline", "sweep", "cli"),
    "pipeline": ("sweep", "cli"),
    "sweep": ("cli",),
}


def imported_packages(path: Path) -> set[str]:
    """The aperture_fab sub-packages or modules a file imports (first name after the package)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        for name in names:
            parts = name.split(".")
            if parts[0] == "aperture_fab" and len(parts) > 1:
                found.add(parts[1])
    return found


def files_of(unit: str) -> list[Path]:
    folder = PACKAGE / unit
    return sorted(folder.rglob("*.py")) if folder.is_dir() else [PACKAGE / f"{unit}.py"]


@pytest.mark.parametrize("unit", sorted(FORBIDDEN))
def test_lower_layers_do_not_import_higher_ones(unit: str) -> None:
    files = files_of(unit)
    assert files and all(f.is_file() for f in files)
    broken = {f.relative_to(PACKAGE).as_posix(): sorted(imported_packages(f) & set(FORBIDDEN[unit]))
              for f in files}
    assert not {f: bad for f, bad in broken.items() if bad}


def test_the_checker_sees_imports_inside_functions(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from aperture_fab.pipeline.design_job import design\n"
                      "import aperture_fab.optics.scene\n")
    assert imported_packages(source) == {"pipeline", "optics"}
