"""Kernels of relighting (docs/method.md, Relighting): locate queries, interpolate Gaussian sets, compose images.

The kernels that turn Q query directions into Q images, whatever Q is (the rasterizer draws S'
between steps 2 and 3):

1. ``deepest_faces`` (query x slice of the faces) then ``locate_directions`` (one thread per query,
   float64): the face of the triangulation the query's ray crosses and its planar barycentric
   weights; on a dome, a query outside the covered region is first moved to the nearest point of the
   boundary (the same rules as ``SphericalTriangulation.locate``). The faces are searched by
   ``FACE_SLICES`` threads per query: one thread looping over the 496 faces of 250 lights took most
   of a single query's device time.
2. ``interpolate_gaussians`` (query x corner x slot): the interpolated set G' of every query, 3N slots
   (corner k's moved set in slots k N .. k N + N - 1), ready for the rasterizer.
3. ``compose_images`` (query x pixel, or query x row on the CPU): I' = scale max(B' + c(x) S', 0) with B' the residual
   (residual transfer: a barycentric blend of the per-light residual images, or the low-rank
   residual from per-query weights that ``blend_images`` blends, or ``blend_rbf`` with radial basis
   weights over every light), the Lambertian model, a blend of per-light images, or nothing;
   ``blend_images`` is the alpha-blend baseline of a per-light stack.

A low-rank residual reaches the device as its codes: ``dequantise_basis`` makes the pixel-major
float32 basis that ``compose_images`` reads, and ``decode_low_rank`` decodes every captured light's
residual image from it once (the images a query then blends).

None of these is differentiated: relighting only renders.
"""

# ruff: noqa: UP018, RUF046  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

from typing import Any

import warp as wp

from warp_highlights.model.gaussians import GaussianArrays
from warp_highlights.model.residual import FLOAT16_SAFE, LUMINANCE_WEIGHTS

from .retarget import rotate_vec2

__all__ = [
    "DIFFUSE_BLEND",
    "DIFFUSE_LAMBERT",
    "DIFFUSE_NONE",
    "arc_position",
    "DIFFUSE_LOWRANK",
    "DIFFUSE_DECODED",
    "blend_images",
    "compose_images",
    "decode_low_rank",
    "deepest_faces",
    "dequantise_basis",
    "FACE_SLICES",
    "interpolate_gaussians",
    "locate_directions",
]

DIFFUSE_NONE = 0
"""``compose_images`` mode: no diffuse term."""
DIFFUSE_LAMBERT = 1
"""``compose_images`` mode: D' = max(nbar . omega, 0) + k_a per pixel and channel."""
DIFFUSE_BLEND = 2
"""``compose_images`` mode: D' = barycentric blend of the three corner lights' images."""
DIFFUSE_LOWRANK = 3
"""``compose_images`` mode: the low-rank residual (luminance, and chroma for colour)."""
DIFFUSE_DECODED = 4
"""``compose_images`` mode: a residual already decoded per query (the learned residual), ``diffuse_images[q]``."""

# luminance weights of the opponent colour split, for the chroma decode
_WR = wp.constant(LUMINANCE_WEIGHTS[0])
_WG = wp.constant(LUMINANCE_WEIGHTS[1])
_WB = wp.constant(LUMINANCE_WEIGHTS[2])
# decoded images are clipped to this, as ``residual.decode.decoded_images`` clips them
_FLOAT16_SAFE = wp.constant(FLOAT16_SAFE)


