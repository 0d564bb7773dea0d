"""Quantization of open-area fractions to makeable holes.

Webs, radii and the area bound are checked against independent calculations: brute-force
distances between every pair of holes at both plate faces, and the allowed sizes recomputed here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aperture_fab.fabrication.layout import HoleLayout, face_webs, layout_stats
from aperture_fab.fabrication.process import PROCESSES, Process, UnmakeableError, resolve_process
from aperture_fab.fabrication.quantize import quantize
from aperture_fab.optics.scene import Plate, hole_radius_mm, open_fraction_of

TOL = 1e-9


def make_plate(nx: int, ny: int, pitch: tuple[float, float], thickness: float,
               axis: str = "straight") -> Plate:
    return Plate(cells=(nx, ny), pitch_mm=pitch, gap_mm=10.0, thickness_mm=thickness,
                 hole_axis=axis)  # type: ignore[arg-type]


#: Holes compared at once against all others by the brute-force web check (bounds memory).
PAIR_CHUNK = 512


def pairwise_min_web(layout: HoleLayout) -> float:
    """Smallest distance between the walls of any two holes, at both faces (brute force)."""
    if layout.count < 2:
        return math.inf
    best = math.inf
    r = layout.radii_mm
    for z in (-layout.thickness_mm / 2, layout.thickness_mm / 2):
        c = layout.centres_mm + z * layout.axes
        for start in range(0, layout.count, PAIR_CHUNK):
            rows = np.arange(start, min(start + PAIR_CHUNK, layout.count))
            d = np.hypot(c[rows, None, 0] - c[None, :, 0], c[rows, None, 1] - c[None, :, 1])
            gap = d - r[rows, None] - r[None, :]
            gap[np.arange(len(rows)), rows] = np.inf
            best = min(best, float(gap.min()))
    return best


def edge_min_web(layout: HoleLayout) -> float:
    best = math.inf
    if layout.count == 0:
        return best
    for z in (-layout.thickness_mm / 2, layout.thickness_mm / 2):
        c = layout.centres_mm + z * layout.axes
        half_w, half_h = layout.outline_mm[0] / 2, layout.outline_mm[1] / 2
        best = min(best, float(np.min(half_w - np.abs(c[:, 0]) - layout.radii_mm)),
                   float(np.min(half_h - np.abs(c[:, 1]) - layout.radii_mm)))
    return best


def allowed_radii(process: Process, r_lo: float, r_hi: float) -> list[float] | None:
    """Sizes the process allows between r_lo and r_hi; None for any radius."""
    if process.hole_sizes_mm:
        return [d / 2 for d in process.hole_sizes_mm if r_lo - TOL <= d / 2 <= r_hi + TOL]
    if process.radius_step_mm > 0:
        s = process.radius_step_mm
        return [k * s for k in range(1, int(r_hi / s) + 2) if r_lo - TOL <= k * s <= r_hi + TOL]
    return None


@st.composite
def cases(draw: st.DrawFn) -> tuple[np.ndarray, Plate, Process]:
    min_hole = draw(st.floats(0.02, 0.3))
    min_web = draw(st.floats(0.01, 0.2))
    px = draw(st.floats(min_hole + min_web + 0.01, 1.0))
    py = draw(st.floats(px, px * 1.5))
    mode = draw(st.sampled_from(["continuous", "step", "sizes"]))
    step = 0.0
    sizes: tuple[float, ...] = ()
    r_hi = px / 2 - min_web / 2
    if mode == "step":
        step = draw(st.floats(0.002, 0.05))
    elif mode == "sizes":
        ds = draw(st.lists(st.floats(min_hole, 2 * r_hi), min_size=1, max_size=5, unique=True))
        sizes = tuple(sorted(set(ds)))
    process = Process("test", "hypothesis", min_hole_mm=min_hole, min_web_mm=min_web,
                      thickness_range_mm=(0.01, 5.0), radius_step_mm=step, hole_sizes_mm=sizes)
    nx, ny = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    a_max = math.pi * (min(px, py) / 2) ** 2 / (px * py)
    values = draw(st.lists(st.floats(0.0, a_max * 1.05), min_size=nx * ny, max_size=nx * ny))
    a = np.clip(np.array(values).reshape(ny, nx), 0.0, 1.0)
    thickness = draw(st.floats(0.02, 1.0))
    return a, make_plate(nx, ny, (px, py), thickness), process


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases())
def test_radii_webs_and_area_bound(case: tuple[np.ndarray, Plate, Process]) -> None:
    a, plate, process = case
    layout = quantize(a, plate, process, force=True)
    px, py = plate.pitch_mm
    r_lo = process.min_hole_mm / 2
    r_hi = min(px, py) / 2 - process.min_web_mm / 2
    # Every hole is makeable: within [min, max] and on the step / size list.
    assert np.all(layout.radii_mm >= r_lo - TOL)
    assert np.all(layout.radii_mm <= r_hi + TOL)
    if process.radius_step_mm > 0:
        k = layout.radii_mm / process.radius_step_mm
        np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    if process.hole_sizes_mm:
        assert all(np.isclose(2 * r, process.hole_sizes_mm).any() for r in layout.radii_mm)
    # Webs, between every pair of holes and to the edge.
    assert pairwise_min_web(layout) >= process.min_web_mm - TOL
    assert edge_min_web(layout) >= process.min_web_mm - TOL
    # Open area: only the last cell's snapping error leaves the plate, so the made area is
    # within E = half the largest gap between allowed areas (0 included) of the wanted area
    # (clipped to the largest allowed hole).
    radii = allowed_radii(process, r_lo, r_hi)
    cell = px * py
    if radii is None:
        largest, half_gap = math.pi * r_hi**2, math.pi * r_lo**2 / 2
    elif radii:
        areas = [0.0] + [math.pi * r * r for r in radii]
        largest, half_gap = areas[-1], max(np.diff(areas)) / 2
    else:
        largest, half_gap = 0.0, 0.0
    wanted = float(np.minimum(a * cell, largest).sum())
    made = float(np.sum(math.pi * layout.radii_mm**2))
    assert abs(made - wanted) <= half_gap * (1 + 1e-9) + 1e-12


@settings(max_examples=60, deadline=None)
@given(
    nx=st.integers(1, 9), ny=st.integers(1, 9),
    thickness=st.floats(0.02, 0.5),
    eye=st.floats(2.0, 30.0),
    target=st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0)),
    fill=st.floats(0.0, 1.0),
)
def test_chief_ray_holes_point_at_the_eye_and_keep_webs(
    nx: int, ny: int, thickness: float, eye: float, target: tuple[float, float], fill: float
) -> None:
    foil = resolve_process("photomask", {"thickness_range_mm": (0.005, 1.0)})
    plate = make_plate(nx, ny, (0.2, 0.2), thickness, "chief_ray")
    a = np.full((ny, nx), fill * plate.max_open_fraction)
    layout = quantize(a, plate, foil, tilt_target_mm=target, eye_distance_mm=eye, force=True)
    assert layout.converge_mm == (target[0], target[1], eye)
    if layout.count:
        reach = layout.centres_mm + eye * layout.axes  # the axis passes through the eye
        np.testing.assert_allclose(reach, np.broadcast_to(target, reach.shape), atol=1e-9)
        # At each face the hole is centred in its cell of the grid scaled about the eye by
        # 1 - z / D, and keeps half a web inside it.
        xs, ys = plate.cell_centres_mm()
        mid = np.stack([xs[layout.cells[:, 1]], ys[layout.cells[:, 0]]], axis=1)
        for z in (-thickness / 2, thickness / 2):
            scale = 1 - z / eye
            c = layout.centres_mm + z * layout.axes
            cell_c = np.asarray(target) + (mid - np.asarray(target)) * scale
            np.testing.assert_allclose(c, cell_c, atol=1e-12)
            slack = 0.1 * scale - foil.min_web_mm / 2 - layout.radii_mm
            assert np.all(slack >= -TOL)
    assert pairwise_min_web(layout) >= foil.min_web_mm - TOL
    assert edge_min_web(layout) >= foil.min_web_mm - TOL


def test_near_eye_chief_ray_plate_keeps_every_hole() -> None:
    """80 x 80 cells of 0.25 mm, 0.3 mm thick, eye 10.15 mm away: a hole 10 mm off axis moves
    0.3 mm between the faces, more than a cell, yet every hole fits its scaled cell."""
    n, pitch, t, eye = 80, 0.25, 0.3, 10.15
    plate = make_plate(n, n, (pitch, pitch), t, "chief_ray")
    resin = PROCESSES["resin"]
    a = np.full((n, n), 0.2)
    layout = quantize(a, plate, resin, tilt_target_mm=(0.0, 0.0), eye_distance_mm=eye)
    assert layout.count == n * n
    assert not layout.violations
    corner = np.abs(layout.axes).max() * t  # shift between the faces at the plate's corner
    assert corner > pitch
    web = 2 * 0.022  # resin: 2 pixels of 22 um
    assert pairwise_min_web(layout) >= web - TOL
    assert edge_min_web(layout) >= web - TOL
    # Largest hole the top face (pitch x (1 - t / 2D)) allows, on the half-pixel radius step.
    r_top = pitch * (1 - t / (2 * eye)) / 2 - web / 2
    assert np.all(layout.radii_mm <= r_top + TOL)
    # Open area kept within half the largest gap between neighbouring allowed areas.
    step = 0.011
    areas = math.pi * (step * np.arange(0, int(r_top / step + 1e-9) + 1)) ** 2
    made = float(np.sum(math.pi * layout.radii_mm**2))
    assert abs(made - a.sum() * pitch**2) <= np.diff(areas).max() / 2


def test_chief_ray_holes_too_big_for_the_top_face_are_cut_as_tilt() -> None:
    """Continuous sizes: the top face's cell (pitch x (1 - t / 2D)) sets the largest hole."""
    foil = resolve_process("photomask", {"thickness_range_mm": (0.005, 1.0)})
    t, eye, pitch = 0.5, 2.5, 0.2
    plate = make_plate(3, 3, (pitch, pitch), t, "chief_ray")
    r_top = pitch * (1 - t / (2 * eye)) / 2 - foil.min_web_mm / 2
    r_straight = pitch / 2 - foil.min_web_mm / 2
    r_want = (r_top + r_straight) / 2
    a = np.full((3, 3), math.pi * r_want**2 / pitch**2)
    layout = quantize(a, plate, foil, tilt_target_mm=(0.1, 0.0), eye_distance_mm=eye)
    np.testing.assert_allclose(layout.radii_mm, r_top)
    assert {v.rule for v in layout.violations} == {"tilt"}
    assert {v.cell for v in layout.violations} == {(i, j) for i in range(3) for j in range(3)}
    assert all(v.limit_mm == pytest.approx(r_top) for v in layout.violations)


