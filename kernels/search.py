"""Retargeting's coarse start: for every connected component of every edge's source set, the translation
on a grid that best lays it onto the target's (blurred) specular image.

Between lights far apart (a sparse capture) a sharp highlight travels further than its own size, and
the rigid phase's gradient, which only sees the overlap of the component with the target, has nothing
to follow. So before it, every component tries every offset t of a disc of candidates:

    score(t) = prior(t) * sum_{p in component} w_p a_p^2 * T_blur(mu_p + t)

(the Gaussians' peaks times the target blurred by about the grid step, sampled at the moved centres).
The prior says nearer is likelier (a Gaussian of width r in |t|) and, where the lights' half-vectors
tell which way a highlight goes (``image_headings``), that it goes that way or back (narrower across
that line). It starts from the best offset where it scores at least
``gain`` times the unmoved component and ``margin`` times every offset further than ``exclusion`` from it: a
highlight that could have gone to several places (glints on a bumpy surface, which do not travel but
fade where they are) keeps its place. One thread per (edge, component slot); ``blur_along`` blurs the
targets in two launches.
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

import math

import numpy as np
import warp as wp

from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

__all__ = ["blur_along", "blurred", "candidate_offsets", "component_members", "half_vector_changes", "image_headings",
           "search_blur_px", "search_translations", "searched_translations"]


@wp.kernel(enable_backward=False)
def blur_along(images: wp.array3d(dtype=float), sigma: float, radius: int, across_rows: int,
               out: wp.array3d(dtype=float)):
    """out = images convolved with a unit-sum Gaussian of ``sigma`` pixels (zeros beyond the image) along each
    row (``across_rows`` 0) or each column (1)."""
    b, row, col = wp.tid()
    total = float(0.0)
    norm = float(0.0)
    for k in range(-radius, radius + 1):
        weight = wp.exp(-0.5 * float(k * k) / (sigma * sigma))
        norm += weight
        r = row + k * across_rows
        c = col + k * (1 - across_rows)
        if r >= 0 and r < images.shape[1] and c >= 0 and c < images.shape[2]:
            total += weight * images[b, r, c]
    out[b, row, col] = total / norm


@wp.func
def _sample(images: wp.array3d(dtype=float), b: int, point: wp.vec2, height: float) -> float:
    # nearest pixel of a point in image heights; 0 outside the image
    col = int(wp.floor(point[0] * height))
    row = int(wp.floor(point[1] * height))
    if row < 0 or col < 0 or row >= images.shape[1] or col >= images.shape[2]:
        return 0.0
    return images[b, row, col]


@wp.func
def _lies_on(mean: wp.array2d(dtype=wp.vec2), peak: wp.array2d(dtype=float), members: wp.array2d(dtype=wp.int32),
             first: int, count: int, targets: wp.array3d(dtype=float), b: int, offset: wp.vec2) -> float:
    # the component's peaks times the target at its moved centres
    height = float(targets.shape[1])
    score = float(0.0)
    for k in range(count):
        p = members[b, first + k]
        score += peak[b, p] * _sample(targets, b, mean[b, p] + offset, height)
    return score


@wp.func
def _prior(offset: wp.vec2, heading: wp.vec2, width: float, side_width: float) -> float:
    # Gaussian in the offset's length; where the edge has a heading (a unit vector), narrower across it
    if wp.length(heading) > 0.0:
        along = wp.dot(offset, heading)
        across = wp.dot(offset, offset) - along * along
        return wp.exp(-0.5 * (along * along / (width * width) + across / (side_width * side_width)))
    return wp.exp(-0.5 * wp.dot(offset, offset) / (width * width))


@wp.kernel(enable_backward=False)
def search_translations(
    mean: wp.array2d(dtype=wp.vec2),
    peak: wp.array2d(dtype=float),
    members: wp.array2d(dtype=wp.int32),
    starts: wp.array2d(dtype=wp.int32),
    counts: wp.array2d(dtype=wp.int32),
    targets: wp.array3d(dtype=float),
    offsets: wp.array(dtype=wp.vec2),
    heading: wp.array(dtype=wp.vec2),
    prior_width: float,
    side_width: float,
    gain: float,
    margin: float,
    exclusion: float,
    motion: wp.array2d(dtype=wp.vec3),
):
    """motion[b, c] = (t_x, t_y, 0) of component c's best offset where it beats staying by ``gain`` and
    every offset further than ``exclusion`` from it by ``margin``; ``members[b, starts[b, c] + k]`` for k <
    ``counts[b, c]`` are its slots, ``peak`` each slot's weight x amplitude^2."""
    b, c = wp.tid()
    count = counts[b, c]
    if count == 0:
        return
    first = starts[b, c]
    stay = _lies_on(mean, peak, members, first, count, targets, b, wp.vec2(0.0, 0.0))
    best = float(0.0)
    best_k = int(-1)
    for k in range(offsets.shape[0]):
        score = _lies_on(mean, peak, members, first, count, targets, b, offsets[k])
        score *= _prior(offsets[k], heading[b], prior_width, side_width)
        if score > best:
            best = score
            best_k = k
    if best_k < 0 or best <= gain * stay:
        return
    # unambiguous: no offset away from the best (another glint, another highlight) scores near it
    found = offsets[best_k]
    rival = float(0.0)
    for k in range(offsets.shape[0]):
        if wp.length(offsets[k] - found) > exclusion:
            score = _lies_on(mean, peak, members, first, count, targets, b, offsets[k])
            rival = wp.max(rival, score * _prior(offsets[k], heading[b], prior_width, side_width))
    if best > margin * rival:
        motion[b, c] = wp.vec3(found[0], found[1], 0.0)


