"""Lost Gaussians: retargeted slots that lost their highlight, placed where their own motion expects it.

A retargeted Gaussian that found nothing on its target (``restore_vanished``) is put back at its source, so
that along that edge it fades in place; one that retargeting pushed out of the picture (nothing to fit where
it was) leaves it whichever way the optimiser took it. Two cases deserve better, and both are common where a
capture is sparse:

- the highlight has travelled out of the picture (a flat or gently curved object under a perspective camera
  or near lights: the highlight sweeps across it and off its edge as the light goes down). It should glide off
  the edge its motion leads to;
- the highlight travelled further than retargeting's search could follow. It should go where it went.

A highlight's position on the image is a smooth function of the half-vector h = (l + v) / |l + v| (it sits
where the surface's normal is h), so each Gaussian's motion is fitted as a linear map of the half-vector's
change on the image, from the outgoing edges on which it was found in the picture: d_e = M dh_e, by least
squares, pulled towards the capture's common isotropic map s I (a ridge). A lost slot (vanished, or with less
than ``RetargetSettings.lost_share`` of the light it had in the frame still in it) goes, with its source's
shape and brightness, to its expected position on the target where that lies outside the frame, or inside it
where the target's specular image holds it there (its support at least ``residual.move_support``); elsewhere
it stays as retargeting and ``restore_vanished`` left it (a highlight gone into a shadow or onto a matte part).

Units: means in image heights (x right, y down), the frame [0, width / height] x [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.search import half_vector_changes
from ..kernels.support import support_fractions
from ..model.config import RasterSettings
from ..model.gaussians import GaussianBatch, GaussianParams

__all__ = ["LostPlacement", "expected_motion", "follow_lost", "in_frame_share", "lost_slots", "place_lost"]

_GRID = 17
"""Samples along each axis of a Gaussian's own coordinates for ``in_frame_share`` (289 a slot: the share within
0.03 of sampling a million points, ``tests/test_lost.py``; enough to tell a Gaussian in the picture from one
pushed out of it)."""

_SAMPLES_AT_ONCE = 1 << 22
"""Samples ``in_frame_share`` holds at once (about 32 MiB an array), however many edges and slots."""


@dataclass(frozen=True)
class LostPlacement:
    """Attributes: sets (E, N) the retargeted sets with the lost slots placed; left_frame, followed (E, N) bool the
    lost slots sent out of the frame and those sent to their expected place inside it; motion (n, N, 2, 2) the
    ``expected_motion`` (for the move check's edges); found (E, N) bool the slots it was fitted on (those that kept
    their highlight)."""

    sets: GaussianParams
    left_frame: np.ndarray
    followed: np.ndarray
    motion: np.ndarray
    found: np.ndarray


def expected_motion(sources: GaussianParams, retargeted: GaussianParams, found: np.ndarray, edges: np.ndarray,
                    directions: np.ndarray, *, ridge: float) -> np.ndarray:
    """(n, N, 2, 2) each light's Gaussians' image motion per unit change of the half-vector on the image.

    Args:
        sources: (E, N) each edge's source set; retargeted: (E, N) the sets on the targets.
        found: (E, N) bool the slots that found their highlight on the target (active, not vanished).
        edges: (E, 2) directed edges (source, target) of lights ``directions`` (n, 3).
        ridge: the pull towards the capture's isotropic map, in shares of the median edge's squared change
            (``RetargetSettings.motion_ridge``).
    """
    edges = np.asarray(edges, dtype=np.int64)
    n = len(directions)
    capacity = sources.active.shape[1]
    change = half_vector_changes(directions, edges)  # (E, 2)
    moved = np.where(found[..., None], retargeted.mean - sources.mean, 0.0)  # (E, N, 2)
    weight = found.astype(np.float64)
    outer = weight[..., None, None] * change[:, None, :, None] * change[:, None, None, :]  # (E, N, 2, 2)
    cross = moved[..., :, None] * change[:, None, None, :] * weight[..., None, None]  # d dh^T
    gram = np.zeros((n, capacity, 2, 2))
    products = np.zeros((n, capacity, 2, 2))
    np.add.at(gram, edges[:, 0], outer)
    np.add.at(products, edges[:, 0], cross)
    squared = np.sum(change**2, axis=1)
    common = float(np.trace(products.sum(axis=(0, 1))) / max(np.trace(gram.sum(axis=(0, 1))), 1e-300))
    pull = ridge * (float(np.median(squared)) if len(squared) else 0.0) + 1e-12
    eye = np.eye(2)
    return (products + pull * common * eye) @ np.linalg.inv(gram + pull * eye)


def in_frame_share(params: GaussianParams, aspect: float) -> np.ndarray:
    """(B, N) the share of each slot's light that falls inside the frame [0, aspect] x [0, 1] (image heights),
    from the Gaussian sampled at a fixed grid of its own standard coordinates (within 3 sigma, weighted by
    the density); 0 for a free slot."""
    axis = np.linspace(-3.0, 3.0, _GRID)
    u, v = (grid.ravel() for grid in np.meshgrid(axis, axis, indexing="xy"))
    density = np.exp(-0.5 * (u**2 + v**2))
    density /= density.sum()
    share = np.zeros(params.active.shape)
    step = max(1, _SAMPLES_AT_ONCE // (u.size * max(1, params.active.shape[1])))  # rows a block: bounded memory
    for start in range(0, len(share), step):
        rows = slice(start, start + step)
        cos, sin = np.cos(params.theta[rows])[..., None], np.sin(params.theta[rows])[..., None]
        du = np.abs(params.sigma[rows, :, 0])[..., None] * u
        dv = np.abs(params.sigma[rows, :, 1])[..., None] * v
        x = params.mean[rows, :, 0, None] + cos * du - sin * dv
        y = params.mean[rows, :, 1, None] + sin * du + cos * dv
        share[rows] = ((x >= 0) & (x <= aspect) & (y >= 0) & (y <= 1)) @ density
    return np.where(params.active, share, 0.0)


def lost_slots(sources: GaussianParams, sets: GaussianParams, vanished: np.ndarray, aspect: float,
               share: float) -> np.ndarray:
    """(E, N) bool the retargeted slots that lost their highlight: vanished, or with less than ``share`` of the
    light they had inside the frame at their source left inside it."""
    inside = in_frame_share(sets, aspect) < share * in_frame_share(sources, aspect)
    return vanished | (sets.active & sources.active & inside)


def place_lost(sources: GaussianParams, sets: GaussianParams, lost: np.ndarray, edges: np.ndarray,
               directions: np.ndarray, motion: np.ndarray, specular_luminance: wp.array, *, landing: float,
               raster: RasterSettings) -> tuple[GaussianParams, np.ndarray, np.ndarray]:
    """``sets`` with the ``lost`` slots at their expected position on the target, their source's shape and
    brightness, where that lies outside the frame or where the target's specular image supports them there
    (``kernels.support``, at least ``landing``).

    Args:
        sources, sets: (E, N) each directed edge's source set and its retargeted set (vanished slots put back).
        lost: (E, N) bool (``lost_slots``); edges: (E, 2) (source, target) of lights ``directions`` (n, 3).
        motion: (n, N, 2, 2) the lights' Gaussians' ``expected_motion``.
        specular_luminance: (n, H, W) the targets' specular part (the frame's aspect is its width over height).
    Returns the sets and the (E, N) masks of the slots sent out of the frame and of those placed inside it.
    """
    edges = np.asarray(edges, dtype=np.int64)
    lost = lost & sources.active
    none = np.zeros_like(lost)
    if not lost.any():
        return sets, none, none
    _, height, width = specular_luminance.shape
    change = half_vector_changes(directions, edges)
    expected = sources.mean + np.einsum("enij,ej->eni", motion[edges[:, 0]], change)
    outside = ((expected[..., 0] < 0) | (expected[..., 0] > width / height) | (expected[..., 1] < 0)
               | (expected[..., 1] > 1))
    moved = sources.copy()
    moved.mean = np.where(lost[..., None], expected, sources.mean)
    moved.active = lost & ~outside
    followed = none
    if moved.active.any():
        rows = np.flatnonzero(moved.active.any(axis=1))
        batch = GaussianBatch.from_numpy(moved.take(rows), device=specular_luminance.device, requires_grad=False)
        support = support_fractions(batch, edges[rows, 1], specular_luminance, settings=raster)
        followed = none.copy()
        followed[rows] = moved.active[rows] & (support >= landing)
    left = lost & outside
    placed = left | followed
    out = sources.where(placed, sets)
    out.mean = np.where(placed[..., None], expected, out.mean)
    return out, left, followed


def follow_lost(sources: GaussianParams, sets: GaussianParams, vanished: np.ndarray, edges: np.ndarray,
                directions: np.ndarray, specular_luminance: wp.array, *, share: float, ridge: float, landing: float,
                raster: RasterSettings) -> LostPlacement:
    """The fit's edges: the motion fitted on the slots that kept their highlight, then the lost ones placed
    (``lost_slots``, ``place_lost``)."""
    _, height, width = specular_luminance.shape
    lost = lost_slots(sources, sets, vanished, width / height, share)
    found = sources.active & sets.active & ~lost
    motion = expected_motion(sources, sets, found, edges, directions, ridge=ridge)
    out, left, followed = place_lost(sources, sets, lost, edges, directions, motion, specular_luminance,
                                     landing=landing, raster=raster)
    return LostPlacement(out, left, followed, motion, found)