@pytest.mark.parametrize("eye", [0.3, 0.2, -1.0, math.inf])
def test_chief_ray_eye_must_be_beyond_the_plate(eye: float) -> None:
    plate = make_plate(4, 4, (0.25, 0.25), 0.3, "chief_ray")
    with pytest.raises(ValueError, match="eye_distance_mm"):
        quantize(np.full((4, 4), 0.2), plate, PROCESSES["resin"], eye_distance_mm=eye)


def test_chief_ray_margin_covers_the_scaled_grid() -> None:
    """The bottom face's grid (pitch x (1 + t / 2D)) reaches past the mid-plane grid by
    t / 2D x (half the grid + |eye offset|): the margin must cover that plus half a web."""
    n, pitch, t, eye, ex = 40, 0.25, 0.3, 1.0, 2.0
    plate = make_plate(n, n, (pitch, pitch), t, "chief_ray")
    resin = PROCESSES["resin"]
    overhang = t / (2 * eye) * (n * pitch / 2 + ex)  # 0.15 x 7 = 1.05 mm
    a = np.full((n, n), 0.1)
    layout = quantize(a, plate, resin, tilt_target_mm=(ex, 0.0), eye_distance_mm=eye)
    margin = (layout.outline_mm[0] - n * pitch) / 2
    assert margin == pytest.approx(overhang + 2 * 0.044)
    assert edge_min_web(layout) >= 0.044 - TOL
    assert pairwise_min_web(layout) >= 0.044 - TOL
    least = overhang + 0.022
    layout = quantize(a, plate, resin, outline_margin_mm=least + 1e-6,
                      tilt_target_mm=(ex, 0.0), eye_distance_mm=eye)
    assert edge_min_web(layout) >= 0.044 - TOL
    with pytest.raises(ValueError, match="outline_margin_mm"):
        quantize(a, plate, resin, outline_margin_mm=least - 1e-3, tilt_target_mm=(ex, 0.0),
                 eye_distance_mm=eye)


