"""Which regular arrays get a fitted display before one is called the best: a climb over hole
sizes at the best pitches of the family.

The report judges the whole regular family with elemental images (cheap), then fits the
display of its likely winners, as the part's display is fitted. The elemental pass ranks the
fitted arrays poorly: a fitted display lifts large holes far more than small ones. On the
default photo part (near-eye preset, photomask, 4 made copies x 32 eye states, 2026-12-07)
the 3 mm arrays gained 0.5 dB with 0.57 mm holes (17.66 dB fitted) and 2.8 dB with 2.26 mm
holes (20.09 dB), which the elemental pass had ranked 7th; picking the smallest holes bright
enough at each pitch, as the report did until then, missed it and put the part 2.6 dB above
the regular array where it is 1.2 dB above it. On the digit the small holes win (2.5 mm,
0.40 mm). At one pitch, in all 24 arrays fitted on each of the two targets, the fitted p10
rises with the hole size to one peak and falls after it; the climb walks to that peak from the
size the elemental pass liked best, at the pitches it liked best.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aperture_fab.validation.regular import RegularFront

__all__ = ["RIVAL_PITCHES", "climb_rivals"]

#: Pitches whose hole sizes are climbed: the best by the elemental pass (each pitch's best
#: bright array). On the photo and the digit (above) the best fitted array's pitch was 1st and
#: 2nd by that rank.
RIVAL_PITCHES = 3
#: Relative slack of the light comparison (as `RegularFront.best_at`).
_SLACK = 1e-9


def climb_rivals(family: RegularFront, eye_level: float, judge: Callable[[int], float],
                 pitches: int = RIVAL_PITCHES) -> list[int]:
    """The arrays of `family` (judged with elemental images) to judge with a fitted display,
    in the order judged: at each of the `pitches` pitches with the best elemental p10 among
    the arrays at least `eye_level` bright at the eye, a climb over that pitch's bright hole
    sizes from the elemental best toward larger holes while the fitted p10 rises, else toward
    smaller ones. judge(i) is array i's fitted p10 (-inf when its fitted display leaves it
    darker than eye_level); it is called once per array returned."""
    if pitches < 1:
        raise ValueError(f"pitches = {pitches} is out of range; allowed: at least 1 (the "
                         "number of the family's lattice pitches to climb).")
    elemental = family.p10.mean(1)
    bright = family.eye_level >= eye_level * (1 - _SLACK)
    ladders = []
    for pitch in np.unique(family.pitch_mm[bright]):
        at = np.flatnonzero(bright & np.isclose(family.pitch_mm, pitch, rtol=_SLACK))
        ladders.append(at[np.argsort(family.diameter_mm[at])])
    ladders.sort(key=lambda ladder: -float(elemental[ladder].max()))
    judged: dict[int, float] = {}

    def fitted(index: int) -> float:
        if index not in judged:
            judged[index] = judge(index)
        return judged[index]

    for ladder in ladders[:pitches]:
        start = int(np.argmax(elemental[ladder]))
        fitted(int(ladder[start]))
        for step in (1, -1):
            k = start
            while 0 <= k + step < len(ladder) and \
                    fitted(int(ladder[k + step])) > fitted(int(ladder[k])):
                k += step
            if k != start:
                break
    return list(judged)