@wp.func
def arc_position(mean_a: wp.vec2, mean_b: wp.vec2, delta: float, fraction: float, straight_below: float) -> wp.vec2:
    """The point ``fraction`` of the way along the arc that carries mean_a to mean_b turning by delta.

    Chord form of R(f delta)(mean_a - O) + O (no centre needed, exact for any radius):
    mean_a + sin(f delta / 2) / sin(delta / 2) R((f - 1) delta / 2)(mean_b - mean_a); the straight
    blend when |delta| < straight_below. Matches ``warp_highlights.model.arcs.circular_position``.
    """
    chord = mean_b - mean_a
    sin_half = wp.sin(0.5 * delta)
    if wp.abs(delta) < straight_below or sin_half == 0.0:
        return mean_a + fraction * chord
    return mean_a + (wp.sin(0.5 * fraction * delta) / sin_half) * rotate_vec2(chord, 0.5 * (fraction - 1.0) * delta)


FACE_SLICES = 32
"""Threads that search the faces for one query (``deepest_faces``): each reads every 32nd face."""


@wp.kernel(enable_backward=False)
def deepest_faces(
    queries: wp.array(dtype=wp.vec3d),
    edge_normals: wp.array2d(dtype=wp.vec3d),
    depths: wp.array2d(dtype=wp.float64),
    best_faces: wp.array2d(dtype=wp.int32),
):
    """For query q and slice s (faces s, s + S, s + 2 S, ... with S = ``depths.shape[1]``): the largest
    smallest edge-plane margin of the query over the slice's faces and the first face with it (-2 and
    face -1 for an empty slice)."""
    q, s = wp.tid()
    query = queries[q]
    best = int(-1)
    depth = wp.float64(-2.0)
    for f in range(s, edge_normals.shape[0], depths.shape[1]):
        margin = wp.min(wp.min(wp.dot(query, edge_normals[f, 0]), wp.dot(query, edge_normals[f, 1])),
                        wp.dot(query, edge_normals[f, 2]))
        if margin > depth:
            depth = margin
            best = f
    depths[q, s] = depth
    best_faces[q, s] = best


@wp.kernel(enable_backward=False)
def locate_directions(
    queries: wp.array(dtype=wp.vec3d),
    depths: wp.array2d(dtype=wp.float64),
    best_faces: wp.array2d(dtype=wp.int32),
    inverses: wp.array(dtype=wp.mat33d),
    rim_start: wp.array(dtype=wp.vec3d),
    rim_end: wp.array(dtype=wp.vec3d),
    rim_normal: wp.array(dtype=wp.vec3d),
    rim_along: wp.array(dtype=wp.vec3d),
    rim_back: wp.array(dtype=wp.vec3d),
    rim_face: wp.array(dtype=wp.int32),
    rim_opposite: wp.array(dtype=wp.int32),
    is_dome: int,
    inside_tolerance: wp.float64,
    faces: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec3),
    located: wp.array(dtype=wp.vec3),
    clamped: wp.array(dtype=wp.int32),
):
    """Face and barycentric weights of each unit query (float64 geometry, float32 results).

    The face is the one the query lies deepest inside (largest smallest edge-plane margin, first on
    ties), from the slices' best of ``deepest_faces``. On a dome, a query more than
    ``inside_tolerance`` outside every face moves to the nearest point of the rim arcs (``rim_*``: per
    boundary edge its ends, great-circle normal, the in-plane directions along the arc at its start
    and back at its end, its face and that face's opposite corner, whose weight is then 0).
    """
    q = wp.tid()
    query = queries[q]
    best = int(0)
    depth = wp.float64(-2.0)
    for s in range(depths.shape[1]):
        face = best_faces[q, s]
        if face >= 0 and (depths[q, s] > depth or (depths[q, s] == depth and face < best)):
            depth = depths[q, s]
            best = face
    point = query
    opposite = int(-1)
    outside = is_dome != 0 and depth < -inside_tolerance
    if outside:
        edge = int(0)
        closest = wp.float64(-3.0)
        for e in range(rim_face.shape[0]):
            off_plane = wp.dot(query, rim_normal[e])
            foot = wp.sqrt(wp.max(wp.float64(1.0) - off_plane * off_plane, wp.float64(0.0)))
            over_arc = (wp.dot(query, rim_along[e]) >= wp.float64(0.0) and wp.dot(query, rim_back[e]) >= wp.float64(0.0)
                        and foot > wp.float64(1.0e-12))
            closeness = wp.max(wp.dot(query, rim_start[e]), wp.dot(query, rim_end[e]))
            if over_arc:
                closeness = foot
            if closeness > closest:
                closest = closeness
                edge = e
        off_plane = wp.dot(query, rim_normal[edge])
        foot = wp.sqrt(wp.max(wp.float64(1.0) - off_plane * off_plane, wp.float64(0.0)))
        if (wp.dot(query, rim_along[edge]) >= wp.float64(0.0) and wp.dot(query, rim_back[edge]) >= wp.float64(0.0)
            and foot > wp.float64(1.0e-12)):
            inner = query - off_plane * rim_normal[edge]
            point = inner / wp.max(wp.length(inner), wp.float64(1.0e-300))
        elif wp.dot(query, rim_start[edge]) >= wp.dot(query, rim_end[edge]):
            point = rim_start[edge]
        else:
            point = rim_end[edge]
        best = rim_face[edge]
        opposite = rim_opposite[edge]
    w = inverses[best] @ point
    total = wp.float64(0.0)
    for k in range(3):
        if k == opposite or w[k] < wp.float64(0.0):
            w[k] = wp.float64(0.0)
        total += w[k]
    faces[q] = best
    weights[q] = wp.vec3(float(w[0] / total), float(w[1] / total), float(w[2] / total))
    located[q] = wp.vec3(float(point[0]), float(point[1]), float(point[2]))
    clamped[q] = int(outside)


