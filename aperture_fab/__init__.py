"""aperture-fab: design and fabricate coded pinhole apertures for slim near-eye displays."""

from aperture_fab import targets
from aperture_fab.config import Config, resolve
from aperture_fab.pipeline import DesignResult, design
from aperture_fab.scene import Display, Eye, Plate, Scene

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