def test_straight_holes_do_not_converge() -> None:
    layout = quantize(np.full((2, 2), 0.2), make_plate(2, 2, (0.25, 0.25), 0.05),
                      PROCESSES["etched-foil"])
    assert layout.converge_mm is None


def test_straight_holes_have_zero_axes_and_cell_centres() -> None:
    plate = make_plate(5, 3, (0.25, 0.3), 0.05)
    a = np.full((3, 5), 0.3)
    layout = quantize(a, plate, PROCESSES["etched-foil"])
    assert layout.count == 15
    np.testing.assert_array_equal(layout.axes, 0.0)
    for (i, j), (x, y) in zip(layout.cells, layout.centres_mm, strict=True):
        assert x == pytest.approx((j - 2) * 0.25)
        assert y == pytest.approx((1 - i) * 0.3)
    np.testing.assert_allclose(math.pi * layout.radii_mm**2 / (0.25 * 0.3), 0.3)


@pytest.mark.parametrize("fraction", [0.5, 0.25, 0.1])
def test_uniform_below_min_hole_gives_regular_sparse_pattern(fraction: float) -> None:
    n = 48
    plate = make_plate(n, n, (0.1, 0.1), 0.1)
    mask = PROCESSES["photomask"]
    a_min = math.pi * (mask.min_hole_mm / 2) ** 2 / 0.01
    layout = quantize(np.full((n, n), fraction * a_min), plate, mask)
    # Opened holes are (about) the smallest one, as many as the area asks for.
    r_min = mask.min_hole_mm / 2
    assert np.all((layout.radii_mm >= r_min - TOL) & (layout.radii_mm <= 1.02 * r_min))
    assert abs(layout.count - fraction * n * n) <= 1
    # Regular: every 8 x 8 window holds the expected count to within half of it.
    occupied = np.zeros((n, n), dtype=bool)
    occupied[layout.cells[:, 0], layout.cells[:, 1]] = True
    w = 8
    expected = fraction * w * w
    counts = [occupied[i:i + w, j:j + w].sum() for i in range(n - w + 1) for j in range(n - w + 1)]
    assert max(abs(c - expected) for c in counts) <= expected / 2
    (v,) = [v for v in layout.violations if v.rule == "min_hole"]
    assert v.cell is None
    assert v.resolution.startswith(f"{n * n} cells below 0.025 mm: error-diffused: "
                                   f"{layout.count} opened")
    assert f"{n * n - layout.count} closed" in v.resolution


