"""The variants a report judges, in one registry: adding a baseline or a view of the part is one
entry here (and the code that renders it, in `validate`).

Each variant is a plate (or none) with a display content, rendered for every target and judged
the same way. Their order in `VARIANTS` is report.json's; `PART_FIRST` is the order of tables and
figures, the part first.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

__all__ = ["EYE_BASELINES", "EYE_VARIANTS", "PART_FIRST", "SHOWN_VARIANTS", "VARIANTS",
           "VariantInfo",
           "eye_first"]

#: What the display shows with a variant, which is also what its light efficiency is measured
#: against: the content fitted to the part, the content the design was optimized with, or the
#: target itself.
DisplayOf = Literal["shown", "designed", "target"]


@dataclass(frozen=True)
class VariantInfo:
    """One judged variant.

    name: its key in report.json and views.npz. label: what it is, for tables and verdicts.
    short: its name in the eye-distribution table, figures and the terminal (None: not judged
    over the eye distribution). phrase: how a verdict names it when the part must beat it (None:
    not such a baseline). display: what the display shows with it. figure: drawn beside the
    target in the report's main figure. panel: its title on a view panel when neither short
    nor label is short enough.
    """

    name: str
    label: str
    display: DisplayOf
    short: str | None = None
    phrase: str | None = None
    figure: bool = True
    panel: str | None = None

    @property
    def title(self) -> str:
        """A view panel's title: panel, else short, else label."""
        return self.panel or self.short or self.label


VARIANTS: dict[str, VariantInfo] = {v.name: v for v in (
    VariantInfo("open", "open display (no plate)", "target", "open display", "the open display"),
    VariantInfo("regular_pinholes", "regular pinhole array", "target", "regular pinholes",
            "the regular pinhole array"),
    VariantInfo("random", "random mask (the dissertation's start)", "target",
                panel="random mask"),
    VariantInfo("optimized", "optimized design", "designed", "optimized"),
    VariantInfo("quantized", "after quantization", "shown", figure=False),
    VariantInfo("as_built", "as built (real holes, real thickness)", "shown", "as built"),
    VariantInfo("as_built_mesh", "as built, traced through the written mesh", "shown",
                panel="traced through the mesh"),
    VariantInfo("as_built_diffraction", "as built, with diffraction", "shown",
                panel="with diffraction"),
)}
#: Tables and figures list the part first, then the design, then the baselines.
PART_FIRST: tuple[str, ...] = ("as_built", "optimized", "open", "regular_pinholes", "random",
                               "as_built_mesh", "as_built_diffraction", "quantized")
#: Variants judged over the eye distribution, in table order.
EYE_VARIANTS: tuple[str, ...] = tuple(v for v in PART_FIRST if VARIANTS[v].short is not None)
#: Variants beside the target in the main figure, in order.
SHOWN_VARIANTS: tuple[str, ...] = tuple(v for v in PART_FIRST if VARIANTS[v].figure)
#: The baselines the part must beat over the eye distribution: (name, phrase).
EYE_BASELINES: tuple[tuple[str, str], ...] = tuple(
    (v.name, v.phrase) for v in VARIANTS.values() if v.phrase is not None)


def eye_first(names: Iterable[str]) -> list[str]:
    """Variant names with those of EYE_VARIANTS first, in that order, then the rest as given."""
    names = list(names)
    return [v for v in EYE_VARIANTS if v in names] + [v for v in names if v not in EYE_VARIANTS]
