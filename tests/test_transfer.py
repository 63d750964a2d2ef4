"""kernels.transfer.to_host: the same values as ``numpy()``, on every path."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from warp_highlights.kernels.transfer import rows_down, rows_up, to_host

from warp_highlights.model import threads


@pytest.mark.parametrize("dtype", [wp.float32, wp.float16, wp.int32])
@pytest.mark.parametrize("cores", [1, 4])
def test_to_host_gives_numpy_s_values(device, monkeypatch, dtype, cores):
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 1024)  # the threaded path for a small array too
    monkeypatch.setattr(threads, "NUMPY_THREADS", cores)
    values = np.random.default_rng(2).normal(size=(7, 33, 5)) * 100
    array = wp.array(values.astype(wp.dtype_to_numpy(dtype)), dtype=dtype, device=device)
    host = to_host(array)
    assert isinstance(host, np.ndarray) and host.dtype == wp.dtype_to_numpy(dtype) and host.shape == (7, 33, 5)
    assert host.tobytes() == array.numpy().tobytes()


def test_to_host_of_vectors_views_and_numpy_input(device, monkeypatch):
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 16)
    vectors = wp.array(np.arange(30, dtype=np.float32).reshape(10, 3), dtype=wp.vec3, device=device)
    np.testing.assert_array_equal(to_host(vectors), vectors.numpy())  # not a scalar type: numpy() as it is
    stack = wp.array(np.arange(60, dtype=np.float32).reshape(6, 10), dtype=float, device=device)
    strided = stack[:, 2:5]
    np.testing.assert_array_equal(to_host(strided), strided.numpy())  # not contiguous: numpy() as it is
    plain = np.ones(3)
    assert to_host(plain) is plain


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_rows_up_and_down_a_band_of_a_stack(device, dtype):
    """A band of rows of an (n, H, W, C) stack (each image's rows one run of memory) up to a contiguous
    device array and back into another stack's band, value for value; the whole stack in one copy."""
    stack = np.random.default_rng(4).normal(size=(5, 9, 4, 3)).astype(dtype)
    band = stack[:, 2:6]
    assert not band.flags.c_contiguous
    there = rows_up(band, device)
    assert there.shape == band.shape and there.is_contiguous
    np.testing.assert_array_equal(there.numpy(), band)
    back = np.zeros_like(stack)
    rows_down(there, back[:, 2:6])
    np.testing.assert_array_equal(back[:, 2:6], band)
    assert not back[:, :2].any() and not back[:, 6:].any()
    np.testing.assert_array_equal(rows_down(rows_up(stack, device), np.empty_like(stack)), stack)
    with pytest.raises(ValueError, match="cannot come down"):
        rows_down(there, np.empty((5, 3, 4, 3), dtype))
    with pytest.raises(ValueError, match="contiguous"):
        rows_down(rows_up(stack[:, :, :2], device), np.empty_like(stack)[:, :, :2])
