"""Training the learned residual's decoder (``kernels.neural``) on the device: a fused step with a
hand-written adjoint, Adam on the device, samples shuffled on the device, a CUDA graph per step.

One step is six launches, none of which needs a host value, so a CUDA graph replays it:

1. ``gather_batch``: ``batch`` (light, pixel) samples of the current epoch's shuffle (a keyed Feistel
   permutation of the used samples, ``shuffled_sample``), their features [code, light direction, sqrt(g), g]
   (g the Gaussians' luminance for a model that sees the highlights, else 0) and targets, for every model;
2. ``train_tiles`` (``make_train_tiles``): per tile of samples, the MLP forward, the squared error and the
   whole backward pass (tile matrix products); each block's sums of the weights' gradients stored as
   its partial sums, the features' gradients stored;
3. ``sum_partials``: the blocks' partial sums added to the gradient buffer, block by block (the same
   sum in every run);
4. ``scatter_code_gradients``: the features' gradients added to their pixels' codes;
5. ``adam_flat``: Adam over every parameter of every model (codes and weights are views of one flat
   buffer), the learning rate of the step's epoch from the device's step counter; it zeroes the
   gradients it used;
6. ``advance``: the step counter + 1.

``M`` models (the learned check's two candidates) train side by side in the same launches, on the
same samples, each with its own targets. Loss values stay on the device until an epoch's end. Every model
trains with ``INPUTS`` = 14 inputs: one that does not see the highlights has zero inputs for them, so the
gradient of its w0's last two columns is 0 and they stay 0 (they are dropped from its result).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_highlights.model.config import LEARNED_MATHDX, LEARNED_TILE
from warp_highlights.model.residual import NEURAL_INPUTS, sees_highlights

from .neural import (
    CODE_SIZE,
    HIDDEN,
    HIGHLIGHT_ROW,
    INPUTS,
    OUTPUTS,
    NeuralDecoder,
    elu,
    initial_model,
    kernel_weights,
    used_lights,
)

__all__ = ["DecoderTrainer", "make_train_tiles", "elu_gradient", "shuffled_sample", "train_decoder", "train_decoders"]

_MODULE_OPTIONS = {"enable_backward": False, "enable_mathdx_gemm": LEARNED_MATHDX, "max_unroll": 0}
# the hand-written adjoint is the only one: no tape, no generated backward code to compile
wp.set_module_options(_MODULE_OPTIONS)

ADAM_BETA1 = 0.9
ADAM_BETA2 = 0.999
ADAM_EPSILON = 1e-8
"""Adam's constants: those of ``warp.optim.Adam`` and PyTorch's default."""

_WEIGHT_SHAPES = ((HIDDEN, INPUTS), (HIDDEN, 1), (HIDDEN, HIDDEN), (HIDDEN, 1), (HIDDEN, HIDDEN), (HIDDEN, 1),
                  (OUTPUTS, HIDDEN), (OUTPUTS, 1))


@wp.func
def elu_gradient(upstream: float, output: float):
    """d elu / d input times ``upstream``, from elu's output (1 above 0, else output + 1 = exp(input))."""
    return wp.where(output > 0.0, upstream, upstream * (output + 1.0))


@wp.func
def _round_value(value: wp.int64, key: int, round_index: int, mask: wp.int64):
    state = wp.rand_init(key * 8 + round_index, int(value))
    return wp.int64(wp.randi(state)) & mask


@wp.func
def shuffled_sample(position: wp.int64, total: wp.int64, key: int, half_bits: int):
    """The ``position``-th of ``total`` samples in the shuffle keyed ``key``: a four-round Feistel
    permutation of [0, 4^half_bits), walked until it lands below ``total`` (a bijection of [0, total))."""
    mask = (wp.int64(1) << wp.int64(half_bits)) - wp.int64(1)
    x = position
    done = bool(False)
    while not done:
        left = x >> wp.int64(half_bits)
        right = x & mask
        for r in range(4):
            mixed = left ^ _round_value(right, key, r, mask)
            left = right
            right = mixed
        x = (left << wp.int64(half_bits)) | right
        done = x < total
    return x


