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

__all__ = ["compose_upsampled", "residual_at_source", "source_axis", "upsample_images", "widen_narrow_gaussians"]


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
def _bilinear(array: wp.array2d(dtype=float), i00: int, i01: int, i10: int, i11: int, fy: float, fx: float,
              c: int) -> float:
    # column c of ``array`` between the four source pixels (flattened indices) around an output pixel
    top = (1.0 - fx) * array[i00, c] + fx * array[i01, c]
    bottom = (1.0 - fx) * array[i10, c] + fx * array[i11, c]
    return (1.0 - fy) * top + fy * bottom


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
        y = i // width
        x = i - y * width
        along_y = source_axis(y, height, source_height)
        along_x = source_axis(x, width, source_width)
        y0 = int(along_y[0])
        x0 = int(along_x[0])
        y1 = wp.min(y0 + 1, source_height - 1)
        x1 = wp.min(x0 + 1, source_width - 1)
        fy = along_y[1]
        fx = along_x[1]
        i00 = y0 * source_width + x0
        i01 = y0 * source_width + x1
        i10 = y1 * source_width + x0
        i11 = y1 * source_width + x1
        s = residual_scale[0]
        if diffuse_mode == DIFFUSE_LOWRANK and not one_scale:
            s = ((1.0 - fy) * ((1.0 - fx) * residual_scale[i00] + fx * residual_scale[i01])
                 + fy * ((1.0 - fx) * residual_scale[i10] + fx * residual_scale[i11]))
        for c in range(channels):
            value = float(0.0)
            if diffuse_mode == DIFFUSE_LAMBERT:
                m = ((1.0 - fy) * ((1.0 - fx) * lambert[i00, c] + fx * lambert[i01, c])
                     + fy * ((1.0 - fx) * lambert[i10, c] + fx * lambert[i11, c]))
                value = wp.max(m[0] * omega[0] + m[1] * omega[1] + m[2] * omega[2], 0.0) + m[3]
            elif diffuse_mode == DIFFUSE_BLEND or diffuse_mode == DIFFUSE_DECODED or diffuse_mode == DIFFUSE_LOWRANK:
                top = (1.0 - fx) * source[q, i00, c] + fx * source[q, i01, c]
                bottom = (1.0 - fx) * source[q, i10, c] + fx * source[q, i11, c]
                value = (1.0 - fy) * top + fy * bottom
                if diffuse_mode == DIFFUSE_LOWRANK:
                    value = s * value
            if add_specular != 0:
                colour = pixel_colour[0, c]
                if not one_colour:
                    colour = _bilinear(pixel_colour, i00, i01, i10, i11, fy, fx, c)
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
        y = i // width
        x = i - y * width
        along_y = source_axis(y, height, source_height)
        along_x = source_axis(x, width, source_width)
        y0 = int(along_y[0])
        x0 = int(along_x[0])
        y1 = wp.min(y0 + 1, source_height - 1)
        x1 = wp.min(x0 + 1, source_width - 1)
        fy = along_y[1]
        fx = along_x[1]
        top = (1.0 - fx) * source[q, y0 * source_width + x0] + fx * source[q, y0 * source_width + x1]
        bottom = (1.0 - fx) * source[q, y1 * source_width + x0] + fx * source[q, y1 * source_width + x1]
        out[q, i] = (1.0 - fy) * top + fy * bottom


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
