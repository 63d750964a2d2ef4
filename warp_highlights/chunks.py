"""Splitting a batch of independent problems over CPU threads.

Warp runs each CPU launch on one thread (and releases the GIL while it runs), so a batch fitted on
the CPU is split into one chunk per core, each fitted by its own thread with its own arrays. On CUDA
one launch already fills the GPU: one chunk.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

__all__ = ["Cancelled", "map_chunks", "problem_chunks"]


class Cancelled(Exception):
    """Raised inside a chunk's thread when another chunk failed or the user interrupted."""


def problem_chunks(count: int, device, workers: int | None = None) -> list[slice]:
    """Contiguous slices of ``range(count)``: one on CUDA, up to ``workers`` (default: CPU cores) on the CPU."""
    device = wp.get_device(device)
    if device.is_cuda:
        parts = 1
    else:
        parts = workers if workers is not None else (os.cpu_count() or 1)
    parts = max(1, min(int(parts), count))
    bounds = [round(k * count / parts) for k in range(parts + 1)]
    return [slice(bounds[k], bounds[k + 1]) for k in range(parts) if bounds[k + 1] > bounds[k]]


def map_chunks(function, chunks: list[slice]) -> list:
    """``[function(chunk, stop) for chunk in chunks]``, on one thread per chunk when there are several.

    ``stop`` is a ``threading.Event`` that long loops should poll (and raise ``Cancelled``): it is set
    when any chunk fails or the caller is interrupted (Ctrl-C), so no thread keeps fitting after the
    caller gave up. The first exception is re-raised after every thread has stopped.
    """
    stop = threading.Event()
    if len(chunks) == 1:
        return [function(chunks[0], stop)]
    pool = ThreadPoolExecutor(max_workers=len(chunks), thread_name_prefix="warp-highlights")
    futures = [pool.submit(function, chunk, stop) for chunk in chunks]
    try:
        results = []
        for future in futures:
            try:
                results.append(future.result())
            except BaseException:
                stop.set()
                raise
        return results
    except BaseException:
        stop.set()
        raise
    finally:
        pool.shutdown(wait=True)
