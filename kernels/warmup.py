"""Warp started, and a CUDA device's context made, in a thread while the host does other work.

``wp.init`` and the device's (primary) context, made on its first use, take a noticeable part of a
short ``fit`` command, during which nothing else would run (``benchmarks/bench_transfer.py`` times
both). Both are mostly the CUDA driver's calls, which let go of the GIL: started in a thread, Warp
starts while the command imports the pipeline (which defines its kernels without starting Warp), and
the context is made while the images decode. (The memory pool needs no such start: its first
allocations are quick.)

``InBackground`` runs other work in a thread the same way: the fit command's loading, whose decoding
lets go of the GIL, while the command imports the rest of the pipeline and Warp starts.

With the kernels, the layer that owns Warp and its devices; the module imports nothing of the package
(nor Warp, until its thread runs), so the command can start it before the pipeline is imported. Fit's
pipeline and the fit command use both classes.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

__all__ = ["DeviceWarmup", "InBackground"]


class DeviceWarmup:
    """Starts Warp (``wp.init``) and then makes ``device``'s context (a CUDA device only) in a thread.

    Nothing else may start Warp until ``started`` returns (starting it from two threads at once is not
    safe); ``join`` before the device's work. The warm-up's errors are not raised: Warp's start is
    tried again by the caller after ``started`` (``cli.args.check_device``), and the device's own
    work meets any other error again and reports it in its own line."""

    def __init__(self, device: str | None):
        self.requested = device
        self.device = None  # the Warp device, once resolved (set before ``started`` returns; None: not available here)
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._warm, name="device-warmup", daemon=True)
        self._thread.start()

    def _warm(self) -> None:
        try:
            import warp as wp

            wp.init()
            self.device = wp.get_device(self.requested)
        except Exception:  # noqa: BLE001 (the caller starts Warp again and reports what is wrong)
            return
        finally:
            self._started.set()
        if self.device.is_cuda:
            try:
                self.device.context  # noqa: B018 (the primary context, made on first use)
            except Exception:  # noqa: BLE001 (the device's own work reports what is wrong)
                return

    def started(self, timeout: float | None = None) -> bool:
        """Wait for Warp's start (not for the context), at most ``timeout`` seconds; whether it ended."""
        return self._started.wait(timeout)

    def join(self) -> None:
        """Wait for the warm-up to end."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None


class InBackground:
    """Runs ``work(stop)`` in a thread from now on (a one-thread executor's future): ``result`` waits for
    it and returns what it returned or raises what it raised; ``cancel`` sets ``stop`` (a
    ``threading.Event`` the work checks between its steps, stopping early) and waits for it to end.
    Call one of them before returning: a caller that meets an error or Ctrl-C meanwhile cancels
    (``with`` does so). Either way the thread has ended when they return."""

    def __init__(self, work: Callable, *, name: str):
        self.stop = threading.Event()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._future = self._executor.submit(work, self.stop)

    def result(self):
        """Wait for the work; its value, or its error raised here."""
        try:
            return self._future.result()
        finally:
            self._executor.shutdown(wait=True)

    def done(self) -> bool:
        """Whether the work has ended (returned or raised)."""
        return self._future.done()

    def cancel(self) -> None:
        """Ask the work to stop and wait until it has."""
        self.stop.set()
        self._executor.shutdown(wait=True)

    def __enter__(self) -> InBackground:
        return self

    def __exit__(self, kind, error, trace) -> None:
        if kind is not None:
            self.cancel()