@wp.kernel(enable_backward=False)
def interpolate_gaussians(
    estimated: GaussianArrays,
    retargeted: GaussianArrays,
    path_delta: wp.array2d(dtype=float),
    moving: wp.array2d(dtype=wp.int32),
    face_vertices: wp.array2d(dtype=wp.int32),
    face_edges: wp.array3d(dtype=wp.int32),
    faces: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec3),
    circular: int,
    straight_below: float,
    out: GaussianArrays,
):
    """out[q, k N + p] = slot p of corner k's set moved to query q (docs/method.md, Relighting).

    For corner A = face_vertices[f, k] with weights (lA, lB, lC) rotated so lA is corner k's:
    |a'| = lA |a_A| + lB |a_AB| + lC |a_AC| (likewise |sigma|), theta' = theta_A + lB delta_AB + lC delta_AC,
    mu' = arc(A->B, lB) + arc(A->C, lC) - mu_A (circular) or the barycentric blend (straight); the
    slot's weight is lA. A slot with lA = 0 is left inactive: it would draw nothing. A Gaussian that
    does not move (``moving[A, p]`` = 0, decided at fit time) stays where it is in G_A with weight lA:
    it blends in place, like the alpha baseline.
    ``face_edges[f, k]`` holds the rows of the directed edges A->B and A->C; ``path_delta`` is in
    radians, means and sizes in image heights.
    """
    q, k, p = wp.tid()
    slot = k * estimated.active.shape[1] + p
    f = faces[q]
    a = face_vertices[f, k]
    w = weights[q]
    la = w[k]
    lb = w[(k + 1) % 3]
    lc = w[(k + 2) % 3]
    if estimated.active[a, p] == 0 or la <= 0.0:
        out.active[q, slot] = 0
        out.amplitude[q, slot] = 0.0
        out.mean[q, slot] = wp.vec2(0.0, 0.0)
        out.sigma[q, slot] = wp.vec2(0.0, 0.0)
        out.theta[q, slot] = 0.0
        out.weight[q, slot] = 1.0
        return
    if moving[a, p] == 0:
        out.active[q, slot] = 1
        out.amplitude[q, slot] = wp.abs(estimated.amplitude[a, p])
        out.mean[q, slot] = estimated.mean[a, p]
        out.sigma[q, slot] = wp.vec2(wp.abs(estimated.sigma[a, p][0]), wp.abs(estimated.sigma[a, p][1]))
        out.theta[q, slot] = estimated.theta[a, p]
        out.weight[q, slot] = la
        return
    to_b = face_edges[f, k, 0]
    to_c = face_edges[f, k, 1]
    delta_b = path_delta[to_b, p]
    delta_c = path_delta[to_c, p]
    mean_a = estimated.mean[a, p]
    mean_b = retargeted.mean[to_b, p]
    mean_c = retargeted.mean[to_c, p]
    mean = la * mean_a + lb * mean_b + lc * mean_c
    if circular != 0:
        mean = (arc_position(mean_a, mean_b, delta_b, lb, straight_below)
                + arc_position(mean_a, mean_c, delta_c, lc, straight_below) - mean_a)
    sa = estimated.sigma[a, p]
    sb = retargeted.sigma[to_b, p]
    sc = retargeted.sigma[to_c, p]
    out.active[q, slot] = 1
    # only a^2 is drawn and fitting may flip a's sign: blend |a|, or a highlight would fade through 0
    out.amplitude[q, slot] = (la * wp.abs(estimated.amplitude[a, p]) + lb * wp.abs(retargeted.amplitude[to_b, p])
                              + lc * wp.abs(retargeted.amplitude[to_c, p]))
    out.mean[q, slot] = mean
    out.sigma[q, slot] = wp.vec2(
        la * wp.abs(sa[0]) + lb * wp.abs(sb[0]) + lc * wp.abs(sc[0]),
        la * wp.abs(sa[1]) + lb * wp.abs(sb[1]) + lc * wp.abs(sc[1]),
    )
    out.theta[q, slot] = estimated.theta[a, p] + lb * delta_b + lc * delta_c
    out.weight[q, slot] = la


