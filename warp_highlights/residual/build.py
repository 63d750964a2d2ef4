"""The residual built: the low-rank field (luminance and chroma stacks within the size budget) or the
images themselves (float16).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..io.codes import CompressedCodes
from ..kernels.gram import DeviceProducts
from ..kernels.stacks import NormalisedStacks
from ..model.config import ResidualSettings
from ..model.memory import available_memory
from ..model.residual import (
    LUMINANCE_WEIGHTS,
    ResidualModel,
    code_levels,
    colour_codes,
)
from ..model.threads import NUMPY_THREADS, mapped_empty, parallel_map
from ..quality.metrics import srgb_psnr
from .decode import decoded_lights
from .inputs import (
    HeldImages,
    residual_of,
    residual_scale,
    row_bands,
    scale_of_mean_square,
)
from .opponent import luminance_of, to_opponent
from .principal import PrincipalImages
from .quantise import quantised_stack
from .rate import (
    FILE_BYTES,
    LIGHT_BYTES,
    StackPlan,
    allocate,
    entry_bytes,
    finest_within,
    quantised_bytes,
)

__all__ = ["CHROMA_GAIN", "HELD_STACK_SHARE", "LUMINANCE_GAIN", "NormalisedResidual", "SCORED_LIGHTS", "build_residual",
           "captured_psnr"]

LUMINANCE_GAIN = 3.0
"""Squared RGB error per unit of squared luminance error: an error in Y shifts R, G and B alike."""
CHROMA_GAIN = 1.0 + 0.5 * ((LUMINANCE_WEIGHTS[0] / LUMINANCE_WEIGHTS[1]) ** 2
                           + (LUMINANCE_WEIGHTS[2] / LUMINANCE_WEIGHTS[1]) ** 2)
"""The same for the chroma planes (B - Y, R - Y), averaged: an error in B - Y moves B and, by wb / wg, G."""
HELD_STACK_SHARE = 0.25
"""The normalised luminance and chroma stacks (float32, as large as the images) are held while they take
at most this share of the available memory; beyond it they are computed from the images a block at a
time in each of their three passes, and their principal directions (as large) are kept in a temporary
file mapped into memory (``spilled_empty``). The 250-light 480x270 donut: 0.5 GB less at the peak, 3.8 s
more on the 2-core CPU (``benchmarks/bench_residual.py``); a 100-light 3840x2160 capture's stacks are 10 GB.
Where a CUDA device holds the stacks instead (``kernels.stacks``), the same share decides whether the
principal images' host copy goes to that mapped file, where the device has no room for them (else they
stay there, and the host keeps no copy)."""


def build_residual(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, *, settings: ResidualSettings,
                   other_bytes: int = 0,
                   device=None, held_images: HeldImages | None = None, display_scale: float = 1.0,
                   report: dict | None = None) -> ResidualModel:
    """The ``ResidualModel`` of (n, H, W, C) images (field units) and their own (n, H, W) highlights.
    On a CUDA ``device`` the stacks' products (Gram matrices, projections, the weights' normal
    equations) are summed there (``kernels.gram``); elsewhere by the host's BLAS. There too, where they
    fit (``kernels.gram.HELD_SHARE`` of its free memory), the normalised stacks are made and held
    there (``kernels.stacks``), and then the principal images, which are quantised there
    (``kernels.quantise``).

    Compressed, a stack whose rank the settings fix keeps that many basis images, each quantised over
    its whole range. Otherwise the whole field is kept within ``size_budget`` of the 8-bit capture,
    counting ``other_bytes`` (the Gaussians and paths) and the compressed size of every stored array:
    ``allocate_steps`` chooses, for the luminance and chroma together, how many basis images to keep
    and how finely to quantise each, so that each adds the same squared RGB error (at most
    ``max_luminance_rank`` luminance images, at least ``min_luminance_rank``). The codes are 8 or 16
    bits as the settings say, or else those of the lower squared error the rate-distortion model
    predicts (``StackPlan.distortion``); 16 bits are not tried where 8-bit codes already hold every
    kept image's step (16-bit codes would store the same quantisation in more bytes). ``held_images``:
    the images (and, where not None, ``own``) on the device already (``HeldImages``), read there.

    Where the rate search decides a rank and the field gives the captured lights back below
    ``min_captured_psnr_db`` (``captured_psnr``; ``display_scale`` takes field units to display units), the budget
    grows by half at a time up to ``max_size_budget``. ``report``, where given, receives the budget used
    (``size_budget``, a share of the capture) and the captured lights' score (``captured_psnr_db``).
    """
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 3:
        images = images[..., None]
    n, height, width, channels = images.shape
    tint = np.broadcast_to(np.ones((1, 1, channels), np.float32) if colour is None else colour,
                           (height, width, channels))
    if settings.kind == "images":
        stored = np.empty(images.shape, np.float16)

        def subtract(band: slice) -> None:
            stored[:, band] = residual_of(images[:, band], own[:, band], tint[band])

        parallel_map(subtract, row_bands(images))
        return ResidualModel(images=stored, highlight_colour=colour)
    products = _device_products(device)
    available = available_memory()
    held = available is None or n * height * width * channels * 4 <= HELD_STACK_SHARE * available
    if products is not None and products.holds(NormalisedStacks.nbytes(images.shape)):
        # on the device: the stacks made there from the images' bands, and read there by every product; the
        # principal images there too where they fit, else on the host (in a file mapped into memory where
        # the host's stacks would not be held)
        stacks = NormalisedStacks.make(images, own, tint, products, scale_of=scale_of_mean_square,
                                       held_images=None if held_images is None else held_images.images,
                                       held_own=None if held_images is None else held_images.own)
        if held_images is not None:  # read: the device's memory let go for the principal images
            held_images.images = held_images.own = None
        light_scale = np.sqrt(stacks.squares / (height * width))
        luminance = PrincipalImages.of_source(stacks.luminance, light_scale, spill=not held, products=products)
        chroma = (None if stacks.chroma is None
                  else PrincipalImages.of_source(stacks.chroma, light_scale, spill=not held, products=products))
        return _floored(lambda share: _compressed(luminance, chroma, stacks.scale, colour, settings, other_bytes,
                                                  n * height * width * channels, share),
                        images, own, tint, settings, display_scale, report)
    # s(x), each light's sum of squares of its normalised luminance and, where they fit the memory, the
    # normalised luminance and chroma stacks (float32), a band of rows at a time (float64 inside)
    scale = np.empty((height, width), np.float32)
    luminance_stack = mapped_empty((n, height, width, 1), np.float32) if held else None
    chroma_stack = mapped_empty((n, height, width, 2), np.float32) if held and channels == 3 else None

    def normalise(band: slice) -> np.ndarray:  # the bands in threads; returns each light's sum of squares over the band
        residual = residual_of(images[:, band], own[:, band], tint[band])
        y, opponent = ((residual[..., 0].astype(np.float64), None) if channels == 1
                       else to_opponent(residual, with_chroma=chroma_stack is not None))
        scale[band] = residual_scale(y)
        normalised = y / scale[band]
        if luminance_stack is not None:
            luminance_stack[:, band, :, 0] = normalised
        if chroma_stack is not None:
            chroma_stack[:, band] = opponent / scale[band, :, None]
        return np.sum(normalised**2, axis=(1, 2))

    squares = sum(parallel_map(normalise, row_bands(images)))
    light_scale = np.sqrt(squares / (height * width))  # both stacks weigh each light by its brightness
    if held:
        luminance = PrincipalImages.of(luminance_stack, light_scale, products=products)
        chroma = None if chroma_stack is None else PrincipalImages.of(chroma_stack, light_scale, products=products)
    else:
        # read from the images a block at a time (three passes each instead of one), never held whole; the principal
        # directions, as large, in a file mapped into memory (paged out as memory runs short), or on the device where
        # the products are summed there and it has room for them (no host copy then)
        luminance = PrincipalImages.of_source(NormalisedResidual(images, own, tint, scale, "luminance"), light_scale,
                                              spill=True, products=products)
        chroma = None if channels == 1 else PrincipalImages.of_source(NormalisedResidual(images, own, tint, scale,
                                                                                         "chroma"), light_scale,
                                                                      spill=True,
                                                                      products=products)
    luminance_stack = chroma_stack = None  # the principal images hold them now
    return _floored(lambda share: _compressed(luminance, chroma, scale, colour, settings, other_bytes,
                                              n * height * width * channels, share),
                    images, own, tint, settings, display_scale, report)


def _device_products(device) -> DeviceProducts | None:
    """Where ``build_residual`` sums its stacks' products and holds them: a CUDA device's
    ``DeviceProducts``; None elsewhere (the host's BLAS, the host's stacks)."""
    return DeviceProducts(device) if device is not None and wp.get_device(device).is_cuda else None


_BUDGET_GROWTH = 1.5
"""The size budget's factor a step while the captured lights come back below ``min_captured_psnr_db``."""