def test_snapping_to_discrete_sizes_is_nearest_in_area() -> None:
    drills = Process("drills", "test", min_hole_mm=0.1, min_web_mm=0.05,
                     thickness_range_mm=(0.1, 1.0), hole_sizes_mm=(0.1, 0.2, 0.3))
    plate = make_plate(1, 1, (0.5, 0.5), 0.2)
    for d_want, d_made in [(0.13, 0.1), (0.165, 0.2), (0.24, 0.2), (0.26, 0.3), (0.4, 0.3)]:
        a = np.array([[math.pi * (d_want / 2) ** 2 / 0.25]])
        layout = quantize(a, plate, drills, force=True)
        assert 2 * layout.radii_mm[0] == pytest.approx(d_made)
        assert any(v.rule == "max_size" for v in layout.violations) == (d_want > 0.3)


def test_fdm_on_quarter_millimetre_cells_is_unmakeable() -> None:
    plate = make_plate(10, 10, (0.25, 0.25), 0.5)
    a = np.full((10, 10), 0.2)
    with pytest.raises(UnmakeableError) as info:
        quantize(a, plate, PROCESSES["fdm"])
    message = str(info.value)
    assert "fdm" in message and "1.8 mm" in message and "7.2x" in message
    assert "processes that can make it at 0.5 mm: resin" in message
    layout = quantize(a, plate, PROCESSES["fdm"], force=True)
    assert any(v.rule == "process" for v in layout.violations)
    assert pairwise_min_web(layout) >= 0  # forced holes still never overlap


def test_resin_holes_on_the_near_eye_pitch_are_on_the_pixel_grid() -> None:
    plate = make_plate(12, 12, (0.25, 0.25), 0.3)  # the near-eye pitch and thickness
    a = np.random.default_rng(0).uniform(0.0, 0.5, (12, 12))
    resin = PROCESSES["resin"]
    layout = quantize(a, plate, resin)
    # Independent numbers: 22 um pixels; radius in half-pixel steps, hole >= 4 pixels,
    # web >= 2 pixels.
    step, r_lo, web = 0.011, 0.044, 0.044
    k = layout.radii_mm / step
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    assert np.all(layout.radii_mm >= r_lo - TOL)
    assert np.all(layout.radii_mm <= 0.125 - web / 2 + TOL)
    assert pairwise_min_web(layout) >= web - TOL
    assert layout.count > 0.8 * a.size  # most cells ask for more than the smallest hole
    assert not [v for v in layout.violations if v.rule in ("process", "open_area")]


