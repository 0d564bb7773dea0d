"""A measurement as files' contents: the made holes as a hole table (HoleLayout), measured.json's
dict, and a short HTML page (the scan with the fitted holes over it, the deviation map)."""

from __future__ import annotations

import base64
import html
import io
import math
from dataclasses import replace
from typing import Any

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.measure.measure import HOLE_STATES, Measurement

__all__ = ["measured_json", "measured_layout", "measured_page", "notes"]

#: Longest side of the scan thumbnail on the page, px.
THUMBNAIL_PX = 900
#: Micrometres per millimetre.
UM = 1000.0
#: How many times the centre deviations are drawn larger than the plate on the map.
ARROW_GAIN = 20.0
#: The scale found may differ from the one given by this much before the page warns.
SCALE_NOTE = 0.01


def measured_layout(m: Measurement) -> HoleLayout:
    """The holes as made, in the design's cells and frame: blocked holes left out (closed), the
    measured centre and radius of every other (the design's hole axes kept)."""
    d = m.design
    keep = np.isfinite(m.radii_mm) & (m.radii_mm > 0)
    return replace(d, cells=d.cells[keep], centres_mm=m.centres_mm[keep],
                   radii_mm=m.radii_mm[keep], axes=d.axes[keep], violations=(),
                   converge_mm=None)


def notes(m: Measurement) -> list[str]:
    """What the user should know, one sentence each (the mirror, a scale off, defects)."""
    out = []
    reg = m.registration
    if reg.transform.mirror:
        out.append("The scan shows the plate from its back (mirrored): it was measured "
                   "mirrored. Next time put the plate's eye side (top face) on the glass.")
    if reg.tied:
        out.append("The hole sizes could not tell the plate's turn or side apart (a symmetric "
                   "design): check the alignment chamfer's corner in the page's scan.")
    if abs(reg.scale_ratio - 1) > SCALE_NOTE:
        out.append(f"The plate measures {reg.scale_ratio:.4f} times the scale given: the "
                   "scanner's dpi is off or the plate shrank; sizes use the scale given.")
    for state in HOLE_STATES[1:]:
        n = m.count(state)
        if n:
            out.append(f"{n} hole(s) {state.replace('_', ' ')}.")
    if len(m.extra_index):
        out.append(f"{len(m.extra_index)} opening(s) where the design has none (dust, pin "
                   "holes in the solid).")
    if m.solid_at_floor:
        out.append(f"The solid is darker than the scan can show: its optical density is at "
                   f"least {m.optical_density:.2f}.")
    return out


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def measured_json(m: Measurement, scan: str, design: str) -> dict[str, Any]:
    """measured.json: the registration, the process on this plate, defects and every hole."""
    reg, t = m.registration, m.registration.transform
    deviation = m.radii_mm - m.design.radii_mm
    holes = [{"row": int(r), "col": int(c), "state": str(s),
              "design_x_mm": float(dx), "design_y_mm": float(dy),
              "design_radius_mm": float(dr),
              "x_mm": _finite(x), "y_mm": _finite(y), "radius_mm": _finite(r_mm),
              "radius_deviation_mm": _finite(dev),
              "centre_deviation_mm": _finite(math.hypot(x - dx, y - dy))}
             for (r, c), s, (dx, dy), dr, (x, y), r_mm, dev in zip(
                 m.design.cells.tolist(), m.state, m.design.centres_mm.tolist(),
                 m.design.radii_mm.tolist(), m.centres_mm.tolist(), m.radii_mm.tolist(),
                 deviation.tolist(), strict=True)]
    return {
        "scan": scan, "design": design, "mm_per_px": m.mm_per_px,
        "registration": {
            "mirror": t.mirror, "rotation_deg": math.degrees(t.rotation_rad) % 360,
            "scale_ratio": reg.scale_ratio, "px_per_mm": t.px_per_mm,
            "design_origin_px": list(t.centre_px), "matched_holes": int(reg.scan_index.size),
            "centre_residual_mm": reg.residual_mm,
            "radius_mismatch_mm": reg.radius_mismatch_mm, "tied": reg.tied,
        },
        "process": {"radius_bias_mm": _finite(m.bias_mm), "radius_sigma_mm": _finite(m.sigma_mm),
                    "position_sigma_mm": _finite(m.position_sigma_mm),
                    "holes_used": m.count("ok")},
        "solid": {"transmission": m.solid_transmission, "optical_density": m.optical_density,
                  "at_noise_floor": m.solid_at_floor},
        "scan_quality": {"blur_px": m.light.blur_px,
                         "open_level": float(np.median(m.fits.open_level))},
        "defects": {state: int(m.count(state)) for state in HOLE_STATES[1:]}
        | {"extra_openings": [{"x_mm": float(x), "y_mm": float(y), "radius_mm": float(r)}
                              for (x, y), r in zip(m.extra_centres_mm.tolist(),
                                                   m.extra_radii_mm.tolist(), strict=True)]},
        "notes": notes(m),
        "holes": holes,
    }


