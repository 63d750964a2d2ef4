"""Kernels of retargeting phase 1: rigid motions of connected components, and the image gather.

Phase 1 moves every connected component of a set as one rigid body: a translation t_c and a rotation
phi_c about the component's energy-weighted centroid o_c,

    mu' = R(phi_c)(mu - o_c) + o_c + t_c,    theta' = theta + phi_c,

with amplitude and sizes unchanged. ``apply_rigid`` writes the moved set into a ``GaussianBatch``
(which the rasterizer then draws) and registers its adjoint on the tape; ``RigidAdam`` steps the
motions. One launch covers every (problem, slot).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_highlights.model.config import rpx_to_normalized
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianArrays, GaussianBatch

from .tape import active_tape

__all__ = ["RigidAdam", "RigidMotion", "apply_rigid", "apply_rigid_backward", "gather_images", "rigid_adam_step",
           "rotate_vec2"]


@wp.func
def rotate_vec2(v: wp.vec2, angle: float) -> wp.vec2:
    """R(angle) v: turns (x, y) by ``angle`` radians from +x towards +y."""
    c = wp.cos(angle)
    s = wp.sin(angle)
    return wp.vec2(c * v[0] - s * v[1], s * v[0] + c * v[1])


@wp.kernel
def apply_rigid(
    source: GaussianArrays,
    labels: wp.array2d(dtype=wp.int32),
    centroids: wp.array2d(dtype=wp.vec2),
    motion: wp.array2d(dtype=wp.vec3),
    moved: GaussianArrays,
):
    """moved[b, p] = source[b, p] moved by motion[b, labels[b, p]] = (t_x, t_y, phi) about centroids[b, p]."""
    b, p = wp.tid()
    if source.active[b, p] == 0:
        return
    m = motion[b, labels[b, p]]
    offset = source.mean[b, p] - centroids[b, p]
    moved.mean[b, p] = rotate_vec2(offset, m[2]) + centroids[b, p] + wp.vec2(m[0], m[1])
    moved.theta[b, p] = source.theta[b, p] + m[2]
    moved.amplitude[b, p] = source.amplitude[b, p]
    moved.sigma[b, p] = source.sigma[b, p]
    moved.weight[b, p] = source.weight[b, p]


@wp.kernel
def apply_rigid_backward(
    source: GaussianArrays,
    labels: wp.array2d(dtype=wp.int32),
    centroids: wp.array2d(dtype=wp.vec2),
    motion: wp.array2d(dtype=wp.vec3),
    moved_grad: GaussianArrays,
    motion_grad: wp.array2d(dtype=wp.vec3),
):
    """motion_grad[b, c] += d(moved[b, p]) / d(motion) applied to the moved set's gradient, for p in component c."""
    b, p = wp.tid()
    if source.active[b, p] == 0:
        return
    c = labels[b, p]
    angle = motion[b, c][2]
    offset = source.mean[b, p] - centroids[b, p]
    g = moved_grad.mean[b, p]
    # d/dphi of R(phi) offset is R(phi + pi/2) offset
    turn = rotate_vec2(offset, angle + 0.5 * wp.pi)
    wp.atomic_add(motion_grad, b, c, wp.vec3(g[0], g[1], wp.dot(g, turn) + moved_grad.theta[b, p]))


@wp.kernel
def rigid_adam_step(
    motion: wp.array2d(dtype=wp.vec3),
    grad: wp.array2d(dtype=wp.vec3),
    used: wp.array2d(dtype=wp.int32),
    lr_translation: float,
    lr_rotation: float,
    beta1: float,
    beta2: float,
    epsilon: float,
    first: wp.array2d(dtype=wp.vec3),
    second: wp.array2d(dtype=wp.vec3),
    steps: wp.array2d(dtype=wp.int32),
):
    """One Adam step of every used component motion (translation and rotation have their own rates)."""
    b, c = wp.tid()
    if used[b, c] == 0:
        return
    g = grad[b, c]
    if not (wp.isfinite(g[0]) and wp.isfinite(g[1]) and wp.isfinite(g[2])):
        return
    t = steps[b, c] + 1
    steps[b, c] = t
    m = beta1 * first[b, c] + (1.0 - beta1) * g
    v = beta2 * second[b, c] + (1.0 - beta2) * wp.cw_mul(g, g)
    first[b, c] = m
    second[b, c] = v
    correction1 = 1.0 - wp.pow(beta1, float(t))
    correction2 = 1.0 - wp.pow(beta2, float(t))
    step = wp.vec3()
    for k in range(3):
        rate = lr_translation
        if k == 2:
            rate = lr_rotation
        step[k] = rate * (m[k] / correction1) / (wp.sqrt(v[k] / correction2) + epsilon)
    motion[b, c] = motion[b, c] - step


