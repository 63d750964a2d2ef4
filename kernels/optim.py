"""Batched Adam over every problem and slot of a ``GaussianBatch``: one kernel launch per step.

Each slot keeps its own moments and step count on the device, so a step needs no host value (it can
be captured in a CUDA graph), free slots are left untouched, and a slot whose contents were replaced
from the host (``GaussianBatch.add``/``assign``/``copy_from`` bump its generation) restarts with zero
moments and fresh bias correction, without the caller having to remember it. Parameter groups: amplitude, mean, sigma,
theta, each with its own learning rate (``AdamSettings``, lengths in rpx); the weight is not optimised.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model.config import AdamSettings, rpx_to_normalized
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianArrays, GaussianBatch

__all__ = ["GaussianAdam", "adam_step", "reset_slots"]


vec6 = wp.types.vector(length=6, dtype=float)


@wp.struct
class AdamConstants:
    lr_amplitude: float
    lr_mean: float  # normalised units
    lr_sigma: float  # normalised units
    lr_theta: float
    beta1: float
    beta2: float
    epsilon: float


@wp.func
def _moments(m: float, v: float, g: float, beta1: float, beta2: float) -> wp.vec2:
    return wp.vec2(beta1 * m + (1.0 - beta1) * g, beta2 * v + (1.0 - beta2) * g * g)


@wp.func
def _update(m: float, v: float, lr: float, correction1: float, correction2: float, epsilon: float) -> float:
    return lr * (m / correction1) / (wp.sqrt(v / correction2) + epsilon)


@wp.kernel(enable_backward=False)
def adam_step(
    constants: AdamConstants,
    g: GaussianArrays,
    grad: GaussianArrays,
    generation: wp.array2d(dtype=wp.int32),
    first: wp.array3d(dtype=float),
    second: wp.array3d(dtype=float),
    steps: wp.array2d(dtype=wp.int32),
    seen: wp.array2d(dtype=wp.int32),
):
    """One Adam step of slot (b, n). Moments are packed per slot as (a, mu_x, mu_y, s_x, s_y, theta)."""
    b, n = wp.tid()
    if g.active[b, n] == 0:
        return
    if seen[b, n] != generation[b, n]:  # new contents: forget the old moments
        seen[b, n] = generation[b, n]
        steps[b, n] = 0
        for i in range(6):
            first[b, n, i] = 0.0
            second[b, n, i] = 0.0
    k = constants
    t = steps[b, n] + 1
    steps[b, n] = t
    correction1 = 1.0 - wp.pow(k.beta1, float(t))
    correction2 = 1.0 - wp.pow(k.beta2, float(t))
    g_mean = grad.mean[b, n]
    g_sigma = grad.sigma[b, n]
    gradients = vec6(grad.amplitude[b, n], g_mean[0], g_mean[1], g_sigma[0], g_sigma[1], grad.theta[b, n])
    rates = vec6(k.lr_amplitude, k.lr_mean, k.lr_mean, k.lr_sigma, k.lr_sigma, k.lr_theta)
    steps_taken = vec6()
    for i in range(6):
        mv = _moments(first[b, n, i], second[b, n, i], gradients[i], k.beta1, k.beta2)
        first[b, n, i] = mv[0]
        second[b, n, i] = mv[1]
        steps_taken[i] = _update(mv[0], mv[1], rates[i], correction1, correction2, k.epsilon)
    g.amplitude[b, n] = g.amplitude[b, n] - steps_taken[0]
    g.mean[b, n] = g.mean[b, n] - wp.vec2(steps_taken[1], steps_taken[2])
    g.sigma[b, n] = g.sigma[b, n] - wp.vec2(steps_taken[3], steps_taken[4])
    g.theta[b, n] = g.theta[b, n] - steps_taken[5]


@wp.kernel(enable_backward=False)
def reset_slots(mask: wp.array2d(dtype=wp.int32), first: wp.array3d(dtype=float), second: wp.array3d(dtype=float),
                steps: wp.array2d(dtype=wp.int32)):
    """Zero the moments and step count of slots where mask != 0."""
    b, n = wp.tid()
    if mask[b, n] == 0:
        return
    steps[b, n] = 0
    for i in range(6):
        first[b, n, i] = 0.0
        second[b, n, i] = 0.0


class GaussianAdam:
    """Adam state for one ``GaussianBatch``; ``step()`` applies the gradients in the batch's ``.grad``."""

    def __init__(self, batch: GaussianBatch, settings: AdamSettings | None = None):
        if not batch.requires_grad:
            raise InputError("Adam needs a batch made with requires_grad=True")
        self.batch = batch
        self.settings = settings or AdamSettings()
        shape = batch.shape
        self.first = wp.zeros((*shape, 6), dtype=float, device=batch.device)
        self.second = wp.zeros((*shape, 6), dtype=float, device=batch.device)
        self.steps = wp.zeros(shape, dtype=wp.int32, device=batch.device)
        self.seen = wp.clone(batch.generation)
        self._constants = self._make_constants(self.settings)

    @staticmethod
    def _make_constants(s: AdamSettings) -> AdamConstants:
        k = AdamConstants()
        k.lr_amplitude = s.lr_amplitude
        k.lr_mean = rpx_to_normalized(s.lr_mean_rpx)
        k.lr_sigma = rpx_to_normalized(s.lr_sigma_rpx)
        k.lr_theta = s.lr_theta
        k.beta1 = s.beta1
        k.beta2 = s.beta2
        k.epsilon = s.epsilon
        return k

    def step(self) -> None:
        """Update every active slot from its gradient (does not zero the gradients)."""
        b = self.batch
        wp.launch(
            adam_step,
            dim=b.shape,
            inputs=[self._constants, b.arrays, b.grad_arrays, b.generation],
            outputs=[self.first, self.second, self.steps, self.seen],
            device=b.device,
            record_tape=False,
        )

    def reset(self, mask=None) -> None:
        """Forget the moments and step counts of the slots in ``mask`` (B, N) (all when None).

        Slots refilled through the batch's host methods are reset automatically; this is for the
        rest, e.g. a restart after parameters were changed by a kernel.
        """
        shape = self.batch.shape
        if mask is None:
            mask = np.ones(shape, dtype=bool)
        if isinstance(mask, wp.array):
            device_mask = mask
        else:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != shape:
                raise InputError(f"reset mask must have shape {shape}, got {mask.shape}")
            device_mask = wp.array(mask.astype(np.int32), dtype=wp.int32, device=self.batch.device)
        wp.launch(reset_slots, dim=shape, inputs=[device_mask], outputs=[self.first, self.second, self.steps],
                  device=self.batch.device, record_tape=False)