@wp.kernel(enable_backward=False)
def blend_images(
    stack: wp.array2d(dtype=float),
    face_vertices: wp.array2d(dtype=wp.int32),
    faces: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec3),
    out: wp.array2d(dtype=float),
):
    """out[q, i] = sum_k weights[q][k] stack[corner k of q's face, i]: the alpha blend of flattened images
    (or of any per-light rows, such as a low-rank residual's weights)."""
    q, i = wp.tid()
    f = faces[q]
    w = weights[q]
    out[q, i] = (w[0] * stack[face_vertices[f, 0], i] + w[1] * stack[face_vertices[f, 1], i]
                 + w[2] * stack[face_vertices[f, 2], i])


@wp.kernel(enable_backward=False)
def blend_rbf(
    rows: wp.array2d(dtype=wp.float64),
    lights: wp.array(dtype=wp.vec3d),
    inverse_sigma_squared: wp.float64,
    located: wp.array(dtype=wp.vec3),
    out: wp.array2d(dtype=float),
):
    """out[q, i] = sum_j exp(-|w_q - l_j|^2 / sigma^2) rows[j, i], in float64: a radial basis blend of per-light
    rows already multiplied by (K + lambda I)^-1 (``model.rbf``; a low-rank residual's weights), at the
    located query directions w_q (on a dome's rim where a query lies outside)."""
    q, i = wp.tid()
    w = located[q]
    d = wp.vec3d(wp.float64(w[0]), wp.float64(w[1]), wp.float64(w[2]))
    total = wp.float64(0.0)
    for j in range(lights.shape[0]):
        r = d - lights[j]
        total += wp.exp(-wp.dot(r, r) * inverse_sigma_squared) * rows[j, i]
    out[q, i] = float(total)


@wp.func
def _low_rank(mean: wp.array2d(dtype=float), basis: wp.array3d(dtype=float), coefficients: wp.array2d(dtype=float),
              q: int, i: int, plane: int) -> float:
    # coefficients[q] = (basis weights..., mean weight): the query's blend of the per-light rows
    # basis is pixel-major, (pixels, k, planes): one pixel's basis values are contiguous
    rank = coefficients.shape[1] - 1
    value = coefficients[q, rank] * mean[i, plane]
    for j in range(rank):
        value += coefficients[q, j] * basis[i, j, plane]
    return value


