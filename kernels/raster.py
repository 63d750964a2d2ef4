"""Differentiable rasterizer of batched 2D Gaussian sets (docs/method.md, Building blocks).

One image per problem, all of the same size, in coordinates normalised by the image height: pixel
(col, row) samples the point ((col + 0.5) / H, (row + 0.5) / H). A Gaussian with amplitude a, mean mu,
sizes sigma and rotation theta contributes, where its Mahalanobis distance d is below the cut-off c,

    w a^2 (exp(-d^2 / 2) - tau) / (1 - tau),    tau = exp(-c^2 / 2),

and nothing elsewhere: the cut-off level is subtracted so the value reaches zero continuously at the
cut-off ellipse (a hard cut would make the image jump as a Gaussian moves).

Forward, three launches:

1. ``prepare_gaussians`` (problem x slot): principal frame (rotation, inverse variances), scaled
   amplitude, pixel bounding box.
2. ``bin_tiles`` (problem x tile): the list of Gaussians whose cut-off ellipse reaches the tile's
   pixel centres (exact ellipse/rectangle test), in slot order so sums are deterministic.
3. ``rasterize_tiles`` (tile-major 1D launch; one thread per pixel on CUDA, per tile on the CPU): each
   pixel sums its tile's list. ``render(drawn_only=True)`` draws only the tiles whose list is not
   empty (``bin_tiles`` lists them; on CUDA ``rasterize_drawn_tiles``, a fixed grid of threads over
   that list) and leaves the other pixels as they were: what a fitting step needs, since its adjoint
   reads the image only inside the Gaussians' cut-off.

Steps 1-2 build an index and stay off the tape. Step 3 is recorded on the active ``wp.Tape`` with a
hand-written adjoint, ``rasterize_backward``: Gaussian-major, one thread per (problem, slot, lane),
lanes striding over the columns of the Gaussian's footprint and, per column, over the rows inside the
ellipse. Each thread sums its pixels' contributions to six image moments in registers and adds seven
numbers to the parameter gradients at the end, so no pixel-level atomics pile onto a parameter.
Forward and backward apply the same per-pixel test d^2 < c^2, computed the same way.
``LogL1Loss.of_render`` records render and fit loss as one step: the adjoint then computes the loss's
image gradient at each pixel it visits instead of reading a stored image gradient.

This module holds one thing: the Gaussian rasterizer, forward and backward.
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

import warp as wp

from warp_highlights.model.config import RasterSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianArrays, GaussianBatch

from .chunks import map_chunks, problem_chunks
from .losses import log_l1_factor, log_l1_gradient
from .tape import active_tape

__all__ = [
    "LAUNCH_PIXELS",
    "Rasterizer",
    "bin_tiles",
    "ellipse_reaches_rectangle",
    "frame_conic",
    "frame_distance2",
    "gaussian_frame",
    "prepare_gaussians",
    "problems_per_launch",
    "rasterize_backward",
    "rasterize_drawn_tiles",
    "rasterize_tiles",
]

LAUNCH_PIXELS = 2**31
"""Pixels one launch may index: Warp's launch dimensions and the kernels' flat pixel indices are 32-bit."""

_BOX_MARGIN = 1  # pixels added around computed ranges; the per-pixel test decides membership

THREADED_TILES = 1024
"""Fewest tiles a CPU ``render`` splits over its ``threads`` (a thread's start costs about a small tile list's
drawing; 1024 tiles of 16 x 16 pixels are a 512 x 512 image)."""
PARTS_PER_THREAD = 8
"""Parts a threaded CPU ``render`` splits its tiles into, per thread (highlights cover some rows of tiles only)."""
DRAWN_TILES_PER_SWEEP = 8192
"""Tiles one sweep of ``rasterize_drawn_tiles`` covers (2M threads at 16 x 16 tiles: more than an H100
holds at once, so that the sweep is not what limits it; chosen so, not swept); more listed tiles take
more sweeps of the same threads."""
_CULL_SLACK = 1.0 + 1e-5
"""``bin_tiles`` lists a Gaussian for a tile its cut-off ellipse reaches within this relative slack of
the squared cut-off: a listing never misses a pixel the per-pixel test d^2 < c^2 draws (or the adjoint
visits) for a float32 rounding of the rectangle's minimum; a tile listed by the slack alone draws
nothing of it."""


@wp.func
def gaussian_frame(sigma: wp.vec2, theta: float, eps: float) -> wp.vec4:
    """(cos theta, sin theta, 1 / (sigma_x^2 + eps), 1 / (sigma_y^2 + eps)): the Gaussian's principal frame."""
    return wp.vec4(wp.cos(theta), wp.sin(theta), 1.0 / (sigma[0] * sigma[0] + eps), 1.0 / (sigma[1] * sigma[1] + eps))


