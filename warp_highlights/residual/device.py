"""A low-rank residual on a Warp device: its stacks uploaded for the relighter's per-query decode (with a radial
basis residual's rows), or every captured light's image decoded there once; and the rule that decides between
the two."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..io.resample import resample_image
from ..kernels import interpolation as kernels
from ..model.errors import InputError
from ..model.memory import device_free_memory
from ..model.rbf import rbf_system
from ..model.residual import LowRankStack, ResidualModel, code_levels
from .decode import stack_basis

__all__ = ["DECODED_RESIDUAL_BYTES", "DECODED_RESIDUAL_SHARE", "RESIDUAL_DECODES", "LowRankArrays", "RbfRows",
           "decode_on_load", "decode_residual", "decodes_on_device", "rbf_rows"]

RESIDUAL_DECODES = ("auto", "query", "load")
"""How a ``Relighter`` decodes a low-rank residual (its ``residual_decode`` argument)."""
DECODED_RESIDUAL_SHARE = 0.25
"""Share of the free device memory that "auto" gives a low-rank residual decoded once into float16 images
on CUDA: 250 lights of 1920x1080 RGB take 3.1 GB of an 80 GB card, and a query then blends three images
instead of reading every basis image, far less work at 1080p."""
DECODED_RESIDUAL_BYTES = 512 * 2**20
"""Most memory "auto" gives the decoded residual on the CPU (and on CUDA where the free memory is
unknown): 250 lights of 480x270 RGB take 194 MB. The decoding is host matrix work, slow on a few
cores, which a single query would wait for; a larger field is decoded per query instead."""
# of the free device memory that decoding on the device may hold at once (basis, codes, images)
DEVICE_DECODE_SHARE = 0.75


def decode_on_load(residual: ResidualModel, output_pixels: int, decode: str, device) -> bool:
    """Whether a low-rank ``residual`` is decoded once into images (see ``Relighter``'s ``residual_decode``):
    for "auto", where its float16 images fit ``DECODED_RESIDUAL_SHARE`` of the free memory of a CUDA
    ``device`` (else ``DECODED_RESIDUAL_BYTES``) and blending three of them reads less than the basis."""
    if residual.rbf_sigma is not None:
        if decode == "load":
            raise InputError("this field's residual weighs every captured light (radial basis), which images decoded "
                             "once per light cannot serve; relight it with residual_decode 'query' or 'auto'")
        return False
    if decode != "auto":
        return decode == "load"
    held = residual.light_count * output_pixels * residual.channels * 2
    per_query = residual.luminance.rank + 1 + (0 if residual.chroma is None else 2 * (residual.chroma.rank + 1))
    free = device_free_memory(device) if device.is_cuda else None
    budget = DECODED_RESIDUAL_SHARE * free if free is not None else DECODED_RESIDUAL_BYTES
    return held <= budget and per_query > 3 * residual.channels


@dataclass(frozen=True)
class LowRankArrays:
    """A ``LowRankStack`` on the device at the output size: mean (P, planes), basis (P, max(k, 1), planes),
    pixel-major, weights (n, k + 1): each light's basis weights, then its mean weight."""

    mean: wp.array
    basis: wp.array
    weights: wp.array
    rank: int
    uploaded: bool = True

    @classmethod
    def empty(cls, device, planes: int) -> LowRankArrays:
        return cls(wp.zeros((1, planes), dtype=float, device=device),
                   wp.zeros((1, 1, planes), dtype=float, device=device),
                   wp.zeros((1, 1), dtype=float, device=device), 0, uploaded=False)

    @classmethod
    def upload(cls, stack: LowRankStack, width: int, height: int, device) -> LowRankArrays:
        """The stack at ``width`` x ``height``: at its own size its codes go to the device and are dequantised
        there (``dequantise_basis``: half the bytes of the float32 basis, no host pass over it), else
        the dequantised basis is resampled on the host."""
        planes = stack.mean.shape[2]
        mean = resample_image(stack.mean, width, height).reshape(height * width, planes)
        weights = np.concatenate([stack.weights, stack.mean_weights[:, None]], axis=1)
        array = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=float, device=device)
        if stack.rank and stack.mean.shape[:2] == (height, width):
            codes = wp.array(stack.codes.reshape(stack.rank, height * width, planes),
                             dtype=wp.uint16 if stack.bits == 16 else wp.uint8, device=device)
            low = stack.ranges[:, 0]
            # float32, as decode.stack_basis
            step = (stack.ranges[:, 1] - stack.ranges[:, 0]) / np.float32(code_levels(stack.bits))
            basis = wp.empty((height * width, stack.rank, planes), dtype=float, device=device)
            wp.launch(kernels.dequantise_basis, dim=(stack.rank, height * width),
                      inputs=[codes, array(low), array(step)], outputs=[basis], device=device)
            return cls(array(mean), basis, array(weights), stack.rank)
        if stack.rank:
            basis = np.stack([resample_image(image, width, height)
                              for image in stack_basis(stack)]).reshape(stack.rank, height * width, planes)
            basis = basis.transpose(1, 0, 2)  # pixel-major: a pixel's k values are contiguous
        else:
            basis = np.zeros((height * width, 1, planes), np.float32)
        return cls(array(mean), array(basis), array(weights), stack.rank)