def _floored(compressed, images: np.ndarray, own: np.ndarray, tint: np.ndarray, settings: ResidualSettings,
             display_scale: float, report: dict | None) -> ResidualModel:
    """``compressed(share)`` (the model within ``share`` of the capture) at ``size_budget``, and at budgets grown by
    ``_BUDGET_GROWTH`` up to ``max_size_budget`` while it gives the captured lights back below
    ``min_captured_psnr_db`` (only where the rate search decides a rank: fixed ranks ignore the budget)."""
    share = settings.size_budget
    fixed = settings.luminance_rank and (settings.chroma_rank or images.shape[-1] == 1)
    floor = 0.0 if fixed else settings.min_captured_psnr_db
    while True:
        model = compressed(share)
        score = captured_psnr(model, images, own, tint, display_scale) if floor > 0 or report is not None else None
        if floor <= 0 or score >= floor or share >= settings.max_size_budget:
            break
        share = min(share * _BUDGET_GROWTH, settings.max_size_budget)
    if report is not None:
        report.update(size_budget=float(share), captured_psnr_db=round(float(score), 3))
    return model


SCORED_LIGHTS = 16
"""``captured_psnr`` scores at most this many captured lights, spread evenly over the capture's order: its cost stays
that of 16 decoded images however many lights (1,000 at 1920x1080 would otherwise decode a thousand)."""