@wp.func
def _low_rank_opponent(luminance_mean: wp.array2d(dtype=float), luminance_basis: wp.array3d(dtype=float),
                       luminance_weights: wp.array2d(dtype=float),
                       chroma_mean: wp.array2d(dtype=float), chroma_basis: wp.array3d(dtype=float),
                       chroma_weights: wp.array2d(dtype=float),
                       residual_scale: wp.array(dtype=float), q: int, i: int, channels: int) -> wp.vec3:
    # (Y, B - Y, R - Y) of the low-rank residual at pixel i for coefficient row q, times the residual scale; chroma 0
    # for grey
    s = residual_scale[0]
    if residual_scale.shape[0] > 1:
        s = residual_scale[i]
    y = s * _low_rank(luminance_mean, luminance_basis, luminance_weights, q, i, 0)
    cb = float(0.0)
    cr = float(0.0)
    if channels == 3:
        cb = s * _low_rank(chroma_mean, chroma_basis, chroma_weights, q, i, 0)
        cr = s * _low_rank(chroma_mean, chroma_basis, chroma_weights, q, i, 1)
    return wp.vec3(y, cb, cr)


@wp.func
def _opponent_channel(opponent: wp.vec3, c: int, channels: int) -> float:
    # channel c of the colour (Y, B - Y, R - Y) splits into (``model.residual.from_opponent``); Y alone for grey
    y = opponent[0]
    if channels != 3:
        return y
    if c == 0:
        return y + opponent[2]
    if c == 1:
        return y - (_WR * opponent[2] + _WB * opponent[1]) / _WG
    return y + opponent[1]


@wp.kernel(enable_backward=False)
def compose_images(
    specular: wp.array2d(dtype=float),
    specular_colour: wp.vec3,
    pixel_colour: wp.array2d(dtype=float),
    add_specular: int,
    diffuse_mode: int,
    lambert: wp.array2d(dtype=wp.vec4),
    diffuse_images: wp.array3d(dtype=wp.float16),
    luminance_mean: wp.array2d(dtype=float),
    luminance_basis: wp.array3d(dtype=float),
    luminance_weights: wp.array2d(dtype=float),
    chroma_mean: wp.array2d(dtype=float),
    chroma_basis: wp.array3d(dtype=float),
    chroma_weights: wp.array2d(dtype=float),
    residual_scale: wp.array(dtype=float),
    face_vertices: wp.array2d(dtype=wp.int32),
    faces: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    scale: float,
    pixels_per_thread: int,
    out: wp.array3d(dtype=float),
):
    """out[q, i, c] = scale max(B'[q, i, c] + colour[c] c_i[c] S'[q, i], 0) for pixel i and channel c;
    thread (q, t) does pixels t p .. t p + p - 1 (p = ``pixels_per_thread``: 1 on CUDA, a row's worth on
    the CPU, where each thread's start costs about as much as a pixel).

    B' per ``diffuse_mode``: ``DIFFUSE_NONE`` 0; ``DIFFUSE_LAMBERT`` max(nbar . omega_q, 0) + k_a from
    ``lambert[i, c]`` = (nbar_x, nbar_y, nbar_z, k_a); ``DIFFUSE_BLEND`` the barycentric blend of
    ``diffuse_images[light, i, c]`` (the residual images, or diffuse images); ``DIFFUSE_LOWRANK`` the
    low-rank residual: luminance Y = m mean + sum_j coefficient_j basis_j (m and the coefficients:
    the query's blend of the per-light weights, ``luminance_weights[q]`` = (coefficients..., m)), chroma (B - Y, R - Y)
    likewise when there are three channels, both times ``residual_scale[i]`` (one entry: 1 everywhere);
    ``DIFFUSE_DECODED`` ``diffuse_images[q, i, c]``. S' is added only when ``add_specular`` is set; c_i is
    ``pixel_colour[i]`` (row 0 when it has one row).
    """
    q, t = wp.tid()
    f = faces[q]
    w = weights[q]
    omega = directions[q]
    corner0 = face_vertices[f, 0]
    corner1 = face_vertices[f, 1]
    corner2 = face_vertices[f, 2]
    channels = out.shape[2]
    one_colour = pixel_colour.shape[0] == 1
    first = t * pixels_per_thread
    for i in range(first, wp.min(first + pixels_per_thread, out.shape[1])):
        value = float(0.0)
        row = i
        if one_colour:
            row = 0
        opponent = wp.vec3(0.0)
        if diffuse_mode == DIFFUSE_LOWRANK:
            opponent = _low_rank_opponent(luminance_mean, luminance_basis, luminance_weights, chroma_mean, chroma_basis,
                                          chroma_weights,
                                          residual_scale, q, i, channels)
        for c in range(channels):
            value = 0.0
            if diffuse_mode == DIFFUSE_LAMBERT:
                m = lambert[i, c]
                value = wp.max(m[0] * omega[0] + m[1] * omega[1] + m[2] * omega[2], 0.0) + m[3]
            elif diffuse_mode == DIFFUSE_BLEND:
                value = (w[0] * float(diffuse_images[corner0, i, c]) + w[1] * float(diffuse_images[corner1, i, c])
                         + w[2] * float(diffuse_images[corner2, i, c]))
            elif diffuse_mode == DIFFUSE_DECODED:
                value = float(diffuse_images[q, i, c])
            elif diffuse_mode == DIFFUSE_LOWRANK:
                value = _opponent_channel(opponent, c, channels)
            if add_specular != 0:
                value += specular_colour[c] * pixel_colour[row, c] * specular[q, i]
            out[q, i, c] = scale * wp.max(value, 0.0)