@dataclass(frozen=True)
class RbfRows:
    """A radial basis residual on the device (``kernels.interpolation.blend_rbf``): each stack's per-light rows
    (n, k + 1) float64 multiplied by (K + lambda I)^-1 (``model.rbf``), the lights (n,) vec3d and 1 / sigma^2."""

    rows: dict
    lights: wp.array
    inverse_sigma_squared: float


def rbf_rows(residual: ResidualModel, lights: np.ndarray, device) -> RbfRows:
    """``RbfRows`` of a low-rank ``residual`` with ``rbf_sigma`` at its unit ``lights`` (n, 3), solved in float64 on
    the host: the large, cancelling values of a badly conditioned K stay in float64 (the kernel sums in it)."""
    lights = np.asarray(lights, dtype=np.float64)
    system = rbf_system(lights, residual.rbf_sigma)
    rows = {}
    for name, stack in (("luminance", residual.luminance), ("chroma", residual.chroma)):
        if stack is not None:
            per_light = np.concatenate([stack.weights, stack.mean_weights[:, None]], axis=1).astype(np.float64)
            rows[name] = wp.array(np.linalg.solve(system, per_light), dtype=wp.float64, device=device)
    return RbfRows(rows, wp.array(lights, dtype=wp.vec3d, device=device), 1.0 / residual.rbf_sigma ** 2)


def decode_residual(residual: ResidualModel, device) -> wp.array:
    """Every captured light's image of a low-rank ``residual`` at its own size, decoded on a Warp
    ``device`` (``decode_low_rank``): (n, H W, C) float16, what ``decode.decoded_images`` gives
    (to float32 rounding). The basis is held on the device meanwhile (``decodes_on_device``)."""
    pixels = residual.height * residual.width
    lum = LowRankArrays.upload(residual.luminance, residual.width, residual.height, device)
    chroma = (LowRankArrays.empty(device, 2) if residual.chroma is None
              else LowRankArrays.upload(residual.chroma, residual.width, residual.height, device))
    scale = np.ones(1, np.float32) if residual.scale is None else residual.scale.reshape(-1)
    out = wp.empty((residual.light_count, pixels, residual.channels), dtype=wp.float16, device=device)
    wp.launch(kernels.decode_low_rank, dim=(residual.light_count, pixels),
              inputs=[lum.mean, lum.basis, lum.weights, chroma.mean, chroma.basis, chroma.weights,
                      wp.array(np.ascontiguousarray(scale, np.float32), dtype=float, device=device)], outputs=[out],
              device=device)
    return out


def decodes_on_device(residual: ResidualModel, width: int, height: int, device) -> bool:
    """Whether ``decode_residual`` serves a ``Relighter`` at ``width`` x ``height``: the residual's own size,
    and its float32 basis, codes and decoded images within ``DEVICE_DECODE_SHARE`` of the free memory."""
    if residual.luminance is None or (residual.height, residual.width) != (height, width):
        return False
    pixels = height * width
    stacks = [stack for stack in (residual.luminance, residual.chroma) if stack is not None]
    basis = sum(4 * pixels * max(stack.rank, 1) * stack.mean.shape[2] for stack in stacks)
    codes = max(stack.codes.nbytes for stack in stacks)
    images = 2 * residual.light_count * pixels * residual.channels
    free = device_free_memory(device)
    return free is not None and basis + codes + images <= DEVICE_DECODE_SHARE * free
