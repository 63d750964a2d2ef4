"""The RTI light file (``.lp``): the count N, then N lines ``<image file> <x> <y> <z>``.

Directions follow the ``LightSet`` convention (towards the light; x right, y up the image, z towards
the camera).
"""

from __future__ import annotations

import codecs
import math
import os
import re
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..model.errors import InputError
from ..model.lights import LightSet
from .atomic import atomic_file

__all__ = ["read_lp", "write_lp"]

_DUPLICATE_CHORD = 1e-6  # unit vectors closer than this (about 0.2 arc seconds) count as one direction
_DOT_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_COMMA_NUMBER = re.compile(r"^[+-]?(\d+,?\d*|,\d+)([eE][+-]?\d+)?$")
_COUNT = re.compile(r"^[+-]?\d+$")


def read_lp(path, *, check_files: bool = True) -> LightSet:
    """Read an RTI light file: the count N, then N lines ``<image file> <x> <y> <z>``.

    Liberal in what it accepts: UTF-8 (with or without BOM) or UTF-16 with BOM, CRLF, blank lines,
    tabs, trailing spaces, decimal commas (when a line's numbers all use them), file names with
    spaces and backslashes, unnormalised vectors.

    Args:
        path: The ``.lp`` file.
        check_files: Require every listed image to exist, relative to the file's folder, and to be
            listed once.

    Raises:
        InputError: One line naming the file and line: unreadable or empty file, bad count,
            malformed line, zero vector, count mismatch, duplicate direction, missing or repeated image.
    """
    path = Path(path)
    lines = _numbered_lines(path)
    if not lines:
        raise InputError(f"{path}: empty light file; expected a count, then '<image file> <x> <y> <z>' lines")
    count = _parse_count(path, *lines[0])
    entries = [_parse_entry(path, number, text) for number, text in lines[1:]]
    if len(entries) != count:
        raise InputError(
            f"{path}:{lines[0][0]}: the count says {count} lights but {len(entries)} are listed; "
            "correct the count or the list"
        )
    line_numbers = [number for number, _ in lines[1:]]
    lights = LightSet(np.array([vector for _, vector in entries]), [name for name, _ in entries])
    _check_duplicates(path, lights.directions, line_numbers)
    if check_files:
        _check_repeated_names(path, lights.filenames, line_numbers)
        _check_files(path, lights.filenames, line_numbers)
    return lights


def write_lp(lights: LightSet, path, filenames: list[str] | None = None) -> None:
    """Write an RTI light file atomically (temp file in the same folder, then rename).

    Args:
        lights: The directions to write.
        path: Target ``.lp`` file.
        filenames: Image names to list; default ``lights.filenames``, else ``0000``, ``0001``, ...
            (4 digits, more when needed).
    """
    path = Path(path)
    names = filenames if filenames is not None else lights.filenames
    if names is None:
        names = [f"{i:04d}" for i in range(lights.light_count)]
    if len(names) != lights.light_count:
        raise InputError(f"{path}: {len(names)} file names for {lights.light_count} light directions")
    rows = [str(lights.light_count)]
    for name, (x, y, z) in zip(names, lights.directions):
        if not str(name).strip() or "\n" in str(name) or "\r" in str(name):
            raise InputError(f"{path}: image file name {str(name)!r} cannot be written to a light file")
        rows.append(f"{name} {float(x)!r} {float(y)!r} {float(z)!r}")
    with atomic_file(path, checked=False) as tmp:
        tmp.write_text("\n".join(rows) + "\n", encoding="utf-8")


def _numbered_lines(path: Path) -> list[tuple[int, str]]:
    """Non-blank lines of a text file with their 1-based line numbers."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: light file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read light file ({exc.strerror})") from exc
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            text = raw.decode("utf-16")
        except UnicodeDecodeError as exc:
            raise InputError(f"{path}: not valid UTF-16 text ({exc.reason}); save the light file as UTF-8") from None
    else:
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError:
            text = raw.decode("latin-1")
    return [(number, line) for number, line in enumerate(text.splitlines(), start=1) if line.strip()]


def _parse_count(path: Path, number: int, text: str) -> int:
    token = text.split()[0]
    if not _COUNT.match(token):
        raise InputError(f"{path}:{number}: the first line must be the light count, got {_clip(text)!r}")
    if len(token.lstrip("+-0")) > 18:  # int() refuses over 4300 digits; no capture has 10**18 lights
        raise InputError(
            f"{path}:{number}: the light count {_clip(token)} is absurdly large; give the number of lights")
    if int(token) < 1:
        raise InputError(f"{path}:{number}: the light count must be positive, got {int(token)}")
    return int(token)


def _parse_entry(path: Path, number: int, text: str) -> tuple[str, tuple[float, float, float]]:
    """One ``<file> <x> <y> <z>`` line -> (file name with '/' separators, vector scaled by a power of two
    to a largest component in [0.5, 1), so that normalising it can neither overflow nor underflow)."""
    fields = text.strip().rsplit(None, 3)  # the name may hold spaces; the numbers are the last 3 fields
    if len(fields) < 4:
        raise InputError(f"{path}:{number}: expected '<image file> <x> <y> <z>', got {_clip(text)!r}")
    name, *tokens = fields
    commas = any("," in t for t in tokens) and not any("." in t for t in tokens)
    pattern = _COMMA_NUMBER if commas else _DOT_NUMBER
    for token in tokens:
        if not pattern.match(token):
            raise InputError(f"{path}:{number}: {token!r} is not a number in {_clip(text)!r}")
    vector = tuple(float(t.replace(",", ".")) for t in tokens)
    if not all(math.isfinite(v) for v in vector) or not any(vector):
        raise InputError(
            f"{path}:{number}: the light direction {vector} is zero or not finite; give the direction towards the light"
        )
    exponent = math.frexp(max(abs(v) for v in vector))[1]
    return name.replace("\\", "/"), tuple(math.ldexp(v, -exponent) for v in vector)


def _check_duplicates(path: Path, directions: np.ndarray, line_numbers: list[int]) -> None:
    pairs = cKDTree(directions).query_pairs(_DUPLICATE_CHORD)
    if pairs:
        a, b = min(pairs)
        raise InputError(
            f"{path}: lines {line_numbers[a]} and {line_numbers[b]} give the same light direction; remove one"
        )


def _check_repeated_names(path: Path, filenames: list[str], line_numbers: list[int]) -> None:
    """Refuse an image listed twice (compared as paths: ``a.jpg`` and ``./a.jpg`` are one file)."""
    first_line: dict[str, int] = {}
    for name, number in zip(filenames, line_numbers):
        key = os.path.normpath(name)
        if key in first_line:
            raise InputError(
                f"{path}:{number}: image {name!r} is listed again (first on line {first_line[key]}); "
                "each light needs its own image"
            )
        first_line[key] = number


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except (OSError, ValueError):  # a name too long or holding a NUL byte names no file
        return False


def _check_files(path: Path, filenames: list[str], line_numbers: list[int]) -> None:
    folder = path.parent
    for name, number in zip(filenames, line_numbers):
        if not _is_file(folder / name):
            try:
                mode = (folder / name).stat().st_mode
            except (OSError, ValueError):
                raise InputError(
                    f"{path}:{number}: image {name!r} not found in {folder}; fix the name or add the image") from None
            from .images import file_kind

            raise InputError(f"{path}:{number}: image {name!r} in {folder} is not a regular file but "
                             f"{file_kind(mode)}; replace it by the image file")


def _clip(text: str, limit: int = 60) -> str:
    text = text.strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."
