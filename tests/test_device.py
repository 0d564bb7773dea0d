"""aperture_fab.optics.device: the config's device and precision names, and host-to-device
copies that do not wait for a GPU's queue."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from aperture_fab.optics.device import resolve_device, to_device, torch_dtype


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_to_device_copies_host_values_contiguously_in_the_dtype(dtype):
    strided = np.arange(16.0).reshape(4, 4)[:, ::2]  # a view the kernels could not read
    copied = to_device(strided, dtype, torch.device("cpu"))
    assert copied.dtype == dtype and copied.is_contiguous()
    assert np.array_equal(copied.numpy(), strided.astype(copied.numpy().dtype))
    assert to_device([0.25, 0.75], dtype, torch.device("cpu")).tolist() == [0.25, 0.75]


def test_to_device_copies_a_read_only_array():
    """torch would share it and warn the user that writing to the tensor is undefined."""
    frozen = np.arange(4.0)
    frozen.flags.writeable = False
    tensor = to_device(frozen, torch.float64, torch.device("cpu"))
    assert not np.shares_memory(tensor.numpy(), frozen)
    torch.testing.assert_close(tensor, torch.arange(4.0, dtype=torch.float64))
    writable = np.arange(4.0)  # shared, as before: no copy for the common case
    assert np.shares_memory(to_device(writable, torch.float64, torch.device("cpu")).numpy(),
                            writable)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_to_device_reaches_the_gpu_without_a_blocking_copy():
    torch.cuda.set_sync_debug_mode("error")  # a synchronizing copy raises
    try:
        copied = to_device(np.arange(8.0), torch.float64, torch.device("cuda"))
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert copied.cpu().tolist() == list(np.arange(8.0))


def test_device_and_precision_names():
    assert resolve_device("cpu") == torch.device("cpu")
    assert torch_dtype("float64") is torch.float64 and torch_dtype("float32") is torch.float32
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")
