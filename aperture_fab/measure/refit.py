"""Re-fitting the display content to a measured plate (issue 17, item 3), and how much of the
tolerance loss that recovers.

Views, each judged by PSNR after gain against the targets over the config's eye positions (the
mean squared error over targets and positions, as one PSNR):

- nominal: the design's plate as the design meant it to be made (its drawn holes plus the
  process's bias), with the design's display content: what the design promised;
- made: the plate as measured, with the design's display content: what the made plate shows;
- refit: the plate as measured, with the display content re-fitted to it (the design's own
  loss, from the design's content; the plate is fixed, the display is software);
- nominal refit: the nominal plate with its content re-fitted the same way (as many
  iterations, from the same start).

The tolerance loss is nominal - made. What is left of it after the refit is nominal refit -
refit: the same extra iterations on both plates, so that a design whose content was not yet
converged does not pass its own further optimization off as recovery. The refit recovers
1 - (nominal refit - refit) / (nominal - made) of the loss (for a converged design, nominal
refit = nominal and this is (refit - made) / (nominal - made)). All views use the exact model
of the holes as open fractions (aperture_fab.optics.model), the model `validate` judges its
as_built variant with; the re-fit optimizes that same model, its display stack sampled as
finely as the judgement's (`STACK_OVERSAMPLE`, where the design optimizes at one sample per
pixel): fitted in the coarser model, the content was judged in one it had not optimized (on
the test design's nominal plate the refit lost 0.11 dB where the same fit in the judgement's
model gains 0.23 dB). The fit starts from the design's converged content, so it steps at a
share of the design's learning rate (`WARM_START_LR_SHARE`): at the full rate its first steps
undo the content before they improve it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from aperture_fab.metrics import gain, psnr_db
from aperture_fab.optics.device import resolve_device, torch_dtype
from aperture_fab.optics.model import STACK_OVERSAMPLE, Renderer
from aperture_fab.optics.scene import Scene
from aperture_fab.optimize.optimizer import OptimizerSettings, fit_display

__all__ = ["Refit", "judge_psnr_db", "refit_display"]

#: The refit's learning rate as a share of the design's. Measured on simulated made copies of
#: the test design (docs/measure.md): the share of the loss recovered at a third of the
#: design's iterations went 24 -> 67 % on the copy with the largest loss at 0.2 (0.1: 64 %,
#: 0.5: 58 %) and stayed within 0.03 on the others.
WARM_START_LR_SHARE = 0.2


@dataclass(frozen=True)
class Refit:
    """A re-fit and its figures.

    displays: (T, C, H, W) float64 in [0, 1], the display content re-fitted to the made plate.
    nominal_db, made_db, refit_db, nominal_refit_db: PSNR after gain (module docstring).
    loss_history: (N,) the fit's loss per iteration. iterations: the fit's.
    """

    displays: np.ndarray
    nominal_db: float
    made_db: float
    refit_db: float
    nominal_refit_db: float
    loss_history: np.ndarray
    iterations: int

    @property
    def loss_db(self) -> float:
        """The tolerance loss: nominal - made, dB (negative: the made plate is better)."""
        return self.nominal_db - self.made_db

    @property
    def left_db(self) -> float:
        """What is left of it after the refit: nominal refit - refit, dB."""
        return self.nominal_refit_db - self.refit_db

    @property
    def recovered(self) -> float | None:
        """The share of the tolerance loss the refit recovers, 1 - left / loss; None when the
        made plate lost nothing."""
        return 1 - self.left_db / self.loss_db if self.loss_db > 0 else None


def judge_psnr_db(scene: Scene, open_fraction: np.ndarray, displays: np.ndarray,
                  targets: np.ndarray, settings: OptimizerSettings) -> float:
    """PSNR after gain (dB) of the plate `open_fraction` (rows, cols) showing `displays`
    (T, C, H, W) against `targets` (T, C, ny, nx), the squared error averaged over targets and
    the scene's eye positions."""
    device = resolve_device(settings.device)
    dtype = torch_dtype(settings.precision)
    renderer = Renderer(scene, device=device, dtype=dtype)
    a = torch.as_tensor(open_fraction, dtype=dtype, device=device)
    errors = []
    with torch.no_grad():
        for display, target in zip(displays, targets, strict=True):
            d = torch.as_tensor(display, dtype=dtype, device=device)
            for position in range(len(scene.eye.positions_mm)):
                view = renderer.render(a, d, position).cpu().double().numpy()
                errors.append(float(np.mean((gain(view, target) * view - target) ** 2)))
    return psnr_db(float(np.mean(errors)))


def refit_display(scene: Scene, targets: np.ndarray, nominal: np.ndarray, made: np.ndarray,
                  shipped: np.ndarray, settings: OptimizerSettings, iterations: int,
                  progress: bool = False) -> Refit:
    """Re-fit `shipped` (T, C, H, W), the design's display content, to the made plate `made`
    (rows, cols open fractions as measured) for `targets` (T, C, ny, nx, linear), and to the
    nominal plate `nominal` (the design's, as meant to be made) the same way; judge the four
    views (module docstring)."""
    settings = replace(settings, learning_rate=settings.learning_rate * WARM_START_LR_SHARE)
    fitted, history = fit_display(scene, targets, made, shipped, settings, iterations,
                                  oversample=STACK_OVERSAMPLE, progress=progress)
    reference, _ = fit_display(scene, targets, nominal, shipped, settings, iterations,
                               oversample=STACK_OVERSAMPLE, progress=progress)
    return Refit(np.clip(fitted, 0.0, 1.0),
                 judge_psnr_db(scene, nominal, shipped, targets, settings),
                 judge_psnr_db(scene, made, shipped, targets, settings),
                 judge_psnr_db(scene, made, fitted, targets, settings),
                 judge_psnr_db(scene, nominal, reference, targets, settings), history,
                 iterations)
