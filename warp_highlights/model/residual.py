"""The residual of a fitted field: what each captured image holds beyond its own moving highlights.

Relighting by residual transfer (method.md section 6) composes ``I'(w) = R~(w) + c(x) S'(w)``, where
``R_i = I_i - c(x) R(x; G_i)`` is light i's captured image minus its own fitted highlights,
``R~`` interpolates those residuals over the triangulation with the query's barycentric weights, and
``c(x)`` is the per-pixel highlight colour. A :class:`ResidualModel` stores the residuals in one of
two ways:

- **uncompressed**: the n residual images, float16 (what the alpha blend needs too);
- **low rank** (the default): R_i(x) = s(x) N_i(x), with s(x) a per-pixel scale (the RMS of the
  pixel's residual luminance over the lights) and N the normalised residual in an opponent colour
  split, luminance Y = 0.2126 R + 0.7152 G + 0.0722 B and chroma (B - Y, R - Y), each a
  :class:`LowRankStack`: a mean image plus k basis images with per-light weights. Blending the
  weights barycentrically blends the images exactly, so a query costs k multiply-adds per pixel and
  plane. Normalising by s(x) spreads the approximation error in proportion to each pixel's
  brightness, as the eye (and 8-bit sRGB) sees it, instead of letting bright pixels take all of it;
  dark backgrounds stay dark. The basis images are kept as 8- or 16-bit codes with a per-image range, and
  s(x) as float16, exactly as the field file stores them.
- **learned** (``fit --residual neural``, for a GPU): a :class:`NeuralResidual`, a code of 9 numbers
  per pixel and a small MLP that decodes code + query direction to the residual directly (NeuralRTI's
  model, ``kernels.neural``); no barycentric blend of residuals, so a captured light is given back
  only as well as the model learned it.

All values are in the field's units (the fit's exposure applied).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Iterator, Protocol

import numpy as np

from .errors import InputError, finite_array
from .threads import NUMPY_THREADS, mapped_empty, parallel_map

__all__ = ["ArraySource", "COLOUR_STEP", "DeflatedPieces", "FLOAT16_SAFE", "HeldDirections", "clamped_steps", "quantisation_grid", "quantised_codes", "LUMINANCE_WEIGHTS", "LowRankStack", "StackSource", "NeuralResidual", "decode_display", "encode_display", "PrincipalImages", "ResidualModel", "code_levels", "codes_in_place", "colour_codes", "colour_from_codes", "from_opponent", "luminance_of", "quantise_basis", "spilled_empty", "to_opponent"]

LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB primaries, linear: luminance Y of an RGB value."""

FLOAT16_SAFE = 6.0e4
"""Decoded residual images are clipped to +-this (float16's largest finite value is 65504)."""
_LIGHT_SCALE_FLOOR = 1e-3  # of the brightest image's RMS: a black image is not divided by zero
COLOUR_STEP = 4.0 / 255
"""Resolution of the stored highlight colour c(x): 8 bits over [0, 4] per channel (4: a highlight four
times brighter in one channel than its luminance, beyond any metal's tint)."""


def colour_codes(colour: np.ndarray) -> np.ndarray:
    """A highlight colour c(x) as the file keeps it: uint8 codes of ``COLOUR_STEP``."""
    return np.round(np.asarray(colour, dtype=np.float64) / COLOUR_STEP).clip(0, 255).astype(np.uint8)


def colour_from_codes(codes: np.ndarray) -> np.ndarray:
    """Inverse of ``colour_codes``: float32 c(x)."""
    return np.asarray(codes).astype(np.float32) * np.float32(COLOUR_STEP)