@wp.func
def frame_distance2(frame: wp.vec4, dx: float, dy: float) -> float:
    """Squared Mahalanobis distance of the offset (dx, dy): u^2 / var_x + v^2 / var_y in the principal frame.

    Evaluated in the rotated frame rather than as A dx^2 + 2 B dx dy + C dy^2, which loses most of
    float32's digits to cancellation for needle-like Gaussians.
    """
    u = frame[0] * dx + frame[1] * dy
    v = frame[0] * dy - frame[1] * dx
    return u * u * frame[2] + v * v * frame[3]


@wp.func
def frame_conic(frame: wp.vec4) -> wp.vec3:
    """Inverse covariance (A, B, C) with d^2 = A dx^2 + 2 B dx dy + C dy^2."""
    c = frame[0]
    s = frame[1]
    return wp.vec3(c * c * frame[2] + s * s * frame[3], c * s * (frame[2] - frame[3]),
                   s * s * frame[2] + c * c * frame[3])


@wp.func
def pixel_range(lo: float, hi: float, height: float, count: int) -> wp.vec2i:
    """Pixels whose centres (i + 0.5) / height may lie in [lo, hi] (with a margin), clamped to [0, count)."""
    first = wp.clamp(wp.floor(lo * height - 0.5), -1.0, float(count)) - float(_BOX_MARGIN)
    last = wp.clamp(wp.ceil(hi * height - 0.5), -1.0, float(count)) + float(_BOX_MARGIN)
    return wp.vec2i(wp.max(int(first), 0), wp.min(int(last), count - 1))


@wp.func
def _edge_minimum(frame: wp.vec4, along_x: bool, fixed: float, lo: float, hi: float) -> float:
    # min of d^2 along the rectangle edge {other coordinate = fixed, this one in [lo, hi]}:
    # the minimiser comes from the conic, the value from the stable principal-frame form
    conic = frame_conic(frame)
    d2 = float(0.0)
    if along_x:
        t = wp.clamp(-conic[1] * fixed / conic[0], lo, hi)
        d2 = frame_distance2(frame, t, fixed)
    else:
        t = wp.clamp(-conic[1] * fixed / conic[2], lo, hi)
        d2 = frame_distance2(frame, fixed, t)
    return d2


@wp.func
def ellipse_reaches_rectangle(frame: wp.vec4, mean: wp.vec2, lo: wp.vec2, hi: wp.vec2, limit2: float) -> bool:
    """Whether some point of the rectangle [lo, hi] has squared Mahalanobis distance <= ``limit2``.

    d^2 is convex, so off the mean its minimum over the rectangle lies on an edge.
    """
    x0 = lo[0] - mean[0]
    x1 = hi[0] - mean[0]
    y0 = lo[1] - mean[1]
    y1 = hi[1] - mean[1]
    if x0 <= 0.0 and x1 >= 0.0 and y0 <= 0.0 and y1 >= 0.0:
        return True
    best = _edge_minimum(frame, False, x0, y0, y1)
    best = wp.min(best, _edge_minimum(frame, False, x1, y0, y1))
    best = wp.min(best, _edge_minimum(frame, True, y0, x0, x1))
    best = wp.min(best, _edge_minimum(frame, True, y1, x0, x1))
    return best <= limit2


@wp.func
def slot_is_drawn(g: GaussianArrays, b: int, n: int, peak_scale: float) -> bool:
    """Whether slot (b, n) takes part: active, all parameters finite, and w a^2 / (1 - tau) finite.

    The forward and the backward skip exactly the same slots (broken ones are left for pruning).
    """
    a = g.amplitude[b, n]
    finite = (wp.isfinite(a) and wp.isfinite(g.weight[b, n]) and wp.isfinite(g.mean[b, n])
              and wp.isfinite(g.sigma[b, n]) and wp.isfinite(g.theta[b, n]))
    return g.active[b, n] != 0 and finite and wp.isfinite(g.weight[b, n] * a * a * peak_scale)


