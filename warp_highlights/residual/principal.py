"""Principal images of a residual stack (an uncentred PCA through the n x n Gram matrix), read a block of
columns at a time from a ``StackSource``; the products summed by the host's BLAS or on a device
(``StackProducts``, which ``kernels.gram`` implements).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from ..model.errors import InputError
from ..model.threads import NUMPY_THREADS, mapped_empty, parallel_map

__all__ = ["ArraySource", "HeldDirections", "PrincipalImages", "StackProducts", "StackSource", "column_slices",
           "spilled_empty", "uploaded_block"]


class StackSource(Protocol):
    """An (n, H, W, P) stack read a block of columns at a time, so that it need not be held whole
    (``residual.build`` computes the normalised residual's blocks from the images). A source held on the
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

    def project(self, matrix: np.ndarray, block: np.ndarray, out: np.ndarray | None = None, *, keep=None,
                columns: slice | None = None,
                host: bool = True) -> np.ndarray | None: ...

    def held_directions(self, count: int, shape: tuple) -> HeldDirections | None:
        """Room on the device for ``count`` principal images of ``shape`` (``project`` fills it through
        ``keep``, at ``columns``), or None where they would not fit."""


class HeldDirections(Protocol):
    """Principal images held on a device as well (``kernels.quantise.DeviceBasis``), quantised there with
    ``codes_in_place``'s rounding: ``codes`` of images first .. first + len(step) into a (c, M) host
    array; ``stored`` their codes as ``io.codes`` stores them, at ``rows`` (each less its row ``above``,
    -1: none), into a (c, P, [2,] R, W) uint8 host array; ``design`` a block of the weights' design
    matrix there (``quantise.quantised_stack``); ``rows`` a (count, M) float32 host copy, ``extremes``
    each image's float32 (min, max) from ``first`` on. ``values``: M."""

    values: int

    def rows(self, first: int, count: int) -> np.ndarray: ...

    def extremes(self, first: int) -> tuple[np.ndarray, np.ndarray]: ...

    def codes(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, out: np.ndarray) -> np.ndarray: ...

    def stored(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, rows: np.ndarray, above: np.ndarray,
               out: np.ndarray) -> np.ndarray: ...

    def design(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, decoded_low: np.ndarray,
               decoded_step: np.ndarray,
               mean: np.ndarray, columns: slice):
        """The weights' (1 + c, w) design block there: ``mean`` and the images' decoded codes at ``columns``."""


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
    (``residual.build.NormalisedResidual``) is never held whole on the host.

    Attributes:
        source: the stack.
        shape: (H, W, P).
        energies: (r,) float64 descending sums of squares of the normalised images along each direction
            (r <= n: the directions of non-zero energy; at least 1): what keeping it removes.
        directions: (r, M) float32 unit rows on the host; None where ``held`` has them
            (``host_directions`` copies them down).
        mean: (M,) float64 the first direction at the images' scale.
        products: where the stack's products were summed (None: the host's BLAS); ``quantise.quantised_stack``
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
            raise InputError("principal images need their directions on the host or held on a device "
                             "(host_directions() copies them down)")

    @classmethod
    def of(cls, stack: np.ndarray, light_scale: np.ndarray | None = None, *,
           products: StackProducts | None = None) -> PrincipalImages:
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
            light_scale = np.sqrt(sum((np.sum(np.square(block), axis=1) for block in _blocks(source)), np.zeros(n))
                                  / max(pixels, 1))
        light_scale = _floored(light_scale, n)
        factor = 1.0 / light_scale
        if products is None:
            gram = np.zeros((n, n))
            for block in _blocks(source, light_scale):
                gram += block @ block.T  # BLAS's own threads
        else:
            total = products.cross_sum(n, n)
            for columns in column_slices(n, pixels):
                total.add(uploaded_block(products, source, columns))
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
                directions = (spilled_empty((len(order), pixels), np.float32) if spill
                              else mapped_empty((len(order), pixels), np.float32))
            if products is None:
                for columns, block in zip(column_slices(n, pixels), _blocks(source, light_scale)):
                    directions[:, columns] = projection @ block
            else:
                scaled = projection * factor[None, :]
                for columns in column_slices(n, pixels):
                    products.project(scaled, uploaded_block(products, source, columns),
                                     out=None if held is not None else directions[:, columns], keep=held,
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


_LIGHT_SCALE_FLOOR = 1e-3  # of the brightest image's RMS: a black image is not divided by zero
_BLOCK_VALUES = 1 << 23
"""Values of a stack ``PrincipalImages`` and ``quantise.quantised_stack`` take into float64 at a time (64 MB)."""


def column_slices(rows: int, columns: int) -> list[slice]:
    """Slices of ``columns`` so that ``rows`` x a slice holds about ``_BLOCK_VALUES`` values."""
    width = max(1, _BLOCK_VALUES // max(rows, 1))
    return [slice(start, min(start + width, columns)) for start in range(0, max(columns, 1), width)]


def _blocks(source: StackSource, light_scale: np.ndarray | None = None):
    """Column blocks of a stack as float64, each row divided by ``light_scale`` when given."""
    factor = None if light_scale is None else 1.0 / light_scale
    for columns in column_slices(source.light_count, int(np.prod(source.shape))):
        block = source.block(columns)
        if factor is not None:
            _scale_rows(block, factor)
        yield block


def _block32(source: StackSource, columns: slice) -> np.ndarray:
    """A block of columns as float32 (the stack's values are float32: exact)."""
    block32 = getattr(source, "block32", None)
    return block32(columns) if block32 is not None else source.block(columns).astype(np.float32)


def uploaded_block(products: StackProducts, source: StackSource, columns: slice):
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
