"""The residual of a fitted field: what each captured image holds beyond its own moving highlights.

Relighting by residual transfer (``docs/method.md``, "The residual") composes ``I'(w) = R~(w) + c(x) S'(w)``, where
``R_i = I_i - c(x) R(x; G_i)`` is light i's captured image minus its own fitted highlights,
``R~`` interpolates those residuals over the triangulation with the query's barycentric weights, and
``c(x)`` is the per-pixel highlight colour. A :class:`ResidualModel` stores the residuals as one of
three kinds (``ResidualModel.kind``):

- **images**: the n residual images, float16 (what the alpha blend needs too);
- **lowrank**: R_i(x) = s(x) N_i(x), with s(x) a per-pixel scale (the RMS of the
  pixel's residual luminance over the lights) and N the normalised residual in an opponent colour
  split, luminance Y = 0.2126 R + 0.7152 G + 0.0722 B and chroma (B - Y, R - Y), each a
  :class:`LowRankStack`: a mean image plus k basis images with per-light weights. Blending the
  weights barycentrically blends the images exactly, so a query costs k multiply-adds per pixel and
  plane. A low-rank residual may instead be interpolated with radial basis weights over every light
  (``rbf_sigma``, ``model.rbf``): the same blend of the weight rows, with other weights. Normalising by s(x)
  spreads the approximation error in proportion to each pixel's
  brightness, as the eye (and 8-bit sRGB) sees it, instead of letting bright pixels take all of it;
  dark backgrounds stay dark. The basis images are kept as 8- or 16-bit codes with a per-image range, and
  s(x) as float16, exactly as the field file stores them.
- **learned** (``fit --residual learned``, the default on a GPU): a :class:`NeuralResidual`, a code of 9 numbers
  per pixel and a small MLP that decodes code + query direction to the residual directly (NeuralRTI's
  model, ``kernels.neural``); no barycentric blend of residuals, so a captured light is given back
  only as well as the model learned it.

All values are in the field's units (the fit's exposure applied). This module holds the data and
its checks; ``warp_highlights.residual`` builds, compresses, learns and decodes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .errors import InputError, finite_array

__all__ = ["COLOUR_STEP", "CompressedChunks", "FLOAT16_SAFE", "LUMINANCE_WEIGHTS", "LowRankStack", "NEURAL_CODE_SIZE",
           "NEURAL_HIDDEN", "NEURAL_HIGHLIGHT_INPUTS", "NEURAL_INPUTS", "NEURAL_LAYER_SHAPES", "NEURAL_MAX_HIDDEN",
           "NeuralResidual",
           "ResidualModel", "code_levels", "colour_codes", "colour_from_codes", "decoder_layer_shapes",
           "decoder_widths", "highlight_inputs", "learned_bounds", "parse_hidden", "sees_highlights",
           "standard_decoder"]

LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB primaries, linear: luminance Y of an RGB value."""

FLOAT16_SAFE = 6.0e4
"""Decoded residual images are clipped to +-this (float16's largest finite value is 65504)."""
COLOUR_STEP = 4.0 / 255
"""Resolution of the stored highlight colour c(x): 8 bits over [0, 4] per channel (4: a highlight four
times brighter in one channel than its luminance, beyond any metal's tint)."""


def colour_codes(colour: np.ndarray) -> np.ndarray:
    """A highlight colour c(x) as the file keeps it: uint8 codes of ``COLOUR_STEP``."""
    return np.round(np.asarray(colour, dtype=np.float64) / COLOUR_STEP).clip(0, 255).astype(np.uint8)


def colour_from_codes(codes: np.ndarray) -> np.ndarray:
    """Inverse of ``colour_codes``: float32 c(x)."""
    return np.asarray(codes).astype(np.float32) * np.float32(COLOUR_STEP)








def code_levels(bits: int) -> int:
    """Highest code of ``bits``-bit basis codes: 255 or 65535 (other bits: ``InputError``)."""
    if bits not in (8, 16):
        raise InputError(f"residual basis bits must be 8 or 16, got {bits}")
    return 255 if bits == 8 else 65535








