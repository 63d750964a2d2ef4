"""Image files in and out: OpenEXR (linear), PNG and TIFF 8/16-bit, JPEG (sRGB), float TIFF (linear),
as float32 NumPy arrays.

Arrays are ``(H, W)`` for grayscale or ``(H, W, 3)`` for RGB, row 0 at the top of the image. Pixel
values are linear radiance (EXR as stored; PNG and JPEG decoded with the sRGB transfer function unless
the caller says the file holds linear values). Every write goes to a temporary file in the target
folder, then replaces the target, so a failed write never leaves half a file.

The readers refuse, in one line naming the file, an image over a pixel budget (``max_pixels``,
default :data:`DEFAULT_MAX_PIXELS`), checked from the header before any pixel is decoded, and a damaged
or truncated file (never a grey-filled guess).

PNG, JPEG and TIFF pixels are decoded by OpenImageIO (8 and 16 bits per channel, grey, RGB, palette,
with or without alpha; float TIFF), which also writes 16-bit PNG and TIFF; EXIF orientation is applied
(a camera's portrait JPEG comes out upright), and an embedded ICC profile other than sRGB is named
once per profile in the ``warp_highlights`` log and converted to sRGB by Pillow's ImageCms where it
can (8-bit RGB; otherwise the values are read as sRGB). Headers of PNG and JPEG
files are read with Pillow, whose parser sees a decompression bomb's size without decoding it; EXR goes
through OpenEXR. Each library is imported inside the functions that use it.

This module holds one thing: reading and writing single image files.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import math
import os
import stat
import struct
import sys
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from .atomic import atomic_file

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "IMAGE_EXTENSIONS",
    "ImageHeader",
    "display_rgb8",
    "encode_levels",
    "file_kind",
    "image_encoding",
    "image_header",
    "image_shape",
    "image_size",
    "linear_to_srgb",
    "quiet_native_stderr",
    "read_image",
    "read_pixels",
    "srgb_to_linear",
    "write_image",
]

IMAGE_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg", ".tif", ".tiff")
"""File extensions :func:`read_image` and :func:`write_image` accept (case-insensitive)."""

_TIFF_SUFFIXES = (".tif", ".tiff")
_OIIO_FLOATS = ("half", "float", "double")  # OpenImageIO's stored formats that hold linear floats
_EXIF_ORIENTATIONS = {  # EXIF Orientation -> what turns the stored rows upright (numpy, rows down)
    1: lambda a: a,
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.swapaxes(0, 1),
    6: lambda a: a.swapaxes(0, 1)[:, ::-1],
    7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
    8: lambda a: a.swapaxes(0, 1)[::-1],
}
_REPORTED_PROFILES: set[str] = set()  # ICC profiles already named in the log (once per profile and process)
_PIL_GRAY16_MODES = {"I;16", "I;16B", "I;16L", "I;16N", "I"}
_PIL_GRAY8_MODES = {"1", "L", "LA", "La"}
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error)  # what Pillow raises on bad files
_PIL_FORMATS = ("PNG", "JPEG")  # what Pillow may take a file for, whatever its extension says
_EXIF_ORIENTATION_TAG = 0x0112
_READ_LOCK = threading.RLock()  # Pillow's reads set process-wide limits

DEFAULT_MAX_PIXELS = 160_000_000
"""Most pixels (width x height) an image may have before the readers refuse it: 160 megapixels.

The largest single-shot camera backs used for RTI and cultural-heritage capture are 150 MP (Phase
One IQ4 150MP: 14204 x 10652 = 151.3 MP); 160 MP admits them with a margin. An image at the limit
takes 1.9 GB as float32 RGB once read. A decompression bomb (a few kB of PNG claiming 20000 x 20000 = 400 MP,
4.8 GB as float32 RGB) is refused from its header. ``max_pixels=None`` lifts the limit; the command
line raises it with ``--max-megapixels N``.
"""


def srgb_to_linear(x) -> np.ndarray:
    """Decode sRGB-encoded values to linear ones (IEC 61966-2-1 piecewise transfer function).

    Args:
        x: Encoded values, nominally in [0, 1]; any shape.

    Returns:
        Linear values, same shape; float32 input stays float32, anything else becomes float64.
    """
    x = _as_float(x)
    curve = ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(x <= 0.04045, x / 12.92, curve).astype(x.dtype, copy=False)


def linear_to_srgb(x) -> np.ndarray:
    """Encode linear values with the sRGB transfer function (inverse of :func:`srgb_to_linear`).

    Args:
        x: Linear values, nominally in [0, 1]; any shape.

    Returns:
        Encoded values, same shape; float32 input stays float32, anything else becomes float64.
    """
    x = _as_float(x)
    curve = 1.055 * np.maximum(x, 0.0031308) ** (1.0 / 2.4) - 0.055
    return np.where(x <= 0.0031308, x * 12.92, curve).astype(x.dtype, copy=False)


def display_rgb8(image) -> np.ndarray:
    """Linear image (H, W), (H, W, 1) or (H, W, 3) -> (H, W, 3) uint8 sRGB for the screen.

    Values are clipped to [0, 1] (1 is display white), NaN shows as black and +inf as white.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"a displayed image must be (H, W), (H, W, 1) or (H, W, 3), got {image.shape}")
    encoded = linear_to_srgb(np.clip(np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0))
    return np.round(encoded * 255.0).astype(np.uint8)


