"""A learned per-pixel residual (NeuralRTI-style): a code per pixel and a small MLP that decodes code +
light direction to RGB (``fit --residual learned``; its quality against the low-rank residual is measured
by ``benchmarks/bench_neural_residual.py``), decoded with Warp tiles; ``kernels.neural_training`` trains it.

Model: ``y(p, w) = W3 elu(W2 elu(W1 elu(W0 [z_p, w] + b0) + b1) + b2) + b3``, z_p the pixel's
``CODE_SIZE`` numbers, w the unit light direction; y in display units (signed sRGB encoding of the
target, so that the squared error is the one 8-bit sRGB PSNR measures). Codes start as the pixels'
leading principal components over all lights (a linear encoder), the weights at random. A decoder that sees
the highlights (``model.residual.sees_highlights``) also takes (sqrt(g), g), g the Gaussians' luminance at the
pixel for that light in display units: W0 [z_p, w, sqrt(g), g].

The kernels take ``INPUTS`` = 14 inputs for either kind: a decoder without the highlights' inputs is given zero
weights for them (``kernel_weights``) and zero inputs.

One launch covers a batch of (light, pixel) samples, ``BLOCK`` per tile block. ``QueryDecoder`` decodes
a field's learned residual for the relighter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_highlights.model.config import LEARNED_MATHDX
from warp_highlights.model.residual import (
    NEURAL_CODE_SIZE,
    NEURAL_HIGHLIGHT_INPUTS,
    NEURAL_INPUTS,
    NEURAL_LAYER_SHAPES,
    sees_highlights,
)
from warp_highlights.model.threads import blas_on_one_thread, parallel_map

# decoding only (training has its own adjoint, ``kernels.neural_training``): no backward code to compile; tile
# products without cuBLASDx (``LEARNED_MATHDX``)
wp.set_module_options({"enable_backward": False, "enable_mathdx_gemm": LEARNED_MATHDX})

__all__ = ["BLOCK", "CODE_SIZE", "HIDDEN", "HIGHLIGHT_ROW", "INPUTS", "MAX_SAMPLES", "NeuralDecoder", "QueryDecoder",
           "bound_decoded", "decode", "initial_model", "kernel_weights", "samples_fit", "used_lights"]

CODE_SIZE = wp.constant(NEURAL_CODE_SIZE)
"""Numbers per pixel: NeuralRTI's code size."""
HIDDEN = wp.constant(NEURAL_LAYER_SHAPES[0][0])
"""Units of each of the three hidden layers (NeuralRTI: 50)."""
HIGHLIGHT_ROW = wp.constant(NEURAL_INPUTS)
"""The features' row of sqrt(g), after the code and the light direction; g's is the next."""
INPUTS = wp.constant(NEURAL_INPUTS + NEURAL_HIGHLIGHT_INPUTS)
"""The kernels' inputs: code, light direction, sqrt(g), g (0 and 0 for a decoder that does not see the highlights)."""
OUTPUTS = wp.constant(3)
BLOCK = wp.constant(64)
"""Samples per tile block."""

MAX_SAMPLES = 2**31 - 1
"""The training samples are indexed light x pixels + pixel in 32 bits (int32 shuffles, half the memory of int64):
at most this many light x pixel pairs (1,035 lights of 1920x1080, 258 of 3840x2160)."""


def samples_fit(lights: int, pixels: int) -> bool:
    """Whether ``lights`` images of ``pixels`` each can be learned (their sample indices fit 32 bits)."""
    return int(lights) * int(pixels) <= MAX_SAMPLES


def used_lights(lights: int, pixels: int, used) -> np.ndarray:
    """The sorted indices of the lights a training learns from (``used``, default all), once ``lights``
    images of ``pixels`` are known to fit the sample index (ValueError otherwise)."""
    if not samples_fit(lights, pixels):
        raise ValueError(f"{lights} lights of {pixels} pixels pass the learned residual's 32-bit sample index (2^31); "
                         f"learn fewer or smaller images")
    used = np.arange(lights) if used is None else np.unique(np.asarray(used, dtype=np.int64))
    if not len(used) or used[0] < 0 or used[-1] >= lights:
        raise ValueError(f"used must name some of the {lights} lights")
    return used


@wp.func
def elu(x: float):
    return wp.where(x > 0.0, x, wp.exp(wp.min(x, 0.0)) - 1.0)


