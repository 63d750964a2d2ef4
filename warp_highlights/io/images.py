"""Image files in and out: OpenEXR (linear), PNG 8/16-bit and JPEG (sRGB), as float32 NumPy arrays.

Arrays are ``(H, W)`` for grayscale or ``(H, W, 3)`` for RGB, row 0 at the top of the image. Pixel
values are linear radiance (EXR as stored; PNG and JPEG decoded with the sRGB transfer function unless
the caller says the file holds linear values). Every write goes to a temporary file in the target
folder, then replaces the target, so a failed write never leaves half a file.

Pillow and OpenEXR are imported inside the functions that use them. Pillow cannot hold 16-bit colour
images (it reads a 16-bit RGB PNG as 8-bit and cannot write one), so 16-bit colour PNGs go through
VTK's PNG codec instead.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import struct
import uuid
import zlib
from collections.abc import Callable, Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..model.errors import InputError

__all__ = [
    "IMAGE_EXTENSIONS",
    "atomic_folder",
    "check_replaceable_folder",
    "display_rgb8",
    "image_size",
    "linear_to_srgb",
    "read_image",
    "srgb_to_linear",
    "write_image",
]

IMAGE_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg")
"""File extensions :func:`read_image` and :func:`write_image` accept (case-insensitive)."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PIL_GRAY16_MODES = {"I;16", "I;16B", "I;16L", "I;16N", "I"}
_PIL_GRAY8_MODES = {"1", "L", "LA", "La"}
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error)  # what Pillow raises on bad files


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


def read_image(path, *, linear: bool = False) -> np.ndarray:
    """Read an image file as linear float32 values.

    Args:
        path: An ``.exr``, ``.png`` (8 or 16 bits per channel) or ``.jpg``/``.jpeg`` file.
        linear: PNG/JPEG only: the stored values are already linear; scale to [0, 1] but skip the
            sRGB decode.

    Returns:
        float32 array ``(H, W)`` for grayscale, ``(H, W, 3)`` for colour. Alpha is dropped; palette
        images are expanded to RGB.

    Raises:
        InputError: Missing file, unsupported extension, or a file that cannot be decoded.
    """
    path = Path(path)
    suffix = _checked_suffix(path)
    if not path.is_file():
        raise InputError(f"{path}: image file not found")
    if suffix == ".exr":
        return _read_exr(path)
    if suffix == ".png" and _png_is_16bit_colour(path):
        levels = _read_png16_colour(path)
    else:
        levels = _read_with_pillow(path)
    return _decode_levels(levels, linear=linear)


def write_image(path, image, *, half: bool = False, bits: int = 8, linear: bool = False) -> None:
    """Write an image, choosing the format from the file extension; atomic (temp file + rename).

    Args:
        path: Target ``.exr``, ``.png``, ``.jpg`` or ``.jpeg`` file; missing parent folders are made.
        image: Linear values, ``(H, W)`` (written as one channel, ``Y`` in EXR) or ``(H, W, 3)``.
        half: EXR only: store 16-bit half floats instead of float32.
        bits: PNG only: 8 or 16 bits per channel. JPEG is always 8-bit.
        linear: PNG/JPEG only: store the values as they are (clipped to [0, 1]) instead of
            sRGB-encoding them.

    Raises:
        InputError: Unsupported extension, an option the format does not have, or a bad array shape.
    """
    path = Path(path)
    suffix = _checked_suffix(path)
    image = _checked_image(path, image)
    if half and suffix != ".exr":
        raise InputError(f"{path}: half floats are an EXR option; use a .exr file or drop half")
    if bits not in (8, 16) or (bits == 16 and suffix != ".png"):
        raise InputError(f"{path}: bits={bits} is not possible; PNG takes 8 or 16, JPEG only 8, EXR none")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_target(path) as tmp:
        if suffix == ".exr":
            _write_exr(tmp, image, half=half)
        elif bits == 16 and image.ndim == 3:
            _write_png16_colour(tmp, _encode_levels(image, 65535, linear=linear))
        else:
            _write_with_pillow(tmp, suffix, _encode_levels(image, 2**bits - 1, linear=linear))