def read_image(path, *, linear: bool = False, max_pixels: int | None = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read an image file as linear float32 values.

    Args:
        path: An ``.exr``, ``.png`` or ``.tif``/``.tiff`` (8 or 16 bits per channel; a float TIFF
            holds linear values, as EXR does) or ``.jpg``/``.jpeg`` file.
        linear: integer PNG/JPEG/TIFF only: the stored values are already linear; scale to [0, 1]
            but skip the sRGB decode.
        max_pixels: Refuse an image of more pixels (width x height) than this, seen in its header
            before any pixel is decoded; None for no limit.

    Returns:
        float32 array ``(H, W)`` for grayscale, ``(H, W, 3)`` for colour, upright (EXIF orientation
        applied). Alpha is dropped; palette images are expanded to RGB.

    Raises:
        InputError: Missing file, unsupported extension, more than ``max_pixels`` pixels, or a file
            that cannot be decoded (damaged or truncated).
    """
    pixels = read_pixels(path, linear=linear, max_pixels=max_pixels)
    # an EXR's values as stored (half, or a view of its interleaved channels) into a fresh float32 array; the
    # other readers' float32 arrays are fresh already
    return pixels.astype(np.float32) if Path(path).suffix.lower() == ".exr" or pixels.dtype != np.float32 else pixels


def read_pixels(path, *, linear: bool = False, max_pixels: int | None = DEFAULT_MAX_PIXELS,
                header: ImageHeader | None = None) -> np.ndarray:
    """:func:`read_image`'s values before its float32 copy: an EXR's channels as stored (float16, float32
    or uint32; an ``(H, W, 3)`` view of its interleaved R, G, B, or ``(H, W)``), any other file as
    ``read_image`` returns it. Widened to float32 (``astype``, or copied into a float32 array) they are
    ``read_image``'s values exactly: a caller that copies them into a float32 stack anyway makes one copy.

    ``header``: the file's :func:`image_header`, read and checked before (the loader reads every
    image's header first): not read again, unless the file has changed since (its size or modification
    time). Raises as :func:`read_image`."""
    path, suffix, stamp = _stamped_image(path)
    if header is not None and header.stamp != stamp:
        header = None  # another file in its place since its header was read: read and checked again
    if suffix == ".exr":
        return _read_exr(path, max_pixels, header=header)
    if header is None:
        _header(path, suffix, max_pixels)  # the pixel budget, before anything is decoded
    pixels = _read_with_oiio(path)
    if pixels.dtype == np.float32:
        return pixels
    return _decode_levels(pixels, linear=linear)


def write_image(path, image, *, half: bool = False, bits: int = 8, linear: bool = False) -> None:
    """Write an image, choosing the format from the file extension; atomic (temp file + rename).

    Args:
        path: Target ``.exr``, ``.png``, ``.tif``/``.tiff``, ``.jpg`` or ``.jpeg`` file; missing parent
            folders are made.
        image: Linear values, ``(H, W)`` (written as one channel, ``Y`` in EXR) or ``(H, W, 3)``.
        half: EXR only: store 16-bit half floats instead of float32.
        bits: PNG and TIFF: 8 or 16 bits per channel. JPEG is always 8-bit.
        linear: PNG/JPEG/TIFF only: store the values as they are (clipped to [0, 1]) instead of
            sRGB-encoding them.

    Raises:
        InputError: Unsupported extension, an option the format does not have, or a bad array shape.
    """
    path = Path(path)
    suffix = _checked_suffix(path)
    image = _checked_image(path, image)
    if half and suffix != ".exr":
        raise InputError(f"{path}: half floats are an EXR option; use a .exr file or drop half")
    if bits not in (8, 16) or (bits == 16 and suffix not in (".png", *_TIFF_SUFFIXES)):
        raise InputError(f"{path}: bits={bits} is not possible; PNG and TIFF take 8 or 16, JPEG only 8, EXR none")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, checked=False) as tmp:
        if suffix == ".exr":
            _write_exr(tmp, image, half=half)
        elif bits == 16 or suffix in _TIFF_SUFFIXES:
            _write_with_oiio(tmp, "tiff" if suffix in _TIFF_SUFFIXES else "png",
                             encode_levels(image, 2**bits - 1, linear=linear))
        else:
            _write_with_pillow(tmp, suffix, encode_levels(image, 2**bits - 1, linear=linear))


def image_size(path, *, max_pixels: int | None = DEFAULT_MAX_PIXELS) -> tuple[int, int]:
    """Size of an image file from its header, without decoding the pixels.

    Args:
        path: An ``.exr``, ``.png``, ``.tif``/``.tiff``, ``.jpg`` or ``.jpeg`` file.
        max_pixels: Refuse an image of more pixels (width x height) than this; None for no limit.

    Returns:
        ``(width, height)`` in pixels, upright (EXIF orientation applied).

    Raises:
        InputError: Missing file, unsupported extension, an unreadable header, or more than
            ``max_pixels`` pixels.
    """
    path, suffix = _existing_image(path)
    if suffix == ".exr":
        width, height, _, _ = _exr_header(path, max_pixels)
        return width, height
    width, height, _ = _header(path, suffix, max_pixels)
    return width, height


def image_shape(path, *, max_pixels: int | None = DEFAULT_MAX_PIXELS) -> tuple[int, ...]:
    """The shape :func:`read_image` returns, ``(H, W)`` or ``(H, W, 3)``, from the header alone.

    Args:
        path: An ``.exr``, ``.png``, ``.tif``/``.tiff``, ``.jpg`` or ``.jpeg`` file.
        max_pixels: Refuse an image of more pixels (width x height) than this; None for no limit.

    Raises:
        InputError: As :func:`image_size`, and an EXR with neither R, G, B nor Y channels.
    """
    return image_header(path, max_pixels=max_pixels).shape


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header says, as :func:`image_header` read and checked it: the ``shape``
    :func:`read_image` returns; for an EXR, the channels it reads (``exr_channels``; None otherwise) and
    whether OpenEXR can give its R, G and B as one interleaved channel (``exr_grouped``); the file's size
    and modification time then (``stamp``, bytes and ns)."""

    shape: tuple[int, ...]
    exr_channels: tuple[str, ...] | None = None
    exr_grouped: bool = False
    stamp: tuple[int, int] | None = None


