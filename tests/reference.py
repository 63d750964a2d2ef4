"""Float64 NumPy references of the Gaussian kernels: the ground truth the Warp kernels are tested on."""

from __future__ import annotations

import numpy as np

from warp_highlights.model.config import REFERENCE_HEIGHT_PX, RasterSettings
from warp_highlights.model.gaussians import GaussianParams


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pixel-centre coordinates (x, y), each (H, W)."""
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    return (cols + 0.5) / height, (rows + 0.5) / height


def distance2(params: GaussianParams, b: int, n: int, x: np.ndarray, y: np.ndarray, eps: float) -> np.ndarray:
    """Squared Mahalanobis distance of the points (x, y) from Gaussian (b, n), by explicit matrices."""
    c, s = np.cos(params.theta[b, n]), np.sin(params.theta[b, n])
    rotation = np.array([[c, -s], [s, c]])
    covariance = rotation @ np.diag(params.sigma[b, n] ** 2 + eps) @ rotation.T
    inverse = np.linalg.inv(covariance)
    d = np.stack([x - params.mean[b, n, 0], y - params.mean[b, n, 1]], axis=-1)
    return np.einsum("...i,ij,...j->...", d, inverse, d)


def render(params: GaussianParams, height: int, width: int, settings: RasterSettings | None = None, *,
           truncate: bool = True) -> np.ndarray:
    """(B, H, W) float64 image of every problem; ``truncate=False`` gives the plain Gaussian sum."""
    settings = settings or RasterSettings()
    x, y = pixel_grid(height, width)
    tau = settings.cutoff_level
    images = np.zeros((params.problem_count, height, width))
    for b in range(params.problem_count):
        for n in np.flatnonzero(params.active[b]):
            d2 = distance2(params, b, n, x, y, settings.sigma_eps)
            peak = params.weight[b, n] * params.amplitude[b, n] ** 2
            if truncate:
                images[b] += np.where(d2 < settings.cutoff**2, peak * (np.exp(-0.5 * d2) - tau) / (1 - tau), 0.0)
            else:
                images[b] += peak * np.exp(-0.5 * d2)
    return images


def widened(params: GaussianParams, least: float, eps: float) -> GaussianParams:
    """``kernels.upsample.widen_narrow_gaussians``: every Gaussian at least ``least`` wide along each axis
    (normalised units), a^2 sqrt((sigma_x^2 + eps)(sigma_y^2 + eps)) kept; wider ones as they are."""
    out = params.copy()
    sx, sy = np.abs(params.sigma[..., 0]), np.abs(params.sigma[..., 1])
    narrow = (sx < least) | (sy < least)
    wx, wy = np.maximum(sx, least), np.maximum(sy, least)
    kept = np.sqrt(np.sqrt((sx**2 + eps) * (sy**2 + eps)) / np.sqrt((wx**2 + eps) * (wy**2 + eps)))
    out.amplitude = np.where(narrow, params.amplitude * kept, params.amplitude)
    out.sigma = np.where(narrow[..., None], np.stack([wx, wy], axis=-1), params.sigma)
    return out


def pixel_area(height: int) -> float:
    """Area of one pixel in rpx^2 for an image ``height`` pixels tall."""
    return (REFERENCE_HEIGHT_PX / height) ** 2


def log_l1(image: np.ndarray, target: np.ndarray, height: int) -> np.ndarray:
    """Per-problem fit loss: sum |log2(1 + R) - log2(1 + S)| times the pixel area in rpx^2."""
    area = (REFERENCE_HEIGHT_PX / height) ** 2
    return area * np.abs(np.log2(1 + image) - np.log2(1 + np.maximum(target, 0))).sum(axis=(1, 2))


def energy(params: GaussianParams, settings: RasterSettings | None = None) -> np.ndarray:
    """(B, N) integral of each Gaussian, intensity x rpx^2 (0 for free slots)."""
    settings = settings or RasterSettings()
    eps = settings.sigma_eps
    e = 2 * np.pi * params.amplitude**2 * np.sqrt((params.sigma[..., 0] ** 2 + eps) * (params.sigma[..., 1] ** 2 + eps))
    return np.where(params.active, e * REFERENCE_HEIGHT_PX**2, 0.0)


def energy_loss(params: GaussianParams, reference: GaussianParams,
                settings: RasterSettings | None = None) -> np.ndarray:
    """Per-problem sum over slots active in both of (E(reference) - E(current))^2."""
    both = params.active & reference.active
    return np.where(both, (energy(reference, settings) - energy(params, settings)) ** 2, 0.0).sum(axis=1)


def structure_loss(params: GaussianParams, reference: GaussianParams, gamma: float = 4.0, threshold: float = 15.0,
                   eps: float = 1e-6, *, thesis_form: bool = False) -> np.ndarray:
    """Per-problem structure loss of retargeting (docs/method.md, Fitting step 5), by explicit pair loops (distances in
    rpx).

    ``thesis_form`` uses the thesis' printed (rho s - rho^)^2 instead, which method.md corrects.
    """
    losses = np.zeros(params.problem_count)
    for b in range(params.problem_count):
        slots = np.flatnonzero(params.active[b] & reference.active[b])
        pairs = [(p, q) for p in slots for q in slots if p != q]
        if not pairs:
            continue
        rho = np.array([np.linalg.norm(params.mean[b, p] - params.mean[b, q]) for p, q in pairs]) * REFERENCE_HEIGHT_PX
        rho_ref = (np.array([np.linalg.norm(reference.mean[b, p] - reference.mean[b, q]) for p, q in pairs])
                   * REFERENCE_HEIGHT_PX)
        scale = rho.sum() / (rho_ref.sum() + eps)
        weight = (1 + np.tanh(gamma * (threshold - rho_ref))) / 2
        difference = rho * scale - rho_ref if thesis_form else rho - scale * rho_ref
        losses[b] = np.sum(weight * difference**2)
    return losses


# --- the RTI baselines (warp_highlights/relight/baselines.py) -------------------------------------


def ptm_terms(direction) -> np.ndarray:
    """(6,) PTM terms of one light direction (Malzbender et al. 2001): lu^2, lv^2, lu lv, lu, lv, 1."""
    x, y, z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    return np.array([x**2, y**2, x * y, x, y, 1.0])


def hsh_terms(direction, order: int) -> np.ndarray:
    """(order^2,) hemispherical harmonics of one light direction, from its angles (theta at most pi / 2)."""
    x, y, z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    theta = min(np.arccos(np.clip(z, -1.0, 1.0)), np.pi / 2)
    phi = np.arctan2(y, x)
    ct = np.cos(theta) if theta < np.pi / 2 else 0.0
    root = np.sqrt(max(ct - ct**2, 0.0))
    terms = [
        1 / np.sqrt(2 * np.pi),
        np.sqrt(6 / np.pi) * np.cos(phi) * root,
        np.sqrt(3 / (2 * np.pi)) * (-1 + 2 * ct),
        np.sqrt(6 / np.pi) * root * np.sin(phi),
        np.sqrt(30 / np.pi) * np.cos(2 * phi) * (-ct + ct**2),
        np.sqrt(30 / np.pi) * np.cos(phi) * (-1 + 2 * ct) * root,
        np.sqrt(5 / (2 * np.pi)) * (1 - 6 * ct + 6 * ct**2),
        np.sqrt(30 / np.pi) * (-1 + 2 * ct) * root * np.sin(phi),
        np.sqrt(30 / np.pi) * (-ct + ct**2) * np.sin(2 * phi),
    ]
    return np.array(terms[: order * order])


def baseline_terms(method: str, directions) -> np.ndarray:
    """(Q, M) basis matrix of ``ptm``, ``hsh2`` or ``hsh3``, one direction at a time."""
    if method == "ptm":
        return np.array([ptm_terms(d) for d in directions])
    return np.array([hsh_terms(d, int(method[-1])) for d in directions])


def least_squares_planes(basis: np.ndarray, images: np.ndarray) -> np.ndarray:
    """(M, ...) coefficients minimising |basis @ c - images|^2 per pixel and channel (lstsq, float64)."""
    flat = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
    coefficients = np.linalg.lstsq(basis, flat, rcond=None)[0]
    return coefficients.reshape((basis.shape[1],) + np.shape(images)[1:])


def relit_planes(query_basis: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(Q, ...) max(sum_m query_basis[q, m] planes[m], 0), float64."""
    flat = np.asarray(planes, dtype=np.float64).reshape(len(planes), -1)
    return np.maximum(query_basis @ flat, 0.0).reshape((len(query_basis),) + np.shape(planes)[1:])