@wp.kernel(enable_backward=False)
def prepare_gaussians(
    g: GaussianArrays,
    eps: float,
    cutoff: float,
    peak_scale: float,
    height: int,
    width: int,
    frames: wp.array2d(dtype=wp.vec4),
    scales: wp.array2d(dtype=float),
    boxes: wp.array2d(dtype=wp.vec4i),
):
    """Per Gaussian: principal frame, w a^2 / (1 - tau) (0 when free), and pixel box (c0, r0, c1, r1), empty
    when off-image or not drawn. A drawn slot of scale 0 (weight 0) keeps its box: the adjoint walks
    its footprint (its weight's gradient), so ``bin_tiles`` lists its tiles too."""
    b, n = wp.tid()
    a = g.amplitude[b, n]
    scale = float(0.0)
    drawn = slot_is_drawn(g, b, n, peak_scale)
    if drawn:
        scale = g.weight[b, n] * a * a * peak_scale
    frames[b, n] = gaussian_frame(g.sigma[b, n], g.theta[b, n], eps)
    scales[b, n] = scale
    if not drawn:
        boxes[b, n] = wp.vec4i(0, 0, -1, -1)
        return
    # axis-aligned half extents of the cut-off ellipse: c * sqrt(Sigma_xx), c * sqrt(Sigma_yy)
    c = wp.cos(g.theta[b, n])
    s = wp.sin(g.theta[b, n])
    var_x = g.sigma[b, n][0] * g.sigma[b, n][0] + eps
    var_y = g.sigma[b, n][1] * g.sigma[b, n][1] + eps
    half_x = cutoff * wp.sqrt(c * c * var_x + s * s * var_y)
    half_y = cutoff * wp.sqrt(s * s * var_x + c * c * var_y)
    mu = g.mean[b, n]
    h = float(height)
    cols = pixel_range(mu[0] - half_x, mu[0] + half_x, h, width)
    rows = pixel_range(mu[1] - half_y, mu[1] + half_y, h, height)
    boxes[b, n] = wp.vec4i(cols[0], rows[0], cols[1], rows[1])


@wp.kernel(enable_backward=False)
def bin_tiles(
    frames: wp.array2d(dtype=wp.vec4),
    means: wp.array2d(dtype=wp.vec2),
    scales: wp.array2d(dtype=float),
    boxes: wp.array2d(dtype=wp.vec4i),
    tile_size: int,
    tiles_x: int,
    height: int,
    width: int,
    limit2: float,
    cull: int,
    tile_lists: wp.array3d(dtype=wp.int32),
    tile_counts: wp.array2d(dtype=wp.int32),
    drawn_tiles: wp.array(dtype=wp.int32),
    drawn_count: wp.array(dtype=wp.int32),
):
    """Per (problem, tile): the slots whose cut-off ellipse reaches a pixel centre of the tile, ascending;
    a tile with any is appended (as b x tiles + t, in any order) to ``drawn_tiles`` where that is not
    empty (it has room for every tile of the batch)."""
    b, t = wp.tid()
    tx = t % tiles_x
    ty = t // tiles_x
    c0 = tx * tile_size
    r0 = ty * tile_size
    c1 = wp.min(c0 + tile_size, width) - 1
    r1 = wp.min(r0 + tile_size, height) - 1
    h = float(height)
    lo = wp.vec2((float(c0) + 0.5) / h, (float(r0) + 0.5) / h)
    hi = wp.vec2((float(c1) + 0.5) / h, (float(r1) + 0.5) / h)
    count = int(0)  # noqa: RUF046 (a mutable Warp local)
    for n in range(scales.shape[1]):
        box = boxes[b, n]
        if scales[b, n] != 0.0 or box[2] >= box[0]:  # drawn (a slot of weight 0 too, where its box is on the image)
            keep = True
            if cull != 0:
                keep = box[0] <= c1 and box[2] >= c0 and box[1] <= r1 and box[3] >= r0
                if keep:
                    keep = ellipse_reaches_rectangle(frames[b, n], means[b, n], lo, hi, limit2)
            if keep:
                tile_lists[b, t, count] = n
                count += 1
    tile_counts[b, t] = count
    if count > 0 and drawn_tiles.shape[0] > 0:
        k = wp.atomic_add(drawn_count, 0, 1)
        if k < drawn_tiles.shape[0]:
            drawn_tiles[k] = b * tile_counts.shape[1] + t


