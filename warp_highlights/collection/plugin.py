"""The worker plugin that stops a closing worker's commands (imported only where Dask distributed is)."""

from __future__ import annotations

import signal
import threading

from distributed import WorkerPlugin

from .job import stop_children

__all__ = ["StopChildren"]


class StopChildren(WorkerPlugin):
    """When a worker closes mid-capture (Ctrl-C, the cluster going away), its running ``warp-highlights`` commands get
    SIGTERM, remove their partial outputs and end; the capture's temporary folder goes with the failed task.

    A local worker ignores SIGINT: Ctrl-C reaches the client, which closes the cluster (and the commands, which get it
    too, clean up after themselves), instead of every worker printing its own traceback.
    """

    name = "warp-highlights-stop-children"

    def __init__(self, ignore_interrupts: bool = True):
        self.ignore_interrupts = ignore_interrupts

    def setup(self, worker) -> None:
        if self.ignore_interrupts and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    def teardown(self, worker) -> None:
        stop_children()
