"""Connected components of a Gaussian set, for the rigid phase of retargeting (docs/method.md, Fitting step 5).

Two active Gaussians of one set *touch* when their level-k ellipses intersect, where the level-k
ellipse of a Gaussian is the filled region {x : (x - mu)^T Sigma^-1 (x - mu) <= k^2} (k = 2 by
default, ``ComponentSettings.level``). A component is a connected component of the "touch" graph.

The ellipse test is exact (up to float64 rounding), after D. Eberly, "Intersection of Ellipses" and
"Distance from a Point to an Ellipse" (Geometric Tools): map one ellipse to the unit disc, then the
two intersect iff the other one contains the origin or its boundary comes within distance 1 of it.

Units: positions and sizes in image heights (docs/method.md, Units and conventions), energies in intensity x image
height^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .config import ComponentSettings, RasterSettings
from .errors import InputError
from .gaussians import GaussianParams

__all__ = ["ConnectedComponents", "ellipses_intersect", "gaussian_covariances"]

_BISECTION_STEPS = 120
"""Bisection steps for the point-to-ellipse distance. The bracket is at most e_max^2 wide and the root
at least distance x e_min (semi-axes e in the unit-disc frame), so 120 halvings pin the root down to
float64 resolution whenever e_max^2 / (e_min x distance) < 1e20, far beyond aspect ratios of 1e-6."""

_TOLERANCE = 1e-9
"""Default tangency tolerance: a gap of up to this fraction of ellipse A's size counts as touching."""


