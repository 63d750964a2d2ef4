"""The classic RTI relighting methods as baselines: PTM, HSH and RBF, fitted and relit on a device.

Each is linear in the image values: per pixel and channel, the value under a light direction w is
sum_m b_m(w) c_m, with M basis functions b_m shared by every pixel and M coefficients c_m per pixel.

- ``ptm``: polynomial texture maps (Malzbender et al. 2001), the biquadratic in the projected light
  direction (lu, lv) = (x, y): lu^2, lv^2, lu lv, lu, lv, 1 (M = 6).
- ``hsh2``, ``hsh3``: hemispherical harmonics (Gautron et al. 2004) of order 2 and 3 (M = 4, 9), in the
  form the RTI fitters and viewers use (RTIViewer, relight/OpenLIME), theta and phi of the light
  direction with z towards the camera. A direction at or below the horizon (z <= 0) is evaluated on
  the horizon (theta = pi / 2), where the basis is still finite.
- ``rbf``: Gaussian radial basis interpolation over the light directions, phi(r) = exp(-(r / sigma)^2)
  with r the chord between unit vectors, regularised by ``regularisation`` on the kernel matrix's
  diagonal (whose entries are 1). Its M = n planes are the light images themselves: a query's basis
  values are phi(w)^T (K + lambda I)^-1 (the per-light weights (K + lambda I)^-1 y folded into the
  query side, computed in float64 on the host), so float32 planes never carry the large, cancelling
  weights of a badly conditioned K. sigma is chosen by leave-one-out (Rippa 1999) when not given.

PTM and HSH fit by least squares: coefficients = pinv(A) images with A the (n, M) basis matrix of the
lights (float64, ``PINV_RCOND``). Fitting and relighting are one kernel launch each over every pixel
(``warp_highlights.kernels.baselines``); relit values are clamped at 0. Values are in whatever units
the caller uses (linear radiance or sRGB-encoded values, as RTI viewers fit): the fit and the relight
are linear in them, so scaling the images scales the relit images.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import baselines as kernels
from ..model.errors import InputError
from ..model.rbf import RBF_REGULARISATION, RBF_SIGMA_FACTORS, loo_sigma, rbf_kernel, rbf_loo_errors, rbf_system
from ..model.triangulation import unit_query_directions

__all__ = [
    "BASELINE_METHODS",
    "PINV_RCOND",
    "RBF_LOO_PIXELS",
    "RBF_REGULARISATION",
    "RBF_SIGMA_FACTORS",
    "BaselineModel",
    "baseline_basis",
    "choose_rbf_sigma",
    "fit_baseline",
    "hsh_basis",
    "minimum_lights",
    "ptm_basis",
    "rbf_kernel",
    "rbf_loo_errors",
]

BASELINE_METHODS = ("ptm", "hsh2", "hsh3", "rbf")
_COEFFICIENTS = {"ptm": 6, "hsh2": 4, "hsh3": 9}

PINV_RCOND = 1e-10
"""Singular values of the PTM/HSH basis matrix below this fraction of the largest count as zero: a term
the light directions do not determine (e.g. all lights at one elevation) gets the minimum-norm fit."""

RBF_LOO_PIXELS = 4096
"""Pixels (all their channels) drawn, without replacement and with a fixed seed, to score the sigma
candidates; every pixel when the images have fewer."""

_CHUNK_BYTES = 256 * 2**20  # float32 output images one relight launch may hold; more queries run in chunks


def ptm_basis(directions) -> np.ndarray:
    """(Q, 6) float64 PTM basis of unit (Q, 3) directions: lu^2, lv^2, lu lv, lu, lv, 1 with (lu, lv) = (x, y)."""
    d = np.asarray(directions, dtype=np.float64)
    lu, lv = d[:, 0], d[:, 1]
    return np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=1)


def hsh_basis(directions, order: int) -> np.ndarray:
    """(Q, order^2) float64 hemispherical harmonics of unit (Q, 3) directions, order 1 to 3.

    With t = cos(theta) = z clamped to [0, 1] (a light at or below the horizon is evaluated on it),
    phi = atan2(y, x) and s = sqrt(t - t^2) = sqrt(cos(theta) (1 - cos(theta))): 1 / sqrt(2 pi);
    sqrt(6 / pi) s cos(phi), sqrt(3 / (2 pi)) (2t - 1), sqrt(6 / pi) s sin(phi); sqrt(30 / pi) (t^2 - t)
    cos(2 phi), sqrt(30 / pi) (2t - 1) s cos(phi), sqrt(5 / (2 pi)) (6t^2 - 6t + 1), sqrt(30 / pi)
    (2t - 1) s sin(phi), sqrt(30 / pi) (t^2 - t) sin(2 phi) (the RTI fitters' order and signs).
    """
    if order not in (1, 2, 3):
        raise InputError(f"hemispherical harmonics order must be 1, 2 or 3, got {order}")
    d = np.asarray(directions, dtype=np.float64)
    t = np.clip(d[:, 2], 0.0, 1.0)
    phi = np.arctan2(d[:, 1], d[:, 0])
    s = np.sqrt(np.maximum(t - t * t, 0.0))
    terms = [np.full_like(t, 1.0 / np.sqrt(2.0 * np.pi))]
    if order >= 2:
        terms += [np.sqrt(6.0 / np.pi) * s * np.cos(phi), np.sqrt(1.5 / np.pi) * (2.0 * t - 1.0),
                  np.sqrt(6.0 / np.pi) * s * np.sin(phi)]
    if order >= 3:
        c = np.sqrt(30.0 / np.pi)
        terms += [
            c * (t * t - t) * np.cos(2.0 * phi),
            c * (2.0 * t - 1.0) * s * np.cos(phi),
            np.sqrt(2.5 / np.pi) * (6.0 * t * t - 6.0 * t + 1.0),
            c * (2.0 * t - 1.0) * s * np.sin(phi),
            c * (t * t - t) * np.sin(2.0 * phi),
        ]
    return np.stack(terms, axis=1)


def baseline_basis(method: str, directions) -> np.ndarray:
    """(Q, M) float64 basis values of ``ptm``, ``hsh2`` or ``hsh3`` at unit (Q, 3) directions."""
    if method == "ptm":
        return ptm_basis(directions)
    if method in ("hsh2", "hsh3"):
        return hsh_basis(directions, int(method[-1]))
    raise InputError(
        f"baseline_basis takes ptm, hsh2 or hsh3, got '{method}' (rbf depends on its lights: use BaselineModel.basis)")


def choose_rbf_sigma(images, directions, *, regularisation: float = RBF_REGULARISATION, candidates=None,
                     pixels: int = RBF_LOO_PIXELS, seed: int = 0) -> tuple[float, np.ndarray, np.ndarray]:
    """The RBF sigma with the least mean squared leave-one-out error over a subsample of pixels.

    Args:
        images: (n, H, W[, C]) values.
        directions: (n, 3) unit light directions.
        regularisation: lambda on the kernel matrix's diagonal.
        candidates: sigmas to try (chord units); default ``RBF_SIGMA_FACTORS`` times the median
            nearest-neighbour chord of the lights.
        pixels: how many pixels score the candidates (``RBF_LOO_PIXELS``).
        seed: of the pixel draw.

    Returns:
        (sigma, candidates, mean squared LOO error of each candidate); the first minimum on ties.
    """
    images, directions = _checked_inputs(images, directions)
    if not (_is_number(regularisation) and regularisation > 0):
        raise InputError(f"rbf regularisation must be a positive number, got {regularisation}")
    if not (isinstance(pixels, (int, np.integer)) and pixels >= 1):
        raise InputError(f"the rbf leave-one-out subsample needs at least 1 pixel, got {pixels}")
    n = len(images)
    if n < 2:
        raise InputError("choosing the rbf sigma by leave-one-out needs at least 2 lights; pass sigma")
    flat = images.reshape(n, -1, images.shape[3])
    count = flat.shape[1]
    chosen = (np.sort(np.random.default_rng(seed).choice(count, size=pixels, replace=False)) if count > pixels
              else slice(None))
    return loo_sigma(flat[:, chosen].reshape(n, -1), directions, candidates=candidates, regularisation=regularisation)


class BaselineModel:
    """A fitted RTI baseline on one device: M coefficient planes per pixel and channel.

    Made by :func:`fit_baseline`. Attributes:
        method: one of ``BASELINE_METHODS``.
        sigma: the RBF's Gaussian width (chord units), None for PTM/HSH.
        regularisation: the RBF's lambda, None for PTM/HSH.
        loo: (candidates, mean squared LOO errors) of the RBF sigma search, None when sigma was given.
        coefficient_count: M, planes per channel (6, 4, 9, or n for RBF).
        bytes_per_pixel_8bit: M * C, what an 8-bit file of the planes takes per pixel (for RBF the n
            light images themselves).
        lights: (n, 3) the unit light directions fitted to.
        height, width, channels: of the images (C = 1 for grayscale input).
        device: the Warp device holding the planes.
        max_batch: queries per relight launch (default: about 256 MB of output per launch).
    """

    def __init__(self, method: str, planes: wp.array2d, lights: np.ndarray, shape: tuple[int, int, int], *, sigma=None,
                 regularisation=None, loo=None):
        self.method = method
        self.sigma = sigma
        self.regularisation = regularisation
        self.loo = loo
        self.lights = lights
        self.height, self.width, self.channels = shape
        self.device = planes.device
        self._planes = planes
        self.coefficient_count = planes.shape[0]
        self.bytes_per_pixel_8bit = self.coefficient_count * self.channels
        self._rbf_inverse = np.linalg.inv(rbf_system(lights, sigma, regularisation)) if method == "rbf" else None
        self.max_batch = max(1, _CHUNK_BYTES // (4 * self.height * self.width * self.channels))

    def basis(self, directions) -> np.ndarray:
        """(Q, M) float64 values the relight kernel weighs the planes with, for (Q, 3) or (3,) directions.

        PTM/HSH: the basis functions. RBF: phi(w_q)^T (K + lambda I)^-1, which times the light images
        is the interpolant phi(w_q)^T (K + lambda I)^-1 y.
        """
        queries = unit_query_directions(directions)
        if self.method == "rbf":
            return rbf_kernel(queries, self.lights, self.sigma) @ self._rbf_inverse
        return baseline_basis(self.method, queries)

    def coefficients(self) -> np.ndarray:
        """(M, H, W, C) float32 host copy of the coefficient planes (RBF: the light images)."""
        return self._planes.numpy().reshape(self.coefficient_count, self.height, self.width, self.channels)

    def relight(self, directions) -> np.ndarray:
        """Images for (Q, 3) or (3,) light directions (any non-zero length; towards the light, z to the
        camera): (Q, H, W, C) or (H, W, C) float32 in the fitted images' units, every value >= 0 and finite."""
        single = np.ndim(directions) == 1
        weights = self.basis(directions).astype(np.float32)
        count = len(weights)
        columns = self.height * self.width * self.channels
        out = np.empty((count, columns), dtype=np.float32)
        if self.max_batch < 1:
            raise InputError(f"max_batch must be >= 1, got {self.max_batch}")
        for start in range(0, count, self.max_batch):
            stop = min(start + self.max_batch, count)
            basis = wp.array(weights[start:stop], dtype=float, device=self.device)
            out[start:stop] = kernels.evaluate(basis, self._planes).numpy()
        images = out.reshape(count, self.height, self.width, self.channels)
        return images[0] if single else images


def fit_baseline(method: str, images, directions, *, device=None, sigma: float | None = None,
                 regularisation: float | None = None) -> BaselineModel:
    """Fit an RTI baseline to images of one object under n light directions.

    Args:
        method: one of ``BASELINE_METHODS``.
        images: (n, H, W) or (n, H, W, C) values (float32 on the device; any units, the fit is linear).
        directions: (n, 3) directions towards the lights (normalised here), z towards the camera.
        device: Warp device (default: Warp's default device).
        sigma: RBF only: the Gaussian width in chord units; default chosen by leave-one-out
            (:func:`choose_rbf_sigma`).
        regularisation: RBF only: lambda on the kernel matrix's diagonal (default ``RBF_REGULARISATION``).

    Raises:
        InputError: an unknown method, wrong shapes, non-finite values, zero directions, fewer lights
            than the method has coefficients, a bad sigma or regularisation.
    """
    if method not in BASELINE_METHODS:
        raise InputError(f"method must be one of {', '.join(BASELINE_METHODS)}, got '{method}'")
    images, lights = _checked_inputs(images, directions)
    n, height, width, channels = images.shape
    device = wp.get_device(device)
    stack = wp.array(images.reshape(n, -1), dtype=float, device=device)
    if method == "rbf":
        regularisation = RBF_REGULARISATION if regularisation is None else regularisation
        if not (_is_number(regularisation) and regularisation > 0):
            raise InputError(f"rbf regularisation must be a positive number, got {regularisation}")
        loo = None
        if sigma is None:
            sigma, candidates, errors = choose_rbf_sigma(images, lights, regularisation=regularisation)
            loo = (candidates, errors)
        elif not (_is_number(sigma) and sigma > 0):
            raise InputError(f"rbf sigma must be a positive number (chord units), got {sigma}")
        return BaselineModel(method, stack, lights, (height, width, channels), sigma=float(sigma),
                             regularisation=float(regularisation), loo=loo)
    if sigma is not None or regularisation is not None:
        raise InputError(f"sigma and regularisation apply only to the rbf method, not {method}; leave them out")
    count = _COEFFICIENTS[method]
    if n < count:
        raise InputError(f"{method} has {count} coefficients but only {n} lights were given; use at least {count} "
                         f"lights or a method with fewer coefficients")
    pseudo_inverse = np.linalg.pinv(baseline_basis(method, lights), rcond=PINV_RCOND)
    matrix = wp.array(pseudo_inverse.astype(np.float32), dtype=float, device=device)
    planes = kernels.project(matrix, stack)
    del stack
    return BaselineModel(method, planes, lights, (height, width, channels))


def minimum_lights(method: str) -> int:
    """The fewest lights ``method`` can be fitted to: its coefficient count (PTM 6, HSH 4 or 9), 2 for RBF."""
    if method not in BASELINE_METHODS:
        raise InputError(f"baseline must be one of {', '.join(BASELINE_METHODS)}, got '{method}'")
    return _COEFFICIENTS.get(method, 2)


def _is_number(value) -> bool:
    """A finite real number (not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            and bool(np.isfinite(value)))


def _checked_inputs(images, directions) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W, C) float32 images and (n, 3) float64 unit directions, or InputError."""
    try:
        with np.errstate(over="ignore"):  # a value beyond float32 becomes inf, refused below
            images = np.asarray(images, dtype=np.float32)
    except (TypeError, ValueError):
        raise InputError("images must be an array of numbers of shape (n, H, W) or (n, H, W, C)") from None
    if images.ndim == 3:
        images = images[..., None]
    if images.ndim != 4 or min(images.shape) < 1:
        raise InputError(
            f"images must have shape (n, H, W) or (n, H, W, C) with every size >= 1, got {np.shape(images)}")
    bad = np.flatnonzero(~np.isfinite(images).reshape(len(images), -1).all(axis=1))
    if bad.size:
        raise InputError(
            f"image {bad[0]} has non-finite values (NaN, inf, or beyond float32); replace them before fitting")
    try:
        lights = np.array(directions, dtype=np.float64, ndmin=2)
    except (TypeError, ValueError):
        raise InputError("light directions must be numbers of shape (n, 3)") from None
    if lights.shape != (len(images), 3):
        raise InputError(
            f"light directions must have shape (n, 3) with n = {len(images)} images, got {np.shape(directions)}")
    scale = np.abs(lights).max(axis=1)  # divide by the largest component first: no overflow or underflow
    bad = np.flatnonzero(~(np.isfinite(scale) & (scale > 0.0)))
    if bad.size:
        raise InputError(f"light direction {bad[0]} is zero or not finite: {lights[bad[0]].tolist()}")
    lights = lights / scale[:, None]
    return images, lights / np.linalg.norm(lights, axis=1, keepdims=True)
