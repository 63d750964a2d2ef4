"""Light files: the RTI ``.lp`` (the count N, then N lines ``<image file> <x> <y> <z>``) and relight's JSON
files, a dome's ``.dome`` and a RelightLab project's ``.relight``.

Directions follow the ``LightSet`` convention (towards the light; x right, y up the image, z towards
the camera), which is also relight's.
"""

from __future__ import annotations

import codecs
import json
import math
import os
import re
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..model.errors import InputError
from ..model.lights import LightSet
from .atomic import atomic_file
from .images import IMAGE_EXTENSIONS

__all__ = ["LIGHT_FILE_SUFFIXES", "images_in_order", "read_lights", "read_lp", "write_lp"]

LIGHT_FILE_SUFFIXES = (".lp", ".relight", ".dome")
"""The light files ``read_lights`` reads, in the order a dataset folder's is looked for."""

_DUPLICATE_CHORD = 1e-6  # unit vectors closer than this (about 0.2 arc seconds) count as one direction
_DOT_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_COMMA_NUMBER = re.compile(r"^[+-]?(\d+,?\d*|,\d+)([eE][+-]?\d+)?$")
_COUNT = re.compile(r"^[+-]?\d+$")
_NATURAL = re.compile(r"(\d+)")
# a relight JSON file larger than this is not a light file (a 1,000-light dome with positions is about 300 KB)
JSON_LIGHT_FILE_MAX_BYTES = 16 << 20
_LIGHT_CONFIGURATIONS = {"spherical": "positionsSphere", "lights3d": "positions3d"}  # relight's; "directional": none


def read_lights(path, *, check_files: bool = True) -> LightSet:
    """Read a light file by its suffix: ``.lp`` (``read_lp``), or relight's ``.dome`` or ``.relight`` JSON
    (``read_relight_json``). ``InputError``, one line, for anything else or what cannot be read."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".dome", ".relight"):
        return read_relight_json(path, check_files=check_files)
    if suffix != ".lp":
        raise InputError(f"{path}: not a light file (one of {', '.join(LIGHT_FILE_SUFFIXES)})")
    return read_lp(path, check_files=check_files)


def read_lp(path, *, check_files: bool = True) -> LightSet:
    """Read an RTI light file: the count N, then N lines ``<image file> <x> <y> <z>``.

    Liberal in what it accepts: UTF-8 (with or without BOM) or UTF-16 with BOM, CRLF, blank lines,
    tabs, trailing spaces, decimal commas (when a line's numbers all use them), file names with
    spaces and backslashes, images in sub-folders (``jpg/name.jpg``), unnormalised vectors; lines of
    three numbers without file names (the lights paired with the folder's images in ``images_in_order``);
    a fifth column (a number after the direction on every line, e.g. an intensity: ignored).

    Args:
        path: The ``.lp`` file.
        check_files: Require every listed image to exist, relative to the file's folder, and to be
            listed once; for a file without names, that the folder holds as many images as lights (without
            this check such a file pairs them where the counts agree, else gives no file names).

    Raises:
        InputError: One line naming the file and line: unreadable or empty file, bad count,
            malformed line, zero vector, count mismatch, duplicate direction, missing or repeated image.
    """
    path = Path(path)
    lines = _numbered_lines(path)
    if not lines:
        raise InputError(f"{path}: empty light file; expected a count, then '<image file> <x> <y> <z>' lines")
    count = _parse_count(path, *lines[0])
    layout = _layout(path, lines[1:], check_files)
    entries = [_parse_entry(path, number, text, layout) for number, text in lines[1:]]
    if len(entries) != count:
        raise InputError(
            f"{path}:{lines[0][0]}: the count says {count} lights but {len(entries)} are listed; "
            "correct the count or the list"
        )
    line_numbers = [number for number, _ in lines[1:]]
    directions = np.array([vector for _, vector in entries])
    names = [name for name, _ in entries] if layout != "nameless" else _paired_names(path, count, check_files)
    lights = LightSet(directions, names)
    _check_duplicates(path, lights.directions, line_numbers)
    if check_files and layout != "nameless":
        _check_repeated_names(path, lights.filenames, line_numbers)
        _check_files(path, lights.filenames, line_numbers)
    return lights


def images_in_order(folder: Path) -> list[str]:
    """The names of the images (``IMAGE_EXTENSIONS``) in ``folder``, in natural order (case-insensitive, digits
    compared as numbers: ``img2`` before ``img10``): the order that pairs them with a light file that lists no
    names."""
    try:
        names = [entry.name for entry in os.scandir(folder)
                 if entry.is_file() and not entry.name.startswith(".")
                 and os.path.splitext(entry.name)[1].lower() in IMAGE_EXTENSIONS]
    except OSError as exc:
        raise InputError(f"{folder}: cannot list the images ({exc.strerror})") from exc
    return sorted(names, key=lambda name: [int(part) if part.isdigit() else part.lower()
                                           for part in _NATURAL.split(name)])


def _paired_names(path: Path, count: int, check_files: bool) -> list[str] | None:
    """The folder's images for a light file of ``count`` lights that names none (None where they cannot pair
    and ``check_files`` is off)."""
    names = images_in_order(path.parent)
    if len(names) == count:
        return names
    if not check_files:
        return None
    raise InputError(f"{path}: the light file lists {count} directions without image names, paired with the "
                     f"folder's images in name order, but the folder holds {len(names)} images "
                     f"({', '.join(IMAGE_EXTENSIONS)}); name each light's image in the light file")


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


def _is_number(token: str) -> bool:
    return bool(_DOT_NUMBER.match(token) or _COMMA_NUMBER.match(token))


def _layout(path: Path, lines: list[tuple[int, str]], check_files: bool) -> str:
    """How the file's light lines read: ``named`` (``<file> <x> <y> <z>``), ``nameless`` (every line three
    numbers) or ``fifth`` (every line a name, the direction and one more number). A name that ends in a
    number token reads as ``named`` where those names are the folder's files and the shorter ones are not."""
    tokens = [text.split() for _, text in lines]
    if tokens and all(len(t) == 3 and all(map(_is_number, t)) for t in tokens):
        return "nameless"
    if tokens and all(len(t) >= 5 and all(map(_is_number, t[-4:])) for t in tokens):
        if check_files and all(_is_file(path.parent / " ".join(t[:-3])) for t in tokens) \
                and not all(_is_file(path.parent / " ".join(t[:-4])) for t in tokens):
            return "named"
        return "fifth"
    return "named"