@wp.kernel
def gather_batch(step: wp.array[wp.int64], batch: int, total: wp.int64, half_bits: int, seed: int,
                 used: wp.array[wp.int32], pixels: int, codes: wp.array3d[float], lights: wp.array[wp.vec3],
                 targets: wp.array3d[wp.vec3], highlights: wp.array2d[float], sees: wp.array[wp.int32],
                 samples: wp.array[wp.int64], features: wp.array3d[float], batch_targets: wp.array3d[float]):
    """Sample i of this step: its (used light, pixel) index into ``samples``, and for each model m its
    features (INPUTS, batch) and targets (OUTPUTS, batch). The features' last two rows: sqrt(g), g for g =
    max(highlights[light, pixel], 0) (display units) where ``sees[m]`` is not 0, else 0 and 0 (``highlights`` is
    then not read: it may be empty)."""
    i = wp.tid()
    position = step[0] * wp.int64(batch) + wp.int64(i)
    epoch = position / total
    sample = shuffled_sample(position - epoch * total, total, seed * 65599 + int(epoch), half_bits)
    light = used[int(sample / wp.int64(pixels))]
    pixel = int(sample % wp.int64(pixels))
    samples[i] = wp.int64(light) * wp.int64(pixels) + wp.int64(pixel)
    direction = lights[light]
    for m in range(codes.shape[0]):
        for k in range(CODE_SIZE):
            features[m, k, i] = codes[m, pixel, k]
        for k in range(3):
            features[m, CODE_SIZE + k, i] = direction[k]
        g = float(0.0)
        if sees[m] != 0:
            g = wp.max(highlights[light, pixel], 0.0)
        features[m, HIGHLIGHT_ROW, i] = wp.sqrt(g)
        features[m, HIGHLIGHT_ROW + 1, i] = g
        target = targets[m, light, pixel]
        for c in range(OUTPUTS):
            batch_targets[m, c, i] = target[c]


