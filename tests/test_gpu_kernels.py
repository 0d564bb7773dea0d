"""The fused GPU kernels (aperture_fab.optics.gpu_kernels) against the fused CPU kernels: views
and gradients (radii and display), for eye states that share their display samples (all at
infinity) and states that do not, with displaced holes, tilted hole axes, display-side optics
and a float32 stack.

Without CUDA the kernels run in Triton's interpreter (TRITON_INTERPRET=1, set here before the
module is imported, as Triton reads it then) on small scenes; on a machine with CUDA they are
compiled and run there, and larger scenes are compared too. Triton is not a dependency of the
CPU install: where it is missing these tests skip, unless APERTURE_FAB_REQUIRE_TRITON=1 (set by
.ci/run, which installs it) makes that a failure.
"""

from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest
import torch
from test_display_optics import with_display
from test_kernels import states, views_and_grads
from test_model import make_scene

from aperture_fab.optics.model import Renderer

CUDA = torch.cuda.is_available()
if not CUDA:
    os.environ.setdefault("TRITON_INTERPRET", "1")
if importlib.util.find_spec("triton") is None:
    if os.environ.get("APERTURE_FAB_REQUIRE_TRITON") == "1":
        raise ImportError("triton is not installed, and APERTURE_FAB_REQUIRE_TRITON=1 asks for "
                          "these tests: pip install triton==3.6.0")
    pytest.skip("triton is not installed (pip install triton==3.6.0 runs these tests on the "
                "CPU in its interpreter)", allow_module_level=True)

DEVICE = "cuda" if CUDA else "cpu"
#: Small enough for the interpreter: a 1 mm pupil over 0.25 mm cells walks about 6 x 6 holes.
SMALL = {"cells": (8, 8), "pupil": 1.0, "view": (8, 8), "pixels": (40, 40), "size": 10.0}
CASES = {
    "thin straight": {},
    "thick chief-ray": {"thickness": 0.3, "axis": "chief_ray"},
    "thick straight, finite focus": {"thickness": 0.2, "focus": 500.0},
}
BATCHES = {
    "infinity": ([(0.0, 0.0), (0.3, -0.2), (-0.4, 0.3)], [1.0, 0.8, 1.4], [0.0, 0.0, 0.0]),
    "mixed focus": ([(0.0, 0.0), (0.2, 0.1)], [1.0, 1.2], [0.0, 1.5]),
}
DISPLAY_OPTICS = {"cover_glass_mm": 0.5, "emission": "cosine_power", "emission_exponent": 4.0}


def compare(scene, batch, offsets, dtype=torch.float64, rtol=1e-9, seed=3, sparse=False,
            reference="kernel", dead=()):
    """The triton backend against `reference` ("kernel": the CPU kernels; "torch": the pair
    tables and grid_sample, on this test's device); the states `dead` get no gradient."""
    rng = np.random.default_rng(seed)
    rows, cols = scene.plate.cells[1], scene.plate.cells[0]
    a = rng.uniform(0, 0.6, (rows, cols))
    if sparse:  # most cells closed, as a made plate
        a = np.where(rng.random((rows, cols)) < 0.3, a, 0.0)
    pixels = scene.display.pixels
    display = rng.random((3, pixels[1], pixels[0]))
    view = scene.eye.view_pixels
    weight = rng.random((len(batch), 3, view[1], view[0]))
    weight[list(dead)] = 0.0
    got = views_and_grads(Renderer(scene, device=DEVICE, dtype=dtype, backend="triton",
                                   hole_offset_mm=offsets), a.astype(np.float64),
                          display, batch, weight)
    where = DEVICE if reference == "torch" else "cpu"
    want = views_and_grads(Renderer(scene, device=where, dtype=dtype, backend=reference,
                                    hole_offset_mm=offsets), a, display, batch, weight)
    assert float(want[0].abs().max()) > 0
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g.cpu(), w, rtol=rtol, atol=rtol * float(w.abs().max()))


