"""Basis images quantised to 8- or 16-bit codes, and a low-rank stack made from principal images: the
basis quantised, then every light's weights fitted by least squares against the stored planes.
"""

from __future__ import annotations

import numpy as np

from ..model.errors import InputError
from ..model.residual import FLOAT16_SAFE, CompressedChunks, LowRankStack, code_levels
from ..model.threads import NUMPY_THREADS, mapped_empty, parallel_map
from .principal import HeldDirections, PrincipalImages, column_slices, uploaded_block

__all__ = ["clamped_steps", "codes_in_place", "fit_stack", "quantisation_grid", "quantise_basis", "quantised_codes",
           "quantised_stack"]


def clamped_steps(steps: np.ndarray, span: np.ndarray, levels: int) -> np.ndarray:
    """float64 quantisation steps: each at least its image's ``span`` over the ``levels``, so that its codes fit."""
    return np.maximum(np.asarray(steps, dtype=np.float64), np.maximum(np.asarray(span, np.float64), 1e-300) / levels)


def quantisation_grid(lows: np.ndarray, highs: np.ndarray, steps: np.ndarray,
                      levels: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, step) float64 of each basis image's codes: from its minimum, ``clamped_steps`` apart."""
    low = np.asarray(lows, np.float64)
    return low, clamped_steps(steps, np.asarray(highs, np.float64) - low, levels)


def quantise_basis(basis: np.ndarray | None, steps: np.ndarray, *, bits: int, lows: np.ndarray | None = None,
                   highs: np.ndarray | None = None, held: HeldDirections | None = None,
                   first: int = 0) -> tuple[np.ndarray, np.ndarray]:
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
        # the shape alone: the device makes the codes
        basis = np.broadcast_to(np.zeros((), np.float32), (len(steps), held.values))
    basis = np.asarray(basis)
    k = len(basis)
    lows = basis.min(axis=1) if lows is None and k else lows
    highs = basis.max(axis=1) if highs is None and k else highs
    if k and (np.shape(lows) != (k,) or np.shape(highs) != (k,)):
        raise InputError(f"quantise_basis needs one minimum and maximum per basis image ({k}), got {np.shape(lows)} "
                         f"and {np.shape(highs)}")
    low, steps = quantisation_grid(lows, highs, steps, levels) if k else (np.zeros(0), np.zeros(0))
    codes = mapped_empty(basis.shape, np.uint8 if bits == 8 else np.uint16)
    if held is not None and k:
        held.codes(first, low, steps, bits, out=codes)
        return codes, np.stack([low, low + steps * levels], axis=1).astype(np.float32)

    def part(columns: slice) -> None:  # float64 a block at a time, the blocks in threads
        codes[:, columns] = codes_in_place(basis[:, columns].astype(np.float64), low[:, None], steps[:, None], levels)

    parallel_map(part, column_slices(k * NUMPY_THREADS, basis.shape[1]) if k else [])
    return codes, np.stack([low, low + steps * levels], axis=1).astype(np.float32)


_QUANTISE_CHUNK = 1 << 18
"""Values ``quantised_codes`` rounds in float64 at a time (2 MB: about a server core's L2 cache; on the
2-core CPU a 3840x2160 plane took 10-13 ms in chunks of 2^15-2^18 values, 35 ms whole)."""


def quantised_codes(values: np.ndarray, low: np.ndarray, step: np.ndarray, levels: int, *,
                    out: np.ndarray) -> np.ndarray:
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
    """Index tuples that cover an array of ``shape`` in chunks of at most ``limit`` values (whole rows of
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
    ``quantise_basis`` and of the rate search's sampled codes (``residual.rate.RateSample``)."""
    np.subtract(values, low, out=values)
    np.divide(values, step, out=values)
    np.round(values, out=values)
    return np.clip(values, 0, levels, out=values)


