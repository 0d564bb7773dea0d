"""Validation: what the eye sees through the part as built, beside the design and simple
alternatives, and how tolerances spread it.

Variants, each rendered for every target and eye position and judged the same way:

- ``open``: no plate, the display showing the target;
- ``regular_pinholes``: optimal pinholes on a regular lattice, the display showing elemental
  images (for the nominal eye position);
- ``random``: a uniform random mask (the dissertation's start), the display showing the target;
- ``optimized``: the design before quantization;
- ``quantized``: the holes as drawn in the files (quantized, bias-compensated) in the design
  model, as if the process added no bias;
- ``as_built``: the holes as the process makes them on average (its radius bias applied): the
  design, when the process's bias is what it claims;
- ``as_built_mesh``: an independent ray trace through the mesh that was written (nominal eye
  position; Monte Carlo, its standard error reported). The mesh holds the holes as drawn, so it
  checks ``quantized``: that the file is the layout;
- ``as_built_diffraction``: ``as_built`` with each hole's Airy spread per colour channel.

Tolerances (Monte Carlo): hole-radius bias and sigma of the process, hole position error of the
process (each hole displaced laterally), gap error, plate tilt, eye position across the eyebox.

Plate tilt. The plate turns by a small angle alpha (right-handed) about the in-plane axis
u = (cos phi, sin phi) through its centre at mid-thickness (a tilt about another axis is this
tilt plus a gap error). The mid-thickness centre p of a hole then rises toward the eye by
delta = sin(alpha) d, d = y cos(phi) - x sin(phi) its signed distance from the axis, and moves
in-plane by -(1 - cos(alpha)) d (-sin(phi), cos(phi)). The model holds holes in one plane, so a
raised hole is replaced by the hole at the original height that the eye (lateral position c,
s_h = eye relief + t/2 above the mid-plane) sees in the same place: its central projection
p_e = c + (p' - c) s_h / (s_h - delta), i.e. a lateral shift e ~ delta (p - c) / s_h along its
chief ray. Why that is right to first order in delta / s_h (h = gap + t/2, infinite focus; the
same holds along y): for view direction v (tan), the raised hole shows display point
x_h + (h + delta) v to rays whose pupil footprint is offset by x_h - c - (s_h - delta) v from the
hole; the shifted hole shows x_h + e + h v, footprint offset x_h + e - c - s_h v. With
v_c = (x_h - c) / s_h the chief direction, both differ by delta (v - v_c) + O(delta^2 / s_h): zero
on the chief ray (there both are exact: same window centre, same direction), and at most
delta R / s_h across the range |v - v_c| <= R / s_h over which the pupil (radius R) sees the hole.
So the window centre agrees to delta R / s_h on the display (delta R / (s_h h) in view angle,
1e-3 for delta = 0.05 mm, R = 2 mm, s_h = h = 10 mm: 0.15 of a near-eye view pixel) and
the pupil's edge to the same fraction delta / s_h of its radius, while the shift itself is
delta |x_h - c| / s_h, largest for the holes far off the eye's axis. Neglected: the hole axis
turns with the plate (by alpha against the chief ray: more or less wall vignetting in a thick
plate), the delta / h change of each hole's angular magnification, plate warp.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import Config
from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.config.stages import YIELD_MARGIN_DB, ValidationSettings
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.part import Part
from aperture_fab.fabrication.process import Process, UnmakeableError
from aperture_fab.io.images import resample
from aperture_fab.metrics import gain_mse, gain_psnr_db, psnr_db
from aperture_fab.metrics import metrics as view_metrics
from aperture_fab.optics.baselines import elemental_display, regular_pinholes
from aperture_fab.optics.device import resolve_device, torch_dtype
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer, StackShape
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.scene import Eye, Plate, Scene, open_fraction_of
from aperture_fab.validation.judged_cache import JudgedCache, cached
from aperture_fab.validation.made_part import made_part_block
from aperture_fab.validation.robustness import EyeQuality, Variant, judge_eyes
from aperture_fab.validation.variants import VARIANTS

__all__ = ["BASELINES", "Validation", "baseline_views", "judge_made_part", "layout_fractions",
           "validate"]

#: Eye states each tolerance sample of a moving-eye design is judged over.
TOLERANCE_EYE_STATES = 8


@dataclass(frozen=True)
class Validation:
    """views: {variant: (T, P, C, ny, nx) float64} (as_built_mesh: P = 1, nominal position).
    metrics: {variant: {target: {mse, psnr_db, ssim, light_efficiency}}} at the nominal eye
        position, plus "eyebox" means when there are several positions.
    mesh_stderr: (T, C, ny, nx) Monte Carlo standard error of as_built_mesh, or None.
    tolerance: {"samples", "psnr_db": [...], "psnr_percentiles", "threshold_db", "yield"} or None.
    timings_s: seconds per part of the validation.
    eyes: the part (as_built) and the baselines judged over the eye distribution, or None.
    made_part: report.json's "made_part" block (`made_part.made_part_block`): the part as made
        over made copies x eye states beside the best regular array, or None.
    """

    views: dict[str, np.ndarray]
    metrics: dict[str, dict[str, dict[str, float]]]
    mesh_stderr: np.ndarray | None
    tolerance: dict[str, Any] | None
    timings_s: dict[str, float]
    eyes: EyeQuality | None = None
    made_part: dict[str, Any] | None = None


def layout_fractions(layout: HoleLayout, bias_mm: float = 0.0) -> np.ndarray:
    """Open-area fraction per cell (rows, cols) of the holes as made (radius + bias, >= 0)."""
    nx, ny = layout.grid
    a = np.zeros((ny, nx))
    radii = np.clip(layout.radii_mm + bias_mm, 0, None)
    a[layout.cells[:, 0], layout.cells[:, 1]] = open_fraction_of(radii, layout.pitch_mm)
    return a


def _render_all(renderer: Renderer, a: np.ndarray, displays: list[torch.Tensor],
                positions: range) -> np.ndarray:
    dtype, device = renderer.dtype, renderer.device
    a_t = torch.as_tensor(a, dtype=dtype, device=device)
    with torch.no_grad():
        return np.stack([
            np.stack([renderer.render(a_t, d, p).cpu().double().numpy() for p in positions])
            for d in displays
        ])


#: The variants `baseline_views` renders: what the part is compared with, whatever it is.
BASELINES = ("open", "regular_pinholes")


def baseline_views(renderer: Renderer, targets: np.ndarray, cache: JudgedCache | None = None
                   ) -> dict[str, np.ndarray]:
    """The baselines' views (T, P, C, ny, nx) at every eye position of the renderer's scene:
    the open display showing each target ("open", the best it can do without a plate) and the
    regular pinhole array showing its elemental images ("regular_pinholes").

    targets: (T, C, ny, nx) linear, on the view grid. cache: keeps them between runs (they
    depend on the scene and the targets alone)."""
    return cached(cache, partial(_baseline_views, renderer, targets), "baseline views",
                  targets, *_renderer_key(renderer))


def _renderer_key(renderer: Renderer) -> tuple[Any, ...]:
    """What a renderer's views depend on besides the plate and the display."""
    return (renderer.scene, renderer.hole_offset_mm, renderer.oversample, renderer.backend,
            renderer.dtype, renderer.device.type)


