"""Kernels that compose relit images larger than the field, its per-pixel arrays read at the field's size.

A relit image of W x H output pixels from a field of w x h pixels (W >= w, H >= h) is composed from
the field's own arrays, never resampled whole on the host: ``residual_at_source`` makes each query's
residual (or diffuse) term at the field's size, then ``compose_upsampled`` reads it, the per-pixel
residual scale, the highlight colour c(x) and the Lambertian planes by bilinear interpolation at
every output pixel and adds the highlights S' drawn at the output size. Bilinear interpolation is
that of ``io.resample.resample_image`` when it enlarges (output pixel centres mapped onto the input's,
edges clamped), and every interpolated array enters the image linearly but for the clamp at 0, the
residual scale and c(x), which are interpolated on their own as before: the image equals the one
composed from arrays resampled on the host, to float rounding, at a cost of a few reads per output
pixel and channel instead of k + 1 per basis image (``compose_images``).
"""

# ruff: noqa: UP018, RUF046  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

import warp as wp

from warp_highlights.model.gaussians import GaussianArrays

from .interpolation import (
    DIFFUSE_BLEND,
    DIFFUSE_DECODED,
    DIFFUSE_LAMBERT,
    DIFFUSE_LOWRANK,
    _low_rank_opponent,
    _opponent_channel,
)

__all__ = [
    "compose_upsampled",
    "residual_at_source",
    "source_axis",
    "source_taps",
    "source_weights",
    "upsample_images",
    "widen_narrow_gaussians",
]


@wp.func
def source_axis(out_index: int, out_size: int, source_size: int) -> wp.vec2:
    """(first input index, weight of the next one) of output pixel ``out_index`` along one axis: the pixel
    centre (out_index + 0.5) source_size / out_size - 0.5, clamped to the input's first and last pixel."""
    position = (float(out_index) + 0.5) * float(source_size) / float(out_size) - 0.5
    position = wp.clamp(position, 0.0, float(source_size - 1))
    first = wp.min(int(wp.floor(position)), source_size - 1)
    return wp.vec2(float(first), position - float(first))


@wp.kernel(enable_backward=False)
def residual_at_source(
    diffuse_mode: int,
    diffuse_images: wp.array3d(dtype=wp.float16),
    luminance_mean: wp.array2d(dtype=float),
    luminance_basis: wp.array3d(dtype=float),
    luminance_weights: wp.array2d(dtype=float),
    chroma_mean: wp.array2d(dtype=float),
    chroma_basis: wp.array3d(dtype=float),
    chroma_weights: wp.array2d(dtype=float),
    unit_scale: wp.array(dtype=float),
    face_vertices: wp.array2d(dtype=wp.int32),
    faces: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec3),
    out: wp.array3d(dtype=float),
):
    """out[q, p, c] = query q's residual term at field pixel p: the blend of ``diffuse_images``
    (``DIFFUSE_BLEND``), the low-rank residual before its per-pixel scale (``DIFFUSE_LOWRANK``; ``unit_scale``
    holds one 1), or ``diffuse_images[q]`` (``DIFFUSE_DECODED``); what ``compose_images`` adds at a
    pixel, without c(x) S', the clamp and the exposure."""
    q, p = wp.tid()
    channels = out.shape[2]
    f = faces[q]
    w = weights[q]
    if diffuse_mode == DIFFUSE_LOWRANK:
        opponent = _low_rank_opponent(luminance_mean, luminance_basis, luminance_weights, chroma_mean, chroma_basis,
                                      chroma_weights, unit_scale, q, p, channels)
        for c in range(channels):
            out[q, p, c] = _opponent_channel(opponent, c, channels)
    elif diffuse_mode == DIFFUSE_BLEND:
        corner0 = face_vertices[f, 0]
        corner1 = face_vertices[f, 1]
        corner2 = face_vertices[f, 2]
        for c in range(channels):
            out[q, p, c] = (w[0] * float(diffuse_images[corner0, p, c]) + w[1] * float(diffuse_images[corner1, p, c])
                            + w[2] * float(diffuse_images[corner2, p, c]))
    elif diffuse_mode == DIFFUSE_DECODED:
        for c in range(channels):
            out[q, p, c] = float(diffuse_images[q, p, c])
    else:
        for c in range(channels):
            out[q, p, c] = 0.0


@wp.func
def source_taps(i: int, width: int, height: int, source_width: int, source_height: int) -> wp.vec4i:
    """The four source pixels (flattened: top left, top right, bottom left, bottom right) around output pixel
    ``i`` of a ``width`` x ``height`` image read from a ``source_width`` x ``source_height`` one."""
    y = i // width
    y0 = int(source_axis(y, height, source_height)[0])
    x0 = int(source_axis(i - y * width, width, source_width)[0])
    y1 = wp.min(y0 + 1, source_height - 1)
    x1 = wp.min(x0 + 1, source_width - 1)
    return wp.vec4i(y0 * source_width + x0, y0 * source_width + x1, y1 * source_width + x0, y1 * source_width + x1)


@wp.func
def source_weights(i: int, width: int, height: int, source_width: int, source_height: int) -> wp.vec2:
    """(weight of the bottom row, weight of the right column) of ``source_taps``' four pixels."""
    y = i // width
    return wp.vec2(source_axis(y, height, source_height)[1], source_axis(i - y * width, width, source_width)[1])


@wp.func
def _between(v00: float, v01: float, v10: float, v11: float, weights: wp.vec2) -> float:
    # bilinear: along x in each row, then along y
    return (1.0 - weights[0]) * ((1.0 - weights[1]) * v00 + weights[1] * v01) + weights[0] * (
        (1.0 - weights[1]) * v10 + weights[1] * v11)