def image_header(path, *, max_pixels: int | None = DEFAULT_MAX_PIXELS) -> ImageHeader:
    """:func:`image_shape`'s header, kept for :func:`read_pixels` (which then does not read it again).
    Raises as :func:`image_shape`."""
    path, suffix, stamp = _stamped_image(path)
    if suffix == ".exr":
        width, height, names, grouped = _exr_header(path, max_pixels)
        keep = _exr_channels_to_keep(path, names)
        return ImageHeader((height, width, 3) if len(keep) == 3 else (height, width), keep, grouped, stamp)
    width, height, colour = _header(path, suffix, max_pixels)
    return ImageHeader((height, width, 3) if colour else (height, width), stamp=stamp)


def image_encoding(path, *, linear: bool = False) -> dict:
    """How an image file stores its values, from its header: ``{"format": "PNG" | "JPEG" | "TIFF" |
    "EXR", "bits": bits per channel, "values": "sRGB" | "linear", "profile": ICC profile name or None}``
    (``linear`` as :func:`read_image` takes it; EXR and float TIFF hold linear values)."""
    path, suffix = _existing_image(path)
    if suffix == ".exr":
        import OpenEXR

        try:
            with quiet_native_stderr():
                channel = next(iter(OpenEXR.File(str(path), header_only=True).parts[0].header["channels"]))
            bits = 16 if "HALF" in str(channel.type).upper() else 32
        except Exception as exc:  # noqa: BLE001 (OpenEXR raises many kinds)
            raise _unreadable(path, exc) from exc
        return {"format": "EXR", "bits": bits, "values": "linear", "profile": None}
    spec = _oiio_spec(path)
    stored = str(spec.format)
    floating = stored in _OIIO_FLOATS
    bits = (spec.get_int_attribute("oiio:BitsPerSample", 0)
            or {"uint8": 8, "uint16": 16, "half": 16, "float": 32, "double": 64}.get(stored, 16))
    icc = spec.getattribute("ICCProfile")
    profile = _icc_profile(bytes(np.asarray(icc, dtype=np.uint8)))[0] if icc is not None and len(icc) else None
    name = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(suffix, "TIFF")
    return {"format": name, "bits": int(bits), "values": "linear" if floating or linear else "sRGB", "profile": profile}