def _baseline_views(renderer: Renderer, targets: np.ndarray) -> dict[str, np.ndarray]:
    scene, dtype, device = renderer.scene, renderer.dtype, renderer.device
    positions = range(len(scene.eye.positions_mm))
    on_display = [torch.as_tensor(resample(t, scene.display.pixels), dtype=dtype, device=device)
                  for t in targets]
    pinholes = regular_pinholes(scene)
    with torch.no_grad():
        views = {"open": np.stack([
            np.stack([render_open(scene, d, p).cpu().double().numpy() for p in positions])
            for d in on_display
        ])}
    views["regular_pinholes"] = _render_all(
        renderer, pinholes.open_fraction,
        [elemental_display(scene, pinholes, torch.as_tensor(t, dtype=dtype, device=device))
         for t in targets], positions)
    return views


def validate(
    config: Config,
    targets: np.ndarray,
    displays: np.ndarray,
    open_fraction: np.ndarray,
    part: Part,
    process: Process,
    names: tuple[str, ...],
    settings: ValidationSettings,
    mesh: PlateMesh | None = None,
    *,
    built_displays: np.ndarray | None = None,
    baselines: Mapping[str, np.ndarray] | None = None,
    cache: JudgedCache | None = None,
    made_part: dict[str, Any] | None = None,
) -> Validation:
    """Validate a design and its part.

    targets: (T, C, ny, nx) linear, on the view grid; displays: (T, C, H, W) the display content
    the design was optimized with; built_displays: the content re-fitted to the part (default:
    displays), used for every variant made from the part.
    open_fraction: (rows, cols) the optimized design before quantization.
    mesh: the mesh as written and re-read (default: part.mesh).
    baselines: `baseline_views` of these targets when the caller rendered them already (the
    design job has); None renders them.
    cache: keeps what does not depend on the part between runs: the regular family's
    judgements (`made_part_block`), the baselines' views and their figures over the eye
    distribution (`judge_eyes`), the random mask's views.
    made_part: the part's `judge_made_part` block when the caller judged it already (the
    design job does, to choose its lattice); None judges it here.
    """
    scene = config.scene
    device = resolve_device(config.optimizer.device)
    dtype = torch_dtype(config.optimizer.precision)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    renderer = Renderer(scene, device=device, dtype=dtype)
    positions = range(len(scene.eye.positions_mm))
    designed = [torch.as_tensor(d, dtype=dtype, device=device) for d in displays]
    shown = designed if built_displays is None else [
        torch.as_tensor(d, dtype=dtype, device=device) for d in built_displays]
    on_display = [torch.as_tensor(resample(t, scene.display.pixels), dtype=dtype, device=device)
                  for t in targets]
    rng = np.random.default_rng(settings.seed)
    quantized = layout_fractions(part.layout)
    as_built = layout_fractions(part.layout, process.radius_bias_mm)
    views = dict(baseline_views(renderer, targets, cache) if baselines is None else baselines)
    random_mask = rng.uniform(0, scene.plate.max_open_fraction, open_fraction.shape)
    views["random"] = cached(
        cache, lambda: {"views": _render_all(renderer, random_mask, on_display, positions)},
        "random mask views", random_mask, on_display, *_renderer_key(renderer))["views"]
    views["optimized"] = _render_all(renderer, open_fraction, designed, positions)
    views["quantized"] = _render_all(renderer, quantized, shown, positions)
    views["as_built"] = _render_all(renderer, as_built, shown, positions)
    timings["render_s"] = time.perf_counter() - start

    mesh_stderr = None
    if settings.mesh_samples != 0:
        from aperture_fab.validation.retrace import trace_mesh_view

        start = time.perf_counter()
        traced = [trace_mesh_view(mesh if mesh is not None else part.mesh, scene,
                                  d.cpu().double().numpy(), 0, settings.mesh_samples,
                                  settings.seed) for d in shown]
        views["as_built_mesh"] = np.stack([t.view[None] for t in traced])
        mesh_stderr = np.stack([t.stderr for t in traced])
        timings["mesh_retrace_s"] = time.perf_counter() - start
    if settings.diffraction:
        from aperture_fab.optics.diffraction import diffraction_view

        start = time.perf_counter()
        a_t = torch.as_tensor(as_built, dtype=dtype, device=device)
        with torch.no_grad():
            views["as_built_diffraction"] = np.stack([
                np.stack([diffraction_view(renderer, a_t, d, p).cpu().double().numpy()
                          for p in positions])
                for d in shown
            ])
        timings["diffraction_s"] = time.perf_counter() - start

    metrics = _metrics(scene, views, targets, shown, designed, on_display, names)
    eyes = None
    if settings.eye_states > 0:
        start = time.perf_counter()
        as_numpy = [d.cpu().double().numpy() for d in shown]
        pinholes = regular_pinholes(scene)
        eyes = judge_eyes(scene, targets, {
            "as_built": Variant(as_built, np.stack(as_numpy)),
            "optimized": Variant(open_fraction, np.stack([d.cpu().double().numpy()
                                                          for d in designed])),
            "open": Variant(None, np.stack([d.cpu().double().numpy() for d in on_display])),
            "regular_pinholes": Variant(pinholes.open_fraction, np.stack([
                elemental_display(scene, pinholes, torch.as_tensor(t, dtype=dtype, device=device))
                .cpu().double().numpy() for t in targets])),
        }, device=device, dtype=dtype, count=settings.eye_states, cache=cache)
        timings["eye_distribution_s"] = time.perf_counter() - start
    if made_part is None and settings.eye_states > 0 and settings.made_copies > 0:
        start = time.perf_counter()
        made_part = judge_made_part(scene, config.optimizer, targets, part, process,
                                    np.stack([d.cpu().double().numpy() for d in shown]),
                                    settings, cache)
        timings["made_part_s"] = time.perf_counter() - start
    tolerance = None
    if settings.tolerance_samples > 0:
        start = time.perf_counter()
        tolerance = tolerance_analysis(scene, targets, shown, part.layout, process, settings,
                                       settings.threshold_db, device, dtype)
        timings["tolerance_s"] = time.perf_counter() - start
    return Validation(views, metrics, mesh_stderr, tolerance, timings, eyes, made_part)


