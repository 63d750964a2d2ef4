"""Splitting a batch of independent problems over CPU threads.

Warp runs each CPU launch on one thread (and releases the GIL while it runs), so a batch fitted on
the CPU is split into one chunk per core, each fitted by its own thread with its own arrays. On CUDA
one launch already fills the GPU: one chunk.
"""

from __future__ import annotations

import threading
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

import warp as wp

from warp_highlights.model.threads import child_initializer, core_count

__all__ = ["CPU_PARTS_PER_WORKER", "DEVICE_SHARE", "Cancelled", "chunk_progress", "map_chunks", "memory_chunks",
           "problem_chunks"]

DEVICE_SHARE = 0.5
"""The share of a CUDA device's free memory one batch's arrays may take (the rest is for the stage's
smaller arrays, the fit's other stages and other programs); a batch that needs more runs in parts."""

CPU_PARTS_PER_WORKER = 2
"""Parts per CPU thread that the fit's batches of lights or edges are cut into (``problem_chunks``'s ``per_worker``),
taken by the threads as they come: problems differ in cost (a dome's low lights, without highlights, are fitted far
faster than its glossy ones, and they come in order of elevation), so one part per thread left one thread with most
of the work; each part's launches cost time too. Whole low-rank fits on 2 cores, the same Gaussians in
every case (``benchmarks/bench_fit.py --device cpu --set residual.kind=lowrank --parts-per-worker ...``, the values
in one run): the dome sample at 160x160, 109.2 s with 1 part per thread, 95.8 and 90.6 with 2, 80.4 with 4; the
statue at 192x181 (54 evenly lit lights), 71.8 s with 1, 72.4 with 2, 85.1 and 83.4 with 4."""


class Cancelled(Exception):
    """Raised inside a chunk's thread when another chunk failed or the user interrupted."""


def problem_chunks(count: int, device, workers: int | None = None, *, most_each: int | None = None,
                   per_worker: int = 1) -> list[slice]:
    """Contiguous slices of ``range(count)``: one on CUDA, up to ``workers`` (default: CPU cores) on the CPU, times
    ``per_worker`` where there are several workers to share them; more where a slice would hold over ``most_each``
    problems (one launch's bound, e.g. ``problems_per_launch``)."""
    device = wp.get_device(device)
    if device.is_cuda:
        parts = 1
    else:
        parts = workers if workers is not None else core_count()
        parts *= max(1, int(per_worker)) if parts > 1 else 1
    return _equal_slices(count, max(1, min(int(parts), count)), most_each)


def _equal_slices(count: int, parts: int, most_each: int | None) -> list[slice]:
    if most_each is not None:
        parts = max(parts, -(-count // max(1, int(most_each))))
    bounds = [round(k * count / parts) for k in range(parts + 1)]
    return [slice(bounds[k], bounds[k + 1]) for k in range(parts) if bounds[k + 1] > bounds[k]]


def chunk_progress(progress, chunk: slice, count: int):
    """``progress`` for one chunk of ``count`` problems: its ``advance(steps)`` reported as the share of
    the stage's steps (``steps`` x chunk / count), so a bar over the stage's steps fills once, however many
    chunks run. None stays None."""
    if progress is None:
        return None
    share = (chunk.stop - chunk.start) / max(count, 1)
    return lambda steps: progress(steps * share)


def map_chunks(function, chunks: list[slice], *, parallel: bool = True, threads: int | None = None) -> list:
    """``[function(chunk, stop) for chunk in chunks]``, on one thread per chunk when there are several, at most
    ``threads`` at once (default: every chunk at once; ``parallel=False``: one after the other on this thread, for
    parts that share one device's memory).

    ``stop`` is a ``threading.Event`` that long loops should poll (and raise ``Cancelled``): it is set
    as soon as any chunk fails or the caller is interrupted (Ctrl-C), so no thread keeps fitting after
    the work is lost. The first real error (not a ``Cancelled``) is re-raised once every thread has
    stopped.
    """
    stop = threading.Event()
    if len(chunks) == 1 or not parallel:  # parallel=False: one after the other (``memory_chunks``' parts of one device)
        return [function(chunk, stop) for chunk in chunks]

    def guarded(chunk: slice):
        try:
            return function(chunk, stop)
        except BaseException:
            stop.set()
            raise

    pool = ThreadPoolExecutor(max_workers=min(len(chunks), max(1, int(threads or len(chunks)))),
                              thread_name_prefix="warp-highlights",
                              initializer=child_initializer())
    futures = [pool.submit(guarded, chunk) for chunk in chunks]
    try:
        wait(futures, return_when=FIRST_EXCEPTION)
        wait(futures)
    except BaseException:  # Ctrl-C while waiting
        stop.set()
        pool.shutdown(wait=True)
        raise
    pool.shutdown(wait=True)
    errors = [f.exception() for f in futures if f.exception() is not None]
    if errors:
        real = [e for e in errors if not isinstance(e, Cancelled)]
        raise (real or errors)[0]
    return [f.result() for f in futures]


def memory_chunks(count: int, device, workers: int | None = None, *, bytes_each: float, share: float = DEVICE_SHARE,
                  most_each: int | None = None, per_worker: int = 1) -> list[slice]:
    """``problem_chunks``; on CUDA, as many equal contiguous parts (run one after the other) as keep each
    part's ``bytes_each`` per problem within ``share`` of the device's free memory, and its problems at
    most ``most_each``."""
    device = wp.get_device(device)
    if not device.is_cuda or count == 0:
        return problem_chunks(count, device, workers, most_each=most_each, per_worker=per_worker)
    fits = max(1, int(share * device.free_memory // max(bytes_each, 1)))
    return _equal_slices(count, -(-count // fits), most_each)
