"""Exact ellipse-ellipse test (against brute force) and connected components of Gaussian sets."""

from __future__ import annotations

import numpy as np
import pytest

from gaussian_cases import random_params
from warp_highlights.model.components import (
    ConnectedComponents,
    _exterior_distance,
    ellipses_intersect,
    gaussian_covariances,
)
from warp_highlights.model.config import RasterSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianParams

LEVEL = 2.0


def _rotation(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _random_pairs(rng, count):
    """Ellipses (sigma log-uniform over two orders of magnitude per axis, any rotation), B placed at
    0 to 1.3 times the sum of the two bounding radii from A, so about half the pairs intersect."""
    sigma = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (2, count, 2)))
    theta = rng.uniform(0, 2 * np.pi, (2, count))
    centre_a = rng.uniform(-1, 1, (count, 2))
    reach = LEVEL * (sigma[0].max(-1) + sigma[1].max(-1))
    angle = rng.uniform(0, 2 * np.pi, count)
    centre_b = centre_a + (rng.uniform(0, 1.3, count) * reach)[:, None] * np.stack(
        [np.cos(angle), np.sin(angle)], -1
    )
    return centre_a, sigma[0], theta[0], centre_b, sigma[1], theta[1]


def _near_tangent_pairs(rng, count, relative_gap, sigma=None):
    """Pairs built to have a known gap: B's boundary point whose outward normal is -n sits at
    p + gap n, where p is a random boundary point of A (level-2 ellipses) and n A's outward normal
    there. gap > 0: a line separates them; gap < 0 with |gap| below A's smallest radius of curvature
    b^2 / a: that point of B is inside A. ``relative_gap`` (count,) is the gap in units of
    b^2 / a of A. ``sigma`` (2, count, 2) defaults to log-uniform in [0.01, 1]."""
    if sigma is None:
        sigma = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (2, count, 2)))
    theta = rng.uniform(0, 2 * np.pi, (2, count))
    centre_a = rng.uniform(-1, 1, (count, 2))
    factor_a = _rotation(theta[0]) * (LEVEL * sigma[0])[:, None, :]
    factor_b = _rotation(theta[1]) * (LEVEL * sigma[1])[:, None, :]
    angle = rng.uniform(0, 2 * np.pi, count)
    u = np.stack([np.cos(angle), np.sin(angle)], -1)
    point = centre_a + np.einsum("pij,pj->pi", factor_a, u)
    normal = np.einsum("pji,pj->pi", np.linalg.inv(factor_a), u)  # F_a^-T u
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    support = np.einsum("pji,pj->pi", factor_b, -normal)  # F_b^T (-n)
    support /= np.linalg.norm(support, axis=1, keepdims=True)
    curvature_radius = LEVEL * sigma[0].min(-1) ** 2 / sigma[0].max(-1)
    gap = relative_gap * curvature_radius
    centre_b = (
        point + gap[:, None] * normal - np.einsum("pij,pj->pi", factor_b, support)
    )
    return (centre_a, sigma[0], theta[0], centre_b, sigma[1], theta[1]), gap


def _unit_disc_samples():
    """Points of the unit disc: a dense boundary and a polar grid filling the inside (and the centre)."""
    boundary = np.linspace(0, 2 * np.pi, 16384, endpoint=False)
    radii = np.linspace(0, 1, 33)[1:-1]
    angles = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    r, a = np.meshgrid(radii, angles, indexing="ij")
    ring = np.stack([np.cos(boundary), np.sin(boundary)], -1)
    fill = np.stack([r.ravel() * np.cos(a.ravel()), r.ravel() * np.sin(a.ravel())], -1)
    return np.concatenate([ring, fill, np.zeros((1, 2))])