def fit_stack(stack: np.ndarray, rank: int, *, light_scale: np.ndarray | None = None, bits: int = 8) -> LowRankStack:
    """A rank-``rank`` approximation of an (n, H, W, P) stack (a mean image and ``rank`` basis images
    of ``bits`` = 8 or 16 bits, each quantised over its whole range): ``quantised_stack`` of the stack's
    ``PrincipalImages`` (normalised by ``light_scale``, default each image's RMS). A stack that spans
    fewer than ``rank + 1`` dimensions is kept up to that."""
    principal = PrincipalImages.of(stack, light_scale)
    rank = int(max(0, min(rank, principal.count - 1)))
    levels = code_levels(bits)
    return quantised_stack(principal, principal.spans[:rank] / levels, bits=bits)


def quantised_stack(principal: PrincipalImages, steps: np.ndarray, *, bits: int = 8,
                    chunks: CompressedChunks | None = None) -> LowRankStack:
    """The stack of ``principal``'s mean image (float16) and its first k = len(``steps``) further
    principal images, basis image j quantised with step ``steps[j]`` (in the units of a unit-norm
    image; at least its span over the ``bits``' levels, so its codes fit). Then every image's mean
    weight and basis weights are fitted to it by least squares against the stored planes, so
    quantisation only costs what they cannot represent. ``chunks``: kept as the stack's (see the
    class)."""
    k = len(steps)
    if k > principal.count - 1:
        raise InputError(f"{k} basis images asked of a stack of {principal.count - 1}")
    basis = None if principal.directions is None else principal.directions[1 : k + 1]
    codes, ranges = quantise_basis(basis, steps, bits=bits, lows=principal.lows[:k], highs=principal.highs[:k],
                                   held=principal.held, first=1)
    mean = principal.mean
    # the mean as the file keeps it: float16 unless a value is beyond its range
    mean32 = (mean.astype(np.float16).astype(np.float32) if np.abs(mean).max(initial=0.0) < FLOAT16_SAFE
              else mean.astype(np.float32))
    shape = principal.shape
    n, pixels = principal.light_count, principal.values
    model = LowRankStack(mean32.reshape(shape), codes.reshape((k,) + shape), ranges, np.zeros((n, k), np.float32))
    # least squares by the (k + 1)-square normal equations (the planes are nearly orthogonal),
    # summed over blocks of the stored planes (float32 as the relighter decodes them)
    low, step = model.ranges[:, 0], (model.ranges[:, 1] - model.ranges[:, 0]) / np.float32(code_levels(bits))
    products = principal.products
    held = principal.held if products is not None else None
    if held is not None:  # the design's planes decoded where the images are held: no host pass, no upload
        quantised_low, quantised_step = quantisation_grid(principal.lows[:k], principal.highs[:k], steps,
                                                          code_levels(bits))
    normal, right = np.zeros((k + 1, k + 1)), np.zeros((k + 1, n))
    normal_sum = right_sum = None
    if products is not None:  # float32 design and stack blocks, summed in float64 there: the same products
        normal_sum, right_sum = products.cross_sum(k + 1, k + 1), products.cross_sum(k + 1, n)
    for columns in column_slices(max(k + 1, n), pixels):
        if held is not None:
            uploaded = held.design(1, quantised_low, quantised_step, bits, low, step, mean32[columns], columns)
            normal_sum.add(uploaded)
            right_sum.add(uploaded, uploaded_block(products, principal.source, columns))
            continue
        shape = (k + 1, columns.stop - columns.start)
        # there: filled where the upload reads it
        design = np.empty(shape, np.float64) if products is None else products.staging(shape)
        design[0] = mean32[columns]

        # threads, a few basis images each, in float32 (as decoded)
        def planes(rows: slice, columns=columns, design=design) -> None:
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
            right_sum.add(uploaded, uploaded_block(products, principal.source, columns))
    if products is not None:
        normal, right = normal_sum.value(), right_sum.value()
    normal[np.diag_indices_from(normal)] += max(1e-12 * float(np.trace(normal)), 1e-30)  # a black stack: weights 0
    solution = np.linalg.solve(normal, right)
    return LowRankStack(model.mean, model.codes, model.ranges, solution[1:].T.astype(np.float32),
                        solution[0].astype(np.float32), chunks=chunks)
