"""Circular paths and the choice of rotation direction (docs/method.md, Fitting step 6).

The expected decisions below are worked out by hand from method.md's formulas (numbers in the
comments), not by calling the implementation's helper functions.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warp_highlights.fit.paths import PathDecisions, decide_paths
from warp_highlights.model.arcs import circular_position, path_centre, rotation_options
from warp_highlights.model.config import PathSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianParams

L = 15.0 / 270.0  # default length scale, 15 rpx in image heights
DEG = math.pi / 180.0


def rotate(vector, angle):
    """R(angle) (x, y), written out independently of the module."""
    vector = np.asarray(vector, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack(
        [
            c * vector[..., 0] - s * vector[..., 1],
            s * vector[..., 0] + c * vector[..., 1],
        ],
        -1,
    )


def first_term(d):
    """(cos d + d - pi/2) / (pi/2 - 1): -1 at d = 0, 0 at d = pi/2 (cos = 0, d - pi/2 = 0), +1 at pi."""
    return (math.cos(d) + d - math.pi / 2) / (math.pi / 2 - 1)


def edge_sets(gaussians, capacity=None):
    """(source, retargeted) for one edge from tuples (mean_a, mean_b, sigma, theta_a, theta_b)."""
    source = [{"mean": g[0], "sigma": g[2], "theta": g[3]} for g in gaussians]
    target = [{"mean": g[1], "sigma": g[2], "theta": g[4]} for g in gaussians]

    def pack(items):
        return GaussianParams.from_sets(
            [
                {
                    "amplitude": np.ones(len(items)),
                    "mean": [i["mean"] for i in items],
                    "sigma": [i["sigma"] for i in items],
                    "theta": [i["theta"] for i in items],
                }
            ],
            capacity=capacity,
        )

    return pack(source), pack(target)


# --- geometry ---------------------------------------------------------------------------------------


def random_pairs(rng, count):
    mean_a = rng.uniform(0.0, 2.0, (count, 2))
    mean_b = mean_a + rng.normal(0.0, 0.2, (count, 2)) * rng.choice(
        [1e-6, 1.0, 3.0], (count, 1)
    )
    magnitude = rng.uniform(1e-3, np.pi, count)
    delta = magnitude * rng.choice([-1.0, 1.0], count)
    return mean_a, mean_b, delta


def test_centre_turns_a_into_b_and_is_equidistant():
    rng = np.random.default_rng(1)
    mean_a, mean_b, delta = random_pairs(rng, 5000)
    centre = path_centre(mean_a, mean_b, delta)
    assert centre.shape == (5000, 2)
    np.testing.assert_allclose(
        rotate(mean_a - centre, delta) + centre, mean_b, rtol=0, atol=1e-10
    )
    radius_a = np.linalg.norm(mean_a - centre, axis=-1)
    radius_b = np.linalg.norm(mean_b - centre, axis=-1)
    np.testing.assert_allclose(radius_a, radius_b, rtol=1e-12, atol=1e-12)
    # on the perpendicular bisector: (O - midpoint) . chord == 0
    chord = mean_b - mean_a
    along = np.sum((centre - 0.5 * (mean_a + mean_b)) * chord, axis=-1)
    np.testing.assert_allclose(along, 0.0, atol=1e-10)


def test_centre_by_hand_quarter_turn():
    # A = (0, 0), B = (1, 0), delta = +pi/2: R(pi/2) turns (x, y) into (-y, x); O = (1/2, 1/2)
    # gives A - O = (-1/2, -1/2) -> (1/2, -1/2) = B - O.
    np.testing.assert_allclose(
        path_centre([0.0, 0.0], [1.0, 0.0], np.pi / 2), [0.5, 0.5], atol=1e-15
    )
    np.testing.assert_allclose(
        path_centre([0.0, 0.0], [1.0, 0.0], -np.pi / 2), [0.5, -0.5], atol=1e-15
    )


def test_centre_edge_cases_stay_finite():
    a = np.array([0.3, 0.4])
    b = np.array([0.5, 0.1])
    # a half turn: O is the midpoint
    for delta in (np.pi, -np.pi, np.nextafter(-np.pi, 0.0)):
        np.testing.assert_allclose(path_centre(a, b, delta), 0.5 * (a + b), atol=1e-15)
    # coincident ends: O = A for every rotation
    for delta in (0.0, 1e-9, 0.3, -np.pi):
        np.testing.assert_allclose(path_centre(a, a, delta), a, atol=1e-15)
    # straight: the midpoint, also at delta = 0 with a zero threshold
    np.testing.assert_array_equal(path_centre(a, b, 5e-5), 0.5 * (a + b))
    np.testing.assert_array_equal(
        path_centre(a, b, 0.0, straight_below=0.0), 0.5 * (a + b)
    )
    assert np.all(np.isfinite(path_centre(a, b, 1e-300, straight_below=0.0)))
    # just above the threshold it is a real (far) centre
    assert np.linalg.norm(path_centre(a, b, 2e-4) - a) > 100.0
    # broadcasting: many deltas for one pair
    assert path_centre(a, b, np.linspace(-3, 3, 7)).shape == (7, 2)
    with pytest.raises(InputError):
        path_centre(a, b, 0.1, straight_below=-1.0)


def test_circular_position_follows_the_arc():
    rng = np.random.default_rng(2)
    mean_a, mean_b, delta = random_pairs(rng, 3000)
    centre = path_centre(mean_a, mean_b, delta)
    np.testing.assert_allclose(
        circular_position(mean_a, mean_b, delta, 0.0), mean_a, atol=1e-14
    )
    np.testing.assert_allclose(
        circular_position(mean_a, mean_b, delta, 1.0), mean_b, atol=1e-12
    )
    radius = np.linalg.norm(mean_a - centre, axis=-1)
    for fraction in (0.1, 1 / 3, 0.5, 0.9):
        position = circular_position(mean_a, mean_b, delta, fraction)
        # the literal formula R(f delta)(A - O) + O
        literal = rotate(mean_a - centre, fraction * delta) + centre
        np.testing.assert_allclose(position, literal, rtol=0, atol=1e-10)
        np.testing.assert_allclose(
            np.linalg.norm(position - centre, axis=-1), radius, rtol=1e-10, atol=1e-12
        )
    # per-element fractions broadcast with the deltas
    fractions = rng.uniform(0, 1, 3000)
    literal = rotate(mean_a - centre, fractions * delta) + centre
    np.testing.assert_allclose(
        circular_position(mean_a, mean_b, delta, fractions), literal, atol=1e-10
    )


def test_circular_position_small_rotation_is_the_straight_blend():
    a = np.array([0.2, 0.7])
    b = np.array([0.9, 0.3])
    for fraction in (0.0, 0.25, 0.5, 1.0):
        blend = a + fraction * (b - a)
        np.testing.assert_array_equal(circular_position(a, b, 5e-5, fraction), blend)
        np.testing.assert_array_equal(circular_position(a, b, -5e-5, fraction), blend)
        np.testing.assert_array_equal(
            circular_position(a, b, 0.0, fraction, straight_below=0.0), blend
        )
        # just above the threshold the arc bulges by at most |chord| |delta| / 8 (the sagitta)
        bulge = np.linalg.norm(circular_position(a, b, 2e-4, fraction) - blend)
        assert bulge <= np.linalg.norm(b - a) * 2e-4 / 8 * (1 + 1e-6)
    # a half turn about O = (1/2, 0) from A = (0, 0) to B = (1, 0): with f = 1/2, A - O = (-1/2, 0)
    # turned by pi/2 is (0, -1/2), so the path passes (1/2, -1/2)
    half = circular_position([0.0, 0.0], [1.0, 0.0], np.pi, 0.5)
    np.testing.assert_allclose(half, [0.5, -0.5], atol=1e-15)


def test_rotation_options_reach_the_same_orientation():
    rng = np.random.default_rng(3)
    theta_a = rng.uniform(-10, 10, 10000)
    theta_b = rng.uniform(-10, 10, 10000)
    theta_b[:100] = theta_a[:100]  # no turn
    theta_b[100:200] = (
        theta_a[100:200] + np.pi
    )  # a half turn is no turn for an orientation
    theta_b[200:300] = theta_a[200:300] - 1e-17  # rounding just below zero
    delta_pos, delta_neg = rotation_options(theta_a, theta_b)
    assert np.all((delta_pos >= 0) & (delta_pos < np.pi))
    assert np.all((delta_neg >= -np.pi) & (delta_neg < 0))
    np.testing.assert_allclose(delta_pos - delta_neg, np.pi, atol=1e-15)
    for delta in (delta_pos, delta_neg):
        # same orientation mod pi <=> sin of the difference is 0
        np.testing.assert_allclose(np.sin(theta_a + delta - theta_b), 0.0, atol=1e-12)
    np.testing.assert_allclose(delta_pos[:300], 0.0, atol=1e-12)
    pos, neg = rotation_options(0.0, 10 * DEG)
    assert math.isclose(pos, 10 * DEG) and math.isclose(neg, -170 * DEG)


# --- decisions: single Gaussians ----------------------------------------------------------------------

A0 = (0.5, 0.5)
CHORD = 0.1  # image heights, along +x
B0 = (A0[0] + CHORD, A0[1])
ELONGATED = (3 / 270, 1 / 270)


def single(theta_a, turn, sigma=ELONGATED, settings=None):
    source, target = edge_sets([(A0, B0, sigma, theta_a, theta_a + turn)])
    return decide_paths(source, target, settings)


def test_small_turn_chooses_the_small_rotation():
    # +10 deg: delta+ = 10 deg, delta- = -170 deg. d = 170 deg gives a first term of
    # (cos 170 + 2.9671 - 1.5708) / 0.5708 = (-0.9848 + 1.3963) / 0.5708 = +0.7208; the thetabar term
    # is at most 0.05, so w > 0: positive.
    for theta_a in (0.0, 0.7, 2.0, -1.0):
        result = single(theta_a, 10 * DEG)
        assert not result.negative[0, 0]
        assert math.isclose(result.delta[0, 0], 10 * DEG, abs_tol=1e-12)
        assert 0.72 - 0.051 < result.score[0, 0] < 0.7209 + 0.051
    # 170 deg: delta- = -10 deg, first term -0.7208: negative, a 10 degree clockwise turn
    for theta_a in (0.0, 0.7, 2.0, -1.0):
        result = single(theta_a, 170 * DEG)
        assert result.negative[0, 0]
        assert math.isclose(result.delta[0, 0], -10 * DEG, abs_tol=1e-12)
        assert -0.7209 - 0.051 < result.score[0, 0] < -0.72 + 0.051


# Near the break-even d = pi/2 of the first term, thetabar decides. Take delta+ = pi/2 - 0.2, so
# delta- = -(pi/2 + 0.2), d = pi/2 + 0.2, first term (0.2 - sin 0.2) / (pi/2 - 1) = +0.0023313.
# The negative option's centre, by hand: O = midpoint + (c/2) cot(delta-/2) (0, 1) with
# cot(-(pi/4 + 0.1)) = -tan(pi/4 - 0.1) = -0.817630, so O - A = (0.05, -0.040882): the direction
# from A to O is at angle -(pi/4 - 0.1) = -0.685398 rad.
BREAK_TURN = np.pi / 2 - 0.2
BREAK_FIRST = 0.0023312504696916
TOWARDS_O = -(np.pi / 4 - 0.1)


@pytest.mark.parametrize(
    "theta_a, sigma, expected_w",
    [
        # major axis along A->O: cos^2 = 1, w = 0.0023313 + 0.05: positive
        (TOWARDS_O + np.pi, ELONGATED, BREAK_FIRST + 0.05),
        # major axis across A->O (the negative path moves along the Gaussian): w = 0.0023313 - 0.05
        (TOWARDS_O + np.pi / 2, ELONGATED, BREAK_FIRST - 0.05),
        # the same major axis given by sigma_y > sigma_x with theta a quarter turn back
        (TOWARDS_O, ELONGATED[::-1], BREAK_FIRST - 0.05),
        # axis at 45 degrees: cos^2 = 1/2, the term vanishes and the first term decides: positive
        (TOWARDS_O + np.pi / 4, ELONGATED, BREAK_FIRST),
    ],
)
def test_thetabar_decides_near_the_break_even(theta_a, sigma, expected_w):
    result = single(theta_a, BREAK_TURN, sigma=sigma)
    # one Gaussian: eta = xi_pp = 1, M = [[1]], w' = w
    assert math.isclose(result.score[0, 0], expected_w, abs_tol=1e-9)
    assert result.negative[0, 0] == (expected_w <= 0)
    expected_delta = BREAK_TURN - np.pi if expected_w <= 0 else BREAK_TURN
    assert math.isclose(result.delta[0, 0], expected_delta, abs_tol=1e-12)


def test_thetabar_overrides_a_weak_first_term_the_other_way():
    # delta+ = pi/2 + 0.2, delta- = -(pi/2 - 0.2): first term -0.0023313 (negative on its own). Here
    # O - A = (c/2)(1, -cot(pi/4 - 0.1)) = (0.05, -0.061152), angle -(pi/4 + 0.1); a major axis
    # along it adds +0.05: positive.
    turn = np.pi / 2 + 0.2
    result = single(-(np.pi / 4 + 0.1), turn)
    assert math.isclose(result.score[0, 0], -BREAK_FIRST + 0.05, abs_tol=1e-9)
    assert not result.negative[0, 0]
    result = single(-(np.pi / 4 + 0.1) + np.pi / 2, turn)
    assert math.isclose(result.score[0, 0], -BREAK_FIRST - 0.05, abs_tol=1e-9)
    assert result.negative[0, 0]


def test_straight_negative_option_and_resting_gaussian():
    # delta+ = pi - 1e-6: delta- = -1e-6 is a straight path; w ~ -1 + small: negative, centre = midpoint
    result = single(0.3, np.pi - 1e-6)
    assert result.negative[0, 0]
    assert math.isclose(result.delta[0, 0], -1e-6, rel_tol=1e-6)
    np.testing.assert_allclose(
        result.centre[0, 0], [A0[0] + CHORD / 2, A0[1]], atol=1e-15
    )
    assert -1.06 < result.score[0, 0] < -0.94
    # a Gaussian that stays put: no direction to O, thetabar term 0, w = first term exactly
    source, target = edge_sets([(A0, A0, ELONGATED, 0.4, 0.4 + BREAK_TURN)])
    result = decide_paths(source, target)
    assert math.isclose(result.score[0, 0], BREAK_FIRST, abs_tol=1e-12)
    np.testing.assert_allclose(result.centre[0, 0], A0, atol=1e-15)


# --- decisions: propagation -------------------------------------------------------------------------

Q_THETA = (
    TOWARDS_O + np.pi / 2
)  # q alone: w_q = 0.0023313 - 0.05 = -0.0476687, chooses negative
W_Q = BREAK_FIRST - 0.05
# p parallel to q (same theta), turning +10 deg: first term +0.7208449; its negative option (-170 deg)
# has A->O at angle pi/2 - delta-/2 = 175 deg; the axis at pi/4 + 0.1 = 50.73 deg is 124.27 deg from
# it: cos^2 = 0.3170811, term -0.0182919, w_p = 0.7025531
W_P = 0.7208449481334932 + (0.3170810637564401 - 0.5) / 10


def pair_edge(
    offset, p_theta=Q_THETA, p_turn=10 * DEG, q_theta=Q_THETA, q_turn=BREAK_TURN
):
    """q at A0 -> B0, p displaced by ``offset`` (image heights, along y) in both sets."""
    pa = (A0[0], A0[1] + offset)
    pb = (B0[0], B0[1] + offset)
    return edge_sets(
        [
            (pa, pb, ELONGATED, p_theta, p_theta + p_turn),
            (A0, B0, ELONGATED, q_theta, q_theta + q_turn),
        ]
    )


def test_neighbour_vote_pulls_a_weak_gaussian():
    # rho = rhobar = 1 length scale: xi = 1/3, eta = 4/3, M = [[3/4, 1/4], [1/4, 3/4]],
    # M^2 = [[5/8, 3/8], [3/8, 5/8]]: w'_q = 3/8 w_p + 5/8 w_q = 0.263457 - 0.029793 = +0.233664
    source, target = pair_edge(L)
    result = decide_paths(source, target)
    assert math.isclose(result.score[0, 1], 3 / 8 * W_P + 5 / 8 * W_Q, abs_tol=1e-9)
    assert math.isclose(result.score[0, 0], 5 / 8 * W_P + 3 / 8 * W_Q, abs_tol=1e-9)
    assert not result.negative[
        0, 1
    ]  # alone it would be negative (see the break-even test)
    assert math.isclose(result.delta[0, 1], BREAK_TURN, abs_tol=1e-12)
    # the length scale is in rpx: at 7.5 rpx the same pair is 2 units apart, xi = 1/9, eta = 10/9,
    # M = [[0.9, 0.1], [0.1, 0.9]], M^2 = [[0.82, 0.18], [0.18, 0.82]]: w'_q = 0.12646 - 0.03909
    result = decide_paths(source, target, PathSettings(length_scale_rpx=7.5))
    assert math.isclose(result.score[0, 1], 0.18 * W_P + 0.82 * W_Q, abs_tol=1e-9)
    assert not result.negative[0, 1]


def test_an_exact_tie_goes_negative():
    # two resting Gaussians on one point (xi = 1, eta = 2, M = [[1/2, 1/2], [1/2, 1/2]], no thetabar
    # term), turning by 10 and 170 deg: d = 170 and 10 deg, and the first term is odd about pi/2
    # (f(pi - d) = -f(d)), so w = (+0.7208, -0.7208), M w = 0 and w' = 0: both take delta-.
    source, target = edge_sets(
        [
            (A0, A0, ELONGATED, 0.0, 10 * DEG),
            (A0, A0, ELONGATED, 0.0, 170 * DEG),
        ]
    )
    result = decide_paths(source, target, parity="orientation")
    np.testing.assert_array_equal(result.score, 0.0)
    assert result.negative.all()
    np.testing.assert_allclose(result.delta[0], [-170 * DEG, -10 * DEG], atol=1e-12)
    # comparing rotations (the default), delta+ = 10 and 170 deg are more than pi/2 apart: phi = -1,
    # M = [[1/2, -1/2], [-1/2, 1/2]], M^2 = M, w' = w: each Gaussian takes its own short turn
    result = decide_paths(source, target)
    np.testing.assert_allclose(result.score[0], [0.7208449481334932, -0.7208449481334932], atol=1e-12)
    np.testing.assert_allclose(result.delta[0], [10 * DEG, -10 * DEG], atol=1e-12)


def test_far_apart_gaussians_decide_alone():
    # 100 length scales apart: xi = 1 / 20001, the vote is ~2e-5 of w_p
    source, target = pair_edge(100 * L)
    result = decide_paths(source, target)
    assert result.negative[0, 1] and not result.negative[0, 0]
    assert math.isclose(result.score[0, 1], W_Q, abs_tol=1e-3)
    assert math.isclose(result.score[0, 0], W_P, abs_tol=1e-3)


def test_parity_inverts_the_vote():
    # wrap case: p at theta 0.02, q at pi - 0.02 (nearly parallel, either side of the 0/pi wrap).
    # q turns by pi/2 - 0.2; its axis -0.02 is 0.6654 rad from A->O: cos^2 = 0.6188513, w_q = 0.0142164.
    # p turns by +10 deg; axis 0.02 vs A->O at 175 deg = -0.0873: cos^2 = 0.9885380, w_p = 0.7696987.
    w_q, w_p = 0.014216381791048371, 0.7696987449756298
    source, target = pair_edge(L, p_theta=0.02, q_theta=np.pi - 0.02)
    # orientation parity: |0.02 - (pi - 0.02)| > pi/2, phi = -1, M^2 off-diagonal -3/8:
    # w'_q = -3/8 w_p + 5/8 w_q = -0.279752: negative
    result = decide_paths(source, target, parity="orientation")
    assert math.isclose(result.score[0, 1], -3 / 8 * w_p + 5 / 8 * w_q, abs_tol=1e-9)
    assert result.negative[0, 1]
    # rotation parity compares delta+ = 10 deg and 78.5 deg: phi = +1, w'_q = +0.297522: positive
    result = decide_paths(source, target, parity="rotation")
    assert math.isclose(result.score[0, 1], 3 / 8 * w_p + 5 / 8 * w_q, abs_tol=1e-9)
    assert not result.negative[0, 1]
    # the settings choose the default: compare_rotations=True is parity="rotation"
    assert np.array_equal(decide_paths(source, target).score, result.score)
    by_orientation = decide_paths(source, target, PathSettings(compare_rotations=False))
    assert math.isclose(by_orientation.score[0, 1], -3 / 8 * w_p + 5 / 8 * w_q, abs_tol=1e-9)
    with pytest.raises(InputError, match="parity"):
        decide_paths(source, target, parity="sideways")


# --- batching, padding, robustness ----------------------------------------------------------------


def random_edges(rng, edges, slots, inactive=0.3):
    """Clustered Gaussians (strong coupling), small moves, any rotation; garbage in free slots."""
    shape = (edges, slots)
    active = rng.random(shape) >= inactive
    mean_a = rng.uniform(0.4, 0.6, shape + (2,))
    mean_b = mean_a + rng.normal(0, 10 / 270, shape + (2,))
    sigma = rng.uniform(0.5, 8, shape + (2,)) / 270
    theta_a = rng.uniform(-4, 4, shape)
    theta_b = theta_a + rng.uniform(-np.pi, np.pi, shape)

    def make(mean, theta):
        return GaussianParams(
            amplitude=np.ones(shape),
            mean=mean,
            sigma=sigma,
            theta=theta,
            weight=np.ones(shape),
            active=active,
        )

    return make(mean_a, theta_a), make(mean_b, theta_b)


def take(params, rows, cols):
    return GaussianParams(
        amplitude=params.amplitude[rows][:, cols],
        mean=params.mean[rows][:, cols],
        sigma=params.sigma[rows][:, cols],
        theta=params.theta[rows][:, cols],
        weight=params.weight[rows][:, cols],
        active=params.active[rows][:, cols],
    )


def assert_same(batched: PathDecisions, alone: PathDecisions, row, cols):
    np.testing.assert_allclose(
        batched.score[row, cols], alone.score[0], rtol=1e-12, atol=1e-14
    )
    decided = np.abs(alone.score[0]) > 1e-9  # exact ties may round either way
    np.testing.assert_array_equal(
        batched.negative[row, cols][decided], alone.negative[0][decided]
    )
    np.testing.assert_allclose(
        batched.delta[row, cols][decided], alone.delta[0][decided], atol=0
    )
    np.testing.assert_allclose(
        batched.centre[row, cols][decided], alone.centre[0][decided], atol=1e-12
    )


def test_batched_equals_per_edge_and_padding_is_ignored():
    rng = np.random.default_rng(4)
    source, target = random_edges(rng, 9, 12)
    batched = decide_paths(source, target)
    assert batched.negative.any() and (~batched.negative & source.active).any()
    all_slots = np.arange(12)
    for e in range(9):
        # each edge alone
        assert_same(
            batched,
            decide_paths(take(source, [e], all_slots), take(target, [e], all_slots)),
            e,
            all_slots,
        )
        # only its active Gaussians, packed without padding
        keep = np.flatnonzero(source.active[e])
        if keep.size:
            assert_same(
                batched,
                decide_paths(take(source, [e], keep), take(target, [e], keep)),
                e,
                keep,
            )


def test_edge_blocks_do_not_change_the_result(monkeypatch):
    from warp_highlights.fit import paths

    rng = np.random.default_rng(8)
    source, target = random_edges(rng, 7, 12)
    whole = decide_paths(source, target)
    monkeypatch.setattr(
        paths, "_PAIR_BLOCK", 3 * 12 * 12
    )  # blocks of 3 edges: 3 + 3 + 1
    blocked = decide_paths(source, target)
    np.testing.assert_array_equal(blocked.score, whole.score)
    np.testing.assert_array_equal(blocked.negative, whole.negative)


def test_inactive_slots_do_not_matter():
    rng = np.random.default_rng(5)
    source, target = random_edges(rng, 4, 10)
    reference = decide_paths(source, target)
    # scramble every parameter of the free slots
    free = ~source.active
    scrambled = []
    for params in (source, target):
        copy = params.copy()
        copy.mean[free] = rng.uniform(-5, 5, (free.sum(), 2))
        copy.sigma[free] = rng.uniform(0, 1, (free.sum(), 2))
        copy.theta[free] = rng.uniform(-9, 9, free.sum())
        scrambled.append(copy)
    again = decide_paths(*scrambled)
    on = source.active
    np.testing.assert_array_equal(again.negative, reference.negative)
    np.testing.assert_array_equal(again.score[on], reference.score[on])
    np.testing.assert_array_equal(again.delta, reference.delta)
    # free slots: no rotation, centre at the source mean, not negative, score 0
    assert (
        np.all(again.delta[free] == 0)
        and not again.negative[free].any()
        and np.all(again.score[free] == 0)
    )
    np.testing.assert_array_equal(again.centre[free], scrambled[0].mean[free])


def test_outputs_are_finite_and_consistent_on_degenerate_input():
    rng = np.random.default_rng(6)
    source, target = random_edges(rng, 30, 16, inactive=0.1)
    target = target.copy()
    target.mean[:10] = source.mean[:10]  # resting Gaussians
    target.theta[10:15] = source.theta[10:15]  # no turn: delta- = -pi
    target.theta[15:20] = source.theta[15:20] + np.pi / 2  # exactly a quarter turn
    target.theta[20:22] = source.theta[20:22] + np.pi - 1e-9  # straight negative option
    source = source.copy()
    source.mean[22:26, :] = source.mean[
        22:26, :1
    ]  # all Gaussians of an edge on one point
    source.sigma[26:] = source.sigma[26:, :, :1]  # round Gaussians
    result = decide_paths(source, target)
    on = source.active
    for name in ("delta", "centre", "score"):
        assert np.all(np.isfinite(getattr(result, name))), name
    assert (
        result.delta.dtype == np.float64
        and result.centre.shape == (30, 16, 2)
        and result.negative.dtype == bool
    )
    assert np.all(np.abs(result.score) <= 1.05 + 1e-12)
    # the chosen rotation reaches theta_B and lies in its option's range
    np.testing.assert_allclose(
        np.sin(source.theta + result.delta - target.theta)[on], 0.0, atol=1e-9
    )
    assert np.all(result.delta[on & result.negative] < 0) and np.all(
        result.delta[on & ~result.negative] >= 0
    )
    # the stored centre turns mu_A into mu_B wherever the path is an arc
    arc = on & (np.abs(result.delta) >= PathSettings().straight_below)
    turned = rotate(source.mean - result.centre, result.delta) + result.centre
    np.testing.assert_allclose(turned[arc], target.mean[arc], atol=1e-9)


def test_mismatched_shapes_are_an_input_error():
    rng = np.random.default_rng(7)
    source, _ = random_edges(rng, 3, 5)
    _, target = random_edges(rng, 3, 6)
    with pytest.raises(InputError, match="same"):
        decide_paths(source, target)


def _dense_propagation(weight, mean_a, mean_b, parity_angle, active, length_scale):
    """Float64 reference of w' = M (M w): every slot of every edge, free ones zero (no packing)."""
    pair = active[:, :, None] & active[:, None, :]
    distance2 = sum((means[:, :, None, axis] - means[:, None, :, axis]) ** 2 for means in (mean_a, mean_b)
                    for axis in (0, 1))
    xi = np.where(pair, 1.0 / (1.0 + distance2 / length_scale**2), 0.0)
    eta = xi.sum(axis=-1)
    phi = np.sign(0.5 * np.pi - np.abs(parity_angle[:, :, None] - parity_angle[:, None, :]))
    matrix = phi * xi / np.where(eta > 0, eta, 1.0)[..., None]
    once = np.einsum("epq,eq->ep", matrix, np.where(active, weight, 0.0))
    return np.einsum("epq,eq->ep", matrix, once)


@pytest.mark.parametrize("seed", range(6))
def test_packed_propagation_is_the_dense_one(seed):
    """Edges of 0 to all active slots (groups of 1, 2, 4, ... packed slots) give the dense M (M w) to rounding."""
    from warp_highlights.fit import paths

    rng = np.random.default_rng(seed)
    edges, slots = 40, 13
    source, target = random_edges(rng, edges, slots, inactive=0.0)
    counts = rng.integers(0, slots + 1, edges)
    active = np.zeros((edges, slots), bool)
    for e, count in enumerate(counts):
        active[e, rng.choice(slots, count, replace=False)] = True
    weight = rng.uniform(-1, 1, (edges, slots))
    angle = rng.uniform(0, np.pi, (edges, slots))
    angle[~active] = np.nan  # garbage in free slots stays out
    packed = paths._propagate(weight, source.mean, target.mean, angle, active, 0.05)
    dense = _dense_propagation(weight, source.mean, target.mean, np.nan_to_num(angle), active, 0.05)
    np.testing.assert_allclose(packed, np.where(active, dense, 0.0), rtol=1e-12, atol=1e-14)
    assert np.all(packed[~active] == 0)