def judge_made_part(scene: Scene, optimizer: OptimizerSettings, targets: np.ndarray,
                    part: Part, process: Process, displays: np.ndarray,
                    settings: ValidationSettings, cache: JudgedCache | None = None
                    ) -> dict[str, Any] | None:
    """report.json's "made_part" block (`made_part.made_part_block`) for a part showing
    displays (T, C, H, W): its holes as made (the process's bias) over made copies x eye states
    beside the best regular array; None when the settings skip it (no eye states or no made
    copies) or the process makes no regular family (a forced part)."""
    if settings.eye_states == 0 or settings.made_copies == 0:
        return None
    try:
        return made_part_block(
            scene, optimizer, targets, layout_fractions(part.layout, process.radius_bias_mm),
            displays, process, states=settings.eye_states, copies=settings.made_copies,
            seed=settings.seed, device=resolve_device(optimizer.device),
            dtype=torch_dtype(optimizer.precision), cache=cache)
    except UnmakeableError:
        return None


def _metrics(scene: Scene, views: dict[str, np.ndarray], targets: np.ndarray,
             shown: list[torch.Tensor], designed: list[torch.Tensor],
             on_display: list[torch.Tensor], names: tuple[str, ...]
             ) -> dict[str, dict[str, dict[str, float]]]:
    """Metrics at the nominal position; light efficiency against the open display showing the
    same content as the variant's display."""
    with torch.no_grad():
        levels = {
            "shown": [float(render_open(scene, d).mean()) for d in shown],
            "designed": [float(render_open(scene, d).mean()) for d in designed],
            "target": [float(render_open(scene, d).mean()) for d in on_display],
        }
    out: dict[str, dict[str, dict[str, float]]] = {}
    for variant, v in views.items():
        reference = levels[VARIANTS[variant].display]
        out[variant] = {
            name: view_metrics(v[t, 0], targets[t], reference[t]) for t, name in enumerate(names)
        }
    return out