@wp.func
def _pixel_of_tile(t: int, p: int, tile_shift: int, tiles_x: int) -> wp.vec2i:
    """(row, col) of pixel p (row-major within the tile) of tile t (row-major over the image)."""
    ty = t // tiles_x
    return wp.vec2i((ty << tile_shift) + (p >> tile_shift),
                    ((t - ty * tiles_x) << tile_shift) + (p & ((1 << tile_shift) - 1)))


@wp.func
def _tile_pixel(
    frames: wp.array2d(dtype=wp.vec4),
    means: wp.array2d(dtype=wp.vec2),
    scales: wp.array2d(dtype=float),
    tile_lists: wp.array3d(dtype=wp.int32),
    b: int,
    t: int,
    count: int,
    row: int,
    col: int,
    h: float,
    cutoff2: float,
    tau: float,
) -> float:
    """Value of pixel (row, col) of problem b: the sum over the ``count`` Gaussians listed for tile t."""
    px = (float(col) + 0.5) / h
    py = (float(row) + 0.5) / h
    value = float(0.0)
    for k in range(count):
        n = tile_lists[b, t, k]
        mu = means[b, n]
        d2 = frame_distance2(frames[b, n], px - mu[0], py - mu[1])
        if d2 < cutoff2:
            value += scales[b, n] * (wp.exp(-0.5 * d2) - tau)
    return value


@wp.kernel(enable_backward=False)
def rasterize_tiles(
    frames: wp.array2d(dtype=wp.vec4),
    means: wp.array2d(dtype=wp.vec2),
    scales: wp.array2d(dtype=float),
    boxes: wp.array2d(dtype=wp.vec4i),
    tile_lists: wp.array3d(dtype=wp.int32),
    tile_counts: wp.array2d(dtype=wp.int32),
    tile_shift: int,
    tiles_x: int,
    cutoff2: float,
    tau: float,
    whole_tile: int,
    first_tile: int,
    image: wp.array3d(dtype=float),
):
    """Per pixel: the sum of the truncated Gaussians listed for its tile.

    A 1D launch in tile-major order (problem, tile, pixel of the tile): the threads of a warp share a
    tile's list, and the index arithmetic is 32-bit shifts instead of the 64-bit divisions a 3D
    launch spends on every thread. On the CPU (``whole_tile`` = 1, or 2 to skip the tiles no Gaussian
    reaches) a thread draws a whole tile instead,
    one launch index per tile: the per-pixel index divisions would cost more than the drawing of the
    mostly empty tiles of a highlight image. That thread clears the tile, then adds the listed Gaussians
    one after the other (the same sums in the same order as a pixel's loop), each over the part of its
    pixel box inside the tile only, with its parameters loaded once; launch index k draws tile
    ``first_tile`` + k of the batch's tiles (problem-major), so that threads can share one image.
    """
    h = float(image.shape[1])
    if whole_tile == 0:
        i = wp.tid()
        tile_pixels = 1 << (2 * tile_shift)
        per_problem = tile_counts.shape[1] * tile_pixels
        b = i // per_problem
        t = (i - b * per_problem) >> (2 * tile_shift)
        at = _pixel_of_tile(t, i & (tile_pixels - 1), tile_shift, tiles_x)
        if at[0] < image.shape[1] and at[1] < image.shape[2]:
            image[b, at[0], at[1]] = _tile_pixel(frames, means, scales, tile_lists, b, t, tile_counts[b, t], at[0],
                                                 at[1], h, cutoff2, tau)
    else:
        i = wp.tid() + first_tile
        b = i // tile_counts.shape[1]
        t = i - b * tile_counts.shape[1]
        if whole_tile == 2 and tile_counts[b, t] == 0:
            return  # drawn_only: a tile no Gaussian reaches keeps its pixels
        ty = t // tiles_x
        size = 1 << tile_shift
        row0 = ty << tile_shift
        col0 = (t - ty * tiles_x) << tile_shift
        row_end = wp.min(row0 + size, image.shape[1])
        col_end = wp.min(col0 + size, image.shape[2])
        for row in range(row0, row_end):
            for col in range(col0, col_end):
                image[b, row, col] = 0.0
        for k in range(tile_counts[b, t]):
            n = tile_lists[b, t, k]
            box = boxes[b, n]
            frame = frames[b, n]
            mu = means[b, n]
            scale = scales[b, n]
            for row in range(wp.max(row0, box[1]), wp.min(row_end, box[3] + 1)):
                dy = (float(row) + 0.5) / h - mu[1]
                for col in range(wp.max(col0, box[0]), wp.min(col_end, box[2] + 1)):
                    d2 = frame_distance2(frame, (float(col) + 0.5) / h - mu[0], dy)
                    if d2 < cutoff2:
                        image[b, row, col] = image[b, row, col] + scale * (wp.exp(-0.5 * d2) - tau)


