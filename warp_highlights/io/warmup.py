"""A CUDA device made ready in a thread while the host does other work: its context and a first block of
its memory pool.

Measured on the lent H100 (250 lights, 480x270, the whole ``fit`` command): the device's context was
made by the fit's first memory query (about 0.3 s) and the memory pool grew at the segmentation's first
allocation (about 0.15 s), both while nothing else ran. Made in a thread while the fit command imports
the pipeline and decodes the images, they cost nothing there (the CUDA driver calls let go of the GIL).
"""

from __future__ import annotations

import threading

__all__ = ["DeviceWarmup", "WARM_POOL_SHARE"]

WARM_POOL_SHARE = 0.25
"""The most of the device's free memory the warm-up takes into its memory pool (as one block, given
back to the pool at once), where the pool keeps what is given back; the fit's first stages take more."""


class DeviceWarmup:
    """Starts ``device``'s context and memory pool in a thread (a CUDA device only; elsewhere nothing).

    ``pool_bytes``: the block taken from the pool and given back (at most ``WARM_POOL_SHARE`` of the
    free memory; nothing where the pool gives its memory back to the system on the next synchronisation).
    Warp must be started (``wp.init``) first: starting it from two threads at once is not safe. ``join``
    before the device's work: the warm-up's errors are not raised (the work that needs the device meets
    and reports them itself)."""

    def __init__(self, device, *, pool_bytes: int = 1 << 30):
        import warp as wp

        self.device = wp.get_device(device)
        self.pool_bytes = int(pool_bytes)
        self._thread = None
        if self.device.is_cuda:
            self._thread = threading.Thread(target=self._warm, name="device-warmup", daemon=True)
            self._thread.start()

    def _warm(self) -> None:
        import warp as wp

        try:
            device = self.device
            device.context  # noqa: B018 (the primary context, made on first use)
            if not (device.is_mempool_supported and device.is_mempool_enabled):
                return
            size = min(self.pool_bytes, int(WARM_POOL_SHARE * device.free_memory))
            if size <= 0 or wp.get_mempool_release_threshold(device) < size:
                return
            block = wp.empty(size, dtype=wp.uint8, device=device)
            del block
        except Exception:  # noqa: BLE001 (the device's own work reports what is wrong)
            return

    def join(self) -> None:
        """Wait for the warm-up to end."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