@wp.kernel
def gather_images(images: wp.array3d(dtype=float), index: wp.array(dtype=wp.int32), out: wp.array3d(dtype=float)):
    """out[b] = images[index[b]]."""
    b, row, col = wp.tid()
    out[b, row, col] = images[index[b], row, col]


class RigidMotion:
    """One rigid motion per connected component of every set of a batch, applied differentiably.

    Args:
        source: the sets to move (fixed).
        labels: (B, N) component of every slot (any value on free slots).
        centroids: (B, N, 2) centre of rotation of every slot's component (image heights).
    """

    def __init__(self, source: GaussianBatch, labels: np.ndarray, centroids: np.ndarray):
        shape = source.shape
        labels = np.asarray(labels)
        if labels.shape != shape or np.asarray(centroids).shape != (*shape, 2):
            raise InputError(f"labels and centroids must have shapes {shape} and {(*shape, 2)}")
        self.source = source
        device = source.device
        labels = np.where(source.active.numpy() != 0, labels, 0).astype(np.int32)
        if labels.min() < 0 or labels.max() >= shape[1]:
            raise InputError("component labels must lie in 0..capacity-1 on active slots")
        self.labels = wp.array(labels, dtype=wp.int32, device=device)
        self.centroids = wp.array(np.asarray(centroids, dtype=np.float32), dtype=wp.vec2, device=device)
        used = np.zeros(shape, dtype=np.int32)
        active = source.active.numpy() != 0
        used[np.nonzero(active)[0], labels[active]] = 1
        self.used = wp.array(used, dtype=wp.int32, device=device)
        self.motion = wp.zeros(shape, dtype=wp.vec3, device=device, requires_grad=True)

    def apply(self, out: GaussianBatch) -> GaussianBatch:
        """Write the moved sets into ``out`` (same shape; its active mask must equal the source's)."""
        src = self.source
        if out.shape != src.shape or out.device != src.device:
            raise InputError(f"out must be a {src.shape} batch on {src.device}")
        inputs = [src.arrays, self.labels, self.centroids, self.motion]
        wp.launch(apply_rigid, dim=src.shape, inputs=inputs, outputs=[out.arrays], device=src.device, record_tape=False)
        tape = active_tape()
        if tape is not None and out.requires_grad:

            def backward():
                wp.launch(apply_rigid_backward, dim=src.shape, inputs=[*inputs, out.grad_arrays],
                          outputs=[self.motion.grad], device=src.device, record_tape=False)

            tape.record_func(backward=backward, arrays=[*out.parameters(), self.motion])
        return out


class RigidAdam:
    """Adam over the component motions of a ``RigidMotion`` (translation in rpx, rotation in radians)."""

    def __init__(self, rigid: RigidMotion, *, lr_translation_rpx: float, lr_rotation: float, beta1: float = 0.9,
                 beta2: float = 0.999, epsilon: float = 1e-8):
        self.rigid = rigid
        shape = rigid.motion.shape
        device = rigid.motion.device
        self.first = wp.zeros(shape, dtype=wp.vec3, device=device)
        self.second = wp.zeros(shape, dtype=wp.vec3, device=device)
        self.steps = wp.zeros(shape, dtype=wp.int32, device=device)
        self.constants = [rpx_to_normalized(lr_translation_rpx), float(lr_rotation), float(beta1), float(beta2),
                          float(epsilon)]

    def step(self) -> None:
        r = self.rigid
        wp.launch(
            rigid_adam_step,
            dim=r.motion.shape,
            inputs=[r.motion, r.motion.grad, r.used, *self.constants],
            outputs=[self.first, self.second, self.steps],
            device=r.motion.device,
            record_tape=False,
        )