@wp.kernel
def gather_features(samples: wp.array[wp.int32], first: int, count: int, pixels: int, codes: wp.array2d[float],
                    lights: wp.array[wp.vec3], highlights: wp.array2d[float], scale: float,
                    features: wp.array2d[float]):
    """Column i of ``features`` (INPUTS, padded batch): sample s = samples[i] (or first + i when
    ``samples`` is empty) = light * pixels + pixel as [code of the pixel, light direction, sqrt(g), g], g =
    max(highlights[light, pixel] * scale, 0) (display units), or 0 and 0 when ``highlights`` is empty (shape (0, 0));
    padding columns (i >= count) repeat the last sample."""
    i = wp.tid()
    s = first + wp.min(i, count - 1)
    if samples.shape[0] > 0:
        s = samples[wp.min(i, count - 1)]
    light = s / pixels
    pixel = s - light * pixels
    for k in range(CODE_SIZE):
        features[k, i] = codes[pixel, k]
    direction = lights[light]
    for k in range(3):
        features[CODE_SIZE + k, i] = direction[k]
    g = float(0.0)
    if highlights.shape[0] > 0:
        g = wp.max(highlights[light, pixel] * scale, 0.0)
    features[HIGHLIGHT_ROW, i] = wp.sqrt(g)
    features[HIGHLIGHT_ROW + 1, i] = g


@wp.kernel
def decoder_tiles(features: wp.array2d[float], w0: wp.array2d[float], b0: wp.array2d[float], w1: wp.array2d[float],
                  b1: wp.array2d[float],
                  w2: wp.array2d[float], b2: wp.array2d[float], w3: wp.array2d[float], b3: wp.array2d[float],
                  out: wp.array2d[float]):
    """The MLP on BLOCK columns of ``features`` per block: (OUTPUTS, BLOCK) values into ``out``."""
    block = wp.tid()
    x = wp.tile_load(features, shape=(INPUTS, BLOCK), offset=(0, block * BLOCK))
    h = wp.tile_map(elu, wp.tile_matmul(wp.tile_load(w0, shape=(HIDDEN, INPUTS)), x)
                    + wp.tile_broadcast(wp.tile_load(b0, shape=(HIDDEN, 1)), shape=(HIDDEN, BLOCK)))
    h = wp.tile_map(elu, wp.tile_matmul(wp.tile_load(w1, shape=(HIDDEN, HIDDEN)), h)
                    + wp.tile_broadcast(wp.tile_load(b1, shape=(HIDDEN, 1)), shape=(HIDDEN, BLOCK)))
    h = wp.tile_map(elu, wp.tile_matmul(wp.tile_load(w2, shape=(HIDDEN, HIDDEN)), h)
                    + wp.tile_broadcast(wp.tile_load(b2, shape=(HIDDEN, 1)), shape=(HIDDEN, BLOCK)))
    y = (wp.tile_matmul(wp.tile_load(w3, shape=(OUTPUTS, HIDDEN)), h)
         + wp.tile_broadcast(wp.tile_load(b3, shape=(OUTPUTS, 1)), shape=(OUTPUTS, BLOCK)))
    wp.tile_store(out, y, offset=(0, block * BLOCK))


@dataclass
class NeuralDecoder:
    """Codes (P, CODE_SIZE) and the MLP's weights, NumPy float32 (``weights``: w0 (HIDDEN, 12), or (HIDDEN, 14) for a
    decoder that sees the highlights, b0 (HIDDEN, 1), w1, b1, w2, b2 (HIDDEN, HIDDEN), (HIDDEN, 1), w3 (3, HIDDEN),
    b3 (3, 1))."""

    codes: np.ndarray
    weights: list[np.ndarray]

    @property
    def stored_bytes_per_pixel(self) -> float:
        """Codes as float16 per pixel, plus the weights (float32) spread over the pixels."""
        return 2.0 * CODE_SIZE + 4.0 * sum(w.size for w in self.weights) / len(self.codes)

    @property
    def sees_highlights(self) -> bool:
        """Whether the decoder takes the Gaussians' luminance (w0 has 14 columns)."""
        return sees_highlights(self.weights)


def kernel_weights(weights) -> list[np.ndarray]:
    """The decoder's float32 arrays as the kernels take them: w0 (HIDDEN, INPUTS), given zero columns for the
    highlights' inputs where it has 12."""
    arrays = [np.ascontiguousarray(w, np.float32) for w in weights]
    first = arrays[0]
    if first.ndim != 2 or first.shape[1] not in (NEURAL_INPUTS, INPUTS):
        raise ValueError(f"a decoder's w0 has {NEURAL_INPUTS} or {INPUTS} columns, got shape {first.shape}")
    if first.shape[1] == NEURAL_INPUTS:
        arrays[0] = np.concatenate([first, np.zeros((len(first), NEURAL_HIGHLIGHT_INPUTS), np.float32)], axis=1)
    return arrays