class CompressedChunks(Protocol):
    """Where the field writer finds a basis image's stored codes already compressed (``io.codes.CompressedCodes``)."""

    def chunk(self, stored: np.ndarray) -> bytes: ...





















@dataclass(frozen=True, eq=False)
class LowRankStack:
    """n images of P planes: image i = mean_weights[i] mean + weights[i] @ basis.

    Attributes:
        mean: (H, W, P) float32.
        codes: (k, H, W, P) uint8 or uint16: basis image j is ``low[j] + codes[j] * (high[j] - low[j]) / L``
            with L = 255 or 65535.
        ranges: (k, 2) float32 (low, high) per basis image.
        weights: (n, k) float32 per-light weights.
        mean_weights: (n,) float32 per-light weight of the mean image (None: all 1).
        chunks: the basis images' codes compressed as the field file stores them (``io.codes.CompressedCodes``,
            found by content), where the fit's rate search measured them; the field writer compresses
            what it does not find there. Not part of the model (never compared, never stored).
    """

    mean: np.ndarray
    codes: np.ndarray
    ranges: np.ndarray
    weights: np.ndarray
    mean_weights: np.ndarray | None = None
    chunks: CompressedChunks | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        mean = finite_array(self.mean, np.float32, "residual mean")
        codes = np.ascontiguousarray(self.codes)
        if codes.dtype not in (np.uint8, np.uint16):
            raise InputError(f"residual basis codes must be uint8 or uint16, got {codes.dtype}")
        ranges = finite_array(self.ranges, np.float32, "residual basis ranges")
        weights = finite_array(self.weights, np.float32, "residual weights")
        if mean.ndim != 3 or codes.ndim != 4 or codes.shape[1:] != mean.shape:
            raise InputError(
                f"residual basis {codes.shape} does not match its mean image {mean.shape}: expected (k, H, W, P)")
        k = len(codes)
        if ranges.shape != (k, 2) or weights.ndim != 2 or weights.shape[1] != k:
            raise InputError(
                f"residual ranges {ranges.shape} and weights {weights.shape} must be ({k}, 2) and (n, {k})")
        mean_weights = (np.ones(len(weights), np.float32) if self.mean_weights is None
                        else finite_array(self.mean_weights, np.float32, "residual mean weights"))
        if mean_weights.shape != (len(weights),):
            raise InputError(f"residual mean weights must have shape ({len(weights)},), got {mean_weights.shape}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "mean_weights", mean_weights)



    @property
    def rank(self) -> int:
        return len(self.codes)

    @property
    def bits(self) -> int:
        """8 or 16: the basis codes' bits."""
        return 8 * self.codes.dtype.itemsize


























NEURAL_CODE_SIZE = 9
"""Numbers per pixel of a learned residual (``kernels.neural.CODE_SIZE``)."""
NEURAL_INPUTS = NEURAL_CODE_SIZE + 3
"""A decoder's inputs: the pixel's code and the unit light direction (x, y, z)."""
NEURAL_HIGHLIGHT_INPUTS = 2
"""Inputs a decoder that sees the highlights takes after the code and the direction: sqrt(g) and g, g the
Gaussians' luminance at the pixel for that light, display units (``highlight_inputs``)."""
NEURAL_HIDDEN = (48, 48, 48)
"""The hidden layers' widths of the decoder a fit learns (``kernels.neural``; NeuralRTI: three of 50)."""


def highlight_inputs(luminance) -> np.ndarray:
    """(..., 2) float32 (sqrt(g), g) of the Gaussians' luminance g (display units, negative values taken as 0): the
    inputs a decoder that sees the highlights takes after the code and the direction."""
    g = np.maximum(np.asarray(luminance, np.float32), np.float32(0.0))
    return np.stack([np.sqrt(g), g], axis=-1)


def decoder_layer_shapes(hidden, highlights: bool = False) -> tuple:
    """Shapes of the weight and bias arrays w0, b0, ..., of a decoder with ``hidden`` layer widths: each
    hidden layer (width, inputs) and (width, 1), then the RGB output's (3, last width) and (3, 1); ``highlights``:
    the first layer also takes ``NEURAL_HIGHLIGHT_INPUTS``."""
    widths = [NEURAL_INPUTS + (NEURAL_HIGHLIGHT_INPUTS if highlights else 0), *map(int, hidden), 3]
    return tuple(shape for inputs, outputs in zip(widths[:-1], widths[1:]) for shape in ((outputs, inputs),
                                                                                         (outputs, 1)))


NEURAL_LAYER_SHAPES = decoder_layer_shapes(NEURAL_HIDDEN)
"""Shapes of a fitted learned residual's weights w0, b0, ..., w3, b3 (``kernels.neural``)."""
NEURAL_MAX_HIDDEN = len(NEURAL_HIDDEN)
"""A decoder has 1 to this many hidden layers, each at most as wide as the fitted decoder's
(``NEURAL_HIDDEN``): a smaller one (``residual.distil``) decodes exactly through the fitted decoder's
kernels once embedded in its shape (``standard_decoder``)."""


def parse_hidden(text: str) -> tuple[int, ...]:
    """'24,24' -> (24, 24): 1 to ``NEURAL_MAX_HIDDEN`` widths of 1 to the fitted decoder's (InputError)."""
    try:
        widths = tuple(int(part) for part in str(text).split(","))
    except ValueError:
        widths = ()
    if not 1 <= len(widths) <= NEURAL_MAX_HIDDEN or not all(1 <= w <= NEURAL_HIDDEN[0] for w in widths):
        raise InputError(f"hidden layers must be 1 to {NEURAL_MAX_HIDDEN} comma-separated widths of 1 to "
                         f"{NEURAL_HIDDEN[0]} (e.g. 24,24), got {text!r}")
    return widths


def decoder_widths(weights) -> tuple[int, ...]:
    """The hidden layers' widths of a decoder's weight arrays (w0, b0, ...)."""
    return tuple(int(np.shape(w)[0]) for w in list(weights)[0:-2:2])


def sees_highlights(weights) -> bool:
    """Whether a decoder's weight arrays (w0, b0, ...) take the highlights' inputs (``highlight_inputs``)."""
    return int(np.shape(list(weights)[0])[1]) == NEURAL_INPUTS + NEURAL_HIGHLIGHT_INPUTS


def standard_decoder(weights) -> tuple:
    """The eight float32 arrays (``NEURAL_LAYER_SHAPES``) of a decoder that computes exactly what ``weights``
    (1 to ``NEURAL_MAX_HIDDEN`` hidden layers no wider than ``NEURAL_HIDDEN``) computes, up to float32
    rounding: each layer padded with zero units, and missing hidden layers passing their input on.

    A passing layer adds 1 and its successor takes the 1 back: an ELU's output is >= -1, so the ELU
    of (h + 1) is h + 1 itself."""
    weights = [np.asarray(w, np.float32) for w in weights]
    widths = decoder_widths(weights)
    shapes = decoder_layer_shapes(NEURAL_HIDDEN, sees_highlights(weights))
    if len(widths) == NEURAL_MAX_HIDDEN and all(w.shape == s for w, s in zip(weights, shapes)):
        return tuple(weights)
    layers = [[w, b.reshape(-1)] for w, b in zip(weights[0::2], weights[1::2])]
    last = len(widths)  # the output layer's index
    for _ in range(NEURAL_MAX_HIDDEN - len(widths)):  # pass the last hidden layer's values on, shifted by 1
        layers.insert(last, [np.eye(widths[-1], dtype=np.float32), np.ones(widths[-1], np.float32)])
    if len(widths) < NEURAL_MAX_HIDDEN:
        w_out, b_out = layers[-1]
        layers[-1] = [w_out, b_out - w_out.sum(axis=1)]  # the shift taken back
        for k in range(last + 1, NEURAL_MAX_HIDDEN):
            layers[k][1] = np.zeros(widths[-1], np.float32)  # already shifted
    standard = []
    for (w, b), (w_shape, b_shape) in zip(layers, zip(shapes[0::2], shapes[1::2])):
        padded = np.zeros(w_shape, np.float32)
        padded[:w.shape[0], :w.shape[1]] = w
        bias = np.zeros(b_shape, np.float32)
        bias[:len(b), 0] = b
        standard += [padded, bias]
    return tuple(standard)






@dataclass(frozen=True, eq=False)
class NeuralResidual:
    """A learned residual: R(x, w) = unit * decode_display(MLP(code(x), w)), field units, RGB; for a decoder that
    sees the highlights, the whole image unit * decode_display(MLP(code(x), w, sqrt(g), g)), g the moved Gaussians'
    luminance at x in display units (``highlight_inputs``).

    Attributes:
        codes: (H, W, 9) float16 per-pixel codes.
        weights: the MLP's float32 arrays w0, b0, ... (``decoder_layer_shapes``): the fitted decoder's eight
            (``NEURAL_LAYER_SHAPES``), or a smaller one's (1 to ``NEURAL_MAX_HIDDEN`` hidden layers no wider).
        unit: field units per display unit (the fit's exposure factor).
        light_count: lights it was trained on.
        bounds: (2, H, W, 3) float16 field units, or None: per pixel and channel the lowest and highest value
            a relit residual may take (``learned_bounds``); None leaves it unbounded (files before version 7).
    """

    codes: np.ndarray
    weights: tuple
    unit: float
    light_count: int
    bounds: np.ndarray | None = None

    @property
    def hidden(self) -> tuple[int, ...]:
        """The decoder's hidden layers' widths (``NEURAL_HIDDEN`` for a fitted one)."""
        return decoder_widths(self.weights)

    @property
    def sees_highlights(self) -> bool:
        """Whether the decoder also takes the Gaussians' luminance at the pixel (``highlight_inputs``): its output is
        then the whole image, the Gaussians its inputs, not added to it."""
        return sees_highlights(self.weights)

    def within_bounds(self, values: np.ndarray) -> np.ndarray:
        """(..., H, W, 3) residual values (field units) kept within ``bounds``; as they are without bounds."""
        if self.bounds is None:
            return values
        return np.clip(values, self.bounds[0].astype(values.dtype), self.bounds[1].astype(values.dtype))

    @property
    def standard_weights(self) -> tuple:
        """The decoder as the fitted decoder's eight arrays, computing the same (``standard_decoder``)."""
        return standard_decoder(self.weights)

    def __post_init__(self):
        codes = finite_array(self.codes, np.float16, "learned residual codes")
        if codes.ndim != 3 or codes.shape[2] != NEURAL_CODE_SIZE:
            raise InputError(f"learned residual codes must have shape (H, W, {NEURAL_CODE_SIZE}), got {codes.shape}")
        weights = tuple(finite_array(w, np.float32, "learned residual weights") for w in self.weights)
        layers = len(weights) // 2 - 1
        if len(weights) % 2 or not 1 <= layers <= NEURAL_MAX_HIDDEN:
            raise InputError(f"a learned residual's decoder has 1 to {NEURAL_MAX_HIDDEN} hidden layers: 4 to "
                             f"{2 * NEURAL_MAX_HIDDEN + 2} weight arrays, got {len(weights)}")
        widths = decoder_widths(weights)
        expected = decoder_layer_shapes(widths, sees_highlights(weights))
        if (any(w.shape != shape for w, shape in zip(weights, expected))
                or any(not 1 <= width <= limit for width, limit in zip(widths, NEURAL_HIDDEN))):
            raise InputError(f"learned residual weights must have shapes {list(expected)} with hidden layers of 1 to "
                             f"{NEURAL_HIDDEN[0]} units, got {[x.shape for x in weights]}")
        if not (np.isfinite(self.unit) and self.unit > 0) or int(self.light_count) < 1:
            raise InputError(
                f"a learned residual needs a unit > 0 and at least one light, got {self.unit} and {self.light_count}")
        if self.bounds is not None:
            bounds = finite_array(self.bounds, np.float16, "learned residual bounds")
            if bounds.shape != (2, *codes.shape[:2], 3) or np.any(bounds[0] > bounds[1]):
                raise InputError(f"learned residual bounds must have shape (2, {codes.shape[0]}, {codes.shape[1]}, 3), "
                                 f"the lows not above the highs, got {bounds.shape}")
            object.__setattr__(self, "bounds", bounds)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "unit", float(self.unit))
        object.__setattr__(self, "light_count", int(self.light_count))