def _tilt_offsets_mm(scene: Scene, eye_mm: tuple[float, float], tilt_rad: float,
                     axis_rad: float) -> np.ndarray:
    """Lateral hole offsets (rows, cols, 2) mm equivalent to tilting the plate by tilt_rad about
    the in-plane axis at axis_rad through its centre, for an eye at eye_mm (module docstring)."""
    plate = scene.plate
    xs, ys = plate.cell_centres_mm()
    x, y = np.meshgrid(xs, ys)  # (rows, cols)
    nx, ny = -math.sin(axis_rad), math.cos(axis_rad)  # in-plane normal to the tilt axis
    d = x * nx + y * ny
    rise = math.sin(tilt_rad) * d
    s_h = scene.mid_plane_distance_mm
    low, high = -plate.gap_mm, scene.eye.eye_relief_mm
    if rise.min() <= low or rise.max() >= high:
        raise ValueError(
            f"a plate tilt of {math.degrees(tilt_rad):.3g} deg moves holes by {rise.min():.3g} "
            f"to {rise.max():.3g} mm, into the display or the eye (allowed: {low:g} to {high:g}); "
            "lower validation.tilt_sigma_deg."
        )
    shrink = (1 - math.cos(tilt_rad)) * d
    tilted_x, tilted_y = x - shrink * nx, y - shrink * ny
    scale = s_h / (s_h - rise)
    return np.stack([eye_mm[0] + (tilted_x - eye_mm[0]) * scale - x,
                     eye_mm[1] + (tilted_y - eye_mm[1]) * scale - y], axis=-1)