def image_size(path) -> tuple[int, int]:
    """Size of an image file from its header, without decoding the pixels.

    Args:
        path: An ``.exr``, ``.png``, ``.jpg`` or ``.jpeg`` file.

    Returns:
        ``(width, height)`` in pixels.

    Raises:
        InputError: Missing file, unsupported extension, or an unreadable header.
    """
    path = Path(path)
    suffix = _checked_suffix(path)
    if not path.is_file():
        raise InputError(f"{path}: image file not found")
    if suffix == ".exr":
        import OpenEXR

        try:
            lo, hi = OpenEXR.File(str(path), header_only=True).header()["dataWindow"]
        except Exception as exc:  # OpenEXR raises RuntimeError/ValueError/KeyError on bad files
            raise _unreadable(path, exc) from exc
        return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except _PIL_ERRORS as exc:
        raise _unreadable(path, exc) from exc


@contextlib.contextmanager
def atomic_target(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on error it is removed.

    Shared by the writers of this package (images here, light files in ``lights``).
    """
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def check_replaceable_folder(path: Path, *, overwrite: bool, owned: Callable[[str], bool]) -> None:
    """Raise ``InputError`` unless ``atomic_folder`` may write ``path``.

    A missing or empty folder is fine; an existing one needs ``overwrite`` and may hold only entries
    for which ``owned(name)`` is true (what the writer itself makes), so other files are never deleted.
    """
    if not path.exists():
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            raise InputError(f"folder {parent} for the output {path.name} does not exist; create it first")
        return
    if not path.is_dir():
        raise InputError(f"output {path} is a file; give a folder name")
    entries = [entry.name for entry in path.iterdir()]
    if entries and not overwrite:
        raise InputError(f"output folder {path} exists; pass --overwrite to replace it")
    foreign = sorted(name for name in entries if not owned(name))
    if foreign:
        raise InputError(f"output folder {path} holds other files ({foreign[0]}, ...); choose another folder, it is not replaced")


@contextlib.contextmanager
def atomic_folder(path: Path, *, overwrite: bool, owned: Callable[[str], bool]) -> Iterator[Path]:
    """Yield a new temporary folder beside ``path``; on success it takes ``path``'s place.

    ``check_replaceable_folder`` runs first. The old folder is moved aside before the new one is
    renamed in and removed after, so a failure at any point leaves either the old or the new output.
    """
    check_replaceable_folder(path, overwrite=overwrite, owned=owned)
    tag = uuid.uuid4().hex[:12]
    tmp = path.with_name(f".{path.name}.{tag}.tmp")
    old = path.with_name(f".{path.name}.{tag}.old")
    tmp.mkdir(parents=True)
    try:
        yield tmp
        check_replaceable_folder(path, overwrite=overwrite, owned=owned)  # nothing appeared meanwhile
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
    finally:
        for leftover in (tmp, old):
            if leftover.exists():
                shutil.rmtree(leftover)


# --- helpers -----------------------------------------------------------------------------------


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


def _encode_levels(image: np.ndarray, top: int, *, linear: bool) -> np.ndarray:
    """Linear float image -> integer codes 0..top (uint8 or uint16), sRGB-encoded unless ``linear``."""
    values = np.clip(np.nan_to_num(image, nan=0.0), 0.0, 1.0)
    if not linear:
        values = linear_to_srgb(values)
    return np.rint(values * top).astype(np.uint8 if top == 255 else np.uint16)


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
        channels = {name: channel.pixels for name, channel in exr.channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError on bad files
        raise _unreadable(path, exc) from exc
    if {"R", "G", "B"} <= channels.keys():
        return np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float32)
    if "Y" in channels:
        return channels["Y"].astype(np.float32)
    if len(channels) == 1:
        return next(iter(channels.values())).astype(np.float32)
    raise InputError(f"{path}: EXR channels {sorted(channels)} are neither R,G,B nor Y; cannot pick the image")


def _write_exr(path: Path, image: np.ndarray, *, half: bool) -> None:
    import OpenEXR

    image = image.astype(np.float16 if half else np.float32)
    if image.ndim == 2:
        channels = {"Y": np.ascontiguousarray(image)}
    else:
        channels = {c: np.ascontiguousarray(image[:, :, i]) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def _read_with_pillow(path: Path) -> np.ndarray:
    """8-bit (any mode) or 16-bit grayscale image -> uint8/uint16 codes, (H, W) or (H, W, 3)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in _PIL_GRAY16_MODES:
                return np.asarray(im).astype(np.uint16)
            return np.asarray(im.convert("L" if im.mode in _PIL_GRAY8_MODES else "RGB"))
    except _PIL_ERRORS as exc:
        raise _unreadable(path, exc) from exc


def _write_with_pillow(path: Path, suffix: str, levels: np.ndarray) -> None:
    from PIL import Image

    if suffix == ".png":
        Image.fromarray(levels).save(path, format="PNG")
    else:
        Image.fromarray(levels).save(path, format="JPEG", quality=95)


def _png_is_16bit_colour(path: Path) -> bool:
    """True for a PNG whose header says 16 bits per channel and colour or alpha (types 2, 4, 6)."""
    with open(path, "rb") as f:
        head = f.read(29)
    if len(head) < 29 or not head.startswith(_PNG_SIGNATURE) or head[12:16] != b"IHDR":
        return False  # let Pillow identify it or report the damage
    return head[24] == 16 and head[25] in (2, 4, 6)


def _check_png_chunks(path: Path) -> None:
    """Raise InputError unless every chunk is complete with a valid CRC and the file ends with IEND.

    libpng inside VTK kills the process on a damaged file instead of reporting it, so 16-bit colour
    PNGs are checked here (chunk framing) and by a full Pillow decode (image data) before VTK reads them.
    """
    data = path.read_bytes()
    pos = len(_PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            break
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(data[pos + 4 : end - 4]) != crc:
            name = kind.decode("latin-1")
            raise InputError(f"{path}: cannot read image (CRC error in chunk {name}); the file is damaged")
        if kind == b"IEND":
            return
        pos = end
    raise InputError(f"{path}: cannot read image (file is truncated); the file is damaged")


def _read_png16_colour(path: Path) -> np.ndarray:
    """16-bit RGB/RGBA/gray+alpha PNG -> uint16 codes, (H, W, 3) or (H, W) with alpha dropped."""
    _check_png_chunks(path)
    _read_with_pillow(path)  # decodes every row at 8 bits: reports damaged image data cleanly
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOImage import vtkPNGReader

    reader = vtkPNGReader()
    reader.SetFileName(str(path))
    reader.Update()
    output = reader.GetOutput()
    width, height, _ = output.GetDimensions()
    scalars = output.GetPointData().GetScalars()
    if reader.GetErrorCode() or scalars is None:
        raise InputError(f"{path}: cannot read image (VTK PNG reader failed); the file is damaged")
    levels = vtk_to_numpy(scalars).reshape(height, width, -1)[::-1]  # VTK rows run bottom-up
    levels = levels[:, :, 0] if levels.shape[2] <= 2 else levels[:, :, :3]
    return np.ascontiguousarray(levels, dtype=np.uint16)


def _write_png16_colour(path: Path, levels: np.ndarray) -> None:
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkIOImage import vtkPNGWriter

    height, width, channels = levels.shape
    data = vtkImageData()
    data.SetDimensions(width, height, 1)
    rows_bottom_up = np.ascontiguousarray(levels[::-1]).reshape(-1, channels)
    data.GetPointData().SetScalars(numpy_to_vtk(rows_bottom_up, deep=True))
    writer = vtkPNGWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(data)
    writer.Write()
    if writer.GetErrorCode() or not path.is_file():
        raise InputError(f"{path}: VTK could not write the 16-bit PNG (error code {writer.GetErrorCode()})")
