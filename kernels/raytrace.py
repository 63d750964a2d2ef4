"""Ray-traced shading of one triangle mesh under many distant lights (the synthetic-data renderer).

Two passes, both batched:

1. ``trace_camera_samples`` (one thread per pixel sample): primary rays of a pinhole camera, jittered
   inside a k x k stratified grid per pixel; the hit point, the smooth shading normal and a shadow-ray
   origin are stored. It does not depend on the light, so it runs once per view.
2. ``shade_lights`` (one thread per light x covered pixel): for every sample of the pixel, a shadow ray
   towards the light, then the diffuse cosine and the normalised Blinn-Phong lobe. The sample average
   goes to two scalar images per light (diffuse irradiance and specular radiance).
3. ``compose_images`` (one thread per light x pixel) turns the scalar images into colour images:
   diffuse = albedo * irradiance + ambient * coverage, specular = colour * radiance, full = their sum.

Units: the scene is in the mesh's units (the renderer normalises meshes to a unit bounding sphere);
light intensity is 1, so a white Lambertian surface facing the light has radiance 1 (display white).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = [
    "CameraSamples",
    "PinholeCamera",
    "ShadingParameters",
    "compose_images",
    "make_camera",
    "make_shading_parameters",
    "shade_and_compose",
    "shade_lights",
    "trace_camera",
    "trace_camera_samples",
]


@wp.struct
class PinholeCamera:
    """A pinhole camera at ``position`` looking along -z (x right, y up in the image).

    ``tan_half_fov_y`` is tan(vertical field of view / 2); ``aspect`` = width / height.
    """

    position: wp.vec3
    tan_half_fov_y: float
    aspect: float
    width: int
    height: int


@wp.struct
class ShadingParameters:
    """Material and sampling constants shared by every thread of ``shade_lights``."""

    shininess: float  # Blinn-Phong exponent of (n . h)
    lobe_normalisation: float  # (shininess + 8) / (8 pi): the lobe keeps its energy as it sharpens
    alpha: float  # GGX roughness; 0 selects the Blinn-Phong lobe
    samples_per_pixel: int


@wp.func
def _terminator_safe_origin(mesh: wp.uint64, face: int, u: float, v: float, normals: wp.array(dtype=wp.vec3),
                            indices: wp.array(dtype=wp.int32), hit: wp.vec3) -> wp.vec3:
    """Lift a hit point of a flat triangle towards the smooth surface its vertex normals describe.

    A shadow ray from the flat facet itself is blocked by neighbouring facets near the shadow
    terminator, which shows as jagged self-shadowing. Moving the origin onto the tangent planes of the
    vertices (weighted by the barycentrics) removes it without a large constant bias.
    """
    i0 = indices[face * 3 + 0]
    i1 = indices[face * 3 + 1]
    i2 = indices[face * 3 + 2]
    p0 = wp.mesh_eval_position(mesh, face, 1.0, 0.0)
    p1 = wp.mesh_eval_position(mesh, face, 0.0, 1.0)
    p2 = wp.mesh_eval_position(mesh, face, 0.0, 0.0)
    w = 1.0 - u - v
    lift = u * wp.min(wp.dot(hit - p0, normals[i0]), 0.0) * normals[i0]
    lift += v * wp.min(wp.dot(hit - p1, normals[i1]), 0.0) * normals[i1]
    lift += w * wp.min(wp.dot(hit - p2, normals[i2]), 0.0) * normals[i2]
    return hit - lift


@wp.kernel
def trace_camera_samples(
    mesh: wp.uint64,
    normals: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    camera: PinholeCamera,
    grid: int,
    seed: int,
    shadow_bias: float,
    hit_mask: wp.array3d(dtype=wp.int32),
    shading_normal: wp.array3d(dtype=wp.vec3),
    view_direction: wp.array3d(dtype=wp.vec3),
    shadow_origin: wp.array3d(dtype=wp.vec3),
):
    """One thread per (row, col, sample): cast the camera ray, store what shading needs.

    Samples are stratified: sample s sits in cell (s % grid, s // grid) of a grid x grid split of the
    pixel, jittered uniformly inside its cell.
    """
    row, col, s = wp.tid()
    state = wp.rand_init(seed, (row * camera.width + col) * grid * grid + s)
    sx = (float(s % grid) + wp.randf(state)) / float(grid)
    sy = (float(s / grid) + wp.randf(state)) / float(grid)
    ndc_x = (2.0 * (float(col) + sx) / float(camera.width) - 1.0) * camera.aspect * camera.tan_half_fov_y
    ndc_y = (1.0 - 2.0 * (float(row) + sy) / float(camera.height)) * camera.tan_half_fov_y
    direction = wp.normalize(wp.vec3(ndc_x, ndc_y, -1.0))

    query = wp.mesh_query_ray(mesh, camera.position, direction, 1.0e10)
    if not query.result:
        hit_mask[row, col, s] = 0
        return
    hit = camera.position + query.t * direction
    i0 = indices[query.face * 3 + 0]
    i1 = indices[query.face * 3 + 1]
    i2 = indices[query.face * 3 + 2]
    w = 1.0 - query.u - query.v
    normal = wp.normalize(query.u * normals[i0] + query.v * normals[i1] + w * normals[i2])
    geometric = query.normal
    # Open meshes show their inside: shade the side that faces the camera.
    if wp.dot(geometric, direction) > 0.0:
        geometric = -geometric
        normal = -normal
        origin = hit
    else:
        origin = _terminator_safe_origin(mesh, query.face, query.u, query.v, normals, indices, hit)
    hit_mask[row, col, s] = 1
    shading_normal[row, col, s] = normal
    view_direction[row, col, s] = -direction
    shadow_origin[row, col, s] = origin + shadow_bias * geometric


@wp.func
def _ggx_radiance(cos_h: float, cos_l: float, cos_v: float, alpha: float):
    """GGX (Trowbridge-Reitz) lobe times n.l: D(h) G(l, v) / (4 n.v), Smith's separable shadowing;
    cos_l > 0; a surface seen edge-on (n.v <= 0) reflects nothing."""
    if cos_v <= 0.0:
        return 0.0
    a2 = alpha * alpha
    t = cos_h * cos_h * (a2 - 1.0) + 1.0
    d = a2 / (wp.pi * t * t)
    g_l = 2.0 * cos_l / (cos_l + wp.sqrt(a2 + (1.0 - a2) * cos_l * cos_l))
    g_v = 2.0 * cos_v / (cos_v + wp.sqrt(a2 + (1.0 - a2) * cos_v * cos_v))
    return d * g_l * g_v / (4.0 * cos_v)


@wp.kernel
def shade_lights(
    mesh: wp.uint64,
    light_directions: wp.array(dtype=wp.vec3),
    pixel_rows: wp.array(dtype=wp.int32),
    pixel_cols: wp.array(dtype=wp.int32),
    hit_mask: wp.array3d(dtype=wp.int32),
    shading_normal: wp.array3d(dtype=wp.vec3),
    view_direction: wp.array3d(dtype=wp.vec3),
    shadow_origin: wp.array3d(dtype=wp.vec3),
    params: ShadingParameters,
    irradiance: wp.array2d(dtype=wp.float32),
    specular: wp.array2d(dtype=wp.float32),
):
    """One thread per (light, covered pixel): average diffuse cosine and specular lobe (Blinn-Phong or
    GGX, ``params.alpha``) over the samples."""
    light, p = wp.tid()
    row = pixel_rows[p]
    col = pixel_cols[p]
    omega = light_directions[light]
    diffuse_sum = float(0.0)
    specular_sum = float(0.0)
    for s in range(params.samples_per_pixel):
        if hit_mask[row, col, s] == 0:
            continue
        normal = shading_normal[row, col, s]
        cosine = wp.dot(normal, omega)
        if cosine <= 0.0:
            continue
        if wp.mesh_query_ray_anyhit(mesh, shadow_origin[row, col, s], omega, 1.0e10):
            continue
        view = view_direction[row, col, s]
        half_vector = wp.normalize(omega + view)
        cos_h = wp.max(wp.dot(normal, half_vector), 0.0)
        diffuse_sum += cosine
        if params.alpha > 0.0:
            specular_sum += _ggx_radiance(cos_h, cosine, wp.dot(normal, view), params.alpha)
        else:
            specular_sum += params.lobe_normalisation * wp.pow(cos_h, params.shininess) * cosine
    scale = 1.0 / float(params.samples_per_pixel)
    irradiance[light, p] = diffuse_sum * scale
    specular[light, p] = specular_sum * scale


@wp.kernel
def compose_images(
    pixel_rows: wp.array(dtype=wp.int32),
    pixel_cols: wp.array(dtype=wp.int32),
    coverage: wp.array(dtype=wp.float32),
    irradiance: wp.array2d(dtype=wp.float32),
    specular_radiance: wp.array2d(dtype=wp.float32),
    albedo: wp.array2d(dtype=wp.float32),
    ambient: wp.array(dtype=wp.float32),
    specular_colour: wp.array2d(dtype=wp.float32),
    full: wp.array4d(dtype=wp.float32),
    diffuse: wp.array4d(dtype=wp.float32),
    specular: wp.array4d(dtype=wp.float32),
):
    """One thread per (light, covered pixel, channel): write the colour images (background stays 0);
    albedo and specular colour per covered pixel (a texture) and channel."""
    light, p, c = wp.tid()
    row = pixel_rows[p]
    col = pixel_cols[p]
    d = albedo[p, c] * irradiance[light, p] + ambient[c] * coverage[p]
    s = specular_colour[p, c] * specular_radiance[light, p]
    diffuse[light, row, col, c] = d
    specular[light, row, col, c] = s
    full[light, row, col, c] = d + s


@dataclass
class CameraSamples:
    """Per-sample results of the camera pass, kept on the device for every light chunk of a view.

    Attributes:
        hit_mask, shading_normal, view_direction, shadow_origin: (H, W, S) arrays from the camera pass.
        pixel_rows, pixel_cols: (P,) int32, the pixels hit by at least one sample.
        coverage: (P,) float32, the fraction of each such pixel's samples that hit the object.
        coverage_image: (H, W) float32 host copy of the coverage (0 on background).
    """

    hit_mask: wp.array
    shading_normal: wp.array
    view_direction: wp.array
    shadow_origin: wp.array
    pixel_rows: wp.array
    pixel_cols: wp.array
    coverage: wp.array
    coverage_image: np.ndarray

    @property
    def covered_pixel_count(self) -> int:
        return int(self.pixel_rows.shape[0])


def make_camera(position: np.ndarray, fov_y_deg: float, width: int, height: int) -> PinholeCamera:
    """A :class:`PinholeCamera` at ``position`` (scene units) with vertical field of view in degrees."""
    camera = PinholeCamera()
    camera.position = wp.vec3(*[float(x) for x in position])
    camera.tan_half_fov_y = math.tan(math.radians(fov_y_deg) / 2.0)
    camera.aspect = width / height
    camera.width = int(width)
    camera.height = int(height)
    return camera


def trace_camera(
    mesh: wp.Mesh,
    normals: wp.array,
    camera: PinholeCamera,
    *,
    grid: int,
    seed: int,
    shadow_bias: float,
    device,
) -> CameraSamples:
    """Run the camera pass and list the covered pixels (a one-off host copy per view, not per light)."""
    shape = (camera.height, camera.width, grid * grid)
    hit_mask = wp.zeros(shape, dtype=wp.int32, device=device)
    shading_normal = wp.zeros(shape, dtype=wp.vec3, device=device)
    view_direction = wp.zeros(shape, dtype=wp.vec3, device=device)
    shadow_origin = wp.zeros(shape, dtype=wp.vec3, device=device)
    wp.launch(
        trace_camera_samples,
        dim=shape,
        inputs=[mesh.id, normals, mesh.indices, camera, grid, seed, shadow_bias],
        outputs=[hit_mask, shading_normal, view_direction, shadow_origin],
        device=device,
    )
    coverage_image = hit_mask.numpy().mean(axis=2, dtype=np.float32)
    rows, cols = np.nonzero(coverage_image > 0)
    return CameraSamples(
        hit_mask=hit_mask,
        shading_normal=shading_normal,
        view_direction=view_direction,
        shadow_origin=shadow_origin,
        pixel_rows=wp.array(rows.astype(np.int32), dtype=wp.int32, device=device),
        pixel_cols=wp.array(cols.astype(np.int32), dtype=wp.int32, device=device),
        coverage=wp.array(coverage_image[rows, cols], dtype=wp.float32, device=device),
        coverage_image=coverage_image,
    )


def shade_and_compose(
    mesh: wp.Mesh,
    samples: CameraSamples,
    light_directions: np.ndarray,
    params: ShadingParameters,
    *,
    albedo: np.ndarray,
    ambient: np.ndarray,
    specular_colour: np.ndarray,
    height: int,
    width: int,
    device,
) -> tuple[wp.array, wp.array, wp.array]:
    """Shade every light of ``light_directions`` ((L, 3) unit vectors) in two launches.

    Args:
        albedo, specular_colour: (C,) for a uniform material, or (P, C) per covered pixel (a texture).
        ambient: (C,).

    Returns:
        (full, diffuse, specular) device arrays of shape (L, H, W, C), C = albedo's last axis.
    """
    light_count = len(light_directions)
    pixel_count = samples.covered_pixel_count
    channels = np.shape(albedo)[-1]
    lights = wp.array(np.asarray(light_directions, dtype=np.float32), dtype=wp.vec3, device=device)
    irradiance = wp.zeros((light_count, pixel_count), dtype=wp.float32, device=device)
    specular_radiance = wp.zeros((light_count, pixel_count), dtype=wp.float32, device=device)
    image_shape = (light_count, height, width, channels)
    full = wp.zeros(image_shape, dtype=wp.float32, device=device)
    diffuse = wp.zeros(image_shape, dtype=wp.float32, device=device)
    specular = wp.zeros(image_shape, dtype=wp.float32, device=device)
    if pixel_count == 0 or light_count == 0:
        return full, diffuse, specular

    def shade(first: int, last: int):
        wp.launch(
            shade_lights,
            dim=(last - first, pixel_count),
            inputs=[
                mesh.id,
                lights[first:last],
                samples.pixel_rows,
                samples.pixel_cols,
                samples.hit_mask,
                samples.shading_normal,
                samples.view_direction,
                samples.shadow_origin,
                params,
            ],
            outputs=[irradiance[first:last], specular_radiance[first:last]],
            device=device,
        )

    _run_split(shade, light_count, device)
    wp.launch(
        compose_images,
        dim=(light_count, pixel_count, channels),
        inputs=[
            samples.pixel_rows,
            samples.pixel_cols,
            samples.coverage,
            irradiance,
            specular_radiance,
            _per_pixel(albedo, pixel_count, device),
            _float_array(ambient, device),
            _per_pixel(specular_colour, pixel_count, device),
        ],
        outputs=[full, diffuse, specular],
        device=device,
    )
    return full, diffuse, specular


def make_shading_parameters(*, shininess: float, samples_per_pixel: int, roughness: float = 0.0) -> ShadingParameters:
    """Fill :class:`ShadingParameters`; the lobe normalisation follows from the shininess; roughness > 0
    selects the GGX lobe."""
    params = ShadingParameters()
    params.shininess = float(shininess)
    params.lobe_normalisation = (float(shininess) + 8.0) / (8.0 * math.pi)
    params.alpha = float(roughness)
    params.samples_per_pixel = int(samples_per_pixel)
    return params


def _run_split(launch, count: int, device) -> None:
    """Call ``launch(first, last)`` over [0, count): once on a GPU, in one thread per core on the CPU.

    Warp runs a CPU kernel on one thread and releases the GIL while it runs, so contiguous slices of
    the light axis launched from a thread pool use every core; the results are identical. Lights differ
    a lot in cost (back lights shade few pixels), so the slices are several per core, taken as the
    threads come free.
    """
    workers = min(os.cpu_count() or 1, count) if wp.get_device(device).is_cpu else 1
    if workers <= 1:
        launch(0, count)
        return
    bounds = np.linspace(0, count, min(count, 8 * workers) + 1).astype(int)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for future in [pool.submit(launch, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
            future.result()


def _per_pixel(values, pixel_count: int, device) -> wp.array:
    """(P, C) float32 device array of per-pixel values, a (C,) constant repeated for every pixel."""
    values = np.asarray(values, dtype=np.float32)
    if values.ndim == 1:
        values = np.broadcast_to(values, (pixel_count, len(values)))
    return wp.array(np.ascontiguousarray(values), dtype=wp.float32, device=device)


def _float_array(values, device) -> wp.array:
    return wp.array(np.asarray(values, dtype=np.float32).ravel(), dtype=wp.float32, device=device)