def gaussian_covariances(sigma, theta, eps: float = 0.0) -> np.ndarray:
    """Covariances R(theta) diag(sigma_x^2 + eps, sigma_y^2 + eps) R(theta)^T (docs/method.md, Building blocks).

    Args:
        sigma: (..., 2) standard deviations along the Gaussian's own axes, image heights (the sign
            does not matter).
        theta: (...) rotation in radians from +x towards +y, so R = [[cos, -sin], [sin, cos]].
        eps: added to every variance, image heights^2 (``RasterSettings.sigma_eps``).

    Returns:
        (..., 2, 2) float64 symmetric covariances, image heights^2.
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    variance = sigma**2 + float(eps)
    c, s = np.cos(theta), np.sin(theta)
    vx, vy = variance[..., 0], variance[..., 1]
    xx = c * c * vx + s * s * vy
    yy = s * s * vx + c * c * vy
    xy = c * s * (vx - vy)
    return np.stack([np.stack([xx, xy], axis=-1), np.stack([xy, yy], axis=-1)], axis=-2)


def ellipses_intersect(
    centre_a,
    cov_a,
    centre_b,
    cov_b,
    level: float = 2.0,
    *,
    tolerance: float = _TOLERANCE,
) -> np.ndarray:
    """Whether the filled ellipses {x : (x - c)^T cov^-1 (x - c) <= level^2} of A and B intersect.

    Exact up to float64 rounding: A is mapped affinely onto the unit disc, which maps B onto a filled
    ellipse B'; the two intersect iff B' contains the origin or the distance from the origin to the
    boundary of B' is at most 1. That distance is the root of a monotone one-dimensional function
    (Eberly's point-to-ellipse distance), found by bisection to float64 resolution, so no step
    approximates the geometry: the only errors are the rounding of the inputs and of a few
    arithmetic operations, which is why the ``tolerance`` can be tiny. Tangent ellipses (identical,
    nested or touching from outside) count as intersecting.

    Args:
        centre_a, centre_b: (..., 2) centres (any length unit).
        cov_a, cov_b: (..., 2, 2) symmetric positive definite matrices, the unit squared.
        level: Mahalanobis radius of the ellipses (> 0).
        tolerance: a gap of up to this fraction of A's size (its semi-axis towards B) still counts
            as touching.

    Returns:
        bool array of the broadcast batch shape.

    Raises:
        InputError: a covariance is not positive definite or a value is not finite.
    """
    level = float(level)
    if not (np.isfinite(level) and level > 0):
        raise InputError(f"level must be a finite number > 0, got {level}")
    axes_a, angle_a = _principal_axes(cov_a, "cov_a")
    axes_b, angle_b = _principal_axes(cov_b, "cov_b")
    centre_a = np.asarray(centre_a, dtype=np.float64)
    centre_b = np.asarray(centre_b, dtype=np.float64)
    if centre_a.shape[-1:] != (2,) or centre_b.shape[-1:] != (2,):
        raise InputError(
            f"centres must have shape (..., 2), got {centre_a.shape} and {centre_b.shape}"
        )
    return _intersect_axes(
        centre_a, level * axes_a, angle_a, centre_b, level * axes_b, angle_b, tolerance
    )


def _principal_axes(cov, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations (..., 2), major first, and the major axis' angle (...) of covariances."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape[-2:] != (2, 2):
        raise InputError(f"{name} must have shape (..., 2, 2), got {cov.shape}")
    p, r = cov[..., 0, 0], cov[..., 1, 1]
    q = 0.5 * (cov[..., 0, 1] + cov[..., 1, 0])
    large = 0.5 * (p + r) + np.hypot(0.5 * (p - r), q)
    with np.errstate(divide="ignore", invalid="ignore"):
        # det / large: no cancellation against ``large`` for thin ellipses
        small = (p * r - q * q) / large
    if not (np.all(np.isfinite(cov)) and np.all(small > 0)):
        raise InputError(
            f"{name} must hold finite symmetric positive definite 2x2 matrices"
        )
    angle = 0.5 * np.arctan2(2.0 * q, p - r)
    return np.stack([np.sqrt(large), np.sqrt(small)], axis=-1), angle


def _intersect_axes(
    centre_a, axes_a, angle_a, centre_b, axes_b, angle_b, tolerance: float = _TOLERANCE
) -> np.ndarray:
    """Core of ``ellipses_intersect`` for ellipses given by semi-axes (..., 2) (> 0) and angles (...).

    Ellipse A is {centre_a + R(angle_a) diag(axes_a) u : |u| <= 1}, likewise B.
    """
    vectors = [
        np.asarray(v, dtype=np.float64) for v in (centre_a, axes_a, centre_b, axes_b)
    ]
    angles = [np.asarray(v, dtype=np.float64) for v in (angle_a, angle_b)]
    shape = np.broadcast_shapes(
        *(v.shape[:-1] for v in vectors), *(v.shape for v in angles)
    )
    centre_a, axes_a, centre_b, axes_b = (
        np.broadcast_to(v, shape + (2,)).reshape(-1, 2) for v in vectors
    )
    angle_a, angle_b = (np.broadcast_to(v, shape).reshape(-1) for v in angles)
    # The unit-disc frame of A: u = diag(1 / axes_a) R(-angle_a) (x - centre_a).
    delta = centre_b - centre_a
    ca, sa = np.cos(angle_a), np.sin(angle_a)
    dx = (ca * delta[..., 0] + sa * delta[..., 1]) / axes_a[..., 0]
    dy = (-sa * delta[..., 0] + ca * delta[..., 1]) / axes_a[..., 1]
    # B' = {d + M u : |u| <= 1} with M = diag(1 / axes_a) R(angle_b - angle_a) diag(axes_b).
    c, s = np.cos(angle_b - angle_a), np.sin(angle_b - angle_a)
    m00 = c * axes_b[..., 0] / axes_a[..., 0]
    m01 = -s * axes_b[..., 1] / axes_a[..., 0]
    m10 = s * axes_b[..., 0] / axes_a[..., 1]
    m11 = c * axes_b[..., 1] / axes_a[..., 1]
    # Closed-form 2x2 SVD M = R(phi) diag(e0, e1) R(psi): the semi-axes of B' are e0 >= e1 > 0 and
    # its major axis points along R(phi) (1, 0). e1 = det / e0 avoids the cancellation of Q - R.
    e_ = 0.5 * (m00 + m11)
    f_ = 0.5 * (m00 - m11)
    g_ = 0.5 * (m10 + m01)
    h_ = 0.5 * (m10 - m01)
    e0 = np.hypot(e_, h_) + np.hypot(f_, g_)
    det = (axes_b[..., 0] * axes_b[..., 1]) / (axes_a[..., 0] * axes_a[..., 1])
    e1 = det / e0
    phi = 0.5 * (np.arctan2(h_, e_) + np.arctan2(g_, f_))
    # The origin in B''s principal frame, folded into the first quadrant.
    cp, sp = np.cos(phi), np.sin(phi)
    z0 = np.abs(cp * dx + sp * dy)
    z1 = np.abs(-sp * dx + cp * dy)
    inside = (z0 / e0) ** 2 + (z1 / e1) ** 2 <= 1.0
    result = np.array(inside, dtype=bool, copy=True)
    outside = ~result
    if np.any(outside):
        distance = _exterior_distance(
            e0[outside], e1[outside], z0[outside], z1[outside]
        )
        result[outside] = distance <= 1.0 + tolerance
    return result.reshape(shape)


def _exterior_distance(e0, e1, z0, z1, steps: int = _BISECTION_STEPS) -> np.ndarray:
    """Distance from points (z0, z1) >= 0 outside the ellipse (x0/e0)^2 + (x1/e1)^2 = 1 to it.

    Eberly: the nearest point is x_i = e_i^2 z_i / (t + e_i^2) with t > 0 the root of the decreasing
    F(t) = sum_i (e_i z_i / (t + e_i^2))^2 - 1 (F(0) > 0 outside). Since each term is at most
    (e_i z_i / t)^2, F(|e z|) <= 0, and since t + e_i^2 <= t + e_max^2, F(|e z| - e_max^2) >= 0; the
    bisection runs on that bracket. Then x - z = -z t / (t + e^2) (no cancellation).
    """
    ez = np.hypot(e0 * z0, e1 * z1)
    lo = np.maximum(ez - np.maximum(e0, e1) ** 2, 0.0)
    hi = ez.copy()
    a0, a1 = e0 * e0, e1 * e1
    for _ in range(steps):
        t = 0.5 * (lo + hi)
        value = (e0 * z0 / (t + a0)) ** 2 + (e1 * z1 / (t + a1)) ** 2 - 1.0
        positive = value > 0
        lo = np.where(positive, t, lo)
        hi = np.where(positive, hi, t)
    t = 0.5 * (lo + hi)
    return np.hypot(z0 * t / (t + a0), z1 * t / (t + a1))


@dataclass(frozen=True, eq=False)
class ConnectedComponents:
    """Connected components of every set of a batch: active Gaussians touch when their level-k
    ellipses intersect (docs/method.md, Fitting step 4). Build with ``ConnectedComponents.of``.

    Attributes:
        labels: (B, N) int32 component of each slot within its problem, numbered 0..counts[b] - 1 in
            order of each component's lowest slot; -1 for inactive slots.
        counts: (B,) int64 components per problem (0 for a problem without active slots).
        centroids: (B, N, 2) float64 energy-weighted centroid of component k of problem b in row
            [b, k], image heights; rows k >= counts[b] are zero. A component of zero total energy
            gets the plain mean of its Gaussians' centres.
        level: the Mahalanobis radius of the ellipses.
        sigma_eps: the epsilon added to sigma^2, image heights^2.
    """

    labels: np.ndarray
    counts: np.ndarray
    centroids: np.ndarray
    level: float
    sigma_eps: float

    @classmethod
    def of(
        cls,
        params: GaussianParams,
        *,
        level: float = ComponentSettings.level,
        sigma_eps: float | None = None,
    ) -> ConnectedComponents:
        """Components of every problem of ``params`` (all problems at once, one graph).

        Args:
            params: B sets of N slots; only active slots take part.
            level: Mahalanobis radius k of the ellipses (method.md: 2).
            sigma_eps: epsilon added to sigma^2, image heights^2; default ``RasterSettings().sigma_eps``.
                Energies E = 2 pi a^2 sqrt((sigma_x^2 + eps)(sigma_y^2 + eps)) use it too.
        """
        level = float(level)
        if not (np.isfinite(level) and level > 0):
            raise InputError(f"level must be a finite number > 0, got {level}")
        eps = RasterSettings().sigma_eps if sigma_eps is None else float(sigma_eps)
        if not (np.isfinite(eps) and eps >= 0):
            raise InputError(f"sigma_eps must be a finite number >= 0, got {eps}")
        problems, slots = params.shape
        active = params.active
        if np.any(active & ~params.finite):
            raise InputError(
                "an active Gaussian has non-finite parameters; remove diverged slots first"
            )
        variance = params.sigma**2 + eps
        if np.any(active & ~np.all(variance > 0, axis=-1)):
            raise InputError(
                "an active Gaussian has a zero size and sigma_eps is 0, so its ellipse is "
                "degenerate; use sigma_eps > 0"
            )
        axes = level * np.sqrt(variance)

        # Every pair i < j of active slots of every problem; the bounding circles reject far pairs.
        first, second = np.triu_indices(slots, 1)
        pair_problem, pair = np.nonzero(active[:, first] & active[:, second])
        i, j = first[pair], second[pair]
        mean_i, mean_j = params.mean[pair_problem, i], params.mean[pair_problem, j]
        axes_i, axes_j = axes[pair_problem, i], axes[pair_problem, j]
        gap = np.hypot(*(mean_j - mean_i).T)
        near = gap <= (axes_i.max(axis=-1) + axes_j.max(axis=-1)) * (1.0 + 1e-6)
        touch = np.zeros(len(pair), dtype=bool)
        if np.any(near):
            touch[near] = _intersect_axes(
                mean_i[near],
                axes_i[near],
                params.theta[pair_problem[near], i[near]],
                mean_j[near],
                axes_j[near],
                params.theta[pair_problem[near], j[near]],
            )

        # One block-diagonal graph over all B * N slots; node b * N + n is slot n of problem b.
        node_count = problems * slots
        u = pair_problem[touch] * slots + i[touch]
        v = pair_problem[touch] * slots + j[touch]
        graph = coo_matrix(
            (np.ones(len(u), dtype=np.int8), (u, v)), shape=(node_count, node_count)
        ).tocsr()
        _, global_label = connected_components(graph, directed=False)

        # Renumber: components ordered by their lowest node, i.e. by (problem, lowest slot).
        nodes = np.flatnonzero(active.ravel())
        unique, first_position, inverse = np.unique(
            global_label[nodes], return_index=True, return_inverse=True
        )
        order = np.argsort(first_position)
        rank = np.empty(len(unique), dtype=np.int64)
        rank[order] = np.arange(len(unique))
        component = rank[inverse.reshape(-1)]  # per active node, global rank
        component_problem = nodes[first_position[order]] // slots  # per rank
        counts = np.bincount(component_problem, minlength=problems).astype(np.int64)
        offsets = np.cumsum(counts) - counts
        local = component - offsets[nodes // slots]
        labels = np.full(node_count, -1, dtype=np.int32)
        labels[nodes] = local
        labels = labels.reshape(problems, slots)

        # Energy-weighted centroids (plain mean where a component has no energy).
        energy = (
            2.0
            * np.pi
            * params.amplitude**2
            * np.sqrt(variance[..., 0] * variance[..., 1])
        )
        weight = energy.ravel()[nodes]
        centre = params.mean.reshape(-1, 2)[nodes]
        total = np.bincount(component, weights=weight, minlength=len(unique))
        members = np.bincount(component, minlength=len(unique))
        centroid = np.empty((len(unique), 2))
        for axis in range(2):
            weighted = np.bincount(
                component, weights=weight * centre[:, axis], minlength=len(unique)
            )
            plain = np.bincount(
                component, weights=centre[:, axis], minlength=len(unique)
            )
            with np.errstate(divide="ignore", invalid="ignore"):
                centroid[:, axis] = np.where(
                    total > 0, weighted / total, plain / np.maximum(members, 1)
                )
        centroids = np.zeros((problems, slots, 2))
        centroids[
            component_problem, np.arange(len(unique)) - offsets[component_problem]
        ] = centroid
        return cls(
            labels=labels,
            counts=counts,
            centroids=centroids,
            level=level,
            sigma_eps=eps,
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(problems, slots)."""
        return tuple(self.labels.shape)

    def centroid_of_slot(self) -> np.ndarray:
        """(B, N, 2) centroid of each slot's component, image heights; zeros for inactive slots."""
        problems, _ = self.labels.shape
        rows = np.arange(problems)[:, None]
        centroid = self.centroids[rows, np.maximum(self.labels, 0)]
        return np.where((self.labels >= 0)[..., None], centroid, 0.0)