@wp.kernel(enable_backward=False)
def rasterize_drawn_tiles(
    frames: wp.array2d(dtype=wp.vec4),
    means: wp.array2d(dtype=wp.vec2),
    scales: wp.array2d(dtype=float),
    tile_lists: wp.array3d(dtype=wp.int32),
    tile_counts: wp.array2d(dtype=wp.int32),
    drawn_tiles: wp.array(dtype=wp.int32),
    drawn_count: wp.array(dtype=wp.int32),
    tile_shift: int,
    tiles_x: int,
    cutoff2: float,
    tau: float,
    launched: int,
    image: wp.array3d(dtype=float),
):
    """``rasterize_tiles`` (CUDA) over the listed tiles only: a fixed grid of threads strides over the
    ``drawn_count`` tiles of ``drawn_tiles``, one thread per pixel of a tile. Pixels of unlisted tiles
    keep what they held. The launch size (``launched``) does not depend on the count, so a captured graph replays it."""
    i = wp.tid()
    tile_pixels = 1 << (2 * tile_shift)
    p = i & (tile_pixels - 1)
    stride = launched >> (2 * tile_shift)  # ``launched`` threads: a whole number of tiles
    count = drawn_count[0]
    per_problem = tile_counts.shape[1]
    k = i >> (2 * tile_shift)
    while k < count:
        b = drawn_tiles[k] // per_problem
        t = drawn_tiles[k] - b * per_problem
        at = _pixel_of_tile(t, p, tile_shift, tiles_x)
        if at[0] < image.shape[1] and at[1] < image.shape[2]:
            image[b, at[0], at[1]] = _tile_pixel(frames, means, scales, tile_lists, b, t, tile_counts[b, t], at[0],
                                                 at[1], float(image.shape[1]), cutoff2,
                                                 tau)
        k += stride