# --- helper functions --------------------------------------------------------------------------


def _as_float(x) -> np.ndarray:
    x = np.asarray(x)
    return x if x.dtype in (np.float32, np.float64) else x.astype(np.float64)


def _checked_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in IMAGE_EXTENSIONS:
        raise InputError(
            f"{path}: unsupported image type '{path.suffix}'; supported: {', '.join(IMAGE_EXTENSIONS)}"
        )
    return suffix


def _checked_image(path: Path, image) -> np.ndarray:
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or 0 in image.shape:
        raise InputError(f"{path}: cannot write an image of shape {image.shape}; expected (H, W) or (H, W, 3)")
    return image


def _unreadable(path: Path, exc: Exception) -> InputError:
    reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return InputError(f"{path}: cannot read image ({reason}); the file is damaged or not an image")


def _existing_image(path) -> tuple[Path, str]:
    """``(Path, lower-case suffix)`` of an existing image file of a supported type."""
    return _stamped_image(path)[:2]


def _stamped_image(path) -> tuple[Path, str, tuple[int, int]]:
    """``_existing_image`` and the file's (size, modification time in ns), from the one ``stat`` that finds it."""
    path = Path(path)
    suffix = _checked_suffix(path)
    try:
        status = path.stat()
    except (OSError, ValueError):  # as Path.is_file: missing, unreadable folder, bad name
        status = None
    if status is None:
        raise InputError(f"{path}: image file not found")
    if not stat.S_ISREG(status.st_mode):
        raise InputError(f"{path}: is not a regular file but {file_kind(status.st_mode)}; give an image file")
    return path, suffix, (status.st_size, status.st_mtime_ns)


