"""Gaussian sets moved to query directions (docs/method.md, Relighting), in float64 NumPy, on plain arrays.

For a query in triangle (A, B, C) with barycentric (lA, lB, lC), each vertex V contributes its set
moved towards the other two vertices' retargeted sets: |amplitudes| and |sizes| blend barycentrically,
positions follow the circular paths (or straight lines), rotations turn by lB delta_AB + lC
delta_AC. The union of the three moved sets, weighted lA, lB, lC, is the interpolated set. At a vertex
(lA = 1) it is exactly G_A. ``relight.interpolation.interpolate_sets`` applies it to a field; the fit's
leave-one-out check (``fit.validation``) to triangles the field's own triangulation does not have.
Batched over queries (no Python loop per query). Units: means in image heights, angles in radians.
"""

from __future__ import annotations

import numpy as np

from .arcs import circular_position
from .errors import InputError
from .gaussians import GaussianParams

__all__ = ["INTERPOLATION_METHODS", "edge_rows", "move_sets"]

INTERPOLATION_METHODS = ("circular", "straight")


def move_sets(estimated: GaussianParams, retargeted: GaussianParams, directed_edges: np.ndarray, path_delta: np.ndarray,
              vertices: np.ndarray, barycentric: np.ndarray, *, method: str = "circular", straight_below: float,
              moving: np.ndarray | None = None) -> GaussianParams:
    """(Q, 3N) interpolated sets for queries given by their triangle vertices (Q, 3) and weights (Q, 3).

    Args:
        estimated: (n, N) every light's own set; retargeted: (E, N) the sets of ``directed_edges``
            (E, 2) (source, target), sorted lexicographically; path_delta: (E, N) their rotations.
        vertices: (Q, 3) light indices of each query's triangle (any order; weights follow it); every
            directed edge between two of them must be in ``directed_edges``.
        barycentric: (Q, 3) non-negative weights summing to 1.
        method: "circular" (the stored paths) or "straight" (straight lines between the positions).
        straight_below: rotations below this (radians) follow the chord (``PathSettings``).
        moving: (n, N) bool the Gaussians that move; the others stay at their own parameters, drawn
            with their corner's weight (None: all move).
    """
    if method not in INTERPOLATION_METHODS:
        raise InputError(f"method must be one of {', '.join(INTERPOLATION_METHODS)}, got '{method}'")
    vertices = np.asarray(vertices, dtype=np.int64)
    weights = np.asarray(barycentric, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or weights.shape != vertices.shape:
        raise InputError(
            f"vertices and barycentric must both have shape (Q, 3), got {vertices.shape} and {weights.shape}")
    light_count = len(estimated.active)
    parts = []
    for k in range(3):
        a, b, c = vertices[:, k], vertices[:, (k + 1) % 3], vertices[:, (k + 2) % 3]
        la, lb, lc = weights[:, k], weights[:, (k + 1) % 3], weights[:, (k + 2) % 3]
        ab = edge_rows(directed_edges, light_count, a, b)
        ac = edge_rows(directed_edges, light_count, a, c)
        part = _moved_vertex_set(estimated, retargeted, path_delta, a, ab, ac, la, lb, lc, method, straight_below)
        parts.append(part if moving is None else _in_place_unless_moving(part, estimated, moving, a))
    return GaussianParams.concatenate(parts, axis=1)


def _in_place_unless_moving(part: GaussianParams, source: GaussianParams, moving: np.ndarray, a) -> GaussianParams:
    """``part`` (the moved G'_A, (Q, N)) with every Gaussian of A that does not move back at its own parameters
    (its weight, lA, unchanged)."""
    still = (source.active[a] & ~np.asarray(moving, dtype=bool)[a])
    return GaussianParams(
        amplitude=np.where(still, np.abs(source.amplitude[a]), part.amplitude),
        mean=np.where(still[..., None], source.mean[a], part.mean),
        sigma=np.where(still[..., None], np.abs(source.sigma[a]), part.sigma),
        theta=np.where(still, source.theta[a], part.theta),
        weight=part.weight,
        active=part.active,
    )


def edge_rows(directed_edges: np.ndarray, light_count: int, sources, targets) -> np.ndarray:
    """Rows of the directed edges sources -> targets in ``directed_edges`` (sorted lexicographically,
    as ``SphericalTriangulation.directed_edges`` gives them); ``InputError`` if one is missing."""
    edges = np.asarray(directed_edges, dtype=np.int64)
    keys = edges[:, 0] * light_count + edges[:, 1]
    wanted = np.asarray(sources, dtype=np.int64) * light_count + np.asarray(targets, dtype=np.int64)
    rows = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
    if not np.all(keys[rows] == wanted):
        raise InputError("a triangle uses an edge the field has no retargeted sets for")
    return rows


def _moved_vertex_set(source: GaussianParams, retargeted: GaussianParams, path_delta: np.ndarray, a, ab, ac, la, lb, lc,
                      method: str, straight_below: float) -> GaussianParams:
    """G'_A for every query: (Q, N); ``ab``, ``ac`` are the rows of edges A->B, A->C in the retargeted sets."""
    to_b = to_c = retargeted
    active = source.active[a]
    # only a^2 is drawn and fitting may flip a's sign: blend |a| (like |sigma|)
    amplitude = (la[:, None] * np.abs(source.amplitude[a]) + lb[:, None] * np.abs(to_b.amplitude[ab])
                 + lc[:, None] * np.abs(to_c.amplitude[ac]))
    sigma = (la[:, None, None] * np.abs(source.sigma[a]) + lb[:, None, None] * np.abs(to_b.sigma[ab])
             + lc[:, None, None] * np.abs(to_c.sigma[ac]))
    delta_b = path_delta[ab].astype(np.float64)
    delta_c = path_delta[ac].astype(np.float64)
    theta = source.theta[a] + lb[:, None] * delta_b + lc[:, None] * delta_c
    mean_a = source.mean[a]
    if method == "circular":
        towards_b = circular_position(mean_a, to_b.mean[ab], delta_b, lb[:, None], straight_below)
        towards_c = circular_position(mean_a, to_c.mean[ac], delta_c, lc[:, None], straight_below)
        mean = towards_b + towards_c - mean_a
    else:
        mean = la[:, None, None] * mean_a + lb[:, None, None] * to_b.mean[ab] + lc[:, None, None] * to_c.mean[ac]
    weight = np.broadcast_to(la[:, None], active.shape).copy()
    zero = ~active
    return GaussianParams(
        amplitude=np.where(zero, 0.0, amplitude),
        mean=np.where(zero[..., None], 0.0, mean),
        sigma=np.where(zero[..., None], 0.0, sigma),
        theta=np.where(zero, 0.0, theta),
        weight=np.where(zero, 1.0, weight),
        active=active.copy(),
    )
