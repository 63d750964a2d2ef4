"""Which way each Gaussian turns along each triangle edge: the path decisions (docs/method.md, Fitting step 6).

Every Gaussian of G_A can reach its retargeted self in G_{A->B} by turning either way (the two
rotation options, delta+ and delta-; their geometry is ``warp_highlights.model.arcs``).
``decide_paths`` picks one option per Gaussian per directed edge, once, at fit time; the
interpolation then only evaluates ``circular_position`` along the stored choice.

Units: means and centres in image heights (x right, y down); angles in radians from +x towards +y.
Every function is vectorised NumPy float64 and broadcasts over leading axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.arcs import path_centre, rotate_vectors, rotation_options, wrap_half_turn
from ..model.config import PathSettings, rpx_to_normalized
from ..model.errors import InputError
from ..model.gaussians import GaussianParams

__all__ = ["PARITY_MODES", "PathDecisions", "decide_paths"]

PARITY_MODES = ("orientation", "rotation")
"""What phi_pq compares (``decide_paths(parity=...)``): the orientations theta_A of the two
Gaussians (method.md, thesis eq. 3.27 as written) or their positive rotation options delta+."""

# Pairs of Gaussians handled at once by the propagation (bounds the (edges, K, K) temporaries of K packed slots).
_PAIR_BLOCK = 1 << 22


@dataclass(frozen=True)
class PathDecisions:
    """The path of every Gaussian on every directed edge A->B, decided at fit time.

    Attributes:
        delta: (E, N) float64, the chosen signed rotation (radians): delta+ in [0, pi) or delta- in
            [-pi, 0); theta_A + delta reaches theta_{A->B} (mod pi). 0 in inactive slots.
        centre: (E, N, 2) float64, the arc's centre O for ``delta`` (image heights); the chord's
            midpoint for a straight path; the source mean in inactive slots.
        negative: (E, N) bool, True where the negative option was chosen (False when inactive).
        score: (E, N) float64, the propagated weight w' = M^2 w (<= 0 chooses negative); 0 when
            inactive. |w'| <= 1.05.
    """

    delta: np.ndarray
    centre: np.ndarray
    negative: np.ndarray
    score: np.ndarray


def _negative_option_weight(mean_a, mean_b, sigma_a, theta_a, delta_neg) -> np.ndarray:
    """w (thesis eq. 3.24) for the negative option, (E, N).

    The angle thetabar between the major axis and the direction mu_A -> O follows from the chord
    alone: that direction is R(pi/2 - delta/2) applied to the unit chord (up to sign, which cos^2
    ignores). For a straight path (O at infinity) this is the limit |delta| -> 0, the chord's
    normal. When mu_A == mu_B there is no direction and the second term is 0.
    """
    d = np.abs(delta_neg)
    straightness = (np.cos(d) + d - 0.5 * np.pi) / (0.5 * np.pi - 1.0)
    chord = mean_b - mean_a
    length = np.hypot(chord[..., 0], chord[..., 1])
    moved = length > 0
    unit_chord = chord / np.where(moved, length, 1.0)[..., None]
    towards_centre = rotate_vectors(unit_chord, 0.5 * np.pi - 0.5 * delta_neg)
    # sigma_x lies along theta, sigma_y across it; a round Gaussian takes theta as its axis
    axis = theta_a + np.where(
        np.abs(sigma_a[..., 1]) > np.abs(sigma_a[..., 0]), 0.5 * np.pi, 0.0
    )
    cos_bar = (
        np.cos(axis) * towards_centre[..., 0] + np.sin(axis) * towards_centre[..., 1]
    )
    cos2 = np.where(moved, cos_bar * cos_bar, 0.5)
    return straightness + (cos2 - 0.5) / 10.0


def _propagate(
    weight, mean_a, mean_b, parity_angle, active, length_scale
) -> np.ndarray:
    """w' = M (M w) per edge over its active Gaussians (thesis eq. 3.25-3.29).

    Only active Gaussians take part, so each edge's are packed first and the edges grouped by how many
    they have (rounded up to a power of two, the group's width): a set holds a few Gaussians in 64
    slots, and (E, 64, 64) pair arrays would be mostly padding."""
    edges, slots = weight.shape
    inv_scale2 = 1.0 / (length_scale * length_scale)
    propagated = np.zeros_like(weight)
    counts = np.count_nonzero(active, axis=1)
    order = np.argsort(~active, axis=1, kind="stable")  # each edge's active slots first, in slot order
    widths = np.where(counts > 0, 1 << np.ceil(np.log2(np.maximum(counts, 1))).astype(np.int64), 0)
    for width in np.unique(widths[widths > 0]):
        group = np.flatnonzero(widths == width)
        width = min(int(width), slots)
        block = max(1, _PAIR_BLOCK // (width * width))
        for start in range(0, len(group), block):  # blocks of edges, each fully vectorised
            rows = group[start : start + block, None]
            packed = order[rows[:, 0], :width]  # (e, width) slots, the active ones first
            on = active[rows, packed]
            pair = on[:, :, None] & on[:, None, :]
            distance2 = np.zeros(pair.shape)
            for means in (mean_a[rows, packed], mean_b[rows, packed]):
                for axis in (0, 1):
                    difference = means[:, :, None, axis] - means[:, None, :, axis]
                    distance2 += difference * difference
            xi = np.where(pair, 1.0 / (1.0 + distance2 * inv_scale2), 0.0)
            # eta includes xi_pp = 1, so every active row of |M| sums to 1
            eta = xi.sum(axis=-1)
            angle = parity_angle[rows, packed]
            # the padding inert phi_pp = 1 and xi_pp = 1 give M_pp = 1 / eta_p; free rows and columns are 0
            phi = np.where(pair, np.sign(0.5 * np.pi - np.abs(angle[:, :, None] - angle[:, None, :])), 0.0)
            matrix = phi * xi / np.where(eta > 0, eta, 1.0)[..., None]
            once = np.einsum("epq,eq->ep", matrix, np.where(on, weight[rows, packed], 0.0))
            propagated[rows, packed] = np.where(on, np.einsum("epq,eq->ep", matrix, once), 0.0)
    return propagated


def decide_paths(
    source: GaussianParams,
    retargeted: GaussianParams,
    settings: PathSettings | None = None,
    *,
    parity: str | None = None,
) -> PathDecisions:
    """Choose the rotation option of every Gaussian on every directed edge A->B (docs/method.md, Fitting step 6).

    Per Gaussian, the weight of the negative option (thesis eq. 3.24) is
    ``w = (cos d + d - pi/2) / (pi/2 - 1) + (cos^2(thetabar) - 1/2) / 10`` with d = |delta-| and
    thetabar the angle between the major axis in G_A (theta if |sigma_x| >= |sigma_y|, else
    theta + pi/2) and the direction from mu_A to the negative option's centre. Neighbours then vote:
    ``xi_pq = 1 / (1 + rho_pq^2 + rhobar_pq^2)`` (mean distances in G_A and G_{A->B}, in units of
    ``settings.length_scale_rpx``), ``eta_p = sum_q xi_pq``, ``M_pp = 1 / eta_p``,
    ``M_pq = phi_pq xi_pq / eta_p``, ``w' = M (M w)`` over the edge's active Gaussians.
    w' <= 0 chooses delta-, w' > 0 chooses delta+.

    Choices where the thesis is silent or loose:
        - eta_p sums over every active q *including* q = p (xi_pp = 1), as eq. 3.26 is written; only
          then does each row of |M| sum to 1, which keeps w' in the range of w as the thesis intends.
        - thetabar for a straight negative option (|delta-| < ``straight_below``, O at infinity) is
          its limit, measured against the chord's normal; if mu_A == mu_B there is no direction and
          the thetabar term is 0. A round Gaussian (|sigma_x| == |sigma_y|) takes theta as its axis.
        - phi_pq = sign(pi/2 - |a_p - a_q|) with a in [0, pi); exactly perpendicular pairs get
          phi = 0 (no vote). ``parity="orientation"`` (method.md / eq. 3.27 as written) uses
          a = theta_A; ``parity="rotation"`` (the default) uses a = delta+, for which phi = +1 exactly when
          the same-sign options of p and q are closer rotations than the opposite-sign ones (with
          theta_A, two near-parallel Gaussians either side of the 0/pi wrap get phi = -1).

    Args:
        source: G_A per directed edge, (E, N) slots (the estimated set of each edge's start light).
        retargeted: G_{A->B}, (E, N); slot p is the same Gaussian as in ``source``. Only slots active
            in ``source`` take part.
        settings: ``PathSettings`` (straight_below, length_scale_rpx); default ``PathSettings()``.
        parity: ``"orientation"`` or ``"rotation"``, what phi_pq compares (see above); default from
            ``settings.compare_rotations``.

    Returns:
        ``PathDecisions`` with (E, N) arrays; finite for finite inputs.
    """
    settings = PathSettings() if settings is None else settings
    if source.shape != retargeted.shape:
        raise InputError(
            f"source and retargeted Gaussian sets must have the same (edges, slots) shape, got "
            f"{source.shape} and {retargeted.shape}"
        )
    if parity is None:
        parity = "rotation" if settings.compare_rotations else "orientation"
    if parity not in PARITY_MODES:
        raise InputError(
            f"parity must be one of {', '.join(PARITY_MODES)}, got {parity!r}"
        )
    active = np.asarray(source.active, dtype=bool)
    mean_a = np.asarray(source.mean, dtype=np.float64)
    mean_b = np.asarray(retargeted.mean, dtype=np.float64)
    theta_a = np.asarray(source.theta, dtype=np.float64)
    delta_pos, delta_neg = rotation_options(theta_a, retargeted.theta)

    weight = np.where(
        active,
        _negative_option_weight(mean_a, mean_b, source.sigma, theta_a, delta_neg),
        0.0,
    )
    parity_angle = wrap_half_turn(theta_a) if parity == "orientation" else delta_pos
    length_scale = rpx_to_normalized(settings.length_scale_rpx)
    score = _propagate(weight, mean_a, mean_b, parity_angle, active, length_scale)

    negative = active & (score <= 0)
    delta = np.where(active, np.where(negative, delta_neg, delta_pos), 0.0)
    centre = path_centre(mean_a, mean_b, delta, settings.straight_below)
    centre = np.where(active[..., None], centre, mean_a)
    return PathDecisions(
        delta=delta,
        centre=centre,
        negative=negative,
        score=np.where(active, score, 0.0),
    )
