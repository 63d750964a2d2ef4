"""Kernels of the RTI baselines (PTM, HSH, RBF): two per-pixel linear maps, one launch each.

Every baseline is linear in the image values, so fitting and relighting are matrix products over the
flattened stack (pixel x channel columns, ``H * W * C`` of them):

1. ``project_planes`` (plane x column): coefficients[m, p] = sum_i matrix[m, i] images[i, p], the fit
   by a matrix shared by every pixel (a least-squares pseudo-inverse, computed on the host in float64).
2. ``evaluate_planes`` (query x column): out[q, p] = max(sum_m basis[q, m] planes[m, p], 0), the relit
   images of Q queries from their basis values, never negative and always finite.

Both sum in float64 and store float32. ``project`` and ``evaluate`` are their launch wrappers. Neither
is differentiated: the baselines are solved in closed form.
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0))

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = ["FLOAT32_MAX", "evaluate", "evaluate_planes", "project", "project_planes"]

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest relit value ``evaluate_planes`` stores; a larger (or NaN) sum becomes this (or 0)."""


@wp.kernel(enable_backward=False)
def project_planes(matrix: wp.array2d(dtype=float), images: wp.array2d(dtype=float), out: wp.array2d(dtype=float)):
    """out[m, p] = sum_i matrix[m, i] images[i, p] over the n images (float64 sum), for plane m and column p."""
    m, p = wp.tid()
    total = wp.float64(0.0)
    for i in range(images.shape[0]):
        total += wp.float64(matrix[m, i]) * wp.float64(images[i, p])
    out[m, p] = float(total)


@wp.kernel(enable_backward=False)
def evaluate_planes(basis: wp.array2d(dtype=float), planes: wp.array2d(dtype=float), largest: wp.float64,
                    out: wp.array2d(dtype=float)):
    """out[q, p] = sum_m basis[q, m] planes[m, p] (float64 sum), clamped to [0, largest]; NaN gives 0."""
    q, p = wp.tid()
    total = wp.float64(0.0)
    for m in range(planes.shape[0]):
        total += wp.float64(basis[q, m]) * wp.float64(planes[m, p])
    if not (total >= wp.float64(0.0)):  # negative or NaN
        total = wp.float64(0.0)
    out[q, p] = float(wp.min(total, largest))


def project(matrix: wp.array2d, images: wp.array2d, out: wp.array2d | None = None) -> wp.array2d:
    """(M, n) matrix times (n, P) images -> (M, P) coefficient planes, one launch on the images' device."""
    if matrix.shape[1] != images.shape[0]:
        raise ValueError(f"matrix {matrix.shape} does not multiply images {images.shape}")
    device = images.device
    if out is None:
        out = wp.empty((matrix.shape[0], images.shape[1]), dtype=float, device=device)
    wp.launch(project_planes, dim=out.shape, inputs=[matrix, images], outputs=[out], device=device)
    return out


def evaluate(basis: wp.array2d, planes: wp.array2d, out: wp.array2d | None = None) -> wp.array2d:
    """(Q, M) basis values times (M, P) planes, clamped to [0, FLOAT32_MAX] -> (Q, P), one launch on the planes'
    device."""
    if basis.shape[1] != planes.shape[0]:
        raise ValueError(f"basis {basis.shape} does not multiply planes {planes.shape}")
    device = planes.device
    if out is None:
        out = wp.empty((basis.shape[0], planes.shape[1]), dtype=float, device=device)
    wp.launch(evaluate_planes, dim=out.shape, inputs=[basis, planes, FLOAT32_MAX], outputs=[out], device=device)
    return out
