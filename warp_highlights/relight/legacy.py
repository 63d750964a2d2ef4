"""RTIViewer's models relit and fitted: a ``.ptm`` or ``.rti`` file's coefficients (``io.legacy_rti``) under any light
direction, and a capture's PTM or HSH made for those files."""

from __future__ import annotations

import numpy as np

from ..io.images import srgb_to_linear
from ..io.legacy_rti import LegacyRTI
from ..model.errors import InputError
from ..model.lights import LightSet
from .baselines import baseline_basis, fit_baseline
from .maps import SurfaceMaps, maps_from_images

__all__ = ["LEGACY_METHODS", "MAPS_LIGHTS", "fit_legacy", "legacy_surface_maps", "relight_legacy"]

MAPS_LIGHTS = 64
"""A legacy model's surface maps are estimated from it relit at this many dome lights (a Fibonacci dome above 15
degrees of elevation): about as many as a capture has, spread evenly where RTI domes light from."""

LEGACY_METHODS = {"ptm": "ptm", "rti": "hsh3"}
"""``export --format``'s legacy files and the baseline each holds (an ``.rti`` file: HSH of order 3)."""


def relight_legacy(model: LegacyRTI, directions) -> np.ndarray:
    """(Q, H, W, 3) float32 display values (clipped to [0, 1], as the viewers show them) of ``model`` at the (Q, 3)
    light directions."""
    terms = model.coefficients.shape[2]
    method = "ptm" if model.kind == "ptm" else {4: "hsh2", 9: "hsh3"}.get(terms)
    if method is None:
        raise InputError(f"HSH with {terms} terms cannot be relit here (4 or 9)")
    queries = np.asarray(directions, np.float64).reshape(-1, 3)
    queries = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    weights = baseline_basis(method, queries).astype(np.float32)
    return np.clip(np.einsum("qm,hwmc->qhwc", weights, model.coefficients), 0.0, 1.0)


def fit_legacy(file_format: str, values: np.ndarray, directions, *, device=None) -> np.ndarray:
    """(H, W, M, 3) float32 coefficients of ``LEGACY_METHODS[file_format]`` fitted by least squares to the
    (n, H, W, 3) display values at the (n, 3) light directions."""
    model = fit_baseline(LEGACY_METHODS[file_format], values, directions, device=device)
    return np.ascontiguousarray(model.coefficients().transpose(1, 2, 0, 3))


def legacy_surface_maps(model: LegacyRTI, *, flatten: bool | str = False) -> SurfaceMaps:
    """Normal, albedo and (white) highlight-colour maps of a legacy model, from it relit at ``MAPS_LIGHTS`` dome
    lights (``relight.maps.maps_from_images``; the relit values clip at white, which marks those lights
    unusable for the pixel)."""
    directions = LightSet.fibonacci_dome(MAPS_LIGHTS, min_elevation_deg=15.0).directions
    images = srgb_to_linear(relight_legacy(model, directions))
    return maps_from_images(images, directions, white=1.0, flatten=flatten)
