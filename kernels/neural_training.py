"""Training the learned residual's decoder (``kernels.neural``) on the device: a fused step with a
hand-written adjoint, Adam on the device, samples shuffled on the device, a CUDA graph per step.

One step is three launches, none of which needs a host value, so a CUDA graph replays it:

1. ``gather_batch``: ``batch`` (light, pixel) samples of the current epoch's shuffle (a keyed Feistel
   permutation of the used samples, ``shuffled_sample``): their pixels, and for every model the features that
   do not belong to the pixel [light direction, sqrt(g), g] (g the Gaussians' luminance for a model that sees the
   highlights, else 0) and the targets; its first thread writes the step's number for Adam;
2. ``train_tiles`` (``make_train_tiles``; on a GPU with tensor cores ``kernels.neural_tensor_cores``, the same work
   with TF32 products): per tile of samples, the pixels' codes gathered, the MLP forward, the
   squared error and the whole backward pass (tile matrix products); the codes' gradients added to their
   pixels' (atomic adds); each block's sums of the weights' and biases' gradients stored as its partial sums;
3. ``adam_flat``: Adam over every parameter of every model (codes and weights are views of one flat
   buffer), the learning rate of the step's epoch; a weight's gradient is the sum of the blocks' partial sums, added
   block by block (the same sum in every run); it zeroes the gradients it used, and its first thread advances the
   step counter.

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

from warp_highlights.model.config import LEARNED_MATHDX, LEARNED_TENSOR_CORES, LEARNED_TENSOR_PASSES, LEARNED_TILE
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
from .neural_tensor_cores import MIN_ARCH, SAMPLES_PER_PASS, THREADS, make_tensor_core_step

__all__ = ["DecoderTrainer", "LIGHT_ROWS", "make_train_tiles", "elu_gradient", "has_tensor_cores", "shuffled_sample",
           "train_decoder", "train_decoders"]

_MODULE_OPTIONS = {"enable_backward": False, "enable_mathdx_gemm": LEARNED_MATHDX, "max_unroll": 0}
# the hand-written adjoint is the only one: no tape, no generated backward code to compile
wp.set_module_options(_MODULE_OPTIONS)

ADAM_BETA1 = 0.9
ADAM_BETA2 = 0.999
ADAM_EPSILON = 1e-8
"""Adam's constants: those of ``warp.optim.Adam`` and PyTorch's default."""

LIGHT_ROWS = INPUTS - CODE_SIZE
"""The features a sample takes from its light rather than its pixel: direction (3), sqrt(g), g."""

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
                 used: wp.array[wp.int32], pixels: int, lights: wp.array[wp.vec3],
                 targets: wp.array3d[wp.vec3], highlights: wp.array2d[float], sees: wp.array[wp.int32],
                 samples: wp.array[wp.int64], pixel_index: wp.array[wp.int32], light_features: wp.array3d[float],
                 batch_targets: wp.array3d[float], adam_step: wp.array[wp.int64]):
    """Sample i of this step: its (used light, pixel) index into ``samples``, its pixel into ``pixel_index``, and
    for each model m its light's features (LIGHT_ROWS, batch): the direction, then sqrt(g), g for g =
    max(highlights[light, pixel], 0) (display units) where ``sees[m]`` is not 0, else 0 and 0 (``highlights`` is
    then not read: it may be empty); and its targets (OUTPUTS, batch). Thread 0 writes the step's number for Adam
    (1-based) into ``adam_step``."""
    i = wp.tid()
    if i == 0:
        adam_step[0] = step[0] + wp.int64(1)
    position = step[0] * wp.int64(batch) + wp.int64(i)
    epoch = position / total
    sample = shuffled_sample(position - epoch * total, total, seed * 65599 + int(epoch), half_bits)
    light = used[int(sample / wp.int64(pixels))]
    pixel = int(sample % wp.int64(pixels))
    samples[i] = wp.int64(light) * wp.int64(pixels) + wp.int64(pixel)
    pixel_index[i] = pixel
    direction = lights[light]
    for m in range(light_features.shape[0]):
        for k in range(3):
            light_features[m, k, i] = direction[k]
        g = float(0.0)
        if sees[m] != 0:
            g = wp.max(highlights[light, pixel], 0.0)
        light_features[m, HIGHLIGHT_ROW - CODE_SIZE, i] = wp.sqrt(g)
        light_features[m, HIGHLIGHT_ROW - CODE_SIZE + 1, i] = g
        target = targets[m, light, pixel]
        for c in range(OUTPUTS):
            batch_targets[m, c, i] = target[c]


@functools.cache
def make_train_tiles(columns: int, sub_batches: int, threads: int = 0, blocks_per_sm: int = 0):
    """The fused step's kernel for tiles of ``columns`` samples, each tile block (of ``threads`` threads) looping
    over ``sub_batches`` of them; ``blocks_per_sm`` > 0 asks the compiler for registers enough for that many
    blocks on a multiprocessor (CUDA's launch bounds), 0 leaves it free. The weights' and biases' gradients add
    up in the block and are stored once a block as its partial sums (``adam_flat`` adds them up), so no atomic
    add serialises the launch and the sum is the same in every run. Shared memory is three allocations (arenas),
    every tile a view at a fixed offset into one, so that a thread keeps three base addresses rather than one for
    each tile (registers decide how many blocks an SM runs). A layer's gradient takes its activation's place (the
    activation is spent once its weights' gradient is summed); each activation carries a row of ones, so its
    weights' gradient product gives the bias's gradient too, in one more column. Rows of activations are one
    column wider than they are used (a row stride of ``columns`` + 1), so that walking down a column, as the
    weights' gradients' products do through a transposed view, crosses the shared-memory banks."""

    wide = columns + 1
    H, I, O, C, L = HIDDEN, INPUTS, OUTPUTS, CODE_SIZE, LIGHT_ROWS
    G = H + 1  # an activation's rows and a constant row of ones: its weights' and its bias' gradients in one product
    I1 = I + 1  # the inputs and a constant one
    activation_rows = H + 3 * G + O + I1  # hidden (products), h1, h2, h3 (each with its ones row), y, x (and ones)
    weight_rows = 2 * (2 * H + O)  # w1, w2, w3 (each with its bias as the last column), then their gradients' sums
    input_rows = 2 * H + columns  # w0 (and b0), its gradient's sum (and b0's), x with its samples as rows (and ones)
    bounds = {"launch_bounds": (threads, blocks_per_sm)} if blocks_per_sm > 0 else {}

    @wp.kernel(module="unique", module_options=_MODULE_OPTIONS, **bounds)
    def train_tiles(light_features: wp.array3d[float], pixel_index: wp.array[wp.int32], codes: wp.array3d[float],
                    code_gradients: wp.array3d[float], batch_targets: wp.array3d[float], scale: float,
                    w0: wp.array3d[float], b0: wp.array3d[float], w1: wp.array3d[float], b1: wp.array3d[float],
                    w2: wp.array3d[float], b2: wp.array3d[float], w3: wp.array3d[float], b3: wp.array3d[float],
                    g0: wp.array4d[float], c0: wp.array4d[float], g1: wp.array4d[float], c1: wp.array4d[float],
                    g2: wp.array4d[float], c2: wp.array4d[float], g3: wp.array4d[float], c3: wp.array4d[float],
                    loss: wp.array2d[float]):
        """Model m, ``sub_batches`` tiles of ``columns`` samples: loss += scale * sum |y - t|^2; the gradients of
        that term stored in g*[block, m] (weights) and c*[block, m] (biases), and added to ``code_gradients``
        (M, CODE_SIZE, P: a transposed view) at the samples' pixels. ``codes``: (M, CODE_SIZE, P), a transposed
        view."""
        m, block = wp.tid()
        activations = wp.tile_zeros(shape=(activation_rows, wide), dtype=float, storage="shared")
        weights = wp.tile_zeros(shape=(weight_rows, G), dtype=float, storage="shared")
        inputs = wp.tile_zeros(shape=(input_rows, I1), dtype=float, storage="shared")
        hidden = wp.tile_view(activations, offset=(0, 0), shape=(H, columns))  # scratch: products
        h1 = wp.tile_view(activations, offset=(H, 0), shape=(H, columns))
        h2 = wp.tile_view(activations, offset=(H + G, 0), shape=(H, columns))
        h3 = wp.tile_view(activations, offset=(H + 2 * G, 0), shape=(H, columns))
        h1_ones = wp.tile_view(activations, offset=(H, 0), shape=(G, columns))  # h1 and its row of ones
        h2_ones = wp.tile_view(activations, offset=(H + G, 0), shape=(G, columns))
        h3_ones = wp.tile_view(activations, offset=(H + 2 * G, 0), shape=(G, columns))
        x_ones = wp.tile_view(activations, offset=(H + 3 * G + O, 0), shape=(I1, columns))
        # as a layer's right operand the ones add the bias (the weights' last column); seen with their samples as
        # rows, they make the gradients' sums give the bias's gradient in their last column
        h1_rows = wp.tile_transpose(h1_ones)
        h2_rows = wp.tile_transpose(h2_ones)
        h3_rows = wp.tile_transpose(h3_ones)
        for layer in range(wp.static(3)):  # the rows of ones: set once, never overwritten
            wp.tile_assign(wp.tile_view(activations, offset=(H + H + layer * G, 0), shape=(1, columns)),
                           wp.tile_ones(shape=(1, columns), dtype=float))
        wp.tile_assign(wp.tile_view(activations, offset=(H + 3 * G + O + I, 0), shape=(1, columns)),
                       wp.tile_ones(shape=(1, columns), dtype=float))
        y = wp.tile_view(activations, offset=(H + 3 * G, 0), shape=(O, columns))
        x = wp.tile_view(activations, offset=(H + 3 * G + O, 0), shape=(I, columns))
        x_codes = wp.tile_view(activations, offset=(H + 3 * G + O, 0), shape=(C, columns))
        x_lights = wp.tile_view(activations, offset=(H + 3 * G + O + C, 0), shape=(L, columns))
        weight1 = wp.tile_view(weights, offset=(0, 0), shape=(H, H))
        weight2 = wp.tile_view(weights, offset=(H, 0), shape=(H, H))
        weight3 = wp.tile_view(weights, offset=(2 * H, 0), shape=(O, H))
        layer1 = wp.tile_view(weights, offset=(0, 0), shape=(H, G))  # [w1 | b1]
        layer2 = wp.tile_view(weights, offset=(H, 0), shape=(H, G))
        layer3 = wp.tile_view(weights, offset=(2 * H, 0), shape=(O, G))
        sum1 = wp.tile_view(weights, offset=(2 * H + O, 0), shape=(H, G))
        sum2 = wp.tile_view(weights, offset=(3 * H + O, 0), shape=(H, G))
        sum3 = wp.tile_view(weights, offset=(4 * H + O, 0), shape=(O, G))
        weight0 = wp.tile_view(inputs, offset=(0, 0), shape=(H, I))
        layer0 = wp.tile_view(inputs, offset=(0, 0), shape=(H, I1))  # [w0 | b0]
        sum0 = wp.tile_view(inputs, offset=(H, 0), shape=(H, I1))
        x_rows = wp.tile_view(inputs, offset=(2 * H, 0), shape=(columns, I))  # x with its samples as rows, then ones
        wp.tile_assign(wp.tile_view(inputs, offset=(2 * H, I), shape=(columns, 1)),
                       wp.tile_ones(shape=(columns, 1), dtype=float))
        x_rows_ones = wp.tile_view(inputs, offset=(2 * H, 0), shape=(columns, I1))
        wp.tile_assign(weight0, wp.tile_load(w0[m], shape=(H, I), storage="register"))
        wp.tile_assign(weight1, wp.tile_load(w1[m], shape=(H, H), storage="register"))
        wp.tile_assign(weight2, wp.tile_load(w2[m], shape=(H, H), storage="register"))
        wp.tile_assign(weight3, wp.tile_load(w3[m], shape=(O, H), storage="register"))
        wp.tile_assign(wp.tile_view(inputs, offset=(0, I), shape=(H, 1)), wp.tile_load(b0[m], shape=(H, 1),
                                                                                    storage="register"))
        wp.tile_assign(wp.tile_view(weights, offset=(0, H), shape=(H, 1)), wp.tile_load(b1[m], shape=(H, 1),
                                                                                     storage="register"))
        wp.tile_assign(wp.tile_view(weights, offset=(H, H), shape=(H, 1)), wp.tile_load(b2[m], shape=(H, 1),
                                                                                     storage="register"))
        wp.tile_assign(wp.tile_view(weights, offset=(2 * H, H), shape=(O, 1)), wp.tile_load(b3[m], shape=(O, 1),
                                                                                         storage="register"))
        squares = wp.tile_zeros(shape=(O, columns), dtype=float)
        for sub in range(sub_batches):
            offset = (block * sub_batches + sub) * columns
            pixels = wp.tile_load(pixel_index, shape=(columns,), offset=(offset,), storage="shared")
            wp.tile_assign(x_codes, wp.tile_load_indexed(codes[m], pixels, shape=(C, columns), axis=1))
            wp.tile_assign(x_lights, wp.tile_load(light_features[m], shape=(L, columns), offset=(0, offset),
                                                  storage="register"))
            wp.tile_matmul(layer0, x_ones, hidden, beta=0.0)
            wp.tile_assign(h1, wp.tile_map(elu, hidden))
            wp.tile_matmul(layer1, h1_ones, hidden, beta=0.0)
            wp.tile_assign(h2, wp.tile_map(elu, hidden))
            wp.tile_matmul(layer2, h2_ones, hidden, beta=0.0)
            wp.tile_assign(h3, wp.tile_map(elu, hidden))
            wp.tile_matmul(layer3, h3_ones, y, beta=0.0)
            error = y - wp.tile_load(batch_targets[m], shape=(O, columns), offset=(0, offset))
            squares += wp.tile_map(wp.mul, error, error)
            wp.tile_assign(y, error * (2.0 * scale))  # d loss / d y
            wp.tile_matmul(y, h3_rows, sum3)
            wp.tile_matmul(wp.tile_transpose(weight3), y, hidden, beta=0.0)
            wp.tile_assign(h3, wp.tile_map(elu_gradient, hidden, h3))  # d loss / d layer 3's pre-activation
            wp.tile_matmul(h3, h2_rows, sum2)
            wp.tile_matmul(wp.tile_transpose(weight2), h3, hidden, beta=0.0)
            wp.tile_assign(h2, wp.tile_map(elu_gradient, hidden, h2))
            wp.tile_matmul(h2, h1_rows, sum1)
            wp.tile_matmul(wp.tile_transpose(weight1), h2, hidden, beta=0.0)
            wp.tile_assign(h1, wp.tile_map(elu_gradient, hidden, h1))
            wp.tile_assign(x_rows, wp.tile_transpose(x))
            wp.tile_matmul(h1, x_rows_ones, sum0)
            wp.tile_matmul(wp.tile_transpose(weight0), h1, x, beta=0.0)  # x is spent: its gradient takes its place
            wp.tile_atomic_add_indexed(code_gradients[m], pixels, x_codes * 1.0, axis=1)
        wp.tile_atomic_add(loss[m], wp.tile_sum(squares) * scale)
        wp.tile_store(g0[block, m], wp.tile_view(sum0, offset=(0, 0), shape=(H, I)))
        wp.tile_store(c0[block, m], wp.tile_view(sum0, offset=(0, I), shape=(H, 1)))
        wp.tile_store(g1[block, m], wp.tile_view(sum1, offset=(0, 0), shape=(H, H)))
        wp.tile_store(c1[block, m], wp.tile_view(sum1, offset=(0, H), shape=(H, 1)))
        wp.tile_store(g2[block, m], wp.tile_view(sum2, offset=(0, 0), shape=(H, H)))
        wp.tile_store(c2[block, m], wp.tile_view(sum2, offset=(0, H), shape=(H, 1)))
        wp.tile_store(g3[block, m], wp.tile_view(sum3, offset=(0, 0), shape=(O, H)))
        wp.tile_store(c3[block, m], wp.tile_view(sum3, offset=(0, H), shape=(O, 1)))

    return train_tiles


@wp.kernel
def adam_flat(adam_step: wp.array[wp.int64], batch: int, total: wp.int64, epochs: int, partials: wp.array2d[float],
              start: int, log_lr: wp.array[float], log_final_lr: float, params: wp.array[float],
              gradients: wp.array[float], first: wp.array[float], second: wp.array[float], step: wp.array[wp.int64]):
    """Adam's step t = ``adam_step[0]`` (1-based) on every parameter: parameter i >= ``start`` (a weight) takes as its
    gradient the sum over blocks b of ``partials[b, i - start]``; parameter i's learning rate
    decays geometrically from exp(``log_lr[i]``) (first epoch; each model's own) to exp(``log_final_lr``) (epoch
    ``epochs`` - 1) at the epoch of step t - 1 (``batch`` samples a step, ``total`` an epoch); bias corrections
    1 - beta^t; the gradient is zeroed once used. Thread 0 sets the step counter ``step`` to t (no other thread
    reads it). Thread k takes parameter k + ``start`` (modulo their number): the weights, whose sums take longest,
    start first."""
    k = wp.tid()
    i = k + start
    if i >= params.shape[0]:
        i -= params.shape[0]
    t = adam_step[0]
    epoch = ((t - wp.int64(1)) * wp.int64(batch)) / total
    fraction = wp.min(float(epoch) / float(wp.max(epochs - 1, 1)), 1.0)
    rate = wp.exp((1.0 - fraction) * log_lr[i] + fraction * log_final_lr)
    g = gradients[i]
    if i >= start:  # four sums side by side (their loads in flight together), then added: the same order every run
        column = i - start
        blocks = partials.shape[0]
        sums = wp.vec4(0.0)
        b = int(0)
        while b + 4 <= blocks:
            sums += wp.vec4(partials[b, column], partials[b + 1, column], partials[b + 2, column],
                            partials[b + 3, column])
            b += 4
        while b < blocks:
            sums[0] = sums[0] + partials[b, column]
            b += 1
        g += (sums[0] + sums[1]) + (sums[2] + sums[3])
    gradients[i] = 0.0
    m = ADAM_BETA1 * first[i] + (1.0 - ADAM_BETA1) * g
    v = ADAM_BETA2 * second[i] + (1.0 - ADAM_BETA2) * g * g
    first[i] = m
    second[i] = v
    correction1 = 1.0 - wp.pow(ADAM_BETA1, float(t))
    correction2 = 1.0 - wp.pow(ADAM_BETA2, float(t))
    params[i] = params[i] - rate * (m / correction1) / (wp.sqrt(v / correction2) + ADAM_EPSILON)
    if k == 0:
        step[0] = t


def has_tensor_cores(device) -> bool:
    """Whether ``device`` trains on tensor cores by default: ``LEARNED_TENSOR_CORES`` and a CUDA GPU of compute
    capability 8.0 or newer."""
    device = wp.get_device(device)
    return bool(LEARNED_TENSOR_CORES) and device.is_cuda and device.arch >= MIN_ARCH


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

    def codes_by_row(self, gradient: bool = False) -> wp.array:
        """The codes (or their gradients), (M, P, CODE_SIZE), as an (M, CODE_SIZE, P) view: a code's number k of
        every pixel along a row, as the training tiles gather them."""
        codes = (self.gradients if gradient else self.views)[0]
        count, pixels, size = codes.shape
        item = np.dtype(np.float32).itemsize
        return wp.array(ptr=codes.ptr, dtype=float, shape=(count, size, pixels),
                        strides=(pixels * size * item, item, size * item), device=codes.device)

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
    model that sees them, 14. ``tensor_cores``: whether the step's products run on the GPU's tensor cores (TF32
    inputs, float32 sums; default ``has_tensor_cores``), in blocks of ``tensor_passes`` passes of 128 samples; else
    Warp's tile products in ``tile`` shapes."""

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
    tile: tuple[int, ...] = LEARNED_TILE
    highlights: np.ndarray | None = None
    sees: tuple | None = None
    tensor_cores: bool | None = None
    tensor_passes: int = LEARNED_TENSOR_PASSES

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
        if self.tensor_cores is None:
            self.tensor_cores = has_tensor_cores(device)
        if self.tensor_cores:
            if not (device.is_cuda and device.arch >= MIN_ARCH):
                raise ValueError(f"tensor cores need a CUDA GPU of compute capability 8.0 or newer, not {device}")
            if int(self.tensor_passes) < 1:
                raise ValueError(f"tensor_passes must be >= 1, got {self.tensor_passes}")
            unit = SAMPLES_PER_PASS * int(self.tensor_passes)
            self.threads = THREADS
            self.kernel = make_tensor_core_step(int(self.tensor_passes))
        else:
            columns, sub_batches, self.threads, *bounds = self.tile
            unit = columns * sub_batches  # samples per tile block
            self.kernel = make_train_tiles(columns, sub_batches, self.threads, *bounds)
        self.batch = max(unit, -(-int(self.batch) // unit) * unit)
        self.blocks = self.batch // unit
        self.params = _FlatParameters(self.models, device)
        self.partials, self.partial_views = self.params.block_partials(self.blocks, device)
        self.rates = np.broadcast_to(np.asarray(self.lr, np.float64), (count,)).copy()
        if not (np.all(np.isfinite(self.rates)) and np.all(self.rates > 0)):
            raise ValueError(f"learning rates must be > 0, got {self.lr}")
        self.log_rates = wp.array(np.log(self.params.per_model(self.rates)), dtype=float, device=device)
        self.adam_step = wp.zeros(1, dtype=wp.int64, device=device)  # the step's number for Adam (1-based)
        self.first = wp.zeros(self.params.size, dtype=float, device=device)
        self.second = wp.zeros(self.params.size, dtype=float, device=device)
        self.step = wp.zeros(1, dtype=wp.int64, device=device)
        self.loss = wp.zeros((count, 1), dtype=float, device=device)
        self.target_array = wp.array(np.ascontiguousarray(self.targets, np.float32), dtype=wp.vec3, device=device)
        self.light_array = wp.array(np.asarray(self.lights, np.float32), dtype=wp.vec3, device=device)
        self.used_array = wp.array(np.asarray(self.used, np.int32), dtype=wp.int32, device=device)
        self.samples = wp.zeros(self.batch, dtype=wp.int64, device=device)
        self.pixel_index = wp.zeros(self.batch, dtype=wp.int32, device=device)
        self.light_features = wp.zeros((count, LIGHT_ROWS, self.batch), dtype=float, device=device)
        self.batch_targets = wp.zeros((count, OUTPUTS, self.batch), dtype=float, device=device)
        self.codes_by_row = self.params.codes_by_row()
        self.code_gradients_by_row = self.params.codes_by_row(gradient=True)
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
                        self.light_array, self.target_array, self.highlight_array, self.sees_array],
                outputs=[self.samples, self.pixel_index, self.light_features, self.batch_targets, self.adam_step],
                device=device)),
            ("train_tiles", lambda: wp.launch_tiled(
                self.kernel, dim=[count, self.blocks],
                inputs=[self.light_features, self.pixel_index, self.codes_by_row, self.code_gradients_by_row,
                        self.batch_targets, 1.0 / self.batch, *p.views[1:], *self.partial_views],
                outputs=[self.loss], block_dim=self.threads, device=device)),
            ("adam_flat", lambda: wp.launch(
                adam_flat, dim=p.size,
                inputs=[self.adam_step, self.batch, self.total, self.epochs, self.partials, int(p.starts[1]),
                        self.log_rates, math.log(self.final_lr)],
                outputs=[p.flat, p.gradient, self.first, self.second, self.step], device=device)),
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

    def step_gradients(self) -> list[np.ndarray]:
        """The gradients a step's training launch leaves for Adam (after ``launches()`` up to ``adam_flat``), float64:
        the codes' (M, P, CODE_SIZE), then each weight array's (M, rows, cols), the sum of the blocks' partial sums."""
        flat = self.params.gradient.numpy().astype(np.float64)
        flat[int(self.params.starts[1]):] += self.partials.numpy().astype(np.float64).sum(axis=0)
        starts = self.params.starts
        return [flat[int(a):int(b)].reshape(shape) for a, b, shape in zip(starts[:-1], starts[1:], self.params.shapes)]

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
                               self.device, self.tile, self.highlights, self.sees[m:m + 1], self.tensor_cores,
                               self.tensor_passes)
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
                   sees=None, stop_when_settled: bool = False,
                   tensor_cores: bool | None = None) -> tuple[list[NeuralDecoder], np.ndarray]:
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
    winner will not be kept). ``tensor_cores``: ``DecoderTrainer``'s.
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
                             highlights=highlights, sees=sees, tensor_cores=tensor_cores)
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
