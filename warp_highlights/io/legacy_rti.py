"""RTIViewer's files: ``.ptm`` (polynomial texture maps, format 1.2: ``PTM_FORMAT_RGB`` and ``PTM_FORMAT_LRGB``,
uncompressed or as JPEG streams, ``PTM_FORMAT_JPEG_RGB`` and ``PTM_FORMAT_JPEG_LRGB``) and ``.rti``
(hemispherical harmonics, RTI type 3), read into and written from per-pixel coefficients.

Both hold, per pixel and colour channel, the coefficients c_m of M basis functions of the light direction
(PTM: lu^2, lv^2, lu lv, lu, lv, 1 of the light's (x, y); HSH: ``relight.baselines.hsh_basis``), as bytes with a
scale and bias per coefficient; rows are stored bottom-up. ``LegacyRTI.coefficients`` is (H, W, M, 3) float32
in display units (1 = white, sRGB-encoded values as the viewers show them), rows top-down. In an LRGB PTM the
polynomial is the luminance, times the pixel's RGB: read here as its per-channel equivalent.

- ``.ptm``: the lines ``PTM_1.2``, the format, the width, the height, 6 scales, 6 integer biases, then the
  bytes: for RGB, each channel's (R, G, B) rows of 6 coefficients a pixel; for LRGB, the rows of 6 luminance
  coefficients a pixel, then the rows of R, G, B. A coefficient is (byte - bias) scale, in 0..255 units. The
  JPEG variants add the lines: the quality, then for each of the 18 (RGB) or 9 (LRGB) planes its transform,
  motion x and y (0 here), decoding order, reference plane (-1, or a plane it is predicted from: its value is
  the stream's plus the reference's (or 255 minus it, where the transform's bit 0 is set) minus 128, modulo
  256), JPEG size and side-information size; then each plane's greyscale JPEG followed by its side
  information (5-byte records: a big-endian offset and the byte there). Plane i is coefficient i mod 6 of
  block i div 6, the blocks of the uncompressed layout.
- ``.rti``: ``#`` comment lines, the RTI type (3), ``width height 3``, ``terms basis_type element_size``,
  ``terms`` float32 scales then biases (little-endian), then per pixel its R, G and B terms as bytes. A
  coefficient is byte / 255 scale + bias.
"""

from __future__ import annotations

import io
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from .atomic import atomic_file

__all__ = ["LEGACY_SUFFIXES", "LegacyRTI", "is_legacy_rti", "read_legacy_rti", "write_hsh_rti", "write_ptm"]

LEGACY_SUFFIXES = (".ptm", ".rti")
"""The RTIViewer files ``read_legacy_rti`` reads."""
MAX_SIDE = 1 << 16
"""The widest and tallest image a legacy file may declare (pixels): larger headers are refused before any
allocation."""
_HEADER_BYTES = 4096  # the text header of either format is read within this many bytes
_PTM_FORMATS = {"PTM_FORMAT_RGB": "rgb", "PTM_FORMAT_LRGB": "lrgb", "PTM_FORMAT_JPEG_RGB": "rgb",
                "PTM_FORMAT_JPEG_LRGB": "lrgb"}
_PTM_TERMS = 6


@dataclass(frozen=True)
class LegacyRTI:
    """A legacy RTI file's model: ``kind`` ``ptm`` or ``hsh``; ``coefficients`` (H, W, M, 3) float32 in display
    units, rows top-down; ``source``: what the file was (e.g. ``PTM_FORMAT_LRGB``)."""

    kind: str
    coefficients: np.ndarray
    source: str

    @property
    def width(self) -> int:
        return int(self.coefficients.shape[1])

    @property
    def height(self) -> int:
        return int(self.coefficients.shape[0])


def is_legacy_rti(path) -> bool:
    """Whether ``path`` names a ``.ptm`` or ``.rti`` file (by its suffix): what the looking commands read with
    ``read_legacy_rti`` rather than as a field."""
    return Path(path).suffix.lower() in LEGACY_SUFFIXES


