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


def _stage_settings(extra: Any) -> tuple[Any, Any]:
    """Fabrication and validation settings from a config's extra tables ([process],
    [fabrication], [validation])."""
    from aperture_fab.fabrication.part import fabrication_settings
    from aperture_fab.validation.validate import validation_settings

    return fabrication_settings(extra), validation_settings(extra)


def resolve_point(preset: str | None, base_file: Mapping[str, Any] | None,
                  overrides: Mapping[str, Any]) -> tuple[Any, Any, Any]:
    """(Config, FabricationSettings, ValidationSettings) of a point; raises what resolve does."""
    from aperture_fab.config import resolve

    config = resolve(preset, base_file, overrides, file_source="the [sweep] config file")
    fabrication, validation = _stage_settings(config.extra)
    return config, fabrication, validation
