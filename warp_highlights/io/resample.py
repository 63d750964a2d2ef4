"""Resampling of images and image stacks to a working or output resolution, through scikit-image:
area averaging (``resize_local_mean``, what OpenCV calls ``INTER_AREA``) along an axis that shrinks,
linear interpolation (``resize`` of order 1, edges clamped) along one that grows."""

from __future__ import annotations

import numpy as np

from ..model.errors import InputError
from ..model.threads import NUMPY_THREADS, parallel_map

__all__ = ["resample_image", "resize_stack", "working_size"]


def resize_stack(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, H, W[, C]) -> (n, height, width[, C]) float32, each image as ``resample_image`` does it: to a
    working size, an area average (each output pixel the mean of the input area it covers)."""
    images = np.asarray(images, dtype=np.float32)
    if tuple(images.shape[1:3]) == (height, width):
        return images
    out = np.empty((len(images), height, width) + images.shape[3:], np.float32)

    def part(lights: slice) -> None:  # a few images a thread: each is resampled alone, so the split changes nothing
        out[lights] = _resample(images[lights], 1, (height, width))

    step = max(1, -(-len(images) // (4 * NUMPY_THREADS)))
    parallel_map(part, [slice(start, start + step) for start in range(0, len(images), step)])
    return out


def resample_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, ...) -> (height, width, ...) float32: area average along an axis that shrinks, linear
    interpolation at the output pixel centres (edges clamped) along one that grows."""
    return _resample(np.asarray(image, dtype=np.float32), 0, (height, width))


def _resample(array: np.ndarray, first: int, size: tuple[int, int]) -> np.ndarray:
    """``array`` with its axes ``first`` and ``first + 1`` resampled to ``size``, the others kept."""
    now = array.shape[first : first + 2]
    if now == size:
        return array
    from skimage.transform import resize, resize_local_mean
    shape = lambda rows_cols: array.shape[:first] + rows_cols + array.shape[first + 2 :]
    shrunk = (min(now[0], size[0]), min(now[1], size[1]))
    if shrunk != now and now[0] % shrunk[0] == 0 and now[1] % shrunk[1] == 0:
        # whole blocks (e.g. half size): their means are the area average, several times faster than skimage's
        blocks = array.reshape(shape((shrunk[0], now[0] // shrunk[0], shrunk[1], now[1] // shrunk[1])))
        array = blocks.mean(axis=(first + 1, first + 3), dtype=np.float64)
    elif shrunk != now:
        array = resize_local_mean(array, shape(shrunk), grid_mode=True, preserve_range=True)
    if shrunk != size:
        array = resize(array, shape(size), order=1, mode="edge", anti_aliasing=False, preserve_range=True)
    return np.ascontiguousarray(array, dtype=np.float32)


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
        raise InputError(f"working size {new_width}x{new_height} is larger than the {width}x{height} images; only "
                         f"downsampling is supported")
    return new_width, new_height

