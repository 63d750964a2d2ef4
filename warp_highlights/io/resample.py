"""Area resampling of image stacks to a working resolution (NumPy only)."""

from __future__ import annotations

import numpy as np

from ..model.errors import InputError

__all__ = ["area_weights", "linear_weights", "resample_image", "resize_stack", "working_size"]


def area_weights(source: int, target: int) -> np.ndarray:
    """(target, source) matrix averaging the source pixels each target pixel covers (box filter, rows sum to 1)."""
    edges_out = np.arange(target + 1) * (source / target)
    lo = np.maximum(edges_out[:-1, None], np.arange(source)[None, :])
    hi = np.minimum(edges_out[1:, None], np.arange(1, source + 1)[None, :])
    overlap = np.clip(hi - lo, 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def linear_weights(source: int, target: int) -> np.ndarray:
    """(target, source) matrix of linear interpolation at the target pixel centres (edges clamped, rows sum to 1)."""
    centres = (np.arange(target) + 0.5) * (source / target) - 0.5
    centres = np.clip(centres, 0.0, source - 1)
    lower = np.minimum(np.floor(centres).astype(np.int64), max(source - 2, 0))
    frac = centres - lower
    weights = np.zeros((target, source))
    rows = np.arange(target)
    weights[rows, lower] += 1.0 - frac
    weights[rows, np.minimum(lower + 1, source - 1)] += frac
    return weights


def resample_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, ...) -> (height, width, ...) float32: area average along an axis that shrinks, linear along one that grows."""
    image = np.asarray(image, dtype=np.float32)
    source_height, source_width = image.shape[:2]
    if (source_height, source_width) == (height, width):
        return image
    pick = lambda s, t: area_weights(s, t) if t <= s else linear_weights(s, t)
    rows = pick(source_height, height).astype(np.float32)
    cols = pick(source_width, width).astype(np.float32)
    flat = image.reshape(source_height, source_width, -1)
    out = np.einsum("ij,jkc,lk->ilc", rows, flat, cols, optimize=True)
    return out.reshape((height, width) + image.shape[2:])


def working_size(width: int, height: int, requested: tuple[int, int] | None) -> tuple[int, int]:
    """Check a requested (width, height) keeps the aspect ratio (to within a pixel); None keeps the size."""
    if requested is None:
        return width, height
    new_width, new_height = requested
    if min(new_width, new_height) < 8:
        raise InputError(f"working size {new_width}x{new_height} is too small; use at least 8 pixels a side")
    if abs(new_width - width * new_height / height) > 1.0:
        raise InputError(
            f"working size {new_width}x{new_height} changes the aspect ratio of the {width}x{height} images; "
            f"use e.g. {round(width * new_height / height)}x{new_height}"
        )
    if new_width > width or new_height > height:
        raise InputError(f"working size {new_width}x{new_height} is larger than the {width}x{height} images; only downsampling is supported")
    return new_width, new_height


def resize_stack(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, H, W[, C]) -> (n, height, width[, C]) float32 by area averaging (energy preserving per pixel area)."""
    images = np.asarray(images, dtype=np.float32)
    if images.shape[1:3] == (height, width):
        return images
    rows = area_weights(images.shape[1], height).astype(np.float32)
    cols = area_weights(images.shape[2], width).astype(np.float32)
    if images.ndim == 3:
        return np.einsum("ij,njk,lk->nil", rows, images, cols, optimize=True)
    return np.einsum("ij,njkc,lk->nilc", rows, images, cols, optimize=True)
