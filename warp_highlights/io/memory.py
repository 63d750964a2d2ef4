"""How much memory a request may take: what is available, and byte counts people can read."""

from __future__ import annotations

import os

from ..model.errors import InputError

__all__ = ["available_memory", "bytes_text", "check_memory"]


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
