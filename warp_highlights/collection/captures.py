"""Finding the captures of a collection: folders with a light file, named uniquely, with their held-out lights."""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..io.dataset import HELDOUT_FOLDER, find_heldout_folder, has_light_file
from ..model.errors import InputError

__all__ = ["HELDOUT_FOLDER", "Capture", "find_captures", "fingerprint", "image_size"]

log = logging.getLogger(__name__)

_SKIPPED = {"__pycache__", "node_modules"}


@dataclass(frozen=True)
class Capture:
    """One capture of a collection.

    Attributes:
        name: Unique within the collection, safe as a folder name: the capture's output is ``OUT/name``.
        folder: The dataset folder (its ``.lp`` file and images), as ``fit`` takes it.
        heldout: A folder of held-out lights and images for ``evaluate --heldout``; None when there is none
            or they are in the folder (``heldout.lp``).
        has_heldout: Whether held-out lights exist (else the collection holds out every k-th light).
    """

    name: str
    folder: Path
    heldout: Path | None
    has_heldout: bool


def find_captures(paths) -> list[Capture]:
    """The captures under ``paths``: each path is a capture folder, or a folder searched (depth first, in name order)
    for capture folders. A capture folder holds one light file (``lights.lp`` or a single ``*.lp`` other than
    ``heldout.lp``); its sub-folders are not searched. Raises ``InputError`` for a missing path or none found."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    found: list[tuple[Path, Path, Path | None]] = []  # (dataset folder, the folder that names it, held-out folder)
    seen: set[Path] = set()  # folders searched (a link back up is not followed twice)
    for given in paths:
        root = Path(given).absolute()  # absolute: a remote worker resolves nothing against its own working folder
        if not root.is_dir():
            raise InputError(f"{given}: not a folder; give capture folders or folders that contain them")
        if root.resolve() in seen:
            continue  # given twice, or inside a folder given before
        before = len(found)
        _search(root, found, seen)
        if len(found) == before:
            raise InputError(f"{root}: no capture found (a folder with a .lp light file and its images)")
    unique: dict[Path, tuple[Path, Path | None]] = {}
    for folder, named, heldout in found:
        unique.setdefault(folder.resolve(), (named, heldout))
    names = _unique_names([named for named, _ in unique.values()])
    return [Capture(name, folder, heldout, heldout is not None or (folder / "heldout.lp").is_file())
            for name, (folder, (named, heldout)) in zip(names, unique.items())]


def _search(folder: Path, found: list, seen: set[Path]) -> None:
    real = folder.resolve()
    if real in seen:
        return
    seen.add(real)
    if has_light_file(folder):
        if folder.name == HELDOUT_FOLDER and has_light_file(folder.parent):
            return  # the held-out lights of the capture above
        heldout = find_heldout_folder(folder)
        # SynthRTI: OBJECT/Dome beside OBJECT/Test, named OBJECT
        named = folder.parent if heldout is not None and heldout.parent != Path(os.path.abspath(folder)) else folder
        found.append((folder, named, heldout))
        return
    try:
        with os.scandir(folder) as listing:
            entries = sorted((e for e in listing if not e.name.startswith(".") and e.name not in _SKIPPED
                              and _is_folder(e)), key=lambda e: e.name)
    except OSError as error:
        advice = _ADVICE.get(error.errno, "check its permissions")
        raise InputError(f"{folder}: cannot list the folder ({error.strerror}); {advice}") from None
    with_lights = {e.name for e in entries if has_light_file(Path(e.path))}
    for entry in entries:
        if entry.name == HELDOUT_FOLDER and len(with_lights - {HELDOUT_FOLDER}) == 1:
            # the held-out lights of the capture beside it (OBJECT/Dome and OBJECT/Test), whatever the names' order
            continue
        _search(Path(entry.path), found, seen)


_ADVICE = {errno.ELOOP: "a symbolic link on the way points back at itself; fix or remove it",
           errno.ENOENT: "it went away meanwhile; run again"}


def _is_folder(entry: os.DirEntry) -> bool:
    """Whether a folder entry is a folder (links followed); an entry that cannot be followed (a link loop, a link
    to nothing readable) is skipped with a warning naming it."""
    try:
        return entry.is_dir()
    except OSError as error:
        log.warning("%s: skipped, it cannot be followed (%s); %s", entry.path, error.strerror,
                    _ADVICE.get(error.errno, "check its permissions"))
        return False


def _unique_names(folders: list[Path]) -> list[str]:
    """Folder names made safe (letters, digits, ``-``, ``_``, ``.``); where two are equal, their parents' names are
    prefixed until they differ (``museum-a/coin`` and ``museum-b/coin`` -> ``museum-a_coin``, ``museum-b_coin``)."""
    parts = [f.resolve().parts for f in folders]
    depth = [1] * len(folders)
    names = [_safe(p[-1]) for p in parts]
    while True:
        clashing = [k for k, name in enumerate(names) if names.count(name) > 1 and depth[k] < len(parts[k])]
        if not clashing:
            break
        for k in clashing:
            depth[k] += 1
            names[k] = _safe("_".join(parts[k][-depth[k]:]))
    seen: dict[str, int] = {}
    result = []
    for name in names:  # still equal only where the paths are (odd links): numbered
        seen[name] = seen.get(name, 0) + 1
        result.append(name if seen[name] == 1 else f"{name}-{seen[name]}")
    return result


def _safe(text: str) -> str:
    text = re.sub(r"[^A-Za-z0-9._-]+", "-", text.strip("/")).strip("-.") or "capture"
    return text[:120]


def fingerprint(capture: Capture) -> str:
    """A digest of the capture's files (relative paths, sizes, modification times; its held-out folder's too): a
    rerun redoes a capture whose files changed since it was finished, or since it failed."""
    digest = hashlib.sha256()
    for root in (capture.folder, capture.heldout):
        if root is None:
            continue
        for folder, subfolders, files in os.walk(root):
            subfolders[:] = sorted(d for d in subfolders if not d.startswith(".") and not (Path(
                folder) == capture.folder and d == HELDOUT_FOLDER
                                                                                            and capture.heldout
                                                                                           is not None))
            for name in sorted(files):
                if name.startswith("."):
                    continue
                path = Path(folder) / name
                try:
                    stat = path.stat()
                except OSError:
                    continue
                digest.update(f"{path.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode(
                    "utf-8", "surrogateescape"))
    return digest.hexdigest()[:32]


def image_size(capture: Capture) -> tuple[int, int]:
    """(width, height) in pixels of the capture's images, from its first image's header (nothing decoded)."""
    from ..io.dataset import find_light_file
    from ..io.images import image_header
    from ..io.lightfile import read_lights

    light_file = find_light_file(capture.folder)
    lights = read_lights(light_file, check_files=False)
    shape = image_header(light_file.parent / lights.filenames[0], max_pixels=None).shape
    return int(shape[1]), int(shape[0])