@functools.cache
def make_train_tiles(columns: int, sub_batches: int):
    """The fused step's kernel for tiles of ``columns`` samples, each tile block looping over
    ``sub_batches`` of them: the weights' gradients add up in the block and are stored once a block as
    its partial sums (``sum_partials`` adds them up), so no atomic add serialises the launch and the sum
    is the same in every run. The block keeps few tiles in shared memory (each layer's product is
    written into one scratch tile, each activation into its own, the bias gradients add up in
    registers); a layer's gradient takes its activation's place once the activation is spent. A weight
    gradient's product sums over the samples: its right operand is the activation read through a transposed
    view, whose rows are one column wider than they are used, so that the threads of a warp walking down a
    column read different shared-memory banks."""

    wide_columns = columns + 1  # the padded tiles' row length

    @wp.kernel(module="unique", module_options=_MODULE_OPTIONS)
    def train_tiles(features: wp.array3d[float], batch_targets: wp.array3d[float], scale: float,
                    w0: wp.array3d[float], b0: wp.array3d[float], w1: wp.array3d[float], b1: wp.array3d[float],
                    w2: wp.array3d[float], b2: wp.array3d[float], w3: wp.array3d[float], b3: wp.array3d[float],
                    g0: wp.array4d[float], c0: wp.array4d[float], g1: wp.array4d[float], c1: wp.array4d[float],
                    g2: wp.array4d[float], c2: wp.array4d[float], g3: wp.array4d[float], c3: wp.array4d[float],
                    feature_gradients: wp.array3d[float], loss: wp.array2d[float]):
        """Model m, ``sub_batches`` tiles of ``columns`` samples: loss += scale * sum |y - t|^2; the
        gradients of that term stored in g*[block, m] (weights) and c*[block, m] (biases); d loss / d
        features stored."""
        m, block = wp.tid()
        weight0 = wp.tile_load(w0[m], shape=(HIDDEN, INPUTS))
        weight1 = wp.tile_load(w1[m], shape=(HIDDEN, HIDDEN))
        weight2 = wp.tile_load(w2[m], shape=(HIDDEN, HIDDEN))
        weight3 = wp.tile_load(w3[m], shape=(OUTPUTS, HIDDEN))
        bias0 = wp.tile_broadcast(wp.tile_load(b0[m], shape=(HIDDEN, 1)), shape=(HIDDEN, columns))
        bias1 = wp.tile_broadcast(wp.tile_load(b1[m], shape=(HIDDEN, 1)), shape=(HIDDEN, columns))
        bias2 = wp.tile_broadcast(wp.tile_load(b2[m], shape=(HIDDEN, 1)), shape=(HIDDEN, columns))
        bias3 = wp.tile_broadcast(wp.tile_load(b3[m], shape=(OUTPUTS, 1)), shape=(OUTPUTS, columns))
        sum0 = wp.tile_zeros(shape=(HIDDEN, INPUTS), dtype=float, storage="shared")
        sum1 = wp.tile_zeros(shape=(HIDDEN, HIDDEN), dtype=float, storage="shared")
        sum2 = wp.tile_zeros(shape=(HIDDEN, HIDDEN), dtype=float, storage="shared")
        sum3 = wp.tile_zeros(shape=(OUTPUTS, HIDDEN), dtype=float, storage="shared")
        # Each of these is a view of a tile one column wider, so that walking down a column crosses the
        # shared-memory banks (a row stride of 65 floats; one of 64 puts a column in one).
        padded_hidden = wp.tile_zeros(shape=(HIDDEN, wide_columns), dtype=float, storage="shared")
        hidden = wp.tile_view(padded_hidden, offset=(0, 0), shape=(HIDDEN, columns))  # scratch: products
        padded_h1 = wp.tile_zeros(shape=(HIDDEN, wide_columns), dtype=float, storage="shared")
        h1 = wp.tile_view(padded_h1, offset=(0, 0), shape=(HIDDEN, columns))
        padded_h2 = wp.tile_zeros(shape=(HIDDEN, wide_columns), dtype=float, storage="shared")
        h2 = wp.tile_view(padded_h2, offset=(0, 0), shape=(HIDDEN, columns))
        padded_h3 = wp.tile_zeros(shape=(HIDDEN, wide_columns), dtype=float, storage="shared")
        h3 = wp.tile_view(padded_h3, offset=(0, 0), shape=(HIDDEN, columns))
        input_rows = wp.tile_zeros(shape=(columns, INPUTS), dtype=float, storage="shared")
        y = wp.tile_zeros(shape=(OUTPUTS, columns), dtype=float, storage="shared")
        bias_sum0 = wp.tile_zeros(shape=(HIDDEN, columns), dtype=float)
        bias_sum1 = wp.tile_zeros(shape=(HIDDEN, columns), dtype=float)
        bias_sum2 = wp.tile_zeros(shape=(HIDDEN, columns), dtype=float)
        bias_sum3 = wp.tile_zeros(shape=(OUTPUTS, columns), dtype=float)
        squares = wp.tile_zeros(shape=(OUTPUTS, columns), dtype=float)
        for sub in range(sub_batches):
            offset = (block * sub_batches + sub) * columns
            x = wp.tile_load(features[m], shape=(INPUTS, columns), offset=(0, offset))
            wp.tile_matmul(weight0, x, hidden, beta=0.0)
            wp.tile_assign(h1, wp.tile_map(elu, hidden + bias0))
            wp.tile_matmul(weight1, h1, hidden, beta=0.0)
            wp.tile_assign(h2, wp.tile_map(elu, hidden + bias1))
            wp.tile_matmul(weight2, h2, hidden, beta=0.0)
            wp.tile_assign(h3, wp.tile_map(elu, hidden + bias2))
            wp.tile_matmul(weight3, h3, y, beta=0.0)
            error = y + bias3 - wp.tile_load(batch_targets[m], shape=(OUTPUTS, columns), offset=(0, offset))
            squares += wp.tile_map(wp.mul, error, error)
            output_gradient = error * (2.0 * scale)  # d loss / d y
            bias_sum3 += output_gradient
            wp.tile_assign(y, output_gradient)
            wp.tile_matmul(y, wp.tile_transpose(h3), sum3)
            wp.tile_matmul(wp.tile_transpose(weight3), y, hidden, beta=0.0)
            wp.tile_assign(h3, wp.tile_map(elu_gradient, hidden, h3))  # d loss / d pre-activation, in h3's place
            bias_sum2 += h3
            wp.tile_matmul(h3, wp.tile_transpose(h2), sum2)
            wp.tile_matmul(wp.tile_transpose(weight2), h3, hidden, beta=0.0)
            wp.tile_assign(h2, wp.tile_map(elu_gradient, hidden, h2))
            bias_sum1 += h2
            wp.tile_matmul(h2, wp.tile_transpose(h1), sum1)
            wp.tile_matmul(wp.tile_transpose(weight1), h2, hidden, beta=0.0)
            wp.tile_assign(h1, wp.tile_map(elu_gradient, hidden, h1))
            bias_sum0 += h1
            wp.tile_assign(input_rows, wp.tile_transpose(x))
            wp.tile_matmul(h1, input_rows, sum0)
            wp.tile_matmul(wp.tile_transpose(weight0), h1, x, beta=0.0)  # x is spent: its gradient takes its place
            wp.tile_store(feature_gradients[m], x, offset=(0, offset))
        wp.tile_atomic_add(loss[m], wp.tile_sum(squares) * scale)
        wp.tile_store(g0[block, m], sum0)
        wp.tile_store(g1[block, m], sum1)
        wp.tile_store(g2[block, m], sum2)
        wp.tile_store(g3[block, m], sum3)
        # the bias gradients' row sums, each through the scratch tiles (a register tile would take shared memory
        # of its own)
        wp.tile_assign(hidden, bias_sum0)
        wp.tile_store(c0[block, m], wp.tile_reshape(wp.tile_sum(hidden, axis=1), shape=(HIDDEN, 1)))
        wp.tile_assign(hidden, bias_sum1)
        wp.tile_store(c1[block, m], wp.tile_reshape(wp.tile_sum(hidden, axis=1), shape=(HIDDEN, 1)))
        wp.tile_assign(hidden, bias_sum2)
        wp.tile_store(c2[block, m], wp.tile_reshape(wp.tile_sum(hidden, axis=1), shape=(HIDDEN, 1)))
        wp.tile_assign(y, bias_sum3)
        wp.tile_store(c3[block, m], wp.tile_reshape(wp.tile_sum(y, axis=1), shape=(OUTPUTS, 1)))

    return train_tiles


