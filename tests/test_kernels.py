"""The fused CPU kernels (aperture_fab.optics.kernels) against the torch path (pair tables and
grid_sample), values and gradients, and a batch of eye states against each state alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit
from test_model import make_scene

from aperture_fab.metrics import gain_mse, gain_mse_states
from aperture_fab.optics import kernels
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.kernel_pair import (
    CACHE_FIELDS,
    EMISSION,
    LENS_R,
    lens_radius,
    pair_chord,
    pair_geometry,
)
from aperture_fab.optics.kernel_stack import UNROLLED_CHANNELS
from aperture_fab.optics.kernels import open_index
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.optimizer import combine_states


def states(offsets, pupils, diopters) -> EyeStates:
    count = len(pupils)
    return EyeStates(np.asarray(offsets, dtype=np.float64), np.asarray(pupils, dtype=np.float64),
                     np.asarray(diopters, dtype=np.float64), np.zeros((count, 2)),
                     np.full(count, 1.0 / count))


def views_and_grads(renderer: Renderer, a: np.ndarray, display: np.ndarray, batch: EyeStates,
                    weight: np.ndarray):
    a_t = torch.as_tensor(a, device=renderer.device).requires_grad_(True)
    d_t = torch.as_tensor(display, device=renderer.device).requires_grad_(True)
    view = renderer.render_states(a_t, renderer.display_stack(d_t), batch)
    (view * torch.as_tensor(weight, device=renderer.device)).sum().backward()
    return view.detach().cpu(), a_t.grad.cpu(), d_t.grad.cpu()


CASES = {
    "thin straight": {},
    "thick chief-ray": {"thickness": 0.3, "axis": "chief_ray"},
    "thick straight, finite focus": {"thickness": 0.2, "focus": 500.0},
    "offset eye": {"positions": ((1.2, -0.7),)},
}
BATCHES = {
    "infinity": ([(0.0, 0.0), (0.9, -0.5), (-1.5, 1.0)], [4.0, 3.0, 6.0], [0.0, 0.0, 0.0]),
    "mixed focus": ([(0.0, 0.0), (0.4, 0.3)], [4.0, 5.0], [0.0, 1.5]),
}


@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("displaced", [False, True])
def test_kernels_match_the_torch_path(case, batch_name, displaced):
    """Same views and gradients (radii and display) from both backends, float64, for states
    that share their display samples (all at infinity) and states that do not."""
    rng = np.random.default_rng(3)
    scene = make_scene(**CASES[case])
    offsets = rng.normal(0, 0.05, (12, 12, 2)) if displaced else None
    batch = states(*BATCHES[batch_name])
    a = rng.uniform(0, 0.6, (12, 12))
    display = rng.random((3, 60, 60))
    weight = rng.random((len(batch), 3, 32, 32))
    got = views_and_grads(Renderer(scene, dtype=torch.float64, backend="kernel",
                                   hole_offset_mm=offsets), a, display, batch, weight)
    want = views_and_grads(Renderer(scene, dtype=torch.float64, backend="torch",
                                    hole_offset_mm=offsets), a, display, batch, weight)
    assert float(want[0].abs().max()) > 0
    for g, w in zip(got, want, strict=True):
        # atol: the torch path pads with closed cells of radius 1e-6 (area ~3e-12).
        torch.testing.assert_close(g, w, rtol=1e-7, atol=1e-9 * float(w.abs().max()))


@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("channels", [1, 2, 4, 5, 6])
def test_kernels_match_the_torch_path_for_any_channel_count(channels, batch_name):
    """The kernels unroll a stack's first UNROLLED_CHANNELS channels and loop over the others:
    views and gradients match the torch path's for fewer, as many and more channels (three:
    the test above)."""
    assert UNROLLED_CHANNELS == 4
    rng = np.random.default_rng(8)
    scene = make_scene(thickness=0.3, axis="chief_ray")
    batch = states(*BATCHES[batch_name])
    a = rng.uniform(0, 0.6, (12, 12))
    display = rng.random((channels, 60, 60))
    weight = rng.random((len(batch), channels, 32, 32))
    got = views_and_grads(Renderer(scene, dtype=torch.float64, backend="kernel"), a, display,
                          batch, weight)
    want = views_and_grads(Renderer(scene, dtype=torch.float64, backend="torch"), a, display,
                           batch, weight)
    assert got[0].shape[1] == channels and float(want[0].abs().max()) > 0
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-7, atol=1e-9 * float(w.abs().max()))


@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("dead", [(0,), (1,), (0, 1)])
def test_states_without_gradient_are_left_out_of_the_backward(batch_name, dead, monkeypatch):
    """States whose views get no gradient (a tail loss's best ones) add nothing: the backward
    walks only the others, and its gradients are those of the batch without them (none left:
    zero, and no walk)."""
    walked: list[int] = []
    backward = kernels.view_backward

    def counting(*args):
        walked.append(len(args[4]))
        return backward(*args)

    monkeypatch.setattr(kernels, "view_backward", counting)
    rng = np.random.default_rng(6)
    renderer = Renderer(make_scene(thickness=0.2), dtype=torch.float64, backend="kernel")
    batch = states(*BATCHES[batch_name])
    a = rng.uniform(0, 0.6, (12, 12))
    display = rng.random((3, 60, 60))
    weight = rng.random((len(batch), 3, 32, 32))
    weight[list(dead)] = 0.0
    live = [s for s in range(len(batch)) if s not in dead]
    _, grad_a, grad_display = views_and_grads(renderer, a, display, batch, weight)
    assert walked == ([len(live)] if live else [])
    if not live:
        assert not grad_a.any() and not grad_display.any()
        return
    _, want_a, want_display = views_and_grads(renderer, a, display, batch.subset(live),
                                              weight[live])
    assert want_a.abs().max() > 0
    torch.testing.assert_close(grad_a, want_a, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(grad_display, want_display, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("case", ["thin straight", "thick straight, finite focus"])
def test_a_render_without_hole_gradient_skips_closed_cells_exactly(case):
    """A sparse plate (most cells closed) renders the same views whether or not the holes need
    a gradient (without one the kernels skip closed cells), and as the torch path does."""
    rng = np.random.default_rng(5)
    scene = make_scene(**CASES[case])
    batch = states(*BATCHES["mixed focus"])
    a = np.where(rng.random((12, 12)) < 0.2, rng.uniform(0.05, 0.6, (12, 12)), 0.0)
    display = torch.as_tensor(rng.random((3, 60, 60)))
    kernel = Renderer(scene, dtype=torch.float64, backend="kernel")
    stack = kernel.display_stack(display)
    with torch.no_grad():
        skipped = kernel.render_states(torch.as_tensor(a), stack, batch)
    walked = kernel.render_states(torch.as_tensor(a).requires_grad_(True), stack, batch)
    reference = Renderer(scene, dtype=torch.float64, backend="torch").render_states(
        torch.as_tensor(a), stack, batch)
    assert skipped.abs().max() > 0
    # A closed cell's sqrt(eps) radius leaves a trace of about 1e-12 where it is walked.
    torch.testing.assert_close(skipped, walked.detach(), rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(skipped, reference, rtol=1e-9, atol=1e-10)


@settings(max_examples=50, deadline=None)
@given(rows=st.integers(1, 6), cols=st.integers(1, 9), share=st.floats(0, 1),
       seed=st.integers(0, 2**16))
def test_the_open_index_names_the_next_open_hole_of_each_row(rows, cols, share, seed):
    """open_index(i, j) is the first column at or after j whose hole is open (radius above
    `closed`), or cols: the kernels' walk visits exactly the open holes through it."""
    rng = np.random.default_rng(seed)
    closed = 1e-3
    radius = np.where(rng.random(rows * cols) < share, rng.uniform(0.002, 0.1, rows * cols),
                      rng.uniform(0, closed, rows * cols))
    table = open_index(radius, (cols, rows), closed)
    grid = radius.reshape(rows, cols)
    want = [[next((k for k in range(j, cols) if grid[i, k] > closed), cols)
             for j in range(cols)] for i in range(rows)]
    assert table.dtype == np.int64 and table.shape == (rows, cols)
    np.testing.assert_array_equal(table, want)


def test_batched_states_equal_states_rendered_alone():
    """Rendering a batch of eye states in one pass gives each state's own view, and the
    expected loss over the batch is the weighted mean of the states' separate losses."""
    rng = np.random.default_rng(4)
    scene = make_scene(thickness=0.3, axis="chief_ray")
    renderer = Renderer(scene, dtype=torch.float64)
    batch = states([(0.0, 0.0), (1.0, 0.5), (-0.8, -1.1), (0.3, 0.0)], [4.0, 3.2, 5.5, 6.0],
                   [0.0] * 4)
    a = torch.as_tensor(rng.uniform(0, 0.6, (12, 12)))
    stack = renderer.display_stack(torch.as_tensor(rng.random((3, 60, 60))))
    target = torch.as_tensor(rng.random((3, 32, 32)))
    together = renderer.render_states(a, stack, batch)
    alone = [renderer.render_states(a, stack, batch.subset([s]))[0] for s in range(len(batch))]
    for s, view in enumerate(alone):
        torch.testing.assert_close(together[s], view, rtol=1e-12, atol=1e-14)
    losses = gain_mse_states(together, target)
    separate = torch.stack([gain_mse(view, target) for view in alone])
    torch.testing.assert_close(losses, separate)
    weights = torch.tensor(batch.weight)
    torch.testing.assert_close(combine_states(losses, weights, 1.0), separate.mean())


@pytest.mark.parametrize("share", [0.1, 0.3, 0.5, 1.0])
def test_tail_loss_is_the_mean_of_the_worst_states(share):
    """combine_states with tail_share q averages the worst q of the weight (a CVaR)."""
    losses = torch.tensor([0.5, 4.0, 1.0, 3.0, 2.0, 0.1, 0.7, 6.0, 0.2, 0.3], dtype=torch.float64)
    weights = torch.full((10,), 0.1, dtype=torch.float64)
    worst = torch.sort(losses, descending=True).values[: round(share * 10)]
    torch.testing.assert_close(combine_states(losses, weights, share), worst.mean())


def test_tail_loss_takes_part_of_a_state():
    """A tail that ends inside a state's weight takes that share of it."""
    losses = torch.tensor([1.0, 3.0, 2.0], dtype=torch.float64)
    weights = torch.tensor([0.5, 0.25, 0.25], dtype=torch.float64)
    # Worst first: 3 (0.25), 2 (0.25), then 0.1 of the 1.0 state's weight.
    want = (3.0 * 0.25 + 2.0 * 0.25 + 1.0 * 0.1) / 0.6
    assert float(combine_states(losses, weights, 0.6)) == pytest.approx(want)


def test_kernel_backend_refuses_cuda():
    with pytest.raises(ValueError, match="runs on the CPU"):
        Renderer(make_scene(), device="cuda", backend="kernel")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_the_cpu_kernels():
    """The same scene on CUDA (torch path) and on the CPU (kernels), float32 tolerance."""
    rng = np.random.default_rng(5)
    scene = make_scene(thickness=0.3, axis="chief_ray")
    batch = states(*BATCHES["infinity"])
    a = rng.uniform(0, 0.6, (12, 12))
    display = rng.random((3, 60, 60))
    cpu = Renderer(scene).render_states(torch.as_tensor(a, dtype=torch.float32),
                                        Renderer(scene).display_stack(
                                            torch.as_tensor(display, dtype=torch.float32)),
                                        batch)
    gpu_renderer = Renderer(scene, device="cuda")
    gpu = gpu_renderer.render_states(
        torch.as_tensor(a, dtype=torch.float32, device="cuda"),
        gpu_renderer.display_stack(torch.as_tensor(display, dtype=torch.float32, device="cuda")),
        batch)
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-6)


