"""Whether a Gaussian's motion follows the light: the share of its retargeted displacements that a linear map of
the half-vector's change explains.

A highlight on a smooth surface sits where the normal is the half-vector, so as the light moves it glides by an
amount that is, locally, a linear function of the half-vector's change on the image (``fit.lost.expected_motion``).
A glint on a rough or bumpy surface does not glide: it flares and fades in place while another one lights up
nearby, and retargeting pairs it with whichever neighbouring glint lies closest, in no particular direction.
Moving such a Gaussian draws a glint sliding across the surface where the truth twinkles in place: it should blend.

For light i and slot p with k >= 3 outgoing edges e on which the Gaussian kept its highlight, with displacement d_e
(image heights) and the map M fitted to them:

    coherence = 1 - (sum_e |d_e - M dh_e|^2 / (2k - 4)) / (sum_e |d_e|^2 / (2k))

the share of the displacements' mean square that the map explains, adjusted for the 4 numbers of M fitted to 2k
(random displacements score about 0, a glide 1). Where a slot has fewer edges, or moves by less than
``_STILL_SIGMAS`` of its own size, there is nothing to tell (NaN).
"""

from __future__ import annotations

import numpy as np

from ..kernels.search import half_vector_changes
from ..model.gaussians import GaussianParams

__all__ = ["motion_coherence"]

_MIN_EDGES = 3
"""Edges a slot needs for a verdict: two determine the 2x2 map exactly (nothing left to explain)."""

_STILL_SIGMAS = 0.25
"""A slot whose root-mean-square displacement is under this share of its size (the geometric mean of its two
standard deviations) barely moves: moving it or blending it draws nearly the same image, and its direction is
noise."""


def motion_coherence(sources: GaussianParams, retargeted: GaussianParams, found: np.ndarray, edges: np.ndarray,
                     directions: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """(n, N) float64 each light's Gaussians' motion coherence (module docstring; NaN: no verdict).

    Args:
        sources: (E, N) each directed edge's source set; retargeted: (E, N) its retargeted set.
        found: (E, N) bool the slots that kept their highlight on the target (the motion's own edges).
        edges: (E, 2) directed edges (source, target) of the lights ``directions`` (n, 3).
        motion: (n, N, 2, 2) the fitted maps (``fit.lost.expected_motion`` of the same edges).
    """
    edges = np.asarray(edges, dtype=np.int64)
    n, capacity = motion.shape[:2]
    change = half_vector_changes(directions, edges)  # (E, 2)
    moved = retargeted.mean - sources.mean  # (E, N, 2)
    predicted = np.einsum("enij,ej->eni", motion[edges[:, 0]], change)
    found = np.asarray(found, bool)
    residual = np.where(found, np.sum((moved - predicted) ** 2, axis=-1), 0.0)
    total = np.where(found, np.sum(moved**2, axis=-1), 0.0)
    size = np.where(found, np.sqrt(np.abs(sources.sigma[..., 0] * sources.sigma[..., 1])), 0.0)
    sums = {name: np.zeros((n, capacity)) for name in ("residual", "total", "count", "size")}
    for name, values in (("residual", residual), ("total", total), ("count", found.astype(np.float64)),
                         ("size", size)):
        np.add.at(sums[name], edges[:, 0], values)
    count = sums["count"]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_square = sums["total"] / count
        still = mean_square < (_STILL_SIGMAS * sums["size"] / count) ** 2
        coherence = 1.0 - 2.0 * (sums["residual"] / (2.0 * count - 4.0)) / mean_square
    return np.where((count >= _MIN_EDGES) & ~still & (mean_square > 0), coherence, np.nan)
