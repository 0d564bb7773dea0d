"""Optimize the plate's open-area fractions (and the display content) so the view matches targets.

The loss (docs/design.md): the MSE between the target and the view scaled by its least-squares gain,
averaged over targets, plus an optional light-efficiency term, per eye state; each iteration
draws its eye states afresh from the eye distribution (`aperture_fab.optics.eyes`, a stratified
set) and takes their expected loss, or the mean over the worst share of them (`tail_share`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.errors import Refused
from aperture_fab.fabrication.quantize import MadeSizes
from aperture_fab.metrics import gain_mse_states, psnr_db
from aperture_fab.optics.as_made import MadeDraw, MadeOptics, draw_errors, made_views, made_white
from aperture_fab.optics.device import resolve_device, to_device, torch_dtype
from aperture_fab.optics.eyes import EyeStates, distribution_of, iteration_seed
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Eye, Scene
from aperture_fab.optimize.budget import OPTIMIZER_OVERSAMPLE, check_budget
from aperture_fab.optimize.descent import SGD, Adam, Stepper
from aperture_fab.optimize.start import initial_state

__all__ = [
    "MaskDesign",
    "Interrupted",
    "DivergedError",
    "combine_states",
    "position_states",
    "training_states",
    "optimize",
    "fit_display",
    "fit_settings",
    "made_draw",
    "FIT_SETTINGS",
]

#: The cosine schedule decays the learning rate to this share of its start.
COSINE_FLOOR = 0.05
#: Share of the snapped iterations after which only the display content moves (0.75 rather
#: than 0.5: the plate's last quarter of moves gained 0.2 to 0.3 dB p10, and a quarter of the
#: run still fits the display to the settled plate).
FROZEN_PLATE_START = 0.75
#: MLEM iterations per eye state and design iteration of a tracked design (see _tracked_loss).
TRACKED_SOLVE_ITERATIONS = 2
#: Weight of the brightness floors' penalty (1 - light / floor)^2: light 10 % below the floor
#: costs 0.01, more than a typical image loss (MSE 1e-3), so the floor holds to a few %.
FLOOR_WEIGHT = 1.0
#: Share of the iterations before the brightness floor (min_efficiency) applies: it is for the
#: plate as made, and the start (a regular array, every other cell barely open) is darker than
#: the plate the optimizer settles on. Held from the start, the floor's push opened the photo's
#: plate to 4.3 % for a floor of 2 % (2.7 % without a floor), and nothing closed it again.
FLOOR_FROM = 0.25
#: The brightness floor's penalty holds the light efficiency at this multiple of the floor:
#: the penalty settles a little below where it aims, and the report judges other made copies
#: and eye states than an iteration's (the line pattern's part at 1.99 % for a floor of 2 %).
FLOOR_AIM = 1.03
#: View pixels per axis, at most, of the renderer the brightness floor measures the light
#: efficiency with (`light_renderer`): a white view's mean over 40 x 40 directions is within
#: 0.1 % of its mean over the near-eye preset's 128 x 128 in every eye state (the default part
#: and a random plate), at a ninth of the cost; 32 and 16 alias with the hole lattice (up to 1.4
#: and 7 % off).
LIGHT_VIEW_PIXELS = 40
#: Above the floor on the light at the eye by more than this share, the display content is
#: scaled down to it after the step, while the floor's penalty is still pushing (below). The
#: image loss is blind to the content's scale, so nothing else brings it down once the
#: penalty's steps have overshot (they left the view at twice a floor of 1 % on natural, its
#: content clipped at 1), and a dimmer content has more headroom.
EYE_FLOOR_HEADROOM = 0.05
#: Steps after the light at the eye was last below its floor during which the penalty's push
#: goes on: Adam's momentum (beta1 = 0.9) remembers about 10 steps. Past them, content whose
#: own light is above the floor is left alone: a cap there made the line pattern's part darker
#: than without the floor (0.47 to 0.26 % at the eye) and its margin over the regular arrays at
#: that light 1.2 dB smaller (benchmarks/bench_made_part.py, 2026-11-29).
EYE_FLOOR_MEMORY = 10


@dataclass(frozen=True)
class MaskDesign:
    """An optimized plate and the display content that goes with it.

    open_fraction: (rows, cols) float64, open-area fraction of each cell's hole.
    displays: (T, C, H, W) float64, linear display content per target.
    loss_history: (N,) float64, loss per iteration.
    bounds: (a_min, a_max), the open-area fractions the optimizer was allowed.
    stopped: why it stopped: "completed" or "plateau".
    continuous: when the last iterations saw the plate snapped to makeable holes, the design
        (open_fraction, displays) just before: the unconstrained optimum. None otherwise, and
        when every iteration saw the snapped plate (there is no unconstrained design).
    snapped: whether iterations saw the plate snapped to makeable holes: `open_fraction` is
        then makeable as it is (every value one of MadeSizes) and `displays` fitted to it.
    """

    open_fraction: np.ndarray
    displays: np.ndarray
    loss_history: np.ndarray
    bounds: tuple[float, float]
    stopped: str
    continuous: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def optimum(self) -> tuple[np.ndarray, np.ndarray]:
        """The optimized design before quantization: (open fractions, displays)."""
        if self.continuous is not None:
            return self.continuous
        return self.open_fraction, self.displays
    snapped: bool = False


class Interrupted(Exception):
    """The run was interrupted (Ctrl-C); `state` resumes it with `optimize(..., state=state)`."""

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__(f"interrupted at iteration {state['iteration']}")
        self.state = state


class DivergedError(Refused, FloatingPointError):
    """The loss became NaN or infinite."""


def _snapped(a: torch.Tensor, made: MadeSizes) -> torch.Tensor:
    """The nearest makeable fraction forward, the identity backward (straight through), so
    the loss sees the holes the process makes and the gradient still moves every cell."""
    with torch.no_grad():
        if made.levels is None:
            snap = torch.where(a < made.lo / 2, torch.zeros_like(a), a.clamp(made.lo, made.hi))
        else:
            levels = torch.as_tensor(made.levels, dtype=a.dtype, device=a.device)
            index = torch.searchsorted(levels, a.contiguous()).clamp(1, len(levels) - 1)
            below, above = levels[index - 1], levels[index]
            snap = torch.where(a - below <= above - a, below, above)
    return a + (snap - a).detach()


def position_states(eye: Eye) -> EyeStates:
    """The scene's fixed eyebox positions (eye.positions_mm, eye.weights) as eye states with
    the nominal pupil and focus."""
    count = len(eye.positions_mm)
    diopters = 0.0 if eye.focus_mm is None else 1000.0 / eye.focus_mm
    return EyeStates(np.asarray(eye.positions_mm, dtype=np.float64),
                     np.full(count, eye.pupil_mm), np.full(count, diopters),
                     np.zeros((count, 2)), np.asarray(eye.weights) / sum(eye.weights))


def training_states(scene: Scene, settings: OptimizerSettings, iteration: int) -> EyeStates:
    """The eye states iteration `iteration` is judged at: `settings.eye_states` states drawn
    afresh from the eye distribution as a stratified set (`EyeDistribution.stratified`: even
    over the distribution, unbiased, less noisy than independent draws: +0.3 dB p10 as made on
    the photo, README), seeded by (settings.seed, iteration) so that a resumed run draws the
    same ones; or, when the distribution is a single point, the scene's fixed eyebox
    positions."""
    distribution = distribution_of(scene.eye)
    if distribution.is_point:
        return position_states(scene.eye)
    return distribution.stratified(settings.eye_states, iteration_seed(settings.seed, iteration))


def combine_states(losses: torch.Tensor, weights: torch.Tensor, tail_share: float
                   ) -> torch.Tensor:
    """One loss from per-state losses (S,) and weights (S,) summing to 1: the expected loss
    (tail_share 1), or the mean over the worst tail_share of the weight (a CVaR: the states are
    taken from the worst down until their weight reaches tail_share, the last one in part)."""
    if tail_share >= 1:
        return (losses * weights).sum()
    order = torch.argsort(losses.detach(), descending=True)
    w = weights[order]
    before = torch.cumsum(w, 0) - w
    taken = torch.minimum(w, (tail_share - before).clamp(min=0))
    return (losses[order] * taken).sum() / taken.sum()


def _design_loss(renderer: Renderer, a: torch.Tensor, displays: torch.Tensor,
                 targets: torch.Tensor, states: EyeStates, efficiency_weight: float,
                 tail_share: float = 1.0, min_efficiency: float = 0.0,
                 optics: MadeOptics | None = None, draw: MadeDraw | None = None,
                 min_eye_level: float = 0.0, seen: dict[str, float] | None = None,
                 light: Renderer | None = None) -> torch.Tensor:
    """The design loss: gain-corrected MSE, averaged over targets, per eye state, plus
    efficiency_weight x (1 - light efficiency of the content); combined over the states by
    `combine_states`; plus, below a brightness floor min_efficiency, FLOOR_WEIGHT x (1 - E /
    (FLOOR_AIM floor))^2 with E the plate's light efficiency as the report judges it (its view
    of a uniform white display, the states' weighted mean), rendered by `light` (default:
    renderer; the optimizer's `light_renderer`); and below a floor on the light at the eye
    min_eye_level, FLOOR_WEIGHT x (1 - level / floor)^2 with level the mean view over states
    and targets. Both floors hold means, as the report judges them: each state's own floor
    would hold the dimmest state and overshoot the mean.
    optics: view the plate as made (`aperture_fab.optics.as_made`: diffraction, the leakage
    veil, and the errors of one made copy `draw`); None: the geometric view of the holes.
    seen: when given (and the floor set), receives "eye_level", that mean (a float)."""
    per_state = torch.zeros(len(states), dtype=renderer.dtype, device=renderer.device)
    eye_level = torch.zeros((), dtype=renderer.dtype, device=renderer.device)
    for t in range(targets.shape[0]):
        if optics is None:
            views = through = renderer.render_states(a, renderer.display_stack(displays[t]),
                                                     states)
        else:
            views, through = made_views(renderer, a, displays[t], states, optics, draw)
        per_state = per_state + gain_mse_states(views, targets[t])
        if min_eye_level > 0:
            eye_level = eye_level + views.mean() / targets.shape[0]
        if efficiency_weight > 0:
            # The open display's view of the content is the content over the field, so its
            # mean is the display's mean (the field spans the display from the eyebox; the
            # content at the display's edge, which some states do not see, is the difference).
            efficiency = through.mean((1, 2, 3)) / (displays[t].mean() + 1e-12)
            per_state = per_state + efficiency_weight * (1 - efficiency)
    weights = to_device(states.weight, renderer.dtype, renderer.device)
    loss = combine_states(per_state / targets.shape[0], weights, tail_share)
    if min_efficiency > 0:
        loss = loss + _efficiency_penalty(light or renderer, a, states, draw, min_efficiency)
    if min_eye_level > 0:
        loss = loss + FLOOR_WEIGHT * torch.clamp(1 - eye_level / min_eye_level, min=0) ** 2
        if seen is not None:
            seen["eye_level"] = float(eye_level.detach())
    return loss


def _efficiency_penalty(light: Renderer, a: torch.Tensor, states: EyeStates,
                        draw: MadeDraw | None, min_efficiency: float) -> torch.Tensor:
    """FLOOR_WEIGHT x (1 - E / (FLOOR_AIM min_efficiency))^2 below the floor, 0 above it; E the
    plate's light efficiency as the report judges it: the made copy's view of a uniform white
    display, the states' weighted mean, rendered by `light`."""
    weights = to_device(states.weight, light.dtype, light.device)
    efficiency = (made_white(light, a, states, draw) * weights).sum() / weights.sum()
    return FLOOR_WEIGHT * torch.clamp(1 - efficiency / (FLOOR_AIM * min_efficiency), min=0) ** 2


