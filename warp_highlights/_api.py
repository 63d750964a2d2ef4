"""Plumbing of the public API, usable from every layer: lazy exports and warnings for moved names."""

from __future__ import annotations

import importlib
import sys
import warnings
from collections.abc import Callable

__all__ = ["lazy_exports", "warn_moved"]


def lazy_exports(
    package: str, exports: dict[str, str], *, modules: dict[str, str] | None = None
) -> tuple[Callable[[str], object], Callable[[], list[str]], list[str]]:
    """``__getattr__``, ``__dir__`` and ``__all__`` for a package ``__init__`` that exports names on first use.

    Importing a package then costs nothing until one of its names is used, so that ``import
    warp_highlights`` (and the command line's ``--help``) does not load Warp or pyvista.

    Args:
        package: The package's ``__name__``.
        exports: Public name -> the module that defines it, relative to the package: ``"model.field"``
            for a sub-module, ``"..kernels.segmentation"`` (leading dots) for one further up.
        modules: Public name -> a module exported as a whole, written the same way (``"view.viz"``).
    """
    modules = modules or {}

    def _module(relative: str):
        return importlib.import_module(relative if relative.startswith(".") else "." + relative, package)

    def __getattr__(name: str):
        if name in exports:
            value = getattr(_module(exports[name]), name)
        elif name in modules:
            value = _module(modules[name])
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports) | set(modules))

    return __getattr__, __dir__, sorted([*exports, *modules])


def warn_moved(old: str, new: str) -> None:
    """Warn that ``old`` is deprecated in favour of ``new`` (both as the user writes them), pointing at the
    line that called the deprecated name (a ``DeprecationWarning``)."""
    warnings.warn(f"{old} is deprecated and will be removed in warp-highlights 0.3; use {new}", DeprecationWarning, stacklevel=3)
