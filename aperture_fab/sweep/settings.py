"""What one point of a sweep resolves to (its config and stage settings), and the sweep's
optional dependencies: the lowest layer of the sweep, which the runner, the workers and the
results all read."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["EXTRA", "require", "resolve_point"]

EXTRA = "pip install 'aperture-fab[sweep]'"


def require(module: str) -> Any:
    """Import an optional dependency, or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"the sweep needs {module.split('.')[0]}, which is not installed: "
                          f"{EXTRA}") from err


def resolve_point(preset: str | None, base_file: Mapping[str, Any] | None,
                  overrides: Mapping[str, Any]) -> tuple[Any, Any, Any]:
    """(Config, FabricationSettings, ValidationSettings) of a point; raises what resolve does.
    A point designs on its own plate (optimizer.lattice = "fixed") unless the sweep sets
    optimizer.lattice: the design job would otherwise design a losing part again on another
    lattice, and a sweep over the plate would compare parts it did not ask for."""
    from aperture_fab.config import resolve

    if "optimizer.lattice" not in overrides and "lattice" not in dict(
            (base_file or {}).get("optimizer", {})):
        overrides = {**overrides, "optimizer.lattice": "fixed"}
    config = resolve(preset, base_file, overrides, file_source="the [sweep] config file")
    return config, config.fabrication, config.validation
