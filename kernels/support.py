"""How much of each retargeted Gaussian the target image supports: the fit-time move decision's measure.

For Gaussian p of set b, drawn as the rasterizer draws it (truncated at the cut-off, weight 1) into
the image of light ``targets[b]``:

    support[b, p] = sum_x min(g_p(x), S(x)) / sum_x g_p(x)

in [0, 1]: 1 when the target's specular image holds at least the Gaussian everywhere it draws, 0
when the Gaussian landed on nothing. One thread per (set, slot) walks the Gaussian's pixel box.
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model.config import RasterSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch

from .raster import frame_distance2, prepare_gaussians

__all__ = ["gaussian_support", "support_fractions"]


@wp.kernel(enable_backward=False)
def gaussian_support(
    frames: wp.array2d(dtype=wp.vec4),
    means: wp.array2d(dtype=wp.vec2),
    scales: wp.array2d(dtype=float),
    boxes: wp.array2d(dtype=wp.vec4i),
    targets: wp.array(dtype=wp.int32),
    images: wp.array3d(dtype=float),
    cutoff2: float,
    tau: float,
    out: wp.array2d(dtype=float),
):
    """out[b, p] = sum min(g, S) / sum g over the Gaussian's footprint; -1 for a slot that draws nothing."""
    b, p = wp.tid()
    scale = scales[b, p]
    box = boxes[b, p]
    if scale <= 0.0 or box[2] < box[0] or box[3] < box[1]:
        out[b, p] = -1.0
        return
    frame = frames[b, p]
    mu = means[b, p]
    h = float(images.shape[1])
    t = targets[b]
    drawn = float(0.0)
    held = float(0.0)
    for row in range(box[1], box[3] + 1):
        y = (float(row) + 0.5) / h - mu[1]
        for col in range(box[0], box[2] + 1):
            x = (float(col) + 0.5) / h - mu[0]
            d2 = frame_distance2(frame, x, y)
            if d2 < cutoff2:
                g = scale * (wp.exp(-0.5 * d2) - tau)
                drawn += g
                held += wp.min(g, wp.max(images[t, row, col], 0.0))
    if drawn > 0.0:
        out[b, p] = held / drawn
    else:
        out[b, p] = -1.0


def support_fractions(batch: GaussianBatch, targets, images: wp.array, *,
                      settings: RasterSettings | None = None) -> np.ndarray:
    """(B, N) float64 support of every slot of ``batch`` in ``images[targets[b]]`` (-1: draws nothing).

    Args:
        batch: B Gaussian sets on the images' device (weights are ignored: each Gaussian counts whole).
        targets: (B,) index of each set's target image.
        images: (n, H, W) float32 Warp array, e.g. the segmentation's specular luminance.
        settings: the rasterizer's cut-off and covariance epsilon (``RasterSettings``).
    """
    s = settings or RasterSettings()
    device = images.device
    problems, capacity = batch.shape
    targets = np.asarray(targets, dtype=np.int32).reshape(-1)
    if len(targets) != problems or (problems and (targets.min() < 0 or targets.max() >= images.shape[0])):
        raise InputError(f"support needs one target image in 0..{images.shape[0] - 1} per set, got {len(targets)} for "
                         f"{problems} sets")
    height, width = images.shape[1], images.shape[2]
    tau = s.cutoff_level
    frames = wp.empty((problems, capacity), dtype=wp.vec4, device=device)
    scales = wp.empty((problems, capacity), dtype=float, device=device)
    boxes = wp.empty((problems, capacity), dtype=wp.vec4i, device=device)
    unit = GaussianBatch(problems, capacity, device=device, requires_grad=False)
    for name in ("amplitude", "mean", "sigma", "theta", "active"):
        wp.copy(getattr(unit, name), getattr(batch, name))
    wp.launch(prepare_gaussians, dim=(problems, capacity),
              inputs=[unit.arrays, s.sigma_eps, s.cutoff, 1.0 / (1.0 - tau), height, width],
              outputs=[frames, scales, boxes], device=device, record_tape=False)
    out = wp.empty((problems, capacity), dtype=float, device=device)
    wp.launch(gaussian_support, dim=(problems, capacity),
              inputs=[frames, unit.mean, scales, boxes, wp.array(targets, dtype=wp.int32, device=device), images,
                      s.cutoff**2, tau],
              outputs=[out], device=device)
    return out.numpy().astype(np.float64)