@wp.kernel
def sum_partials(partials: wp.array2d[float], start: int, gradients: wp.array[float]):
    """gradients[start + i] += the sum over blocks b of partials[b, i], in the order of b."""
    i = wp.tid()
    total = float(0.0)
    for b in range(partials.shape[0]):
        total += partials[b, i]
    gradients[start + i] = gradients[start + i] + total


@wp.kernel
def scatter_code_gradients(samples: wp.array[wp.int64], pixels: int, feature_gradients: wp.array3d[float],
                           code_gradients: wp.array3d[float]):
    """Each sample's code gradient added to its pixel's, for every model."""
    i = wp.tid()
    pixel = int(samples[i] % wp.int64(pixels))
    for m in range(code_gradients.shape[0]):
        for k in range(CODE_SIZE):
            wp.atomic_add(code_gradients, m, pixel, k, feature_gradients[m, k, i])


@wp.kernel
def adam_flat(step: wp.array[wp.int64], batch: int, total: wp.int64, epochs: int, lr: wp.array[float],
              final_lr: float,
              params: wp.array[float], gradients: wp.array[float], first: wp.array[float], second: wp.array[float]):
    """Adam on every parameter; parameter i's learning rate decays geometrically from ``lr[i]`` (first epoch; each
    model's own) to ``final_lr`` (epoch ``epochs``); the gradient is zeroed once used."""
    i = wp.tid()
    t = step[0] + wp.int64(1)
    epoch = (step[0] * wp.int64(batch)) / total
    fraction = wp.min(float(epoch) / float(wp.max(epochs - 1, 1)), 1.0)
    start = lr[i]
    rate = start * wp.pow(final_lr / start, fraction)
    g = gradients[i]
    gradients[i] = 0.0
    m = ADAM_BETA1 * first[i] + (1.0 - ADAM_BETA1) * g
    v = ADAM_BETA2 * second[i] + (1.0 - ADAM_BETA2) * g * g
    first[i] = m
    second[i] = v
    correction1 = 1.0 - wp.pow(ADAM_BETA1, float(t))
    correction2 = 1.0 - wp.pow(ADAM_BETA2, float(t))
    params[i] = params[i] - rate * (m / correction1) / (wp.sqrt(v / correction2) + ADAM_EPSILON)


