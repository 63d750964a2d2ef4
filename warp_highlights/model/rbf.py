"""Gaussian radial basis interpolation over light directions, in float64: the RBF baseline's and a low-rank
residual's interpolant (docs/method.md, The residual).

Values y_i at n unit light directions l_i are interpolated at a direction w as phi(w)^T (K + lambda I)^-1 y with
phi_i(w) = exp(-(|w - l_i| / sigma)^2), r = |w - l_i| the chord between unit vectors (0 to 2), K the (n, n)
matrix of phi between the lights (unit diagonal) and lambda a small regularisation. The per-light weights
phi(w)^T (K + lambda I)^-1 are what a relighter blends stored per-light rows with; sigma is chosen by
leave-one-out (Rippa 1999), whose errors have a closed form. (With a constant term added, the weights would sum to
1; measured along the light paths of ``benchmarks/bench_motion.py``, it scored 0.13-0.27 dB lower on the three
renders whose fits chose radial basis weights.)
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

__all__ = ["RBF_REGULARISATION", "RBF_SIGMA_FACTORS", "loo_sigma", "rbf_kernel", "rbf_loo_errors", "rbf_system",
           "rbf_weights", "sigma_candidates"]

RBF_REGULARISATION = 1e-6
"""lambda added to the RBF kernel matrix's unit diagonal: keeps (K + lambda I) invertible for nearly
coincident lights; the interpolant then misses a training value by about lambda times its weights."""

RBF_SIGMA_FACTORS = np.geomspace(0.5, 3.0, 41)
"""sigma candidates of the leave-one-out search, as multiples of the median chord from each light to its
nearest neighbour (0.34 on a 49-light dome). Larger sigma makes K so ill-conditioned that lambda, not
the data, shapes the interpolant (on the SynthRTI dome a second leave-one-out dip at 5 spacings
scores far worse on held-out lights)."""


def rbf_kernel(directions, centres, sigma: float) -> np.ndarray:
    """(Q, n) float64 exp(-(|w_q - c_i| / sigma)^2) for unit directions w (Q, 3) and centres c (n, 3)."""
    w = np.asarray(directions, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    chord2 = np.maximum((w * w).sum(1)[:, None] + (c * c).sum(1)[None, :] - 2.0 * w @ c.T, 0.0)
    return np.exp(-chord2 / (sigma * sigma))


def rbf_system(lights, sigma: float, regularisation: float = RBF_REGULARISATION) -> np.ndarray:
    """(n, n) float64 K + lambda I of the interpolation over unit ``lights`` (n, 3)."""
    return rbf_kernel(lights, lights, sigma) + regularisation * np.eye(len(lights))


def rbf_weights(directions, lights, sigma: float, regularisation: float = RBF_REGULARISATION) -> np.ndarray:
    """(Q, n) float64 per-light weights phi(w_q)^T (K + lambda I)^-1 at unit ``directions`` (Q, 3): times the
    lights' values (n, ...) they give the interpolant there (they do not sum to 1: far from every light
    they fall to 0)."""
    system = rbf_system(lights, sigma, regularisation)
    return np.linalg.solve(system, rbf_kernel(directions, lights, sigma).T).T  # K is symmetric


def rbf_loo_errors(matrix: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(n, S) leave-one-out errors of kernel interpolation, Rippa's closed form, float64.

    For each column y of ``values`` (n, S): e_i = (A^-1 y)_i / (A^-1)_ii with A = ``matrix`` (n, n),
    the error at light i of the interpolant fitted to the other n - 1 lights (exact for a regularised
    kernel matrix too: the prediction at light i uses K's off-diagonal row, not lambda).
    """
    inverse = np.linalg.inv(np.asarray(matrix, dtype=np.float64))
    return (inverse @ np.asarray(values, dtype=np.float64)) / np.diag(inverse)[:, None]


def sigma_candidates(lights) -> np.ndarray:
    """``RBF_SIGMA_FACTORS`` times the median chord from each of the unit ``lights`` (n >= 2) to its nearest
    neighbour (chord units)."""
    lights = np.asarray(lights, dtype=np.float64)
    chord = np.linalg.norm(lights[:, None] - lights[None], axis=2)
    np.fill_diagonal(chord, np.inf)
    spacing = float(np.median(chord.min(axis=1)))
    if not spacing > 0.0:
        raise InputError(
            "most lights coincide with another; the rbf sigma cannot be chosen from their spacing; pass sigma")
    return RBF_SIGMA_FACTORS * spacing


def loo_sigma(values, lights, *, candidates=None,
              regularisation: float = RBF_REGULARISATION) -> tuple[float, np.ndarray, np.ndarray]:
    """The sigma with the least mean squared leave-one-out error of ``values`` (n, S) at unit ``lights`` (n, 3).

    Returns (sigma, candidates, mean squared LOO error of each candidate); the first minimum on ties.
    ``candidates`` default to ``sigma_candidates(lights)``.
    """
    lights = np.asarray(lights, dtype=np.float64)
    if len(lights) < 2:
        raise InputError("choosing the rbf sigma by leave-one-out needs at least 2 lights; pass sigma")
    candidates = sigma_candidates(lights) if candidates is None else np.asarray(candidates, np.float64).reshape(-1)
    if candidates.size == 0 or not np.all(np.isfinite(candidates) & (candidates > 0)):
        raise InputError("rbf sigma candidates must be positive finite numbers")
    values = np.asarray(values, dtype=np.float64).reshape(len(lights), -1)
    errors = np.array([np.mean(rbf_loo_errors(rbf_system(lights, float(sigma), regularisation), values) ** 2)
                       for sigma in candidates])
    return float(candidates[int(np.argmin(errors))]), candidates, errors
