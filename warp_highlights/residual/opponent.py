"""Colour transforms of the residual: the opponent split (luminance Y and chroma B - Y, R - Y) that the
low-rank stacks store, and the signed sRGB encoding the learned residual is trained in.
"""

from __future__ import annotations

import numpy as np

from ..model.residual import (
    LUMINANCE_WEIGHTS,
)
from ..model.threads import parallel_map

__all__ = ["ENCODING_BAND", "decode_display", "encode_display", "from_opponent", "luminance_of", "to_opponent"]


def luminance_of(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> luminance Y (...,), float64 (``to_opponent``'s, bit for bit)."""
    return to_opponent(rgb, with_chroma=False)[0]


def to_opponent(rgb: np.ndarray, *, with_chroma: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """(..., 3) linear RGB -> luminance (...,) and chroma (..., 2) = (B - Y, R - Y), float64 (chroma
    None when not asked for)."""
    rgb = np.asarray(rgb)
    # plane by plane: no float64 copy of the whole stack
    red, green, blue = (rgb[..., c].astype(np.float64) for c in range(3))
    y = LUMINANCE_WEIGHTS[0] * red + LUMINANCE_WEIGHTS[1] * green + LUMINANCE_WEIGHTS[2] * blue
    if not with_chroma:
        return y, None
    chroma = np.empty(y.shape + (2,), np.float64)
    np.subtract(blue, y, out=chroma[..., 0])
    np.subtract(red, y, out=chroma[..., 1])
    return y, chroma


def from_opponent(luminance: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """Inverse of ``to_opponent``: (...,) Y and (..., 2) chroma -> (..., 3) RGB, float64."""
    wr, wg, wb = LUMINANCE_WEIGHTS
    y = np.asarray(luminance, dtype=np.float64)
    cb, cr = chroma[..., 0], chroma[..., 1]
    return np.stack([y + cr, y - (wr * cr + wb * cb) / wg, y + cb], axis=-1)


ENCODING_BAND = 1 << 18
"""Values ``encode_display`` and ``decode_display`` convert at a time on a thread (a megabyte of float32: a band's
temporaries stay in the core's cache, and a stack of images is converted at the cores' speed)."""


def encode_display(linear: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Signed sRGB encoding, float32 (display units, 1 = white): sign(x) srgb(|x|), |x| clipped at 1:
    what the learned residual is trained on, so that its squared error is the one 8-bit sRGB PSNR measures.
    Into ``out`` (contiguous float32 of the same size) when given."""
    linear = np.asarray(linear)
    out = np.empty(linear.shape, np.float32) if out is None else out
    if out.dtype != np.float32 or out.size != linear.size or not out.flags.c_contiguous:
        raise ValueError(f"out must be contiguous float32 of {linear.size} values, got {out.dtype} {out.shape}")
    _in_bands(_encode_band, linear, out)
    return out


def decode_display(encoded: np.ndarray) -> np.ndarray:
    """Linear values of signed-sRGB-encoded ones: sign(v) srgb^-1(|v|) (the learned residual's output), float64 for
    float64 values, else float32."""
    encoded = np.asarray(encoded)
    out = np.empty(encoded.shape, np.float64 if encoded.dtype == np.float64 else np.float32)
    _in_bands(_decode_band, encoded, out)
    return out


def _in_bands(convert, values: np.ndarray, out: np.ndarray) -> None:
    """``convert(source, target)`` over bands of ``ENCODING_BAND`` of the flattened arrays, spread over the threads."""
    source, target = np.ascontiguousarray(values).reshape(-1), out.reshape(-1)
    bands = [slice(start, start + ENCODING_BAND) for start in range(0, source.size, ENCODING_BAND)]
    if len(bands) == 1:
        convert(source, target)
        return
    parallel_map(lambda band: convert(source[band], target[band]), bands)


def _encode_band(linear: np.ndarray, out: np.ndarray) -> None:
    x = np.minimum(np.abs(linear, out=out), np.float32(1.0), out=out)
    low = x <= np.float32(0.0031308)
    linear_part = x * np.float32(12.92)
    np.power(x, np.float32(1 / 2.4), out=x)
    x *= np.float32(1.055)
    x -= np.float32(0.055)
    np.copyto(x, linear_part, where=low)
    np.multiply(x, np.sign(linear), out=x)  # sign(0) = 0 keeps a zero unsigned


def _decode_band(encoded: np.ndarray, out: np.ndarray) -> None:
    x = np.abs(encoded, out=out)
    low = x <= 0.04045
    linear_part = x / out.dtype.type(12.92)
    x += out.dtype.type(0.055)
    x /= out.dtype.type(1.055)
    np.power(x, out.dtype.type(2.4), out=x)
    np.copyto(x, linear_part, where=low)
    np.multiply(x, np.sign(encoded), out=x)