def light_renderer(renderer: Renderer) -> Renderer:
    """A renderer of the same scene and settings with at most LIGHT_VIEW_PIXELS view pixels
    per axis: the light efficiency (a white view's mean) needs no finer view."""
    eye = renderer.scene.eye
    nx, ny = eye.view_pixels
    pixels = (min(nx, LIGHT_VIEW_PIXELS), min(ny, LIGHT_VIEW_PIXELS))
    if pixels == eye.view_pixels:
        return renderer
    scene = replace(renderer.scene, eye=replace(eye, view_pixels=pixels))
    return Renderer(scene, device=renderer.device, dtype=renderer.dtype,
                    oversample=renderer.oversample)


def _hold_eye_floor(display: torch.Tensor, seen: dict[str, float], floor: float,
                    since_below: float) -> float:
    """Scale the display content (in place) down to EYE_FLOOR_HEADROOM above the floor on the
    light at the eye when the last loss saw it higher within EYE_FLOOR_MEMORY steps of its last
    being below the floor (the view is linear in the content). since_below: steps since then
    before this one (math.inf: never); returns the count after it."""
    if floor <= 0:
        return since_below
    level, top = seen.get("eye_level", 0.0), floor * (1 + EYE_FLOOR_HEADROOM)
    since_below = 0.0 if level < floor else since_below + 1.0
    if level > top and since_below <= EYE_FLOOR_MEMORY:
        with torch.no_grad():
            display.mul_(top / level)
    return since_below


