"""NumPy work spread over the cores: NumPy's array loops and zlib let go of the GIL, so threads run a
large array operation split into independent parts in parallel (the residual's compression)."""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import contextmanager

import numpy as np

try:
    import threadpoolctl
except ImportError:  # BLAS threads its own products
    threadpoolctl = None

__all__ = ["NUMPY_THREADS", "PREFAULT_BYTES", "all_finite", "blas_on_one_thread", "cancel_and_wait",
           "child_initializer", "core_count", "gather", "in_worker", "mapped_empty", "parallel_map", "shared_pool",
           "submit"]


def core_count() -> int:
    """CPU cores this process may use (affinity and container limits where the OS reports them)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


NUMPY_THREADS = core_count()
"""Threads ``parallel_map`` uses: the cores this process may run on."""

_CONTROLLER = None


@contextmanager
def blas_on_one_thread():
    """A context that yields the threads to split NumPy work over: the cores (``NUMPY_THREADS``), the BLAS
    library held to one thread each meanwhile (threadpoolctl); 1 where threadpoolctl is missing, BLAS left
    to thread its own products. A BLAS library threading its products stalls for milliseconds at a time
    when another process takes a core (ten times slower on a busy 2-core machine), one thread each does not;
    and a product split by the caller alone rounds the same whatever the cores (a BLAS library blocks a
    float32 product by its thread count)."""
    global _CONTROLLER
    if threadpoolctl is None or NUMPY_THREADS == 1:
        yield 1
        return
    if _CONTROLLER is None:  # finds the BLAS libraries loaded (milliseconds): once
        _CONTROLLER = threadpoolctl.ThreadpoolController()
    with _CONTROLLER.limit(limits=1, user_api="blas"):
        yield NUMPY_THREADS


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_IN_POOL = threading.local()


def _mark_worker() -> None:
    _IN_POOL.worker = True


def shared_pool() -> ThreadPoolExecutor:
    """The process's ``NUMPY_THREADS`` worker threads, started once (a pool made for each call started
    its threads again: hundreds of calls in a fit, a few milliseconds each)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=NUMPY_THREADS, thread_name_prefix="numpy", initializer=_mark_worker)
        return _POOL


def in_worker() -> bool:
    """True on one of ``shared_pool``'s threads, or on a thread a pool started from one
    (``child_initializer``): its work runs its own parts in place, as waiting there for parts queued
    behind it could wait for ever."""
    return getattr(_IN_POOL, "worker", False)


def child_initializer():
    """The ``initializer`` of a thread pool about to be started here: on a worker (``in_worker``), one
    that marks the new pool's threads as workers too, so that their maps run in place; else None."""
    return _mark_worker if in_worker() else None


def submit(function, *args, **kwargs) -> Future:
    """``shared_pool().submit(function, *args, **kwargs)``; called from a worker, run in place (a done future)."""
    if not in_worker():
        return shared_pool().submit(function, *args, **kwargs)
    future: Future = Future()
    try:
        future.set_result(function(*args, **kwargs))
    except BaseException as error:  # handed to the caller as the pool would hand it
        future.set_exception(error)
    return future


def gather(futures: list[Future]) -> list:
    """The futures' results in order, once every one has finished (the first exception raised then);
    interrupted (Ctrl-C), the ones not started are cancelled and the running ones waited for."""
    try:
        wait(futures)
    except BaseException:
        cancel_and_wait(futures)
        raise
    return [future.result() for future in futures]


def cancel_and_wait(futures: list[Future]) -> None:
    """Cancel the futures not started and wait for the running ones, raising none of their errors
    (what a caller that is failing or interrupted does, so that no work is left running behind it; a
    second Ctrl-C still stops the wait)."""
    for future in futures:
        future.cancel()
    wait(futures)


def parallel_map(function, items) -> list:
    """``[function(item) for item in items]``, the calls spread over ``shared_pool``'s threads (in
    order; the first exception is raised once every call has finished). One item, one thread, or
    called from a worker: in place, every call made all the same before the first exception is raised."""
    items = list(items)
    if len(items) <= 1 or NUMPY_THREADS == 1 or in_worker():
        results, first = [], None
        for item in items:
            try:
                results.append(function(item))
            except Exception as error:  # noqa: BLE001 (raised once every call has been made)
                first = first or error
        if first is not None:
            raise first
        return results
    futures: list[Future] = []
    try:
        for item in items:
            futures.append(shared_pool().submit(function, item))
    except BaseException:  # Ctrl-C while submitting: the calls not started dropped, the running ones waited for
        cancel_and_wait(futures)
        raise
    return gather(futures)


def all_finite(array) -> bool:
    """``np.isfinite(array).all()``, bands of the first axis in threads: a stack of images is checked at
    the cores' speed and with a band's mask at a time, not one the size of the stack."""
    array = np.asarray(array)
    if array.ndim == 0 or len(array) < 2 or NUMPY_THREADS == 1:
        return bool(np.isfinite(array).all())
    step = -(-len(array) // (4 * NUMPY_THREADS))
    return all(parallel_map(lambda start: bool(np.isfinite(array[start : start + step]).all()),
                            range(0, len(array), step)))


PREFAULT_BYTES = 1 << 26
"""Arrays from this size (64 MiB) are made by ``mapped_empty`` with their pages written from threads;
smaller ones are left to be mapped as they are first written (the threads would cost more)."""


def mapped_empty(shape, dtype) -> np.ndarray:
    """``np.empty(shape, dtype)`` whose memory is mapped already: a large array's pages are written
    (zeros) from threads first. A fresh array's first writes stop at each of its pages while the
    system maps it, one page at a time even from many threads, so a copy into fresh pages runs far
    slower than the threaded zero fill and a copy into mapped pages together (``kernels.transfer``)."""
    array = np.empty(shape, dtype)
    if array.nbytes < PREFAULT_BYTES or NUMPY_THREADS == 1:
        return array
    flat = array.reshape(-1)
    step = -(-flat.size // (4 * NUMPY_THREADS))
    parallel_map(lambda start: flat[start : start + step].fill(0), range(0, flat.size, step))
    return array
