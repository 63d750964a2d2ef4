"""Colour transforms of the residual: the opponent split (luminance Y and chroma B - Y, R - Y) that the
low-rank stacks store, and the signed sRGB encoding the learned residual is trained in.
"""

from __future__ import annotations

import numpy as np

from ..model.residual import (
    LUMINANCE_WEIGHTS,
)

__all__ = ["decode_display", "encode_display", "from_opponent", "luminance_of", "to_opponent"]


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


def encode_display(linear: np.ndarray) -> np.ndarray:
    """Signed sRGB encoding, float32 (display units, 1 = white): sign(x) srgb(|x|), |x| clipped at 1:
    what the learned residual is trained on, so that its squared error is the one 8-bit sRGB PSNR measures."""
    x = np.minimum(np.abs(linear), 1.0)
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (np.sign(linear) * encoded).astype(np.float32)


def decode_display(encoded: np.ndarray) -> np.ndarray:
    """Linear values of signed-sRGB-encoded ones: sign(v) srgb^-1(|v|) (the learned residual's output)."""
    x = np.abs(encoded)
    return np.sign(encoded) * np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))
