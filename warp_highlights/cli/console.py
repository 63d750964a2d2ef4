"""The console entry point (``warp-highlights`` and ``python -m warp_highlights``).

Ctrl-C or SIGTERM while the program is still loading ends it at once with status 130 or 143 (nothing
has been written then); once ``main`` runs, its own handlers take over and clean up.
"""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["run"]


def run() -> None:
    """Run ``warp-highlights`` with the process's arguments and exit with its status."""
    signal.signal(signal.SIGINT, _stop_while_loading)
    signal.signal(signal.SIGTERM, _stop_while_loading)
    from .app import main

    sys.exit(main())


def _stop_while_loading(signum, frame) -> None:
    os.write(2, b"warp-highlights: interrupted while starting; nothing was written\n")
    os._exit(143 if signum == signal.SIGTERM else 130)
