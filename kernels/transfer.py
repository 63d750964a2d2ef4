"""Large device arrays to host memory at the copy's speed.

``wp.array.numpy()`` copies a CUDA array into a fresh NumPy array, and the copy then stops at every
page of it the first time it writes there (the kernel maps the page): on the lent H100's host, 6.2 GB
of a 250-light 1920x1080 specular stack came down in 5.0 s. ``to_host`` first writes every page of
the new array from threads, which the kernel maps in parallel, then copies into it: 0.17 + 0.59 s.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model import threads

__all__ = ["to_host"]


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
