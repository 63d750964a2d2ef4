"""Interpolated Gaussian sets of a field for query directions (docs/method.md, Relighting), in float64 NumPy.

``interpolate_sets`` applies ``model.interpolation.move_sets`` (the geometry, on plain arrays) to a
field's Gaussians, retargeted sets, stored paths and move decisions (a Gaussian that does not move is
drawn at its own parameters with its corner's weight). This is the reference the relighting kernels are
tested against; it is batched over queries (no Python loop per query).
"""

from __future__ import annotations

import numpy as np

from ..model.gaussians import GaussianParams
from ..model.interpolation import INTERPOLATION_METHODS, edge_rows, move_sets

__all__ = ["INTERPOLATION_METHODS", "edge_rows", "interpolate_sets"]


def interpolate_sets(field, vertices: np.ndarray, barycentric: np.ndarray, *,
                     method: str = "circular") -> GaussianParams:
    """(Q, 3N) interpolated sets for queries given by their triangle vertices (Q, 3) and weights (Q, 3).

    Args:
        field: a ``HighlightField``.
        vertices: (Q, 3) light indices of each query's triangle (any order; weights follow it).
        barycentric: (Q, 3) non-negative weights summing to 1.
        method: "circular" (the stored paths) or "straight" (straight lines between the positions).
    """
    return move_sets(field.estimated, field.retargeted, field.directed_edges, field.path_delta, vertices, barycentric,
                     method=method, straight_below=field.fit_settings().paths.straight_below, moving=field.moving_mask)
