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
from ..model.residual import (
    LUMINANCE_WEIGHTS,
    LowRankStack,
    ResidualModel,
    colour_codes,
    colour_from_codes,
    principal_energies,
    to_opponent,
)

__all__ = ["CHROMA_GAIN", "LUMINANCE_GAIN", "MoveDecision", "build_residual", "choose_luminance_rank", "component_bytes", "decide_moving", "deflated_bytes", "display_error", "gaussian_bytes", "highlight_colour", "render_own", "residual_scale", "split_ranks"]

SCALE_FLOOR = 2.0**-10
"""Smallest residual scale s(x), field units (1 = display white): about a quarter of an 8-bit sRGB step
near black, so a black background is approximated to well under one step."""
LUMINANCE_GAIN = 3.0
"""Squared RGB error per unit of squared luminance error: an error in Y shifts R, G and B alike."""
CHROMA_GAIN = 1.0 + 0.5 * ((LUMINANCE_WEIGHTS[0] / LUMINANCE_WEIGHTS[1]) ** 2 + (LUMINANCE_WEIGHTS[2] / LUMINANCE_WEIGHTS[1]) ** 2)
"""The same for the chroma planes (B - Y, R - Y), averaged: an error in B - Y moves B and, by wb / wg, G."""
_ERROR_PIXEL_STEP = 4  # display_error samples 1 pixel in 16
_DEFLATE_LEVEL = 6  # zlib's default, what zipfile's deflate uses
_PARAMETER_BYTES = 24  # six float32 per Gaussian
_PATH_BYTES = 12  # delta and centre (float32) per retargeted Gaussian
_FILE_BYTES = 6144  # the header, the zip's own records and the rest of a field file's small entries
_LIGHT_BYTES = 48  # a light's direction (float64) and its two faces (int32)


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


def component_bytes(stack: LowRankStack) -> np.ndarray:
    """(k,) stored bytes of each basis image of ``stack``: its deflated codes, its range and its per-light weights."""
    return np.array([deflated_bytes(code) + 8 + 4 * len(stack.weights) for code in stack.codes], dtype=np.float64)


def choose_luminance_rank(stack: LowRankStack, fixed_bytes: int, budget_bytes: float) -> int:
    """The largest rank k <= ``stack.rank`` whose first k basis images, deflated, fit ``budget_bytes``
    beside ``fixed_bytes`` (everything else the field stores); at least 1."""
    costs = np.cumsum(component_bytes(stack))
    fits = np.flatnonzero(fixed_bytes + costs <= budget_bytes)
    return int(max(1, fits[-1] + 1 if fits.size else 1))


def split_ranks(luminance_gain: np.ndarray, luminance_bytes: np.ndarray, chroma_gain: np.ndarray, chroma_bytes: float, budget_bytes: float) -> tuple[int, int]:
    """How many luminance and chroma basis images to keep within ``budget_bytes``: greedily the next
    image of either stack that removes the most squared RGB error per byte (gains: the energies
    ``principal_energies`` gives, times ``LUMINANCE_GAIN`` or ``CHROMA_GAIN``; bytes: each luminance
    image's own, one estimate for a chroma image); an image that removes nothing (1e-9 of the total)
    is not taken. Returns (luminance rank, chroma rank)."""
    luminance_count = chroma_count = 0
    spent = 0.0
    least = 1e-9 * (float(np.sum(luminance_gain)) + float(np.sum(chroma_gain)))  # below this an image removes rounding noise only
    while True:
        take_luminance = luminance_count < len(luminance_gain) and spent + luminance_bytes[luminance_count] <= budget_bytes and luminance_gain[luminance_count] > least
        take_chroma = chroma_count < len(chroma_gain) and spent + chroma_bytes <= budget_bytes and chroma_gain[chroma_count] > least
        if not (take_luminance or take_chroma):
            return luminance_count, chroma_count
        luminance_rate = luminance_gain[luminance_count] / max(luminance_bytes[luminance_count], 1.0) if take_luminance else -1.0
        chroma_rate = chroma_gain[chroma_count] / max(chroma_bytes, 1.0) if take_chroma else -1.0
        if luminance_rate >= chroma_rate:
            spent += luminance_bytes[luminance_count]
            luminance_count += 1
        else:
            spent += chroma_bytes
            chroma_count += 1


