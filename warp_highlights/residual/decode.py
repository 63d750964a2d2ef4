"""The residual decoded on the host, in float64 or float32: a low-rank stack's basis images and blends, every
captured light's residual image, the residual blended with per-light weights, and a learned residual at
query directions. The float64 functions are the references the relighter's kernels are tested against."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ..model.errors import InputError
from ..model.rbf import rbf_weights
from ..model.residual import (
    FLOAT16_SAFE,
    NEURAL_CODE_SIZE,
    LowRankStack,
    NeuralResidual,
    ResidualModel,
    code_levels,
)
from ..model.threads import blas_on_one_thread, parallel_map
from .opponent import decode_display, from_opponent

__all__ = ["band_basis", "decoded_blocks", "decoded_images", "decoded_lights", "learned_images", "light_images",
           "light_weights", "stack_basis", "stack_images", "stack_light_images"]

DECODE_BAND_VALUES = 1 << 20
"""Basis values (rows x width x rank) ``decoded_blocks`` dequantises in a thread at a time (4 MB of float32)."""


def band_basis(stack: LowRankStack, rows: slice) -> np.ndarray:
    """(k, rows, W, P) float32 dequantised basis images over a band of ``rows``."""
    low = stack.ranges[:, 0].reshape(-1, 1, 1, 1)
    levels = np.float32(code_levels(stack.bits))
    step = ((stack.ranges[:, 1] - stack.ranges[:, 0]) / levels).reshape(-1, 1, 1, 1)
    return (low + stack.codes[:, rows].astype(np.float32) * step).astype(np.float32)


def stack_basis(stack: LowRankStack) -> np.ndarray:
    """(k, H, W, P) float32 dequantised basis images."""
    return band_basis(stack, slice(None))


def stack_images(stack: LowRankStack, weights: np.ndarray, mean_weights=1.0) -> np.ndarray:
    """(Q, H, W, P) float64 images for (Q, k) weight rows and (Q,) mean weights (e.g. blended per-light ones)."""
    weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    flat = weights @ stack_basis(stack).reshape(stack.rank, stack.mean.size).astype(np.float64)
    mean_weights = np.broadcast_to(np.asarray(mean_weights, dtype=np.float64).reshape(-1), (len(weights),))
    return (flat.reshape((len(weights),) + stack.mean.shape)
            + mean_weights[:, None, None, None] * stack.mean.astype(np.float64))


def stack_light_images(stack: LowRankStack, blend: np.ndarray) -> np.ndarray:
    """(Q, H, W, P) float64 images for (Q, n) per-light blend weights."""
    blend = np.atleast_2d(np.asarray(blend, dtype=np.float64))
    return stack_images(stack, blend @ stack.weights.astype(np.float64), blend @ stack.mean_weights.astype(np.float64))


def decoded_images(residual: ResidualModel, *, block: int = 16) -> np.ndarray:
    """(n, H, W, C) float16: every captured light's residual image R_i (the stored images when
    uncompressed; else decoded once, in float32, ``block`` lights at a time), for relighting by
    blending them as the alpha blend does (values beyond float16's range are clipped to it)."""
    if residual.images is not None:
        return residual.images
    if residual.learned is not None:
        raise InputError("a learned residual is decoded per query direction, not per captured light")
    out = np.empty((residual.light_count, residual.height, residual.width, residual.channels), np.float16)
    for start, images in decoded_blocks(residual, block=block):
        out[start : start + len(images)] = images
    return out


def decoded_blocks(residual: ResidualModel, *, block: int = 16) -> Iterator[tuple[int, np.ndarray]]:
    """The residual images of ``decoded_images`` as (first light, (b, H, W, C) float16) for blocks of
    ``block`` lights in order: a consumer holds one block of the decoded stack at a time."""
    if residual.learned is not None:
        raise InputError("a learned residual is decoded per query direction, not per captured light")
    n = residual.light_count
    if residual.images is not None:
        for start in range(0, n, block):
            yield start, residual.images[start : start + block]
        return
    for start in range(0, n, block):
        yield start, decoded_lights(residual, np.arange(start, min(n, start + block)))


def decoded_lights(residual: ResidualModel, lights: np.ndarray) -> np.ndarray:
    """(b, H, W, C) float16: the residual images of the (b,) captured ``lights`` (a low-rank residual's decoded in
    float32 a band of rows at a time in threads, the basis dequantised a band at a time, never whole)."""
    lights = np.asarray(lights, dtype=np.int64)
    if residual.images is not None:
        return residual.images[lights]
    if residual.learned is not None:
        raise InputError("a learned residual is decoded per query direction, not per captured light")
    scale = np.ones((residual.height, residual.width), np.float32) if residual.scale is None else residual.scale
    stacks = [stack for stack in (residual.luminance, residual.chroma) if stack is not None]
    rows_a_band = max(1, DECODE_BAND_VALUES // max(residual.width * max(stack.rank for stack in stacks), 1))
    bands = [slice(top, min(top + rows_a_band, residual.height)) for top in range(0, residual.height, rows_a_band)]
    out = np.empty((len(lights), residual.height, residual.width, residual.channels), np.float16)

    def band(rows: slice) -> None:
        parts = []
        for stack in stacks:
            basis = band_basis(stack, rows)
            light = np.tensordot(stack.weights[lights], basis, axes=1)
            light += stack.mean_weights[lights, None, None, None] * stack.mean[rows]
            parts.append(light)
        y = parts[0][..., 0] * scale[rows]
        rgb = y[..., None] if len(parts) == 1 else from_opponent(y, parts[1] * scale[rows, :, None])
        out[:, rows] = np.clip(rgb, -FLOAT16_SAFE, FLOAT16_SAFE)

    with blas_on_one_thread():  # the bands' products round alike whatever the cores
        parallel_map(band, bands)
    return out


def light_weights(residual: ResidualModel, triangulation, directions) -> np.ndarray:
    """(Q, n) float64 weights of the captured lights with which relighting blends the ``residual`` at query
    ``directions`` (Q, 3) located on the field's ``triangulation`` (projected onto a dome's rim where outside):
    the query's barycentric weights on its triangle's corners, or for a radial basis residual
    (``ResidualModel.rbf_sigma``) phi(w)^T (K + lambda I)^-1 over every light (``model.rbf``)."""
    location = triangulation.locate(np.atleast_2d(np.asarray(directions, dtype=np.float64)))
    if residual.rbf_sigma is not None:
        return rbf_weights(location.directions, triangulation.directions, residual.rbf_sigma)
    weights = np.zeros((len(location.faces), len(triangulation.directions)))
    np.add.at(weights, (np.arange(len(location.faces))[:, None], location.vertices), location.barycentric)
    return weights


def light_images(residual: ResidualModel, weights: np.ndarray) -> np.ndarray:
    """R~ for (Q, n) per-light blend weights: (Q, H, W, C) float64 (the float64 reference)."""
    weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    if residual.learned is not None:
        raise InputError(
            "a learned residual is decoded per query direction (learned_images), not blended from light weights")
    if residual.images is not None:
        return np.einsum("qn,nhwc->qhwc", weights, residual.images.astype(np.float64))
    scale = 1.0 if residual.scale is None else residual.scale.astype(np.float64)
    y = stack_light_images(residual.luminance, weights)[..., 0] * scale
    if residual.chroma is None:
        return y[..., None]
    chroma = stack_light_images(residual.chroma, weights) * np.asarray(scale)[..., None]
    return from_opponent(y, chroma)


def learned_images(learned: NeuralResidual, directions, highlights: np.ndarray | None = None) -> np.ndarray:
    """(Q, H, W, 3) float64 residuals at (Q, 3) unit directions (the float64 reference of the relighter's decode),
    for a decoder of any shape, kept within the residual's bounds where it has them; ``highlights``: (Q, H, W) the
    Gaussians' luminance there (field units), for a decoder that sees them (its values are then the whole image)."""
    if (highlights is None) == learned.sees_highlights:
        raise InputError("a learned residual that sees the highlights decodes with them, and only such a one does")
    weights = [w.astype(np.float64) for w in learned.weights]
    height, width, _ = learned.codes.shape
    codes = learned.codes.reshape(-1, NEURAL_CODE_SIZE).astype(np.float64)
    elu = lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))
    out = []
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    for q, direction in enumerate(directions):
        columns = [codes, np.broadcast_to(direction, (len(codes), 3))]
        if highlights is not None:
            g = np.maximum(np.asarray(highlights[q], np.float64).reshape(-1) / learned.unit, 0.0)
            columns += [np.sqrt(g)[:, None], g[:, None]]
        h = np.concatenate(columns, axis=1).T
        for w, b in zip(weights[0:-2:2], weights[1:-2:2]):
            h = elu(w @ h + b)
        y = weights[-2] @ h + weights[-1]
        out.append(learned.unit * decode_display(y.T).reshape(height, width, 3))
    return learned.within_bounds(np.stack(out))