@wp.kernel(enable_backward=False)
def rasterize_backward(
    g: GaussianArrays,
    image_grad: wp.array3d(dtype=float),
    fused: int,
    image: wp.array3d(dtype=float),
    target: wp.array3d(dtype=float),
    loss_grad: wp.array(dtype=float),
    loss_scale: float,
    eps: float,
    cutoff: float,
    tau: float,
    lanes: int,
    grad: GaussianArrays,
):
    """Adjoint of ``rasterize_tiles``: adds d(loss)/d(parameters) given d(loss)/d(image).

    With ``fused`` = 0 d(loss)/d(image) is read from ``image_grad``; with 1 it is the fit loss's
    (``losses.log_l1_gradient`` of the rendered ``image``, ``target``, the upstream ``loss_grad`` per
    problem and the loss's ``loss_scale``), computed at each pixel where it is needed.
    """
    b, n, lane = wp.tid()
    peak_scale = 1.0 / (1.0 - tau)
    if not slot_is_drawn(g, b, n, peak_scale):
        return
    factor = float(0.0)
    height = int(0)
    width = int(0)
    if fused != 0:  # no image gradient array then
        factor = log_l1_factor(loss_grad[b], loss_scale)
        height = image.shape[1]
        width = image.shape[2]
    else:
        height = image_grad.shape[1]
        width = image_grad.shape[2]
    h = float(height)
    a = g.amplitude[b, n]
    w = g.weight[b, n]
    scale = w * a * a * peak_scale  # value = scale (e - tau), so d value / d d2 = -scale e / 2
    mu = g.mean[b, n]
    sig = g.sigma[b, n]
    th = g.theta[b, n]
    frame = gaussian_frame(sig, th, eps)
    conic = frame_conic(frame)
    cutoff2 = cutoff * cutoff
    c = frame[0]
    s = frame[1]
    half_x = cutoff * wp.sqrt(c * c / frame[2] + s * s / frame[3])
    cols = pixel_range(mu[0] - half_x, mu[0] + half_x, h, width)

    # moments over the footprint of the principal-frame offsets (u, v), weighted by the incoming
    # gradient g: sum g (e - tau) and sum g e (u, v, u^2, u v, v^2), with e = exp(-d^2 / 2)
    m0 = float(0.0)
    m_u = float(0.0)
    m_v = float(0.0)
    m_uu = float(0.0)
    m_uv = float(0.0)
    m_vv = float(0.0)
    col = cols[0] + lane
    while col <= cols[1]:
        dx = (float(col) + 0.5) / h - mu[0]
        # rows where the ellipse crosses this column: C dy^2 + 2 B dx dy + A dx^2 <= c^2, whose
        # discriminant is C c^2 - dx^2 det(inverse covariance)
        disc = conic[2] * cutoff2 - dx * dx * frame[2] * frame[3]
        if disc >= 0.0:
            half = wp.sqrt(disc) / conic[2]
            centre = mu[1] - conic[1] * dx / conic[2]
            rows = pixel_range(centre - half, centre + half, h, height)
            for row in range(rows[0], rows[1] + 1):
                dy = (float(row) + 0.5) / h - mu[1]
                d2 = frame_distance2(frame, dx, dy)
                if d2 < cutoff2:
                    incoming = float(0.0)
                    if fused != 0:
                        incoming = log_l1_gradient(image[b, row, col], target[b, row, col], factor)
                    else:
                        incoming = image_grad[b, row, col]
                    e = wp.exp(-0.5 * d2)
                    m0 += incoming * (e - tau)
                    ge = incoming * e
                    u = c * dx + s * dy
                    v = c * dy - s * dx
                    m_u += ge * u
                    m_v += ge * v
                    m_uu += ge * u * u
                    m_uv += ge * u * v
                    m_vv += ge * v * v
        col += lanes

    wp.atomic_add(grad.amplitude, b, n, 2.0 * w * a * peak_scale * m0)
    wp.atomic_add(grad.weight, b, n, a * a * peak_scale * m0)
    # d2 = u^2 ix + v^2 iy with u = c dx + s dy, v = c dy - s dx and (dx, dy) = x - mu
    ix = frame[2]
    iy = frame[3]
    wp.atomic_add(grad.mean, b, n, scale * wp.vec2(c * ix * m_u - s * iy * m_v, s * ix * m_u + c * iy * m_v))
    wp.atomic_add(grad.theta, b, n, -scale * (ix - iy) * m_uv)
    wp.atomic_add(grad.sigma, b, n, scale * wp.vec2(sig[0] * ix * ix * m_uu, sig[1] * iy * iy * m_vv))