def _witness_found(
    centre_a, sigma_a, theta_a, centre_b, sigma_b, theta_b, level, samples, chunk=64
):
    """Brute force: does some sample point of the filled ellipse A lie in the filled ellipse B?

    A point of A is centre_a + level F_a u with |u| <= 1 and F = R(theta) diag(sigma); it lies in B
    iff |F_b^-1 (point - centre_b)| <= level, i.e. |w + H u| <= 1 with H = F_b^-1 F_a and
    w = F_b^-1 (centre_a - centre_b) / level."""
    factor_a = _rotation(theta_a) * sigma_a[:, None, :]
    inverse_b = np.linalg.inv(_rotation(theta_b) * sigma_b[:, None, :])
    h = inverse_b @ factor_a
    w = np.einsum("pij,pj->pi", inverse_b, centre_a - centre_b) / level
    ux, uy = samples[:, 0], samples[:, 1]
    found = np.zeros(len(centre_a), dtype=bool)
    for start in range(0, len(centre_a), chunk):
        part = slice(start, start + chunk)
        x = w[part, 0, None] + h[part, 0, 0, None] * ux + h[part, 0, 1, None] * uy
        y = w[part, 1, None] + h[part, 1, 0, None] * ux + h[part, 1, 1, None] * uy
        found[part] = np.any(x * x + y * y <= 1.0, axis=1)
    return found


def _brute_force(pair, level, samples):
    """Witness search in both directions (A's samples in B, B's samples in A)."""
    centre_a, sigma_a, theta_a, centre_b, sigma_b, theta_b = pair
    forward = _witness_found(
        centre_a, sigma_a, theta_a, centre_b, sigma_b, theta_b, level, samples
    )
    return forward | _witness_found(
        centre_b, sigma_b, theta_b, centre_a, sigma_a, theta_a, level, samples
    )


def _exact(pair, level=LEVEL):
    centre_a, sigma_a, theta_a, centre_b, sigma_b, theta_b = pair
    return ellipses_intersect(
        centre_a,
        gaussian_covariances(sigma_a, theta_a),
        centre_b,
        gaussian_covariances(sigma_b, theta_b),
        level,
    )


def _join(*pairs):
    return tuple(np.concatenate(parts) for parts in zip(*pairs, strict=True))


def test_ellipses_intersect_agrees_with_brute_force_sampling():
    rng = np.random.default_rng(7)
    near, _ = _near_tangent_pairs(
        rng,
        600,
        rng.choice([-1.0, 1.0], 600)
        * np.exp(rng.uniform(np.log(0.01), np.log(30.0), 600)),
    )
    pair = _join(_random_pairs(rng, 3000), near)
    samples = _unit_disc_samples()
    margin = 1e-3
    # A sample of A inside B is a witness of intersection; intersection only grows with the level.
    # So a witness at level (1 - margin) proves the pair intersects at the level; no witness even at
    # (1 + margin) means it does not (as far as the sampling can see). Pairs with no witness at the
    # lower level but one at the higher are within the margin of tangency and are left out.
    low = _brute_force(pair, LEVEL * (1 - margin), samples)
    high = low.copy()
    high[~low] = _brute_force(
        tuple(v[~low] for v in pair), LEVEL * (1 + margin), samples
    )
    decided = low | ~high
    exact = _exact(pair)
    assert exact.shape == (3600,) and exact.dtype == bool
    assert decided[:3000].sum() >= 2970 and decided[3000:].sum() >= 450, (
        f"only {decided[:3000].sum()} + {decided[3000:].sum()} pairs decided"
    )
    assert 0.3 < exact[:3000].mean() < 0.7 and 0.3 < exact[3000:].mean() < 0.7, (
        "pairs should mix intersecting and disjoint ones"
    )
    disagree = np.flatnonzero(decided & (exact != low))
    assert len(disagree) == 0, (
        f"{len(disagree)} pairs disagree with brute force, e.g. {disagree[:5]}"
    )
    # symmetric in A and B
    swapped = (pair[3], pair[4], pair[5], pair[0], pair[1], pair[2])
    np.testing.assert_array_equal(_exact(swapped), exact)


