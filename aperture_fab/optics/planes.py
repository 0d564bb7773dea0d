"""The planes of the light path and the affine maps between them: pupil, the plate's faces and
the display, for an eye focused at a distance 1 / q (aperture_fab.optics.model's docstring)."""

from __future__ import annotations

from dataclasses import dataclass

from aperture_fab.optics.scene import Scene

__all__ = ["EPS", "Optics"]

#: A floor for lengths and areas (mm, mm2) that must not reach zero: a hole's radius is
#: sqrt(open area / pi + EPS), so a closed cell has a radius of about 1e-6 mm and no area.
EPS = 1e-12


@dataclass(frozen=True)
class Optics:
    """Distances and the affine maps between planes, all in mm (see module docstring)."""

    s_bottom: float  # pupil to the plate's bottom face
    s_top: float  # pupil to the plate's top face
    s_display: float  # pupil to the display
    beta_bottom: float  # 1 - s q at each plane
    beta_top: float
    beta_display: float

    @classmethod
    def of(cls, scene: Scene, q: float | None = None) -> Optics:
        """The scene's optics, for its eye's focus or for q = 1 / focus distance (1/mm)."""
        if q is None:
            q = 0.0 if scene.eye.focus_mm is None else 1.0 / scene.eye.focus_mm
        s_b, s_t, s_d = scene.plate_distance_mm, scene.eye.eye_relief_mm, scene.display_distance_mm
        return cls(s_b, s_t, s_d, 1 - s_b * q, 1 - s_t * q, 1 - s_d * q)

    @property
    def top_to_bottom(self) -> float:
        """Scale from a top-face offset to the matching bottom-face offset (same pupil point)."""
        return self.beta_bottom / self.beta_top

    @property
    def window_scale(self) -> float:
        """Scale from bottom-face offsets to display offsets for rays of one view direction."""
        return self.beta_display / self.beta_bottom

    @property
    def window_rate(self) -> float:
        """How fast (mm per unit tan) the display window moves as the view direction changes."""
        mu = self.window_scale
        lens_rate = 0.5 * (self.s_bottom - self.top_to_bottom * self.s_top)
        return abs(self.s_display - mu * self.s_bottom + mu * lens_rate)
