"""Circular paths of Gaussians: the geometry of the paths a highlight field stores (docs/method.md, Fitting step 6).

A Gaussian p of the estimated set G_A reappears as slot p of the retargeted set G_{A->B}. Between
the two it turns by a signed angle delta, which can be either of two options that reach the same
orientation (orientations live in [0, pi)):

- the positive option delta+ = wrap_[0, pi)(theta_{A->B} - theta_A), and
- the negative option delta- = delta+ - pi.

Along the edge its mean follows the arc of the circle about the centre O that turns mu_A into
mu_B by delta: ``R(delta)(mu_A - O) + O = mu_B``, with ``R(a) = [[cos a, -sin a], [sin a, cos a]]``
acting on (x, y). For |delta| below ``PathSettings.straight_below`` the arc is replaced by the
straight segment (O then recedes to infinity; the centre returned is the chord's midpoint).

Which option each Gaussian takes is decided once, at fit time (``warp_highlights.fit.paths``); the
interpolation then only evaluates ``circular_position``.

Units: means and centres in image heights (x right, y down); angles in radians from +x towards +y.
Every function is vectorised NumPy float64 and broadcasts over leading axes.
"""

from __future__ import annotations

import numpy as np

from .config import PathSettings
from .errors import InputError

__all__ = ["circular_position", "path_centre", "rotate_vectors", "rotation_options", "wrap_half_turn"]


def wrap_half_turn(angle: np.ndarray) -> np.ndarray:
    """``angle`` (radians) wrapped to [0, pi); rounding can never return pi itself."""
    wrapped = np.mod(angle, np.pi)
    return np.where(wrapped >= np.pi, 0.0, wrapped)


def _straight_threshold(straight_below: float | None) -> float:
    if straight_below is None:
        return PathSettings().straight_below
    value = float(straight_below)
    if not (np.isfinite(value) and value >= 0):
        raise InputError(
            f"straight_below must be a finite angle >= 0 (radians), got {straight_below}"
        )
    return value


def _perpendicular(vector: np.ndarray) -> np.ndarray:
    """``vector`` (..., 2) turned by +pi/2, i.e. R(pi/2) applied to (x, y)."""
    return np.stack([-vector[..., 1], vector[..., 0]], axis=-1)


def rotate_vectors(vector: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """R(angle) applied to ``vector`` (..., 2); ``angle`` broadcasts against ``vector[..., 0]``."""
    cos, sin = np.cos(angle), np.sin(angle)
    x, y = vector[..., 0], vector[..., 1]
    return np.stack([cos * x - sin * y, sin * x + cos * y], axis=-1)


def rotation_options(theta_a, theta_b) -> tuple[np.ndarray, np.ndarray]:
    """The two signed rotations that turn orientation ``theta_a`` into ``theta_b`` (mod pi).

    Args:
        theta_a: orientation in G_A, radians, any shape (any range: only its value mod pi counts).
        theta_b: orientation in G_{A->B}, radians, broadcastable with ``theta_a``.

    Returns:
        ``(delta_pos, delta_neg)``, radians: delta+ = wrap_[0, pi)(theta_b - theta_a) in [0, pi)
        and delta- = delta+ - pi in [-pi, 0).
    """
    delta_pos = wrap_half_turn(
        np.asarray(theta_b, dtype=np.float64) - np.asarray(theta_a, dtype=np.float64)
    )
    return delta_pos, delta_pos - np.pi


def path_centre(
    mean_a, mean_b, delta, straight_below: float | None = None
) -> np.ndarray:
    """Centre O of the arc that carries ``mean_a`` to ``mean_b`` while turning by ``delta``.

    O lies on the chord's perpendicular bisector, at ``midpoint + cot(delta / 2) / 2 * R(pi/2)(mean_b -
    mean_a)``, so that ``R(delta)(mean_a - O) + O == mean_b``.

    Args:
        mean_a: start positions (..., 2), image heights.
        mean_b: end positions (..., 2), image heights.
        delta: signed rotations (...), radians, meant to lie in [-pi, pi].
        straight_below: |delta| (radians) under which the path is the straight segment; default
            ``PathSettings().straight_below``. delta = 0 is always straight.

    Returns:
        O, (..., 2) image heights (broadcast shape). Straight paths get the chord's midpoint (finite,
        unused by the path). Coincident ends give O = mean_a; |delta| = pi gives the midpoint.
    """
    threshold = _straight_threshold(straight_below)
    mean_a = np.asarray(mean_a, dtype=np.float64)
    mean_b = np.asarray(mean_b, dtype=np.float64)
    delta = np.asarray(delta, dtype=np.float64)
    midpoint = 0.5 * (mean_a + mean_b)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        half = 0.5 * delta
        cot = np.cos(half) / np.sin(half)
        straight = ~(np.abs(delta) >= threshold) | ~np.isfinite(cot)
        cot = np.where(straight, 0.0, cot)
        centre = midpoint + 0.5 * cot[..., None] * _perpendicular(mean_b - mean_a)
    return np.where(np.isfinite(centre).all(axis=-1, keepdims=True), centre, midpoint)


def circular_position(
    mean_a, mean_b, delta, fraction, straight_below: float | None = None
) -> np.ndarray:
    """Position a ``fraction`` of the way along the path from ``mean_a`` to ``mean_b``.

    The path is the arc ``R(fraction * delta)(mean_a - O) + O`` with O = ``path_centre(mean_a, mean_b,
    delta)``. It is evaluated in the equivalent chord form ``mean_a + sin(fraction * delta / 2) /
    sin(delta / 2) * R((fraction - 1) * delta / 2)(mean_b - mean_a)``, which needs no O and loses
    no precision when the radius is large. For |delta| below ``straight_below`` (and delta = 0) it is
    the straight blend ``mean_a + fraction * (mean_b - mean_a)``, the arc's limit.

    Args:
        mean_a: start positions (..., 2), image heights (mu_A).
        mean_b: end positions (..., 2), image heights (mu_{A->B}).
        delta: the chosen signed rotations (...), radians, in [-pi, pi] (``PathDecisions.delta``).
        fraction: how far along, (...) or scalar; 0 gives ``mean_a``, 1 gives ``mean_b`` (the
            barycentric weight of the edge's far vertex during interpolation).
        straight_below: as in ``path_centre`` (use the same value for both).

    Returns:
        Positions (..., 2), image heights (broadcast shape).
    """
    threshold = _straight_threshold(straight_below)
    mean_a = np.asarray(mean_a, dtype=np.float64)
    chord = np.asarray(mean_b, dtype=np.float64) - mean_a
    delta = np.asarray(delta, dtype=np.float64)
    fraction = np.asarray(fraction, dtype=np.float64)
    delta, fraction = np.broadcast_arrays(delta, fraction)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        sin_half = np.sin(0.5 * delta)
        straight = ~(np.abs(delta) >= threshold) | (sin_half == 0)
        scale = np.where(
            straight,
            fraction,
            np.sin(0.5 * fraction * delta) / np.where(straight, 1.0, sin_half),
        )
        turn = np.where(straight, 0.0, 0.5 * (fraction - 1.0) * delta)
        position = mean_a + scale[..., None] * rotate_vectors(chord, turn)
        blend = mean_a + fraction[..., None] * chord
    return np.where(np.isfinite(position).all(axis=-1, keepdims=True), position, blend)
