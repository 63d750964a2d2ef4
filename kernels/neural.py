"""A learned per-pixel residual (NeuralRTI-style): a code per pixel and a small MLP that decodes code +
light direction to RGB, trained with Warp tiles and the tape (``fit --residual learned``; its quality
against the low-rank residual is measured by ``benchmarks/bench_neural_residual.py``).

Model: ``y(p, w) = W3 elu(W2 elu(W1 elu(W0 [z_p, w] + b0) + b1) + b2) + b3``, z_p the pixel's
``CODE_SIZE`` numbers, w the unit light direction; y in display units (signed sRGB encoding of the
target, so that the squared error is the one 8-bit sRGB PSNR measures). Codes start as the pixels'
leading principal components over all lights (a linear encoder), the weights at random.

One launch covers a batch of (light, pixel) samples, ``BLOCK`` per tile block; the tape gives the
gradients of the codes and of every weight; ``warp.optim.Adam`` steps them (``train_decoder``, used by
``fit --residual learned``). ``QueryDecoder`` decodes a field's learned residual for the relighter.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_highlights.model.residual import NEURAL_CODE_SIZE, NEURAL_LAYER_SHAPES

__all__ = ["BLOCK", "CODE_SIZE", "HIDDEN", "MAX_SAMPLES", "NeuralDecoder", "QueryDecoder", "decode", "initial_model",
           "samples_fit", "train_decoder"]

CODE_SIZE = wp.constant(NEURAL_CODE_SIZE)
"""Numbers per pixel: NeuralRTI's code size."""
HIDDEN = wp.constant(NEURAL_LAYER_SHAPES[0][0])
"""Units of each of the three hidden layers (NeuralRTI: 50)."""
INPUTS = wp.constant(12)  # code + light direction
OUTPUTS = wp.constant(3)
BLOCK = wp.constant(64)

MAX_SAMPLES = 2**31 - 1
"""The training samples are indexed light x pixels + pixel in 32 bits (int32 shuffles, half the memory of int64):
at most this many light x pixel pairs (1,035 lights of 1920x1080, 258 of 3840x2160)."""


def samples_fit(lights: int, pixels: int) -> bool:
    """Whether ``lights`` images of ``pixels`` each can be learned (their sample indices fit 32 bits)."""
    return int(lights) * int(pixels) <= MAX_SAMPLES
"""Samples per tile block."""


@wp.func
def elu(x: float):
    return wp.where(x > 0.0, x, wp.exp(wp.min(x, 0.0)) - 1.0)


@wp.kernel
def gather_features(samples: wp.array[wp.int32], first: int, count: int, pixels: int, codes: wp.array2d[float],
                    lights: wp.array[wp.vec3],
                    features: wp.array2d[float]):
    """Column i of ``features`` (INPUTS, padded batch): sample s = samples[i] (or first + i when
    ``samples`` is empty) = light * pixels + pixel as [code of the pixel, light direction]; padding
    columns (i >= count) repeat the last sample."""
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


@wp.kernel
def squared_error(samples: wp.array[wp.int32], count: int, pixels: int, values: wp.array2d[float],
                  targets: wp.array2d[wp.vec3],
                  weight: float, loss: wp.array[float]):
    """loss += weight |values[:, i] - targets[light, pixel]|^2 over the batch's first ``count`` columns."""
    i = wp.tid()
    if i < count:
        s = samples[i]
        light = s / pixels
        pixel = s - light * pixels
        error = wp.vec3(values[0, i], values[1, i], values[2, i]) - targets[light, pixel]
        wp.atomic_add(loss, 0, wp.dot(error, error) * weight)


@dataclass
class NeuralDecoder:
    """Codes (P, CODE_SIZE) and the MLP's weights, NumPy float32 (``weights``: w0 (HIDDEN, 12), b0 (HIDDEN, 1),
    w1, b1, w2, b2 (HIDDEN, HIDDEN), (HIDDEN, 1), w3 (3, HIDDEN), b3 (3, 1))."""

    codes: np.ndarray
    weights: list[np.ndarray]

    @property
    def stored_bytes_per_pixel(self) -> float:
        """Codes as float16 per pixel, plus the weights (float32) spread over the pixels."""
        return 2.0 * CODE_SIZE + 4.0 * sum(w.size for w in self.weights) / len(self.codes)


