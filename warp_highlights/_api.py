"""Plumbing of the public API, usable from every layer: the packages' lazy exports."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

__all__ = ["lazy_exports"]


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