def gaussian_rbf(a, b, sigma: float) -> np.ndarray:
    """(len(a), len(b)) exp(-(|a_i - b_j| / sigma)^2) of unit vectors, by explicit distances."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.array([[np.exp(-(np.linalg.norm(p - q) / sigma) ** 2) for q in b] for p in a])


def rbf_relit(images, lights, queries, sigma: float, regularisation: float) -> np.ndarray:
    """(Q, ...) Gaussian RBF interpolation of per-light images at query directions, clamped at 0."""
    lights = np.asarray(lights, dtype=np.float64)
    flat = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
    weights = np.linalg.solve(gaussian_rbf(lights, lights, sigma) + regularisation * np.eye(len(lights)), flat)
    out = np.maximum(gaussian_rbf(queries, lights, sigma) @ weights, 0.0)
    return out.reshape((len(queries),) + np.shape(images)[1:])


def rbf_loo_brute_force(lights, values, sigma: float, regularisation: float) -> np.ndarray:
    """(n, S) y_i minus the (unclamped) RBF interpolant of the other n - 1 lights at light i."""
    lights = np.asarray(lights, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    errors = np.empty_like(values)
    for i in range(len(lights)):
        rest = np.arange(len(lights)) != i
        system = gaussian_rbf(lights[rest], lights[rest], sigma) + regularisation * np.eye(rest.sum())
        weights = np.linalg.solve(system, values[rest])
        errors[i] = values[i] - gaussian_rbf(lights[i : i + 1], lights[rest], sigma)[0] @ weights
    return errors


def neural_decoder(codes: np.ndarray, weights: list, lights) -> np.ndarray:
    """(L, P, 3) float64: the learned residual's MLP (``kernels.neural``) at (L, 3) lights for (P, 9) codes,
    y = W3 elu(W2 elu(W1 elu(W0 [z, w] + b0) + b1) + b2) + b3."""
    w0, b0, w1, b1, w2, b2, w3, b3 = (np.asarray(w, dtype=np.float64) for w in weights)
    codes = np.asarray(codes, dtype=np.float64)

    def elu(v):
        return np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))

    out = []
    for light in np.asarray(lights, dtype=np.float64).reshape(-1, 3):
        x = np.concatenate([codes, np.tile(light, (len(codes), 1))], axis=1).T
        hidden = elu(w2 @ elu(w1 @ elu(w0 @ x + b0) + b1) + b2)
        out.append((w3 @ hidden + b3).T)
    return np.stack(out)


def area_resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W[, C]) -> (height, width[, C]) float64: each output pixel the mean of the input area it
    covers, every input pixel weighted by the area of its overlap (pixel by pixel, by brute force)."""
    image = np.asarray(image, dtype=np.float64)
    rows, cols = image.shape[:2]
    out = np.zeros((height, width) + image.shape[2:])
    for i in range(height):
        top, bottom = i * rows / height, (i + 1) * rows / height
        for j in range(width):
            left, right = j * cols / width, (j + 1) * cols / width
            total, area = 0.0, 0.0
            for r in range(int(np.floor(top)), min(int(np.ceil(bottom)), rows)):
                for c in range(int(np.floor(left)), min(int(np.ceil(right)), cols)):
                    overlap = (min(bottom, r + 1) - max(top, r)) * (min(right, c + 1) - max(left, c))
                    if overlap > 0:
                        total = total + overlap * image[r, c]
                        area += overlap
            out[i, j] = total / area
    return out
