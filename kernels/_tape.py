"""Access to the ``wp.Tape`` being recorded, for operations that register hand-written adjoints."""

from __future__ import annotations

import threading
from contextlib import contextmanager

import warp as wp

__all__ = ["active_tape", "recording"]

_local = threading.local()


@contextmanager
def recording(tape: wp.Tape):
    """Record this project's operations onto ``tape`` in the calling thread only.

    ``with wp.Tape():`` sets one process-wide tape, so two threads fitting separate batches would
    record onto each other's tapes. Every operation here registers its adjoint through
    ``active_tape()`` (their launches are never taped themselves), so a thread-local tape keeps
    concurrent fits apart. Plain ``wp.launch`` calls inside the block are not recorded.
    """
    previous = getattr(_local, "tape", None)
    _local.tape = tape
    try:
        yield tape
    finally:
        _local.tape = previous


def active_tape() -> wp.Tape | None:
    """The calling thread's ``recording`` tape, else the tape of the enclosing ``with wp.Tape():``, or None.

    Warp keeps the latter on its runtime object (``wp.launch`` records onto it the same way); there
    is no public accessor in warp-lang 1.x, so this is the one place that reaches for it.
    """
    local = getattr(_local, "tape", None)
    if local is not None:
        return local
    runtime = getattr(getattr(getattr(wp, "_src", None), "context", None), "runtime", None)
    if runtime is None:
        wp.init()
        runtime = wp._src.context.runtime
    return runtime.tape
