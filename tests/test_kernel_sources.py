"""Numba's cache and the modules a kernel inlines (aperture_fab.kernel_sources)."""

from __future__ import annotations

import ast
import functools
import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

import aperture_fab
from aperture_fab.kernel_sources import check_inlined, sources_digest

PACKAGE = Path(aperture_fab.__file__).parent


def load(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_edited_inlined_module_fails_the_import_and_names_the_digest(tmp_path: Path) -> None:
    path = tmp_path / "helpers.py"
    path.write_text("SCALE = 1.0\n")
    helpers = load(path)
    recorded = sources_digest(helpers)
    assert recorded is not None
    check_inlined("kernels", recorded, helpers)  # unchanged: nothing to say
    path.write_text("SCALE = 2.0\n")
    with pytest.raises(RuntimeError, match="whose source changed") as info:
        check_inlined("kernels", recorded, helpers)
    assert f'INLINED_DIGEST = "{sources_digest(helpers)}" in kernels' in str(info.value)


def test_line_endings_do_not_change_the_digest(tmp_path: Path) -> None:
    unix, windows = tmp_path / "unix.py", tmp_path / "windows.py"
    unix.write_bytes(b"A = 1\nB = 2\n")
    windows.write_bytes(b"A = 1\r\nB = 2\r\n")
    assert sources_digest(load(unix)) == sources_digest(load(windows))


def test_a_module_without_its_source_is_not_checked() -> None:
    compiled = ModuleType("compiled")
    compiled.__file__ = "compiled.cpython-311.pyc"
    assert sources_digest(compiled) is None
    check_inlined("kernels", "0" * 16, compiled)


def _numba_functions(tree: ast.Module) -> set[str]:
    """The functions a module defines with a Numba decorator (named ...jit or _parallel)."""
    return {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)
            and any(name.endswith("jit") or name == "_parallel"
                    for name in (d.id if isinstance(d, ast.Name) else getattr(d, "attr", "")
                                 for d in node.decorator_list))}


@functools.cache
def _jit_functions() -> dict[str, frozenset[str]]:
    """Per module of the package, the Numba functions it defines (modules without any left
    out)."""
    found = {".".join(p.relative_to(PACKAGE.parent).with_suffix("").parts):
             frozenset(_numba_functions(ast.parse(p.read_text()))) for p in PACKAGE.rglob("*.py")}
    return {module: names for module, names in found.items() if names}


def test_every_kernel_that_inlines_another_module_records_its_digest() -> None:
    """A module whose own Numba functions call functions of another of the package's Numba
    modules compiles them in, so it must record their digest (importing a decorator, such as
    `kernel_pair.inline_jit`, compiles nothing in)."""
    missing = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        inlined = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                   and node.module in _jit_functions()
                   and any(alias.name in _jit_functions()[node.module] for alias in node.names)}
        if _numba_functions(tree) and inlined and "INLINED_DIGEST" not in path.read_text():
            missing[path.name] = sorted(inlined)
    assert not missing, (f"these import Numba functions from other modules: {missing}; record "
                         "their digest (aperture_fab.kernel_sources.check_inlined)")