def captured_psnr(model: ResidualModel, images: np.ndarray, own: np.ndarray, tint: np.ndarray,
                  display_scale: float = 1.0) -> float:
    """Mean 8-bit sRGB PSNR (dB) over the captured lights of the (n, H, W, C) ``images`` (field units; at most
    ``SCORED_LIGHTS`` of them, evenly spread) against what the field gives back there: the decoded residual plus
    each light's ``own`` highlights in colour ``tint``, both times ``display_scale``."""
    n = len(images)
    lights = np.unique(np.linspace(0, n - 1, min(n, SCORED_LIGHTS)).round().astype(np.int64))
    scores = []
    for start in range(0, len(lights), 4):  # a few decoded images held at a time
        chosen = lights[start : start + 4]
        for i, decoded in zip(chosen, decoded_lights(model, chosen)):
            given = (decoded.astype(np.float32) + own[i][..., None] * tint) * np.float32(display_scale)
            scores.append(srgb_psnr(given, images[i] * np.float32(display_scale)))
    return float(np.mean(scores))


def _compressed(luminance: PrincipalImages, chroma: PrincipalImages | None, scale: np.ndarray,
                colour: np.ndarray | None,
                settings: ResidualSettings, other_bytes: int, capture_values: int, share: float) -> ResidualModel:
    """``build_residual``'s model from the stacks' principal images: the bits and steps chosen within ``share``
    of the capture (``capture_values`` 8-bit values), the stacks quantised and their weights fitted."""
    n = luminance.light_count
    budget = share * capture_values
    # the other planes as the file stores them, planes first (io.fieldfile), measured in threads
    stored = [luminance.mean.astype(np.float16), scale.astype(np.float16)]
    stored += [colour_codes(colour).transpose(2, 0, 1)] if colour is not None else []
    stored += [chroma.mean.astype(np.float16).reshape(chroma.shape).transpose(2, 0, 1)] if chroma is not None else []
    fixed = (other_bytes + FILE_BYTES + (LIGHT_BYTES + 8) * n + sum(parallel_map(entry_bytes, stored))
             + (4 * n if chroma is not None else 0))
    # both widths when the settings leave it open: 8-bit first, measured on every row only if 16 bits do
    # not beat it (its every image at the finest 8-bit step is plain from the sampled bytes alone, and
    # the whole images' bytes can only make it coarser)
    options = []
    for bits in (8, 16) if settings.basis_bits == 0 else (settings.basis_bits,):
        options.append(_quantisation(luminance, chroma, settings, bits, budget - fixed,
                                     plain_finest=bits == 8 and settings.basis_bits == 0))
        if bits == 8 and settings.basis_bits == 0 and not options[-1].finer_with_16_bits:
            break  # 16-bit codes would hold the same quantisation in more bytes
    choice = min(options, key=lambda option: option.distortion)  # the first on ties: 8 bits
    if not choice.checked:
        options[0] = _quantisation(luminance, chroma, settings, 8, budget - fixed)
        choice = min(options, key=lambda option: option.distortion)
    stacks = {name: quantised_stack(principal, choice.steps[name], bits=choice.bits, chunks=choice.chunks.get(name))
              for name, principal in (("luminance", luminance), ("chroma", chroma)) if principal is not None}
    return ResidualModel(luminance=stacks["luminance"], chroma=stacks.get("chroma"), highlight_colour=colour,
                         scale=scale)


@dataclass(frozen=True)
class _Quantisation:
    """One bit depth's choice for the stacks: their steps by name, the squared RGB error the model
    predicts (``StackPlan.distortion``), and whether 16-bit codes would quantise any kept image finer
    at the same distortion."""

    bits: int
    steps: dict
    distortion: float
    finer_with_16_bits: bool
    checked: bool = True  # False: ``finest_within``'s choice, its bytes not yet measured on every row
    # by name: the chunks its last measurement on every row compressed
    chunks: dict = dataclasses.field(default_factory=dict)


