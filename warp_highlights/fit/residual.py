"""The fit's last stages: which Gaussians move, the highlight colour, and the residual (method.md section 6).

- ``decide_moving``: a Gaussian moves when its retargeted selves land on the neighbours' specular
  images (the median over its outgoing edges of ``kernels.support``); otherwise it stays where it
  is and blends with the barycentric weight, like the alpha baseline.
- ``highlight_colour``: c(x), the colour of the specular part under the Gaussians, of luminance 1,
  pulled towards white where they draw little.
- ``build_residual``: R_i = I_i - c(x) R(x; G_i) for every light (all of its Gaussians: a static one
  blended in place adds back exactly what its light's residual lacks), compressed to low-rank
  luminance and chroma stacks (``ResidualModel``) or kept whole.

Units: images in the field's units (the fit's exposure applied); Gaussians in image heights.
"""

from __future__ import annotations

import warnings
import zlib
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..io.images import linear_to_srgb
from ..kernels.raster import Rasterizer
from ..kernels.support import support_fractions
from ..model.config import RasterSettings, ResidualSettings
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.residual import LUMINANCE_WEIGHTS, LowRankStack, ResidualModel, colour_codes, colour_from_codes, to_opponent

__all__ = ["MoveDecision", "build_residual", "choose_luminance_rank", "decide_moving", "deflated_bytes", "display_error", "gaussian_bytes", "highlight_colour", "render_own", "residual_scale"]

SCALE_FLOOR = 2.0**-10
"""Smallest residual scale s(x), field units (1 = display white): about a quarter of an 8-bit sRGB step
near black, so a black background is approximated to well under one step."""
AUTO_CHROMA_RANKS = (3, 6)
"""Chroma ranks tried when ``ResidualSettings.chroma_rank`` is 0: 3 suits captures whose colour varies
little with the light (the samples), 6 the 64-light donut, whose back-lit images are grey (+1.2 dB)."""
_ERROR_PIXEL_STEP = 4  # display_error samples 1 pixel in 16
_DEFLATE_LEVEL = 6  # zlib's default, what zipfile's deflate uses
_PARAMETER_BYTES = 24  # six float32 per Gaussian
_PATH_BYTES = 12  # delta and centre (float32) per retargeted Gaussian


@dataclass(frozen=True)
class MoveDecision:
    """Attributes: moving (n, N) bool; support (E, N) float64 per directed edge (-1 where a slot draws nothing)."""

    moving: np.ndarray
    support: np.ndarray


def decide_moving(estimated: GaussianParams, retargeted: GaussianParams, edges: np.ndarray, specular_luminance: wp.array,
                  *, settings: ResidualSettings, raster: RasterSettings) -> MoveDecision:
    """Which estimated Gaussians move: median support over the outgoing edges >= ``settings.move_support``."""
    n, capacity = estimated.active.shape
    device = specular_luminance.device
    batch = GaussianBatch.from_numpy(retargeted, device=device, requires_grad=False)
    values = support_fractions(batch, edges[:, 1], specular_luminance, settings=raster)
    values = np.where(retargeted.active, values, np.nan)
    values[values < 0] = 0.0  # a retargeted Gaussian that draws nothing explains nothing
    if settings.move_support <= 0:
        return MoveDecision(estimated.active.copy(), values)
    order = np.argsort(edges[:, 0], kind="stable")
    sources = edges[order, 0]
    starts = np.searchsorted(sources, np.arange(n + 1))
    for_light = values[order]
    # median over each light's outgoing edges, per slot: lights have 3..~8 edges, so pad to the most
    most = int(np.diff(starts).max()) if len(edges) else 0
    padded = np.full((n, max(most, 1), capacity), np.nan)
    position = np.arange(len(edges)) - np.repeat(starts[:-1], np.diff(starts))
    padded[sources, position] = for_light
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: free slots
        median = np.nanmedian(padded, axis=1)
    moving = estimated.active & (np.nan_to_num(median, nan=0.0) >= settings.move_support)
    return MoveDecision(moving, values)


def render_own(estimated: GaussianParams, height: int, width: int, *, raster: RasterSettings, device) -> np.ndarray:
    """(n, H, W) float32: R(x; G_i), every light's own Gaussians drawn as the relighter draws them."""
    batch = GaussianBatch.from_numpy(estimated, device=device, requires_grad=False)
    return Rasterizer(height, width, settings=raster, device=device).render(batch).numpy()


def highlight_colour(specular: np.ndarray, own: np.ndarray, *, prior: float) -> np.ndarray:
    """(H, W, 3) c(x) = (sum_i G_i S_i + prior n) / (sum_i G_i Y(S_i) + prior n), channels in [0, 4] in steps of ``COLOUR_STEP``.

    ``specular``: (n, H, W, 3) the segmentation's specular part; ``own``: (n, H, W) the moving
    Gaussians' images. The luminance of c is 1 up to the clip, so c G keeps G's luminance.
    """
    n = len(own)
    own64 = own.astype(np.float64)
    numerator = np.einsum("nhw,nhwc->hwc", own64, specular.astype(np.float64))
    denominator = numerator @ np.asarray(LUMINANCE_WEIGHTS)
    weight = prior * n
    colour = (numerator + weight) / (denominator[..., None] + weight)
    return colour_from_codes(colour_codes(colour))  # kept as the file keeps it: 8 bits per channel


def deflated_bytes(array: np.ndarray) -> int:
    """Bytes of ``array`` deflated as the field file deflates its entries (zlib's default level)."""
    return len(zlib.compress(np.ascontiguousarray(array).tobytes(), _DEFLATE_LEVEL))


