"""The move check's scores on a device (``fit.validation.check_moving``): both predictions of each
left-out light and its own image shown in 8-bit sRGB, and their squared 8-bit errors summed.

For checked light q with corners v_k and weights w_k (k = 0..2), at pixel p and channel c:

- blend = (w_0 I_v0 + w_1 I_v1) + w_2 I_v2 (float32, the order NumPy sums them in);
- moved = blend + (D_q - sum_k w_k O_vk) t_c: the moved highlights D_q less the corners' own ones O,
  tinted by the highlight colour t;
- each of blend, moved and the truth I_j scaled by ``scale`` (display units) and shown as
  ``io.images.display_rgb8`` shows it: NaN black, +inf white, clipped to [0, 1], the sRGB curve,
  times 255 rounded half to even.

``errors[q, row]`` holds the sums over the row of (moved - truth)^2 and (blend - truth)^2 in 8-bit
codes (float64: sums of integers, exact). The device's ``pow`` and fused multiply-adds may round the
last bit of a value differently from NumPy's, which moves a code by one where a value sits on a code's
edge: the scores match the host's to a few thousandths of a dB (tests/test_scores.py).
"""

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = ["device_tint", "prediction_errors"]

# display_rgb8's float32 constants, each rounded from its double as NumPy casts a Python float
_LINEAR_END = wp.constant(wp.float32(0.0031308))
_GAMMA = wp.constant(wp.float32(1.0 / 2.4))


@wp.func
def _code(value: wp.float32) -> wp.float32:
    """A linear value in display units as its 8-bit sRGB code (0..255, as float)."""
    x = value
    if wp.isnan(x):
        x = wp.float32(0.0)
    x = wp.clamp(x, wp.float32(0.0), wp.float32(1.0))  # +inf -> 1
    encoded = x * wp.float32(12.92)
    if x > _LINEAR_END:
        encoded = wp.float32(1.055) * wp.pow(x, _GAMMA) - wp.float32(0.055)
    return wp.rint(encoded * wp.float32(255.0))


@wp.kernel
def _row_errors(images: wp.array2d(dtype=wp.float32), own: wp.array2d(dtype=wp.float32),
                drawn: wp.array2d(dtype=wp.float32),
                tint: wp.array2d(dtype=wp.float32), corners: wp.array2d(dtype=wp.int32),
                weights: wp.array2d(dtype=wp.float32),
                truth: wp.array(dtype=wp.int32), scale: wp.float32, width: int, errors: wp.array3d(dtype=wp.float64)):
    """Thread (q, row): the sums of squared 8-bit errors of light q's moved and blended predictions over the row."""
    q, row = wp.tid()
    channels = tint.shape[1]
    a, b, c = corners[q, 0], corners[q, 1], corners[q, 2]
    wa, wb, wc = weights[q, 0], weights[q, 1], weights[q, 2]
    j = truth[q]
    moved_sum = wp.float64(0.0)
    blend_sum = wp.float64(0.0)
    for x in range(width):
        p = row * width + x
        highlights = (wa * own[a, p] + wb * own[b, p]) + wc * own[c, p]
        move = drawn[q, p] - highlights
        for k in range(channels):
            i = p * channels + k
            blend = (wa * images[a, i] + wb * images[b, i]) + wc * images[c, i]
            moved = blend + move * tint[p, k]
            shown = _code(images[j, i] * scale)
            moved_error = wp.float64(_code(moved * scale) - shown)
            blend_error = wp.float64(_code(blend * scale) - shown)
            moved_sum += moved_error * moved_error
            blend_sum += blend_error * blend_error
    errors[q, row, 0] = moved_sum
    errors[q, row, 1] = blend_sum


def device_tint(tint: np.ndarray, height: int, width: int, device) -> wp.array:
    """(H W, C) float32 device array of the highlight colour ``tint`` (H, W, C) or (1, 1, C), broadcast to the image."""
    channels = int(np.shape(tint)[-1])
    rows = np.broadcast_to(np.asarray(tint, np.float32), (height, width, channels)).reshape(height * width, channels)
    return wp.array(np.ascontiguousarray(rows), dtype=wp.float32, device=device)


def prediction_errors(images: wp.array, own: wp.array, drawn: wp.array, tint: np.ndarray, corners: np.ndarray,
                      weights: np.ndarray,
                      truth: np.ndarray, *, scale: float, height: int, width: int) -> np.ndarray:
    """(m, 2) float64 sums of squared 8-bit errors of the moved and the blended predictions of m left-out lights.

    Args:
        images: (k, H W C) float32 device array of the images the lights need (field units);
        own: (k, H W) their own highlights; drawn: (m, H W) each light's moved highlights.
        tint: (H, W, C) or (1, 1, C) the highlight colour (broadcast to the image), or ``device_tint`` of it.
        corners: (m, 3) rows of ``images`` / ``own`` blended for each light, ``weights`` (m, 3) theirs.
        truth: (m,) each light's own row of ``images``.
        scale: display units per field unit (1 / the fit's exposure factor).
    """
    device = images.device
    m = len(corners)
    tint_rows = tint if isinstance(tint, wp.array) else device_tint(tint, height, width, device)
    errors = wp.empty((m, height, 2), dtype=wp.float64, device=device)
    wp.launch(_row_errors, dim=(m, height), device=device,
              inputs=[images, own, drawn, tint_rows,
                      wp.array(np.asarray(corners, np.int32), dtype=wp.int32, device=device),
                      wp.array(np.asarray(weights, np.float32), dtype=wp.float32, device=device),
                      wp.array(np.asarray(truth, np.int32), dtype=wp.int32, device=device), wp.float32(scale), width],
              outputs=[errors])
    return errors.numpy().sum(axis=1)
