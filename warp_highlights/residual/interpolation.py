"""How relighting weighs a low-rank residual's captured lights, chosen once per fit (``ResidualSettings.interpolation``,
docs/method.md, The residual): the query triangle's barycentric weights, or radial basis weights over every light
(``model.rbf``).

Each checked light j is predicted from the other lights both ways: the triangle's corners in the triangulation
without j (the move check's ``LeaveOneOut``), and the radial basis interpolant of the other lights, whose weights
have a closed form (Rippa): W = I - diag(A^-1)^-1 A^-1 with A = K + lambda I over every light, a row j that leaves
j out. Both
predictions add light j's own highlights c(x) G_j (what the field draws there either way) and are scored against
image j in 8-bit sRGB, as the move check scores. The radial basis sigma is the one with the
least leave-one-out error of the residual itself (``model.rbf.loo_sigma``) at a fixed subsample of pixels.
Units: the field's (``factor`` per display unit).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..io.images import display_rgb8
from ..model.config import ResidualSettings
from ..model.errors import InputError
from ..model.rbf import loo_sigma, rbf_system
from ..model.residual import LowRankStack, ResidualModel, code_levels
from ..model.threads import parallel_map
from ..quality.metrics import psnr_8bit
from .decode import light_images

__all__ = ["SIGMA_PIXELS", "InterpolationChoice", "choose_interpolation", "loo_rbf_weights", "residual_sigma",
           "stack_values_at"]

SIGMA_PIXELS = 4096
"""Pixels (a fixed draw) at which the residual's stacks score the radial basis sigma candidates (the RBF
baseline's ``RBF_LOO_PIXELS``)."""

_LIGHTS_A_BLOCK = 8  # checked lights predicted at once (two float64 images each, both ways)


@dataclass(frozen=True)
class InterpolationChoice:
    """What ``choose_interpolation`` measured: the chosen "triangle" or "rbf", the radial basis width (chord
    units), and (m,) 8-bit sRGB PSNR (dB) of both predictions at the checked lights (empty where none was
    checked)."""

    chosen: str
    sigma: float | None
    lights: np.ndarray
    triangle_psnr: np.ndarray
    rbf_psnr: np.ndarray

    def report(self) -> dict:
        """Plain figures for the fit report."""
        out = {"chosen": self.chosen, "lights": int(len(self.lights))}
        if self.sigma is not None:
            out["rbf_sigma"] = round(float(self.sigma), 5)
        if len(self.lights):
            out["triangle_psnr_db"] = round(float(np.mean(self.triangle_psnr)), 3)
            out["rbf_psnr_db"] = round(float(np.mean(self.rbf_psnr)), 3)
        return out


