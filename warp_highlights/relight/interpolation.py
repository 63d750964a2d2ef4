"""Interpolated Gaussian sets for query directions (method.md section 6), in float64 NumPy.

For a query in triangle (A, B, C) with barycentric (lA, lB, lC), each vertex V contributes its set
moved towards the other two vertices' retargeted sets: |amplitudes| and |sizes| blend barycentrically,
positions follow the stored circular paths (or straight lines), rotations turn by lB delta_AB + lC
delta_AC. The union of the three moved sets, weighted lA, lB, lC, is the interpolated set. At a vertex
(lA = 1) it is exactly G_A. This is the reference the relighting kernels are tested against; it is
batched over queries (no Python loop per query).
"""

from __future__ import annotations

import numpy as np

from ..model.arcs import circular_position
from ..model.errors import InputError
from ..model.gaussians import GaussianParams

__all__ = ["INTERPOLATION_METHODS", "edge_rows", "interpolate_sets"]

INTERPOLATION_METHODS = ("circular", "straight")


def interpolate_sets(field, vertices: np.ndarray, barycentric: np.ndarray, *, method: str = "circular") -> GaussianParams:
    """(Q, 3N) interpolated sets for queries given by their triangle vertices (Q, 3) and weights (Q, 3).

    Args:
        field: a ``HighlightField``.
        vertices: (Q, 3) light indices of each query's triangle (any order; weights follow it).
        barycentric: (Q, 3) non-negative weights summing to 1.
        method: "circular" (the stored paths) or "straight" (straight lines between the positions).
    """
    if method not in INTERPOLATION_METHODS:
        raise InputError(f"method must be one of {', '.join(INTERPOLATION_METHODS)}, got '{method}'")
    vertices = np.asarray(vertices, dtype=np.int64)
    weights = np.asarray(barycentric, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or weights.shape != vertices.shape:
        raise InputError(f"vertices and barycentric must both have shape (Q, 3), got {vertices.shape} and {weights.shape}")
    straight_below = field.fit_settings().paths.straight_below
    parts = []
    for k in range(3):
        a, b, c = vertices[:, k], vertices[:, (k + 1) % 3], vertices[:, (k + 2) % 3]
        la, lb, lc = weights[:, k], weights[:, (k + 1) % 3], weights[:, (k + 2) % 3]
        ab = edge_rows(field.directed_edges, field.light_count, a, b)
        ac = edge_rows(field.directed_edges, field.light_count, a, c)
        parts.append(_moved_vertex_set(field, a, ab, ac, la, lb, lc, method, straight_below))
    return GaussianParams.concatenate(parts, axis=1)


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


def _moved_vertex_set(field, a, ab, ac, la, lb, lc, method: str, straight_below: float) -> GaussianParams:
    """G'_A for every query: (Q, N); ``ab``, ``ac`` are the rows of edges A->B, A->C in the retargeted sets."""
    source = field.estimated
    to_b = to_c = field.retargeted
    active = source.active[a]
    # only a^2 is drawn and fitting may flip a's sign: blend |a| (like |sigma|)
    amplitude = la[:, None] * np.abs(source.amplitude[a]) + lb[:, None] * np.abs(to_b.amplitude[ab]) + lc[:, None] * np.abs(to_c.amplitude[ac])
    sigma = la[:, None, None] * np.abs(source.sigma[a]) + lb[:, None, None] * np.abs(to_b.sigma[ab]) + lc[:, None, None] * np.abs(to_c.sigma[ac])
    delta_b = field.path_delta[ab].astype(np.float64)
    delta_c = field.path_delta[ac].astype(np.float64)
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