def test_ellipses_intersect_resolves_gaps_far_below_sampling_resolution():
    rng = np.random.default_rng(9)
    relative_gap = rng.choice([-1.0, 1.0], 4000) * np.exp(
        rng.uniform(np.log(1e-5), np.log(0.99), 4000)
    )
    pair, gap = _near_tangent_pairs(rng, 4000, relative_gap)
    np.testing.assert_array_equal(_exact(pair), gap < 0)
    swapped = (pair[3], pair[4], pair[5], pair[0], pair[1], pair[2])
    np.testing.assert_array_equal(_exact(swapped), gap < 0)
    # needles (aspect 1e-3) crossing at any angle: B mapped into A's unit-disc frame has aspect up to 1e-6
    length = np.exp(rng.uniform(np.log(0.1), np.log(1.0), (2, 2000)))
    needles = np.stack([length, 1e-3 * length], axis=-1)
    relative_gap = rng.choice([-1.0, 1.0], 2000) * np.exp(
        rng.uniform(np.log(1e-2), np.log(0.99), 2000)
    )
    pair, gap = _near_tangent_pairs(rng, 2000, relative_gap, needles)
    np.testing.assert_array_equal(_exact(pair), gap < 0)
    # exactly tangent (up to the rounding of the construction): touching
    pair, _ = _near_tangent_pairs(rng, 500, np.zeros(500))
    assert np.all(_exact(pair))


def _nearest_on_grid(e, z, t):
    """Smallest distance from z (P, 2) to the boundary points (e0 cos t, e1 sin t), t (P, S), and its t."""
    distance = np.hypot(
        e[:, 0, None] * np.cos(t) - z[:, 0, None],
        e[:, 1, None] * np.sin(t) - z[:, 1, None],
    )
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(z))
    return distance[rows, best], np.broadcast_to(t, distance.shape)[rows, best]


def test_exterior_distance_matches_dense_boundary_sampling():
    rng = np.random.default_rng(3)
    e = np.sort(np.exp(rng.uniform(np.log(1e-3), np.log(10), (300, 2))), axis=1)[
        :, ::-1
    ]
    direction = rng.uniform(0, np.pi / 2, 300)
    # points outside the ellipse: a boundary point pushed out by a factor 1 + 1e-4 .. 11
    scale = 1 + np.exp(rng.uniform(np.log(1e-4), np.log(10), 300))
    boundary = np.stack([e[:, 0] * np.cos(direction), e[:, 1] * np.sin(direction)], -1)
    z = boundary * scale[:, None]
    exact = _exterior_distance(e[:, 0], e[:, 1], z[:, 0], z[:, 1])
    # a parameter grid over the quarter boundary, then a finer grid around the best point
    brute, best = _nearest_on_grid(e, z, np.linspace(0, np.pi / 2, 20001)[None, :])
    step = np.pi / 2 / 20000
    brute, _ = _nearest_on_grid(
        e, z, best[:, None] + np.linspace(-step, step, 2001)[None, :]
    )
    assert np.all(exact <= brute * (1 + 1e-12)), "the exact distance is a minimum"
    fine_spacing = e[:, 0] * step / 1000
    assert np.all(brute - exact <= fine_spacing), (
        "and within one fine grid step of the sampled one"
    )
    # on the axes, the closest point is the vertex
    np.testing.assert_allclose(
        _exterior_distance(
            np.array([3.0, 3.0]),
            np.array([1.0, 1.0]),
            np.array([5.0, 0.0]),
            np.array([0.0, 4.0]),
        ),
        [2.0, 3.0],
        rtol=1e-14,
    )


def _circle(radius):
    """Covariance whose level-2 ellipse is a circle of this radius."""
    return np.eye(2) * (radius / LEVEL) ** 2


def _needle(length, theta, aspect=1e-3):
    """Covariance whose level-2 ellipse has semi-axes (length, aspect * length), rotated by theta."""
    return gaussian_covariances(np.array([length, aspect * length]) / LEVEL, theta)


def test_circles_at_twice_the_radius_touch_and_just_beyond_do_not():
    r = 0.37
    centre = np.array([0.2, -0.1])
    offsets = np.array([2 * r - 1e-7, 2 * r, 2 * r + 1e-7])[:, None] * np.array(
        [np.cos(1.1), np.sin(1.1)]
    )
    result = ellipses_intersect(centre, _circle(r), centre + offsets, _circle(r), LEVEL)
    np.testing.assert_array_equal(result, [True, True, False])
    # an ellipse tangent to a circle at its co-vertex (semi-axes 2 and 1 at level 1, circle at (0, 2))
    ellipse = np.diag([4.0, 1.0])
    centres = np.array([[0.0, 2.0], [0.0, 2.0 + 1e-7], [0.0, 2.0 - 1e-7]])
    np.testing.assert_array_equal(
        ellipses_intersect(np.zeros(2), ellipse, centres, np.eye(2), 1.0),
        [True, False, True],
    )


