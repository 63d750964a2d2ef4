"""The residual's normalised stacks made and held on a Warp device (``residual.build.build_residual`` on
CUDA, where they fit): each band of rows of the images and of their own highlights is uploaded once;
there the residual R = I - c(x) R(x; G) is split into luminance Y and chroma (B - Y, R - Y) in
float64, each pixel's sum over the lights of Y^2 comes back for its scale s(x) (finished on the host,
as ``residual.inputs.residual_scale`` does), and the normalised planes N = R / s(x) are kept as float32
rows (``DeviceRows``: a light's luminance, a light's chroma). The principal images' products then
read their column blocks there (``NormalisedStacks.luminance.on_device``) instead of uploading the
stacks from host memory in each of their three passes.

The arithmetic is the host's but for the order of a pixel's sum over the lights and a CUDA device's
fused multiply-adds (a rounding of float32 R, of float64 Y): on the CPU device the planes are the
host's bit for bit; on CUDA they agree to a float32 rounding where the float16 scale rounds alike
(a pixel whose sum sits on a float16 tie may take the neighbouring scale; ``tests/test_stacks.py``).
Each light's sum of squares is taken of the float32 planes (the host sums the float64 values): the
lights' scales differ by about 1e-8.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model.residual import LUMINANCE_WEIGHTS

from .rows import DeviceRows
from .transfer import rows_up

__all__ = ["BAND_VALUES", "HeldStack", "NormalisedStacks", "luminance_squares", "normalised_planes", "row_squares"]

wp.set_module_options({"enable_backward": False})

BAND_VALUES = 1 << 28
"""Values of the images a band uploads (1 GB of float32): 3840x2160 images of 100 lights in 10 bands."""
_SQUARE_CHUNK = 4096  # values of a row each thread of ``row_squares`` sums


@wp.func
def _residual(images: wp.array3d(dtype=wp.float32), own: wp.array2d(dtype=wp.float32),
              tint: wp.array2d(dtype=wp.float32),
              i: int, p: int, c: int) -> wp.float64:
    return wp.float64(images[i, p, c] - own[i, p] * tint[p, c])


@wp.func
def _luminance(images: wp.array3d(dtype=wp.float32), own: wp.array2d(dtype=wp.float32),
               tint: wp.array2d(dtype=wp.float32),
               i: int, p: int, wr: wp.float64, wg: wp.float64, wb: wp.float64) -> wp.float64:
    if images.shape[2] == 1:
        return _residual(images, own, tint, i, p, 0)
    return (wr * _residual(images, own, tint, i, p, 0) + wg * _residual(images, own, tint, i, p, 1)
            + wb * _residual(images, own, tint, i, p, 2))


@wp.kernel
def luminance_squares(images: wp.array3d(dtype=wp.float32), own: wp.array2d(dtype=wp.float32),
                      tint: wp.array2d(dtype=wp.float32),
                      wr: wp.float64, wg: wp.float64, wb: wp.float64, sums: wp.array(dtype=wp.float64)):
    """sums[p]: pixel p's sum over the lights of its residual luminance squared (images (n, pixels, C))."""
    p = wp.tid()
    total = wp.float64(0.0)
    for i in range(images.shape[0]):
        y = _luminance(images, own, tint, i, p, wr, wg, wb)
        total += y * y
    sums[p] = total


@wp.kernel
def normalised_planes(images: wp.array3d(dtype=wp.float32), own: wp.array2d(dtype=wp.float32),
                      tint: wp.array2d(dtype=wp.float32),
                      scale: wp.array(dtype=wp.float32), wr: wp.float64, wg: wp.float64, wb: wp.float64,
                      first_light: int, column: int,
                      luminance: wp.array2d(dtype=wp.float32), chroma: wp.array2d(dtype=wp.float32)):
    """Thread (i, p): light ``first_light + i``'s pixel p of the band, normalised: luminance[i, column + p]
    = Y / s, and (3 channels) chroma[i, 2 (column + p) + 0, 1] = (B - Y) / s, (R - Y) / s, as float32."""
    i, p = wp.tid()
    light = first_light + i
    s = wp.float64(scale[p])
    y = _luminance(images, own, tint, light, p, wr, wg, wb)
    luminance[i, column + p] = wp.float32(y / s)
    if images.shape[2] == 3:
        chroma[i, 2 * (column + p)] = wp.float32((_residual(images, own, tint, light, p, 2) - y) / s)
        chroma[i, 2 * (column + p) + 1] = wp.float32((_residual(images, own, tint, light, p, 0) - y) / s)


@wp.kernel
def row_squares(part: wp.array2d(dtype=wp.float32), chunk: int, first_row: int, partials: wp.array2d(dtype=wp.float64)):
    """partials[first_row + i, k]: the sum of squares of row i's values k chunk .. (k + 1) chunk (float64)."""
    i, k = wp.tid()
    total = wp.float64(0.0)
    end = wp.min((k + 1) * chunk, part.shape[1])
    for x in range(k * chunk, end):
        v = wp.float64(part[i, x])
        total += v * v
    partials[first_row + i, k] = total