def luminance_of(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> luminance Y (...,), float64 (``to_opponent``'s, bit for bit)."""
    return to_opponent(rgb, with_chroma=False)[0]


def to_opponent(rgb: np.ndarray, *, with_chroma: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """(..., 3) linear RGB -> luminance (...,) and chroma (..., 2) = (B - Y, R - Y), float64 (chroma
    None when not asked for)."""
    rgb = np.asarray(rgb)
    red, green, blue = (rgb[..., c].astype(np.float64) for c in range(3))  # plane by plane: no float64 copy of the whole stack
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


def code_levels(bits: int) -> int:
    """Highest code of ``bits``-bit basis codes: 255 or 65535 (other bits: ``InputError``)."""
    if bits not in (8, 16):
        raise InputError(f"residual basis bits must be 8 or 16, got {bits}")
    return 255 if bits == 8 else 65535


class StackSource(Protocol):
    """An (n, H, W, P) stack read a block of columns at a time, so that it need not be held whole
    (``fit.residual`` computes the normalised residual's blocks from the images). A source held on the
    products' device (``kernels.stacks.HeldStack``) also has ``on_device(columns)``: the block there."""

    light_count: int
    shape: tuple  # (H, W, P)

    def block(self, columns: slice) -> np.ndarray:
        """(n, len(columns)) float64 values of the flattened stack (H W P values an image, planes last)."""


class StackProducts(Protocol):
    """Where the stack's products are summed instead of the host's BLAS (``kernels.gram.DeviceProducts``
    on CUDA): ``upload`` a (rows, w) float32 block; ``cross_sum(rows, columns)`` a running float64 sum
    of a b^T over uploaded blocks (``add(a, b=None)``, ``value()``); ``project(matrix, block)`` a
    float64 (r, n) matrix times an (n, w) float32 block, as float32, into ``out`` where given. A block
    may be a strided view; ``staging(shape)`` a float32 host array to fill and upload (from where the
    upload reads it)."""

    def staging(self, shape: tuple) -> np.ndarray: ...

    def upload(self, block: np.ndarray): ...

    def cross_sum(self, rows: int, columns: int): ...

    def project(self, matrix: np.ndarray, block: np.ndarray, out: np.ndarray | None = None, *, keep=None, columns: slice | None = None,
                host: bool = True) -> np.ndarray | None: ...

    def held_directions(self, count: int, shape: tuple) -> HeldDirections | None:
        """Room on the device for ``count`` principal images of ``shape`` (``project`` fills it through
        ``keep``, at ``columns``), or None where they would not fit."""


class HeldDirections(Protocol):
    """Principal images held on a device as well (``kernels.quantise.DeviceBasis``), quantised there with
    ``codes_in_place``'s rounding: ``codes`` of images first .. first + len(step) into a (c, M) host
    array; ``stored`` their codes as ``io.codes`` stores them, at ``rows`` (each less its row ``above``,
    -1: none), into a (c, P, [2,] R, W) uint8 host array; ``design`` a block of the weights' design
    matrix there (``LowRankStack.quantised``); ``rows`` a (count, M) float32 host copy, ``extremes``
    each image's float32 (min, max) from ``first`` on. ``values``: M."""

    values: int

    def rows(self, first: int, count: int) -> np.ndarray: ...

    def extremes(self, first: int) -> tuple[np.ndarray, np.ndarray]: ...

    def codes(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, out: np.ndarray) -> np.ndarray: ...

    def stored(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, rows: np.ndarray, above: np.ndarray,
               out: np.ndarray) -> np.ndarray: ...

    def design(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, decoded_low: np.ndarray, decoded_step: np.ndarray,
               mean: np.ndarray, columns: slice):
        """The weights' (1 + c, w) design block there: ``mean`` and the images' decoded codes at ``columns``."""


class DeflatedPieces(Protocol):
    """Where the field writer finds a basis image's stored codes already compressed (``io.codes.CompressedCodes``)."""

    def piece(self, stored: np.ndarray) -> bytes: ...


@dataclass(frozen=True, eq=False)
class ArraySource:
    """A stack held whole as an (n, M) float32 array (M = H W P)."""

    flat: np.ndarray
    shape: tuple

    @property
    def light_count(self) -> int:
        return len(self.flat)

    def block(self, columns: slice) -> np.ndarray:
        return _as_float64(self.flat[:, columns])

    def block32(self, columns: slice) -> np.ndarray:
        """The same block as float32: a view of the stored values (``StackProducts`` copy it on)."""
        return self.flat[:, columns]


@dataclass(frozen=True, eq=False)
class PrincipalImages:
    """The principal images of an (n, H, W, P) stack, from which ``LowRankStack`` keeps a few.

    The images divided by a light scale (default: each image's RMS), uncentred, so a dark light's
    image counts as much as a bright one's; their principal directions come from the n x n Gram
    matrix (cheap for n << pixels). The first direction, scaled to the images' RMS, is the mean image
    every light weighs freely; the others are the basis images, unit norm, in descending energy.

    The stack is read from a ``StackSource`` a block of ``_BLOCK_VALUES`` values at a time, in
    float64; the only full-size copy made here is ``directions`` (float32: a 1,000-light 1920x1080
    luminance stack's are 8.3 GB), on the host, or on the device where the products are summed and
    the device has room for them (``held``; ``directions`` is then None and nothing full-size comes
    back: the extremes and the mean image are found there). A stack computed block by block
    (``fit.residual``'s normalised residual) is never held whole on the host.

    Attributes:
        source: the stack.
        shape: (H, W, P).
        energies: (r,) float64 descending sums of squares of the normalised images along each direction
            (r <= n: the directions of non-zero energy; at least 1): what keeping it removes.
        directions: (r, M) float32 unit rows on the host; None where ``held`` has them
            (``host_directions`` copies them down).
        mean: (M,) float64 the first direction at the images' scale.
        products: where the stack's products were summed (None: the host's BLAS); ``LowRankStack.quantised``
            sums its weights' there too.
        held: the directions held there instead, where they fit (``StackProducts.held_directions``):
            the rate search's codes and ``quantise_basis``' are made there.
    """

    source: StackSource
    shape: tuple
    energies: np.ndarray
    directions: np.ndarray | None
    mean: np.ndarray
    products: StackProducts | None = None
    held: HeldDirections | None = None

    def __post_init__(self):
        if self.directions is None and self.held is None:
            raise InputError("principal images need their directions on the host or held on a device (host_directions() copies them down)")

    @classmethod
    def of(cls, stack: np.ndarray, light_scale: np.ndarray | None = None, *, products: StackProducts | None = None) -> PrincipalImages:
        """The principal images of an (n, H, W, P) array (kept as float32)."""
        stack = np.asarray(stack)
        flat = np.ascontiguousarray(stack.reshape(len(stack), -1), dtype=np.float32)
        return cls.of_source(ArraySource(flat, tuple(stack.shape[1:])), light_scale, products=products)

    @classmethod
    def of_source(cls, source: StackSource, light_scale: np.ndarray | None = None, *, spill: bool = False,
                  products: StackProducts | None = None) -> PrincipalImages:
        """The principal images of the stack ``source`` gives, normalised by ``light_scale`` (default:
        each image's RMS, one more pass over the source). ``spill``: ``directions`` in a temporary
        file mapped into memory (``spilled_empty``) rather than in memory alone (where they are made on
        the host). ``products``: the Gram
        matrix and the projections summed there (the stack's float32 blocks, unscaled: the scale is
        applied to the n x n matrices), else by the host's BLAS on float64 blocks."""
        n = source.light_count
        pixels = int(np.prod(source.shape))
        if light_scale is None:
            light_scale = np.sqrt(sum((np.sum(np.square(block), axis=1) for block in _blocks(source)), np.zeros(n)) / max(pixels, 1))
        light_scale = _floored(light_scale, n)
        factor = 1.0 / light_scale
        if products is None:
            gram = np.zeros((n, n))
            for block in _blocks(source, light_scale):
                gram += block @ block.T  # BLAS's own threads
        else:
            total = products.cross_sum(n, n)
            for columns in _column_slices(n, pixels):
                total.add(_uploaded(products, source, columns))
            gram = total.value() * np.outer(factor, factor)
        values, vectors = np.linalg.eigh(gram)
        order = np.argsort(values)[::-1]
        order = order[values[order] > 1e-12 * max(float(values.max()), 1e-300)]
        energies = values[order]
        held = None
        if len(order) == 0:  # every image is black
            directions, energies = np.zeros((1, pixels), np.float32), np.zeros(1)
        else:
            projection = vectors[:, order].T / np.sqrt(energies)[:, None]
            if products is not None:
                held = products.held_directions(len(order), tuple(source.shape))
            directions = None
            if held is None:
                directions = spilled_empty((len(order), pixels), np.float32) if spill else mapped_empty((len(order), pixels), np.float32)
            if products is None:
                for columns, block in zip(_column_slices(n, pixels), _blocks(source, light_scale)):
                    directions[:, columns] = projection @ block
            else:
                scaled = projection * factor[None, :]
                for columns in _column_slices(n, pixels):
                    products.project(scaled, _uploaded(products, source, columns), out=None if held is not None else directions[:, columns], keep=held,
                                     columns=columns, host=held is None)
        first = (held.rows(0, 1)[0] if directions is None else directions[0]).astype(np.float64)
        rms = np.sqrt(max(float(np.trace(gram)), 0.0) / max(n * pixels, 1))  # of the normalised images
        mean = first * np.sign(first.sum() or 1.0) * rms * np.sqrt(pixels) / max(np.linalg.norm(first), 1e-300)
        return cls(source, tuple(source.shape), energies, directions, mean, products, held)

    @property
    def light_count(self) -> int:
        """n: the stack's images."""
        return self.source.light_count

    @property
    def values(self) -> int:
        """M = H W P: values an image."""
        return int(np.prod(self.shape))

    @property
    def count(self) -> int:
        """Directions held: the mean image and ``count - 1`` basis images."""
        return len(self.energies)

    def host_directions(self) -> np.ndarray:
        """(count, M) float32 ``directions`` on the host, copied down from ``held`` where they are only there."""
        return self.directions if self.directions is not None else self.held.rows(0, self.count)

    @cached_property
    def spans(self) -> np.ndarray:
        """(count - 1,) max - min of each basis image (direction 1 on), float32."""
        return self._extremes[1] - self._extremes[0]

    @property
    def lows(self) -> np.ndarray:
        """(count - 1,) min of each basis image (direction 1 on), float32."""
        return self._extremes[0]

    @property
    def highs(self) -> np.ndarray:
        """(count - 1,) max of each basis image (direction 1 on), float32."""
        return self._extremes[1]

    @cached_property
    def _extremes(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) of each basis image, float32, a few images a thread (found where ``held`` has them)."""
        if self.directions is None:
            return self.held.extremes(1)
        basis = self.directions[1:]
        if not len(basis):
            return np.zeros(0, np.float32), np.zeros(0, np.float32)
        lows, highs = np.empty(len(basis), basis.dtype), np.empty(len(basis), basis.dtype)

        def part(rows: slice) -> None:
            lows[rows], highs[rows] = basis[rows].min(axis=1), basis[rows].max(axis=1)

        parallel_map(part, [slice(start, min(start + 4, len(basis))) for start in range(0, len(basis), 4)])
        return lows, highs



def clamped_steps(steps: np.ndarray, span: np.ndarray, levels: int) -> np.ndarray:
    """float64 quantisation steps: each at least its image's ``span`` over the ``levels``, so that its codes fit."""
    return np.maximum(np.asarray(steps, dtype=np.float64), np.maximum(np.asarray(span, np.float64), 1e-300) / levels)


def quantisation_grid(lows: np.ndarray, highs: np.ndarray, steps: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, step) float64 of each basis image's codes: from its minimum, ``clamped_steps`` apart."""
    low = np.asarray(lows, np.float64)
    return low, clamped_steps(steps, np.asarray(highs, np.float64) - low, levels)


def quantise_basis(basis: np.ndarray | None, steps: np.ndarray, *, bits: int, lows: np.ndarray | None = None,
                   highs: np.ndarray | None = None, held: HeldDirections | None = None, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(k, M) basis images as ``bits``-bit codes with steps ``steps`` (each at least its span over the
    levels, so its codes fit), from each image's minimum: (codes (k, M) uint8 or uint16, ranges (k, 2)
    float32 (low, low + step x levels)), as ``LowRankStack`` stores them. ``lows``, ``highs``: the
    images' minima and maxima where known (else found here). ``held``: the same images held on a
    device from its image ``first`` on, quantised there (the same codes); ``basis`` may then be None
    (k = len(``steps``), the extremes given)."""
    levels = code_levels(bits)
    if basis is None:
        if held is None or lows is None or highs is None:
            raise InputError("quantise_basis needs the basis images, or their device copy and their extremes")
        basis = np.broadcast_to(np.zeros((), np.float32), (len(steps), held.values))  # the shape alone: the device makes the codes
    basis = np.asarray(basis)
    k = len(basis)
    lows = basis.min(axis=1) if lows is None and k else lows
    highs = basis.max(axis=1) if highs is None and k else highs
    if k and (np.shape(lows) != (k,) or np.shape(highs) != (k,)):
        raise InputError(f"quantise_basis needs one minimum and maximum per basis image ({k}), got {np.shape(lows)} and {np.shape(highs)}")
    low, steps = quantisation_grid(lows, highs, steps, levels) if k else (np.zeros(0), np.zeros(0))
    codes = mapped_empty(basis.shape, np.uint8 if bits == 8 else np.uint16)
    if held is not None and k:
        held.codes(first, low, steps, bits, out=codes)
        return codes, np.stack([low, low + steps * levels], axis=1).astype(np.float32)

    def part(columns: slice) -> None:  # float64 a block at a time, the blocks in threads
        codes[:, columns] = codes_in_place(basis[:, columns].astype(np.float64), low[:, None], steps[:, None], levels)

    parallel_map(part, _column_slices(k * NUMPY_THREADS, basis.shape[1]) if k else [])
    return codes, np.stack([low, low + steps * levels], axis=1).astype(np.float32)


_QUANTISE_CHUNK = 1 << 18
"""Values ``quantised_codes`` rounds in float64 at a time (2 MB: about a server core's L2 cache; on the
2-core CPU a 3840x2160 plane took 10-13 ms in chunks of 2^15-2^18 values, 35 ms whole)."""


def quantised_codes(values: np.ndarray, low: np.ndarray, step: np.ndarray, levels: int, *, out: np.ndarray) -> np.ndarray:
    """``codes_in_place`` of (k, ...) ``values`` (float32, any strides) with image j's ``low[j]`` and
    ``step[j]``, written into ``out`` (uint8 or uint16, the same shape): the same codes, rounded in
    float64 ``_QUANTISE_CHUNK`` values at a time (several small images a chunk, a large one in bands)."""
    buffer = np.empty(min(_QUANTISE_CHUNK, max(values.size, 1)), np.float64)
    low, step = np.asarray(low, np.float64), np.asarray(step, np.float64)
    for index in _chunks(values.shape, len(buffer)):
        part = values[index]
        chunk = buffer[: part.size].reshape(part.shape)
        np.copyto(chunk, part)
        images = index[0]
        if isinstance(images, slice):  # whole images: their ranges broadcast along the chunk's first axis
            shape = (-1,) + (1,) * (part.ndim - 1)
            codes_in_place(chunk, low[images].reshape(shape), step[images].reshape(shape), levels)
        else:
            codes_in_place(chunk, low[images], step[images], levels)
        np.copyto(out[index], chunk, casting="unsafe")
    return out


def _chunks(shape: tuple, limit: int):
    """Index tuples that cover an array of ``shape`` in pieces of at most ``limit`` values (whole rows of
    the trailing axes where they fit; one value at least)."""
    if not shape:
        yield ()
        return
    inner = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    if inner <= limit:
        size = max(1, limit // max(inner, 1))
        for start in range(0, shape[0], size):
            yield (slice(start, min(start + size, shape[0])),)
        return
    for first in range(shape[0]):
        for rest in _chunks(shape[1:], limit):
            yield (first, *rest)


def codes_in_place(values: np.ndarray, low: np.ndarray, step: np.ndarray, levels: int) -> np.ndarray:
    """round((values - low) / step) clipped to [0, levels], computed in ``values`` (float64, overwritten:
    no temporaries the size of the block) and returned as it (float64 codes). The one rounding of
    ``quantise_basis`` and of the rate search's sampled codes (``fit.residual.RateSample``)."""
    np.subtract(values, low, out=values)
    np.divide(values, step, out=values)
    np.round(values, out=values)
    return np.clip(values, 0, levels, out=values)


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
        deflated: the basis images' codes compressed as the field file stores them (``io.codes.CompressedCodes``,
            found by content), where the fit's rate search measured them; the field writer compresses
            what it does not find there. Not part of the model (never compared, never stored).
    """

    mean: np.ndarray
    codes: np.ndarray
    ranges: np.ndarray
    weights: np.ndarray
    mean_weights: np.ndarray | None = None
    deflated: DeflatedPieces | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        mean = finite_array(self.mean, np.float32, "residual mean")
        codes = np.ascontiguousarray(self.codes)
        if codes.dtype not in (np.uint8, np.uint16):
            raise InputError(f"residual basis codes must be uint8 or uint16, got {codes.dtype}")
        ranges = finite_array(self.ranges, np.float32, "residual basis ranges")
        weights = finite_array(self.weights, np.float32, "residual weights")
        if mean.ndim != 3 or codes.ndim != 4 or codes.shape[1:] != mean.shape:
            raise InputError(f"residual basis {codes.shape} does not match its mean image {mean.shape}: expected (k, H, W, P)")
        k = len(codes)
        if ranges.shape != (k, 2) or weights.ndim != 2 or weights.shape[1] != k:
            raise InputError(f"residual ranges {ranges.shape} and weights {weights.shape} must be ({k}, 2) and (n, {k})")
        mean_weights = np.ones(len(weights), np.float32) if self.mean_weights is None else finite_array(self.mean_weights, np.float32, "residual mean weights")
        if mean_weights.shape != (len(weights),):
            raise InputError(f"residual mean weights must have shape ({len(weights)},), got {mean_weights.shape}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "mean_weights", mean_weights)

    @classmethod
    def fit(cls, stack: np.ndarray, rank: int, *, light_scale: np.ndarray | None = None, bits: int = 8) -> LowRankStack:
        """A rank-``rank`` approximation of an (n, H, W, P) stack (a mean image and ``rank`` basis images
        of ``bits`` = 8 or 16 bits, each quantised over its whole range): ``quantised`` of the stack's
        ``PrincipalImages`` (normalised by ``light_scale``, default each image's RMS). A stack that spans
        fewer than ``rank + 1`` dimensions is kept up to that."""
        principal = PrincipalImages.of(stack, light_scale)
        rank = int(max(0, min(rank, principal.count - 1)))
        levels = code_levels(bits)
        return cls.quantised(principal, principal.spans[:rank] / levels, bits=bits)

    @classmethod
    def quantised(cls, principal: PrincipalImages, steps: np.ndarray, *, bits: int = 8, deflated: DeflatedPieces | None = None) -> LowRankStack:
        """The stack of ``principal``'s mean image (float16) and its first k = len(``steps``) further
        principal images, basis image j quantised with step ``steps[j]`` (in the units of a unit-norm
        image; at least its span over the ``bits``' levels, so its codes fit). Then every image's mean
        weight and basis weights are fitted to it by least squares against the stored planes, so
        quantisation only costs what they cannot represent. ``deflated``: kept as the stack's (see the
        class)."""
        k = len(steps)
        if k > principal.count - 1:
            raise InputError(f"{k} basis images asked of a stack of {principal.count - 1}")
        basis = None if principal.directions is None else principal.directions[1 : k + 1]
        codes, ranges = quantise_basis(basis, steps, bits=bits, lows=principal.lows[:k], highs=principal.highs[:k], held=principal.held, first=1)
        mean = principal.mean
        # the mean as the file keeps it: float16 unless a value is beyond its range
        mean32 = mean.astype(np.float16).astype(np.float32) if np.abs(mean).max(initial=0.0) < FLOAT16_SAFE else mean.astype(np.float32)
        shape = principal.shape
        n, pixels = principal.light_count, principal.values
        model = cls(mean32.reshape(shape), codes.reshape((k,) + shape), ranges, np.zeros((n, k), np.float32))
        # least squares by the (k + 1)-square normal equations (the planes are nearly orthogonal),
        # summed over blocks of the stored planes (float32 as the relighter decodes them)
        low, step = model.ranges[:, 0], (model.ranges[:, 1] - model.ranges[:, 0]) / np.float32(code_levels(bits))
        products = principal.products
        held = principal.held if products is not None else None
        if held is not None:  # the design's planes decoded where the images are held: no host pass, no upload
            quantised_low, quantised_step = quantisation_grid(principal.lows[:k], principal.highs[:k], steps, code_levels(bits))
        normal, right = np.zeros((k + 1, k + 1)), np.zeros((k + 1, n))
        normal_sum = right_sum = None
        if products is not None:  # float32 design and stack blocks, summed in float64 there: the same products
            normal_sum, right_sum = products.cross_sum(k + 1, k + 1), products.cross_sum(k + 1, n)
        for columns in _column_slices(max(k + 1, n), pixels):
            if held is not None:
                uploaded = held.design(1, quantised_low, quantised_step, bits, low, step, mean32[columns], columns)
                normal_sum.add(uploaded)
                right_sum.add(uploaded, _uploaded(products, principal.source, columns))
                continue
            shape = (k + 1, columns.stop - columns.start)
            design = np.empty(shape, np.float64) if products is None else products.staging(shape)  # there: filled where the upload reads it
            design[0] = mean32[columns]

            def planes(rows: slice, columns=columns, design=design) -> None:  # threads, a few basis images each, in float32 (as decoded)
                part = design[1:][rows]
                np.multiply(codes[rows, columns], step[rows, None], out=part, dtype=np.float32, casting="unsafe")
                np.add(part, low[rows, None], out=part, dtype=np.float32, casting="unsafe")

            parallel_map(planes, [slice(a, min(a + 8, k)) for a in range(0, k, 8)])
            if products is None:
                normal += design @ design.T  # BLAS's own threads
                right += design @ principal.source.block(columns).T
            else:
                uploaded = products.upload(design)
                normal_sum.add(uploaded)
                right_sum.add(uploaded, _uploaded(products, principal.source, columns))
        if products is not None:
            normal, right = normal_sum.value(), right_sum.value()
        normal[np.diag_indices_from(normal)] += max(1e-12 * float(np.trace(normal)), 1e-30)  # a black stack: weights 0
        solution = np.linalg.solve(normal, right)
        return cls(model.mean, model.codes, model.ranges, solution[1:].T.astype(np.float32), solution[0].astype(np.float32), deflated=deflated)

    @property
    def rank(self) -> int:
        return len(self.codes)

    @property
    def bits(self) -> int:
        """8 or 16: the basis codes' bits."""
        return 8 * self.codes.dtype.itemsize

    @property
    def basis(self) -> np.ndarray:
        """(k, H, W, P) float32 dequantised basis images."""
        return self.band_basis(slice(None))

    def band_basis(self, rows: slice) -> np.ndarray:
        """(k, rows, W, P) float32 dequantised basis images over a band of ``rows``."""
        low = self.ranges[:, 0].reshape(-1, 1, 1, 1)
        levels = np.float32(code_levels(self.bits))
        step = ((self.ranges[:, 1] - self.ranges[:, 0]) / levels).reshape(-1, 1, 1, 1)
        return (low + self.codes[:, rows].astype(np.float32) * step).astype(np.float32)

    def images(self, weights: np.ndarray, mean_weights=1.0) -> np.ndarray:
        """(Q, H, W, P) float64 images for (Q, k) weight rows and (Q,) mean weights (e.g. blended per-light ones)."""
        weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        flat = weights @ self.basis.reshape(self.rank, self.mean.size).astype(np.float64)
        mean_weights = np.broadcast_to(np.asarray(mean_weights, dtype=np.float64).reshape(-1), (len(weights),))
        return flat.reshape((len(weights),) + self.mean.shape) + mean_weights[:, None, None, None] * self.mean.astype(np.float64)

    def light_images(self, blend: np.ndarray) -> np.ndarray:
        """(Q, H, W, P) float64 images for (Q, n) per-light blend weights."""
        blend = np.atleast_2d(np.asarray(blend, dtype=np.float64))
        return self.images(blend @ self.weights.astype(np.float64), blend @ self.mean_weights.astype(np.float64))


_DECODE_BAND_VALUES = 1 << 20
"""Basis values (rows x width x rank) ``ResidualModel.decoded_blocks`` dequantises in a thread at a time (4 MB of float32)."""
_BLOCK_VALUES = 1 << 23
"""Values of a stack ``PrincipalImages`` and ``LowRankStack.quantised`` take into float64 at a time (64 MB)."""


def _column_slices(rows: int, columns: int) -> list[slice]:
    """Slices of ``columns`` so that ``rows`` x a slice holds about ``_BLOCK_VALUES`` values."""
    width = max(1, _BLOCK_VALUES // max(rows, 1))
    return [slice(start, min(start + width, columns)) for start in range(0, max(columns, 1), width)]


def _blocks(source: StackSource, light_scale: np.ndarray | None = None):
    """Column blocks of a stack as float64, each row divided by ``light_scale`` when given."""
    factor = None if light_scale is None else 1.0 / light_scale
    for columns in _column_slices(source.light_count, int(np.prod(source.shape))):
        block = source.block(columns)
        if factor is not None:
            _scale_rows(block, factor)
        yield block


def _block32(source: StackSource, columns: slice) -> np.ndarray:
    """A block of columns as float32 (the stack's values are float32: exact)."""
    block32 = getattr(source, "block32", None)
    return block32(columns) if block32 is not None else source.block(columns).astype(np.float32)


def _uploaded(products: StackProducts, source: StackSource, columns: slice):
    """A column block of the stack on the products' device: the source's own copy there where it holds
    one (``on_device``: ``kernels.stacks.HeldStack``), else its float32 block uploaded."""
    on_device = getattr(source, "on_device", None)
    return on_device(columns) if on_device is not None else products.upload(_block32(source, columns))


def spilled_empty(shape: tuple, dtype) -> np.ndarray:
    """An uninitialised array backed by a temporary file (``tempfile``'s folder) mapped into memory: the
    system writes its pages out and reads them back as memory runs short, instead of running out.
    The file has no name from the start (``TemporaryFile``), so nothing is left behind, whatever
    ends the process."""
    import tempfile

    with tempfile.TemporaryFile(prefix="warp-highlights-") as handle:  # the mapping keeps the file open
        return np.memmap(handle, dtype=dtype, mode="w+", shape=shape)


def _scale_rows(block: np.ndarray, factor: np.ndarray) -> None:
    """``block *= factor[:, None]`` in place, a few columns a thread."""

    def part(columns: slice) -> None:
        block[:, columns] *= factor[:, None]

    parallel_map(part, _column_parts(block.shape[1]))


def _as_float64(array: np.ndarray) -> np.ndarray:
    """(rows, width) ``array`` as float64, converted in threads a few columns each."""
    out = np.empty(array.shape, np.float64)

    def part(columns: slice) -> None:
        np.copyto(out[:, columns], array[:, columns], casting="unsafe")

    parallel_map(part, _column_parts(array.shape[1]))
    return out


def _column_parts(width: int) -> list[slice]:
    """``width`` columns in 4 parts a thread (elementwise work spread over ``parallel_map``'s threads)."""
    step = max(1, -(-width // (4 * NUMPY_THREADS)))
    return [slice(start, min(start + step, width)) for start in range(0, width, step)]


def _floored(light_scale, n: int) -> np.ndarray:
    """(n,) light scales floored above 0 (at ``_LIGHT_SCALE_FLOOR`` of the largest)."""
    light_scale = np.asarray(light_scale, dtype=np.float64).reshape(n)
    return np.maximum(light_scale, max(float(light_scale.max(initial=0.0)) * _LIGHT_SCALE_FLOOR, 1e-30))


NEURAL_CODE_SIZE = 9
"""Numbers per pixel of a learned residual (``kernels.neural.CODE_SIZE``)."""
NEURAL_LAYER_SHAPES = ((48, 12), (48, 1), (48, 48), (48, 1), (48, 48), (48, 1), (3, 48), (3, 1))
"""Shapes of a learned residual's weights w0, b0, ..., w3, b3 (``kernels.neural``)."""


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


@dataclass(frozen=True, eq=False)
class NeuralResidual:
    """A learned residual: R(x, w) = unit * decode_display(MLP(code(x), w)), field units, RGB.

    Attributes:
        codes: (H, W, 9) float16 per-pixel codes.
        weights: the MLP's eight float32 arrays (``NEURAL_LAYER_SHAPES``).
        unit: field units per display unit (the fit's exposure factor).
        light_count: lights it was trained on.
    """

    codes: np.ndarray
    weights: tuple
    unit: float
    light_count: int

    def __post_init__(self):
        codes = finite_array(self.codes, np.float16, "learned residual codes")
        if codes.ndim != 3 or codes.shape[2] != NEURAL_CODE_SIZE:
            raise InputError(f"learned residual codes must have shape (H, W, {NEURAL_CODE_SIZE}), got {codes.shape}")
        if len(self.weights) != len(NEURAL_LAYER_SHAPES):
            raise InputError(f"a learned residual has {len(NEURAL_LAYER_SHAPES)} weight arrays, got {len(self.weights)}")
        weights = tuple(finite_array(w, np.float32, "learned residual weights") for w in self.weights)
        for w, shape in zip(weights, NEURAL_LAYER_SHAPES):
            if w.shape != shape:
                raise InputError(f"learned residual weights must have shapes {list(NEURAL_LAYER_SHAPES)}, got {[x.shape for x in weights]}")
        if not (np.isfinite(self.unit) and self.unit > 0) or int(self.light_count) < 1:
            raise InputError(f"a learned residual needs a unit > 0 and at least one light, got {self.unit} and {self.light_count}")
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "unit", float(self.unit))
        object.__setattr__(self, "light_count", int(self.light_count))

    def images(self, directions) -> np.ndarray:
        """(Q, H, W, 3) float64 residuals at (Q, 3) unit directions (the float64 reference of the relighter's decode)."""
        w0, b0, w1, b1, w2, b2, w3, b3 = (w.astype(np.float64) for w in self.weights)
        height, width, _ = self.codes.shape
        codes = self.codes.reshape(-1, NEURAL_CODE_SIZE).astype(np.float64)
        elu = lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))
        out = []
        for direction in np.asarray(directions, dtype=np.float64).reshape(-1, 3):
            x = np.concatenate([codes, np.broadcast_to(direction, (len(codes), 3))], axis=1).T
            y = w3 @ elu(w2 @ elu(w1 @ elu(w0 @ x + b0) + b1) + b2) + b3
            out.append(self.unit * decode_display(y.T).reshape(height, width, 3))
        return np.stack(out)


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
        channels: C, 1 or 3.
    """

    images: np.ndarray | None = None
    luminance: LowRankStack | None = None
    chroma: LowRankStack | None = None
    highlight_colour: np.ndarray | None = None
    scale: np.ndarray | None = None
    learned: NeuralResidual | None = None

    def __post_init__(self):
        if sum(part is not None for part in (self.images, self.luminance, self.learned)) != 1:
            raise InputError("a residual model holds exactly one of: the residual images, a low-rank luminance stack, a learned residual")
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
                    raise InputError("the residual chroma stack must have 2 planes of the luminance's size and the same light count")
        if self.scale is not None:
            scale = finite_array(self.scale, np.float32, "residual scale")
            if self.images is not None or scale.shape != (self.height, self.width) or np.any(scale <= 0):
                raise InputError(f"a residual scale goes with low-rank stacks and must be ({self.height}, {self.width}) values > 0, got {scale.shape}")
            object.__setattr__(self, "scale", scale)
        if self.highlight_colour is not None:
            colour = finite_array(self.highlight_colour, np.float32, "highlight colour")
            if colour.shape != (self.height, self.width, self.channels) or np.any(colour < 0):
                raise InputError(f"highlight colour must be ({self.height}, {self.width}, {self.channels}) values >= 0, got {colour.shape}")
            object.__setattr__(self, "highlight_colour", colour)

    @property
    def compressed(self) -> bool:
        """True for a low-rank stack (not for uncompressed images, nor for a learned residual)."""
        return self.luminance is not None

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
            kind = f"learned ({NEURAL_CODE_SIZE} numbers per pixel and an MLP)"
        else:
            chroma = f" + chroma rank {self.chroma.rank}" if self.chroma is not None else ""
            kind = f"low rank: luminance rank {self.luminance.rank}{chroma} ({self.luminance.bits}-bit bases)"
        colour = "per-pixel" if self.highlight_colour is not None else "white"
        return f"residual: {kind}; highlight colour {colour}"

    def decoded_images(self, *, block: int = 16) -> np.ndarray:
        """(n, H, W, C) float16: every captured light's residual image R_i (the stored images when
        uncompressed; else decoded once, in float32, ``block`` lights at a time), for relighting by
        blending them as the alpha blend does (values beyond float16's range are clipped to it)."""
        if self.images is not None:
            return self.images
        if self.learned is not None:
            raise InputError("a learned residual is decoded per query direction, not per captured light")
        out = np.empty((self.light_count, self.height, self.width, self.channels), np.float16)
        for start, images in self.decoded_blocks(block=block):
            out[start : start + len(images)] = images
        return out

    def decoded_blocks(self, *, block: int = 16) -> Iterator[tuple[int, np.ndarray]]:
        """The residual images of ``decoded_images`` as (first light, (b, H, W, C) float16) for blocks of
        ``block`` lights in order: a consumer holds one block of the decoded stack at a time."""
        if self.learned is not None:
            raise InputError("a learned residual is decoded per query direction, not per captured light")
        n = self.light_count
        if self.images is not None:
            for start in range(0, n, block):
                yield start, self.images[start : start + block]
            return
        scale = np.ones((self.height, self.width), np.float32) if self.scale is None else self.scale
        stacks = [stack for stack in (self.luminance, self.chroma) if stack is not None]
        rows_a_band = max(1, _DECODE_BAND_VALUES // max(self.width * max(stack.rank for stack in stacks), 1))
        bands = [slice(top, min(top + rows_a_band, self.height)) for top in range(0, self.height, rows_a_band)]
        for start in range(0, n, block):
            stop = min(n, start + block)
            out = np.empty((stop - start, self.height, self.width, self.channels), np.float16)

            def band(rows: slice, start=start, stop=stop, out=out) -> None:  # the bands in threads: the basis dequantised a band at a time, never whole
                parts = []
                for stack in stacks:
                    basis = stack.band_basis(rows)
                    light = np.tensordot(stack.weights[start:stop], basis, axes=1)
                    light += stack.mean_weights[start:stop, None, None, None] * stack.mean[rows]
                    parts.append(light)
                y = parts[0][..., 0] * scale[rows]
                rgb = y[..., None] if len(parts) == 1 else from_opponent(y, parts[1] * scale[rows, :, None])
                out[:, rows] = np.clip(rgb, -FLOAT16_SAFE, FLOAT16_SAFE)

            parallel_map(band, bands)
            yield start, out

    def light_images(self, weights: np.ndarray) -> np.ndarray:
        """R~ for (Q, n) per-light blend weights: (Q, H, W, C) float64 (the float64 reference)."""
        weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        if self.learned is not None:
            raise InputError("a learned residual is decoded per query direction (learned.images), not blended from light weights")
        if self.images is not None:
            return np.einsum("qn,nhwc->qhwc", weights, self.images.astype(np.float64))
        scale = 1.0 if self.scale is None else self.scale.astype(np.float64)
        y = self.luminance.light_images(weights)[..., 0] * scale
        if self.chroma is None:
            return y[..., None]
        chroma = self.chroma.light_images(weights) * np.asarray(scale)[..., None]
        return from_opponent(y, chroma)