def component_members(labels: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B, N) int32 slots of each set ordered by component, and (B, N) int32 start and count of component c
    in that order (count 0 where c is no active slot's label)."""
    problems, capacity = labels.shape
    keyed = np.where(active, labels, capacity)  # free slots last
    members = np.argsort(keyed, axis=1, kind="stable").astype(np.int32)
    counts = np.zeros((problems, capacity + 1), np.int32)
    np.add.at(counts, (np.repeat(np.arange(problems), capacity), keyed.ravel()), 1)
    counts = counts[:, :capacity]
    starts = (np.cumsum(counts, axis=1) - counts).astype(np.int32)
    return members, starts, counts


def image_headings(directions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, 2) float32 unit image-plane directions (x right, y down, as the Gaussians' means) in which a
    highlight moves along each directed edge (source, target) of lights ``directions`` ((n, 3): x right,
    y up, z to the camera): the change of the half-vector h = (l + v) / |l + v| for a camera along +z,
    projected on the image. A highlight sits where the surface's normal is h, so on a convex surface it
    moves with h (on a concave one against it: the prior is symmetric). Zero where h barely changes."""
    image = half_vector_changes(directions, edges)
    length = np.linalg.norm(image, axis=1, keepdims=True)
    return np.where(length > 1e-6, image / np.maximum(length, 1e-12), 0.0).astype(np.float32)


def half_vector_changes(directions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, 2) float64 change of the half-vector h = (l + v) / |l + v| (camera along +z) along each directed edge
    (source, target) of lights ``directions`` ((n, 3): x right, y up, z to the camera), on the image plane (x
    right, y down, as the Gaussians' means)."""
    directions = np.asarray(directions, dtype=np.float64)
    half = directions + np.array([0.0, 0.0, 1.0])
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
    edges = np.asarray(edges, dtype=np.int64)
    change = half[edges[:, 1]] - half[edges[:, 0]]
    return np.stack([change[:, 0], -change[:, 1]], axis=1)


def candidate_offsets(radius: float, step: float) -> np.ndarray:
    """(K, 2) float32 offsets of a square grid of ``step`` inside the disc of ``radius`` (image heights),
    the zero offset first."""
    count = int(math.floor(radius / step))
    axis = np.arange(-count, count + 1) * step
    x, y = np.meshgrid(axis, axis, indexing="xy")
    grid = np.stack([x.ravel(), y.ravel()], axis=1)
    grid = grid[np.hypot(grid[:, 0], grid[:, 1]) <= radius + 1e-12]
    order = np.argsort(np.hypot(grid[:, 0], grid[:, 1]), kind="stable")
    return np.ascontiguousarray(grid[order], dtype=np.float32)


def search_blur_px(step: float, height: int) -> float:
    """The targets' blur, pixels: one grid step (``step`` image heights) of an image ``height`` pixels high."""
    return max(step * height, 0.5)


def blurred(images: wp.array, sigma_px: float) -> wp.array:
    """(B, H, W) ``images`` blurred by a Gaussian of ``sigma_px`` pixels (two launches; a new array)."""
    radius = max(1, int(math.ceil(3.0 * sigma_px)))
    across = wp.empty_like(images)
    out = wp.empty_like(images)
    wp.launch(blur_along, dim=images.shape, inputs=[images, float(sigma_px), radius, 0], outputs=[across],
              device=images.device)
    wp.launch(blur_along, dim=images.shape, inputs=[across, float(sigma_px), radius, 1], outputs=[out],
              device=images.device)
    return out


def searched_translations(source: GaussianBatch, params: GaussianParams, labels: np.ndarray, targets: wp.array,
                          motion: wp.array, *,
                          radius: float, step: float, prior_width: float, gain: float, margin: float,
                          exclusion: float, headings: np.ndarray | None = None, side_width: float = 1.0) -> None:
    """Write into ``motion`` ((B, N) vec3, zeros) each component's searched start (``search_translations``).

    Args:
        source: the edges' source sets on the device, ``params`` the same on the host; labels: (B, N) component
            of each slot.
        targets: (B, H, W) each edge's target specular luminance blurred by ``step`` (``blurred`` of the
            lights' images, ``search_blur_px``, then gathered per edge: each light's image is blurred once).
        radius, step, prior_width: the disc of offsets, its grid step and the prior's width, in image
            heights.
        headings: (B, 2) the way each edge's highlights are expected to go in the image (unit vectors,
            ``image_headings``; zero: no expectation), across which the prior is ``side_width`` wide.
        gain, margin: how much better than staying, and than any offset further than ``exclusion``
            (image heights) from it, an offset must score to be taken.
    """
    if radius <= 0.0 or source.problem_count == 0:
        return
    device = source.device
    offsets = wp.array(candidate_offsets(radius, step), dtype=wp.vec2, device=device)
    if headings is None:
        headings = np.zeros((source.problem_count, 2), np.float32)
    heading = wp.array(np.ascontiguousarray(headings, dtype=np.float32), dtype=wp.vec2, device=device)
    peak = wp.array((params.weight * params.amplitude**2).astype(np.float32), dtype=float, device=device)
    members, starts, counts = (wp.array(a, dtype=wp.int32, device=device)
                               for a in component_members(np.asarray(labels), params.active))
    wp.launch(search_translations, dim=source.shape,
              inputs=[source.mean, peak, members, starts, counts, targets, offsets, heading,
                      float(prior_width), float(side_width), float(gain), float(margin), float(exclusion)],
              outputs=[motion], device=device)