@wp.kernel
def advance(step: wp.array[wp.int64]):
    step[0] = step[0] + wp.int64(1)


def _feistel_half_bits(total: int) -> int:
    """Half the bits of the smallest power of 4 >= total (at least 1)."""
    return max(1, math.ceil(math.log2(max(total, 2)) / 2))


class _FlatParameters:
    """Codes (M, P, CODE_SIZE) and the eight weight arrays (M, rows, cols) of M models as views of one flat
    float32 buffer, with a gradient buffer of the same layout."""

    def __init__(self, models: list[NeuralDecoder], device):
        count, pixels = len(models), len(models[0].codes)
        shapes = [(count, pixels, CODE_SIZE)] + [(count, *shape) for shape in _WEIGHT_SHAPES]
        sizes = [int(np.prod(shape)) for shape in shapes]
        weights = [kernel_weights(m.weights) for m in models]
        host = np.concatenate([np.stack([m.codes for m in models]).ravel()]
                              + [np.stack([w[k] for w in weights]).ravel() for k in range(len(_WEIGHT_SHAPES))])
        self.size = int(sum(sizes))
        self.flat = wp.array(host.astype(np.float32), dtype=float, device=device)
        self.gradient = wp.zeros(self.size, dtype=float, device=device)
        self.shapes = shapes
        starts = np.concatenate([[0], np.cumsum(sizes)])
        self.views = [self.flat[int(a):int(b)].reshape(shape) for a, b, shape in zip(starts[:-1], starts[1:], shapes)]
        self.gradients = [self.gradient[int(a):int(b)].reshape(shape)
                          for a, b, shape in zip(starts[:-1], starts[1:], shapes)]
        self.starts = starts

    def block_partials(self, blocks: int, device) -> tuple[wp.array, list[wp.array]]:
        """A (blocks, weights) float32 buffer for each block's sums of the weights' gradients, in this layout's
        order after the codes, and its views for the eight weight arrays, each (blocks, M, rows, cols)."""
        weights = self.size - int(self.starts[1])
        partials = wp.zeros((blocks, weights), dtype=float, device=device)
        item = np.dtype(np.float32).itemsize
        views = []
        for a, shape in zip(self.starts[1:-1], self.shapes[1:]):
            rows, cols = shape[1:]
            strides = (weights * item, rows * cols * item, cols * item, item)
            views.append(wp.array(ptr=partials.ptr + (int(a) - int(self.starts[1])) * item, dtype=float,
                                  shape=(blocks, *shape), strides=strides, device=device))
        return partials, views

    def per_model(self, values) -> np.ndarray:
        """A float32 vector of this layout holding ``values[m]`` in every entry of model m."""
        values = np.asarray(values, np.float32)
        return np.concatenate([np.repeat(values, int(np.prod(shape[1:]))) for shape in self.shapes])

    def models(self, sees) -> list[NeuralDecoder]:
        """The M models (copies); w0 keeps the highlights' two columns where ``sees[m]``, else drops them."""
        arrays = [view.numpy() for view in self.views]
        models = []
        for m in range(len(arrays[0])):
            weights = [a[m].copy() for a in arrays[1:]]
            if not sees[m]:
                weights[0] = np.ascontiguousarray(weights[0][:, :NEURAL_INPUTS])
            models.append(NeuralDecoder(arrays[0][m].copy(), weights))
        return models

    def one_model(self, flat: np.ndarray, m: int) -> np.ndarray:
        """Model m's part of a buffer of this layout (parameters, a gradient, Adam's moments), in the layout of
        one model."""
        parts, start = [], 0
        for shape in self.shapes:
            size = int(np.prod(shape))
            parts.append(flat[start:start + size].reshape(shape[0], -1)[m])
            start += size
        return np.concatenate(parts)