def test_nested_identical_and_concentric_ellipses_intersect():
    big = gaussian_covariances(np.array([1.0, 0.4]), 0.3)
    small = gaussian_covariances(np.array([0.05, 0.01]), 2.0)
    inside = np.array(
        [0.8, 0.6]
    )  # well inside the big ellipse (level 2), off its centre
    assert ellipses_intersect(np.zeros(2), big, inside, small)
    assert ellipses_intersect(inside, small, np.zeros(2), big)
    assert ellipses_intersect(inside, small, inside, small)  # identical
    assert ellipses_intersect(
        np.zeros(2), _needle(1.0, 0.0), np.zeros(2), _needle(1.0, np.pi / 2)
    )  # concentric cross
    assert ellipses_intersect(
        np.zeros(2), _needle(1.0, 0.7), np.zeros(2), _needle(1.0, 0.7)
    )  # identical needles


def test_crossing_needles_intersect_and_parallel_needles_do_not():
    # a plus sign whose arms cross far from both centres: neither centre lies in the other needle
    horizontal = _needle(1.0, 0.0)
    vertical = _needle(1.0, np.pi / 2)
    assert ellipses_intersect(np.zeros(2), horizontal, np.array([0.9, 0.9]), vertical)
    assert ellipses_intersect(np.array([0.9, 0.9]), vertical, np.zeros(2), horizontal)
    assert not ellipses_intersect(
        np.zeros(2), horizontal, np.array([1.01, 0.9]), vertical
    )
    # parallel needles of half-width 1e-3 side by side
    gaps = np.array([[0.0, 2.5e-3], [0.3, 2.1e-3], [0.0, 1.9e-3]])
    np.testing.assert_array_equal(
        ellipses_intersect(np.zeros(2), horizontal, gaps, horizontal),
        [False, False, True],
    )


def test_batch_shapes_broadcast_and_bad_covariances_are_refused():
    centres = np.zeros((4, 3, 2))
    covs = np.broadcast_to(np.eye(2), (4, 3, 2, 2))
    assert ellipses_intersect(centres, covs, centres + 1.5, covs, 1.0).shape == (4, 3)
    with pytest.raises(InputError, match="positive definite"):
        ellipses_intersect(
            np.zeros(2), np.array([[1.0, 2.0], [2.0, 1.0]]), np.zeros(2), np.eye(2)
        )
    with pytest.raises(InputError, match="level"):
        ellipses_intersect(np.zeros(2), np.eye(2), np.zeros(2), np.eye(2), 0.0)


def test_gaussian_covariances_rotate_from_x_towards_y():
    rng = np.random.default_rng(5)
    sigma = rng.uniform(-2, 2, (3, 4, 2))
    theta = rng.uniform(-7, 7, (3, 4))
    eps = 0.01
    expected = (
        _rotation(theta)
        @ (np.eye(2) * (sigma**2 + eps)[..., None, :])
        @ np.swapaxes(_rotation(theta), -1, -2)
    )
    np.testing.assert_allclose(
        gaussian_covariances(sigma, theta, eps), expected, rtol=1e-13, atol=1e-15
    )
    # theta = 30 degrees: the sigma_x axis is (cos 30, sin 30), i.e. +x turned towards +y
    cov = gaussian_covariances(np.array([2.0, 1.0]), np.pi / 6)
    axis = np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    np.testing.assert_allclose(cov @ axis, 4.0 * axis, rtol=1e-13)


# --- connected components ----------------------------------------------------------------------


def _params(sets, capacity=None):
    return GaussianParams.from_sets(
        [
            {
                "amplitude": [g[0] for g in s],
                "mean": [g[1] for g in s],
                "sigma": [g[2] for g in s],
                "theta": [g[3] if len(g) > 3 else 0.0 for g in s],
            }
            for s in sets
        ],
        capacity=capacity,
    )


def _energy(a, sigma, eps):
    sigma = np.asarray(sigma)
    return 2 * np.pi * a**2 * np.sqrt((sigma[0] ** 2 + eps) * (sigma[1] ** 2 + eps))


