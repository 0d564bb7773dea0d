"""Tracked displays: the display content solved for one known eye state, the plate fixed.

A worn device sees a moving eye (docs/design.md section 3, "The eye moves"). Untracked, it shows one
display content for every eye state: the design's. Tracked, it knows the pupil's position and
diameter (and, with a focus tracker, its accommodation) and re-solves the content for that state,
frame by frame, starting from the untracked content. The plate is hardware and stays as made;
only the software content moves. See docs/tracking.md.

The problem. For one eye state the view is linear in the display: v = A d, with A the renderer's
`render_states` after `display_stack` (non-negative: blur kernels, interpolation weights and hole
shares are all >= 0). The loss is docs/design.md's, the MSE to the target t after the view's
least-squares gain, so the display's scale is free: minimise over d >= 0, then rescale to a
maximum of 1 (the result lies in [0, 1] and loses nothing).

The solver: MLEM (Richardson-Lucy), the default. Each iteration is one forward pass and one
backward pass (A^T is the vector-Jacobian product of the render with respect to the display,
`torch.autograd.grad`):

    d <- d * A^T(t / (g A d)) / A^T 1,    g = sum(t) / sum(A d),

then d / max(d). It keeps d >= 0 without a projection, needs no step size, and is invariant to the
scale of A and t (g keeps the ratio near 1), so one setting works for every scene, plate and eye
state. A^T 1 comes from a second backward pass through the first iteration's graph. Safeguards:
display pixels the eye does not see (A^T 1 below 1e-4 of its largest value) keep their start
value; view pixels that get almost no light are floored (1e-3 of the target's peak) before the
division; each pixel's factor is capped at RATIO_CAP per iteration; start pixels are floored at
START_FLOOR of the peak so that black pixels of the untracked content (gaps between elemental
images) can light up when the eye moves (a multiplicative update cannot leave an exact 0).
MLEM minimises the Poisson divergence rather than the MSE, so the PSNR after gain can fall after
many iterations (at (2, 0) mm below: 39.3 dB after 20 iterations, 38.0 after 30); the best
iterate is kept.

Measured (benchmarks/bench_display.py --compare, near-eye preset: 400 x 400 display, 128 x 128
view, 80 x 80 cells; the regular pinhole plate; target `natural`; start: the plate's elemental
display for the nominal eye, i.e. its untracked content; float32 on the CPU), PSNR after gain in
dB, start -> after 1, 2, 5, 10 iterations:

    eye (x, y) mm, pupil | MLEM                           | projected Adam, lr 0.05
    (0, 0), 4 mm         | 25.3 -> 36.4 38.4 41.4 43.9    | 25.3 -> 28.0 30.6 31.2 33.9
    (1, 0), 4 mm         | 22.3 -> 35.5 37.9 41.1 43.7    | 22.3 -> 25.2 27.9 29.1 31.3
    (2, 0), 4 mm         | 18.5 -> 28.6 30.0 33.4 38.3    | 18.5 -> 20.5 22.2 24.7 26.1
    (1.5, 1.5), 6 mm     | 22.2 -> 35.0 37.6 41.0 43.7    | 22.2 -> 25.0 26.7 28.4 31.4

MLEM rose monotonically at every iteration in these runs. Projected Adam (the design optimizer's
way of fitting the display) moves each pixel by at most about its learning rate per step, so it
needs tens of iterations where MLEM needs one or two (lr 0.01, 0.03 and 0.1 were slower than MLEM
too, in an earlier run). Also tried: conjugate gradients on the unconstrained least squares
(CGLS) clipped to d >= 0, 35.7 39.1 43.4 42.7 dB at (0, 0), 32.3 36.8 40.2 40.0 at (1, 0),
23.9 27.8 33.3 34.3 at (2, 0), 30.9 33.0 33.9 33.8 at (1.5, 1.5) with 6 mm: ahead of MLEM only at
(0, 0) after 2 and 5 iterations (by 0.7 and 2.0 dB), behind everywhere else, and not monotone;
ISRA (d <- d A^T t / A^T A d) diverged in float32 without safeguards (an earlier run). Where MLEM
is weak: a plate of large, blurring holes (an ill-conditioned A), where both solvers crawl (the
tests' tiny scene with every cell 0.3 open: 15.2 -> 16.1 dB in 5 MLEM iterations, 16.8 dB with
Adam).

Light. Scaling each iterate to a peak of 1 darkens the view: MLEM sharpens by concentrating
light in a few display pixels, so the peak rises and, after the scaling, the rest dims. With a
light floor f (`light_floor`), each iterate instead takes the smallest scale k >= 1 / peak at
which its light at the eye, sum(A^T 1 * min(k d, 1)), reaches f times the start's (A^T 1 is
already at hand, and the view is linear in d, so no extra render is needed; k by bisection), and
its brightest pixels saturate. The next iteration then corrects for what the saturation lost.
Measured on the scene of the table above (benchmarks/bench_display.py --light-floors 0 0.5 1;
5 iterations; PSNR after gain, the light at the eye as a share of the start's): no floor:
(0, 0) 42.2 dB at 0.36, (1, 0) 42.0 at
0.29, (2, 0) 35.5 at 0.02, (1.5, 1.5) with 6 mm 29.8 at 0.21; floor 0.5: 42.2, 38.4, 33.0,
28.7; floor 1: 31.7, 29.6, 26.6, 24.6 (starts: 22.2, 19.5, 16.2, 15.4 dB). Saturating only the
final iterate instead lost 0.2 to 2.8 dB at floor 1, and blending the peak-1 result with the
start to reach the same light lost 5 to 19 dB at floor 0.5. The floor holds in the renderer's
geometric model; a made copy's veil and diffraction change the light a little.

Cost per solve: n iterations of one forward and one backward pass, one extra backward pass (A^T
1), and with `keep_best` one more forward pass to judge the last iterate. Figures per frame:
docs/tracking.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from aperture_fab.metrics import gain_mse_states, psnr_db
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.descent import Adam

__all__ = ["DEFAULT_ITERATIONS", "DISPLAY_LIGHT_FLOOR", "Solver", "TrackedViews", "solve_display",
           "tracked_views"]

Solver = Literal["mlem", "adam"]
SOLVERS: tuple[Solver, ...] = ("mlem", "adam")
#: Iterations per frame: most of what MLEM gains comes in the first few (see the docstring).
DEFAULT_ITERATIONS = 5
MAX_ITERATIONS = 10_000
#: Largest factor by which one MLEM iteration may brighten a display pixel.
RATIO_CAP = 10.0
#: Start pixels are raised to this share of the start's peak so that black ones can light up.
START_FLOOR = 1e-3
#: Display pixels whose A^T 1 is below this share of its largest value count as unseen.
SEEN_SHARE = 1e-4
#: View pixels are floored at this share of the target's peak before MLEM divides by them.
VIEW_FLOOR = 1e-3
#: The light floor a device's frames use (`aperture-fab display`): all of the untracked light,
#: so that frames for a moving eye are as bright as the untracked content and as one another
#: (unfloored, MLEM's frames are 3 to 50 times darker, by state: the module docstring, "Light").
DISPLAY_LIGHT_FLOOR = 1.0
#: Bisection steps of the light floor's scale (in log k: 2^-40 of its range).
BRIGHTEN_STEPS = 40
#: Projected Adam's learning rate (the near-eye preset's).
ADAM_LR = 0.05


@dataclass(frozen=True)
class TrackedViews:
    """What `tracked_views` solved, for S eye states.

    displays: (S, C, H, W) linear display content per state, in [0, 1].
    views: (S, C, ny, nx) the views of those displays (not gain-scaled).
    psnr_db: (S,) PSNR after gain of each state's tracked view.
    start_psnr_db: (S,) the same for the start (untracked) display.
    history_db: (S, n) PSNR after gain of every iterate judged, the start first.
    """

    displays: torch.Tensor
    views: torch.Tensor
    psnr_db: np.ndarray
    start_psnr_db: np.ndarray
    history_db: np.ndarray


@dataclass(frozen=True)
class _Solved:
    display: torch.Tensor  # (C, H, W), the best iterate (or the last, without keep_best)
    view: torch.Tensor | None  # (C, ny, nx) its view, when it was rendered
    history_db: list[float]  # PSNR of each iterate judged, the start first


def _psnr(view: torch.Tensor, target: torch.Tensor) -> float:
    return psnr_db(float(gain_mse_states(view.detach()[None], target)[0]))


def _check_iterations(iterations: int) -> int:
    if not (isinstance(iterations, (int, np.integer)) and not isinstance(iterations, bool)
            and 0 <= iterations <= MAX_ITERATIONS):
        raise ValueError(f"iterations = {iterations!r} is out of range; allowed: a whole number "
                         f"from 0 to {MAX_ITERATIONS} (0 keeps the start display). A few are "
                         f"enough: the default is {DEFAULT_ITERATIONS}.")
    return int(iterations)


def _no_light(state: EyeStates) -> ValueError:
    (x, y), pupil = state.offset_mm[0], float(state.pupil_mm[0])
    return ValueError(f"the eye at ({x:g}, {y:g}) mm with a {pupil:g} mm pupil sees no light "
                      "through the plate onto the display; allowed: eye states that see some "
                      "of the display (move the eye toward the nominal position).")


def _render(renderer: Renderer, a: torch.Tensor, display: torch.Tensor, state: EyeStates
            ) -> torch.Tensor:
    return renderer.render_states(a, renderer.display_stack(display), state)[0]


def _mlem(renderer: Renderer, a: torch.Tensor, target: torch.Tensor, state: EyeStates,
          start: torch.Tensor, iterations: int, keep_best: bool, light_floor: float) -> _Solved:
    d = start
    best, best_view, best_db = start, None, -math.inf
    history: list[float] = []
    norm = seen = column = None
    goal = 0.0
    t_sum = float(target.sum())
    floor = VIEW_FLOOR * float(target.max())
    for _ in range(iterations):
        leaf = d.detach().requires_grad_(True)
        view = _render(renderer, a, leaf, state)
        value = _psnr(view, target)
        history.append(value)
        if value > best_db:
            best, best_view, best_db = d, view.detach(), value
        v_sum = float(view.detach().sum())
        if not (v_sum > 0 and math.isfinite(v_sum)):
            raise _no_light(state)
        weight = target / (view.detach() * (t_sum / v_sum)).clamp_min(floor)
        if norm is None:
            (column,) = torch.autograd.grad(view, leaf, torch.ones_like(view), retain_graph=True)
            seen = column > SEEN_SHARE * float(column.max())
            norm = torch.where(seen, column, torch.ones_like(column))
            goal = light_floor * float(view.detach().sum())  # the start's light, A 1 . start
            # Let black start pixels light up (see the module docstring).
            d = d.clamp_min(START_FLOOR * float(d.max()))
        assert seen is not None and column is not None
        (back,) = torch.autograd.grad(view, leaf, weight)
        ratio = torch.where(seen, (back / norm).clamp(0, RATIO_CAP), torch.ones_like(back))
        d = _brighten(d.detach() * ratio, column, seen, goal)
    return _finish(renderer, a, target, state, d, iterations, keep_best, best, best_view,
                   best_db, history)


def _brighten(d: torch.Tensor, column: torch.Tensor, seen: torch.Tensor, goal: float
              ) -> torch.Tensor:
    """d scaled by the smallest k >= 1 / (its peak over seen pixels) whose light at the eye,
    column . min(k d, 1), reaches `goal`, and clipped to [0, 1]: the peak-1 scaling when that is
    bright enough, else the brightest pixels saturate (see the module docstring, "Light")."""
    peak = float(torch.where(seen, d, torch.zeros_like(d)).max())
    if not peak > 0:
        return d
    d = d / peak

    def light(k: float) -> float:
        return float((column * (d * k).clamp(max=1)).sum())

    if light(1.0) >= goal:
        return d.clamp(0, 1)
    positive = d[seen & (d > 0)]
    low, high = 1.0, 1.0 / float(positive.min())  # at `high` every lit seen pixel saturates
    # Bisection in log k. If even `high` is too dark (MLEM zeroed some of the start's lit
    # pixels), the result is `high`'s: every lit pixel saturated, the brightest reachable.
    for _ in range(BRIGHTEN_STEPS):
        middle = math.sqrt(low * high)
        low, high = (middle, high) if light(middle) < goal else (low, middle)
    return (d * high).clamp(0, 1)


def _adam(renderer: Renderer, a: torch.Tensor, target: torch.Tensor, state: EyeStates,
          start: torch.Tensor, iterations: int, keep_best: bool, light_floor: float) -> _Solved:
    del light_floor  # refused for Adam by _solve_all
    param = start.clone().requires_grad_(True)
    opt = Adam([param], lr=ADAM_LR)
    best, best_view, best_db = start, None, -math.inf
    history: list[float] = []
    for _ in range(iterations):
        opt.zero_grad()
        view = _render(renderer, a, param, state)
        loss = gain_mse_states(view[None], target)[0]
        value = psnr_db(float(loss.detach()))
        history.append(value)
        if value > best_db:
            best, best_view, best_db = param.detach().clone(), view.detach(), value
        loss.backward()
        opt.step()
        with torch.no_grad():
            param.clamp_(0, 1)
    return _finish(renderer, a, target, state, param.detach(), iterations, keep_best, best,
                   best_view, best_db, history)


def _finish(renderer: Renderer, a: torch.Tensor, target: torch.Tensor, state: EyeStates,
            last: torch.Tensor, iterations: int, keep_best: bool, best: torch.Tensor,
            best_view: torch.Tensor | None, best_db: float, history: list[float]) -> _Solved:
    """Judge the last iterate (keep_best) and return the best one, scaled to a peak of 1."""
    if iterations == 0 or keep_best:
        with torch.no_grad():
            view = _render(renderer, a, last, state)
        value = _psnr(view, target)
        history.append(value)
        if value > best_db or best_view is None:
            best, best_view = last, view
    else:
        best, best_view = last, None
    peak = float(best.max())
    if peak > 0:
        best, best_view = best / peak, None if best_view is None else best_view / peak
    return _Solved(best.clamp(0, 1), best_view, history)


def _states_and_starts(renderer: Renderer, state: EyeStates, start: torch.Tensor | np.ndarray
                       ) -> tuple[list[EyeStates], torch.Tensor]:
    if not isinstance(state, EyeStates):
        raise TypeError(f"state must be an aperture_fab.optics.eyes.EyeStates, got "
                        f"{type(state).__name__}; build one with EyeStates(offset_mm=[[x, y]], "
                        "pupil_mm=[d], focus_diopters=[0], gaze_deg=[[0, 0]], weight=[1]).")
    display = renderer.scene.display
    pixels = (display.pixels[1], display.pixels[0])
    starts = torch.as_tensor(start).detach().to(renderer.device, renderer.dtype)
    given = tuple(starts.shape)
    if starts.ndim == 3:
        starts = starts.expand(len(state), *starts.shape)
    if starts.ndim != 4 or tuple(starts.shape[-2:]) != pixels or starts.shape[0] != len(state):
        raise ValueError(f"start has shape {given}; allowed: (C, H, W) or one per "
                         f"state (S = {len(state)}, C, H, W) with (H, W) = {pixels}, the "
                         "display's pixels. Give the untracked display content.")
    if not bool(torch.isfinite(starts).all()):
        raise ValueError("start holds NaN or infinite values; give display content in [0, 1].")
    states = [EyeStates(state.offset_mm[i : i + 1], state.pupil_mm[i : i + 1],
                        state.focus_diopters[i : i + 1], state.gaze_deg[i : i + 1], np.ones(1))
              for i in range(len(state))]
    return states, starts.clamp(0, 1)


def _solve_all(renderer: Renderer, open_fraction: torch.Tensor | np.ndarray,
               target: torch.Tensor | np.ndarray, state: EyeStates,
               start: torch.Tensor | np.ndarray, iterations: int, method: Solver,
               keep_best: bool, light_floor: float) -> list[_Solved]:
    if method not in SOLVERS:
        raise ValueError(f"method = {method!r} is not allowed; choose one of "
                         f"{', '.join(SOLVERS)} (mlem converges much faster).")
    if not (isinstance(light_floor, (int, float)) and not isinstance(light_floor, bool)
            and 0 <= light_floor <= 1):
        raise ValueError(f"light_floor = {light_floor!r} is out of range; allowed: a share "
                         "from 0 (no floor: each frame scaled to a peak of 1) to 1 (the "
                         "untracked content's light at the eye kept).")
    if light_floor > 0 and method != "mlem":
        raise ValueError(f"light_floor = {light_floor!r} needs method = 'mlem'; the floor is "
                         "held inside MLEM's iterations. Use mlem, or light_floor = 0.")
    iterations = _check_iterations(iterations)
    a = torch.as_tensor(open_fraction).detach().to(renderer.device, renderer.dtype)
    goal = torch.as_tensor(target).detach().to(renderer.device, renderer.dtype)
    given = tuple(goal.shape)
    views = (renderer.scene.eye.view_pixels[1], renderer.scene.eye.view_pixels[0])
    if goal.ndim == 3:
        goal = goal.expand(len(state), *goal.shape)
    if goal.ndim != 4 or tuple(goal.shape[-2:]) != views or goal.shape[0] != len(state):
        raise ValueError(f"target has shape {given}; allowed: (C, ny, nx) or one "
                         f"per state (S = {len(state)}, C, ny, nx) with (ny, nx) = {views}, the "
                         "view grid (resample the image with aperture_fab.io.images.resample).")
    if not bool(torch.isfinite(goal).all()) or float(goal.min()) < 0 or float(goal.max()) <= 0:
        raise ValueError("target must be finite, >= 0 and not all black (linear light in "
                         "[0, 1]).")
    states, starts = _states_and_starts(renderer, state, start)
    if starts.shape[1] != goal.shape[1]:
        raise ValueError(f"start has {starts.shape[1]} channel(s) and target {goal.shape[1]}; "
                         "give both grey (1) or both colour (3).")
    solve = _mlem if method == "mlem" else _adam
    with torch.enable_grad():  # the solvers differentiate the render, even under no_grad
        return [solve(renderer, a, goal[s], states[s], starts[s], iterations, keep_best,
                      float(light_floor)) for s in range(len(states))]


def solve_display(
    renderer: Renderer,
    open_fraction: torch.Tensor | np.ndarray,
    target: torch.Tensor | np.ndarray,
    state: EyeStates,
    start: torch.Tensor | np.ndarray,
    iterations: int = DEFAULT_ITERATIONS,
    *,
    method: Solver = "mlem",
    keep_best: bool = True,
    light_floor: float = 0.0,
) -> torch.Tensor:
    """The display content (S, C, H, W) in [0, 1] for each eye state of `state`, the plate
    fixed: a tracked display (see the module docstring for the solver and its convergence).

    renderer: the scene's renderer (its device and dtype are used). open_fraction: (rows, cols)
    the plate's open-area fractions (as made, for a part). target: (C, ny, nx) linear, on the
    view grid, or one per state (S, C, ny, nx). state: one eye state, or a batch: one display per
    state, each solved on its own. start: the warm start, the untracked display (C, H, W) or one
    per state (S, C, H, W); clipped to [0, 1]. iterations: solver iterations per state (0: the
    start, scaled to a peak of 1). method: "mlem" (default) or "adam" (projected Adam, slower;
    kept for comparison). keep_best: judge the last iterate too (one more forward pass) and
    return the best iterate seen, so the result is never worse than the start; without it, the
    last iterate (for the lowest latency). light_floor: the share of the start's light at the eye
    (the mean of its view, in the renderer's model) that every iterate keeps, from 0 (none: each
    iterate scaled to a peak of 1, which darkens the view) to 1; where the peak-1 scaling is
    darker, the iterate is scaled up and its brightest pixels saturate (MLEM only).
    Deterministic: the same inputs give the same display.
    """
    solved = _solve_all(renderer, open_fraction, target, state, start, iterations, method,
                        keep_best, light_floor)
    return torch.stack([s.display for s in solved])


def tracked_views(
    renderer: Renderer,
    open_fraction: torch.Tensor | np.ndarray,
    targets: torch.Tensor | np.ndarray,
    states: EyeStates,
    start: torch.Tensor | np.ndarray,
    iterations: int = DEFAULT_ITERATIONS,
    *,
    method: Solver = "mlem",
    light_floor: float = 0.0,
) -> TrackedViews:
    """Solve a tracked display for each of `states` (as `solve_display`, keep_best) and return
    the displays, their views and per-state PSNR after gain, beside the start display's.

    targets: (C, ny, nx) for every state, or (S, C, ny, nx). The renderer cannot render S
    different displays in one pass, so the states are solved one after another; each solve
    renders all channels at once, and the start's and the result's views come from the solver's
    own passes (no extra rendering).
    """
    solved = _solve_all(renderer, open_fraction, targets, states, start, iterations, method,
                        True, light_floor)
    views = torch.stack([s.view for s in solved if s.view is not None])
    width = max(len(s.history_db) for s in solved)
    history = np.full((len(solved), width), np.nan)
    for i, s in enumerate(solved):
        history[i, : len(s.history_db)] = s.history_db
    return TrackedViews(
        displays=torch.stack([s.display for s in solved]),
        views=views,
        psnr_db=np.nanmax(history, axis=1),
        start_psnr_db=history[:, 0].copy(),
        history_db=history,
    )
