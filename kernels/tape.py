"""Access to the ``wp.Tape`` being recorded, for operations that register hand-written adjoints; one
Adam iteration on a tape, and its CUDA-graph replay (``ReplayedStep``), which the fitting stages run."""

from __future__ import annotations

import threading
from contextlib import contextmanager

import warp as wp

__all__ = ["ReplayedStep", "active_tape", "adam_iteration", "recording"]

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


def adam_iteration(tape: wp.Tape, loss: wp.array, seed: wp.array, losses, optimiser):
    """One fitting iteration as a function, all on the device (fixed arrays, no copy to the host):
    zero ``loss``, record ``losses()`` on ``tape``, back-propagate ``seed`` from ``loss``, step
    ``optimiser``, zero the gradients."""

    def step() -> None:
        loss.zero_()
        with recording(tape):
            losses()
        tape.backward(grads={loss: seed})
        optimiser.step()
        tape.zero()
        tape.reset()

    return step


class ReplayedStep:
    """Calls ``step`` (device work only, on arrays that stay in place); with ``graphs``, the first call
    runs it (loading its kernels and making its scratch arrays), the second captures it as a CUDA graph,
    and every call from then on replays that graph: the same kernels in the same order."""

    def __init__(self, step, device, *, graphs: bool):
        self.step, self.device, self.graphs = step, device, graphs
        self.calls, self.graph = 0, None

    def __call__(self) -> None:
        self.calls += 1
        if not self.graphs or self.calls == 1:
            self.step()
            return
        if self.graph is None:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self.step()
            self.graph = capture.graph
        wp.capture_launch(self.graph)