def test_losing_most_of_the_open_area_is_unmakeable_unless_forced() -> None:
    plate = make_plate(6, 6, (0.25, 0.25), 0.1)
    a = np.full((6, 6), 0.7)  # the foil web (0.1 mm) allows 0.28 at most
    with pytest.raises(UnmakeableError) as info:
        quantize(a, plate, PROCESSES["etched-foil"])
    message = str(info.value)
    assert "60%" in message and "photomask" in message and "scaling the plate" in message
    layout = quantize(a, plate, PROCESSES["etched-foil"], force=True)
    rules = [v.rule for v in layout.violations]
    assert "open_area" in rules and "min_web" in rules
    assert layout.count == 36


def test_a_design_below_one_smallest_hole_says_so() -> None:
    """One cell asks for a sliver of a hole: nothing can be made, and the web is not why."""
    plate = make_plate(6, 6, (0.15, 0.15), 0.005)
    a = np.zeros((6, 6))
    a[5, 5] = 0.002
    with pytest.raises(UnmakeableError) as info:
        quantize(a, plate, PROCESSES["photomask"])
    message = str(info.value)
    assert "lose 100%" in message and "smaller than the smallest photomask makes" in message
    assert "web" not in message and "scaling the plate" not in message


def test_few_clipped_cells_get_one_violation_each() -> None:
    plate = make_plate(4, 4, (0.25, 0.25), 0.05)
    a = np.full((4, 4), 0.1)
    a[1, 2] = a[3, 0] = 0.6
    layout = quantize(a, plate, PROCESSES["etched-foil"])
    clipped = [v for v in layout.violations if v.rule == "min_web"]
    assert {v.cell for v in clipped} == {(1, 2), (3, 0)}
    assert all(v.limit_mm == pytest.approx(0.125 - 0.038) for v in clipped)


def test_many_clipped_cells_are_aggregated_but_countable() -> None:
    plate = make_plate(10, 10, (0.25, 0.25), 0.05)
    layout = quantize(np.full((10, 10), 0.45), plate, PROCESSES["etched-foil"])
    (v,) = [v for v in layout.violations if v.rule == "min_web"]
    assert v.cell is None and v.resolution.startswith("100 cells")


@pytest.mark.parametrize("thickness", [0.01, 0.8])
def test_thickness_outside_the_range_errors(thickness: float) -> None:
    plate = make_plate(4, 4, (1.0, 1.0), thickness)
    with pytest.raises(ValueError, match=r"0\.025 to 0\.5 mm"):
        quantize(np.full((4, 4), 0.2), plate, PROCESSES["etched-foil"])
    layout = quantize(np.full((4, 4), 0.2), plate, PROCESSES["etched-foil"], force=True)
    assert layout.violations[0].rule == "process"


def test_unknown_process_errors_with_suggestion() -> None:
    with pytest.raises(ValueError, match="Did you mean 'resin'"):
        resolve_process("resn", None)