def _rows_up(block: np.ndarray, products, whole_bytes: int) -> wp.array:
    """An (n, w) float32 host block on the device: row by row from host memory where each row is
    contiguous (``rows_up``: through its page-locked buffers where the ``whole_bytes`` uploaded band by
    band make them pay), else through ``products.upload``."""
    if block.dtype != np.float32 or not products.device.is_cuda or block.strides[1] != 4:
        return products.upload(block)
    return rows_up(block, products.device, whole_bytes=whole_bytes)


class HeldStack:
    """A normalised stack held on the device as a ``StackSource`` (``model.residual``): ``on_device``
    gives its column blocks there, ``block`` brings one to the host (float64)."""

    def __init__(self, rows: DeviceRows, shape: tuple):
        self.rows = rows
        self.light_count = rows.count
        self.shape = tuple(shape)

    def on_device(self, columns: slice) -> wp.array:
        """(n, w) float32 device block of the stack's values ``columns``."""
        return self.rows.block(columns)

    def block(self, columns: slice) -> np.ndarray:
        return self.on_device(columns).numpy().astype(np.float64)


class NormalisedStacks:
    """The normalised luminance (P = 1) and, for colour images, chroma (P = 2) stacks of (n, H, W, C)
    images, made on ``products``' device (``make``). Attributes: ``scale`` (H, W) float32 s(x);
    ``squares`` (n,) each light's sum of squares of its normalised luminance; ``luminance``, ``chroma``
    (``HeldStack``; chroma None for one channel)."""

    def __init__(self, scale: np.ndarray, squares: np.ndarray, luminance: HeldStack, chroma: HeldStack | None):
        self.scale, self.squares, self.luminance, self.chroma = scale, squares, luminance, chroma

    @staticmethod
    def nbytes(images_shape: tuple) -> int:
        """Device bytes the held stacks of (n, H, W, C) images take."""
        n, height, width, channels = images_shape
        return DeviceRows.nbytes(n, height * width * (1 if channels == 1 else 3))

    @classmethod
    def make(cls, images: np.ndarray, own: np.ndarray, tint: np.ndarray, products, scale_of, *,
             held_images: wp.array | None = None,
             held_own: wp.array | None = None) -> NormalisedStacks:
        """The stacks of float32 ``images`` (n, H, W, C), ``own`` (n, H, W) and ``tint`` (H, W, C), the bands
        uploaded through ``products`` (``kernels.gram.DeviceProducts``); ``scale_of(mean_square)`` turns
        a band's (rows, W) mean over the lights of Y^2 (float64) into its float32 s(x). ``held_images``
        (n, H W, C) and ``held_own`` (n, H W): the same values on the device already, read there (a band
        is a view of them) instead of uploaded."""
        n, height, width, channels = images.shape
        device = products.device
        chroma = DeviceRows(n, height * width * 2, device) if channels == 3 else None
        # the lights split alike
        luminance = DeviceRows(n, height * width, device, part_rows=chroma.part_rows if chroma is not None else None)
        unused = wp.empty((1, 1), dtype=wp.float32, device=device)
        scale = np.empty((height, width), np.float32)
        weights = [wp.float64(w) for w in LUMINANCE_WEIGHTS]
        rows = max(1, min(height, BAND_VALUES // max(n * width * channels, 1)))
        uploaded = images.nbytes + own.nbytes  # the bands together: whether staging pays
        for top in range(0, height, rows):
            band = slice(top, min(top + rows, height))
            pixels = (band.stop - band.start) * width
            columns = slice(top * width, band.stop * width)
            if held_images is not None:
                band_images = held_images[:, columns]
            else:
                band_images = _rows_up(images[:, band].reshape(n, pixels * channels), products,
                                       uploaded).reshape((n, pixels, channels))
            band_own = (held_own[:, columns] if held_own is not None
                        else _rows_up(own[:, band].reshape(n, pixels), products, uploaded))
            band_tint = wp.array(np.ascontiguousarray(tint[band].reshape(pixels, channels), np.float32),
                                 dtype=wp.float32, device=device)
            sums = wp.empty(pixels, dtype=wp.float64, device=device)
            wp.launch(luminance_squares, dim=pixels, inputs=[band_images, band_own, band_tint, *weights],
                      outputs=[sums], device=device)
            scale[band] = scale_of(sums.numpy().reshape(-1, width) / n)
            band_scale = wp.array(scale[band].reshape(-1), dtype=wp.float32, device=device)
            for index, part in enumerate(luminance.parts):
                chroma_part = chroma.parts[index] if chroma is not None else unused
                wp.launch(normalised_planes, dim=(part.shape[0], pixels),
                          inputs=[band_images, band_own, band_tint, band_scale, *weights, index * luminance.part_rows,
                                  top * width],
                          outputs=[part, chroma_part], device=device)
        chunks = -(-luminance.values // _SQUARE_CHUNK)
        partials = wp.zeros((n, chunks), dtype=wp.float64, device=device)
        for index, part in enumerate(luminance.parts):
            wp.launch(row_squares, dim=(part.shape[0], chunks),
                      inputs=[part, _SQUARE_CHUNK, index * luminance.part_rows], outputs=[partials],
                      device=device)
        squares = partials.numpy().sum(axis=1)
        return cls(scale, squares, HeldStack(luminance, (height, width, 1)),
                   None if chroma is None else HeldStack(chroma, (height, width, 2)))