def _parse_entry(path: Path, number: int, text: str,
                 layout: str = "named") -> tuple[str | None, tuple[float, float, float]]:
    """One light line -> (file name with '/' separators, or None on a ``nameless`` line; the vector scaled by a
    power of two to a largest component in [0.5, 1), so that normalising it can neither overflow nor
    underflow)."""
    text = text.strip()
    if layout == "nameless":
        name, tokens = None, text.split()
    else:
        if layout == "fifth":
            text = text.rsplit(None, 1)[0]
        fields = text.rsplit(None, 3)  # the name may hold spaces; the numbers are the last 3 fields
        if len(fields) < 4:
            raise InputError(f"{path}:{number}: expected '<image file> <x> <y> <z>', got {_clip(text)!r}")
        name, *tokens = fields
        name = name.replace("\\", "/")
    commas = any("," in t for t in tokens) and not any("." in t for t in tokens)
    pattern = _COMMA_NUMBER if commas else _DOT_NUMBER
    for token in tokens:
        if not pattern.match(token):
            raise InputError(f"{path}:{number}: {token!r} is not a number in {_clip(text)!r}")
    vector = tuple(float(t.replace(",", ".")) for t in tokens)
    return name, _scaled_direction(path, number, vector)


def _scaled_direction(path: Path, where, vector) -> tuple[float, float, float]:
    """A light vector scaled by a power of two to a largest component in [0.5, 1) (``InputError`` for zero or
    not finite; ``where``: the line number or the entry's name)."""
    if not all(math.isfinite(v) for v in vector) or not any(vector):
        raise InputError(
            f"{path}:{where}: the light direction {tuple(vector)} is zero or not finite; give the direction towards "
            "the light"
        )
    exponent = math.frexp(max(abs(v) for v in vector))[1]
    return tuple(math.ldexp(v, -exponent) for v in vector)