def problems_per_launch(height: int, width: int, settings: RasterSettings | None = None) -> int:
    """The most (height x width) images one rasterizer launch draws: every tile-padded pixel indexed below 2^31.

    A batch with more (e.g. the six directed edges per light of a light stage) is drawn in parts; see
    ``kernels.chunks``' ``most_each``.
    """
    tile = (settings or RasterSettings()).tile_size
    padded = -(-int(height) // tile) * -(-int(width) // tile) * tile * tile
    return max(1, (LAUNCH_PIXELS - 1) // padded)


class Rasterizer:
    """Renders a ``GaussianBatch`` to (B, H, W) float32 images, differentiably through ``wp.Tape``.

    Owns the culling buffers for the last batch shape it saw; the output image is allocated per
    call unless ``out`` is given (pass one to keep a fitting step free of allocations, e.g. for CUDA
    graph capture).

    Args:
        height, width: image size in pixels.
        settings: cut-off, covariance epsilon and tile size (``RasterSettings``).
        device: Warp device; defaults to Warp's default device.
        culling: False lists every Gaussian for every tile (the reference the culled path must match).
        backward_lanes: threads per Gaussian in the backward pass; default 64 on CUDA (two warps
            reading coalesced rows; 16/32/64 measured, 64 fastest by 1-10%), 1 on the CPU (one
            thread walks the whole footprint, no idle lanes).
        threads: CPU threads that draw one ``render``'s tiles (Warp runs a CPU launch on one thread):
            for large images rendered alone (relighting); 1 where the caller runs threads of its own.
    """

    def __init__(self, height: int, width: int, *, settings: RasterSettings | None = None, device=None,
                 culling: bool = True, backward_lanes: int | None = None, threads: int = 1):
        if int(height) < 1 or int(width) < 1:
            raise InputError(f"image size must be at least 1 x 1 pixels, got {width} x {height}")
        self.height = int(height)
        self.width = int(width)
        self.settings = settings or RasterSettings()
        self.device = wp.get_device(device)
        self.culling = bool(culling)
        if backward_lanes is None:
            backward_lanes = 64 if self.device.is_cuda else 1
        if int(backward_lanes) < 1:
            raise InputError(f"backward_lanes must be >= 1, got {backward_lanes}")
        self.backward_lanes = int(backward_lanes)
        if int(threads) < 1:
            raise InputError(f"threads must be >= 1, got {threads}")
        self.threads = int(threads)
        tile = self.settings.tile_size
        self.tiles_x = -(-self.width // tile)
        self.tiles_y = -(-self.height // tile)
        self._shape = None

    @property
    def tile_count(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def problems_per_launch(self) -> int:
        """The most images one ``render`` draws: their tile-padded pixels stay below 2^31 (Warp's launch bound)."""
        return problems_per_launch(self.height, self.width, self.settings)

    def _buffers(self, shape: tuple[int, int]) -> None:
        if self._shape == shape:
            return
        problems, capacity = shape
        self.frames = wp.empty(shape, dtype=wp.vec4, device=self.device)
        self.scales = wp.empty(shape, dtype=float, device=self.device)
        self.boxes = wp.empty(shape, dtype=wp.vec4i, device=self.device)
        self.tile_lists = wp.empty((problems, self.tile_count, capacity), dtype=wp.int32, device=self.device)
        self.tile_counts = wp.empty((problems, self.tile_count), dtype=wp.int32, device=self.device)
        self.drawn_tiles = wp.empty(problems * self.tile_count if self.device.is_cuda else 0, dtype=wp.int32,
                                    device=self.device)
        self.drawn_count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._no_tiles = wp.empty(0, dtype=wp.int32, device=self.device)
        self._shape = shape

    def new_image(self, problem_count: int) -> wp.array:
        """A zeroed (B, H, W) image array with a gradient, for ``render(out=...)``."""
        return wp.zeros((problem_count, self.height, self.width), dtype=float, device=self.device, requires_grad=True)

    def render(self, batch: GaussianBatch, *, out: wp.array | None = None, record: bool = True,
               drawn_only: bool = False) -> wp.array:
        """Rasterize every problem of ``batch``; returns (B, H, W) float32 (``out`` when given).

        Inside a ``wp.Tape``, ``tape.backward`` adds the parameter gradients to ``batch``'s
        ``.grad`` arrays (when the batch has them). ``record=False`` leaves the tape alone (for a
        caller that records its own adjoint, e.g. ``LogL1Loss.of_render``). ``drawn_only`` writes
        only the tiles some Gaussian reaches and leaves every other pixel of ``out`` as it was: for a
        caller that reads the image only where the Gaussians draw (the fit loss's fused adjoint), at
        a cost that follows the Gaussians' area rather than the images'.
        """
        if batch.device != self.device:
            raise InputError(f"the batch is on {batch.device} but the rasterizer on {self.device}")
        problems, capacity = batch.shape
        if problems * self.tile_count * self.settings.tile_size**2 >= LAUNCH_PIXELS:  # also one image past it alone
            raise InputError(f"{problems} images of {self.width} x {self.height} exceed one launch (2^31 pixels); "
                             f"render the batch in parts")
        if out is None:
            out = self.new_image(problems)
        elif out.shape != (problems, self.height, self.width) or out.dtype != wp.float32 or out.device != self.device:
            raise InputError(f"out must be a float32 ({problems}, {self.height}, {self.width}) array on {self.device}, "
                             f"got {out.dtype.__name__} {out.shape}")
        self._buffers((problems, capacity))
        s = self.settings
        tau = s.cutoff_level
        wp.launch(
            prepare_gaussians,
            dim=(problems, capacity),
            inputs=[batch.arrays, s.sigma_eps, s.cutoff, 1.0 / (1.0 - tau), self.height, self.width],
            outputs=[self.frames, self.scales, self.boxes],
            device=self.device,
            record_tape=False,
        )
        listed = drawn_only and self.device.is_cuda
        if listed:
            self.drawn_count.zero_()
        wp.launch(
            bin_tiles,
            dim=(problems, self.tile_count),
            inputs=[self.frames, batch.mean, self.scales, self.boxes, s.tile_size, self.tiles_x, self.height,
                    self.width, s.cutoff**2 * _CULL_SLACK,
                    int(self.culling)],
            outputs=[self.tile_lists, self.tile_counts, self.drawn_tiles if listed else self._no_tiles,
                     self.drawn_count],
            device=self.device,
            record_tape=False,
        )
        shift = s.tile_size.bit_length() - 1
        if listed:
            launched = min(problems * self.tile_count, DRAWN_TILES_PER_SWEEP) * s.tile_size**2
            wp.launch(
                rasterize_drawn_tiles,
                dim=launched,
                inputs=[self.frames, batch.mean, self.scales, self.tile_lists, self.tile_counts, self.drawn_tiles,
                        self.drawn_count, shift, self.tiles_x, s.cutoff**2, tau, launched],
                outputs=[out],
                device=self.device,
                record_tape=False,
            )
        else:
            whole_tile = 0 if self.device.is_cuda else (2 if drawn_only else 1)
            launched = problems * self.tile_count * (1 if whole_tile else s.tile_size**2)

            def draw(part: slice, stop=None) -> None:
                wp.launch(rasterize_tiles, dim=part.stop - part.start,
                          inputs=[self.frames, batch.mean, self.scales, self.boxes, self.tile_lists, self.tile_counts,
                                  shift, self.tiles_x, s.cutoff**2, tau, whole_tile, part.start],
                          outputs=[out], device=self.device, record_tape=False)

            # tiles cost what their Gaussians cover: many parts, taken by the threads as they come, share the work
            parts = PARTS_PER_THREAD * self.threads if whole_tile and launched >= THREADED_TILES else 1
            map_chunks(draw, problem_chunks(launched, self.device, parts), threads=self.threads)
        tape = active_tape() if record else None
        if tape is not None and batch.requires_grad:
            if not out.requires_grad:
                raise InputError("inside a wp.Tape the output image needs requires_grad=True (use "
                                 "Rasterizer.new_image) or no gradient reaches the Gaussians")
            tape.record_func(backward=lambda: self.backward(batch, out.grad), arrays=[out, *batch.parameters()])
        return out

    def backward(self, batch: GaussianBatch, image_grad: wp.array | None, *, fit: tuple | None = None) -> None:
        """Add the parameter gradients for the incoming image gradient (B, H, W) to ``batch``'s grads.

        ``fit`` = (image, target, loss_grad, loss_scale) takes the incoming gradient from the fit loss
        instead (``LogL1Loss.of_render``); ``image_grad`` is then None.
        """
        problems, capacity = batch.shape
        s = self.settings
        image, target, loss_grad, loss_scale = fit if fit is not None else (None, None, None, 0.0)
        wp.launch(
            rasterize_backward,
            dim=(problems, capacity, self.backward_lanes),
            inputs=[batch.arrays, image_grad, int(fit is not None), image, target, loss_grad, float(loss_scale),
                    s.sigma_eps, s.cutoff, s.cutoff_level, self.backward_lanes],
            outputs=[batch.grad_arrays],
            device=self.device,
            record_tape=False,
        )

    def tile_statistics(self) -> dict[str, float]:
        """Culling figures of the last render: mean and max Gaussians per tile (copies to the host)."""
        if self._shape is None:
            raise InputError("render something first")
        counts = self.tile_counts.numpy()
        return {"mean_per_tile": float(counts.mean()), "max_per_tile": int(counts.max()), "tiles": int(counts.size)}