@pytest.mark.slow
@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("case", ["thin straight", "thick chief-ray"])
def test_gpu_kernels_match_the_cpu_kernels(case, batch_name):
    compare(make_scene(**SMALL, **CASES[case]), states(*BATCHES[batch_name]), None)


@pytest.mark.slow
@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("displaced", [False, True])
@pytest.mark.parametrize("optics", [False, True])
def test_gpu_kernels_match_the_cpu_kernels_in_every_case(case, batch_name, displaced, optics):
    scene = make_scene(**SMALL, **CASES[case])
    if optics:
        scene = with_display(scene, **DISPLAY_OPTICS)
    offsets = np.random.default_rng(4).normal(0, 0.05, (8, 8, 2)) if displaced else None
    compare(scene, states(*BATCHES[batch_name]), offsets)


def test_gpu_kernels_with_display_optics_and_displaced_holes():
    scene = with_display(make_scene(**SMALL, thickness=0.3, axis="chief_ray"), **DISPLAY_OPTICS)
    offsets = np.random.default_rng(4).normal(0, 0.05, (8, 8, 2))
    compare(scene, states(*BATCHES["mixed focus"]), offsets)


@pytest.mark.parametrize("batch_name, dead", [("infinity", (1,)), ("infinity", (0, 1, 2)),
                                              ("mixed focus", (0,)), ("mixed focus", (0, 1))])
def test_gpu_kernels_leave_states_without_gradient_out(batch_name, dead):
    """The backward walks only the states whose views get a gradient (a tail loss's best ones
    get none; the kernels read which on the device), with the torch path's gradients (none
    left: zero)."""
    compare(make_scene(**SMALL), states(*BATCHES[batch_name]), None, reference="torch",
            dead=dead)


def test_gpu_kernels_in_float32_on_a_sparse_plate():
    """A float32 stack read as float32, sums in float64: the CPU kernels' figures to float32
    rounding; most cells closed."""
    compare(make_scene(**SMALL), states(*BATCHES["infinity"]), None, dtype=torch.float32,
            rtol=1e-5, sparse=True)


@pytest.mark.skipif(not CUDA, reason="compiled Triton kernels need CUDA")
@pytest.mark.parametrize("reference", ["kernel", "torch"])
@pytest.mark.parametrize("batch_name", list(BATCHES))
def test_gpu_kernels_match_on_a_full_size_plate(batch_name, reference):
    """The default scene's sizes (80 x 80 cells, 4 mm pupil, 128 x 128 view), on the GPU,
    against the CPU kernels and against the torch path on the same GPU."""
    scene = make_scene(cells=(80, 80), pupil=4.0, view=(128, 128), pixels=(400, 400), size=20.0,
                       thickness=0.3, axis="chief_ray")
    compare(scene, states(*BATCHES[batch_name]), None, reference=reference,
            rtol=1e-8 if reference == "kernel" else 1e-7)  # the torch path: as tests/test_kernels


def test_moved_holes_are_walked_where_they_moved():
    """`with_hole_offsets` on a renderer that has rendered: the device copy of the offsets is
    the new one (the triton path keeps its fixed inputs on the device)."""
    scene = make_scene(**SMALL)
    rng = np.random.default_rng(5)
    a = torch.as_tensor(rng.uniform(0, 0.6, (8, 8)), device=DEVICE)
    display = torch.as_tensor(rng.random((3, 40, 40)), device=DEVICE)
    offsets = rng.normal(0, 0.05, (8, 8, 2))
    first = Renderer(scene, device=DEVICE, dtype=torch.float64, backend="triton")
    still = first.render(a, display)
    moved = first.with_hole_offsets(offsets).render(a, display)
    fresh = Renderer(scene, device=DEVICE, dtype=torch.float64, backend="triton",
                     hole_offset_mm=offsets).render(a, display)
    torch.testing.assert_close(moved, fresh, rtol=1e-12, atol=0.0)
    assert not torch.allclose(moved, still)


