"""Image quality, the one place it is computed: PSNR on linear values, and PSNR and SSIM on images
as shown in 8-bit sRGB, the way RTI tools are compared (estimation, the move and learned checks,
evaluation and the benchmarks all score through here).

- ``psnr``: dB with peak 1 over the last two axes of linear values clipped to [0, 1], at most ``cap``.
- ``psnr_excluding_black``: (Q,) dB per image of a stack; NaN where both images are all black.
- ``psnr_8bit``: dB (peak 255, at most 100) of two 8-bit images.
- ``srgb_psnr``: dB of two linear images as shown in 8-bit sRGB (``display_rgb8``).
- ``ssim_8bit``: scikit-image's SSIM (7 x 7 window, smaller for tiny images) of two 8-bit RGB images.
- ``srgb_scores``: (Q,) PSNR and SSIM of linear image stacks shown in 8-bit sRGB.
"""

from __future__ import annotations

import numpy as np

from ..model.threads import parallel_map
from .images import display_rgb8

__all__ = ["psnr", "psnr_8bit", "psnr_excluding_black", "psnr_of_mse", "srgb_psnr", "srgb_scores", "ssim_8bit"]


def psnr(image, reference, *, cap: float = 100.0) -> np.ndarray:
    """PSNR in dB with peak 1 over the last two axes, both clipped to [0, 1]; identical images give ``cap``."""
    a = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    b = np.clip(np.asarray(reference, dtype=np.float64), 0.0, 1.0)
    return psnr_of_mse(((a - b) ** 2).mean(axis=(-2, -1)), cap=cap)


def psnr_of_mse(mse, *, cap: float = 100.0) -> np.ndarray:
    """PSNR in dB, peak 1, of mean squared errors (e.g. ``kernels.losses.clipped_mse``'s); 0 gives ``cap``."""
    with np.errstate(divide="ignore"):
        return np.minimum(10.0 * np.log10(1.0 / np.asarray(mse, dtype=np.float64)), cap)


def psnr_excluding_black(images: np.ndarray, truth: np.ndarray, *, cap: float = 100.0) -> np.ndarray:
    """(Q,) PSNR in dB (peak 1, both clipped to [0, 1], at most ``cap``); NaN where both are all zero.

    Works on (Q, H, W) or (Q, H, W, C) stacks.
    """
    a = np.clip(np.asarray(images, dtype=np.float64), 0.0, 1.0).reshape(len(images), -1)
    b = np.clip(np.asarray(truth, dtype=np.float64), 0.0, 1.0).reshape(len(truth), -1)
    mse = ((a - b) ** 2).mean(axis=1)
    with np.errstate(divide="ignore"):
        value = np.minimum(10.0 * np.log10(1.0 / mse), cap)
    black = (a.max(axis=1) <= 0.0) & (b.max(axis=1) <= 0.0)
    return np.where(black, np.nan, value)


def psnr_8bit(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB (peak 255, at most 100 for identical images) of two 8-bit images of one shape."""
    a, b = np.asanyarray(a), np.asanyarray(b)
    if a.dtype == b.dtype == np.uint8 and not (np.ma.isMaskedArray(a) or np.ma.isMaskedArray(b)):  # integers throughout (the move check scores 96 images a fit): the sum is exact, as float64's was
        difference = np.subtract(a, b, dtype=np.int16)
        mse = int(np.square(difference, dtype=np.int32).sum(dtype=np.int64)) / max(difference.size, 1)
    else:
        mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return 100.0 if mse == 0 else min(100.0, 10.0 * np.log10(255.0**2 / mse))


def srgb_psnr(image, reference) -> float:
    """PSNR in dB (peak 255, at most 100 for identical images) of two linear images as shown in 8-bit sRGB (``display_rgb8``)."""
    return psnr_8bit(display_rgb8(image), display_rgb8(reference))


def ssim_8bit(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of 8-bit RGB image ``a`` against ``b`` (scikit-image, over the colour channels): a 7 x 7
    window, the largest odd one for images under 7 pixels, 1 for images under 3."""
    from skimage.metrics import structural_similarity

    small = min(a.shape[0], a.shape[1])
    window = min(7, small if small % 2 else small - 1) if small >= 3 else None  # odd, as SSIM needs
    return 1.0 if window is None else float(structural_similarity(b, a, channel_axis=-1, data_range=255, win_size=window))


def srgb_scores(images: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q,) PSNR (dB, peak 255) and (Q,) SSIM of linear images shown as 8-bit sRGB (``display_rgb8``).

    Works on (Q, H, W) or (Q, H, W, C) stacks; PSNR is capped at 100 dB for identical images.
    """
    def score(q: int) -> tuple[float, float]:
        a, b = display_rgb8(images[q]), display_rgb8(truth[q])
        return psnr_8bit(a, b), ssim_8bit(a, b)

    # the images in threads: NumPy's loops and SciPy's filters (SSIM's means) let go of the GIL (124 images of 480x270 on the
    # lent H200's 16 cores: 7.41 -> 3.94 s, the same scores)
    scores = np.array(parallel_map(score, range(len(images))), dtype=np.float64).reshape(-1, 2)
    return scores[:, 0].copy(), scores[:, 1].copy()
