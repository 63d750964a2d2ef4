"""The learned residual (``kernels.neural``'s model) trained and decoded on the CPU in NumPy float32.

The forward and backward passes are written out as matrix products over a batch of (light, pixel)
samples (rows), the rows split among one thread per core, each with BLAS on one thread
(``model.threads.blas_on_one_thread``), the element-wise steps in place in buffers allocated once.
``train_decoder_cpu`` has the arguments, the loss, the Adam steps and the schedule of
``kernels.neural_training.train_decoder``; ``CpuDecoder`` and ``decode_cpu`` decode a learned residual at query
directions, the first layer's code part computed once per pixel for every direction.
"""

from __future__ import annotations

import time

import numpy as np

from ..kernels.neural import NeuralDecoder, initial_model, kernel_weights, used_lights
from ..model.residual import (
    NEURAL_CODE_SIZE,
    NEURAL_LAYER_SHAPES,
    decoder_widths,
    sees_highlights,
)
from ..model.threads import blas_on_one_thread, parallel_map

__all__ = ["BATCH_CPU", "CpuDecoder", "CpuQueryDecoder", "decode_cpu", "seeing_model", "train_decoder_cpu",
           "training_rate"]

CODE = NEURAL_CODE_SIZE
HIDDEN = NEURAL_LAYER_SHAPES[0][0]
INPUTS = NEURAL_LAYER_SHAPES[0][1]  # code + light direction
BATCH_CPU = 1 << 12
"""Samples per Adam step of ``train_decoder_cpu``: on 2 cores, 180 s of the images learned alone gave the statue
34.5 dB at 2,048 and 4,096 and 33.3 at 8,192 (fewer steps), the dome 48.7 dB at 2,048 and 4,096; 4,096 trains
1.4x as many samples a second as 2,048 (``benchmarks/bench_cpu_learned.py``)."""
DECODE_CHUNK = 1 << 12
"""Pixels ``CpuDecoder`` decodes at a time (a thread's buffers stay in its cache)."""
CODE_PART_BYTES = 1 << 28
"""``CpuDecoder`` keeps the first layer's code part of every pixel up to this size (256 MiB: 1.4 megapixels)."""
_BETA1, _BETA2, _EPS = 0.9, 0.999, 1e-8  # warp.optim.Adam's defaults, as kernels.neural uses it


class _Parameters:
    """Codes and weights as views into one flat float32 vector (and its gradient's), so that one Adam
    step is a few passes over the vector. The first layer is held as (HIDDEN, inputs + 1): w0 | b0, inputs 12 or,
    where it sees the highlights, 14."""

    def __init__(self, model: NeuralDecoder):
        pixels = len(model.codes)
        w0, b0, w1, b1, w2, b2, w3, b3 = (np.asarray(w, np.float32) for w in model.weights)
        self.inputs = w0.shape[1]
        parts = [np.asarray(model.codes, np.float32), np.concatenate([w0, b0], axis=1), w1, b1.reshape(-1), w2,
                 b2.reshape(-1), w3, b3.reshape(-1)]
        sizes = [p.size for p in parts]
        self.flat = np.concatenate([p.reshape(-1) for p in parts]).astype(np.float32)
        self.grad = np.zeros_like(self.flat)
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        shapes = [(pixels, CODE)] + [p.shape for p in parts[1:]]

        def views(vector):
            return [vector[a:b].reshape(s) for a, b, s in zip(offsets[:-1], offsets[1:], shapes)]

        self.codes, self.w0, self.w1, self.b1, self.w2, self.b2, self.w3, self.b3 = views(self.flat)
        self.g_codes, self.g_w0, self.g_w1, self.g_b1, self.g_w2, self.g_b2, self.g_w3, self.g_b3 = views(self.grad)

    def model(self) -> NeuralDecoder:
        """The current codes and the eight weight arrays (copies)."""
        return NeuralDecoder(self.codes.copy(), [self.w0[:, :self.inputs].copy(), self.w0[:, self.inputs:].copy(),
                                                 self.w1.copy(), self.b1.reshape(-1, 1).copy(), self.w2.copy(),
                                                 self.b2.reshape(-1, 1).copy(), self.w3.copy(),
                                                 self.b3.reshape(-1, 1).copy()])