def _png(figure: Any) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _figures(m: Measurement, image: np.ndarray) -> tuple[str, str]:
    """(scan with the fitted holes over it, deviation map), base64 PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    step = max(1, math.ceil(max(image.shape) / THUMBNAIL_PX))
    fig = Figure(figsize=(7, 7 * image.shape[0] / image.shape[1]))
    ax = fig.add_subplot()
    ax.imshow(image[::step, ::step], cmap="gray", vmin=0, extent=(-0.5, image.shape[1] - 0.5,
                                                                  image.shape[0] - 0.5, -0.5))
    theta = np.linspace(0, 2 * math.pi, 48)
    for (u, v), r in zip(m.fits.centres_px, m.fits.radii_px, strict=True):
        ax.plot(u + r * np.cos(theta), v + r * np.sin(theta), color="tab:green", lw=0.6)
    blocked = m.registration.transform.to_image(m.design.centres_mm[m.state == "blocked"])
    ax.plot(blocked[:, 0], blocked[:, 1], "rx", ms=8, label="blocked")
    extra = m.fits.centres_px[m.extra_index]
    ax.plot(extra[:, 0], extra[:, 1], "mo", mfc="none", ms=10, label="extra opening")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_axis_off()
    scan_png = _png(fig)

    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot()
    ok = np.isfinite(m.radii_mm)
    dev = (m.radii_mm - m.design.radii_mm) * UM
    limit = max(float(np.nanmax(np.abs(dev))) if ok.any() else 1.0, 1e-3)
    xs, ys = m.design.centres_mm[ok, 0], m.design.centres_mm[ok, 1]
    dots = ax.scatter(xs, ys, c=dev[ok], cmap="coolwarm", vmin=-limit,
                      vmax=limit, s=30)
    move = (m.centres_mm[ok] - m.design.centres_mm[ok]) * ARROW_GAIN
    ax.quiver(xs, ys, move[:, 0], move[:, 1], angles="xy", scale_units="xy", scale=1,
              width=0.003)
    ax.plot(*m.design.centres_mm[m.state == "blocked"].T, "kx", ms=8)
    fig.colorbar(dots, ax=ax, label="radius made - drawn (um)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"hole radius deviation; arrows: centre deviation x {ARROW_GAIN:g}; x: blocked")
    return scan_png, _png(fig)


def measured_page(m: Measurement, image: np.ndarray, summary: dict[str, Any]) -> str:
    """The HTML page: the figures, the numbers and the notes (summary is measured_json's)."""
    scan_png, map_png = _figures(m, image)
    reg, proc = summary["registration"], summary["process"]

    def um(x: float | None) -> str:
        return "n/a" if x is None else f"{x * UM:.2f} um"

    rows = [("registration", f"rotation {reg['rotation_deg']:.3f} deg, "
             f"{'mirrored' if reg['mirror'] else 'not mirrored'}, scale x "
             f"{reg['scale_ratio']:.5f}, {reg['matched_holes']} holes matched, centre residual "
             f"{um(reg['centre_residual_mm'])} RMS"),
            ("process on this plate", f"radius bias {um(proc['radius_bias_mm'])}, sigma "
             f"{um(proc['radius_sigma_mm'])}, position sigma {um(proc['position_sigma_mm'])} "
             f"(from {proc['holes_used']} holes)"),
            ("solid", f"transmission {summary['solid']['transmission']:.3g}, OD "
             f"{'>= ' if m.solid_at_floor else ''}{m.optical_density:.2f}")]
    table = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                    for k, v in rows)
    items = "".join(f"<li>{html.escape(n)}</li>" for n in summary["notes"]) or "<li>none</li>"
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>measured plate</title>"
            "<style>body{font-family:sans-serif;max-width:960px;margin:2em auto}"
            "th{text-align:left;padding-right:1em}img{max-width:100%}</style></head><body>"
            f"<h1>The plate as made</h1><p>scan {html.escape(summary['scan'])}, design "
            f"{html.escape(summary['design'])}</p><table>{table}</table><h2>Notes</h2>"
            f"<ul>{items}</ul><h2>Scan and fitted holes</h2>"
            f"<img alt='scan with fitted holes' src='data:image/png;base64,{scan_png}'>"
            "<h2>Deviation map</h2>"
            f"<img alt='deviation map' src='data:image/png;base64,{map_png}'></body></html>")