def build_residual(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, *, settings: ResidualSettings, other_bytes: int = 0) -> ResidualModel:
    """The ``ResidualModel`` of (n, H, W, C) images (field units) and their own (n, H, W) highlights.

    Compressed, the ranks are the settings' where given; otherwise the whole field is kept within
    ``size_budget`` of the 8-bit capture, counting ``other_bytes`` (the Gaussians and paths) and the
    deflated size of every stored array: the budget goes to luminance and chroma basis images by
    ``split_ranks`` (the error each removes per byte), then the luminance takes what the chroma left
    (up to ``max_luminance_rank``, at least ``min_luminance_rank``). The basis bits are the settings',
    or else 8 or 16, whichever reproduces the captured images better as 8-bit sRGB (``display_error``).
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
    chroma_stack = None if opponent is None else opponent / scale[..., None]
    light_scale = np.sqrt(np.mean(luminance.reshape(n, -1) ** 2, axis=1))  # both stacks weigh each light by its brightness
    budget = settings.size_budget * n * height * width * channels
    most = min(settings.luminance_rank or settings.max_luminance_rank, n - 1)
    energies = None
    if chroma_stack is not None and not settings.chroma_rank:
        energies = (principal_energies(luminance, light_scale), principal_energies(chroma_stack, light_scale))
    candidates = []
    for bits in (8, 16) if settings.basis_bits == 0 else (settings.basis_bits,):
        widest = LowRankStack.fit(luminance, most, light_scale=light_scale, bits=bits)
        fixed = other_bytes + _FILE_BYTES + (_LIGHT_BYTES + 8) * n + deflated_bytes(widest.mean.astype(np.float16)) + deflated_bytes(scale.astype(np.float16))
        if colour is not None:
            fixed += deflated_bytes(colour_codes(colour))
        chroma = None
        if chroma_stack is not None:
            if settings.chroma_rank:
                chroma_rank = min(settings.chroma_rank, n - 1)
            else:
                costs = component_bytes(widest)
                chroma_bytes = 2.0 * float(np.median(costs)) if costs.size else 1.0  # two planes, each about a luminance image
                floor = min(settings.min_luminance_rank, widest.rank)  # the luminance's floor is paid for first
                left = budget - fixed - 2 * deflated_bytes(widest.mean.astype(np.float16)) - costs[:floor].sum()
                _, chroma_rank = split_ranks(LUMINANCE_GAIN * energies[0][1 + floor : widest.rank + 1], costs[floor:], CHROMA_GAIN * energies[1][1 : most + 1], chroma_bytes, left)
            chroma = LowRankStack.fit(chroma_stack, chroma_rank, light_scale=light_scale, bits=bits)
            chroma_costs = component_bytes(chroma)
            if not settings.chroma_rank and chroma.rank:  # the estimate was low: keep what leaves the luminance its floor
                room = budget - fixed - deflated_bytes(chroma.mean.astype(np.float16)) - costs[:floor].sum()
                keep = int(np.searchsorted(np.cumsum(chroma_costs), room, side="right"))
                if keep < chroma.rank:
                    chroma = LowRankStack.fit(chroma_stack, keep, light_scale=light_scale, bits=bits)
                    chroma_costs = chroma_costs[:keep]
            fixed += deflated_bytes(chroma.mean.astype(np.float16)) + int(chroma_costs.sum())
        stack = widest
        if not settings.luminance_rank:
            rank = max(choose_luminance_rank(widest, fixed, budget), settings.min_luminance_rank)
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