def scaled_field_deg(fov_deg: tuple[float, float], scale: float) -> tuple[float, float]:
    """The full field (x, y), degrees, whose view directions (tan) are `scale` times those of
    fov_deg."""
    return tuple(math.degrees(2 * math.atan(scale * math.tan(math.radians(f) / 2)))
                 for f in fov_deg)  # type: ignore[return-value]


#: A tolerance sample's gap error, judged over the field its gap scales the picture to, moves
#: the view pixel's box on the display by about 1e-6 (relative): within this, its stack is
#: the nominal one's (`StackShape.filters_like`), 16 builds fewer on the default part (about
#: 0.2 s each), the PSNR within 1e-4 dB (tests/test_validate.py).
BOX_RTOL = 1e-4


def tolerance_analysis(scene: Scene, targets: np.ndarray, shown: list[torch.Tensor],
                       layout: HoleLayout, process: Process, settings: ValidationSettings,
                       threshold_db: float | None, device: torch.device, dtype: torch.dtype
                       ) -> dict[str, Any]:
    """PSNR (first target) over Monte Carlo samples of the process and assembly tolerances.

    Per sample: hole radii (process bias + normal sigma), gap, eye position, each hole's
    position (process position sigma per axis) and the plate's tilt (normal angle of
    settings.tilt_sigma_deg about an axis of uniform direction), the last two as lateral hole
    offsets (module docstring). Draws for the older terms come first, so adding the new ones
    leaves their samples as they were.

    A scene whose eye moves (an eye distribution, not a point) is judged per sample by its mean
    PSNR over TOLERANCE_EYE_STATES states of that distribution instead, with the eye position
    error left out: the distribution already holds where the eye may be, and drawing it again
    would count the eye's motion as a manufacturing loss.

    A gap error g + d scales the picture and does not blur it: through every hole, view
    direction v meets the display where direction v (1 + d / g) meets it at the nominal gap
    (exactly for eyes focused at infinity), so the view is the nominal plate's view, (g + d) / g
    times larger. Each sample is judged at its picture's own size (its view directions scaled
    by g / (g + d)), and the size error is given apart (`gap_scale_sigma_percent`): a picture 1 %
    larger is not a worse picture, and PSNR against the target at the nominal size would count
    it as one (a line pattern loses 4 dB at 2 %; tests/test_tolerance.py checks the identity).

    threshold_db: the PSNR a good part reaches; None: the part without errors (its bias
    applied), judged the same way, less YIELD_MARGIN_DB.
    """
    rng = np.random.default_rng(settings.seed + 1)
    nominal_eye = scene.eye.positions_mm[0]
    distribution = distribution_of(scene.eye)
    states = None if distribution.is_point else distribution.evaluation_states(
        TOLERANCE_EYE_STATES)
    rows, cols = layout.cells[:, 0], layout.cells[:, 1]
    target = torch.as_tensor(targets[0])

    built: list[tuple[StackShape, torch.Tensor]] = []

    def stack_of(renderer: Renderer) -> torch.Tensor:
        """The display's stack for a sample's renderer: one built already when it pre-filters
        the same way (BOX_RTOL), else its own."""
        for shape, stack in built:
            if shape.filters_like(renderer.shape, BOX_RTOL):
                return stack
        with torch.no_grad():
            built.append((renderer.shape, renderer.display_stack(shown[0])))
        return built[-1][1]

    def judge(moved: Scene, a: np.ndarray, offsets: np.ndarray | None, position: int) -> float:
        renderer = Renderer(moved, device=device, dtype=dtype, hole_offset_mm=offsets)
        a_t = torch.as_tensor(a, dtype=dtype, device=device)
        with torch.no_grad():
            if states is None:
                view = renderer.render_stack(a_t, stack_of(renderer), position)
                return psnr_db(float(gain_mse(view.cpu().double(), target)))
            views = renderer.render_states(a_t, stack_of(renderer), states)
        return float(np.mean(gain_psnr_db(views.cpu().double().numpy()[None], targets[:1])))

    if threshold_db is None:
        threshold_db = judge(scene, layout_fractions(layout, process.radius_bias_mm), None,
                             0) - YIELD_MARGIN_DB
    values = []
    for _ in range(settings.tolerance_samples):
        radii = layout.radii_mm + process.radius_bias_mm + rng.normal(
            0, process.radius_sigma_mm, layout.radii_mm.shape)
        sample = replace(layout, radii_mm=np.clip(radii, 1e-6, None))
        a = layout_fractions(sample)
        gap = max(1e-3, scene.plate.gap_mm + rng.normal(0, settings.gap_sigma_mm))
        eye = (nominal_eye[0] + rng.normal(0, settings.eye_sigma_mm),
               nominal_eye[1] + rng.normal(0, settings.eye_sigma_mm))
        if states is not None:
            eye = nominal_eye  # drawn all the same, so the other terms' samples stay as they were
        # The holes stay aimed at the nominal eye point: it comes first, the sample second.
        # The view is taken over the field the gap scales the picture to (see the docstring).
        moved = Scene(
            scene.display,
            Plate(scene.plate.cells, scene.plate.pitch_mm, gap, scene.plate.thickness_mm,
                  scene.plate.hole_axis),
            Eye(scene.eye.pupil_mm, scene.eye.eye_relief_mm,
                scaled_field_deg(scene.eye.fov_deg, scene.plate.gap_mm / gap),
                scene.eye.view_pixels, scene.eye.focus_mm, (nominal_eye, eye), (1.0, 1.0)),
        )
        # Position error and tilt move only the holes there are (closed cells stay closed).
        offsets = np.zeros((*scene.plate.cells[::-1], 2))
        offsets[rows, cols] = rng.normal(0, process.position_sigma_mm, (len(rows), 2))
        tilt = math.radians(rng.normal(0, settings.tilt_sigma_deg))
        tilt_axis = rng.uniform(0, math.pi)
        offsets[rows, cols] += _tilt_offsets_mm(moved, eye, tilt, tilt_axis)[rows, cols]
        values.append(judge(moved, a, offsets, 1))
    psnr = np.asarray(values)
    return {
        "samples": len(values),
        "psnr_db": [float(v) for v in psnr],
        "psnr_percentiles": {str(q): float(np.percentile(psnr, q)) for q in (5, 50, 95)},
        "threshold_db": float(threshold_db),
        "yield": float(np.mean(psnr >= threshold_db)),
        "radius_bias_mm": process.radius_bias_mm,
        "radius_sigma_mm": process.radius_sigma_mm,
        "position_sigma_mm": process.position_sigma_mm,
        "gap_sigma_mm": settings.gap_sigma_mm,
        "gap_scale_sigma_percent": 100 * settings.gap_sigma_mm / scene.plate.gap_mm,
        "tilt_sigma_deg": settings.tilt_sigma_deg,
        "eye_sigma_mm": settings.eye_sigma_mm if states is None else 0.0,
        "eye": ("the nominal eye, moved by eye_sigma_mm" if states is None else
                f"mean PSNR over {len(states)} states of the eye distribution"),
        "not_modelled": ["hole axis turned by plate tilt (wall vignetting)",
                         "plate thickness error", "plate warp"],
    }
