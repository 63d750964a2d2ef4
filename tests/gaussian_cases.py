"""Random Gaussian batches for the kernel tests: odd image sizes, tiny to huge sizes, every rotation."""

from __future__ import annotations

import numpy as np

from warp_highlights.model.gaussians import GaussianParams


def random_params(rng: np.random.Generator, problems: int, capacity: int, height: int, width: int, *,
                  sigma_px=(0.3, 40.0), inactive: float = 0.25) -> GaussianParams:
    """Gaussians sized ``sigma_px`` (pixels of this image, log-uniform), rotations in [-2 pi, 2 pi],
    means up to a quarter of the image outside it, weights in [0, 2], a share of free slots."""
    params = GaussianParams.empty(problems, capacity)
    shape = (problems, capacity)
    params.active[:] = rng.random(shape) >= inactive
    params.amplitude[:] = rng.uniform(-1.4, 1.4, shape)
    aspect = width / height
    params.mean[:] = rng.uniform([-0.25 * aspect, -0.25], [1.25 * aspect, 1.25], shape + (2,))
    low, high = np.log(sigma_px[0]), np.log(sigma_px[1])
    params.sigma[:] = np.exp(rng.uniform(low, high, shape + (2,))) / height * rng.choice([-1.0, 1.0], shape + (2,))
    params.theta[:] = rng.uniform(-2 * np.pi, 2 * np.pi, shape)
    params.weight[:] = rng.uniform(0.0, 2.0, shape)
    return GaussianParams(**{name: getattr(params, name)
                             for name in ("amplitude", "mean", "sigma", "theta", "weight", "active")})


def inside_params(rng: np.random.Generator, problems: int, capacity: int, height: int, width: int, *,
                  sigma_px=(1.0, 6.0)) -> GaussianParams:
    """All slots active, means well inside the image, moderate sizes: for gradient checks."""
    params = GaussianParams.empty(problems, capacity)
    shape = (problems, capacity)
    params.active[:] = True
    params.amplitude[:] = rng.uniform(0.5, 1.3, shape)
    params.mean[:] = rng.uniform([0.2, 0.2], [width / height - 0.2, 0.8], shape + (2,))
    params.sigma[:] = rng.uniform(*sigma_px, shape + (2,)) / height
    params.theta[:] = rng.uniform(-np.pi, np.pi, shape)
    params.weight[:] = rng.uniform(0.5, 1.5, shape)
    return GaussianParams(**{name: getattr(params, name)
                             for name in ("amplitude", "mean", "sigma", "theta", "weight", "active")})


def central_differences(function, params: GaussianParams, step: float = 1e-6) -> dict[str, np.ndarray]:
    """d function(params) / d parameter for every parameter of every active slot (float64, NumPy)."""
    gradients = {}
    for name in ("amplitude", "mean", "sigma", "theta", "weight"):
        values = getattr(params, name)
        gradient = np.zeros_like(values)
        for index in np.ndindex(values.shape):
            if not params.active[index[:2]]:
                continue
            plus, minus = params.copy(), params.copy()
            getattr(plus, name)[index] += step
            getattr(minus, name)[index] -= step
            gradient[index] = (function(plus) - function(minus)) / (2 * step)
        gradients[name] = gradient
    return gradients
