"""The residual's basis images held and quantised on a Warp device: the codes of ``residual.quantise``'s
rounding (``codes_in_place``: ``round((v - low) / step)`` in float64, halves to even, clipped to
[0, L]) and their stored form (``io.codes``: each row less the row above, modulo 2^bits, zigzag-mapped,
16-bit values as two byte planes, high bytes first), made where ``DeviceProducts.project`` made the
principal images. The host keeps no copy of those: their extremes (``extremes``) and the mean image
(``rows``) come down, and the codes; nothing else.

The arithmetic is the host's (a float32 value is exact in float64, the subtraction and the division
are IEEE float64 on both, ``rint`` rounds halves to even as ``np.round`` does), so the codes are the
host's bit for bit (``tests/test_quantise.py``). A 4K capture's rate search quantises hundreds of basis
planes, billions of values, several times: here each time is a launch, and the host only compresses.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .rows import DeviceRows

__all__ = ["LAUNCH_BYTES", "DeviceBasis", "basis_codes8", "basis_codes16", "decoded_rows", "row_extremes",
           "stored_rows"]

wp.set_module_options({"enable_backward": False})

LAUNCH_BYTES = 1 << 28
"""The most bytes of codes one launch makes on the device before they are copied down (256 MiB: a
few 3840x2160 basis images; the device's headroom beside the held stacks and images stays small)."""


@wp.func
def _code(value: wp.float32, low: wp.float64, step: wp.float64, levels: wp.float64) -> wp.int32:
    """The code of ``value``: round((value - low) / step) in float64, halves to even, clipped to [0, levels]."""
    return wp.int32(wp.clamp(wp.rint((wp.float64(value) - low) / step), wp.float64(0.0), levels))


@wp.kernel
def stored_rows(basis: wp.array2d(dtype=wp.float32), width: int, planes: int, rows: wp.array(dtype=wp.int32),
                above: wp.array(dtype=wp.int32), low: wp.array(dtype=wp.float64), step: wp.array(dtype=wp.float64),
                levels: wp.float64, wide: int, out: wp.array(dtype=wp.uint8)):
    """Thread (j, p, r, x): image j's plane p at row ``rows[r]``, column x, stored as the file stores it:
    its code less the code at row ``above[r]`` (-1: none), modulo 2^bits, zigzag-mapped (the signed
    difference d as 2d, or -2d - 1 below 0); ``out`` is (images, P, R, W), or (images, P, 2, R, W)
    with the high bytes first where ``wide`` (16 bits)."""
    j, p, r, x = wp.tid()
    count = rows.shape[0]
    value = _code(basis[j, (rows[r] * width + x) * planes + p], low[j], step[j], levels)
    if above[r] >= 0:
        value = value - _code(basis[j, (above[r] * width + x) * planes + p], low[j], step[j], levels)
    modulus = 256
    if wide != 0:
        modulus = 65536
    difference = (value + modulus) % modulus  # modulo 2^bits, then read as a signed difference
    if difference >= modulus / 2:
        difference = difference - modulus
    zigzag = 2 * difference
    if difference < 0:
        zigzag = -2 * difference - 1
    if wide != 0:
        at = ((j * planes + p) * 2 * count + r) * width + x
        out[at] = wp.uint8(zigzag / 256)
        out[at + count * width] = wp.uint8(zigzag % 256)
    else:
        out[((j * planes + p) * count + r) * width + x] = wp.uint8(zigzag)


@wp.kernel
def basis_codes8(basis: wp.array2d(dtype=wp.float32), low: wp.array(dtype=wp.float64), step: wp.array(dtype=wp.float64),
                 levels: wp.float64, out: wp.array2d(dtype=wp.uint8)):
    """out[j, m]: the 8-bit code of basis[j, m]."""
    j, m = wp.tid()
    out[j, m] = wp.uint8(_code(basis[j, m], low[j], step[j], levels))


@wp.kernel
def basis_codes16(basis: wp.array2d(dtype=wp.float32), low: wp.array(dtype=wp.float64),
                  step: wp.array(dtype=wp.float64),
                  levels: wp.float64, out: wp.array2d(dtype=wp.uint16)):
    """out[j, m]: the 16-bit code of basis[j, m]."""
    j, m = wp.tid()
    out[j, m] = wp.uint16(_code(basis[j, m], low[j], step[j], levels))


@wp.kernel
def decoded_rows(basis: wp.array2d(dtype=wp.float32), low: wp.array(dtype=wp.float64), step: wp.array(dtype=wp.float64),
                 levels: wp.float64,
                 decoded_low: wp.array(dtype=wp.float32), decoded_step: wp.array(dtype=wp.float32), column: int,
                 row: int,
                 out: wp.array2d(dtype=wp.float32)):
    """out[row + j, x]: basis[j, column + x] quantised and decoded as the relighter decodes it,
    ``decoded_low[j] + code * decoded_step[j]`` in float32."""
    j, x = wp.tid()
    code = _code(basis[j, column + x], low[j], step[j], levels)
    out[row + j, x] = decoded_low[j] + wp.float32(code) * decoded_step[j]


@wp.kernel
def row_extremes(part: wp.array2d(dtype=wp.float32), lanes: int, first_row: int, lows: wp.array(dtype=wp.float32),
                 highs: wp.array(dtype=wp.float32)):
    """lows[first_row + i], highs[first_row + i]: min and max of the part's row i, ``lanes`` threads a row
    striding over its values (min and max are exact in any order)."""
    i, lane = wp.tid()
    low = part[i, lane % part.shape[1]]
    high = low
    x = lane + lanes
    while x < part.shape[1]:
        value = part[i, x]
        low = wp.min(low, value)
        high = wp.max(high, value)
        x += lanes
    wp.atomic_min(lows, first_row + i, low)
    wp.atomic_max(highs, first_row + i, high)


# threads a row in ``row_extremes``: coalesced reads, few enough atomics (chosen, not swept: the extremes of the
# 1,254 principal images of a 1,000 x 1080p fit took 0.07 s in all)
_EXTREME_LANES = 256


class DeviceBasis(DeviceRows):
    """(count, M) float32 principal images of shape (H, W, P) (M = H W P) held on ``device`` (``DeviceRows``):
    filled a column block at a time (``place``, from ``DeviceProducts.project``), quantised there
    (``codes``, ``stored``, ``design``)."""

    def __init__(self, count: int, shape: tuple, device):
        self.shape = tuple(int(v) for v in shape)
        super().__init__(count, int(np.prod(self.shape)), device)

    def rows(self, first: int, count: int) -> np.ndarray:
        """(count, M) float32 host copy of images ``first`` .. ``first + count``."""
        out = np.empty((count, self.values), np.float32)
        for part, take, done in self.pieces(first, count, count):
            wp.copy(wp.array(out[done : done + take], dtype=wp.float32, device="cpu", copy=False), part)
        wp.synchronize_device(self.device)
        return out

    def extremes(self, first: int) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) float32 of each image from ``first`` on, found there (the host's values: exact)."""
        count = self.count - first
        lows = wp.full(max(count, 1), np.inf, dtype=wp.float32, device=self.device)
        highs = wp.full(max(count, 1), -np.inf, dtype=wp.float32, device=self.device)
        for part, take, done in self.pieces(first, count, count):
            wp.launch(row_extremes, dim=(take, min(_EXTREME_LANES, self.values)),
                      inputs=[part, min(_EXTREME_LANES, self.values), done],
                      outputs=[lows, highs], device=self.device)
        return lows.numpy()[:count].copy(), highs.numpy()[:count].copy()

    def stored(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, rows: np.ndarray, above: np.ndarray,
               out: np.ndarray) -> np.ndarray:
        """Images ``first`` .. ``first + len(step)`` quantised (float64 ``low``, ``step``, ``bits``) and stored as
        ``io.codes`` stores them at rows ``rows`` (each less its row ``above``, -1: none), into the host
        uint8 ``out`` of shape (c, P, R, W), or (c, P, 2, R, W) for 16 bits."""
        count = len(step)
        _, width, planes = self.shape
        wide = 1 if bits == 16 else 0
        per_image = planes * (1 + wide) * len(rows) * width
        if (out.shape[0] != count or out.size != count * per_image or out.dtype != np.uint8
            or not out.flags.c_contiguous):
            raise ValueError(f"stored codes of {count} images need a contiguous ({count}, ...) uint8 array of "
                             f"{count * per_image} values, "
                             f"got {out.shape} {out.dtype}")
        rows_on = wp.array(np.asarray(rows, np.int32), dtype=wp.int32, device=self.device)
        above_on = wp.array(np.asarray(above, np.int32), dtype=wp.int32, device=self.device)
        levels = wp.float64((1 << bits) - 1)
        flat = out.reshape(count, per_image)
        for part, take, done in self.pieces(first, count, LAUNCH_BYTES // max(per_image, 1)):
            result = wp.empty(take * per_image, dtype=wp.uint8, device=self.device)
            wp.launch(stored_rows, dim=(take, planes, len(rows), width),
                      inputs=[part, width, planes, rows_on, above_on, self.float64(low[done : done + take]),
                              self.float64(step[done : done + take]),
                              levels, wide], outputs=[result], device=self.device)
            wp.copy(wp.array(flat[done : done + take].reshape(-1), dtype=wp.uint8, device="cpu", copy=False), result)
        wp.synchronize_device(self.device)
        return out

    def codes(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, out: np.ndarray) -> np.ndarray:
        """Images ``first`` .. ``first + len(step)`` as ``bits``-bit codes into the host (c, M) ``out``
        (uint8 or uint16)."""
        count = len(step)
        values = int(np.prod(self.shape))
        kind, kernel = (wp.uint8, basis_codes8) if bits == 8 else (wp.uint16, basis_codes16)
        if out.shape != (count, values) or out.dtype != wp.dtype_to_numpy(kind) or not out.flags.c_contiguous:
            raise ValueError(f"{bits}-bit codes of {count} images need a contiguous ({count}, {values}) array, got "
                             f"{out.shape} {out.dtype}")
        levels = wp.float64((1 << bits) - 1)
        for part, take, done in self.pieces(first, count, LAUNCH_BYTES // max(values * out.itemsize, 1)):
            result = wp.empty((take, values), dtype=kind, device=self.device)
            wp.launch(kernel, dim=(take, values), inputs=[part, self.float64(low[done : done + take]),
                                                          self.float64(step[done : done + take]), levels],
                      outputs=[result], device=self.device)
            wp.copy(wp.array(out[done : done + take], dtype=kind, device="cpu", copy=False), result)
        wp.synchronize_device(self.device)
        return out

    def design(self, first: int, low: np.ndarray, step: np.ndarray, bits: int, decoded_low: np.ndarray,
               decoded_step: np.ndarray,
               mean: np.ndarray, columns: slice) -> wp.array:
        """(1 + c, w) float32 on the device, for the stack's weights: row 0 the (w,) ``mean``, row 1 + j
        image ``first + j``'s values at ``columns`` quantised (float64 ``low``, ``step``, ``bits``) and
        decoded (float32 ``decoded_low + code * decoded_step``, the multiply-add possibly fused: within
        a rounding of the host's two)."""
        count, width = len(step), columns.stop - columns.start
        out = wp.empty((count + 1, width), dtype=wp.float32, device=self.device)
        wp.copy(out, wp.array(np.ascontiguousarray(mean, np.float32), dtype=wp.float32, device=self.device),
                count=width)
        levels = wp.float64((1 << bits) - 1)
        for part, take, done in self.pieces(first, count, count):
            wp.launch(decoded_rows, dim=(take, width),
                      inputs=[part, self.float64(low[done : done + take]), self.float64(step[done : done + take]),
                              levels,
                              self.float32(decoded_low[done : done + take]),
                              self.float32(decoded_step[done : done + take]),
                              columns.start, 1 + done], outputs=[out], device=self.device)
        return out