def learned_bounds(lowest: np.ndarray, highest: np.ndarray, span: np.ndarray | None = None) -> np.ndarray:
    """(2, H, W, 3) float16 bounds of a learned residual from the (H, W, 3) lowest and highest values of what it
    learned at the captured lights (field units, ``residual.learned.bounded``): that range widened on either side by
    ``span`` (H, W, 3), the range of the captured images themselves (default: its own).

    Between the captured lights a decoder trained on them is free, and where they hardly constrain it (a pixel
    that every light leaves dark, a direction far from any light) it can answer with light the capture never
    shows: a lit background that flashes in on some frames of an animation, or a faint haze over it. Values inside
    the widened range stay as they are: a highlight brighter between two lights than at either (the dome sample's
    broad highlight) keeps its peak. Widened by the images' range, not the residual's, a pixel that no captured
    light shows lit stays within what its residual took there: the faint tails of the Gaussians taken out of it
    vary from light to light, and widened by that variation a black background let a haze of a few 8-bit levels
    through. Measured with ``benchmarks/bench_motion.py`` and ``benchmarks/bench_quality.py``
    (docs/method.md, The residual).
    """
    lowest, highest = np.asarray(lowest, np.float64), np.asarray(highest, np.float64)
    span = highest - lowest if span is None else np.asarray(span, np.float64)
    return np.clip(np.stack([lowest - span, highest + span]), -FLOAT16_SAFE, FLOAT16_SAFE).astype(np.float16)