def _tracked_loss(renderer: Renderer, a: torch.Tensor, displays: torch.Tensor,
                  targets: torch.Tensor, states: EyeStates, tail_share: float,
                  optics: MadeOptics | None = None, draw: MadeDraw | None = None,
                  min_efficiency: float = 0.0, light: Renderer | None = None) -> torch.Tensor:
    """The loss of a tracked design (optimizer.tracking = "tracked"): each eye state sees the
    display content solved for it as a device shows it (`aperture_fab.optimize.tracking.
    solve_display`, TRACKED_SOLVE_ITERATIONS of MLEM warm-started from `displays`, holding
    the warm start's light at the eye: tracking.DISPLAY_LIGHT_FLOOR), the solve seeing the
    nominal plate and each view the made copy `draw` through `optics` (as `_design_loss`;
    None: the geometric view). No gradient flows through the solve: at a solved display the
    loss is stationary in the display, so the plate's gradient is the partial one (the
    envelope theorem; approximate, as a few iterations do not reach the optimum). Its value is
    the tracked loss plus `_design_loss`'s light floor on the plate (min_efficiency, rendered
    by `light`); its gradient moves the plate by those and the warm start `displays` by their
    own (untracked) loss, the plate held: the warm start is the untracked content, whose light
    the frames keep."""
    # tracking imports this module
    from aperture_fab.optimize.tracking import DISPLAY_LIGHT_FLOOR, solve_display

    per_state = torch.zeros(len(states), dtype=renderer.dtype, device=renderer.device)
    for t in range(targets.shape[0]):
        solved = solve_display(renderer, a.detach(), targets[t], states, displays[t].detach(),
                               TRACKED_SOLVE_ITERATIONS, keep_best=False,
                               light_floor=DISPLAY_LIGHT_FLOOR).detach()
        views = torch.cat([
            _views(renderer, a, solved[s], states.subset([s]), optics, draw)
            for s in range(len(states))
        ])
        per_state = per_state + gain_mse_states(views, targets[t])
    weights = to_device(states.weight, renderer.dtype, renderer.device)
    loss = combine_states(per_state / targets.shape[0], weights, tail_share)
    warm = _design_loss(renderer, a.detach(), displays, targets, states, 0.0, tail_share,
                        optics=optics, draw=draw)
    if min_efficiency > 0:
        loss = loss + _efficiency_penalty(light or renderer, a, states, draw, min_efficiency)
    return loss + (warm - warm.detach())


