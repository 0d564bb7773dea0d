"""From an optimized plate to a part: makeable holes (quantize) and the solid (build).

Values in, values out; `aperture_fab.io.formats` turns a part into files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, build_mesh
from aperture_fab.fabrication.mesh_checks import MeshReport, check_mesh
from aperture_fab.fabrication.process import Process, UnmakeableError
from aperture_fab.fabrication.quantize import made_sizes, quantize
from aperture_fab.fabrication.rules import open_fraction_bounds
from aperture_fab.optics.as_made import MadeOptics
from aperture_fab.optics.leakage import solid_transmission
from aperture_fab.optics.scene import Plate, Scene, hole_radius_mm, open_fraction_of

__all__ = [
    "Part",
    "build_part",
    "chord_tolerance_mm",
    "design_bounds",
    "drawn_fractions",
    "make_part",
    "made_optics",
]

#: Chord error of hole polygons as a share of the process's radius sigma: well inside tolerance.
CHORD_SHARE_OF_SIGMA = 0.25
MIN_CHORD_MM = 2e-4
MAX_CHORD_MM = 5e-3
#: Legs of the alignment chamfer on the outline's top-left corner, as a share of the margin.
CORNER_CUT_SHARE = 0.6


def design_bounds(scene: Scene, process: Process) -> tuple[float, float]:
    """Open-area fractions the optimizer may use: up to the largest hole the process makes in a
    cell (as made); below the smallest makeable hole quantization diffuses the area, so the low
    end is 0."""
    _, a_max = open_fraction_bounds(process, scene.plate)
    if a_max <= 0:
        return (0.0, scene.plate.max_open_fraction)  # unmakeable: make_part says why
    try:
        made = made_sizes(scene.plate, process, scene.mid_plane_distance_mm).hi
    except UnmakeableError:  # forced past the process's rules: make_part records them
        made = a_max
    return (0.0, min(made, scene.plate.max_open_fraction))


def made_optics(scene: Scene, process: Process, diffraction: bool = True) -> MadeOptics:
    """How `process` makes this scene's plate, for the view (`aperture_fab.optics.as_made`):
    its random radius and position errors, its material's transmission and, with
    `diffraction`, the Airy kernels of the hole sizes it makes in a cell."""
    mixture = None
    if diffraction:
        from aperture_fab.optics.diffraction import airy_mixture

        sizes = made_sizes(scene.plate, process, scene.mid_plane_distance_mm)
        d_lo, d_hi = (2 * float(hole_radius_mm(level, scene.plate.pitch_mm))
                      for level in (sizes.lo, sizes.hi))
        eye = scene.eye
        mixture = airy_mixture(d_lo, d_hi, eye.view_step, eye.view_pixels)
    return MadeOptics(process.radius_sigma_mm, process.position_sigma_mm,
                      solid_transmission(process.optical_density), mixture)


@dataclass(frozen=True)
class Part:
    """A part ready to write.

    layout: the holes as made.
    mesh: the plate solid (mm, watertight), in part coordinates (bottom face at z = 0).
    report: the mesh's own checks.
    corner_cut_mm: the alignment chamfer's legs (0 for none).
    """

    layout: HoleLayout
    mesh: PlateMesh
    report: MeshReport
    corner_cut_mm: float


def drawn_fractions(open_fraction: np.ndarray, plate: Plate, process: Process) -> np.ndarray:
    """The open fractions to draw so that the process makes `open_fraction` (rows, cols): each
    open cell's radius less the process's radius bias (made = drawn + bias)."""
    a = np.asarray(open_fraction, dtype=np.float64)
    made_r = hole_radius_mm(np.clip(a, 0, None), plate.pitch_mm)
    # No wider than the cell: what the bias cannot add there, quantization records.
    drawn_r = np.where(a > 0, np.clip(made_r - process.radius_bias_mm, 0, min(plate.pitch_mm) / 2),
                       0.0)
    return open_fraction_of(drawn_r, plate.pitch_mm)


def make_part(open_fraction: np.ndarray, scene: Scene, settings: FabricationSettings) -> Part:
    """Quantize to makeable holes and build the checked solid.

    open_fraction: (rows, cols) the open fractions wanted as made; the holes are drawn larger
    or smaller by the process's radius bias so that they come out at that size.
    """
    plate, eye = scene.plate, scene.eye
    process = settings.process
    layout = quantize(drawn_fractions(open_fraction, plate, process), plate, process,
                      tilt_target_mm=eye.positions_mm[0],
                      eye_distance_mm=scene.mid_plane_distance_mm, force=settings.force)
    web = 0.0 if settings.force else process.min_web_for(plate.thickness_mm)
    part = build_part(layout, settings, web)
    report = part.report
    if not (report.watertight and report.consistently_oriented and report.bodies == 1
            and report.genus == layout.count):
        raise RuntimeError(f"the built plate failed its own checks ({report}); this is a bug, "
                           "please report it with the design.")
    return part


def build_part(layout: HoleLayout, settings: FabricationSettings, min_web_mm: float) -> Part:
    """The solid for a layout as it is (checked, not judged): polygons fine enough for the
    process's radius tolerance, the alignment chamfer, webs of at least min_web_mm."""
    margin = (layout.outline_mm[0] - layout.grid[0] * layout.pitch_mm[0]) / 2
    cut = CORNER_CUT_SHARE * margin if settings.alignment_cut and margin > 0 else 0.0
    mesh = build_mesh(layout, chord_tolerance_mm(settings.process), min_web_mm=min_web_mm,
                      corner_cut_mm=cut)
    return Part(layout, mesh, check_mesh(mesh), cut)


def chord_tolerance_mm(process: Process) -> float:
    """How far a hole's polygon may stray from its circle for this process (mm): a share of
    its radius sigma, well inside what it makes, within MIN_CHORD_MM..MAX_CHORD_MM."""
    return min(MAX_CHORD_MM, max(MIN_CHORD_MM, CHORD_SHARE_OF_SIGMA * process.radius_sigma_mm))