def file_kind(mode: int) -> str:
    """What a file of ``os.stat`` mode ``mode`` is, in words ("a folder", "a FIFO (named pipe)", ...)."""
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
             (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
    return next((words for test, words in kinds if test(mode)), "a special file")


def _check_pixels(path: Path, size: str, pixels: int, max_pixels: int | None) -> None:
    """Refuse an image of ``pixels`` pixels (``size`` says how, e.g. ``'20000x20000'``) over ``max_pixels``."""
    if max_pixels is not None and pixels > max_pixels:
        raise InputError(
            f"{path}: image is {size} ({pixels / 1e6:.1f} megapixels), over the limit of {max_pixels / 1e6:g} "
            f"megapixels; if it is a genuine capture, pass --max-megapixels {math.ceil(pixels / 1e6)} "
            "(max_pixels in Python) to read it"
        )


@contextlib.contextmanager
def _pillow_image(path: Path, max_pixels: int | None) -> Iterator:
    """Open a PNG or JPEG with Pillow under this module's limits; yields it with its pixels not decoded.

    Pillow's own decompression-bomb check is off for the read (``_check_pixels`` takes its place,
    from the header size) and truncated files are refused (``LOAD_TRUNCATED_IMAGES`` is False: a cut
    JPEG is not filled with grey). Both are process-wide settings, so reads take a lock and restore them.
    Errors raised inside the ``with`` block by Pillow become one-line ``InputError``s naming the file.
    """
    from PIL import Image, ImageFile

    with _READ_LOCK:
        saved = Image.MAX_IMAGE_PIXELS, ImageFile.LOAD_TRUNCATED_IMAGES
        Image.MAX_IMAGE_PIXELS, ImageFile.LOAD_TRUNCATED_IMAGES = None, False
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(path, formats=_PIL_FORMATS) as im:
                    width, height = im.size
                    _check_pixels(path, f"{width}x{height}", width * height, max_pixels)
                    yield im
        except InputError:
            raise
        except (*_PIL_ERRORS, Image.DecompressionBombError) as exc:
            raise _unreadable(path, exc) from exc
        finally:
            Image.MAX_IMAGE_PIXELS, ImageFile.LOAD_TRUNCATED_IMAGES = saved


def _header(path: Path, suffix: str, max_pixels: int | None) -> tuple[int, int, bool]:
    """``(width, height, colour)`` of a PNG, JPEG or TIFF as :func:`read_image` returns it (upright),
    from its header; refuses more than ``max_pixels`` pixels."""
    if suffix in _TIFF_SUFFIXES:
        width, height, channels, orientation = _oiio_header(path, max_pixels)
        colour = channels >= 3
    else:
        with _pillow_image(path, max_pixels) as im:
            (width, height), colour = im.size, im.mode not in _PIL_GRAY8_MODES | _PIL_GRAY16_MODES
            orientation = im.getexif().get(_EXIF_ORIENTATION_TAG, 1)  # JPEG's APP1 or PNG's eXIf chunk
    return (height, width, colour) if orientation in (5, 6, 7, 8) else (width, height, colour)


def _oiio_spec(path: Path):
    """OpenImageIO's header (``ImageSpec``) of a PNG, JPEG or TIFF; one line naming the file when it cannot be read."""
    import OpenImageIO as oiio

    with quiet_native_stderr():
        image = oiio.ImageInput.open(str(path))
        if image is None:
            raise _unreadable(path, RuntimeError(oiio.geterror() or "unknown format"))
        spec = image.spec()
        image.close()
    return spec


def _icc_profile(icc: bytes):
    """(name, Pillow ``ImageCmsProfile`` or None) of an embedded ICC profile ('unreadable (...)' when it is not one)."""
    from PIL import ImageCms

    try:
        profile = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        return ImageCms.getProfileDescription(profile).strip(), profile
    except (OSError, ImageCms.PyCMSError) as exc:
        return f"unreadable ({exc})", None


def _oiio_header(path: Path, max_pixels: int | None) -> tuple[int, int, int, int]:
    """``(stored width, stored height, channels other than alpha, EXIF orientation)`` from a TIFF's
    header (OpenImageIO); refuses more than ``max_pixels`` pixels."""
    spec = _oiio_spec(path)
    _check_pixels(path, f"{spec.width}x{spec.height}", spec.width * spec.height, max_pixels)
    channels = spec.nchannels - (spec.alpha_channel >= 0)
    return spec.width, spec.height, channels, spec.get_int_attribute("Orientation", 1)


_QUIET_LOCK = threading.Lock()
_quiet = {"depth": 0, "saved": None}  # readers inside quiet_native_stderr now, and the real fd 2 meanwhile


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Discard what C/C++ code prints on file descriptor 2 meanwhile (OpenEXR, libpng and libjpeg print
    their errors there too, Warp its CUDA-driver warning).

    The errors still arrive as exceptions. Python's ``sys.stderr`` is flushed first. Threads share the
    redirection: the first one in points fd 2 at the null device, the last one out points it back, so
    readers in threads decode at once (output of other threads in that time is lost)."""
    with _QUIET_LOCK:
        if _quiet["depth"] == 0:
            try:
                sys.stderr.flush()
                saved = os.dup(2)
            except (OSError, ValueError, AttributeError):  # no file descriptor 2 (embedded interpreters)
                saved = None
            if saved is not None:
                try:
                    null = os.open(os.devnull, os.O_WRONLY)
                    try:
                        os.dup2(null, 2)
                    finally:
                        os.close(null)
                except OSError:  # no null device or no descriptor left: fd 2 stays as it is
                    os.close(saved)
                    saved = None
            _quiet["saved"] = saved
        _quiet["depth"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _quiet["depth"] -= 1
            saved = _quiet["saved"]
            if _quiet["depth"] == 0 and saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
                _quiet["saved"] = None


def _exr_header(path: Path, max_pixels: int | None) -> tuple[int, int, list[str], bool]:
    """``(width, height, channel names, grouped)`` of an EXR's first part, from the headers alone; ``grouped``:
    it has R, G and B, and they and any A are sampled at every pixel (OpenEXR then gives them as one interleaved
    channel, unless their pixel types differ, which the headers do not show).

    The pixel budget counts every part (OpenEXR reads them all). Deep images and empty or inverted
    data windows are refused: none of them allocates anything.
    """
    import OpenEXR

    try:
        with quiet_native_stderr():
            headers = [part.header for part in OpenEXR.File(str(path), header_only=True).parts]
        windows = [tuple(int(v) for corner in header["dataWindow"] for v in corner) for header in headers]
        names = [channel.name for channel in headers[0]["channels"]]
        grouped = {"R", "G", "B"} <= set(names) and all(
            channel.xSampling == channel.ySampling == 1 for channel in headers[0]["channels"]
            if channel.name in ("R", "G", "B", "A"))
        deep = any(header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile) for header in headers)
    except Exception as exc:  # noqa: BLE001 (OpenEXR raises RuntimeError, ValueError, KeyError, UnicodeError, ...)
        raise _unreadable(path, exc) from exc
    if deep:
        raise InputError(f"{path}: deep EXR images are not supported; save a flat (scanline or tiled) EXR")
    sizes = [(x1 - x0 + 1, y1 - y0 + 1) for x0, y0, x1, y1 in windows]
    if any(width < 1 or height < 1 for width, height in sizes):
        raise _unreadable(path, ValueError(f"empty or inverted dataWindow {windows[0]}"))
    width, height = sizes[0]
    described = f"{width}x{height}" if len(sizes) == 1 else f"{len(sizes)} parts, the first {width}x{height}"
    _check_pixels(path, described, sum(w * h for w, h in sizes), max_pixels)
    return width, height, names, grouped


def _exr_channels_to_keep(path: Path, names) -> tuple[str, ...]:
    """The channels ``read_image`` keeps: R, G, B; else Y; else the only one."""
    if {"R", "G", "B"} <= set(names):
        return ("R", "G", "B")
    if "Y" in names:
        return ("Y",)
    if len(names) == 1:
        return (names[0],)
    raise InputError(f"{path}: EXR channels {sorted(names)} are neither R,G,B nor Y; cannot pick the image")


@lru_cache(maxsize=2)
def _srgb_table(levels: int) -> np.ndarray:
    """float32 linear value of every code 0..levels-1 of an sRGB-encoded channel."""
    return srgb_to_linear(np.arange(levels, dtype=np.float64) / (levels - 1)).astype(np.float32)


def _decode_levels(levels: np.ndarray, *, linear: bool) -> np.ndarray:
    """Integer codes (uint8 or uint16) -> float32 in [0, 1], sRGB-decoded unless ``linear``."""
    count = 256 if levels.dtype == np.uint8 else 65536
    if linear:
        return levels.astype(np.float32) / np.float32(count - 1)
    return _srgb_table(count)[levels]


ENCODE_BLOCK = 1 << 20
"""Values encoded at a time by ``encode_levels`` (its temporaries stay a few MB)."""
_SRGB8_CELLS = 1 << 16
"""Cells of [0, 1] in ``encode_levels``' 8-bit table: narrower than the closest two code starts (3e-4 apart)."""


def encode_levels(image: np.ndarray, top: int, *, linear: bool) -> np.ndarray:
    """Linear float image -> integer codes 0..top (uint8 or uint16), sRGB-encoded unless ``linear``: the
    code nearest to the encoded value, NaN as 0, clipped to [0, 1] first.

    8-bit sRGB codes come from a table over ``_SRGB8_CELLS`` cells of [0, 1], each holding the code at
    its start and the one value inside it where the next code begins (float64): two reads and a
    comparison per value, the codes of rounding ``linear_to_srgb`` in float64 (but at exact ties),
    several times faster than the power function. A block of values at a time."""
    kind = np.uint8 if top == 255 else np.uint16
    image = np.asarray(image)
    flat = image.reshape(-1)
    codes = np.empty(flat.shape, kind)
    table = _srgb8_table() if top == 255 and not linear else None
    for first in range(0, flat.size, ENCODE_BLOCK):
        block = np.clip(np.nan_to_num(flat[first : first + ENCODE_BLOCK], nan=0.0), 0.0, 1.0)
        if table is not None:
            start_codes, next_starts = table
            cells = np.minimum((block * _SRGB8_CELLS).astype(np.int32), _SRGB8_CELLS - 1)
            codes[first : first + ENCODE_BLOCK] = start_codes[cells] + (block >= next_starts[cells])
        else:
            encoded = block if linear else linear_to_srgb(block)
            codes[first : first + ENCODE_BLOCK] = np.rint(encoded * top)
    return codes.reshape(image.shape)


@lru_cache(maxsize=1)
def _srgb8_table() -> tuple[np.ndarray, np.ndarray]:
    """Per cell of [0, 1]: the 8-bit sRGB code at its start (uint8) and where in it the next code begins
    (float32; 2 where no code begins in it)."""
    starts = srgb_to_linear((np.arange(1, 256, dtype=np.float64) - 0.5) / 255)  # where code k begins, k = 1..255
    edges = np.arange(_SRGB8_CELLS, dtype=np.float64) / _SRGB8_CELLS
    start_codes = np.searchsorted(starts, edges, side="right").astype(np.uint8)
    following = np.searchsorted(starts, edges, side="right")  # index of the next start after each cell's start
    next_starts = np.full(_SRGB8_CELLS, 2.0)
    has_next = following < len(starts)
    inside = has_next.copy()
    inside[has_next] = starts[following[has_next]] < edges[has_next] + 1.0 / _SRGB8_CELLS
    next_starts[inside] = starts[following[inside]]
    return start_codes, next_starts


def _read_exr(path: Path, max_pixels: int | None, *, header: ImageHeader | None = None) -> np.ndarray:
    """EXR -> its (H, W) or (H, W, 3) channels as stored (see ``read_pixels``); the header is checked first (unless
    ``header`` gives it, checked already), so nothing oversized is allocated. R, G and B come from OpenEXR as
    one interleaved channel ("RGB", or "RGBA" whose alpha is dropped) where the header allows: no stacking, one
    widening copy after; else (and where their pixel types differ) each channel alone."""
    import OpenEXR

    if header is None or header.exr_channels is None:
        width, height, names, grouped = _exr_header(path, max_pixels)
        keep = _exr_channels_to_keep(path, names)
    else:
        (height, width), keep, grouped = header.shape[:2], header.exr_channels, header.exr_grouped
    try:
        with quiet_native_stderr():
            channels = {}
            if len(keep) == 3 and grouped:
                try:
                    channels = {name: channel.pixels for name, channel in OpenEXR.File(str(path)).channels().items()}
                except Exception:  # noqa: BLE001 (R, G and B of several pixel types are not grouped: read apart below)
                    channels = {}
                interleaved = next((channels[name] for name in ("RGB", "RGBA") if name in channels), None)
                if (isinstance(interleaved, np.ndarray)
                    and interleaved.shape in ((height, width, 3), (height, width, 4))):
                    return interleaved[..., :3]
            if not all(name in channels for name in keep):  # not grouped as above (or not read): each channel alone
                channels = {name: channel.pixels
                            for name, channel in OpenEXR.File(str(path), separate_channels=True).channels().items()}
    except Exception as exc:  # noqa: BLE001 (OpenEXR raises RuntimeError, ValueError, UnicodeError, ...)
        raise _unreadable(path, exc) from exc
    planes = [channels.get(name) for name in keep]
    for name, plane in zip(keep, planes):
        if not isinstance(plane, np.ndarray) or plane.shape != (height, width):
            raise _unreadable(path, ValueError(f"channel {name} is missing, subsampled or not {width}x{height}"))
    return planes[0] if len(planes) == 1 else np.stack(planes, axis=-1)


def _write_exr(path: Path, image: np.ndarray, *, half: bool) -> None:
    import OpenEXR

    image = image.astype(np.float16 if half else np.float32)
    if image.ndim == 2:
        channels = {"Y": np.ascontiguousarray(image)}
    else:
        channels = {c: np.ascontiguousarray(image[:, :, i]) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        OpenEXR.File(header, channels).write(str(path))
    except RuntimeError as error:  # OpenEXR reports file-system failures as RuntimeError with the C message
        raise _as_os_error(error, path) from None


_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT,
                 errno.ENOTDIR, errno.ENAMETOOLONG, errno.EIO)


def _as_os_error(error: Exception, path: Path) -> Exception:
    """A library's write failure -> OSError with the errno its message names (else the error itself)."""
    message = str(error)
    for code in _WRITE_ERRNOS:
        if os.strerror(code) in message:
            return OSError(code, os.strerror(code), str(path))
    return error


def _read_with_oiio(path: Path) -> np.ndarray:
    """A PNG, JPEG or TIFF's pixels through OpenImageIO, upright: uint8 or uint16 codes (other integer
    depths as uint16, bilevel and palette images expanded), or float32 for a float TIFF; (H, W) or
    (H, W, 3), alpha dropped. A damaged or truncated file raises (never a partly grey image)."""
    import OpenImageIO as oiio

    with quiet_native_stderr():  # libpng and libjpeg print their complaints on fd 2
        config = oiio.ImageSpec()
        config.attribute("oiio:UnassociatedAlpha", 1)  # colour as stored, not multiplied by alpha (which is dropped)
        image = oiio.ImageInput.open(str(path), config)
        if image is None:
            raise _unreadable(path, RuntimeError(oiio.geterror() or "unknown format"))
        try:
            spec = image.spec()
            stored = str(spec.format)
            kind = "uint8" if stored == "uint8" else "float" if stored in _OIIO_FLOATS else "uint16"
            pixels = image.read_image(0, 0, 0, spec.nchannels, kind)
            error = image.geterror()
        finally:
            image.close()
    if pixels is None or error:
        raise _unreadable(path, RuntimeError(error or "no pixels"))
    pixels = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    keep = [c for c in range(spec.nchannels) if c != spec.alpha_channel]
    pixels = pixels[:, :, keep[:3]] if len(keep) >= 3 else pixels[:, :, keep[0]]
    # as ``_header`` counts it
    pixels = _EXIF_ORIENTATIONS.get(spec.get_int_attribute("Orientation", 1), _EXIF_ORIENTATIONS[1])(pixels)
    icc = spec.getattribute("ICCProfile")
    if icc is not None and len(icc) and pixels.ndim == 3:
        pixels = _to_srgb(path, pixels, bytes(np.asarray(icc, dtype=np.uint8)))
    return np.ascontiguousarray(pixels, dtype=np.float32 if kind == "float" else None)


def _to_srgb(path: Path, levels: np.ndarray, icc: bytes) -> np.ndarray:
    """8-bit RGB codes in the colour space of the ICC profile ``icc`` -> sRGB codes (Pillow's
    ImageCms); 16-bit codes and float values, which ImageCms cannot convert, are kept (floats as
    linear values with sRGB's primaries). A profile other than sRGB is named once per process in the
    ``warp_highlights`` log."""
    from PIL import Image, ImageCms

    name, source = _icc_profile(icc)
    if "srgb" in name.lower().replace(" ", ""):
        return levels
    converted = source is not None and levels.dtype == np.uint8
    if converted:
        try:
            levels = np.asarray(ImageCms.profileToProfile(Image.fromarray(levels), source,
                                                          ImageCms.createProfile("sRGB"), outputMode="RGB"))
        except ImageCms.PyCMSError:
            converted = False
    if name not in _REPORTED_PROFILES:
        _REPORTED_PROFILES.add(name)
        done = ("converted to sRGB" if converted
                else "read as linear sRGB (convert the capture to sRGB for exact colours)"
                if levels.dtype.kind == "f" else "read as sRGB (convert the capture to sRGB for exact colours)")
        logging.getLogger(__name__).warning(f"{path}: colour profile '{name}', not sRGB: {done}")
    return levels


def _write_with_oiio(path: Path, format_name: str, levels: np.ndarray) -> None:
    """uint8 or uint16 codes -> a PNG or TIFF (``format_name`` 'png' or 'tiff'; zip-compressed TIFF)."""
    import OpenImageIO as oiio

    height, width = levels.shape[:2]
    channels = 1 if levels.ndim == 2 else levels.shape[2]
    spec = oiio.ImageSpec(width, height, channels, "uint8" if levels.dtype == np.uint8 else "uint16")
    spec.attribute("oiio:UnassociatedAlpha", 1)  # any alpha channel is stored as given
    if format_name == "tiff":
        spec.attribute("compression", "zip")
        # no EXIF to write; with it on, OpenImageIO 3.2 reports a failed EXIF directory
        spec.attribute("tiff:write_exif", 0)
    pixels = np.ascontiguousarray(levels.reshape(height, width, channels))  # OpenImageIO misreads a 2-D array
    output = oiio.ImageOutput.create(format_name)
    if output is None:
        raise InputError(f"{path}: OpenImageIO has no {format_name} writer ({oiio.geterror()})")
    if not output.open(str(path), spec):  # (closing an output that failed to open crashes OpenImageIO's TIFF writer)
        raise _write_failure(path, output.geterror())
    written = output.write_image(pixels)
    closed = output.close()
    error = output.geterror()  # a short write (disk full) leaves write and close True and says so only here
    if not (written and closed) or error:
        raise _write_failure(path, error)
    # ... or not at all: a small PNG on a full disk ends as an empty file with no error. So the file
    # must read back as written before it may take the target's place.
    check = oiio.ImageInput.open(str(path), spec)  # (its oiio:UnassociatedAlpha: any alpha as stored)
    back = None if check is None else check.read_image(0, 0, 0, channels, spec.format)
    if check is None:
        oiio.geterror()  # taken, or OpenImageIO prints it at exit
    else:
        check.close()
    if back is None or not np.array_equal(np.asarray(back).reshape(pixels.shape), pixels):
        raise _write_failure(path, "the written file does not read back as written")


def _write_failure(path: Path, message: str) -> OSError:
    """OpenImageIO's write complaint -> an OSError with the errno it names, or ENOSPC when the disk
    holding ``path`` is full, EFBIG when the file reached the process's size limit (``ulimit -f``), else EIO
    (its messages carry no errno)."""
    error = _as_os_error(RuntimeError(message), path)
    if isinstance(error, OSError):
        return error
    if _at_size_limit(path):
        return OSError(errno.EFBIG, os.strerror(errno.EFBIG), str(path))
    import shutil

    try:
        full = shutil.disk_usage(path.parent).free < 64 * 1024
    except OSError:
        full = False
    code = errno.ENOSPC if full else errno.EIO
    return OSError(code,
                   f"{os.strerror(code)} ({message.strip().splitlines()[0] if message.strip() else 'write failed'})",
                   str(path))


def _at_size_limit(path: Path) -> bool:
    """Whether ``path`` is as large as the process may make a file (``RLIMIT_FSIZE``, where there is one)."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        return limit != resource.RLIM_INFINITY and path.stat().st_size >= limit
    except (ImportError, OSError, ValueError):
        return False


def _write_with_pillow(path: Path, suffix: str, levels: np.ndarray) -> None:
    from PIL import Image

    if suffix == ".png":
        Image.fromarray(levels).save(path, format="PNG")
    else:
        Image.fromarray(levels).save(path, format="JPEG", quality=95)