def _padded(count: int) -> int:
    return max(BLOCK, -(-count // BLOCK) * BLOCK)


def _arrays(model: NeuralDecoder, device, requires_grad: bool):
    codes = wp.array(np.ascontiguousarray(model.codes, np.float32), dtype=float, device=device,
                     requires_grad=requires_grad)
    weights = [wp.array(np.ascontiguousarray(w, np.float32), dtype=float, device=device, requires_grad=requires_grad)
               for w in model.weights]
    return codes, weights


class _Batch:
    """Device buffers of one padded batch of samples."""

    def __init__(self, size: int, device, requires_grad: bool):
        self.size = size
        self.features = wp.zeros((INPUTS, size), dtype=float, device=device, requires_grad=requires_grad)
        self.values = wp.zeros((OUTPUTS, size), dtype=float, device=device, requires_grad=requires_grad)

    def run(self, samples, count: int, pixels: int, codes, lights, weights, device, first: int = 0) -> None:
        """Decode ``count`` samples into the first columns of ``values`` (the blocks that hold them only:
        a buffer sized for a batch of queries decodes one query at the cost of one)."""
        size = _padded(count)
        if size > self.size:
            raise ValueError(f"{count} samples do not fit a batch of {self.size}")
        wp.launch(gather_features, dim=size, inputs=[samples, first, count, pixels, codes, lights],
                  outputs=[self.features], device=device)
        wp.launch_tiled(decoder_tiles, dim=[size // BLOCK], inputs=[self.features, *weights], outputs=[self.values],
                        block_dim=BLOCK, device=device)


def decode(model: NeuralDecoder, lights: np.ndarray, *, device=None, batch: int = 1 << 20) -> np.ndarray:
    """(L, P, 3) float32 decoded values for (L, 3) light directions, on ``device``."""
    device = wp.get_device(device)
    codes, weights = _arrays(model, device, False)
    pixels = len(model.codes)
    lights = np.asarray(lights, np.float32).reshape(-1, 3)
    light_array = wp.array(lights, dtype=wp.vec3, device=device)
    total = len(lights) * pixels
    out = np.empty((total, 3), np.float32)
    buffers = _Batch(_padded(min(batch, total)), device, False)
    no_samples = wp.empty(0, dtype=wp.int32, device=device)
    for start in range(0, total, batch):
        count = min(batch, total - start)
        buffers.run(no_samples, count, pixels, codes, light_array, weights, device, first=start)
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


class QueryDecoder:
    """A learned residual on one device, decoded for batches of query directions into float16 images.

    Args:
        codes: (P, CODE_SIZE) float32 per output pixel; weights: the eight arrays; unit: field units per
        display unit; batch: samples per launch (bounds the working memory: 60 bytes a sample).
    """

    def __init__(self, codes: np.ndarray, weights, unit: float, *, device=None, batch: int = 1 << 20):
        self.device = wp.get_device(device)
        self.pixels = len(codes)
        self.unit = float(unit)
        self.batch = int(batch)
        self.codes = wp.array(np.ascontiguousarray(codes, np.float32), dtype=float, device=self.device)
        self.weights = [wp.array(np.ascontiguousarray(w, np.float32), dtype=float, device=self.device) for w in weights]
        self._buffers = None
        self._no_samples = wp.empty(0, dtype=wp.int32, device=self.device)

    def decode(self, directions: wp.array, out: wp.array) -> None:
        """(Q,) vec3 unit directions -> out (Q, P, 3) float16, field units."""
        total = directions.shape[0] * self.pixels
        size = _padded(min(self.batch, total))
        if self._buffers is None or self._buffers.size < size:
            self._buffers = _Batch(size, self.device, False)
        for start in range(0, total, self.batch):
            count = min(self.batch, total - start)
            self._buffers.run(self._no_samples, count, self.pixels, self.codes, directions, self.weights, self.device,
                              first=start)
            wp.launch(store_decoded, dim=count, inputs=[self._buffers.values, start, count, self.pixels, self.unit],
                      outputs=[out], device=self.device)


def initial_model(targets: np.ndarray, *, seed: int = 0) -> NeuralDecoder:
    """Codes from the leading principal components of the (n, P, 3) targets (unit variance), weights
    uniform in +-1/sqrt(fan-in)."""
    n, pixels, _ = targets.shape
    flat = targets.transpose(1, 0, 2).reshape(pixels, -1).astype(np.float64)
    flat = flat - flat.mean(axis=0)
    gram = flat.T @ flat
    values, vectors = np.linalg.eigh(gram)
    leading = vectors[:, ::-1][:, :CODE_SIZE]
    codes = flat @ leading
    codes /= np.maximum(codes.std(axis=0), 1e-12)
    if codes.shape[1] < CODE_SIZE:
        codes = np.concatenate([codes, np.zeros((pixels, CODE_SIZE - codes.shape[1]))], axis=1)
    rng = np.random.default_rng(seed)
    shapes = [(HIDDEN, INPUTS), (HIDDEN, HIDDEN), (HIDDEN, HIDDEN), (OUTPUTS, HIDDEN)]
    weights = []
    for rows, cols in shapes:
        bound = 1.0 / np.sqrt(cols)
        weights += [rng.uniform(-bound, bound, (rows, cols)).astype(np.float32),
                    rng.uniform(-bound, bound, (rows, 1)).astype(np.float32)]
    return NeuralDecoder(codes.astype(np.float32), weights)


def train_decoder(targets: np.ndarray, lights: np.ndarray, *, device=None, epochs: int = 40, batch: int = 1 << 16,
                  lr: float = 3e-3,
                  final_lr: float = 3e-4, seed: int = 0, seconds: float | None = None, log=None,
                  used: np.ndarray | None = None,
                  initial: NeuralDecoder | None = None) -> tuple[NeuralDecoder, list[float]]:
    """Fit codes and weights to (n, P, 3) display-unit targets at (n, 3) lights: Adam on the mean
    squared error over shuffled (light, pixel) samples, ``batch`` a step, the learning rate decaying
    geometrically from ``lr`` to ``final_lr`` over ``epochs`` (or until ``seconds`` have passed since
    the first step, which compiles the kernels). ``used``: indices of the lights to learn from (default
    all); the others' targets are never read, neither by the codes' start nor by a step, so they can
    score the model as held-out lights. ``initial``: a model to go on training (default: ``initial_model``
    of the used lights' targets).
    Returns the model and the mean loss of each epoch."""
    device = wp.get_device(device)
    targets = np.ascontiguousarray(targets, np.float32)
    n, pixels, _ = targets.shape
    if not samples_fit(n, pixels):
        raise ValueError(f"{n} lights of {pixels} pixels pass the learned residual's 32-bit sample index (2^31); learn "
                         f"fewer or smaller images")
    used = np.arange(n) if used is None else np.unique(np.asarray(used, dtype=np.int64))
    if not len(used) or used[0] < 0 or used[-1] >= n:
        raise ValueError(f"used must name some of the {n} lights")
    model = initial_model(targets[used], seed=seed) if initial is None else initial
    if model.codes.shape != (pixels, CODE_SIZE):
        raise ValueError(f"initial codes {model.codes.shape} do not match {pixels} pixels")
    codes, weights = _arrays(model, device, True)
    params = [codes, *weights]
    target_array = wp.array(targets, dtype=wp.vec3, device=device)
    light_array = wp.array(np.asarray(lights, np.float32), dtype=wp.vec3, device=device)
    # here, not at the top: it imports Warp's sparse and solver kernels (0.25 s), which only training needs
    import warp.optim

    optimizer = warp.optim.Adam([p.flatten() for p in params], lr=lr)
    grads = [p.grad.flatten() for p in params]
    loss = wp.zeros(1, dtype=float, device=device, requires_grad=True)
    total = len(used) * pixels
    buffers = _Batch(_padded(min(batch, total)), device, True)
    rng = np.random.default_rng(seed)
    history = []
    # the clock starts once the first step has run: compiling the kernels (minutes on a fresh CUDA machine) is not
    # training
    started = None
    for epoch in range(epochs):
        optimizer.lr = lr * (final_lr / lr) ** (epoch / max(epochs - 1, 1))
        shuffled = rng.permutation(total)
        if len(used) < n:  # sample index = light * pixels + pixel, over the used lights only
            shuffled = used[shuffled // pixels] * pixels + shuffled % pixels
        order = wp.array(shuffled.astype(np.int32), dtype=wp.int32, device=device)
        epoch_loss = wp.zeros(1, dtype=float, device=device)
        for start in range(0, total, batch):
            count = min(batch, total - start)
            loss.zero_()
            tape = wp.Tape()
            with tape:
                samples = order[start : start + count]
                buffers.run(samples, count, pixels, codes, light_array, weights, device)
                wp.launch(squared_error, dim=count, inputs=[samples, count, pixels, buffers.values, target_array,
                                                            1.0 / count], outputs=[loss], device=device)
            tape.backward(loss)
            optimizer.step(grads)
            tape.zero()
            _accumulate(epoch_loss, loss, device)
            if started is None:
                wp.synchronize_device(device)
                started = time.perf_counter()
        steps = -(-total // batch)
        history.append(float(epoch_loss.numpy()[0]) / steps)
        if log:
            log(f"epoch {epoch + 1}/{epochs}: mse {history[-1]:.3e} (lr {optimizer.lr:.1e}, "
                f"{time.perf_counter() - started:.1f} s)")
        if seconds is not None and time.perf_counter() - started > seconds:
            break
    model = NeuralDecoder(codes.numpy().copy(), [w.numpy().copy() for w in weights])
    return model, history


@wp.kernel
def _add(total: wp.array[float], value: wp.array[float]):
    """total += value (one thread): an epoch's loss summed on the device, read once an epoch."""
    total[0] = total[0] + value[0]


def _accumulate(total, value, device) -> None:
    wp.launch(_add, dim=1, inputs=[total, value], device=device)
