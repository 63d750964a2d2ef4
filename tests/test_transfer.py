"""kernels.transfer.to_host: the same values as ``numpy()``, on every path."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from warp_highlights.kernels.transfer import to_host

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