def read_legacy_rti(path) -> LegacyRTI:
    """Read a ``.ptm`` or ``.rti`` file (``InputError``, one line, for what cannot be read)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from exc
    if data.startswith(b"PTM_1."):
        return _read_ptm(path, data)
    if data.startswith(b"#") or path.suffix.lower() == ".rti":
        return _read_hsh(path, data)
    raise InputError(f"{path}: neither a PTM (starting 'PTM_1.2') nor an HSH .rti file")


def write_ptm(path, coefficients: np.ndarray) -> None:
    """Write (H, W, 6, 3) PTM coefficients (display units, the order lu^2, lv^2, lu lv, lu, lv, 1) as an
    uncompressed ``PTM_FORMAT_RGB`` file, each coefficient quantised between its range over every pixel and
    channel (one scale and bias a coefficient, as the format has)."""
    coefficients = np.asarray(coefficients, np.float64) * 255.0
    height, width, terms, _ = coefficients.shape
    if terms != _PTM_TERMS:
        raise InputError(f"a PTM has 6 coefficients a channel, got {terms}")
    low = coefficients.min(axis=(0, 1, 3))
    high = coefficients.max(axis=(0, 1, 3))
    scale = np.where(high > low, (high - low) / 255.0, 1.0)
    bias = np.round(-low / scale).astype(np.int64)  # (byte - bias) scale = value: byte = value / scale + bias
    quantised = np.clip(np.round(coefficients / scale[:, None] + bias[:, None]), 0, 255).astype(np.uint8)
    body = quantised[::-1].transpose(3, 0, 1, 2)  # channel, rows bottom-up, pixel, coefficient
    header = "\n".join(["PTM_1.2", "PTM_FORMAT_RGB", str(width), str(height), " ".join(repr(float(s)) for s in scale),
                        " ".join(str(int(b)) for b in bias)]) + "\n"
    with atomic_file(path) as temporary:
        temporary.write_bytes(header.encode("ascii") + body.tobytes())


def write_hsh_rti(path, coefficients: np.ndarray) -> None:
    """Write (H, W, M, 3) HSH coefficients (display units; M = 4 or 9) as an ``.rti`` file (RTI type 3), each term
    quantised between its range over every pixel and channel."""
    coefficients = np.asarray(coefficients, np.float64)
    height, width, terms, _ = coefficients.shape
    low = coefficients.min(axis=(0, 1, 3))
    high = coefficients.max(axis=(0, 1, 3))
    scale = np.where(high > low, high - low, 1.0)
    quantised = np.clip(np.round(255.0 * (coefficients - low[:, None]) / scale[:, None]), 0, 255).astype(np.uint8)
    body = quantised[::-1].transpose(0, 1, 3, 2)  # rows bottom-up, pixel, channel, term
    header = f"#HSH1.2\n3\n{width} {height} 3\n{terms} 2 1\n".encode("ascii")
    with atomic_file(path) as temporary:
        temporary.write_bytes(header + struct.pack(f"<{terms}f", *scale) + struct.pack(f"<{terms}f", *low)
                              + body.tobytes())


def _lines(path: Path, data: bytes, count: int, skip_comments: bool = False, offset: int = 0) -> tuple[list[str], int]:
    """The next ``count`` text lines of the header from ``offset`` (``#`` lines skipped where asked) and the offset
    after them."""
    lines = []
    while len(lines) < count:
        end = data.find(b"\n", offset, _HEADER_BYTES)
        if end < 0:
            raise InputError(f"{path}: the header ends early or is too long (line {len(lines) + 1} missing)")
        line = data[offset:end].decode("latin-1").strip()
        offset = end + 1
        if skip_comments and line.startswith("#"):
            continue
        lines.append(line)
    return lines, offset


def _numbers(path: Path, line: str, count: int, what: str, kind=float) -> list:
    tokens = line.split()
    pattern = r"[+-]?\d+" if kind is int else r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?"
    if len(tokens) != count or not all(re.fullmatch(pattern, t) for t in tokens):
        raise InputError(f"{path}: expected {count} {what}, got {line[:60]!r}")
    values = [kind(t) for t in tokens]
    if kind is float and not all(math.isfinite(v) for v in values):
        raise InputError(f"{path}: the {what} are not finite")
    return values


def _size(path: Path, width: int, height: int) -> tuple[int, int]:
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise InputError(f"{path}: an image of {width}x{height} pixels is not a legacy RTI file's "
                         f"(1 to {MAX_SIDE} a side)")
    return width, height


def _body(path: Path, data: bytes, offset: int, size: int) -> np.ndarray:
    if len(data) - offset < size:
        raise InputError(f"{path}: truncated: {len(data) - offset} bytes of coefficients where the header needs "
                         f"{size}")
    return np.frombuffer(data, np.uint8, size, offset)


def _read_ptm(path: Path, data: bytes) -> LegacyRTI:
    (version, fmt), offset = _lines(path, data, 2)
    if version != "PTM_1.2":
        raise InputError(f"{path}: PTM version {version[:20]!r}; PTM_1.2 files are read")
    if fmt not in _PTM_FORMATS:
        raise InputError(f"{path}: {fmt[:30]!r} is not read here (PTM_FORMAT_RGB, PTM_FORMAT_LRGB and their JPEG "
                         "variants are)")
    rest, offset = _lines(path, data, 4, offset=offset)
    lines = [version, fmt, *rest]
    width, height = _size(path, *(_numbers(path, line, 1, "width/height", int)[0] for line in lines[2:4]))
    scale = np.array(_numbers(path, lines[4], _PTM_TERMS, "scales"), np.float64)
    bias = np.array(_numbers(path, lines[5], _PTM_TERMS, "biases", int), np.float64)
    pixels = width * height
    if "JPEG" in fmt:
        data, offset = _jpeg_planes(path, data, offset, width, height, _PTM_FORMATS[fmt]), 0
    if _PTM_FORMATS[fmt] == "rgb":
        raw = _body(path, data, offset, 3 * pixels * _PTM_TERMS).reshape(3, height, width, _PTM_TERMS)
        values = (raw.astype(np.float64) - bias) * scale / 255.0
        coefficients = values.transpose(1, 2, 3, 0)[::-1]
    else:
        raw = _body(path, data, offset, pixels * (_PTM_TERMS + 3))
        luminance = (raw[: pixels * _PTM_TERMS].reshape(height, width, _PTM_TERMS) - bias) * scale / 255.0
        rgb = raw[pixels * _PTM_TERMS :].reshape(height, width, 3) / 255.0
        coefficients = (luminance[..., :, None] * rgb[..., None, :])[::-1]
    return LegacyRTI("ptm", np.ascontiguousarray(coefficients, np.float32), fmt)


def _jpeg_planes(path: Path, data: bytes, offset: int, width: int, height: int, layout: str) -> bytes:
    """A JPEG PTM's planes decoded, predicted and corrected, as the uncompressed layout's bytes."""
    from PIL import Image, UnidentifiedImageError  # only JPEG PTMs need it
    count = 18 if layout == "rgb" else 9
    lines, offset = _lines(path, data, 8, offset=offset)
    table = [_numbers(path, line, count, what, int) for line, what in
             zip(lines[1:], ("transforms", "motion vectors x", "motion vectors y", "orders", "reference planes",
                             "JPEG sizes", "side-information sizes"))]
    transforms, motion_x, motion_y, order, reference, sizes, sides = (np.array(row, np.int64) for row in table)
    if motion_x.any() or motion_y.any():
        raise InputError(f"{path}: its planes use motion compensation, which is not read here")
    if sorted(order) != list(range(count)) or ((reference < -1) | (reference >= count)).any() \
            or (sizes < 0).any() or (sides < 0).any() or (sides % 5).any():
        raise InputError(f"{path}: the JPEG planes' order, references or sizes are not a valid table")
    if len(data) - offset < int(sizes.sum() + sides.sum()):
        raise InputError(f"{path}: truncated: the JPEG planes need {int(sizes.sum() + sides.sum())} bytes, "
                         f"{len(data) - offset} are there")
    planes, corrections = [], []
    for size, side in zip(sizes, sides):
        stream = data[offset : offset + size]
        offset += size
        try:
            with Image.open(io.BytesIO(stream)) as image:
                if image.size != (width, height):
                    raise InputError(f"{path}: a JPEG plane of {image.size[0]}x{image.size[1]} in a {width}x{height} "
                                     "PTM")
                planes.append(np.asarray(image.convert("L"), np.uint8).copy())
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise InputError(f"{path}: a JPEG plane cannot be decoded ({exc})") from None
        corrections.append(np.frombuffer(data, np.uint8, side, offset).reshape(-1, 5))
        offset += side
    for plane in np.argsort(order):  # in decoding order: a reference is decoded before the planes predicted from it
        if reference[plane] >= 0:
            base = planes[reference[plane]].astype(np.int64)
            base = 255 - base if transforms[plane] & 1 else base
            planes[plane] = ((planes[plane].astype(np.int64) + base - 128) % 256).astype(np.uint8)
        records = corrections[plane]
        if len(records):
            where = (records[:, :4].astype(np.int64) * [1 << 24, 1 << 16, 1 << 8, 1]).sum(axis=1)
            keep = where < width * height
            planes[plane].reshape(-1)[where[keep]] = records[keep, 4]
    if layout == "rgb":  # blocks R, G, B of 6 coefficients a pixel
        return np.stack(planes).reshape(3, _PTM_TERMS, height, width).transpose(0, 2, 3, 1).tobytes()
    luminance = np.stack(planes[:_PTM_TERMS], axis=-1)
    return luminance.tobytes() + np.stack(planes[_PTM_TERMS:], axis=-1).tobytes()


def _read_hsh(path: Path, data: bytes) -> LegacyRTI:
    lines, offset = _lines(path, data, 3, skip_comments=True)
    rti_type = _numbers(path, lines[0], 1, "RTI type", int)[0]
    if rti_type != 3:
        raise InputError(f"{path}: RTI type {rti_type} is not read here (type 3, hemispherical harmonics, is)")
    width, height, colours = _numbers(path, lines[1], 3, "numbers 'width height components'", int)
    _size(path, width, height)
    if colours != 3:
        raise InputError(f"{path}: {colours} colour components; RGB (3) files are read")
    terms = _numbers(path, lines[2], 3, "numbers 'terms basis_type element_size'", int)[0]
    if terms not in (4, 9):
        raise InputError(f"{path}: {terms} HSH terms; 4 or 9 (orders 2 and 3) are read")
    floats = _body(path, data, offset, 8 * terms)
    scale = np.frombuffer(floats[: 4 * terms].tobytes(), "<f4").astype(np.float64)
    bias = np.frombuffer(floats[4 * terms :].tobytes(), "<f4").astype(np.float64)
    if not (np.isfinite(scale).all() and np.isfinite(bias).all()):
        raise InputError(f"{path}: the scales or biases are not finite")
    raw = _body(path, data, offset + 8 * terms, width * height * 3 * terms).reshape(height, width, 3, terms)
    coefficients = (raw / 255.0 * scale + bias).transpose(0, 1, 3, 2)[::-1]
    return LegacyRTI("hsh", np.ascontiguousarray(coefficients, np.float32), f"HSH, {terms} terms")