def _quantisation(luminance: PrincipalImages, chroma: PrincipalImages | None, settings: ResidualSettings, bits: int,
                  left: float,
                  *, plain_finest: bool = False) -> _Quantisation:
    """The steps of both stacks at ``bits`` within ``left`` bytes: a stack whose rank the settings fix,
    each image over its whole range; the others by ``allocate``, or by ``finest_within`` where
    ``plain_finest`` is set, no rank is fixed and the sampled bytes make the choice plain (unchecked)."""
    levels = code_levels(bits)
    steps, plans, distortion, finer, chunks = {}, {}, 0.0, False, {}
    for name, principal, fixed_rank, gain in (("luminance", luminance, settings.luminance_rank, LUMINANCE_GAIN),
                                              ("chroma", chroma, settings.chroma_rank, CHROMA_GAIN)):
        if principal is None:
            continue
        if fixed_rank:
            rank = min(fixed_rank, principal.count - 1)
            steps[name] = principal.spans[:rank] / levels
            distortion += StackPlan(principal, gain, rank).distortion(steps[name])
            chunks[name] = CompressedCodes()
            left -= quantised_bytes(principal, steps[name], bits=bits, keep=chunks[name])
            finer = finer or rank > 0
        else:
            most = min(settings.max_luminance_rank, principal.count - 1) if name == "luminance" else principal.count - 1
            plans[name] = StackPlan(principal, gain, most, settings.min_luminance_rank if name == "luminance" else 0)
            chunks[name] = plans[name].chunks
    checked = True
    if plans:
        plain = finest_within(list(plans.values()), left, bits=bits) if plain_finest and not steps else None
        checked = plain is None
        log_distortion, chosen = plain if plain is not None else allocate(list(plans.values()), left, bits=bits)
        for (name, plan), plan_steps in zip(plans.items(), chosen):
            steps[name] = plan_steps
            distortion += plan.distortion(plan_steps)
            fine = plan.steps(np.exp(log_distortion), code_levels(16))
            finer = finer or len(fine) != len(plan_steps) or not np.array_equal(fine, plan_steps)
    return _Quantisation(bits, steps, distortion, finer, checked, chunks)


class NormalisedResidual:
    """The normalised residual N = (I - c(x) R(x; G)) / s(x) of (n, H, W, C) images as a ``StackSource``:
    its luminance (P = 1) or its chroma (P = 2, B - Y and R - Y), computed a block of columns at a
    time (the lights in threads), float32 values as a held stack would keep them.

    Args:
        images: (n, H, W, C) float32 images, field units.
        own: (n, H, W) float32 their own highlights.
        tint: (H, W, C) or (1, 1, C) float32 highlight colour.
        scale: (H, W) float32 s(x).
        kind: ``"luminance"`` or ``"chroma"``.
    """

    def __init__(self, images: np.ndarray, own: np.ndarray, tint: np.ndarray, scale: np.ndarray, kind: str):
        n, height, width, channels = images.shape
        self.planes = 1 if kind == "luminance" else 2
        self.kind = kind
        self.light_count = n
        self.shape = (height, width, self.planes)
        self.images = images.reshape(n, height * width, channels)
        self.own = own.reshape(n, height * width)
        self.tint = np.broadcast_to(tint, (height, width, channels)).reshape(height * width, channels)
        self.scale = scale.reshape(height * width)

    def block(self, columns: slice) -> np.ndarray:
        first, last = columns.start // self.planes, -(-columns.stop // self.planes)  # the pixels the columns cover
        pixels = slice(first, last)
        out = np.empty((self.light_count, (last - first) * self.planes), np.float64)

        def part(lights: slice) -> None:
            residual = residual_of(self.images[lights, pixels], self.own[lights, pixels], self.tint[pixels])
            if residual.shape[-1] == 1:
                out[lights] = (residual[..., 0].astype(np.float64) / self.scale[pixels]).astype(np.float32)
            elif self.kind == "luminance":
                out[lights] = (luminance_of(residual) / self.scale[pixels]).astype(np.float32)
            else:
                out[lights] = (to_opponent(residual)[1]
                               / self.scale[pixels, None]).astype(np.float32).reshape(len(residual), -1)

        step = max(1, -(-self.light_count // (2 * NUMPY_THREADS)))
        parallel_map(part,
                     [slice(start, min(start + step, self.light_count)) for start in range(0, self.light_count, step)])
        offset = first * self.planes
        return out[:, columns.start - offset : columns.stop - offset]
