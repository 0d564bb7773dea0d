"""Where and in what precision tensors live: the config's device and precision names as torch
objects, looked up in one place."""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

__all__ = ["Precision", "resolve_device", "to_device", "torch_dtype"]

Precision = Literal["float32", "float64"]


def resolve_device(name: str | torch.device) -> torch.device:
    """"auto" (CUDA when present, else the CPU), "cpu", "cuda" or "cuda:N"."""
    if isinstance(name, torch.device):
        return name
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device = {name!r} was asked for but CUDA is not available here; "
                         "use --device cpu or auto.")
    return torch.device(name)


def torch_dtype(precision: Precision) -> torch.dtype:
    """The torch dtype of optimizer.precision."""
    return torch.float64 if precision == "float64" else torch.float32


def to_device(values: np.ndarray | list[float], dtype: torch.dtype, device: torch.device
              ) -> torch.Tensor:
    """Host values as a tensor on `device`, copied without waiting for its queue: a plain copy
    to a GPU from pageable memory first waits for every queued kernel, leaving the GPU idle
    while the host catches up (pinned memory copies asynchronously; PyTorch's host allocator
    keeps the pinned block until the copy is done)."""
    array = np.ascontiguousarray(values)
    if not array.flags.writeable:
        # torch would share a read-only array (a frozen value's) and warn, to the user, that
        # writing to the tensor is undefined: copy it, it is small.
        array = array.copy()
    tensor = torch.as_tensor(array, dtype=dtype)
    if device.type != "cuda":
        return tensor.to(device)
    return tensor.pin_memory().to(device, non_blocking=True)
