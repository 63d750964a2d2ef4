"""How much memory a request may take: what is available, byte counts people can read, and the peak a
block of work used (``PeakMemory``, the fit report's figures).

In the model layer beside ``threads``: the host's (and a Warp device's) resources, which every layer
consults (the dataset loader, fitting, relighting, rendering, the commands) and which need nothing of
the package but ``InputError``; Warp is imported only where a device is asked about.
"""

from __future__ import annotations

import os
import resource
import sys
import threading

from .errors import InputError

__all__ = ["PeakMemory", "available_memory", "bytes_text", "check_memory", "device_free_memory", "resident_memory"]

PEAK_SAMPLE_SECONDS = 0.01
"""How often ``PeakMemory`` reads the current use between the exact high-water marks (10 ms: a stage's
peak is a held array, not a moment's)."""


def available_memory() -> int | None:
    """Bytes of memory a new allocation can get: Linux's ``MemAvailable``, else the free physical pages
    (``os.sysconf``); None when neither is known. Container (cgroup) limits are not looked at."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # the file says kB and means KiB
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def device_free_memory(device) -> int | None:
    """Bytes a new allocation on a Warp ``device`` can get: the free device memory on CUDA, the host's
    ``available_memory`` on the CPU (None when unknown)."""
    return int(device.free_memory) if device.is_cuda else available_memory()


def check_memory(needed: int, what: str, advice: str, *, detail: str = "") -> None:
    """Raise ``InputError`` when ``needed`` bytes exceed the available memory, with both figures;
    nothing is refused when the available memory is unknown.

    Args:
        needed: Estimated bytes the request takes.
        what: What needs it, e.g. ``"relighting at 8000x4500"``.
        advice: What to do instead, e.g. ``"use a smaller --size"``.
        detail: How the estimate was made, shown in brackets, e.g. ``"54 images of 640x480x3 as float32"``.
    """
    available = available_memory()
    if available is not None and needed > available:
        how = f" ({detail})" if detail else ""
        raise InputError(
            f"{what} needs about {bytes_text(needed)} of memory{how} but {bytes_text(available)} is available; {advice}"
        )


def bytes_text(count: float) -> str:
    """``'12.3 GB'``, ``'45.6 MB'``, ``'512.0 kB'`` (decimal units, as memory and disks are sold)."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= size:
            return f"{count / size:.1f} {unit}"
    return f"{int(count)} bytes"


def resident_memory() -> int | None:
    """Bytes of physical memory this process holds now (Linux's ``/proc/self/statm``), None elsewhere."""
    try:
        with open("/proc/self/statm", encoding="ascii") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def _maximum_resident() -> int:
    """The process's resident high-water mark in bytes (``getrusage``: kB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak) if sys.platform == "darwin" else int(peak) * 1024


class PeakMemory:
    """The most host (resident) and device (Warp's CUDA memory pool) memory used while inside ``with``.

    Exact where a high-water mark rose inside (the process's ``ru_maxrss``, the pool's
    ``get_mempool_used_mem_high``); otherwise the largest use read every ``PEAK_SAMPLE_SECONDS`` by a
    thread. ``device``: a Warp device (None: Warp's default). ``host`` and ``device`` are bytes after
    the block; ``device`` is None off CUDA (or without a memory pool), ``host`` None where the
    process's memory cannot be read."""

    def __init__(self, device=None):
        self._device = None
        # the host alone needs no Warp (usable before Warp has started, as the fit command's loading is)
        if device != "cpu":
            import warp as wp

            device = wp.get_device(device)  # None: Warp's default device
            self._device = (device if device.is_cuda and device.is_mempool_supported and device.is_mempool_enabled
                            else None)
        self.host: int | None = None
        self.device: int | None = None
        self._stop = threading.Event()

    def report(self) -> dict:
        """The figures as the fit report keeps them: ``host_peak_bytes`` and ``device_peak_bytes``."""
        return {"host_peak_bytes": self.host, "device_peak_bytes": self.device}

    def _device_now(self) -> int:
        import warp as wp

        return int(wp.get_mempool_used_mem_current(self._device))

    def _device_high(self) -> int:
        import warp as wp

        return int(wp.get_mempool_used_mem_high(self._device))

    def _watch(self) -> None:
        while not self._stop.wait(PEAK_SAMPLE_SECONDS):
            self._sample()

    def _sample(self) -> None:
        now = resident_memory()
        if now is not None:
            self.host = max(self.host or 0, now)
        if self._device is not None:
            self.device = max(self.device or 0, self._device_now())

    def __enter__(self) -> PeakMemory:
        self._host_high = _maximum_resident()
        self._device_start_high = self._device_high() if self._device is not None else 0
        self._sample()
        self._thread = threading.Thread(target=self._watch, name="peak-memory", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()
        high = _maximum_resident()
        if high > self._host_high and self.host is not None:
            self.host = max(self.host, high)  # the process's peak was set inside
        if self._device is not None:
            device_high = self._device_high()
            if device_high > self._device_start_high:
                self.device = max(self.device or 0, device_high)
