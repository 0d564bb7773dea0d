"""The memory budget: the estimate's model, the refusal before any work, and the estimate
against the peak memory the optimizer really takes."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch

from aperture_fab.config.config import resolve
from aperture_fab.optics.model import Renderer, stack_shape
from aperture_fab.optimize import budget

GB = 1e9


def _config(preset: str = "near-eye", **overrides: object):
    return resolve(preset, None, {"optimizer.device": "cpu", **overrides})


@pytest.mark.parametrize(
    ("preset", "overrides"),
    [
        ("near-eye", {}),
        ("seed", {}),
        ("near-eye", {"display.pixels": [640, 480], "eye.view_pixels": [64, 48]}),
        ("near-eye", {"eye.focus_mm": 300.0, "plate.pitch_mm": 0.1, "plate.cells": [200, 200]}),
    ],
)
@pytest.mark.parametrize("oversample", [1, 2])
def test_stack_shape_is_the_renderers(preset: str, overrides: dict[str, object],
                                      oversample: int) -> None:
    """The shape the budget counts is the stack the renderer builds."""
    scene = _config(preset, **overrides).scene
    renderer = Renderer(scene, oversample=oversample)
    shape = stack_shape(scene, oversample)
    stack = renderer.display_stack(torch.zeros(1, scene.display.pixels[1],
                                               scene.display.pixels[0]))
    assert stack.shape[2:] == (shape.levels, shape.height, shape.width)
    assert renderer.kernel_size == shape.kernel_size and renderer.pad == shape.pad
    assert renderer._fft_shape == (shape.fft_height, shape.fft_width)


@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_estimate_grows_with_views_states_and_cells(backend: str) -> None:
    def size(states: int = 4, **overrides: object) -> int:
        scene = _config(**overrides).scene
        return budget.estimate_bytes(scene, states, backend, torch.float32)

    base = size()
    assert base > 0
    assert size(**{"eye.view_pixels": [256, 256]}) > base
    assert size(states=16) > base
    assert size(**{"plate.cells": [400, 400]}) > base
    assert size(**{"display.pixels": [800, 800]}) > base
    scene = _config().scene
    assert (budget.estimate_bytes(scene, 4, backend, torch.float64)
            > budget.estimate_bytes(scene, 4, backend, "float32"))
    assert (budget.estimate_bytes(scene, 4, backend, "float32", channels=3, targets=2)
            > budget.estimate_bytes(scene, 4, backend, "float32", channels=1))
    assert (budget.estimate_bytes(scene, 4, backend, "float32", tracked=True)
            > budget.estimate_bytes(scene, 4, backend, "float32"))


def test_estimate_rejects_bad_arguments() -> None:
    scene = _config().scene
    with pytest.raises(ValueError, match="backend"):
        budget.estimate_bytes(scene, 1, "cuda", "float32")
    with pytest.raises(ValueError, match="float16"):
        budget.estimate_bytes(scene, 1, "kernel", "float16")
    with pytest.raises(ValueError, match="states_per_pass"):
        budget.estimate_bytes(scene, 0, "kernel", "float32")


def test_small_scene_passes_and_returns_the_estimate() -> None:
    config = _config("seed")
    estimate = budget.check_budget(config.scene, config.optimizer, (1, 1, 28, 28))
    assert 0 < estimate < 100 * 2**20
    config = _config()
    assert budget.check_budget(config.scene, config.optimizer, (1, 3, 128, 128)) < 1 * GB


def test_refusal_names_the_estimate_the_budget_and_the_fix() -> None:
    config = _config(**{"eye.view_pixels": [3000, 3000], "optimizer.precision": "float64",
                        "plate.cells": [80, 80], "plate.pitch_mm": [0.25, 0.25],
                        "optimizer.eye_states": 16})
    peak = budget.estimate_bytes(config.scene, 16, "kernel", "float64")
    with pytest.raises(ValueError) as refused:
        budget.check_budget(config.scene, config.optimizer, (1, 3, 3000, 3000),
                            budget_bytes=int(peak / 2))
    message = str(refused.value)
    assert f"about {peak / GB:.1f} GB" in message
    assert f"budget of {peak / 2 / GB:.1f} GB" in message
    assert "eye.view_pixels, now 3000 x 3000" in message
    assert "optimizer.eye_states, now 16" in message
    assert "plate.cells, now 80 x 80" in message
    assert "precision float32" in message
    assert budget.ENV_BUDGET_GB in message
    assert "views" in message  # the largest terms are named
    # Just enough budget: it passes.
    assert budget.check_budget(config.scene, config.optimizer, (1, 3, 3000, 3000),
                               budget_bytes=peak) == peak


def test_refusal_of_a_fixed_eye_float32_offers_no_eye_states_or_float32() -> None:
    config = _config("near-eye-nominal", **{"plate.cells": [5000, 5000]})
    with pytest.raises(ValueError) as refused:
        budget.check_budget(config.scene, config.optimizer, budget_bytes=10**6)
    message = str(refused.value)
    assert "plate.cells, now 5000 x 5000" in message
    assert "eye_states" not in message and "float32" not in message


def test_large_views_and_plates_against_this_machines_budget(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """3000 x 3000 views and 5000 x 5000 cells: the kernel path holds no pair table, so they
    take a few GB (refused only where that is more than the budget); the torch path (today's
    CUDA path without Triton) would need hundreds of GB for the view and is refused on an 80 GB
    GPU."""
    views = _config(**{"eye.view_pixels": [3000, 3000], "optimizer.eye_states": 16})
    cells = _config(**{"plate.cells": [5000, 5000], "optimizer.eye_states": 16})
    for config, low, high in ((views, 4, 20), (cells, 1, 6)):
        peak = budget.estimate_bytes(config.scene, 16, "kernel", "float32")
        assert low * GB < peak < high * GB
        limit, _ = budget.default_budget("cpu")
        if peak <= limit:
            assert budget.check_budget(config.scene, config.optimizer) == peak
        else:
            with pytest.raises(ValueError, match="GB of memory per optimizer iteration"):
                budget.check_budget(config.scene, config.optimizer)
    nominal = _config("near-eye-nominal", **{"eye.view_pixels": [3000, 3000]})
    # On CUDA the GPU kernels (triton) hold nothing per pair either; the torch path would not fit.
    assert budget.estimate_bytes(nominal.scene, 1, "triton", "float32") < 20 * GB
    assert budget.estimate_bytes(nominal.scene, 1, "torch", "float32") > 80 * GB
    with monkeypatch.context() as patch:
        patch.setattr(importlib.util, "find_spec", lambda name, *a: None)  # no triton here
        with pytest.raises(ValueError, match=r"torch renderer on cuda.*budget of 80\.0 GB"):
            budget.check_budget(nominal.scene, nominal.optimizer, device="cuda",
                                budget_bytes=int(80 * GB))


def test_default_budget_share_and_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(budget.ENV_BUDGET_GB, raising=False)
    available = budget.available_bytes("cpu")
    assert available > 0
    limit, why = budget.default_budget("cpu")
    assert limit == pytest.approx(budget.DEFAULT_SHARE * available, rel=0.05)
    assert "80%" in why
    monkeypatch.setenv(budget.ENV_BUDGET_GB, "2.5")
    assert budget.default_budget("cpu") == (int(2.5 * GB), f"set by {budget.ENV_BUDGET_GB}")
    monkeypatch.setenv(budget.ENV_BUDGET_GB, "lots")
    with pytest.raises(ValueError, match="positive number of GB"):
        budget.default_budget("cpu")


def test_optimize_refuses_before_any_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import aperture_fab.optimize.optimizer as optimize_module

    config = _config("seed")
    monkeypatch.setenv(budget.ENV_BUDGET_GB, "0.000001")
    targets = np.zeros((1, 1, 28, 28))
    with mock.patch.object(optimize_module, "Renderer") as renderer, \
            pytest.raises(ValueError, match=f"set by {budget.ENV_BUDGET_GB}"):
        optimize_module.optimize(config.scene, targets, targets, config.optimizer,
                                 progress=False)
    renderer.assert_not_called()


# -- the estimate against the peak RSS of optimize ------------------------------------------------

_PROBE = r"""
import functools, gc, json, sys
from unittest import mock
import numpy as np, torch
import aperture_fab.optimize.optimizer as om
from aperture_fab.optimize import budget
from aperture_fab.config.config import resolve
from aperture_fab.optics.model import Renderer