def _views(renderer: Renderer, a: torch.Tensor, display: torch.Tensor, states: EyeStates,
           optics: MadeOptics | None, draw: MadeDraw | None) -> torch.Tensor:
    """The views (S, C, ny, nx) of one display (C, H, W): as made through `optics` with the
    copy `draw`, or the geometric view of the holes (optics None)."""
    if optics is None:
        return renderer.render_states(a, renderer.display_stack(display), states)
    return made_views(renderer, a, display, states, optics, draw)[0]


#: Stream of the made copies' random errors, apart from the eye states' (iteration_seed).
MADE_STREAM = 1


def made_draw(scene: Scene, settings: OptimizerSettings, optics: MadeOptics | None,
              iteration: int) -> MadeDraw | None:
    """The made copy iteration `iteration` sees (None without process errors): deterministic in
    (seed, iteration), so a resumed run draws the same copies."""
    if optics is None or not optics.has_errors:
        return None
    rng = np.random.default_rng((iteration_seed(settings.seed, iteration), MADE_STREAM))
    return draw_errors((scene.plate.cells[1], scene.plate.cells[0]), optics, rng)


def _lr_at(settings: OptimizerSettings, iteration: int, snap_from: int | None = None) -> float:
    """The learning rate; the cosine runs once over the continuous iterations and again over
    the snapped ones (from snap_from), so that holes can still move between makeable sizes."""
    if settings.schedule == "constant":
        return settings.learning_rate
    first, last = 0, settings.iterations
    if snap_from is not None:
        first, last = (snap_from, last) if iteration >= snap_from else (0, snap_from)
    phase = min(1.0, (iteration - first) / max(1, last - first - 1))
    return settings.learning_rate * (COSINE_FLOOR + (1 - COSINE_FLOOR)
                                     * 0.5 * (1 + math.cos(math.pi * phase)))


