"""Shared fixtures: a tiny scene so design, optimize and CLI tests run in a fraction of a second.

TINY is a 4 x 4 mm display of 32 x 32 pixels behind a 16 x 16 plate of 0.25 mm cells, seen on a
16 x 16 view, on the CPU, for a handful of iterations, without the preset's light floor, from
the nominal eye point (preset near-eye-nominal; tiny_config("near-eye") samples the eye
distribution), its plate kept (optimizer.lattice = "fixed"). Its overrides use the
dotted keys of `aperture_fab.config.config.resolve`; TINY_TOML is the same as a config file for the
CLI. Modules that run the optimizer use `pytestmark = pytest.mark.usefixtures("one_torch_thread")`.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from aperture_fab.config.config import Config, resolve
from aperture_fab.io.images import encode_png
from aperture_fab.pipeline.judged_folder import ENV_CACHE_DIR, OFF
from aperture_fab.targets import asymmetric_marker, pixel_art

# Tests judge afresh: a judgement kept by another test (or by the user's runs) would hide what
# the code under test does. tests/test_judged_cache.py turns the cache on where it tests it.
os.environ[ENV_CACHE_DIR] = OFF

TINY_ITERATIONS = 8

TINY: dict[str, Any] = {
    "display.width_mm": 4.0,
    "display.height_mm": 4.0,
    "display.pixels": [32, 32],
    "plate.cells": [16, 16],
    "plate.pitch_mm": 0.25,
    "eye.view_pixels": [16, 16],
    "optimizer.iterations": TINY_ITERATIONS,
    "optimizer.device": "cpu",
    # The plain image loss: the preset's light floor has its own tests (test_brightness_floor).
    "optimizer.min_efficiency": 0.0,
    # The plate as given: a regular array beats a tiny part, and the design job would design
    # again on its lattice (tested in test_made_part).
    "optimizer.lattice": "fixed",
}

TINY_TOML = f"""\
preset = "near-eye-nominal"

[display]
width_mm = 4.0
height_mm = 4.0
pixels = [32, 32]

[plate]
cells = [16, 16]
pitch_mm = 0.25

[eye]
view_pixels = [16, 16]

[optimizer]
iterations = {TINY_ITERATIONS}
device = "cpu"
min_efficiency = 0.0
lattice = "fixed"
"""


def require_tool(*names: str, install: str) -> str:
    """The path of the first of `names` on PATH (or an absolute path that exists). Where none
    is, the test skips, saying how to install it, unless APERTURE_FAB_REQUIRE_TOOLS=1 (set by
    .ci/run once it has installed them), which makes a missing tool a failure."""
    for name in names:
        found = shutil.which(name) or (name if Path(name).is_absolute() and Path(name).exists()
                                       else None)
        if found:
            return found
    message = f"{names[0]} is not installed ({install})"
    if os.environ.get("APERTURE_FAB_REQUIRE_TOOLS") == "1":
        pytest.fail(message + "; APERTURE_FAB_REQUIRE_TOOLS=1 requires it")
    pytest.skip(message)


def tiny_config(preset: str = "near-eye-nominal", **overrides: Any) -> Config:
    """A near-eye preset shrunk to TINY, with extra dotted-key overrides on top: by default the
    nominal-point one (one eye state per iteration); "near-eye" samples the eye distribution."""
    eyebox = {"eye.eyebox_mm": 2.0} if preset == "near-eye" else {}  # the display is 4 mm
    return resolve(preset, overrides={**TINY, **eyebox, **overrides})


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Run torch on one thread, then restore: tiny scenes gain nothing from more, and on a busy
    machine OpenMP threads that wait for each other make them many times slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def make_config() -> Callable[..., Config]:
    """tiny_config as a fixture: make_config(**{"optimizer.iterations": 3})."""
    return tiny_config


@pytest.fixture
def marker() -> np.ndarray:
    """A grey target (3, 32, 32): the letter F, which no flip maps onto itself."""
    return asymmetric_marker(32)


@pytest.fixture
def colour() -> np.ndarray:
    """A colour target (3, 32, 32): pixel art."""
    return pixel_art(32)


@pytest.fixture
def marker_png(tmp_path: Path) -> Path:
    """The grey marker as an sRGB PNG file."""
    path = tmp_path / "marker.png"
    path.write_bytes(encode_png(asymmetric_marker(32)))
    return path


@pytest.fixture
def tiny_toml(tmp_path: Path) -> Path:
    """TINY as a TOML config file."""
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_TOML)
    return path


def design_tiny(folder: Path, *flags: str) -> int:
    """Write tiny.toml and marker.png into `folder` and run `aperture-fab design` on them with
    `flags` (an --out among them), torch on one thread; the exit status."""
    from aperture_fab.cli import main

    (folder / "tiny.toml").write_text(TINY_TOML)
    (folder / "marker.png").write_bytes(encode_png(asymmetric_marker(32)))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return main(["design", str(folder / "marker.png"), "--config", str(folder / "tiny.toml"),
                     *flags])
    finally:
        torch.set_num_threads(threads)


def interrupt_at_call(monkeypatch: pytest.MonkeyPatch, n: int) -> None:
    """Make the optimizer's n-th loss evaluation raise KeyboardInterrupt (as Ctrl-C would)."""
    import aperture_fab.optimize.optimizer as optimize_module

    calls = {"n": 0}
    real = optimize_module.gain_mse_states

    def interrupted(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return real(view, target)

    monkeypatch.setattr(optimize_module, "gain_mse_states", interrupted)


@pytest.fixture(scope="module")
def designed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A tiny design's folder (design.npz, design.toml, holes.csv, plate.stl) and marker.png,
    made once per test module through the command line."""
    folder = tmp_path_factory.mktemp("designed")
    assert design_tiny(folder, "--out", str(folder / "plate.stl"), "--no-validate",
                       "--quiet") == 0
    yield folder