def test_chain_is_one_component_although_its_ends_do_not_touch():
    s = [0.01, 0.01]  # level-2 circles of radius 0.02
    params = _params(
        [[(1.0, [0.1, 0.5], s), (1.0, [0.135, 0.5], s), (1.0, [0.17, 0.5], s)]]
    )
    assert not ellipses_intersect(
        params.mean[0, 0], np.eye(2) * 1e-4, params.mean[0, 2], np.eye(2) * 1e-4
    )
    comps = ConnectedComponents.of(params, sigma_eps=0.0)
    np.testing.assert_array_equal(comps.labels, [[0, 0, 0]])
    np.testing.assert_array_equal(comps.counts, [1])
    # the same chain with a larger gap in the middle breaks in two
    params.mean[0, 2, 0] = 0.176
    np.testing.assert_array_equal(
        ConnectedComponents.of(params, sigma_eps=0.0).labels, [[0, 0, 1]]
    )


def test_far_clusters_are_numbered_by_their_lowest_slot():
    s = [0.02, 0.005]
    params = _params(
        [
            [
                (1.0, [0.8, 0.8], s),
                (1.0, [0.2, 0.2], s),
                (1.0, [0.83, 0.8], s),
                (0.5, [0.2, 0.21], s),
                (1.0, [0.5, 0.9], s),
            ]
        ]
    )
    comps = ConnectedComponents.of(params)
    np.testing.assert_array_equal(comps.labels, [[0, 1, 0, 1, 2]])
    np.testing.assert_array_equal(comps.counts, [3])


def test_inactive_slots_are_ignored_even_where_they_overlap():
    s = [0.01, 0.01]
    params = _params(
        [
            [
                (1.0, [0.1, 0.5], s),
                (1.0, [0.13, 0.5], s),
                (3.0, [0.16, 0.5], s),
                (2.0, [0.19, 0.5], s),
            ]
        ],
        capacity=6,
    )
    params.active[0, 2] = False  # the bridge between the two halves
    params.amplitude[0, 2] = (
        3.0  # nonzero, to show inactive slots carry no energy into centroids
    )
    params.mean[0, 5] = [0.115, 0.5]  # inactive, overlapping slot 0
    params.sigma[0, 5] = s
    comps = ConnectedComponents.of(params, sigma_eps=0.0)
    np.testing.assert_array_equal(comps.labels, [[0, 0, -1, 1, -1, -1]])
    np.testing.assert_array_equal(comps.counts, [2])
    np.testing.assert_allclose(comps.centroids[0, 1], [0.19, 0.5], rtol=1e-14)
    params.active[0, 2] = True
    np.testing.assert_array_equal(
        ConnectedComponents.of(params, sigma_eps=0.0).labels, [[0, 0, 0, 0, -1, -1]]
    )


def test_centroids_are_energy_weighted():
    eps = RasterSettings().sigma_eps
    gaussians = [
        (1.0, [0.30, 0.40], [0.02, 0.01], 0.3),
        (2.0, [0.33, 0.41], [0.005, 0.005], 1.0),
        (0.5, [0.31, 0.43], [0.03, 0.002], 2.0),
    ]
    lone = (0.7, [0.8, 0.1], [0.01, 0.02], 0.0)
    params = _params([[*gaussians, lone]], capacity=6)
    comps = ConnectedComponents.of(params)
    assert comps.sigma_eps == eps and comps.level == 2.0
    np.testing.assert_array_equal(comps.labels, [[0, 0, 0, 1, -1, -1]])
    energies = np.array([_energy(a, s, eps) for a, _, s, _ in gaussians])
    means = np.array([m for _, m, _, _ in gaussians])
    expected = energies @ means / energies.sum()
    assert (
        np.linalg.norm(expected - means.mean(0)) > 5e-3
    )  # weighting makes a difference here
    np.testing.assert_allclose(comps.centroids[0, 0], expected, rtol=1e-13)
    np.testing.assert_allclose(comps.centroids[0, 1], lone[1], rtol=1e-14)
    np.testing.assert_array_equal(comps.centroids[0, 2:], 0.0)
    per_slot = comps.centroid_of_slot()
    np.testing.assert_allclose(per_slot[0, :3], np.tile(expected, (3, 1)), rtol=1e-13)
    np.testing.assert_allclose(per_slot[0, 3], lone[1])
    np.testing.assert_array_equal(per_slot[0, 4:], 0.0)
    # no energy at all: the plain mean
    params.amplitude[:] = 0.0
    np.testing.assert_allclose(
        ConnectedComponents.of(params).centroids[0, 0], means.mean(0), rtol=1e-14
    )