def optimize(
    scene: Scene,
    targets: np.ndarray,
    target_displays: np.ndarray,
    settings: OptimizerSettings,
    *,
    bounds: tuple[float, float] | None = None,
    made: MadeSizes | None = None,
    optics: MadeOptics | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    progress: bool = True,
) -> MaskDesign:
    """Optimize a plate for targets (T, C, ny, nx) on the view grid, linear light.

    target_displays: (T, C, H, W) the targets on the display's pixel grid (shown as is in
    display mode "target", and the start of optimized displays for non-pinhole inits).
    bounds: allowed open-area fractions (a_min, a_max); default (0, the largest hole a cell takes).
    made: the fractions a process makes; the last settings.quantize_share of the iterations
        (or all after a plateau) see the plate snapped to them, so the result is makeable.
    optics: the part as made (`aperture_fab.optics.as_made`): the loss sees diffraction and
        the leakage veil, and each iteration that sees the snapped plate draws one made copy's
        errors (seeded by the settings' seed and the iteration: a resume draws the same).
    state: a checkpoint from `on_checkpoint` or `Interrupted.state`, to resume.
    """
    device = resolve_device(settings.device)
    dtype = torch_dtype(settings.precision)
    check_budget(scene, settings, np.shape(targets), device=device)  # before any work
    lo, hi = bounds if bounds is not None else (0.0, scene.plate.max_open_fraction)
    if not 0 <= lo < hi <= 1:
        raise ValueError(f"bounds = {(lo, hi)} must satisfy 0 <= a_min < a_max <= 1.")
    target_t = torch.as_tensor(targets, dtype=dtype, device=device)
    shown_t = torch.as_tensor(target_displays, dtype=dtype, device=device)
    expected = (scene.eye.view_pixels[1], scene.eye.view_pixels[0])
    if target_t.ndim != 4 or tuple(target_t.shape[-2:]) != expected:
        raise ValueError(f"targets have shape {tuple(target_t.shape)}; "
                         f"expected (T, C, *{expected}).")
    if state is not None:
        state = copy.deepcopy(state)  # a checkpoint stays valid to resume from again
    else:
        state = initial_state(scene, target_t.cpu().double(), shown_t.cpu().double(), settings,
                               (lo, hi), 0.0 if made is None else made.lo)
    renderer = Renderer(scene, device=device, dtype=dtype, oversample=OPTIMIZER_OVERSAMPLE)
    mask_logits = state["mask_logits"].to(device, dtype).clone().requires_grad_(True)
    params = [mask_logits]
    display_param = None
    if state["display"] is not None:
        display_param = state["display"].to(device, dtype).clone().requires_grad_(True)
        params.append(display_param)
    if settings.method == "adam":
        opt: Stepper = Adam(params, lr=settings.learning_rate)
    else:
        opt = SGD(params, lr=settings.learning_rate, momentum=settings.momentum)
    if state["optimizer"] is not None:
        opt.load_state_dict(state["optimizer"])

    def plate(iteration: int) -> torch.Tensor:
        a = lo + (hi - lo) * torch.sigmoid(mask_logits)
        if made is not None and iteration >= state["snap_from"]:
            return _snapped(a, made)
        return a

    seen: dict[str, float] = {}  # the last loss's light at the eye (_hold_eye_floor)
    floor_from = round(FLOOR_FROM * settings.iterations)
    light = light_renderer(renderer) if settings.min_efficiency > 0 else None

    def loss_fn(iteration: int) -> torch.Tensor:
        states = training_states(scene, settings, iteration)
        snapped = made is not None and iteration >= state["snap_from"]
        draw = made_draw(scene, settings, optics, iteration) if snapped else None
        floor = settings.min_efficiency if iteration >= floor_from else 0.0
        if settings.tracking == "tracked" and display_param is not None:
            return _tracked_loss(renderer, plate(iteration), display_param, target_t, states,
                                 settings.tail_share, optics, draw, floor, light)
        displays = shown_t if display_param is None else display_param
        return _design_loss(renderer, plate(iteration), displays, target_t, states,
                            settings.efficiency_weight, settings.tail_share, floor, optics,
                            draw, settings.min_eye_level, seen, light)

    def keep_continuous() -> None:
        with torch.no_grad():
            state["continuous"] = (
                plate(-1).detach().cpu().clone(),
                None if display_param is None else display_param.detach().cpu().clone(),
            )

    # SGD steps on the summed squared error over the view (the dissertation's per-pixel scale:
    # its lr 0.8 is meaningless on a mean); Adam is invariant to the scale.
    scale = float(target_t[0].numel()) if settings.method == "sgd" else 1.0

    def snapshot(iteration: int) -> dict[str, Any]:
        return {
            "iteration": iteration,
            "history": list(state["history"]),
            "best": state["best"],
            "best_iteration": state["best_iteration"],
            "mask_logits": mask_logits.detach().cpu().clone(),
            "display": None if display_param is None else display_param.detach().cpu().clone(),
            "optimizer": copy.deepcopy(opt.state_dict()),
            "snap_from": state["snap_from"],
            "continuous": state["continuous"],
            "since_below_floor": state["since_below_floor"],
        }

    stopped = "completed"
    start = state["iteration"]
    bar = tqdm(total=settings.iterations, initial=start, disable=not progress, unit="it",
               desc="optimize", leave=False)
    iteration = start
    try:
        for iteration in range(start, settings.iterations):
            opt.lr = _lr_at(settings, iteration, None if made is None else state["snap_from"])
            if made is not None and iteration == state["snap_from"] > 0:
                keep_continuous()
                state["best"] = math.inf  # the snapped loss starts a new curve
            opt.zero_grad()
            loss = loss_fn(iteration)
            (loss * scale).backward()
            # Read once the backward is queued: the host's one wait for a GPU per iteration.
            value = float(loss.detach())
            if not math.isfinite(value):
                raise DivergedError(
                    f"the loss became {value} at iteration {iteration}; lower the learning rate "
                    f"(now {settings.learning_rate}) or use precision float64."
                )
            if made is not None and display_param is not None and iteration >= state[
                    "snap_from"] + FROZEN_PLATE_START * (settings.iterations - state["snap_from"]):
                mask_logits.grad = None  # the plate is settled: fit the display to it
            opt.step()
            if display_param is not None:
                with torch.no_grad():
                    display_param.clamp_(0, 1)
                state["since_below_floor"] = _hold_eye_floor(
                    display_param, seen, settings.min_eye_level, state["since_below_floor"])
            state["history"].append(value)
            if value < state["best"] * (1 - settings.plateau_tolerance):
                state["best"], state["best_iteration"] = value, iteration
            bar.update(1)
            bar.set_postfix(loss=f"{value:.3e}", psnr=f"{psnr_db(value):.1f}dB")
            done = iteration + 1
            if on_checkpoint is not None and done % settings.checkpoint_every == 0:
                on_checkpoint(snapshot(done))
            if settings.plateau_patience and iteration - state["best_iteration"] >= \
                    settings.plateau_patience:
                if made is not None and iteration + 1 < state["snap_from"]:
                    state["snap_from"] = iteration + 1  # converged: go on to makeable holes
                    continue
                stopped = "plateau"
                break
    except KeyboardInterrupt:
        bar.close()
        # The iteration in flight did not step: resume from the last completed one.
        raise Interrupted(snapshot(len(state["history"]))) from None
    bar.close()
    with torch.no_grad():
        a = (lo + (hi - lo) * torch.sigmoid(mask_logits)).cpu().double().numpy()
        displays = (shown_t if display_param is None else display_param).cpu().double().numpy()
    continuous = None
    snapped = made is not None and state["snap_from"] < len(state["history"])
    if snapped:
        assert made is not None
        a = made.snap(a)
    if snapped and state["continuous"] is not None:
        kept_a, kept_display = state["continuous"]
        continuous = (kept_a.double().numpy(),
                      displays if kept_display is None else kept_display.double().numpy())
    return MaskDesign(
        open_fraction=a,
        displays=displays,
        loss_history=np.asarray(state["history"], dtype=np.float64),
        bounds=(lo, hi),
        stopped=stopped,
        continuous=continuous,
        snapped=snapped,
    )