@njit(cache=False)
def _pairs_one_by_one(radius, geometry, offsets, states, v_x, v_y, pairs):
    """`pair_geometry` for each pair (i, j, k), as the kernels' geometry rows."""
    out = np.empty((CACHE_FIELDS, len(pairs)))
    for p in range(len(pairs)):
        values = pair_geometry(radius, geometry, offsets, states, 0, v_x, v_y, pairs[p, 0],
                               pairs[p, 1], True)
        for f in range(LENS_R):
            out[f, p] = values[f]
        out[LENS_R, p] = lens_radius(values[4])
        out[EMISSION, p] = values[10]
    return out


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), states=st.integers(1, 40), cells=st.integers(1, 12))
def test_the_row_chords_loop_is_pair_chord(seed, states, cells):
    """The walk's SIMD loop over the states' chords of a row (`kernels._row_chords`) gives
    `pair_chord`'s columns for every state: spans inside, across and off the plate, radii that
    miss the row, inner radii that are not positive (no inner chord)."""
    rng = np.random.default_rng(seed)
    geometry = np.zeros(len(kernels.GEOMETRY_FIELDS))
    geometry[:4] = cells, cells + rng.integers(0, 3), *rng.uniform(0.2, 0.8, 2)
    spans = np.zeros((kernels._SPAN, states))
    spans[0:2] = rng.uniform(-0.7, 0.7, (2, states)) * cells * geometry[2:4, None]
    spans[2] = rng.uniform(0.0, 0.6, states) * cells * geometry[2]
    spans[3] = spans[2] - rng.uniform(-0.2, 1.5, states) * geometry[2]
    chords = np.zeros((kernels._CHORD, states), dtype=np.int64)
    for i in range(int(geometry[1])):
        kernels._row_chords(geometry, spans, states, i, chords)
        for k in range(states):
            ox, oy, outer, inner = spans[:4, k]
            assert tuple(chords[:2, k]) == pair_chord(geometry, ox, oy, outer, i)
            expected = pair_chord(geometry, ox, oy, inner, i) if inner > 0 else (0, -1)
            assert tuple(chords[2:, k]) == expected


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), chief=st.booleans(), tilt=st.floats(0.0, 0.6))
def test_the_shared_geometry_loop_is_pair_geometry(seed, chief, tilt):
    """The kernels' SIMD loop over shared pairs (`kernels._fill` through `_shared_geometry`,
    every branch a selection) gives `pair_geometry`'s values for every pair: holes of any size
    (disks that miss each other at a steep view, levels clamped at both ends), displaced or
    not, chief-ray axes or not, in a whole stack or one of its upper levels (a level
    offset)."""
    rng = np.random.default_rng(seed)
    cells = 9
    offset = rng.uniform(0.0, 1.5) * rng.integers(0, 2)
    geometry = np.array([cells, cells, 0.5, 0.5, rng.uniform(0.2, 0.5), float(chief), 0.3, -0.2,
                         10.0, 10.0, 9.8, 20.0, 10.0, 10.0, 0.05, 0.05, 8.0, 0.0, 1.5, 0.0,
                         offset])
    assert len(geometry) == len(kernels.GEOMETRY_FIELDS)
    radius = rng.uniform(1e-6, 0.25, cells * cells)
    offsets = rng.normal(0.0, 0.01, (cells * cells, 2)) * rng.integers(0, 2)
    states = np.zeros((1, len(kernels.STATE_FIELDS)))
    states[0, 5] = rng.uniform(2.0, 20.0)  # level scale: large ones clamp levels at 1
    v_x, v_y = rng.uniform(-tilt, tilt, 2)
    pairs = np.array([(i, j, i * cells + j) for i in range(cells) for j in range(cells)])
    size = len(pairs)
    geo = np.zeros((CACHE_FIELDS, size))
    samples, slopes = np.zeros((size, 1)), np.zeros((size, 1))
    stack = np.zeros((3, 8, 8, 1), dtype=np.float32)
    kernels._fill(geo, samples, slopes, np.zeros((kernels._INPUTS, size)), stack, radius,
                  geometry, offsets, states, 0, v_x, v_y, True, pairs, size)
    alone = _pairs_one_by_one(radius, geometry, offsets, states, v_x, v_y, pairs)
    # atol: a lens area that is a difference of two near-equal ones keeps its absolute
    # rounding, not its relative (seed 5366: 0.00302520934770 against ...67, 6e-13 relative).
    np.testing.assert_allclose(geo, alone, rtol=1e-13, atol=1e-12)