def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024

preset, overrides, backend = json.loads(sys.argv[1])
config = resolve(preset, None, {**overrides, "optimizer.device": "cpu",
                                "optimizer.iterations": 1, "optimizer.plateau_patience": 0})
scene, settings = config.scene, config.optimizer
rng = np.random.default_rng(0)
(nx, ny), (w, h) = scene.eye.view_pixels, scene.display.pixels
views, shown = rng.random((1, 3, ny, nx)), rng.random((1, 3, h, w))
factory = functools.partial(Renderer, backend=backend)
with mock.patch.object(om, "Renderer", factory):  # warm: kernels, thread pools, allocator
    small = resolve("near-eye-nominal", None, {"optimizer.device": "cpu",
                    "optimizer.iterations": 1, "eye.view_pixels": [8, 8]})
    om.optimize(small.scene, rng.random((1, 3, 8, 8)), rng.random((1, 3, 400, 400)),
                small.optimizer, progress=False)
    gc.collect()
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = status("VmRSS")
    om.optimize(scene, views, shown, settings, progress=False)
peak = status("VmHWM") - before
states = len(om.training_states(scene, settings, 0))
estimate = budget.estimate_bytes(scene, states, "kernel" if backend == "auto" else backend,
                                 settings.precision)
print(json.dumps({"measured": peak, "estimate": estimate}))
"""


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize(
    ("preset", "overrides", "backend"),
    [
        # Many cells (4 M): the per-cell terms.
        ("near-eye-nominal", {"plate.cells": [2000, 2000], "plate.pitch_mm": 0.01,
                              "eye.view_pixels": [32, 32], "eye.pupil_mm": 0.5}, "auto"),
        # A large display: the stack, its FFTs and the per-thread grad stacks.
        ("near-eye-nominal", {"display.pixels": [800, 800], "eye.view_pixels": [48, 48]},
         "auto"),
        # Many views and states (small pupils keep it quick): the views and their gradient.
        ("near-eye", {"eye.view_pixels": [800, 800], "eye.pupil_range_mm": [0.5, 1.0],
                      "eye.pupil_mm": 1.0, "eye.focus_range_diopters": "nominal",
                      "optimizer.eye_states": 4}, "auto"),
        # The torch path: pair tables and what autograd keeps per pair.
        ("near-eye-nominal", {"eye.view_pixels": [96, 96]}, "torch"),
    ],
    ids=["cells", "display", "views", "torch"],
)
def test_estimate_within_a_factor_of_peak_rss(preset: str, overrides: dict[str, object],
                                              backend: str) -> None:
    done = subprocess.run([sys.executable, "-c", _PROBE,
                           json.dumps([preset, overrides, backend])],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    measured, estimate = figures["measured"], figures["estimate"]
    assert measured > 150 * 2**20, figures  # big enough to judge the model by
    assert 0.5 <= estimate / measured <= 2.0, figures
