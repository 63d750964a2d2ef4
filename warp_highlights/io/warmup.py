"""A CUDA device's context made in a thread while the host does other work.

Warp makes a device's (primary) context on its first use. In the ``fit`` command that was the
segmentation's first memory query, about 0.13-0.3 s on the lent H100 while nothing else ran (measured
with py-spy and a micro-benchmark, benchmarks/README.md "Tenth session"). Made in a thread while the
command imports the pipeline and decodes the images, it costs nothing there: the CUDA driver's calls
let go of the GIL. (The memory pool needs no such start: its first 400 MB took 0.7 ms.)
"""

from __future__ import annotations

import threading

__all__ = ["DeviceWarmup"]


class DeviceWarmup:
    """Makes ``device``'s context in a thread (a CUDA device only; elsewhere nothing).

    Warp must be started (``wp.init``) first: starting it from two threads at once is not safe.
    ``join`` before the device's work. The warm-up's errors are not raised: the work that needs the
    device meets them again and reports them in its own line."""

    def __init__(self, device):
        import warp as wp

        self.device = wp.get_device(device)
        self._thread = None
        if self.device.is_cuda:
            self._thread = threading.Thread(target=self._warm, name="device-warmup", daemon=True)
            self._thread.start()

    def _warm(self) -> None:
        try:
            self.device.context  # noqa: B018 (the primary context, made on first use)
        except Exception:  # noqa: BLE001 (the device's own work reports what is wrong)
            return

    def join(self) -> None:
        """Wait for the warm-up to end."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
