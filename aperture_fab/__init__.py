"""aperture-fab: design and fabricate coded pinhole apertures for slim near-eye displays.

One function per command, each returning what its command prints: `run_design` (`design`: a
folder with the part and its report), `validate`, `render`, `display`, `export`, `assembly`,
`measure_plate` (`measure`: `aperture_fab.measure` is its package); `design` is the design job
without files (targets and config in; the design, its part, the part's files as bytes and, with
validation settings, its judged `Report` out: `Verdict`s and report.json's content).

The public names are loaded on first use (PEP 562): `import aperture_fab` stays cheap, so the
command line can print its help, presets and processes without importing PyTorch, and
`aperture_fab.design` imports the optimizer only when it is asked for.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

# PyTorch's OpenMP threads spin for milliseconds after each parallel region (GNU OpenMP's
# default), holding the cores the Numba kernels that follow run on: a seed design's kernels ran
# at one thread's speed, 1.96 against 1.01 ms a forward (benchmarks/README.md). Passive waiting
# gives the cores back at once. OpenMP reads it when torch loads, so it acts only where torch
# was not imported before aperture_fab; a value already set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

if TYPE_CHECKING:
    from aperture_fab import targets
    from aperture_fab.config import Config, resolve
    from aperture_fab.measure.job import run_measure as measure_plate
    from aperture_fab.optics.scene import Display, Eye, Plate, Scene
    from aperture_fab.pipeline import DesignResult, design, run_design
    from aperture_fab.pipeline.assembly_job import run_assembly as assembly
    from aperture_fab.pipeline.export_job import export
    from aperture_fab.pipeline.render_job import run_display as display
    from aperture_fab.pipeline.render_job import run_render as render
    from aperture_fab.pipeline.validate_job import run_validate as validate
    from aperture_fab.validation.report import Report, Verdict

__all__ = [
    "Config",
    "DesignResult",
    "Display",
    "Eye",
    "Plate",
    "Report",
    "Scene",
    "Verdict",
    "assembly",
    "design",
    "display",
    "export",
    "measure_plate",
    "render",
    "resolve",
    "run_design",
    "targets",
    "validate",
]
__version__ = "0.1.0"

# public name -> (module that defines it, attribute in it; None: the module itself)
_LAZY: dict[str, tuple[str, str | None]] = {
    "Config": ("aperture_fab.config", "Config"),
    "DesignResult": ("aperture_fab.pipeline", "DesignResult"),
    "Display": ("aperture_fab.optics.scene", "Display"),
    "Eye": ("aperture_fab.optics.scene", "Eye"),
    "Plate": ("aperture_fab.optics.scene", "Plate"),
    "Report": ("aperture_fab.validation.report", "Report"),
    "Scene": ("aperture_fab.optics.scene", "Scene"),
    "Verdict": ("aperture_fab.validation.report", "Verdict"),
    "assembly": ("aperture_fab.pipeline.assembly_job", "run_assembly"),
    "design": ("aperture_fab.pipeline", "design"),
    "display": ("aperture_fab.pipeline.render_job", "run_display"),
    "export": ("aperture_fab.pipeline.export_job", "export"),
    "measure_plate": ("aperture_fab.measure.job", "run_measure"),
    "render": ("aperture_fab.pipeline.render_job", "run_render"),
    "resolve": ("aperture_fab.config", "resolve"),
    "run_design": ("aperture_fab.pipeline", "run_design"),
    "targets": ("aperture_fab.targets", None),
    "validate": ("aperture_fab.pipeline.validate_job", "run_validate"),
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