def _padded(count: int) -> int:
    return max(BLOCK, -(-count // BLOCK) * BLOCK)


def _arrays(model: NeuralDecoder, device):
    codes = wp.array(np.ascontiguousarray(model.codes, np.float32), dtype=float, device=device)
    weights = [wp.array(w, dtype=float, device=device) for w in kernel_weights(model.weights)]
    return codes, weights


def _check_highlights(sees: bool, given: bool) -> None:
    """ValueError unless highlights are ``given`` exactly when the decoder ``sees`` them."""
    if sees and not given:
        raise ValueError("a decoder that sees the highlights needs them: pass highlights")
    if given and not sees:
        raise ValueError("a decoder without highlight inputs was given highlights")


class _Batch:
    """Device buffers of one padded batch of samples."""

    def __init__(self, size: int, device):
        self.size = size
        self.features = wp.zeros((INPUTS, size), dtype=float, device=device)
        self.values = wp.zeros((OUTPUTS, size), dtype=float, device=device)
        self.no_highlights = wp.empty((0, 0), dtype=float, device=device)

    def run(self, samples, count: int, pixels: int, codes, lights, weights, device, first: int = 0,
            highlights=None, scale: float = 1.0) -> None:
        """Decode ``count`` samples into the first columns of ``values`` (the blocks that hold them only:
        a buffer sized for a batch of queries decodes one query at the cost of one). ``highlights``: (lights,
        pixels) float array on the device, the Gaussians' luminance times ``scale`` in display units (None: 0)."""
        size = _padded(count)
        if size > self.size:
            raise ValueError(f"{count} samples do not fit a batch of {self.size}")
        highlights = self.no_highlights if highlights is None else highlights
        wp.launch(gather_features, dim=size,
                  inputs=[samples, first, count, pixels, codes, lights, highlights, float(scale)],
                  outputs=[self.features], device=device)
        wp.launch_tiled(decoder_tiles, dim=[size // BLOCK], inputs=[self.features, *weights], outputs=[self.values],
                        block_dim=BLOCK, device=device)


def decode(model: NeuralDecoder, lights: np.ndarray, *, device=None, batch: int = 1 << 20,
           highlights: np.ndarray | None = None) -> np.ndarray:
    """(L, P, 3) float32 decoded values (display units) for (L, 3) light directions, on ``device``. ``highlights``:
    (L, P) the Gaussians' luminance at each light and pixel (display units), required by a decoder that sees them
    and refused by one that does not (ValueError)."""
    _check_highlights(sees_highlights(model.weights), highlights is not None)
    device = wp.get_device(device)
    codes, weights = _arrays(model, device)
    pixels = len(model.codes)
    lights = np.asarray(lights, np.float32).reshape(-1, 3)
    light_array = wp.array(lights, dtype=wp.vec3, device=device)
    highlight_array = None
    if highlights is not None:
        highlights = np.asarray(highlights, np.float32)
        if highlights.size != len(lights) * pixels:
            raise ValueError(f"highlights must be ({len(lights)}, {pixels}), got shape {highlights.shape}")
        highlight_array = wp.array(np.ascontiguousarray(highlights.reshape(len(lights), pixels)), dtype=float,
                                   device=device)
    total = len(lights) * pixels
    out = np.empty((total, 3), np.float32)
    buffers = _Batch(_padded(min(batch, total)), device)
    no_samples = wp.empty(0, dtype=wp.int32, device=device)
    for start in range(0, total, batch):
        count = min(batch, total - start)
        buffers.run(no_samples, count, pixels, codes, light_array, weights, device, first=start,
                    highlights=highlight_array)
        out[start : start + count] = buffers.values.numpy()[:, :count].T
    return out.reshape(len(lights), pixels, 3)


@wp.kernel
def store_decoded(values: wp.array2d[float], first: int, count: int, pixels: int, unit: float,
                  out: wp.array3d[wp.float16]):
    """out[q, pixel, c] = unit * decoded sRGB of values[c, i] for sample first + i = q * pixels + pixel,
    clipped to float16's range: the learned residual in the field's units for the compose kernel."""
    i = wp.tid()
    if i < count:
        s = first + i
        q = s / pixels
        pixel = s - q * pixels
        for c in range(3):
            v = values[c, i]
            x = wp.abs(v)
            linear = x / 12.92
            if x > 0.04045:
                linear = wp.pow((x + 0.055) / 1.055, 2.4)
            out[q, pixel, c] = wp.float16(wp.clamp(wp.sign(v) * linear * unit, -6.0e4, 6.0e4))


@wp.kernel
def bound_decoded(bounds: wp.array3d[wp.float16], out: wp.array3d[wp.float16]):
    """out[q, pixel, c] kept within [bounds[0, pixel, c], bounds[1, pixel, c]]: a learned residual's decoded values
    (field units) within its bounds (``model.residual.learned_bounds``)."""
    q, pixel = wp.tid()
    for c in range(3):
        out[q, pixel, c] = wp.min(wp.max(out[q, pixel, c], bounds[0, pixel, c]), bounds[1, pixel, c])


class QueryDecoder:
    """A learned residual on one device, decoded for batches of query directions into float16 images.

    Args:
        codes: (P, CODE_SIZE) float32 per output pixel; weights: the eight arrays (w0 with 12 columns, or 14 for a
        decoder that sees the highlights); unit: field units per display unit; batch: samples per launch (bounds
        the working memory: 68 bytes a sample).
    """

    def __init__(self, codes: np.ndarray, weights, unit: float, *, device=None, batch: int = 1 << 20):
        self.device = wp.get_device(device)
        self.pixels = len(codes)
        self.unit = float(unit)
        self.batch = int(batch)
        self._sees_highlights = sees_highlights(weights)
        self.codes = wp.array(np.ascontiguousarray(codes, np.float32), dtype=float, device=self.device)
        self.weights = [wp.array(w, dtype=float, device=self.device) for w in kernel_weights(weights)]
        self._buffers = None
        self._no_samples = wp.empty(0, dtype=wp.int32, device=self.device)

    @property
    def sees_highlights(self) -> bool:
        """Whether ``decode`` takes the Gaussians' luminance (the decoder's w0 has 14 columns)."""
        return self._sees_highlights

    def decode(self, directions: wp.array, out: wp.array, highlights: wp.array | None = None) -> None:
        """(Q,) vec3 unit directions -> out (Q, P, 3) float16, field units. ``highlights``: float32 (Q, P) or (Q, H,
        W) on the device, the Gaussians' luminance at each query and pixel in field units (divided by ``unit``
        here), required by a decoder that sees them and refused by one that does not (ValueError)."""
        _check_highlights(self._sees_highlights, highlights is not None)
        queries = directions.shape[0]
        if highlights is not None:
            if highlights.size != queries * self.pixels or highlights.dtype != wp.float32:
                raise ValueError(f"highlights must be float32 ({queries}, {self.pixels}), got {highlights.dtype} "
                                 f"{highlights.shape}")
            highlights = highlights.reshape((queries, self.pixels))
        total = queries * self.pixels
        size = _padded(min(self.batch, total))
        if self._buffers is None or self._buffers.size < size:
            self._buffers = _Batch(size, self.device)
        for start in range(0, total, self.batch):
            count = min(self.batch, total - start)
            self._buffers.run(self._no_samples, count, self.pixels, self.codes, directions, self.weights, self.device,
                              first=start, highlights=highlights, scale=1.0 / self.unit)
            wp.launch(store_decoded, dim=count, inputs=[self._buffers.values, start, count, self.pixels, self.unit],
                      outputs=[out], device=self.device)


INITIAL_BAND = 1 << 14
"""Pixels ``initial_model`` reads at a time on a thread (their n x 3 targets in float64: 8 MB for 64 lights)."""


def initial_model(targets: np.ndarray, *, seed: int = 0) -> NeuralDecoder:
    """Codes from the leading principal components of the (n, P, 3) targets (unit variance), weights
    uniform in +-1/sqrt(fan-in), w0 with 12 columns (no highlights' inputs). The covariance is summed in float64
    over bands of ``INITIAL_BAND`` pixels on the threads, the targets never copied whole."""
    targets = np.asarray(targets)
    n, pixels, _ = targets.shape
    bands = [slice(start, min(start + INITIAL_BAND, pixels)) for start in range(0, pixels, INITIAL_BAND)]
    rows = lambda band: targets[:, band].transpose(1, 0, 2).reshape(-1, 3 * n).astype(np.float64)  # noqa: E731

    def moments(band: slice) -> tuple[np.ndarray, np.ndarray]:
        flat = rows(band)
        return flat.sum(axis=0), flat.T @ flat

    with blas_on_one_thread():
        parts = parallel_map(moments, bands)
        mean = sum(part[0] for part in parts) / pixels
        gram = sum(part[1] for part in parts) - pixels * np.outer(mean, mean)
        values, vectors = np.linalg.eigh(gram)
        leading = vectors[:, ::-1][:, :CODE_SIZE]
        codes = np.concatenate(parallel_map(lambda band: (rows(band) - mean) @ leading, bands))
    codes /= np.maximum(codes.std(axis=0), 1e-12)
    if codes.shape[1] < CODE_SIZE:
        codes = np.concatenate([codes, np.zeros((pixels, CODE_SIZE - codes.shape[1]))], axis=1)
    rng = np.random.default_rng(seed)
    shapes = [(HIDDEN, NEURAL_INPUTS), (HIDDEN, HIDDEN), (HIDDEN, HIDDEN), (OUTPUTS, HIDDEN)]
    weights = []
    for rows, cols in shapes:
        bound = 1.0 / np.sqrt(cols)
        weights += [rng.uniform(-bound, bound, (rows, cols)).astype(np.float32),
                    rng.uniform(-bound, bound, (rows, 1)).astype(np.float32)]
    return NeuralDecoder(codes.astype(np.float32), weights)