@pytest.mark.parametrize(
    ("a", "match"),
    [(np.zeros((3, 4)), "shape"), (np.full((4, 4), np.nan), "NaN"),
     (np.full((4, 4), 1.5), "0 to 1"), (np.full((4, 4), -0.1), "0 to 1")],
)
def test_bad_fractions(a: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        quantize(a, make_plate(4, 4, (0.25, 0.25), 0.05), PROCESSES["etched-foil"])


def test_chief_ray_needs_the_eye_distance() -> None:
    plate = make_plate(4, 4, (0.25, 0.25), 0.05, "chief_ray")
    with pytest.raises(ValueError, match="eye_distance_mm"):
        quantize(np.full((4, 4), 0.2), plate, PROCESSES["etched-foil"])


def test_outline_margin_default_and_explicit() -> None:
    foil = PROCESSES["etched-foil"]  # web 0.3 mm at 0.3 mm thickness -> hole 0.33: pitch 0.63
    plate = make_plate(4, 3, (0.7, 0.7), 0.3)
    layout = quantize(np.full((3, 4), 0.2), plate, foil)
    assert layout.outline_mm == pytest.approx((4 * 0.7 + 2.0, 3 * 0.7 + 2.0))
    layout = quantize(np.full((3, 4), 0.2), plate, foil, outline_margin_mm=0.5)
    assert layout.outline_mm == pytest.approx((4 * 0.7 + 1.0, 3 * 0.7 + 1.0))
    thick = make_plate(4, 3, (1.5, 1.5), 0.6)
    layout = quantize(np.full((3, 4), 0.2), thick, PROCESSES["laser"])
    assert layout.outline_mm == pytest.approx((4 * 1.5 + 2.4, 3 * 1.5 + 2.4))  # 2 x 0.6 web
    with pytest.raises(ValueError, match="outline_margin_mm"):
        quantize(np.full((3, 4), 0.2), plate, foil, outline_margin_mm=0.1)


def test_layout_stats_against_hand_numbers() -> None:
    layout = HoleLayout(
        cells=np.array([[0, 0], [0, 1], [1, 1]]),
        centres_mm=np.array([[-0.5, 0.5], [0.5, 0.5], [0.5, -0.5]]),
        radii_mm=np.array([0.2, 0.3, 0.1]),
        axes=np.zeros((3, 2)),
        pitch_mm=(1.0, 1.0),
        grid=(2, 2),
        outline_mm=(4.0, 4.0),
        thickness_mm=0.5,
    )
    stats = layout_stats(layout)
    assert stats["hole_count"] == 3
    assert stats["smallest_hole_diameter_mm"] == pytest.approx(0.2)
    assert stats["largest_hole_diameter_mm"] == pytest.approx(0.6)
    assert stats["smallest_web_mm"] == pytest.approx(0.5)  # 0.5 and 0.3 -> 1 - 0.3 - 0.1 = 0.6
    assert stats["smallest_edge_web_mm"] == pytest.approx(2 - 0.5 - 0.3)
    assert stats["open_area_fraction"] == pytest.approx(math.pi * (0.04 + 0.09 + 0.01) / 4)
    assert stats["smallest_web_mm"] == pytest.approx(pairwise_min_web(layout))


def test_layout_stats_matches_brute_force_on_a_quantized_tilted_plate() -> None:
    plate = make_plate(7, 5, (0.2, 0.2), 0.1, "chief_ray")
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 0.5, (5, 7))
    layout = quantize(a, plate, PROCESSES["photomask"], tilt_target_mm=(0.3, -0.2),
                      eye_distance_mm=5.0, force=True)
    stats = layout_stats(layout)
    assert stats["smallest_web_mm"] == pytest.approx(pairwise_min_web(layout))
    assert stats["smallest_edge_web_mm"] == pytest.approx(edge_min_web(layout))
    assert stats["hole_count"] == layout.count


def test_face_webs_forward_pairs_meet_every_neighbour_once() -> None:
    # The statistics (forward pairs) and the rule check (all eight neighbours) share face_webs.
    plate = make_plate(7, 5, (0.2, 0.2), 0.1, "chief_ray")
    a = np.random.default_rng(4).uniform(0, 0.5, (5, 7))
    layout = quantize(a, plate, PROCESSES["photomask"], tilt_target_mm=(0.3, -0.2),
                      eye_distance_mm=5.0, force=True)
    webs = face_webs(layout, layout.thickness_mm / 2)
    neighbour = np.minimum(webs.forward_mm, webs.backward_mm)
    assert float(webs.forward_mm.min()) == pytest.approx(float(neighbour.min()))
    assert np.array_equal(webs.thinnest_mm, np.minimum(neighbour, webs.edge_mm))


def test_empty_layout_stats() -> None:
    layout = quantize(np.zeros((3, 3)), make_plate(3, 3, (0.25, 0.25), 0.05),
                      PROCESSES["etched-foil"])
    stats = layout_stats(layout)
    assert stats["hole_count"] == 0 and stats["smallest_web_mm"] is None
    assert stats["open_area_fraction"] == 0.0


@settings(max_examples=50, deadline=None)
@given(fraction=st.floats(0, 1), px=st.floats(0.05, 5), py=st.floats(0.05, 5))
def test_radius_and_open_fraction_invert_each_other(fraction: float, px: float, py: float
                                                    ) -> None:
    # One home for a = pi r^2 / (px py): checked against the hole's area directly.
    radius = float(hole_radius_mm(fraction, (px, py)))
    assert math.pi * radius * radius == pytest.approx(fraction * px * py, rel=1e-12, abs=1e-300)
    assert float(open_fraction_of(radius, (px, py))) == pytest.approx(fraction, rel=1e-12,
                                                                      abs=1e-15)
    grid = np.full((2, 3), fraction)
    np.testing.assert_array_equal(hole_radius_mm(grid, (px, py)), radius)  # arrays alike