@dataclass(frozen=True, eq=False)
class ResidualModel:
    """The residual images R_i of a field's n lights (see the module docstring).

    Attributes:
        images: (n, H, W, C) float16 uncompressed residuals, or None when low rank.
        luminance: ``LowRankStack`` of Y (P = 1), or None when uncompressed.
        chroma: ``LowRankStack`` of (B - Y, R - Y) (P = 2) for colour fields, else None.
        highlight_colour: (H, W, C) float32 c(x) >= 0 (luminance 1 for a grey highlight), or None (white).
        scale: (H, W) float32 s(x) > 0 multiplying the low-rank stacks, or None (1).
        learned: a ``NeuralResidual`` instead of images or stacks, or None.
        rbf_sigma: a low-rank residual's radial basis width (chord units, ``model.rbf``): relighting weighs its
            lights phi(w)^T (K + lambda I)^-1 instead of the query's barycentric weights; None: the triangle's.
        channels: C, 1 or 3.
    """

    images: np.ndarray | None = None
    luminance: LowRankStack | None = None
    chroma: LowRankStack | None = None
    highlight_colour: np.ndarray | None = None
    scale: np.ndarray | None = None
    learned: NeuralResidual | None = None
    rbf_sigma: float | None = None

    def __post_init__(self):
        if sum(part is not None for part in (self.images, self.luminance, self.learned)) != 1:
            raise InputError("a residual model holds exactly one of: the residual images, a low-rank luminance stack, "
                             "a learned residual")
        if self.learned is not None and (self.chroma is not None or self.scale is not None):
            raise InputError("a learned residual takes no chroma stack and no scale")
        if self.images is not None:
            images = finite_array(self.images, np.float16, "residual images")
            if images.ndim != 4 or images.shape[3] not in (1, 3):
                raise InputError(f"residual images must have shape (n, H, W, C) with C 1 or 3, got {images.shape}")
            object.__setattr__(self, "images", images)
            if self.chroma is not None:
                raise InputError("uncompressed residual images take no chroma stack")
        elif self.luminance is not None:
            lum = self.luminance
            if lum.mean.shape[2] != 1:
                raise InputError(f"the residual luminance stack must have 1 plane, got {lum.mean.shape[2]}")
            if self.chroma is not None:
                if self.chroma.mean.shape != lum.mean.shape[:2] + (2,) or len(self.chroma.weights) != len(lum.weights):
                    raise InputError(
                        "the residual chroma stack must have 2 planes of the luminance's size and the same light count")
        if self.rbf_sigma is not None:
            sigma = float(self.rbf_sigma)
            if self.luminance is None or not (np.isfinite(sigma) and 0.0 < sigma <= 4.0):
                raise InputError(f"a radial basis interpolation goes with a low-rank residual and needs a width in "
                                 f"(0, 4] (chord units), got {self.rbf_sigma}")
            object.__setattr__(self, "rbf_sigma", sigma)
        if self.scale is not None:
            scale = finite_array(self.scale, np.float32, "residual scale")
            if self.images is not None or scale.shape != (self.height, self.width) or np.any(scale <= 0):
                raise InputError(f"a residual scale goes with low-rank stacks and must be ({self.height}, "
                                 f"{self.width}) values > 0, got {scale.shape}")
            object.__setattr__(self, "scale", scale)
        if self.highlight_colour is not None:
            colour = finite_array(self.highlight_colour, np.float32, "highlight colour")
            if colour.shape != (self.height, self.width, self.channels) or np.any(colour < 0):
                raise InputError(f"highlight colour must be ({self.height}, {self.width}, {self.channels}) values >= "
                                 f"0, got {colour.shape}")
            object.__setattr__(self, "highlight_colour", colour)

    @property
    def kind(self) -> str:
        """"lowrank", "learned" or "images": how the residual is stored."""
        return "lowrank" if self.luminance is not None else "learned" if self.learned is not None else "images"

    @property
    def interpolation(self) -> str:
        """"rbf" (radial basis weights over every light) or "triangle" (the query's barycentric weights);
        a learned residual is decoded, not interpolated: "triangle" (unused)."""
        return "rbf" if self.rbf_sigma is not None else "triangle"

    @property
    def light_count(self) -> int:
        if self.learned is not None:
            return self.learned.light_count
        return len(self.images) if self.images is not None else len(self.luminance.weights)

    @property
    def height(self) -> int:
        if self.learned is not None:
            return self.learned.codes.shape[0]
        return (self.images.shape[1] if self.images is not None else self.luminance.mean.shape[0])

    @property
    def width(self) -> int:
        if self.learned is not None:
            return self.learned.codes.shape[1]
        return (self.images.shape[2] if self.images is not None else self.luminance.mean.shape[1])

    @property
    def channels(self) -> int:
        if self.images is not None:
            return self.images.shape[3]
        if self.learned is not None:
            return 3
        return 3 if self.chroma is not None else 1

    def describe(self) -> str:
        if self.images is not None:
            kind = f"{self.light_count} residual images (float16)"
        elif self.learned is not None:
            layers = "-".join(map(str, self.learned.hidden))
            inputs = ", code, direction and the moved Gaussians in" if self.learned.sees_highlights else ""
            kind = f"learned ({NEURAL_CODE_SIZE} numbers per pixel and an MLP, hidden layers {layers}{inputs})"
        else:
            chroma = f" + chroma rank {self.chroma.rank}" if self.chroma is not None else ""
            kind = f"low rank: luminance rank {self.luminance.rank}{chroma} ({self.luminance.bits}-bit bases)"
            if self.rbf_sigma is not None:
                kind += f", radial basis weights (sigma {self.rbf_sigma:.3g})"
        colour = "per-pixel" if self.highlight_colour is not None else "white"
        return f"residual: {kind}; highlight colour {colour}"



