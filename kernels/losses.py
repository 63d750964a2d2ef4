"""Per-problem losses of estimation and retargeting (docs/method.md, Fitting steps 2 and 5), differentiable on the tape.

Every loss returns one value per problem, shape (B,), and *adds* ``weight`` x its value into ``out``
when one is given, so the retargeting loss c_fit L_fit + c_str L_str + c_ene L_ene is three calls on
one array. Each records a hand-written adjoint on the active ``wp.Tape``; ``total`` sums the
problems into the one-element array ``tape.backward(loss)`` wants.

- ``LogL1Loss``: sum over pixels of |log2(1 + R) - log2(1 + S)|, times the pixel area in rpx^2 so the
  value is the thesis' plain pixel sum at 270 rows and the same measure at any other height.
- ``StructureLoss``: sum over ordered pairs p != q of h(rho^_pq) (rho_pq - s rho^_pq)^2, distances
  in rpx, s = sum rho / (sum rho^ + eps), h(x) = (1 + tanh(gamma (m - x))) / 2.
- ``EnergyLoss``: sum over slots of (E(p^) - E(p))^2, E = 2 pi a^2 sqrt((sx^2 + eps)(sy^2 + eps))
  in intensity x rpx^2.

The structure and energy losses compare a batch with a fixed *reference* batch of the same shape
(G_i while fitting G_i->j); a pair or slot counts when it is active in both.
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

import math

import numpy as np
import warp as wp

from warp_highlights.model.config import (
    RasterSettings,
    StructureLossSettings,
    normalized_to_rpx,
    pixel_area_rpx2,
)
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianArrays, GaussianBatch

from .tape import active_tape

__all__ = ["EnergyLoss", "LogL1Loss", "StructureLoss", "clipped_mse", "total"]

_LN2 = math.log(2.0)


# --- fit loss --------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def log_transform(image: wp.array3d(dtype=float), out: wp.array3d(dtype=float), non_finite: wp.array(dtype=wp.int32)):
    """out = log2(1 + max(image, 0)); non_finite[0] counts the pixels that are not finite."""
    b, row, col = wp.tid()
    value = image[b, row, col]
    if not wp.isfinite(value):
        wp.atomic_add(non_finite, 0, 1)
    out[b, row, col] = wp.log2(1.0 + wp.max(value, 0.0))


@wp.kernel(enable_backward=False)
def log_l1_partials(image: wp.array3d(dtype=float), log_target: wp.array3d(dtype=float),
                    partials: wp.array3d(dtype=float)):
    """Per (problem, row, lane): sum of |log2(1 + R) - log2(1 + S)| over the columns lane, lane + L, ...

    Neighbouring lanes read neighbouring pixels, so on a GPU a warp's loads are coalesced; on the CPU
    there is one lane and a thread walks its row.
    """
    b, row, lane = wp.tid()
    lanes = partials.shape[2]
    total = float(0.0)
    col = lane
    while col < image.shape[2]:
        r = image[b, row, col]
        difference = -log_target[b, row, col]
        if r != 0.0:  # log2(1 + 0) = 0: empty pixels skip the logarithm
            difference += wp.log2(1.0 + r)
        total += wp.abs(difference)
        col += lanes
    partials[b, row, lane] = total


@wp.kernel(enable_backward=False)
def sum_lanes(partials: wp.array3d(dtype=float), row_sums: wp.array2d(dtype=float)):
    """row_sums[b, row] = sum over lanes of partials[b, row, :]."""
    b, row = wp.tid()
    total = float(0.0)
    for lane in range(partials.shape[2]):
        total += partials[b, row, lane]
    row_sums[b, row] = total


@wp.kernel(enable_backward=False)
def add_row_sums(row_sums: wp.array2d(dtype=float), scale: float, out: wp.array(dtype=float)):
    """out[b] += scale * sum of row_sums[b, :] (one thread per problem, fixed order: deterministic)."""
    b = wp.tid()
    total = float(0.0)
    for row in range(row_sums.shape[1]):
        total += row_sums[b, row]
    out[b] = out[b] + scale * total


@wp.func
def log_l1_factor(out_grad: float, scale: float) -> float:
    """d(scale |log2(1 + R) - log2(1 + S)|)/dR without its sign and 1 / (1 + R), times the upstream gradient."""
    return out_grad * scale / _LN2


@wp.func
def log_l1_gradient(r: float, target: float, factor: float) -> float:
    """d(scale |log2(1 + R) - log2(1 + S)|)/dR at one pixel times the upstream gradient (``factor`` from
    ``log_l1_factor``): log2(1 + x) rises with x, so the sign is that of R - max(S, 0), no logarithm."""
    s = wp.max(target, 0.0)
    step = float(0.0)
    if r != s:
        step = factor * wp.sign(r - s)
        if r != 0.0:  # empty pixels (most of a highlight image) skip the division
            step = step / (1.0 + r)
    return step


@wp.kernel(enable_backward=False)
def log_l1_backward(
    image: wp.array(dtype=float),
    target: wp.array(dtype=float),
    out_grad: wp.array(dtype=float),
    pixels_per_problem: int,
    scale: float,
    pixels_per_thread: int,
    image_grad: wp.array(dtype=float),
):
    """image_grad += d(scale |log2(1 + R) - log2(1 + S)|)/dR * out_grad[problem], over flattened (B H W) arrays.

    1D so each thread spends one 32-bit division on its index rather than a 3D launch's 64-bit ones.
    A thread handles ``pixels_per_thread`` consecutive pixels (1 on CUDA, an image row on the CPU,
    where a thread per pixel costs more in call overhead than the pixel's work).
    """
    first = wp.tid() * pixels_per_thread
    # a thread's pixels lie in one problem (a row never straddles two images)
    factor = log_l1_factor(out_grad[first // pixels_per_problem], scale)
    for j in range(pixels_per_thread):
        i = first + j
        step = log_l1_gradient(image[i], target[i], factor)
        if step != 0.0:
            image_grad[i] = image_grad[i] + step


@wp.kernel(enable_backward=False)
def clipped_square_error_rows(image: wp.array3d(dtype=float), target: wp.array3d(dtype=float),
                              rows: wp.array2d(dtype=wp.float64)):
    """rows[b, row] = sum over the row of (clip(R, 0, 1) - clip(S, 0, 1))^2, in float64."""
    b, row = wp.tid()
    total = wp.float64(0.0)
    for col in range(image.shape[2]):
        d = wp.float64(wp.clamp(image[b, row, col], 0.0, 1.0)) - wp.float64(wp.clamp(target[b, row, col], 0.0, 1.0))
        total += d * d
    rows[b, row] = total


def clipped_mse(image: wp.array, target: wp.array) -> np.ndarray:
    """(B,) float64 mean of (clip(R, 0, 1) - clip(S, 0, 1))^2 over (B, H, W) float32 device images: the
    error of ``quality.metrics.psnr``, summed there; only one float64 per row comes to the host."""
    if image.shape != target.shape or image.ndim != 3:
        raise InputError(f"image {image.shape} and target {target.shape} must be two (B, H, W) arrays of one shape")
    rows = wp.empty(image.shape[:2], dtype=wp.float64, device=image.device)
    wp.launch(clipped_square_error_rows, dim=image.shape[:2], inputs=[image, target], outputs=[rows],
              device=image.device, record_tape=False)
    return rows.numpy().sum(axis=1) / (image.shape[1] * image.shape[2])


class LogL1Loss:
    """The fit loss against fixed targets S (B, H, W); log2(1 + S) is computed once here.

    Negative target pixels count as 0; targets must be finite.
    """

    def __init__(self, target, *, device=None):
        self.device = wp.get_device(device if device is not None else getattr(target, "device", None))
        on_device = isinstance(target, wp.array) and target.device == self.device and target.dtype == wp.float32
        if not on_device:  # host data (or another device): one copy; device targets are used in place
            target = wp.array(np.asarray(target.numpy() if isinstance(target, wp.array) else target, dtype=np.float32),
                              dtype=float, device=self.device)
        if target.ndim != 3:
            raise InputError(f"targets must have shape (problems, height, width), got {target.shape}")
        self.shape = target.shape
        self.target = target  # the adjoint compares with S itself
        self.log_target = wp.empty(self.shape, dtype=float, device=self.device)
        non_finite = wp.zeros(1, dtype=wp.int32, device=self.device)
        wp.launch(log_transform, dim=self.shape, inputs=[target], outputs=[self.log_target, non_finite],
                  device=self.device, record_tape=False)
        count = int(non_finite.numpy()[0])
        if count:
            raise InputError(f"targets have {count} non-finite pixels")
        self.pixel_area = pixel_area_rpx2(self.shape[1])
        self._row_sums = wp.empty(self.shape[:2], dtype=float, device=self.device)
        lanes = 32 if self.device.is_cuda else 1
        self._partials = wp.empty((*self.shape[:2], lanes), dtype=float, device=self.device)

    def __call__(self, image: wp.array, *, out: wp.array | None = None, weight: float = 1.0,
                 value: bool = True) -> wp.array:
        """Per-problem loss of ``image`` (B, H, W); adds weight x loss to ``out`` (B,) and returns it.

        ``value=False`` records only the gradient and leaves ``out`` as it is: for optimisation steps
        whose loss value nobody reads (the gradient does not depend on it).
        """
        out, scale = self._value(image, out, weight, value)

        def backward():
            pixels = self.shape[1] * self.shape[2]
            per_thread = 1 if self.device.is_cuda else self.shape[2]
            inputs = [image.flatten(), self.target.flatten(), out.grad, pixels, scale, per_thread]
            wp.launch(log_l1_backward, dim=image.size // per_thread, inputs=inputs, outputs=[image.grad.flatten()],
                      device=self.device, record_tape=False)

        _record(backward, [out, image])
        return out

    def of_render(self, raster, batch: GaussianBatch, *, image: wp.array, out: wp.array | None = None,
                  weight: float = 1.0, value: bool = True) -> wp.array:
        """The loss of ``raster.render(batch, out=image)``, with one adjoint for both on the active tape.

        The same values and parameter gradients as ``self(raster.render(batch, out=image), ...)``,
        but the backward pass never stores d(loss)/d(image): the rasterizer's adjoint computes it at
        each pixel of a Gaussian's footprint (``Rasterizer.backward(fit=...)``), which saves a pass
        over every pixel and the zeroing of the image gradient. With ``value=False`` only the tiles
        the Gaussians reach are drawn (``render(drawn_only=True)``): ``image`` holds R(G) there and
        stale pixels elsewhere, so render it again before reading it whole.
        """
        # the adjoint reads only where Gaussians draw
        raster.render(batch, out=image, record=False, drawn_only=not value)
        out, scale = self._value(image, out, weight, value)
        tape = active_tape()
        if tape is not None and batch.requires_grad:
            if not out.requires_grad:
                raise InputError("inside a wp.Tape the loss output needs requires_grad=True, or no gradient flows back")
            tape.record_func(backward=lambda: raster.backward(batch, None, fit=(image, self.target, out.grad, scale)),
                             arrays=[out, *batch.parameters()])
        return out

    def _value(self, image: wp.array, out: wp.array | None, weight: float, value: bool) -> tuple[wp.array, float]:
        """Checks ``image``, adds weight x its loss to ``out`` when ``value``; returns ``out`` and the loss scale."""
        if image.shape != self.shape:
            raise InputError(f"image shape {image.shape} does not match the targets' {self.shape}")
        out = _output(out, self.shape[0], self.device)
        scale = float(weight) * self.pixel_area
        if value:
            wp.launch(log_l1_partials, dim=self._partials.shape, inputs=[image, self.log_target],
                      outputs=[self._partials], device=self.device, record_tape=False)
            wp.launch(sum_lanes, dim=self.shape[:2], inputs=[self._partials], outputs=[self._row_sums],
                      device=self.device, record_tape=False)
            wp.launch(add_row_sums, dim=self.shape[0], inputs=[self._row_sums, scale], outputs=[out],
                      device=self.device, record_tape=False)
        return out, scale


# --- structure loss --------------------------------------------------------------------------------


@wp.func
def _distance_rpx(a: wp.vec2, b: wp.vec2, to_rpx: float) -> float:
    d = (a - b) * to_rpx
    return wp.sqrt(wp.dot(d, d) + 1.0e-12)  # smooth at coincident means


@wp.kernel(enable_backward=False)
def structure_sums(
    g: GaussianArrays,
    r: GaussianArrays,
    to_rpx: float,
    sums: wp.array(dtype=wp.vec2),
):
    """sums[b] += (sum over q of rho_pq, sum over q of rho^_pq) for slot p (one thread per slot)."""
    b, p = wp.tid()
    if g.active[b, p] == 0 or r.active[b, p] == 0:
        return
    current = float(0.0)
    fixed = float(0.0)
    for q in range(g.mean.shape[1]):
        if q != p and g.active[b, q] != 0 and r.active[b, q] != 0:
            current += _distance_rpx(g.mean[b, p], g.mean[b, q], to_rpx)
            fixed += _distance_rpx(r.mean[b, p], r.mean[b, q], to_rpx)
    wp.atomic_add(sums, b, wp.vec2(current, fixed))


@wp.func
def _neighbourhood(rho_fixed: float, gamma: float, threshold: float) -> float:
    return 0.5 * (1.0 + wp.tanh(gamma * (threshold - rho_fixed)))


@wp.kernel(enable_backward=False)
def structure_terms(
    g: GaussianArrays,
    r: GaussianArrays,
    sums: wp.array(dtype=wp.vec2),
    to_rpx: float,
    gamma: float,
    threshold: float,
    eps: float,
    weight: float,
    out: wp.array(dtype=float),
    scale_terms: wp.array(dtype=float),
):
    """out[b] += weight * sum over q of h (rho - s rho^)^2; scale_terms[b] += sum of -2 h (rho - s rho^) rho^."""
    b, p = wp.tid()
    if g.active[b, p] == 0 or r.active[b, p] == 0:
        return
    s = sums[b][0] / (sums[b][1] + eps)
    loss = float(0.0)
    scale_term = float(0.0)
    for q in range(g.mean.shape[1]):
        if q != p and g.active[b, q] != 0 and r.active[b, q] != 0:
            rho = _distance_rpx(g.mean[b, p], g.mean[b, q], to_rpx)
            rho_fixed = _distance_rpx(r.mean[b, p], r.mean[b, q], to_rpx)
            h = _neighbourhood(rho_fixed, gamma, threshold)
            d = rho - s * rho_fixed
            loss += h * d * d
            scale_term += -2.0 * h * d * rho_fixed
    wp.atomic_add(out, b, weight * loss)
    wp.atomic_add(scale_terms, b, scale_term)


@wp.kernel(enable_backward=False)
def structure_backward(
    g: GaussianArrays,
    r: GaussianArrays,
    sums: wp.array(dtype=wp.vec2),
    scale_terms: wp.array(dtype=float),
    out_grad: wp.array(dtype=float),
    to_rpx: float,
    gamma: float,
    threshold: float,
    eps: float,
    weight: float,
    grad: GaussianArrays,
):
    """mean_grad[b, p] += d(weight * L_str)/d mu_p; each distance appears in two ordered pairs and in s."""
    b, p = wp.tid()
    if g.active[b, p] == 0 or r.active[b, p] == 0:
        return
    denominator = sums[b][1] + eps
    s = sums[b][0] / denominator
    through_scale = scale_terms[b] / denominator  # d L / d rho_kl via s, the same for every pair
    gradient = wp.vec2(0.0, 0.0)
    for q in range(g.mean.shape[1]):
        if q != p and g.active[b, q] != 0 and r.active[b, q] != 0:
            rho = _distance_rpx(g.mean[b, p], g.mean[b, q], to_rpx)
            rho_fixed = _distance_rpx(r.mean[b, p], r.mean[b, q], to_rpx)
            h = _neighbourhood(rho_fixed, gamma, threshold)
            d_rho = 2.0 * (2.0 * h * (rho - s * rho_fixed) + through_scale)
            gradient += d_rho * (g.mean[b, p] - g.mean[b, q]) * (to_rpx * to_rpx / rho)
    wp.atomic_add(grad.mean, b, p, out_grad[b] * weight * gradient)


class StructureLoss:
    """Keeps the local layout of the means close to the reference's, up to one common scale.

    Its per-problem sums are kept between calls (zeroed on the device each time, so that a fitting
    step can be captured in a CUDA graph): run one call's backward before the next call.
    """

    def __init__(self, reference: GaussianBatch, settings: StructureLossSettings | None = None):
        self.reference = reference
        self.settings = settings or StructureLossSettings()
        self._scratch: tuple | None = None

    def _sums(self, problems: int, device) -> tuple[wp.array, wp.array]:
        if self._scratch is None or self._scratch[0] != (problems, str(device)):
            self._scratch = ((problems, str(device)), wp.zeros(problems, dtype=wp.vec2, device=device),
                             wp.zeros(problems, dtype=float, device=device))
        _, sums, scale_terms = self._scratch
        sums.zero_()
        scale_terms.zero_()
        return sums, scale_terms

    def __call__(self, batch: GaussianBatch, *, out: wp.array | None = None, weight: float = 1.0) -> wp.array:
        _check_reference(batch, self.reference)
        problems, capacity = batch.shape
        device = batch.device
        out = _output(out, problems, device)
        s = self.settings
        sums, scale_terms = self._sums(problems, device)
        common = [batch.arrays, self.reference.arrays]
        to_rpx = normalized_to_rpx(1.0)
        wp.launch(structure_sums, dim=(problems, capacity), inputs=[*common, to_rpx], outputs=[sums], device=device,
                  record_tape=False)
        constants = [to_rpx, s.gamma_per_rpx, s.threshold_rpx, s.scale_eps_rpx, float(weight)]
        wp.launch(structure_terms, dim=(problems, capacity), inputs=[*common, sums, *constants],
                  outputs=[out, scale_terms], device=device, record_tape=False)

        def backward():
            wp.launch(structure_backward, dim=(problems, capacity),
                      inputs=[*common, sums, scale_terms, out.grad, *constants], outputs=[batch.grad_arrays],
                      device=device, record_tape=False)

        _record(backward, [out, *batch.parameters()])
        return out


# --- energy loss -----------------------------------------------------------------------------------


@wp.func
def gaussian_energy(a: float, sigma: wp.vec2, eps: float, area_scale: float) -> float:
    """Integral of a^2 exp(-d^2 / 2): 2 pi a^2 sqrt((sx^2 + eps)(sy^2 + eps)), times ``area_scale``."""
    return 2.0 * wp.pi * a * a * wp.sqrt((sigma[0] * sigma[0] + eps) * (sigma[1] * sigma[1] + eps)) * area_scale


@wp.kernel(enable_backward=False)
def energy_terms(
    g: GaussianArrays,
    r: GaussianArrays,
    eps: float,
    area_scale: float,
    weight: float,
    out: wp.array(dtype=float),
):
    b, p = wp.tid()
    if g.active[b, p] == 0 or r.active[b, p] == 0:
        return
    difference = (gaussian_energy(r.amplitude[b, p], r.sigma[b, p], eps, area_scale)
                  - gaussian_energy(g.amplitude[b, p], g.sigma[b, p], eps, area_scale))
    wp.atomic_add(out, b, weight * difference * difference)


@wp.kernel(enable_backward=False)
def energy_backward(
    g: GaussianArrays,
    r: GaussianArrays,
    eps: float,
    area_scale: float,
    weight: float,
    out_grad: wp.array(dtype=float),
    grad: GaussianArrays,
):
    b, p = wp.tid()
    if g.active[b, p] == 0 or r.active[b, p] == 0:
        return
    a = g.amplitude[b, p]
    sig = g.sigma[b, p]
    var_x = sig[0] * sig[0] + eps
    var_y = sig[1] * sig[1] + eps
    root = wp.sqrt(var_x * var_y)
    energy = 2.0 * wp.pi * a * a * root * area_scale
    difference = gaussian_energy(r.amplitude[b, p], r.sigma[b, p], eps, area_scale) - energy
    d_energy = -2.0 * difference * out_grad[b] * weight
    wp.atomic_add(grad.amplitude, b, p, d_energy * 4.0 * wp.pi * a * root * area_scale)
    # d sqrt(var_x var_y) / d sigma_x = sigma_x var_y / sqrt(var_x var_y)
    wp.atomic_add(grad.sigma, b, p,
                  d_energy * 2.0 * wp.pi * a * a * area_scale / root * wp.vec2(sig[0] * var_y, sig[1] * var_x))


class EnergyLoss:
    """Keeps each Gaussian's integral close to that of the same slot in the reference batch.

    ``settings`` supplies the covariance epsilon; pass the rasterizer's own if it is not the default.
    """

    def __init__(self, reference: GaussianBatch, settings: RasterSettings | None = None):
        self.reference = reference
        self.settings = settings or RasterSettings()

    def __call__(self, batch: GaussianBatch, *, out: wp.array | None = None, weight: float = 1.0) -> wp.array:
        _check_reference(batch, self.reference)
        problems, capacity = batch.shape
        device = batch.device
        out = _output(out, problems, device)
        inputs = [batch.arrays, self.reference.arrays, self.settings.sigma_eps, normalized_to_rpx(1.0) ** 2,
                  float(weight)]
        wp.launch(energy_terms, dim=(problems, capacity), inputs=inputs, outputs=[out], device=device,
                  record_tape=False)

        def backward():
            wp.launch(energy_backward, dim=(problems, capacity), inputs=[*inputs, out.grad],
                      outputs=[batch.grad_arrays], device=device, record_tape=False)

        _record(backward, [out, *batch.parameters()])
        return out


# --- sum over problems -----------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def sum_problems(values: wp.array(dtype=float), out: wp.array(dtype=float)):
    """out[0] = sum of values (one thread, fixed order: deterministic)."""
    total = float(0.0)
    for b in range(values.shape[0]):
        total += values[b]
    out[0] = total


@wp.kernel(enable_backward=False)
def spread_gradient(out_grad: wp.array(dtype=float), values_grad: wp.array(dtype=float)):
    b = wp.tid()
    values_grad[b] = values_grad[b] + out_grad[0]


def total(losses: wp.array) -> wp.array:
    """The sum of per-problem losses as a one-element array, for ``tape.backward(loss)``.

    Problems are independent, so the gradient of the sum is each problem's own gradient.
    """
    out = wp.zeros(1, dtype=float, device=losses.device, requires_grad=True)
    wp.launch(sum_problems, dim=1, inputs=[losses], outputs=[out], device=losses.device, record_tape=False)
    _record(lambda: wp.launch(spread_gradient, dim=losses.shape[0], inputs=[out.grad], outputs=[losses.grad],
                              device=losses.device, record_tape=False), [out, losses])
    return out


# --- helper functions ------------------------------------------------------------------------------


def _output(out: wp.array | None, problems: int, device) -> wp.array:
    if out is None:
        return wp.zeros(problems, dtype=float, device=device, requires_grad=True)
    if out.shape != (problems,) or out.dtype != wp.float32:
        raise InputError(f"out must be a float32 array of shape ({problems},), got {out.dtype.__name__} {out.shape}")
    return out


def _check_reference(batch: GaussianBatch, reference: GaussianBatch) -> None:
    if batch.shape != reference.shape or batch.device != reference.device:
        raise InputError(f"the batch ({batch.shape} on {batch.device}) and its reference ({reference.shape} on "
                         f"{reference.device}) must match")


def _record(backward, arrays: list[wp.array]) -> None:
    """Put ``backward`` on the active tape. ``arrays[0]`` is the output; the rest are the inputs.

    Nothing is recorded when no input wants a gradient; an output without one would silently cut
    the chain, so that is an error.
    """
    tape = active_tape()
    output, inputs = arrays[0], arrays[1:]
    if tape is None or not any(a.requires_grad for a in inputs):
        return
    if not output.requires_grad:
        raise InputError("inside a wp.Tape the loss output needs requires_grad=True, or no gradient flows back")
    tape.record_func(backward=backward, arrays=[a for a in arrays if a.requires_grad])