def read_relight_json(path, *, check_files: bool = True) -> LightSet:
    """Read relight's JSON light files: a ``.dome`` (``directions`` as ``{x, y, z}`` objects, the images paired
    in ``images_in_order``) or a RelightLab ``.relight`` project (its ``images``, each ``filename`` in its
    ``folder`` relative to the file, those with ``skip`` left out, and its ``dome``'s directions, else each
    image's ``direction``). Where the dome's ``lightConfiguration`` is ``spherical`` or ``lights3d``, its
    ``positionsSphere`` or ``positions3d`` (millimetres) are kept as ``LightSet.positions``.
    ``check_files``: as ``read_lp``'s."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > JSON_LIGHT_FILE_MAX_BYTES:
            raise InputError(f"{path}: {size} bytes is too large for a light file; give the capture's .dome, "
                             ".relight or .lp file")
        document = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise InputError(f"{path}: light file not found") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: not a JSON light file ({_clip(str(exc))}); give relight's .dome or .relight "
                         "file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read light file ({exc.strerror})") from exc
    if not isinstance(document, dict):
        raise InputError(f"{path}: expected a JSON object holding the dome's 'directions'")
    project = path.suffix.lower() == ".relight"
    dome = document.get("dome") if project else document
    if not isinstance(dome, dict):
        raise InputError(f"{path}: the project holds no 'dome' object with the light directions")
    if project:
        filenames, keep, entries = _project_images(path, document)
        listed = dome.get("directions")
        directions = (_vectors(path, listed, "directions") if isinstance(listed, list) and len(listed) == len(entries)
                      else _vectors(path, [entry.get("direction") for entry in entries], "direction"))
        directions = [d for d, kept in zip(directions, keep) if kept]
    else:
        directions = _vectors(path, dome.get("directions"), "directions")
    if not directions:
        raise InputError(f"{path}: the light file holds no light directions")
    scaled = [_scaled_direction(path, f"light {i}", d) for i, d in enumerate(directions)]
    positions = None
    key = _LIGHT_CONFIGURATIONS.get(str(dome.get("lightConfiguration", "directional")))
    if key is not None and dome.get(key):
        positions = _vectors(path, dome.get(key), key)
        if project and len(positions) == len(keep):
            positions = [p for p, kept in zip(positions, keep) if kept]
        if len(positions) != len(scaled):
            raise InputError(f"{path}: {len(positions)} '{key}' for {len(scaled)} light directions")
        if not np.isfinite(positions).all():
            raise InputError(f"{path}: a light position in '{key}' is not finite")
    if not project:
        filenames = _paired_names(path, len(scaled), check_files)
    elif check_files:
        _check_repeated_names(path, filenames, [f"image {i}" for i in range(len(filenames))])
        _check_files(path, filenames, [f"image {i}" for i in range(len(filenames))])
    lights = LightSet(np.array(scaled), filenames, positions)
    _check_duplicates(path, lights.directions, [f"light {i}" for i in range(len(scaled))], words=("", ""))
    return lights


def _project_images(path: Path, document: dict) -> tuple[list[str], list[bool], list[dict]]:
    """A ``.relight`` project's images: the names of those kept (their ``folder`` joined, relative to the
    file), which are kept, and every entry."""
    images = document.get("images")
    if not isinstance(images, list) or not all(isinstance(image, dict) for image in images):
        raise InputError(f"{path}: the project has no 'images' list of {{'filename': ...}} objects")
    folder = document.get("folder", ".")
    if not isinstance(folder, str):
        raise InputError(f"{path}: the project's 'folder' is not a path")
    keep, names = [], []
    for i, image in enumerate(images):
        name = image.get("filename")
        if not isinstance(name, str) or not name.strip():
            raise InputError(f"{path}: image {i} of the project has no 'filename'")
        keep.append(not bool(image.get("skip", False)))
        if keep[-1]:
            names.append(os.path.normpath(os.path.join(folder, name.replace("\\", "/"))).replace(os.sep, "/"))
    return names, keep, images


def _vectors(path: Path, values, key: str) -> list[tuple[float, float, float]]:
    """``{x, y, z}`` objects (or ``[x, y, z]`` lists) as float triples; ``InputError`` naming ``key`` and the
    entry otherwise."""
    if not isinstance(values, list):
        raise InputError(f"{path}: no '{key}' list of {{x, y, z}} vectors")
    vectors = []
    for i, value in enumerate(values):
        triple = [value.get(axis) for axis in "xyz"] if isinstance(value, dict) else value
        if (not isinstance(triple, list) or len(triple) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in triple)):
            raise InputError(f"{path}: '{key}' entry {i} is not an {{x, y, z}} vector of numbers: "
                             f"{_clip(json.dumps(value))}")
        vectors.append(tuple(float(v) for v in triple))
    return vectors


def _check_duplicates(path: Path, directions: np.ndarray, line_numbers: list, words=("lines ", "")) -> None:
    pairs = cKDTree(directions).query_pairs(_DUPLICATE_CHORD)
    if pairs:
        a, b = min(pairs)
        raise InputError(
            f"{path}: {words[0]}{line_numbers[a]} and {words[1]}{line_numbers[b]} give the same light direction; "
            "remove one"
        )


def _check_repeated_names(path: Path, filenames: list[str], line_numbers: list[int]) -> None:
    """Refuse an image listed twice (compared as paths: ``a.jpg`` and ``./a.jpg`` are one file)."""
    first_line: dict[str, int] = {}
    for name, number in zip(filenames, line_numbers):
        key = os.path.normpath(name)
        if key in first_line:
            first = first_line[key]
            raise InputError(
                f"{path}:{number}: image {name!r} is listed again (first "
                f"{'on line ' if isinstance(first, int) else 'as '}{first}); each light needs its own image"
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
