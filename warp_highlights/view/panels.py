"""The light designer's panel names (no pyvista or Warp, so the command line can list them without starting either)."""

from __future__ import annotations

from ..model.errors import InputError

__all__ = ["PANELS", "check_panels"]

PANELS = ("sphere", "image", "paths")
"""Panel names, in their default left-to-right order."""


def check_panels(panels) -> tuple[str, ...]:
    """``panels`` as a tuple of distinct names from ``PANELS``; ``InputError`` otherwise."""
    panels = tuple(panels)
    if not panels or any(p not in PANELS for p in panels) or len(set(panels)) != len(panels):
        raise InputError(f"panels must be distinct names from {', '.join(PANELS)}, got {', '.join(panels) or 'none'}")
    return panels