def stack_values_at(stack: LowRankStack, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """(n, S, P) float64 every light's stack values at S pixels (``rows``, ``columns``), dequantised as
    ``decode.band_basis`` does, without decoding the rest of the images."""
    levels = np.float64(code_levels(stack.bits))
    low, high = stack.ranges[:, 0].astype(np.float64), stack.ranges[:, 1].astype(np.float64)
    codes = stack.codes[:, rows, columns].astype(np.float64)  # (k, S, P)
    basis = low[:, None, None] + codes * ((high - low) / levels)[:, None, None]
    values = np.tensordot(stack.weights.astype(np.float64), basis, axes=1)
    return values + stack.mean_weights.astype(np.float64)[:, None, None] * stack.mean[rows, columns][None]


def loo_rbf_weights(lights: np.ndarray, sigma: float) -> np.ndarray:
    """(n, n) float64: row j the radial basis weights that predict light j from the other lights (zero at j)."""
    inverse = np.linalg.inv(rbf_system(lights, sigma))
    return np.eye(len(lights)) - inverse / np.diag(inverse)[:, None]


def choose_interpolation(residual: ResidualModel, images: np.ndarray, own: np.ndarray, colour: np.ndarray | None,
                         directions: np.ndarray, checked: np.ndarray, corners: np.ndarray, barycentric: np.ndarray, *,
                         factor: float, settings: ResidualSettings,
                         seed: int = 0) -> tuple[ResidualModel, InterpolationChoice]:
    """The low-rank ``residual`` with the interpolation ``settings.interpolation`` asks for ("auto": the better
    at the ``checked`` lights, by ``settings.interpolation_margin_db``), and what was measured.

    Args:
        residual: a low-rank residual of the n captured lights (others are returned as they are).
        images: (n, H, W, C) the captured images; own: (n, H, W) their own highlights drawn; colour: (H, W, C)
            the highlight colour or None (white); field units.
        directions: (n, 3) the lights' unit directions.
        checked: (m,) lights left out one at a time; corners, barycentric: (m, 3) their triangles in the
            other lights' triangulations (``fit.validation.LeaveOneOut``).
        factor: field units per display unit.
    """
    wanted = settings.interpolation
    if residual.luminance is None or wanted == "triangle":
        return residual, InterpolationChoice("triangle", None, np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    directions = np.asarray(directions, dtype=np.float64)
    n = len(directions)
    if n < 3:
        if wanted == "rbf":
            raise InputError(f"a radial basis residual needs at least 3 lights, got {n}")
        return residual, InterpolationChoice("triangle", None, np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    sigma = residual_sigma(residual, directions, seed=seed)
    checked = np.asarray(checked, dtype=np.int64)
    triangle_psnr = rbf_psnr = np.zeros(0)
    if len(checked):
        triangle_psnr, rbf_psnr = _scores(residual, images, own, colour, directions, checked, corners, barycentric,
                                          sigma, 1.0 / factor)
    keeps = wanted == "rbf" or (len(checked) > 0
                                and float(np.mean(rbf_psnr)) >= float(np.mean(triangle_psnr))
                                + settings.interpolation_margin_db)
    choice = InterpolationChoice("rbf" if keeps else "triangle", sigma, checked, triangle_psnr, rbf_psnr)
    return (replace(residual, rbf_sigma=sigma) if keeps else residual), choice


def residual_sigma(residual: ResidualModel, directions: np.ndarray, *, seed: int = 0) -> float:
    """The radial basis width (chord units) with the least leave-one-out error of the residual's stacks (luminance,
    and chroma where kept) at ``SIGMA_PIXELS`` pixels drawn with ``seed``, in the stacks' normalised units."""
    height, width = residual.height, residual.width
    count = height * width
    pixels = np.random.default_rng(seed).choice(count, size=min(SIGMA_PIXELS, count), replace=False)
    rows, columns = np.divmod(np.sort(pixels), width)
    values = [stack_values_at(stack, rows, columns).reshape(len(directions), -1)
              for stack in (residual.luminance, residual.chroma) if stack is not None]
    sigma, _, _ = loo_sigma(np.concatenate(values, axis=1), directions)
    return sigma


def _scores(residual, images, own, colour, directions, checked, corners, barycentric, sigma,
            display_scale) -> tuple[np.ndarray, np.ndarray]:
    """(m,) 8-bit sRGB PSNR of the triangle's and the radial basis's predictions of each checked light."""
    n, m = len(directions), len(checked)
    triangle = np.zeros((m, n))
    np.add.at(triangle, (np.arange(m)[:, None], np.asarray(corners, dtype=np.int64)), barycentric)
    rbf = loo_rbf_weights(directions, sigma)[checked]
    colour = np.ones((1, 1, 1)) if colour is None else np.asarray(colour, dtype=np.float64)
    scores = np.zeros((2, m))

    def block(start: int) -> None:
        part = slice(start, min(start + _LIGHTS_A_BLOCK, m))
        lights = checked[part]
        highlights = colour[None] * np.asarray(own[lights], dtype=np.float64)[..., None]
        truth = [display_rgb8(images[light] * display_scale) for light in lights]
        for row, weights in enumerate((triangle[part], rbf[part])):
            predicted = light_images(residual, weights) + highlights
            scores[row, part] = [psnr_8bit(display_rgb8(np.maximum(image, 0.0) * display_scale), target)
                                 for image, target in zip(predicted, truth)]

    parallel_map(block, list(range(0, m, _LIGHTS_A_BLOCK)))
    return scores[0], scores[1]
