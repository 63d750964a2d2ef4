"""Height fields for shapes with relief: a struck coin's face and the small bumps of a worn or hand-made
surface. Pure NumPy, deterministic; lengths in the shape's units (the plate spans [-1, 1] in x and y).

What real captures hold and a smooth mesh does not: slopes that send a highlight across the surface in
steps and ridges, and fine bumps that break a highlight into glints.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BUMP_AMPLITUDE", "BUMP_WAVELENGTH", "bump_height", "coin_height"]

BUMP_AMPLITUDE = 0.006
"""Standard deviation of the bumps, in units of the shape before normalisation (a 1-unit torus tube is
0.4): about 1.5% of a tube's radius, enough to tilt normals by ~10 degrees."""
BUMP_WAVELENGTH = 0.12
"""Mean wavelength of the bumps (same units): a few bumps across a highlight of shininess ~100."""
_WAVES = 48  # sinusoids summed: enough for a pattern without visible periodicity
_SEED = 20261128  # the bumps are part of the shape: one fixed pattern


def bump_height(points: np.ndarray, *, amplitude: float = BUMP_AMPLITUDE,
                wavelength: float = BUMP_WAVELENGTH) -> np.ndarray:
    """(V,) smooth random heights at (V, 3) points: a sum of plane waves in random directions with
    wavelengths within [2/3, 3/2] of ``wavelength``, scaled to standard deviation ``amplitude``."""
    rng = np.random.default_rng(_SEED)
    directions = rng.normal(size=(_WAVES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    wavelengths = wavelength * rng.uniform(2.0 / 3.0, 1.5, size=_WAVES)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=_WAVES)
    waves = np.sin(np.asarray(points, dtype=np.float64) @ (directions.T * (2.0 * np.pi / wavelengths)) + phases)
    return amplitude * np.sqrt(2.0 / _WAVES) * waves.sum(axis=1)


def coin_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of a coin's face on the plate z = 0 at (x, y) in [-1, 1]^2: a raised rim, a bust in the
    middle, a ring of twelve beads and a worn, bumpy field; 0 outside the coin (r > 0.95)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    r = np.hypot(x, y)
    rim = 0.05 * _smooth_step(0.80, 0.84, r) * (1.0 - _smooth_step(0.90, 0.94, r))
    bust = 0.09 * np.exp(-((x + 0.08) ** 2 / 0.05 + (y - 0.04) ** 2 / 0.11)) * (1.0 - _smooth_step(0.5, 0.6, r))
    angle = np.arctan2(y, x)
    bead_angle = np.round(angle / (np.pi / 6.0)) * (np.pi / 6.0)
    bead_d2 = (x - 0.68 * np.cos(bead_angle)) ** 2 + (y - 0.68 * np.sin(bead_angle)) ** 2
    beads = 0.025 * np.exp(-bead_d2 / 0.0025)
    points = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
    wear = bump_height(points, amplitude=0.0006, wavelength=0.08).reshape(x.shape)
    inside = 1.0 - _smooth_step(0.94, 0.97, r)
    return (rim + bust + beads + wear) * inside


def _smooth_step(low: float, high: float, value: np.ndarray) -> np.ndarray:
    t = np.clip((value - low) / (high - low), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)
