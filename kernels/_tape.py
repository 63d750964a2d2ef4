"""Access to the ``wp.Tape`` being recorded, for operations that register hand-written adjoints."""

from __future__ import annotations

import warp as wp

__all__ = ["active_tape"]


def active_tape() -> wp.Tape | None:
    """The tape of the enclosing ``with wp.Tape():`` block, or None.

    Warp keeps it on its runtime object (``wp.launch`` records onto it the same way); there is no
    public accessor in warp-lang 1.x, so this is the one place that reaches for it.
    """
    runtime = getattr(getattr(getattr(wp, "_src", None), "context", None), "runtime", None)
    if runtime is None:
        wp.init()
        runtime = wp._src.context.runtime
    return runtime.tape