#: The optimizer settings `fit_display` reads (its iteration count is an argument of its own):
#: with the plate, targets and starting content, all a fitted content depends on.
FIT_SETTINGS = ("learning_rate", "schedule", "seed", "precision", "device", "eye_states",
                "tail_share", "min_eye_level")


def fit_settings(settings: OptimizerSettings) -> dict[str, Any]:
    """The FIT_SETTINGS of `settings`, by name: a display fit's key (two settings that differ
    elsewhere, the design's start or its lattice choice, fit the same content)."""
    return {name: getattr(settings, name) for name in FIT_SETTINGS}


def fit_display(
    scene: Scene,
    targets: np.ndarray,
    open_fraction: np.ndarray,
    displays: np.ndarray,
    settings: OptimizerSettings,
    iterations: int,
    *,
    optics: MadeOptics | None = None,
    oversample: int = OPTIMIZER_OVERSAMPLE,
    max_radius_mm: float | None = None,
    min_radius_mm: float | None = None,
    progress: bool = False,
    on_iteration: Callable[[int, torch.Tensor], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Re-fit the display content (T, C, H, W) to a fixed plate, e.g. the part as built, from
    `displays`; the plate is hardware, the display content software. Returns the displays and
    the loss history. Adam with the settings' learning rate and schedule, the same loss (with
    `optics`: the plate as made, one made copy drawn per iteration as in `optimize`), its
    display stack sampled `oversample` times per pixel (the optimizer's, by default), for holes
    from min_radius_mm up to max_radius_mm (`Renderer`; None: any, and the largest a cell
    holds).
    on_iteration(n, displays): told the content after each iteration n (1 to iterations; a
    tensor the fit goes on changing: copy what you keep)."""
    device = resolve_device(settings.device)
    dtype = torch_dtype(settings.precision)
    renderer = Renderer(scene, device=device, dtype=dtype, oversample=oversample,
                        max_radius_mm=max_radius_mm, min_radius_mm=min_radius_mm)
    a = torch.as_tensor(open_fraction, dtype=dtype, device=device)
    target_t = torch.as_tensor(targets, dtype=dtype, device=device)
    shown = torch.as_tensor(displays, dtype=dtype, device=device).clone().requires_grad_(True)
    opt = Adam([shown], lr=settings.learning_rate)
    schedule = replace(settings, iterations=iterations)
    seen: dict[str, float] = {}
    since_below = math.inf
    history = []
    for iteration in tqdm(range(iterations), desc="fit display", disable=not progress,
                          leave=False):
        opt.lr = _lr_at(schedule, iteration)
        opt.zero_grad()
        loss = _design_loss(renderer, a, shown, target_t,
                            training_states(scene, settings, iteration), 0.0, settings.tail_share,
                            optics=optics, draw=made_draw(scene, settings, optics, iteration),
                            min_eye_level=settings.min_eye_level, seen=seen)
        value = float(loss.detach())
        if not math.isfinite(value):
            raise DivergedError(f"the display fit's loss became {value} at iteration "
                                f"{iteration}; lower the learning rate.")
        loss.backward()
        opt.step()
        with torch.no_grad():
            shown.clamp_(0, 1)
        since_below = _hold_eye_floor(shown, seen, settings.min_eye_level, since_below)
        history.append(value)
        if on_iteration is not None:
            on_iteration(iteration + 1, shown.detach())
    return shown.detach().cpu().double().numpy(), np.asarray(history)
