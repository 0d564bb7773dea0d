"""aperture-fab: design and fabricate coded pinhole apertures for slim near-eye displays.

The public names are loaded on first use (PEP 562): `import aperture_fab` stays cheap, so the
command line can print its help, presets and processes without importing PyTorch, and
`aperture_fab.design` imports the optimizer only when it is asked for.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from aperture_fab import targets
    from aperture_fab.config import Config, resolve
    from aperture_fab.optics.scene import Display, Eye, Plate, Scene
    from aperture_fab.pipeline import DesignResult, design

__all__ = [
    "Config",
    "DesignResult",
    "Display",
    "Eye",
    "Plate",
    "Scene",
    "design",
    "resolve",
    "targets",
]
__version__ = "0.1.0"

# public name -> (module that defines it, attribute in it; None: the module itself)
_LAZY: dict[str, tuple[str, str | None]] = {
    "Config": ("aperture_fab.config", "Config"),
    "DesignResult": ("aperture_fab.pipeline", "DesignResult"),
    "Display": ("aperture_fab.optics.scene", "Display"),
    "Eye": ("aperture_fab.optics.scene", "Eye"),
    "Plate": ("aperture_fab.optics.scene", "Plate"),
    "Scene": ("aperture_fab.optics.scene", "Scene"),
    "design": ("aperture_fab.pipeline", "design"),
    "resolve": ("aperture_fab.config", "resolve"),
    "targets": ("aperture_fab.targets", None),
}


def __getattr__(name: str) -> Any:
    try:
        module_name, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(
            f"module 'aperture_fab' has no attribute {name!r}; its public names are "
            f"{', '.join(__all__)} and __version__"
        ) from None
    module = importlib.import_module(module_name)
    value = module if attr is None else getattr(module, attr)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
