"""What the residual is made of: each light's own highlights rendered from its Gaussians, the images held
on a CUDA device for the move check and the stacks, the highlight colour c(x), the residual
R = I - c(x) R(x; G) and its per-pixel scale s(x).

Units: images in the field's units (the fit's exposure applied); Gaussians in image heights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.raster import Rasterizer
from ..kernels.transfer import rows_up, to_host
from ..model.config import RasterSettings
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.residual import (
    LUMINANCE_WEIGHTS,
    colour_codes,
    colour_from_codes,
)
from ..model.threads import parallel_map

__all__ = ["BAND_VALUES", "HELD_IMAGES_BYTES", "HELD_IMAGES_SHARE", "HeldImages", "SCALE_FLOOR",
           "diffuse_under_highlights", "highlight_colour",
           "hold_images", "holds_images", "learned_target", "render_own", "render_own_on_device", "residual_of",
           "residual_scale",
           "row_bands", "scale_of_mean_square"]

SCALE_FLOOR = 2.0**-10
"""Smallest residual scale s(x), field units (1 = display white): about a quarter of an 8-bit sRGB step
near black, so a black background is approximated to well under one step."""
HELD_IMAGES_BYTES = 1 << 30
"""A fit's images and own highlights of at most this many bytes (1 GiB: 250 lights at 480x270 take 0.52 GB) are held on
a CUDA device for the move check and the residual's stacks (``hold_images``), within ``HELD_IMAGES_SHARE`` of its free
memory: the images from the segmentation's upload on (through estimation, retargeting and the paths), the own highlights
from their render; larger ones go up band by band where each stage reads them."""
HELD_IMAGES_SHARE = 0.1
# highlight_colour's and build_residual's float64 copies: this many values of the stack a thread at a time (32 MB)
BAND_VALUES = 1 << 22


@dataclass
class HeldImages:
    """A fit's images (n, H W, C) and their own highlights (n, H W; None: not held) as float32 device arrays,
    sent up once for the move check's scores and the residual's stacks (``hold_images``); ``build_residual``
    lets go of both (None) once its stacks have read them."""

    images: wp.array | None
    own: wp.array | None


def holds_images(shape: tuple[int, ...], device) -> bool:
    """Whether ``hold_images`` holds images of ``shape`` (n, H, W, C) and their own highlights on ``device``: a CUDA
    device where together they take at most ``HELD_IMAGES_BYTES`` and ``HELD_IMAGES_SHARE`` of its free memory."""
    device = wp.get_device(device)
    n, height, width, channels = shape
    nbytes = 4 * n * height * width * (channels + 1)
    return device.is_cuda and nbytes <= HELD_IMAGES_BYTES and nbytes <= HELD_IMAGES_SHARE * device.free_memory


def hold_images(images: np.ndarray, own: np.ndarray, device, *, images_up: wp.array | None = None,
                own_up: wp.array | None = None) -> HeldImages | None:
    """``images`` (n, H, W, C) and ``own`` (n, H, W) on a CUDA ``device`` where ``holds_images``; else None (each
    stage sends up what it reads). ``images_up``, ``own_up``: the same values there already (float32, contiguous),
    held as they are instead of sent up again (``images_up`` given: held whatever the memory is free now, as
    ``holds_images`` was asked before it was sent up)."""
    device = wp.get_device(device)
    n, height, width, channels = images.shape
    if images_up is None and not holds_images(images.shape, device):
        return None
    if images_up is None:
        images_up = rows_up(np.asarray(images, np.float32).reshape(n, -1), device)
    if own_up is None:
        own_up = rows_up(np.asarray(own, np.float32).reshape(n, -1), device)
    return HeldImages(images_up.reshape((n, height * width, channels)), own_up.reshape((n, height * width)))


def render_own_on_device(estimated: GaussianParams, height: int, width: int, *, raster: RasterSettings,
                         device) -> wp.array:
    """(n, H, W) float32 on ``device``: R(x; G_i), every light's own Gaussians drawn as the relighter draws them
    (in parts where the lights' pixels pass one launch's 2^31, e.g. 100 lights of 24 megapixels)."""
    rasterizer = Rasterizer(height, width, settings=raster, device=device)
    n, most = estimated.problem_count, rasterizer.problems_per_launch
    if n <= most:
        return rasterizer.render(GaussianBatch.from_numpy(estimated, device=device, requires_grad=False))
    own = wp.empty((n, height, width), dtype=float, device=device)
    for start in range(0, n, most):
        rows = np.arange(start, min(start + most, n))
        rasterizer.render(GaussianBatch.from_numpy(estimated.take(rows), device=device, requires_grad=False),
                          out=own[start:rows[-1] + 1])
    return own


def render_own(estimated: GaussianParams, height: int, width: int, *, raster: RasterSettings, device) -> np.ndarray:
    """``render_own_on_device`` in host memory."""
    return to_host(render_own_on_device(estimated, height, width, raster=raster, device=device))


def highlight_colour(specular: np.ndarray, own: np.ndarray, *, prior: float) -> np.ndarray:
    """(H, W, 3) c(x) = (sum_i G_i S_i + prior n) / (sum_i G_i Y(S_i) + prior n), channels in [0, 4] in steps of
    ``COLOUR_STEP``.

    ``specular``: (n, H, W, 3) the segmentation's specular part; ``own``: (n, H, W) the moving
    Gaussians' images. The luminance of c is 1 up to the clip, so c G keeps G's luminance.
    """
    n = len(own)
    numerator = np.empty(specular.shape[1:], np.float64)

    # float64 a band of rows at a time (no float64 copy of the whole stack), the bands in threads
    def sums(band: slice) -> None:
        numerator[band] = np.einsum("nhw,nhwc->hwc", own[:, band].astype(np.float64),
                                    specular[:, band].astype(np.float64))

    parallel_map(sums, row_bands(specular))
    denominator = numerator @ np.asarray(LUMINANCE_WEIGHTS)
    weight = prior * n
    colour = (numerator + weight) / (denominator[..., None] + weight)
    return colour_from_codes(colour_codes(colour))  # kept as the file keeps it: 8 bits per channel


def residual_of(images: np.ndarray, own: np.ndarray, tint: np.ndarray) -> np.ndarray:
    """R = I - c(x) R(x; G): (..., C) images less their own (...) highlights in the (..., C) colour
    ``tint`` (broadcast from the right: pixels, rows or whole images), float32."""
    return images - own[..., None] * tint


def diffuse_under_highlights(residual: np.ndarray, image: np.ndarray, own: np.ndarray, specular: np.ndarray,
                             level: float) -> np.ndarray:
    """In place and returned: one light's (H, W, C) ``residual`` (its image less its own highlights) becomes the
    (H, W, C) ``image`` less its (H, W, C) ``specular`` part (the segmentation's diffuse part) wherever its own (H, W)
    highlights ``own`` are at least ``level`` of their brightest pixel: what the Gaussians miss of a highlight there
    is that light's alone (``ResidualSettings.diffuse_under_highlights``). Unchanged where ``own`` is all zero or
    ``level`` is 0."""
    peak = float(np.max(own)) if own.size else 0.0
    if level <= 0 or not peak > 0:
        return residual
    under = own >= np.float32(level * peak)
    residual[under] = image[under] - specular[under]
    return residual


def learned_target(image: np.ndarray, own: np.ndarray, tint: np.ndarray, specular: np.ndarray | None = None,
                   level: float = 0.0) -> np.ndarray:
    """(H, W, C) float32 what a learned residual learns at one light (field units): the (H, W, C) ``image`` less its
    own (H, W) highlights in colour ``tint`` (``residual_of``), and with its (H, W, C) ``specular`` part the diffuse
    part under them (``diffuse_under_highlights`` at ``level``)."""
    image = np.asarray(image, np.float32)
    residual = residual_of(image, np.asarray(own, np.float32), tint)
    if specular is not None:
        diffuse_under_highlights(residual, image, own, np.asarray(specular, np.float32), level)
    return residual


def row_bands(images: np.ndarray) -> list[slice]:
    """Bands of rows of an (n, H, W, C) stack of about ``BAND_VALUES`` values each."""
    n, height = images.shape[:2]
    rows = max(1, BAND_VALUES // max(1, images[0, 0].size * n))
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


def residual_scale(luminance: np.ndarray) -> np.ndarray:
    """(H, W) float32 s(x): the RMS over the lights of a pixel's (n, H, W) residual luminance, at least
    ``SCALE_FLOOR``, rounded to float16 as the file keeps it."""
    return scale_of_mean_square(np.mean(np.square(luminance, dtype=np.float64), axis=0))


def scale_of_mean_square(mean_square: np.ndarray) -> np.ndarray:
    """``residual_scale`` from each pixel's float64 mean over the lights of its squared residual luminance."""
    return np.maximum(np.sqrt(mean_square), SCALE_FLOOR).astype(np.float16).astype(np.float32)
