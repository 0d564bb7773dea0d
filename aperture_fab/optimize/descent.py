"""Adam and SGD steps for the design and fit loops, without `torch.optim`.

`torch.optim`'s optimizers import `torch._dynamo` on their first use (its `_disable_dynamo`
wrapper), about 1 s on 2 cores: a fifth of a small design's wall time and of every CLI process
that optimizes. These take the same steps, operation for operation, as torch.optim's
single-tensor Adam and SGD with default options (no weight decay, amsgrad, Nesterov or
dampening), so a design is bit-identical either way on the CPU (tests/test_descent.py compares
them); on CUDA torch.optim would take its multi-tensor form, the same arithmetic. Their
`state_dict` has torch.optim's layout, so a checkpoint written by either resumes with the other.
A parameter whose `.grad` is None is skipped, as torch.optim skips it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["Adam", "SGD", "Stepper"]

#: torch.optim.Adam's defaults.
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8


class _Steps:
    """What the loops use of a torch.optim optimizer: `lr`, `zero_grad`, `step`, `state_dict`
    and `load_state_dict`."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float) -> None:
        if not (isinstance(lr, (int, float)) and lr > 0):
            raise ValueError(f"lr = {lr!r} must be a number > 0 (the step size).")
        self.params = list(params)
        self.lr = float(lr)
        self.state: list[dict[str, Any]] = [{} for _ in self.params]

    def zero_grad(self) -> None:
        """Drop every parameter's gradient (torch.optim's set_to_none=True)."""
        for p in self.params:
            p.grad = None

    def _group(self) -> dict[str, Any]:
        return {"lr": self.lr}

    def state_dict(self) -> dict[str, Any]:
        """torch.optim's layout: {"state": {index: {...}}, "param_groups": [{..., "params"}]}
        (the state's tensors themselves, not copies)."""
        return {"state": {i: dict(s) for i, s in enumerate(self.state) if s},
                "param_groups": [{**self._group(), "params": list(range(len(self.params)))}]}

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """Take `state_dict` output (ours or torch.optim's), its tensors copied onto each
        parameter's device and dtype (the step count keeps its own)."""
        entries = saved["state"]
        for i, p in enumerate(self.params):
            entry = entries.get(i, {})
            self.state[i] = {key: (value if value is None else value.clone() if key == "step"
                                   else value.to(p.device, p.dtype, copy=True))
                             for key, value in entry.items()}
        self.lr = float(saved["param_groups"][0]["lr"])


class Adam(_Steps):
    """torch.optim.Adam(params, lr) with its defaults, step for step."""

    def _group(self) -> dict[str, Any]:
        return {"lr": self.lr, "betas": ADAM_BETAS, "eps": ADAM_EPS, "weight_decay": 0,
                "amsgrad": False, "maximize": False}

    @torch.no_grad()
    def step(self) -> None:
        beta1, beta2 = ADAM_BETAS
        for p, state in zip(self.params, self.state, strict=True):
            grad = p.grad
            if grad is None:
                continue
            if not state:
                # A tensor on the CPU, as torch keeps it (checkpoints match).
                state["step"] = torch.tensor(0.0, dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            step_t, exp_avg, exp_avg_sq = state["step"], state["exp_avg"], state["exp_avg_sq"]
            step_t += 1
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step = step_t.item()
            step_size = self.lr / (1 - beta1**step)
            denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(ADAM_EPS)
            p.addcdiv_(exp_avg, denom, value=-step_size)


class SGD(_Steps):
    """torch.optim.SGD(params, lr, momentum) with its other defaults, step for step."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float, momentum: float = 0.0) -> None:
        super().__init__(params, lr)
        if not (isinstance(momentum, (int, float)) and 0 <= momentum < 1):
            raise ValueError(f"momentum = {momentum!r} must be a number in [0, 1).")
        self.momentum = float(momentum)

    def _group(self) -> dict[str, Any]:
        return {"lr": self.lr, "momentum": self.momentum, "dampening": 0, "weight_decay": 0,
                "nesterov": False, "maximize": False}

    @torch.no_grad()
    def step(self) -> None:
        for p, state in zip(self.params, self.state, strict=True):
            grad = p.grad
            if grad is None:
                continue
            if self.momentum != 0:
                buf = state.get("momentum_buffer")
                if buf is None:
                    buf = state["momentum_buffer"] = grad.detach().clone()
                else:
                    buf.mul_(self.momentum).add_(grad, alpha=1)
                grad = buf
            p.add_(grad, alpha=-self.lr)


#: Either step rule.
Stepper = Adam | SGD