@wp.kernel(enable_backward=False)
def compose_upsampled(
    specular: wp.array2d(dtype=float),
    specular_colour: wp.vec3,
    pixel_colour: wp.array2d(dtype=float),
    add_specular: int,
    diffuse_mode: int,
    lambert: wp.array2d(dtype=wp.vec4),
    source: wp.array3d(dtype=float),
    residual_scale: wp.array(dtype=float),
    directions: wp.array(dtype=wp.vec3),
    width: int,
    source_width: int,
    source_height: int,
    scale: float,
    pixels_per_thread: int,
    first_part: int,
    out: wp.array3d(dtype=float),
):
    """out[q, i, c] = scale max(B'[q, i, c] + colour[c] c_i[c] S'[q, i], 0) at output pixel i of a
    ``width``-wide image, with B' and c_i read from the ``source_width`` x ``source_height`` field arrays
    by bilinear interpolation: ``source[q]`` (``residual_at_source``) times the interpolated
    ``residual_scale`` for ``DIFFUSE_LOWRANK`` (one entry: 1 everywhere), the interpolated Lambertian
    planes for ``DIFFUSE_LAMBERT``, nothing for ``DIFFUSE_NONE``. Thread (q, t) does pixels u p .. u p +
    p - 1 (p = ``pixels_per_thread``, u = t + ``first_part``), as ``compose_images``."""
    q, t = wp.tid()
    t += first_part
    omega = directions[q]
    channels = out.shape[2]
    height = out.shape[1] // width
    one_colour = pixel_colour.shape[0] == 1
    one_scale = residual_scale.shape[0] == 1
    first = t * pixels_per_thread
    for i in range(first, wp.min(first + pixels_per_thread, out.shape[1])):
        k = source_taps(i, width, height, source_width, source_height)
        f = source_weights(i, width, height, source_width, source_height)
        s = residual_scale[0]
        if diffuse_mode == DIFFUSE_LOWRANK and not one_scale:
            s = _between(residual_scale[k[0]], residual_scale[k[1]], residual_scale[k[2]], residual_scale[k[3]], f)
        for c in range(channels):
            value = float(0.0)
            if diffuse_mode == DIFFUSE_LAMBERT:
                m = (1.0 - f[0]) * ((1.0 - f[1]) * lambert[k[0], c] + f[1] * lambert[k[1], c]) + f[0] * (
                    (1.0 - f[1]) * lambert[k[2], c] + f[1] * lambert[k[3], c])
                value = wp.max(m[0] * omega[0] + m[1] * omega[1] + m[2] * omega[2], 0.0) + m[3]
            elif diffuse_mode == DIFFUSE_BLEND or diffuse_mode == DIFFUSE_DECODED or diffuse_mode == DIFFUSE_LOWRANK:
                value = _between(source[q, k[0], c], source[q, k[1], c], source[q, k[2], c], source[q, k[3], c], f)
                if diffuse_mode == DIFFUSE_LOWRANK:
                    value = s * value
            if add_specular != 0:
                colour = pixel_colour[0, c]
                if not one_colour:
                    colour = _between(pixel_colour[k[0], c], pixel_colour[k[1], c], pixel_colour[k[2], c],
                                      pixel_colour[k[3], c], f)
                value += specular_colour[c] * colour * specular[q, i]
            out[q, i, c] = scale * wp.max(value, 0.0)


@wp.kernel(enable_backward=False)
def upsample_images(
    source: wp.array2d(dtype=float),
    width: int,
    source_width: int,
    source_height: int,
    pixels_per_thread: int,
    first_part: int,
    out: wp.array2d(dtype=float),
):
    """out[q, i] = ``source[q]`` (``source_width`` x ``source_height`` pixels) at pixel i of a ``width``-wide
    image, by bilinear interpolation as ``compose_upsampled`` reads (the alpha method's specular blend); the
    threads split the pixels as ``compose_upsampled``'s."""
    q, t = wp.tid()
    t += first_part
    height = out.shape[1] // width
    first = t * pixels_per_thread
    for i in range(first, wp.min(first + pixels_per_thread, out.shape[1])):
        k = source_taps(i, width, height, source_width, source_height)
        f = source_weights(i, width, height, source_width, source_height)
        out[q, i] = _between(source[q, k[0]], source[q, k[1]], source[q, k[2]], source[q, k[3]], f)


@wp.kernel(enable_backward=False)
def widen_narrow_gaussians(sets: GaussianArrays, least: float, eps: float):
    """Each Gaussian of ``sets`` at least ``least`` wide along each axis (normalised units), its amplitude scaled
    so that a^2 sqrt((sigma_x^2 + eps)(sigma_y^2 + eps)), the light it adds, is kept; wider ones are left
    exactly as they are (drawn larger than the field: ``RasterSettings.upsampled_min_sigma_px``)."""
    q, n = wp.tid()
    sigma = sets.sigma[q, n]
    sx = wp.abs(sigma[0])
    sy = wp.abs(sigma[1])
    if sx >= least and sy >= least:
        return
    wx = wp.max(sx, least)
    wy = wp.max(sy, least)
    kept = wp.sqrt(wp.sqrt((sx * sx + eps) * (sy * sy + eps)) / wp.sqrt((wx * wx + eps) * (wy * wy + eps)))
    sets.amplitude[q, n] = sets.amplitude[q, n] * kept
    sets.sigma[q, n] = wp.vec2(wx, wy)