@wp.kernel(enable_backward=False)
def dequantise_basis(codes: wp.array3d(dtype=Any), low: wp.array(dtype=float), step: wp.array(dtype=float),
                     basis: wp.array3d(dtype=float)):
    """basis[i, j, p] = low[j] + codes[j, i, p] step[j]: basis image j's (pixels, planes) codes (uint8 or
    uint16) as float32 values, pixel-major (``compose_images``' layout), as ``residual.decode.stack_basis`` decodes
    them."""
    j, i = wp.tid()
    for p in range(codes.shape[2]):
        basis[i, j, p] = low[j] + float(codes[j, i, p]) * step[j]


@wp.kernel(enable_backward=False)
def decode_low_rank(
    luminance_mean: wp.array2d(dtype=float),
    luminance_basis: wp.array3d(dtype=float),
    luminance_weights: wp.array2d(dtype=float),
    chroma_mean: wp.array2d(dtype=float),
    chroma_basis: wp.array3d(dtype=float),
    chroma_weights: wp.array2d(dtype=float),
    residual_scale: wp.array(dtype=float),
    out: wp.array3d(dtype=wp.float16),
):
    """out[l, i, c] = light l's residual image at pixel i and channel c: the low-rank luminance (and chroma
    for colour) from the light's own weights (``compose_images``' ``DIFFUSE_LOWRANK`` without the blend,
    the clamp at 0 or the exposure), times ``residual_scale``, clipped to float16's range: what
    ``residual.decode.decoded_images`` gives."""
    light, i = wp.tid()
    channels = out.shape[2]
    opponent = _low_rank_opponent(luminance_mean, luminance_basis, luminance_weights, chroma_mean, chroma_basis,
                                  chroma_weights, residual_scale,
                                  light, i, channels)
    for c in range(channels):
        out[light, i, c] = wp.float16(wp.clamp(_opponent_channel(opponent, c, channels), -_FLOAT16_SAFE, _FLOAT16_SAFE))
