"""Warp's kernel cache made usable before Warp starts: ``prepare_kernel_cache`` checks that the folder Warp
would compile its kernels into can be written, and otherwise points Warp at one under the temporary folder.

Warp creates its cache on ``wp.init`` (``$WARP_CACHE_PATH/<version>``, else the user's cache folder:
``$XDG_CACHE_HOME`` or ``~/.cache`` on Linux); a read-only home, a read-only ``XDG_CACHE_HOME`` or a
``WARP_CACHE_PATH`` that names a file would otherwise end every command in Warp's traceback.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

from ..model.errors import InputError

__all__ = ["CACHE_VARIABLE", "default_cache_folder", "prepare_kernel_cache", "writable_folder_problem"]

CACHE_VARIABLE = "WARP_CACHE_PATH"
"""The environment variable Warp reads for its kernel cache's location."""


def default_cache_folder(version: str) -> Path | None:
    """The folder Warp ``version`` compiles its kernels into when nothing is configured (None: not known here)."""
    if CACHE_VARIABLE in os.environ:
        return Path(os.path.realpath(os.environ[CACHE_VARIABLE])) / version
    if sys.platform.startswith("linux"):
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        return Path(base) / "warp" / version
    if sys.platform == "darwin":
        return Path(os.path.expanduser("~/Library/Caches")) / "warp" / version
    return None  # Windows and others: Warp's own choice, checked when Warp starts


def writable_folder_problem(folder: Path) -> str | None:
    """Why ``folder`` cannot be created or written (the system's reason), or None when a file can be made in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        return error.strerror or str(error)
    return None


def _private_fallback() -> Path:
    """This user's kernel cache under the temporary folder, made private (0700); raises OSError when it
    cannot be, or when another user owns it or it is a link."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    base = Path(tempfile.gettempdir()) / f"warp-highlights-kernels-{uid}"
    try:
        base.mkdir(mode=0o700)
    except FileExistsError:
        pass
    status = os.lstat(base)
    if not stat.S_ISDIR(status.st_mode) or (hasattr(os, "getuid") and status.st_uid != uid):
        raise OSError(f"{base} is not a folder of this user")
    return base


def prepare_kernel_cache() -> str | None:
    """Make sure Warp can write its kernel cache; call before Warp starts.

    Returns None when the cache Warp would use is writable (or set by the program already), or a
    one-line warning when it is not and a private folder under the temporary folder is used instead
    (``warp.config.kernel_cache_dir``). Raises ``InputError`` (one line naming ``WARP_CACHE_PATH``)
    when that fails too.
    """
    import warp as wp

    if getattr(wp.config, "kernel_cache_dir", None):
        return None  # chosen by the program: Warp's start reports on it
    folder = default_cache_folder(wp.config.version)
    if folder is None:
        return None
    problem = writable_folder_problem(folder)
    if problem is None:
        return None
    try:
        fallback = _private_fallback()
        fallback_problem = writable_folder_problem(fallback / wp.config.version)
    except OSError as error:
        fallback, fallback_problem = Path(tempfile.gettempdir()), error.strerror or str(error)
    if fallback_problem is not None:
        raise InputError(
            f"Warp's kernel cache {folder} cannot be written ({problem}), nor one under {fallback} "
            f"({fallback_problem}); set {CACHE_VARIABLE} to a writable folder")
    wp.config.kernel_cache_dir = str(fallback)
    return (f"warning: Warp's kernel cache {folder} cannot be written ({problem}); compiling into {fallback} "
            f"instead; set {CACHE_VARIABLE} to a writable folder to keep compiled kernels between runs")