class _Adam:
    """warp.optim.Adam over a flat float32 vector: m, v and the step count t as that optimizer keeps them;
    the vector's parts stepped by ``threads`` threads."""

    def __init__(self, size: int, threads: int = 1):
        self.m = np.zeros(size, np.float32)
        self.v = np.zeros(size, np.float32)
        self.scratch = np.empty(size, np.float32)
        self.bounds = np.linspace(0, size, max(1, min(int(threads), size)) + 1).astype(np.int64)
        self.t = 0

    def step(self, params: np.ndarray, grad: np.ndarray, lr: float) -> None:
        """params -= lr m^ / (sqrt(v^) + eps) after m, v take in ``grad``, in place."""
        self.t += 1
        # lr m^ / (sqrt(v^) + eps) = (lr sqrt(c2) / c1) m / (sqrt(v) + eps sqrt(c2)), c = 1 - beta^t
        root = np.sqrt(1.0 - _BETA2**self.t)
        rate, eps = np.float32(lr * root / (1.0 - _BETA1**self.t)), np.float32(_EPS * root)

        def part(i: int) -> None:
            a, b = self.bounds[i], self.bounds[i + 1]
            m, v, s, g = self.m[a:b], self.v[a:b], self.scratch[a:b], grad[a:b]
            np.multiply(g, np.float32(1.0 - _BETA1), out=s)
            m *= np.float32(_BETA1)
            m += s
            np.multiply(g, g, out=s)
            s *= np.float32(1.0 - _BETA2)
            v *= np.float32(_BETA2)
            v += s
            np.sqrt(v, out=s)
            s += eps
            np.divide(m, s, out=s)
            s *= rate
            params[a:b] -= s

        parallel_map(part, range(len(self.bounds) - 1))


def _elu(z: np.ndarray, out: np.ndarray, e: np.ndarray, zeros: np.ndarray) -> None:
    """out = elu(z) = max(z, e), e = expm1(min(z, 0)) (kept: elu'(z) = e + 1), element-wise."""
    np.minimum(z, zeros, out=e)
    np.expm1(e, out=e)
    np.maximum(z, e, out=out)


