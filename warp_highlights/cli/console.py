"""The console entry point (``warp-highlights`` and ``python -m warp_highlights``).

Ctrl-C or SIGTERM while the program is still loading ends it at once with status 130 or 143 (nothing
has been written then); once ``main`` runs, its own handlers take over and clean up. Once ``main`` has
returned, the process ends at once (``_end``; not under a profiler or coverage tool): the interpreter's
teardown of the modules it loaded (Warp, SciPy, NumPy) would add a noticeable wait after every
command, with nothing left for it to do.
"""

from __future__ import annotations

import logging
import os
import signal
import sys

__all__ = ["run"]


def run() -> None:
    """Run ``warp-highlights`` with the process's arguments and exit with its status."""
    signal.signal(signal.SIGINT, _stop_while_loading)
    signal.signal(signal.SIGTERM, _stop_while_loading)
    from .app import main

    _end(main())


def _end(status: int) -> None:
    """Exit with ``status`` without the interpreter's teardown: every file the command wrote is closed and
    in place by then (written under a temporary name, then renamed), its threads are idle, and neither
    this package nor the libraries it uses leave exit handlers that do work; what is still buffered
    (standard output and error, log handlers) is flushed first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:  # None: started with the stream closed (``>&-``)
                stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``): nothing more can reach it
            pass
    if _observed():
        sys.exit(status)  # a profiler or a coverage tool writes its results at the interpreter's exit
    os._exit(status)


def _observed() -> bool:
    """Whether a profiler, tracer or ``sys.monitoring`` tool (cProfile, coverage) watches the process."""
    if sys.gettrace() is not None or sys.getprofile() is not None:
        return True
    monitoring = getattr(sys, "monitoring", None)
    return monitoring is not None and any(monitoring.get_tool(tool) is not None for tool in range(6))


def _stop_while_loading(signum, frame) -> None:
    os.write(2, b"warp-highlights: interrupted while starting; nothing was written\n")
    os._exit(143 if signum == signal.SIGTERM else 130)