def test_backend_triton_is_refused_where_it_cannot_run(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    if CUDA:
        pytest.skip("CUDA is present: backend triton runs here")
    with pytest.raises(ValueError, match="backend 'triton' runs on CUDA"):
        Renderer(make_scene(**SMALL), backend="triton")


#: Compiles kernel variants for a Hopper GPU (sm_90) with Triton's own ptxas: no GPU needed.
COMPILE = """
import sys
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from aperture_fab.optics import gpu_kernels as g

common = {"radius_ptr": "*fp64", "offsets_ptr": "*fp64", "stack_ptr": sys.argv[1],
          "vx_ptr": "*fp64", "vy_ptr": "*fp64", "states_ptr": "*fp64", "geom_ptr": "*fp64",
          "margin_ptr": "*fp64"}
sizes = {"closed": "fp64", "nx": "i32", "ny": "i32", "L": "i32", "H": "i32", "W": "i32"}
shared, optics = sys.argv[2] == "shared", sys.argv[3] == "optics"
flags = {"C": 3, "CP": 4, "BLOCK": g.BLOCK, "SHARED": shared, "OPTICS": optics}
forward = {**common, "out_ptr": "*fp64", "extra": "fp64", **sizes,
           **{k: "constexpr" for k in flags}}
backward = {**common, "alive_ptr": "*i32", "grad_out_ptr": "*fp64", "grad_radius_ptr": "*fp64",
            "grad_stack_ptr": "*fp64", "extra": "fp64", **sizes, "n_states": "i32",
            **{k: "constexpr" for k in [*flags, "WANT_STACK"]}}
target = GPUTarget("cuda", 90, 32)
for kernel, signature, constants in ((g.forward_kernel, forward, flags),
                                     (g.backward_kernel, backward,
                                      {**flags, "WANT_STACK": True})):
    triton.compile(ASTSource(kernel, signature, constexprs=constants), target=target,
                   options={"num_warps": g.NUM_WARPS})
print("compiled")
"""


@pytest.mark.slow
@pytest.mark.parametrize("stack, shared, optics", [("*fp32", "shared", "plain"),
                                                   ("*fp64", "focused", "optics")])
def test_the_kernels_compile_for_a_hopper_gpu(stack, shared, optics, tmp_path):
    """What the interpreter cannot check (Triton's compile-time rules: constexpr globals,
    types, the libdevice calls) is checked by compiling for sm_90 here, without a GPU."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_CACHE_DIR"] = str(tmp_path)  # compile afresh, never from an earlier run
    done = subprocess.run([sys.executable, "-c", COMPILE, stack, shared, optics], env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0 and "compiled" in done.stdout, done.stderr[-3000:]


@pytest.mark.parametrize("plate", [{}, {"thickness": 0.03, "axis": "chief_ray"}])
def test_gpu_kernels_read_a_stack_of_the_upper_levels(plate):
    """A renderer for holes of at least min_radius_mm (`Renderer`): its stack holds only the
    upper levels, which the kernels reach through the level offset; the CPU kernels' views and
    gradients, holes from that size up on a display fine enough for several levels."""
    scene = make_scene(**{**SMALL, "pixels": (160, 160)}, **plate)
    rng = np.random.default_rng(5)
    a = np.pi * rng.uniform(0.1, 0.12, (8, 8)) ** 2 / 0.0625  # 0.25 mm cells
    display = rng.random((3, 160, 160))
    batch = states(*BATCHES["infinity"])
    weight = rng.random((len(batch), 3, 8, 8))
    got, want = (views_and_grads(Renderer(scene, device=where, dtype=torch.float64,
                                          backend=backend, max_radius_mm=0.12,
                                          min_radius_mm=0.1), a, display, batch, weight)
                 for where, backend in ((DEVICE, "triton"), ("cpu", "kernel")))
    assert Renderer(scene, max_radius_mm=0.12, min_radius_mm=0.1).first_level > 0
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g.cpu(), w, rtol=1e-9, atol=1e-9 * float(w.abs().max()))