class _Worker:
    """One thread's share of a batch: buffers for ``size`` samples (rows), its forward and backward pass, and
    its own gradient of the weights (a flat vector laid out as ``_Parameters.grad`` past the codes)."""

    def __init__(self, size: int, pixels: int, weight_count: int, inputs: int = INPUTS):
        f = np.float32
        self.x = np.empty((size, inputs + 1), f)
        self.x[:, inputs] = 1.0  # the first layer's bias
        self.g = np.empty(size, f) if inputs > INPUTS else None
        self.z = np.empty((size, HIDDEN), f)
        self.h = [np.empty((size, HIDDEN), f) for _ in range(3)]
        self.grad = np.empty((size, HIDDEN), f)
        self.grad_in = np.empty((size, HIDDEN), f)
        self.e = [np.empty((size, HIDDEN), f) for _ in range(3)]  # each hidden layer's expm1(min(z, 0))
        self.zeros = np.zeros((size, HIDDEN), f)
        self.ones = np.ones(size, f)
        self.y = np.empty((size, 3), f)
        self.target = np.empty((size, 3), f)
        self.light = np.empty(size, np.int64)
        self.pixel = np.empty(size, np.int64)
        self.pixels = pixels
        self.weight_grad = np.zeros(weight_count, f)

    def run(self, samples: np.ndarray, scale: float, p: _Parameters, lights: np.ndarray, targets: np.ndarray,
            code_grad: np.ndarray, slots: np.ndarray, highlights: np.ndarray | None = None) -> float:
        """Squared error summed over RGB and the samples = light * pixels + pixel; the gradient of ``scale``
        times it: the weights' into ``weight_grad``, each sample's code row into ``code_grad`` and its
        place in the flat codes (pixel * CODE + k) into ``slots``. ``highlights``: (n * pixels,) the Gaussians'
        luminance of each sample (display units), for a decoder that sees them."""
        n = len(samples)
        x, z, zeros = self.x[:n], self.z[:n], self.zeros[:n]
        h, e = [a[:n] for a in self.h], [a[:n] for a in self.e]
        light, pixel = self.light[:n], self.pixel[:n]
        np.divmod(samples, self.pixels, out=(light, pixel))
        np.take(p.codes, pixel, axis=0, out=x[:, :CODE], mode="clip")
        np.take(lights, light, axis=0, out=x[:, CODE:INPUTS], mode="clip")
        if self.g is not None:  # sqrt(g), g of each sample
            g = self.g[:n]
            np.take(highlights, samples, out=g, mode="clip")
            np.maximum(g, np.float32(0.0), out=x[:, INPUTS + 1])
            np.sqrt(x[:, INPUTS + 1], out=x[:, INPUTS])
        np.take(targets, samples, axis=0, out=self.target[:n], mode="clip")
        # forward
        np.matmul(x, p.w0.T, out=z)
        _elu(z, h[0], e[0], zeros)
        for k, (w, b) in enumerate(((p.w1, p.b1), (p.w2, p.b2))):
            np.matmul(h[k], w.T, out=z)
            z += b
            _elu(z, h[k + 1], e[k + 1], zeros)
        error = self.y[:n]
        np.matmul(h[2], p.w3.T, out=error)
        error += p.b3
        error -= self.target[:n]
        flat = error.reshape(-1)
        squared = float(np.dot(flat, flat))
        # backward from d (scale * squared) / d y = 2 scale error
        error *= np.float32(2.0 * scale)
        g_w0, g_w1, g_b1, g_w2, g_b2, g_w3, g_b3 = _weight_views(self.weight_grad, p)
        ones = self.ones[:n]
        np.matmul(error.T, h[2], out=g_w3)
        np.matmul(ones, error, out=g_b3)
        grad, grad_in = self.grad[:n], self.grad_in[:n]
        np.matmul(error, p.w3, out=grad)
        for k, (w, g_w, g_b) in ((2, (p.w2, g_w2, g_b2)), (1, (p.w1, g_w1, g_b1))):
            e[k] += np.float32(1.0)  # elu'(z)
            grad *= e[k]
            np.matmul(grad.T, h[k - 1], out=g_w)
            np.matmul(ones, grad, out=g_b)
            np.matmul(grad, w, out=grad_in)
            grad, grad_in = grad_in, grad
        e[0] += np.float32(1.0)
        grad *= e[0]
        np.matmul(grad.T, x, out=g_w0)
        np.matmul(grad, p.w0[:, :CODE], out=code_grad)
        np.multiply(pixel[:, None], CODE, out=slots)
        slots += np.arange(CODE)
        return squared


def _weight_views(vector: np.ndarray, p: _Parameters) -> list[np.ndarray]:
    """Views of a flat weight vector shaped as ``p``'s weights (w0 | b0, w1, b1, w2, b2, w3, b3)."""
    views, start = [], 0
    for like in (p.w0, p.w1, p.b1, p.w2, p.b2, p.w3, p.b3):
        views.append(vector[start : start + like.size].reshape(like.shape))
        start += like.size
    return views


