"""The worker plugin that stops a closing worker's commands (imported only where Dask distributed is)."""

from __future__ import annotations

import signal
import threading

from distributed import WorkerPlugin

from .job import stop_children

__all__ = ["StopChildren"]


class StopChildren(WorkerPlugin):
    """One collection run's plugin (named after the run): when a worker closes mid-capture (Ctrl-C, the cluster going
    away) or the run removes the plugin (its end, or its interruption on a running cluster), that run's
    ``warp-highlights`` commands on the worker get SIGTERM, remove their partial outputs and end; other runs on the same
    cluster go on.

    On a local cluster the worker also ignores SIGINT: Ctrl-C reaches the client, which closes the cluster (and the
    commands, which get it too, clean up after themselves), instead of every worker printing its own traceback.
    """

    def __init__(self, run_id: str, ignore_interrupts: bool = True):
        self.run_id, self.ignore_interrupts = run_id, ignore_interrupts
        self.name = f"warp-highlights-{run_id}"

    def setup(self, worker) -> None:
        if self.ignore_interrupts and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    def teardown(self, worker) -> None:
        stop_children(self.run_id)  # the run's flag stays set: a task of it that starts late starts nothing
