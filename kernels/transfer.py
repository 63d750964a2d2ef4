"""Large arrays between host and device memory at the copy's speed.

``wp.array.numpy()`` copies a CUDA array into a fresh NumPy array, and the copy then stops at every
page of it the first time it writes there (the kernel maps the page): on the lent H100's host, 6.2 GB
of a 250-light 1920x1080 specular stack came down in 5.0 s. ``to_host`` first writes every page of
the new array from threads, which the kernel maps in parallel, then copies into it: 0.17 + 0.59 s.

A band of rows of an (n, H, W[, C]) stack is n separate runs of host memory: ``rows_up`` and
``rows_down`` copy each run straight between host and device memory (no contiguous copy of the band
on the host first; the lent H100's host copied 9.4 GB/s so from pageable memory).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model import threads

__all__ = ["rows_down", "rows_up", "to_host"]


def to_host(array) -> np.ndarray:
    """A Warp array as a NumPy array in host memory (a CPU array's own view, as ``numpy()`` gives it).
    A large contiguous CUDA array of a scalar type is copied into pages written from threads first
    (``mapped_empty``)."""
    if not isinstance(array, wp.array):
        return np.asarray(array)
    if not array.device.is_cuda or not wp.types.type_is_scalar(array.dtype) or not array.is_contiguous \
            or array.capacity < threads.PREFAULT_BYTES or threads.NUMPY_THREADS == 1:
        return array.numpy()
    host = threads.mapped_empty(array.shape, wp.dtype_to_numpy(array.dtype))
    wp.copy(wp.array(host, dtype=array.dtype, device="cpu", copy=False), array)
    return host


def rows_up(host: np.ndarray, device) -> wp.array:
    """An (n, ...) host array (a band of a stack will do: each ``host[i]`` contiguous) as a new
    contiguous array on ``device``, of the same scalar type: one copy per ``host[i]``, or one for all
    where the whole is contiguous."""
    host = np.asarray(host)
    kind = wp.dtype_from_numpy(host.dtype)
    out = wp.empty(host.shape, dtype=kind, device=device)
    if host.flags.c_contiguous or len(host) == 0:
        wp.copy(out, wp.array(np.ascontiguousarray(host), dtype=kind, device="cpu", copy=False))
        return out
    for i in range(len(host)):
        wp.copy(out[i], wp.array(np.ascontiguousarray(host[i]), dtype=kind, device="cpu", copy=False))
    return out


def rows_down(array: wp.array, out: np.ndarray) -> np.ndarray:
    """Copy a contiguous (n, ...) device array into the host array ``out`` of its shape and type (a band
    of a stack will do: each ``out[i]`` contiguous), a copy per ``out[i]``; returns ``out``. Copies into
    pages not written yet stop at each: give ``out`` from ``mapped_empty``."""
    if tuple(out.shape) != tuple(array.shape) or out.dtype != wp.dtype_to_numpy(array.dtype) or not array.is_contiguous:
        raise ValueError(f"a contiguous {array.dtype.__name__} {array.shape} array cannot come down into {out.dtype} {out.shape}")
    if out.flags.c_contiguous or len(out) == 0:
        wp.copy(wp.array(out, dtype=array.dtype, device="cpu", copy=False), array)
        wp.synchronize_device(array.device)
        return out
    if not out[0].flags.c_contiguous:  # the rows share their strides: one is all of them
        raise ValueError("each row of the host array must be contiguous")
    for i in range(len(out)):
        wp.copy(wp.array(out[i], dtype=array.dtype, device="cpu", copy=False), array[i])
    wp.synchronize_device(array.device)
    return out