def gaussian_bytes(estimated: GaussianParams, retargeted: GaussianParams) -> int:
    """Stored bytes of a field's Gaussians and paths before deflate (an upper bound of what they take)."""
    return int(estimated.active.sum()) * (_PARAMETER_BYTES + 2) + int(retargeted.active.sum()) * (_PARAMETER_BYTES + _PATH_BYTES) + 2 * len(estimated.active)


def choose_luminance_rank(stack: LowRankStack, fixed_bytes: int, budget_bytes: float) -> int:
    """The largest rank k <= ``stack.rank`` whose first k basis images, deflated, fit ``budget_bytes``
    beside ``fixed_bytes`` (everything else the field stores); at least 1."""
    costs = np.cumsum([deflated_bytes(code) + 8 + 4 * len(stack.weights) for code in stack.codes])  # codes, range, weights
    fits = np.flatnonzero(fixed_bytes + costs <= budget_bytes)
    return int(max(1, fits[-1] + 1 if fits.size else 1))


def build_residual(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, *, settings: ResidualSettings, other_bytes: int = 0) -> ResidualModel:
    """The ``ResidualModel`` of (n, H, W, C) images (field units) and their own (n, H, W) highlights.

    Compressed, the luminance rank is ``settings.luminance_rank``, or else the largest (up to
    ``max_luminance_rank``) that keeps the whole field within ``size_budget`` of the 8-bit capture,
    counting ``other_bytes`` (the Gaussians and paths) and the deflated size of every stored array.
    The basis bits and the chroma rank are the settings', or else the pair of 8/16 bits and
    ``AUTO_CHROMA_RANKS`` (each at the luminance rank the budget leaves it) that reproduces the
    captured images best as 8-bit sRGB (``display_error``).
    """
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 3:
        images = images[..., None]
    n, height, width, channels = images.shape
    tint = np.ones((1, 1, channels), np.float32) if colour is None else colour
    highlights = own[..., None] * tint[None]
    residual = images - highlights
    if not settings.compressed:
        return ResidualModel(images=residual.astype(np.float16), highlight_colour=colour)
    if channels == 1:
        y, opponent = residual[..., 0].astype(np.float64), None
    else:
        y, opponent = to_opponent(residual)
    scale = residual_scale(y)
    luminance = (y / scale)[..., None]
    light_scale = np.sqrt(np.mean(luminance.reshape(n, -1) ** 2, axis=1))  # both stacks weigh each light by its brightness
    candidates = []
    bit_choices = (8, 16) if settings.basis_bits == 0 else (settings.basis_bits,)
    chroma_choices = (None,) if opponent is None else tuple(dict.fromkeys(min(rank, n - 1) for rank in ((settings.chroma_rank,) if settings.chroma_rank else AUTO_CHROMA_RANKS)))
    for bits in bit_choices:
        widest = LowRankStack.fit(luminance, min(settings.luminance_rank or settings.max_luminance_rank, n - 1), light_scale=light_scale, bits=bits)
        for rank_of_chroma in chroma_choices:
            chroma = None
            if opponent is not None:
                chroma = LowRankStack.fit(opponent / scale[..., None], rank_of_chroma, light_scale=light_scale, bits=bits)
            stack = widest
            if not settings.luminance_rank:
                fixed = other_bytes + deflated_bytes(stack.mean.astype(np.float16)) + deflated_bytes(scale.astype(np.float16)) + 8 * n
                if chroma is not None:
                    fixed += deflated_bytes(chroma.mean.astype(np.float16)) + sum(deflated_bytes(code) for code in chroma.codes) + chroma.weights.nbytes
                if colour is not None:
                    fixed += deflated_bytes(colour_codes(colour))
                rank = max(choose_luminance_rank(widest, fixed, settings.size_budget * n * height * width * channels), settings.min_luminance_rank)
                if rank < widest.rank:
                    stack = LowRankStack.fit(luminance, rank, light_scale=light_scale, bits=bits)
            candidates.append(ResidualModel(luminance=stack, chroma=chroma, highlight_colour=colour, scale=scale))
    if len(candidates) == 1:
        return candidates[0]
    errors = [display_error(model, images, highlights) for model in candidates]
    return candidates[int(np.argmin(errors))]


def display_error(model: ResidualModel, images: np.ndarray, highlights: np.ndarray, *, step: int = _ERROR_PIXEL_STEP) -> float:
    """Mean squared difference, in 8-bit sRGB levels, between the (n, H, W, C) images and what ``model``
    plus their (n, H, W, C) own highlights gives back at the captured lights, on every ``step``-th
    pixel of every ``step``-th row (the choice of the basis bits needs no more)."""
    n = len(images)
    picked = ResidualModel(
        luminance=_sub_stack(model.luminance, step), chroma=None if model.chroma is None else _sub_stack(model.chroma, step),
        scale=model.scale[::step, ::step], highlight_colour=None,
    )
    back = picked.light_images(np.eye(n)) + highlights[:, ::step, ::step]
    truth = images[:, ::step, ::step].astype(np.float64)
    encode = lambda a: linear_to_srgb(np.clip(a, 0.0, 1.0)) * 255.0
    return float(np.mean((encode(back) - encode(truth)) ** 2))


def _sub_stack(stack: LowRankStack, step: int) -> LowRankStack:
    return LowRankStack(stack.mean[::step, ::step], stack.codes[:, ::step, ::step], stack.ranges, stack.weights, stack.mean_weights)


def residual_scale(luminance: np.ndarray) -> np.ndarray:
    """(H, W) float32 s(x): the RMS over the lights of a pixel's (n, H, W) residual luminance, at least
    ``SCALE_FLOOR``, rounded to float16 as the file keeps it."""
    rms = np.sqrt(np.mean(np.square(luminance, dtype=np.float64), axis=0))
    return np.maximum(rms, SCALE_FLOOR).astype(np.float16).astype(np.float32)