@dataclass
class DecoderTrainer:
    """The device state of M decoders learning (M, n, P, 3) display-unit targets at (n, 3) lights from
    the ``used`` lights, ``batch`` samples a step, each from its own first learning rate (``lr``: one for all, or M);
    ``steps(k)`` runs k steps (a CUDA graph on CUDA). ``highlights``: (n, P) the Gaussians' luminance at each light
    and pixel (display units), or None; ``sees``: per model whether it takes them (default: every model when
    ``highlights`` is given). A model's w0 has 12 columns (given zero weights for the highlights' inputs) or, for a
    model that sees them, 14."""

    targets: np.ndarray
    lights: np.ndarray
    used: np.ndarray
    models: list[NeuralDecoder]
    batch: int
    epochs: int
    lr: float | tuple = 3e-3
    final_lr: float = 3e-4
    seed: int = 0
    device: object = None
    tile: tuple[int, int, int] = LEARNED_TILE
    highlights: np.ndarray | None = None
    sees: tuple | None = None

    def __post_init__(self):
        device = self.device = wp.get_device(self.device)
        count, n, pixels, _ = self.targets.shape
        self.sees = _seeing_models(count, self.highlights, self.sees)
        for m, model in enumerate(self.models):
            if sees_highlights(model.weights) and not self.sees[m]:
                raise ValueError(f"model {m}'s decoder takes the highlights' inputs but does not see the highlights")
        self.highlight_array = wp.empty((0, 0), dtype=float, device=device)  # read by no model
        if self.highlights is not None:
            highlights = np.asarray(self.highlights, np.float32)
            if highlights.shape != (n, pixels):
                raise ValueError(f"highlights must be ({n}, {pixels}), got shape {highlights.shape}")
            if any(self.sees):
                self.highlight_array = wp.array(np.ascontiguousarray(highlights), dtype=float, device=device)
        self.sees_array = wp.array(np.asarray(self.sees, np.int32), dtype=wp.int32, device=device)
        self.pixels = pixels
        self.total = len(self.used) * pixels
        columns, sub_batches, self.threads = self.tile
        unit = columns * sub_batches  # samples per tile block
        self.batch = max(unit, -(-int(self.batch) // unit) * unit)
        self.blocks = self.batch // unit
        self.kernel = make_train_tiles(columns, sub_batches)
        self.params = _FlatParameters(self.models, device)
        self.partials, self.partial_views = self.params.block_partials(self.blocks, device)
        self.rates = np.broadcast_to(np.asarray(self.lr, np.float64), (count,)).copy()
        if not (np.all(np.isfinite(self.rates)) and np.all(self.rates > 0)):
            raise ValueError(f"learning rates must be > 0, got {self.lr}")
        self.rate_array = wp.array(self.params.per_model(self.rates), dtype=float, device=device)
        self.first = wp.zeros(self.params.size, dtype=float, device=device)
        self.second = wp.zeros(self.params.size, dtype=float, device=device)
        self.step = wp.zeros(1, dtype=wp.int64, device=device)
        self.loss = wp.zeros((count, 1), dtype=float, device=device)
        self.target_array = wp.array(np.ascontiguousarray(self.targets, np.float32), dtype=wp.vec3, device=device)
        self.light_array = wp.array(np.asarray(self.lights, np.float32), dtype=wp.vec3, device=device)
        self.used_array = wp.array(np.asarray(self.used, np.int32), dtype=wp.int32, device=device)
        self.samples = wp.zeros(self.batch, dtype=wp.int64, device=device)
        self.features = wp.zeros((count, INPUTS, self.batch), dtype=float, device=device)
        self.batch_targets = wp.zeros((count, OUTPUTS, self.batch), dtype=float, device=device)
        self.feature_gradients = wp.zeros((count, INPUTS, self.batch), dtype=float, device=device)
        self.half_bits = _feistel_half_bits(self.total)
        self.graph = None

    @property
    def steps_per_epoch(self) -> int:
        return -(-self.total // self.batch)

    def launches(self) -> list[tuple[str, Callable[[], None]]]:
        """The step's launches in order, each as (its kernel's name, a function that queues it)."""
        device, p, count = self.device, self.params, len(self.models)
        return [
            ("gather_batch", lambda: wp.launch(
                gather_batch, dim=self.batch,
                inputs=[self.step, self.batch, self.total, self.half_bits, self.seed, self.used_array, self.pixels,
                        p.views[0], self.light_array, self.target_array, self.highlight_array, self.sees_array],
                outputs=[self.samples, self.features, self.batch_targets], device=device)),
            ("train_tiles", lambda: wp.launch_tiled(
                self.kernel, dim=[count, self.blocks],
                inputs=[self.features, self.batch_targets, 1.0 / self.batch, *p.views[1:], *self.partial_views],
                outputs=[self.feature_gradients, self.loss], block_dim=self.threads, device=device)),
            ("sum_partials", lambda: wp.launch(
                sum_partials, dim=self.partials.shape[1], inputs=[self.partials, int(p.starts[1])],
                outputs=[p.gradient], device=device)),
            ("scatter_code_gradients", lambda: wp.launch(
                scatter_code_gradients, dim=self.batch, inputs=[self.samples, self.pixels, self.feature_gradients],
                outputs=[p.gradients[0]], device=device)),
            ("adam_flat", lambda: wp.launch(
                adam_flat, dim=p.size,
                inputs=[self.step, self.batch, self.total, self.epochs, self.rate_array, self.final_lr],
                outputs=[p.flat, p.gradient, self.first, self.second], device=device)),
            ("advance", lambda: wp.launch(advance, dim=1, outputs=[self.step], device=device)),
        ]

    def launch_step(self) -> None:
        """Queue one training step."""
        for _, launch in self.launches():
            launch()

    def steps(self, count: int) -> None:
        """Run ``count`` training steps (queued; ``losses`` or ``result`` waits for them)."""
        if self.device.is_cuda and self.graph is None and count > 1:
            self.launch_step()  # loads the modules outside the capture
            count -= 1
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self.launch_step()
            self.graph = capture.graph
        for _ in range(count):
            if self.graph is not None:
                wp.capture_launch(self.graph)
            else:
                self.launch_step()

    def losses(self) -> np.ndarray:
        """(M,) the loss summed over the steps since the last call (a mean squared error a step), then zeroed."""
        values = self.loss.numpy()[:, 0].astype(np.float64)
        self.loss.zero_()
        return values

    def result(self) -> list[NeuralDecoder]:
        """The models as they are: w0 with 14 columns for a model that sees the highlights, else 12."""
        return self.params.models(self.sees)

    def keep(self, m: int, used: np.ndarray | None = None) -> DecoderTrainer:
        """A trainer of model m alone that goes on where this one is (parameters, Adam's moments, step);
        ``used``: the lights it learns from from now on (default this trainer's), its step counter moved to
        the same epoch of the new sample count, so the learning rate's schedule goes on from there."""
        wp.synchronize_device(self.device)
        models = self.result()
        alone = DecoderTrainer(self.targets[m:m + 1], self.lights, self.used if used is None else np.asarray(used),
                               [models[m]], self.batch, self.epochs, float(self.rates[m]), self.final_lr, self.seed,
                               self.device, self.tile, self.highlights, self.sees[m:m + 1])
        for mine, theirs in ((self.first, alone.first), (self.second, alone.second)):
            theirs.assign(self.params.one_model(mine.numpy(), m))
        step = int(self.step.numpy()[0])
        epochs_done = round(step / self.steps_per_epoch)
        alone.step.assign(np.array([step if used is None else epochs_done * alone.steps_per_epoch], np.int64))
        return alone


def _seeing_models(count: int, highlights, sees) -> tuple[bool, ...]:
    """Per model whether it sees the highlights: ``sees`` (one bool per model), by default every model when
    ``highlights`` is given and none otherwise (ValueError for a model that sees them without them)."""
    if sees is None:
        return (highlights is not None,) * count
    sees = tuple(bool(s) for s in np.asarray(sees, dtype=bool).reshape(-1))
    if len(sees) != count:
        raise ValueError(f"sees must hold one flag for each of the {count} models, got {len(sees)}")
    if any(sees) and highlights is None:
        raise ValueError("a model that sees the highlights trains with them: pass highlights")
    return sees


def train_decoders(targets: np.ndarray, lights: np.ndarray, *, device=None, epochs: int = 40, batch: int = 1 << 16,
                   lr: float | tuple = 3e-3, final_lr: float = 3e-4, seed: int = 0, seconds: float | None = None,
                   log=None,
                   used: np.ndarray | None = None,
                   initial: list[NeuralDecoder] | None = None, settle=None,
                   settle_epoch: int = 0,
                   settle_used: np.ndarray | None = None,
                   highlights: np.ndarray | None = None,
                   sees=None, stop_when_settled: bool = False) -> tuple[list[NeuralDecoder], np.ndarray]:
    """Fit M decoders (codes and weights) to (M, n, P, 3) display-unit targets at (n, 3) lights, side by side: Adam on
    the mean squared error over shuffled (light, pixel) samples, ``batch`` a step, the learning rate decaying
    geometrically from ``lr`` (one for every model, or one each) to ``final_lr`` over ``epochs`` (or until
    ``seconds`` of training have passed; compiling the kernels and ``settle``'s scoring are not counted). ``used``:
    the lights learned from (default all; the others' targets are never read). ``initial``: models to go on training
    (default: ``initial_model`` of each model's used targets). ``settle(models)``, called after every
    ``settle_epoch`` epochs with the models as they are while more than one learns, may return the index of the one
    model that goes on (the others stop there: their loss is NaN from then on) or None (all go on, to be asked
    again); the one that goes on learns from ``settle_used`` lights from then on (default ``used``).
    ``highlights``: (n, P) float32 the Gaussians' luminance at each light and pixel (display units); ``sees``: one
    bool per model, whether it takes them as inputs (default: every model when ``highlights`` is given). A model
    that sees them is returned with w0 of 14 columns (an initial one of 12 starts with zero weights for them), the
    others with 12. ``stop_when_settled``: once ``settle`` has named one, every model stops there (a check whose
    winner will not be kept).
    Returns the models and the (epochs run, M) mean loss of each epoch."""
    device = wp.get_device(device)
    targets = np.ascontiguousarray(targets, np.float32)
    count, n, pixels, _ = targets.shape
    used = used_lights(n, pixels, used)
    settle_used = None if settle_used is None else used_lights(n, pixels, settle_used)
    models = [initial_model(targets[m][used], seed=seed) for m in range(count)] if initial is None else list(initial)
    if len(models) != count or any(m.codes.shape != (pixels, CODE_SIZE) for m in models):
        raise ValueError(f"initial models must be {count}, each with codes of {pixels} pixels")
    trainer = DecoderTrainer(targets, lights, used, models, batch, epochs, lr, final_lr, seed, device,
                             highlights=highlights, sees=sees)
    trainer.steps(1)  # compiles and loads the kernels (minutes on a fresh CUDA machine): not training time
    wp.synchronize_device(device)
    started = time.perf_counter()
    history, going_on, stopped = [], list(range(count)), None
    for epoch in range(epochs):
        trainer.steps(trainer.steps_per_epoch - (epoch == 0))
        row = np.full(count, np.nan)
        row[going_on] = trainer.losses() / trainer.steps_per_epoch  # waits for the epoch's steps
        history.append(row)
        if log:
            log(f"epoch {epoch + 1}/{epochs}: mse {np.nanmean(row):.3e} ({time.perf_counter() - started:.1f} s)")
        if seconds is not None and time.perf_counter() - started > seconds:
            break
        if (settle is not None and settle_epoch > 0 and (epoch + 1) % settle_epoch == 0 and len(going_on) > 1
                and epoch + 1 < epochs):
            scoring = time.perf_counter()
            kept = settle(trainer.result())
            if kept is not None and stop_when_settled:
                break
            if kept is not None:
                stopped = trainer.result()
                trainer, going_on = trainer.keep(int(kept), used=settle_used), [int(kept)]
            # scoring is not training: on a fresh machine it compiles the decoding kernels, seconds that the
            # training clock would otherwise lose (the dome sample's first fit stopped 1 epoch after settling)
            started += time.perf_counter() - scoring
    models = trainer.result()
    if stopped is not None:
        stopped[going_on[0]] = models[0]
        models = stopped
    return models, np.asarray(history)


def train_decoder(targets: np.ndarray, lights: np.ndarray, *, initial: NeuralDecoder | None = None,
                  **options) -> tuple[NeuralDecoder, list[float]]:
    """``train_decoders`` for one model: (n, P, 3) targets (and ``highlights``, ``sees``: passed on in ``options``);
    returns the model and its mean loss per epoch."""
    models, history = train_decoders(np.asarray(targets)[None], lights,
                                      initial=None if initial is None else [initial], **options)
    return models[0], [float(v) for v in history[:, 0]]
