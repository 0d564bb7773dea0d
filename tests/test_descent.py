"""aperture_fab.optimize.descent: the same steps as torch.optim, without importing torch._dynamo."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from aperture_fab.optimize.descent import SGD, Adam

STEPS = 25


def _params(dtype: torch.dtype) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    return [torch.rand(5, 7, generator=gen, dtype=dtype).requires_grad_(True),
            torch.rand(3, 4, 4, generator=gen, dtype=dtype).requires_grad_(True)]


def _ours(kind: str, params: list[torch.Tensor]) -> Adam | SGD:
    return Adam(params, lr=0.05) if kind == "adam" else SGD(params, lr=0.05,
                                                             momentum=float(kind[4:]))


def _theirs(kind: str, params: list[torch.Tensor]) -> torch.optim.Optimizer:
    if kind == "adam":
        return torch.optim.Adam(params, lr=0.05)
    return torch.optim.SGD(params, lr=0.05, momentum=float(kind[4:]))


def _run(opt, params: list[torch.Tensor], steps: range, ours: bool) -> None:
    """Steps with a changing rate, random gradients, and the second parameter's gradient
    left out now and then (a frozen plate)."""
    for k in steps:
        gen = torch.Generator().manual_seed(100 + k)
        lr = 0.05 * (1 + k % 3) / 3
        if ours:
            opt.lr = lr
            opt.zero_grad()
        else:
            for group in opt.param_groups:
                group["lr"] = lr
            opt.zero_grad(set_to_none=True)
        for i, p in enumerate(params):
            if i == 0 or k % 4 != 3:
                p.grad = torch.randn(p.shape, generator=gen, dtype=p.dtype)
        opt.step()


@pytest.mark.parametrize("kind", ["adam", "sgd 0.9", "sgd 0.0"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_steps_match_torch_optim_bit_for_bit(kind: str, dtype: torch.dtype) -> None:
    ours_p, theirs_p = _params(dtype), _params(dtype)
    ours, theirs = _ours(kind, ours_p), _theirs(kind, theirs_p)
    _run(ours, ours_p, range(STEPS), True)
    _run(theirs, theirs_p, range(STEPS), False)
    for a, b in zip(ours_p, theirs_p, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["adam", "sgd 0.9"])
@pytest.mark.parametrize("direction", ["torch to ours", "ours to torch"])
def test_a_checkpoint_resumes_across_implementations(kind: str, direction: str) -> None:
    """state_dict has torch.optim's layout: a run stopped under one and resumed under the
    other takes the steps an unbroken run takes."""
    whole_p = _params(torch.float64)
    whole = _theirs(kind, whole_p)
    _run(whole, whole_p, range(STEPS), False)
    first_p = _params(torch.float64)
    first_ours = direction == "ours to torch"
    first = _ours(kind, first_p) if first_ours else _theirs(kind, first_p)
    _run(first, first_p, range(10), first_ours)
    saved = first.state_dict()
    second_p = [p.detach().clone().requires_grad_(True) for p in first_p]
    second = _theirs(kind, second_p) if first_ours else _ours(kind, second_p)
    second.load_state_dict(saved)
    _run(second, second_p, range(10, STEPS), not first_ours)
    for a, b in zip(second_p, whole_p, strict=True):
        assert torch.equal(a, b)


def test_loading_copies_the_saved_state() -> None:
    """A checkpoint stays valid to resume from again: stepping does not change it."""
    params = _params(torch.float64)
    opt = Adam(params, lr=0.05)
    _run(opt, params, range(3), True)
    saved = {"state": {i: {k: v.clone() for k, v in s.items()} for i, s in
                       opt.state_dict()["state"].items()},
             "param_groups": opt.state_dict()["param_groups"]}
    again = Adam(params, lr=0.05)
    again.load_state_dict(saved)
    before = {k: v.clone() for k, v in saved["state"][0].items()}
    _run(again, params, range(3, 6), True)
    assert all(torch.equal(saved["state"][0][k], before[k]) for k in before)


@pytest.mark.parametrize("bad", [0.0, -1.0, "0.1"])
def test_a_bad_rate_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="lr"):
        Adam(_params(torch.float32), lr=bad)  # type: ignore[arg-type]


def test_stepping_does_not_import_dynamo() -> None:
    """The reason for the module: torch.optim imports torch._dynamo (about 1 s) on first use."""
    code = ("import sys, torch\n"
            "from aperture_fab.optimize.descent import Adam, SGD\n"
            "for opt_type in (Adam, SGD):\n"
            "    p = torch.zeros(3, requires_grad=True)\n"
            "    opt = opt_type([p], lr=0.1)\n"
            "    (p * p).sum().backward()\n"
            "    opt.step()\n"
            "    opt.load_state_dict(opt.state_dict())\n"
            "assert 'torch._dynamo' not in sys.modules, 'torch._dynamo was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