def test_problems_of_a_batch_are_independent():
    s = [0.01, 0.01]
    sets = [
        [(1.0, [0.1, 0.1], s), (1.0, [0.5, 0.5], s), (1.0, [0.12, 0.1], s)],
        [
            (1.0, [0.1, 0.1], s),
            (1.0, [0.12, 0.1], s),
            (1.0, [0.14, 0.1], s),
            (1.0, [0.9, 0.9], s),
        ],
        [],
        [(2.0, [0.5, 0.5], s)],
    ]
    params = _params(sets, capacity=5)
    comps = ConnectedComponents.of(params)
    np.testing.assert_array_equal(
        comps.labels,
        [[0, 1, 0, -1, -1], [0, 0, 0, 1, -1], [-1] * 5, [0, -1, -1, -1, -1]],
    )
    np.testing.assert_array_equal(comps.counts, [2, 2, 0, 1])
    assert comps.labels.dtype == np.int32 and comps.centroids.shape == (4, 5, 2)
    np.testing.assert_allclose(comps.centroids[3, 0], [0.5, 0.5])
    np.testing.assert_array_equal(comps.centroids[2], 0.0)
    # the same as each problem on its own
    for b in range(4):
        alone = ConnectedComponents.of(
            GaussianParams(**{k: v[b : b + 1] for k, v in vars(params).items()})
        )
        np.testing.assert_array_equal(alone.labels[0], comps.labels[b])
        np.testing.assert_allclose(alone.centroids[0], comps.centroids[b])


def _find(root, n):
    while root[n] != n:
        n = root[n]
    return n


def _reference_labels(params, level, eps):
    """Pairwise tests and union-find, one problem at a time, numbered by lowest slot."""
    labels = np.full(params.shape, -1)
    for b in range(params.problem_count):
        slots = np.flatnonzero(params.active[b])
        root = {n: n for n in slots}
        cov = gaussian_covariances(params.sigma[b], params.theta[b], eps)
        for x in slots:
            for y in slots:
                if x < y and ellipses_intersect(
                    params.mean[b, x], cov[x], params.mean[b, y], cov[y], level
                ):
                    root[_find(root, y)] = _find(root, x)
        names = {}
        for n in slots:
            labels[b, n] = names.setdefault(_find(root, n), len(names))
    return labels


def test_random_batches_match_a_pairwise_union_find():
    params = random_params(
        np.random.default_rng(11), 6, 16, 40, 60, sigma_px=(0.3, 6.0)
    )
    eps = RasterSettings().sigma_eps
    counts = []
    for level in (1.0, 2.0, 4.0):
        comps = ConnectedComponents.of(params, level=level)
        expected = _reference_labels(params, level, eps)
        np.testing.assert_array_equal(comps.labels, expected)
        np.testing.assert_array_equal(comps.counts, expected.max(axis=1) + 1)
        counts.append(comps.counts)
    # growing ellipses only merge components: never more at a larger level, and fewer somewhere
    assert np.all(counts[1] <= counts[0]) and np.all(counts[2] <= counts[1])
    assert counts[2].sum() < counts[1].sum() < counts[0].sum()


def test_bad_arguments_are_refused():
    params = _params([[(1.0, [0.1, 0.1], [0.0, 0.01])]])
    with pytest.raises(InputError, match="sigma_eps"):
        ConnectedComponents.of(params, sigma_eps=0.0)
    with pytest.raises(InputError, match="level"):
        ConnectedComponents.of(params, level=-1.0)
    diverged = GaussianParams.__new__(GaussianParams)
    diverged.__dict__.update({k: v.copy() for k, v in vars(params).items()})
    diverged.mean[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        ConnectedComponents.of(diverged)