class _Batch:
    """A step's forward and backward pass over a batch of at most ``size`` samples, its rows split among
    ``threads`` workers; the gradient lands in ``_Parameters.grad`` (every entry)."""

    def __init__(self, size: int, pixels: int, weight_count: int, threads: int = 1, inputs: int = INPUTS):
        self.threads = max(1, min(int(threads), size))
        share = -(-size // self.threads)
        self.workers = [_Worker(share, pixels, weight_count, inputs) for _ in range(self.threads)]
        self.code_grad = np.empty((size, CODE), np.float32)
        self.slots = np.empty((size, CODE), np.int64)

    def step(self, samples: np.ndarray, p: _Parameters, lights: np.ndarray, targets: np.ndarray,
             highlights: np.ndarray | None = None) -> float:
        """Loss (mean over the samples of the squared error summed over RGB) of samples = light * pixels +
        pixel, and its gradient; ``highlights`` as ``_Worker.run`` takes them."""
        n = len(samples)
        bounds = np.linspace(0, n, min(self.threads, n) + 1).astype(np.int64)

        def part(i: int) -> float:
            a, b = bounds[i], bounds[i + 1]
            return self.workers[i].run(samples[a:b], 1.0 / n, p, lights, targets, self.code_grad[a:b],
                                       self.slots[a:b], highlights)

        squared = sum(parallel_map(part, range(len(bounds) - 1)))
        weights = p.grad[p.codes.size :]
        np.copyto(weights, self.workers[0].weight_grad)
        for worker in self.workers[1 : len(bounds) - 1]:
            weights += worker.weight_grad
        # the codes' gradient: every sample's row added to its pixel's (pixel x CODE slots of the flat codes)
        p.g_codes.fill(0.0)
        np.add.at(p.g_codes.reshape(-1), self.slots[:n].reshape(-1), self.code_grad[:n].reshape(-1))
        return squared / n


def train_decoder_cpu(targets: np.ndarray, lights: np.ndarray, *, device=None, epochs: int = 40,
                      batch: int = BATCH_CPU, lr: float = 3e-3, final_lr: float = 3e-4, seed: int = 0,
                      seconds: float | None = None, log=None, used: np.ndarray | None = None,
                      initial: NeuralDecoder | None = None,
                      highlights: np.ndarray | None = None) -> tuple[NeuralDecoder, list[float]]:
    """``kernels.neural_training.train_decoder`` on the CPU in NumPy: fit codes and weights to (n, P, 3) display-unit
    targets at (n, 3) lights by Adam on the mean squared error over shuffled (light, pixel) samples, ``batch``
    a step, the learning rate decaying geometrically from ``lr`` to ``final_lr`` over ``epochs`` (or until
    ``seconds`` have passed since the first step). ``used``: the lights to learn from (default all; the
    others' targets are never read); ``initial``: a model to go on training (default ``initial_model`` of
    the used lights' targets); ``device``: None or the CPU (as ``train_decoder`` takes it); ``highlights``: (n, P)
    the Gaussians' luminance at each light and pixel (display units): the decoder sees them (``highlight_inputs``; an
    initial decoder that does not is given zero weights for them). Returns the model and the mean loss of each
    epoch."""
    if device is not None and str(device) != "cpu":
        raise ValueError(f"train_decoder_cpu trains on the CPU, not on {device}")
    targets = np.ascontiguousarray(targets, np.float32)
    n, pixels, _ = targets.shape
    used = used_lights(n, pixels, used)
    model = initial_model(targets[used], seed=seed) if initial is None else initial
    if model.codes.shape != (pixels, CODE):
        raise ValueError(f"initial codes {model.codes.shape} do not match {pixels} pixels")
    flat_highlights = None
    if highlights is not None:
        flat_highlights = np.ascontiguousarray(np.asarray(highlights, np.float32).reshape(n * pixels))
        model = seeing_model(model)
    elif sees_highlights(model.weights):
        raise ValueError("a decoder that sees the highlights trains with them: pass highlights")
    lights = np.ascontiguousarray(np.asarray(lights, np.float32).reshape(n, 3))
    flat_targets = targets.reshape(n * pixels, 3)
    total = len(used) * pixels
    params = _Parameters(model)
    rng = np.random.default_rng(seed)
    history = []
    started = None
    with blas_on_one_thread() as threads:
        adam = _Adam(params.flat.size, threads)
        buffers = _Batch(min(int(batch), total), pixels, params.flat.size - params.codes.size, threads,
                         params.inputs)
        for epoch in range(epochs):
            rate = lr * (final_lr / lr) ** (epoch / max(epochs - 1, 1))
            shuffled = rng.permutation(total)
            if len(used) < n:  # sample index = light * pixels + pixel, over the used lights only
                shuffled = used[shuffled // pixels] * pixels + shuffled % pixels
            epoch_loss = 0.0
            for start in range(0, total, batch):
                epoch_loss += buffers.step(shuffled[start : start + batch], params, lights, flat_targets,
                                           flat_highlights)
                adam.step(params.flat, params.grad, rate)
                if started is None:
                    started = time.perf_counter()
            history.append(epoch_loss / -(-total // batch))
            if log:
                log(f"epoch {epoch + 1}/{epochs}: mse {history[-1]:.3e} (lr {rate:.1e}, "
                    f"{time.perf_counter() - started:.1f} s)")
            if seconds is not None and time.perf_counter() - started > seconds:
                break
    return params.model(), history


def seeing_model(model: NeuralDecoder) -> NeuralDecoder:
    """``model`` as a decoder that sees the highlights: its first layer given zero weights for their inputs where it
    has none (it computes what it did while they are 0)."""
    return NeuralDecoder(model.codes, kernel_weights(model.weights))


def training_rate(steps: int = 32, batch: int = BATCH_CPU, pixels: int = 1 << 14) -> float:
    """(light, pixel) samples a second that ``train_decoder_cpu`` trains at on this machine now: ``steps`` steps of
    ``batch`` samples of a small random capture, timed after one untimed step (under half a second on 2 cores)."""
    rng = np.random.default_rng(0)
    pixels = max(1, int(pixels))
    targets = rng.random((4, pixels, 3), dtype=np.float32)
    lights = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [-1, 0, 1]], np.float32)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    model = initial_model(targets, seed=0)
    params = _Parameters(model)
    with blas_on_one_thread() as threads:
        adam = _Adam(params.flat.size, threads)
        buffers = _Batch(batch, pixels, params.flat.size - params.codes.size, threads)
        samples = rng.integers(0, 4 * pixels, size=(steps + 1, batch))
        flat = targets.reshape(-1, 3)
        started = None
        for step, rows in enumerate(samples):
            buffers.step(rows, params, lights, flat)
            adam.step(params.flat, params.grad, 1e-3)
            if step == 0:
                started = time.perf_counter()
        return steps * batch / max(time.perf_counter() - started, 1e-9)


class CpuDecoder:
    """A learned residual decoded on the CPU for query directions: the first layer's code part
    (P, first hidden width) computed once for every pixel (once per call and chunk of pixels where it would pass
    ``CODE_PART_BYTES``), the pixels decoded in chunks of ``DECODE_CHUNK`` spread over the threads.

    Args:
        codes: (P, CODE) float32 per pixel; weights: the decoder's arrays w0, b0, ... (any
            ``model.residual.decoder_layer_shapes``: the fitted decoder or a smaller one).
    """

    def __init__(self, codes: np.ndarray, weights):
        self.codes = np.ascontiguousarray(np.asarray(codes, np.float32).reshape(-1, CODE))
        weights = [np.asarray(w, np.float32) for w in weights]
        self.widths = decoder_widths(weights)
        w0, b0 = weights[0], weights[1]
        self.code_weights = np.ascontiguousarray(w0[:, :CODE].T)
        self.light_weights, self.b0 = w0[:, CODE:INPUTS].T.astype(np.float32), b0.reshape(-1)
        # (2, first width): the weights of sqrt(g) and g, for a decoder that sees the highlights
        self.highlight_weights = np.ascontiguousarray(w0[:, INPUTS:].T) if sees_highlights(weights) else None
        # the hidden layers after the first, then the output layer
        self.layers = [(np.ascontiguousarray(w.T), b.reshape(-1)) for w, b in zip(weights[2::2], weights[3::2])]
        self.code_part = None
        if self.codes.nbytes // CODE * self.widths[0] <= CODE_PART_BYTES:
            with blas_on_one_thread():
                self.code_part = self.codes @ self.code_weights

    @property
    def sees_highlights(self) -> bool:
        """Whether the decoder takes the Gaussians' luminance at each pixel (``decode``'s ``highlights``)."""
        return self.highlight_weights is not None

    def decode(self, directions: np.ndarray, out: np.ndarray | None = None, unit: float | None = None,
               highlights: np.ndarray | None = None, highlight_scale: float = 1.0) -> np.ndarray:
        """(Q, 3) unit directions -> (Q, P, 3) float32 display units, or with ``unit`` (field units per display
        unit) float16 field units as ``kernels.neural.store_decoded`` stores them; into ``out`` when given.
        ``highlights``: (Q, P) the Gaussians' luminance at each query and pixel, times ``highlight_scale`` in display
        units: required by a decoder that sees them, refused by one that does not."""
        directions = np.asarray(directions, np.float32).reshape(-1, 3)
        pixels = len(self.codes)
        if (highlights is None) == self.sees_highlights:
            raise ValueError("a decoder that sees the highlights decodes with them, and only such a decoder does")
        if highlights is not None:
            highlights = np.asarray(highlights, np.float32).reshape(len(directions), pixels)
        if out is None:
            out = np.empty((len(directions), pixels, 3), np.float32 if unit is None else np.float16)
        if out.shape != (len(directions), pixels, 3):
            raise ValueError(f"out has shape {out.shape}, not {(len(directions), pixels, 3)}")
        light_part = directions @ self.light_weights + self.b0  # (Q, HIDDEN): each direction's part and the bias
        size = min(DECODE_CHUNK, pixels)
        chunks = [slice(start, min(start + size, pixels)) for start in range(0, pixels, size)]
        with blas_on_one_thread() as threads:
            groups = [chunks[i::threads] for i in range(min(threads, len(chunks)))]
            parallel_map(lambda group: self._decode_chunks(group, size, light_part, out, unit, highlights,
                                                           np.float32(highlight_scale)), groups)
        return out

    def _decode_chunks(self, chunks: list[slice], size: int, light_part: np.ndarray, out: np.ndarray,
                       unit: float | None, highlights: np.ndarray | None = None,
                       highlight_scale: np.float32 = np.float32(1.0)) -> None:
        f = np.float32
        if highlights is not None:  # g, sqrt(g) and one of their products with the first layer's weights
            g, root, term = np.empty(size, f), np.empty(size, f), np.empty((size, self.widths[0]), f)
        # per hidden layer: its pre-activation, elu's kept exponent, its values, zeros
        buffers = [tuple(np.empty((size, width), f) for _ in range(3)) + (np.zeros((size, width), f),)
                   for width in self.widths]
        # the hidden layers' biases a row each: an add of whole arrays runs twice as fast as a broadcast one
        biases = [np.broadcast_to(b, (size, len(b))).copy() for _, b in self.layers[:-1]]
        own_part = np.empty((size, self.widths[0]), f) if self.code_part is None else None
        if unit is not None:  # the output layer's values, two buffers and a mask for their conversion
            y, scratch, linear, low = (np.empty((size, 3), f), np.empty((size, 3), f), np.empty((size, 3), f),
                                       np.empty((size, 3), bool))
        for rows in chunks:
            k = rows.stop - rows.start
            if own_part is None:
                codes = self.code_part[rows]
            else:  # the code part of these pixels, once for every direction
                codes = own_part[:k]
                np.matmul(self.codes[rows], self.code_weights, out=codes)
            for q in range(len(light_part)):
                z, slope, h, zeros = (buffer[:k] for buffer in buffers[0])
                np.add(codes, light_part[q], out=z)
                if highlights is not None:
                    np.multiply(highlights[q, rows], highlight_scale, out=g[:k])
                    np.maximum(g[:k], f(0.0), out=g[:k])
                    np.sqrt(g[:k], out=root[:k])
                    for column, weights in zip((root[:k], g[:k]), self.highlight_weights):
                        np.multiply(column[:, None], weights, out=term[:k])
                        z += term[:k]
                _elu(z, h, slope, zeros)
                for (w, _), b, layer in zip(self.layers[:-1], biases, buffers[1:]):
                    z, slope, following, zeros = (buffer[:k] for buffer in layer)
                    np.matmul(h, w, out=z)
                    z += b[:k]
                    _elu(z, following, slope, zeros)
                    h = following
                w, b = self.layers[-1]
                values = y[:k] if unit is not None else out[q, rows]
                np.matmul(h, w, out=values)
                values += b
                if unit is not None:
                    _store_field_units(values, unit, scratch[:k], linear[:k], low[:k], out[q, rows])


def _store_field_units(values: np.ndarray, unit: float, scratch: np.ndarray, linear: np.ndarray, low: np.ndarray,
                       out: np.ndarray) -> None:
    """out = unit sign(v) srgb^-1(|v|) of the display-unit values v, clipped to float16's range (as
    ``kernels.neural.store_decoded``); ``scratch``, ``linear`` and the mask ``low`` are overwritten."""
    np.abs(values, out=scratch)
    np.less_equal(scratch, np.float32(0.04045), out=low)
    np.add(scratch, np.float32(0.055), out=linear)
    linear *= np.float32(1.0 / 1.055)
    np.power(linear, np.float32(2.4), out=linear)
    scratch *= np.float32(1.0 / 12.92)
    np.copyto(linear, scratch, where=low)
    np.copysign(linear, values, out=linear)
    linear *= np.float32(unit)
    np.clip(linear, np.float32(-6.0e4), np.float32(6.0e4), out=linear)
    np.copyto(out, linear, casting="same_kind")


class CpuQueryDecoder:
    """``kernels.neural.QueryDecoder``'s interface on the CPU (``CpuDecoder``): the relighter's learned residual.

    Args:
        codes: (P, CODE) float32 per output pixel; weights: the eight arrays; unit: field units per display
        unit; device, batch: accepted as ``QueryDecoder`` takes them (the CPU; chunks of ``DECODE_CHUNK``).
    """

    def __init__(self, codes: np.ndarray, weights, unit: float, *, device=None, batch: int | None = None):
        if device is not None and str(device) != "cpu":
            raise ValueError(f"CpuQueryDecoder decodes on the CPU, not on {device}")
        self.decoder = CpuDecoder(codes, weights)
        self.pixels = len(self.decoder.codes)
        self.unit = float(unit)

    @property
    def sees_highlights(self) -> bool:
        """Whether ``decode`` takes the Gaussians' luminance (``CpuDecoder.sees_highlights``)."""
        return self.decoder.sees_highlights

    def decode(self, directions, out, highlights=None) -> None:
        """(Q,) vec3 unit directions -> out (Q, P, 3) float16, field units (Warp CPU arrays or NumPy arrays);
        ``highlights``: (Q, P) the Gaussians' luminance in field units, for a decoder that sees them."""
        self.decoder.decode(_host(directions), out=_host(out), unit=self.unit,
                            highlights=None if highlights is None else _host(highlights),
                            highlight_scale=1.0 / self.unit)


def _host(array) -> np.ndarray:
    """A NumPy view of a Warp CPU array (its memory), or the NumPy array itself."""
    return array if isinstance(array, np.ndarray) else array.numpy()


def decode_cpu(codes: np.ndarray, weights, directions: np.ndarray, highlights: np.ndarray | None = None) -> np.ndarray:
    """(Q, P, 3) float32 display-unit values of a learned residual with (P, CODE) codes and its decoder's weight
    arrays at (Q, 3) unit directions (``CpuDecoder``); ``highlights``: (Q, P) display units, for a decoder that sees
    them."""
    return CpuDecoder(codes, weights).decode(directions, highlights=highlights)
