"""Diffuse/specular segmentation of a reflectance field, one thread per pixel and channel (docs/method.md, Fitting step
1).

Every (pixel, channel) fits the Lambertian model D~_i = nbar . omega_i + k_a, k_a >= 0, to its samples I_i over
the lights, by a 4 x 4 normal-equation solve (a 3 x 3 one with k_a = 0 where the free k_a is negative), robustly:

1. L = the lights with I_i >= t (shadowed or unlit samples say nothing about nbar);
2. fit over the current set, residuals l_i = |I_i - D~_i| over L, median m~; the next set is
   L' = {i in L : l_i <= max(f m~, floor)}; repeat until L' stops changing (or the iteration cap);
3. D~_i = max(D~_i, floor) + offset, D_i = min(I_i, D~_i), S_i = I_i - D_i.

Pixels with fewer than ``min_valid`` valid lights are all diffuse (S = 0). The sets never need storing:
L' is a function of the fit and threshold that produced it, so two sets are compared by re-evaluating
both memberships over the lights. The median is a bisection on the residual value (no per-thread
scratch memory), accurate to float32 resolution; its two ranks are bisected together, two halvings a
pass over the lights (``_median_residual``: the passes, each a read of the pixel's samples over all
lights, are what the kernel spends its time on).
"""

# ruff: noqa: UP018, RUF046  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import warp as wp

from warp_highlights.model.config import SegmentationSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import LUMINANCE_WEIGHTS  # the luminance the Gaussians are fitted to
from warp_highlights.model.threads import all_finite, mapped_empty

from .chunks import DEVICE_SHARE, map_chunks, problem_chunks
from .transfer import HALF_MAX, as_half, rows_down, rows_up, to_host

__all__ = ["LUMINANCE_WEIGHTS", "Segmentation", "band_rows", "count_non_finite", "host_array", "luminance", "segment",
           "segment_in_bands", "segment_pixels",
           "shrink_by"]

_MEDIAN_BISECTIONS = 26  # halvings of [0, max residual]: 2^-26 ~ float32 resolution (even: two a pass)


@wp.func
def _lambert(direction: wp.vec3, fit: wp.vec4) -> float:
    return direction[0] * fit[0] + direction[1] * fit[1] + direction[2] * fit[2] + fit[3]


@wp.func
def _in_set(value: float, direction: wp.vec3, threshold: float, fit: wp.vec4, limit: float) -> int:
    # membership of one sample in the set defined by (fit, limit); limit < 0 means "all valid"
    if value < threshold:
        return 0
    if limit < 0.0:
        return 1
    if wp.abs(value - _lambert(direction, fit)) <= limit:
        return 1
    return 0


@wp.func
def _solve(images: wp.array2d(dtype=float), directions: wp.array(dtype=wp.vec3), q: int, threshold: float, fit: wp.vec4,
           limit: float, nonnegative: int) -> wp.vec4:
    """Least-squares (nbar, k_a) over the set defined by (fit, limit); where ``nonnegative`` and the free fit's k_a
    is negative, the fit of nbar alone with k_a = 0 (the least-squares minimum under k_a >= 0); NaN vector when
    singular."""
    normal = wp.mat44()
    rhs = wp.vec4()
    for i in range(images.shape[0]):
        value = images[i, q]
        if _in_set(value, directions[i], threshold, fit, limit) == 1:
            row = wp.vec4(directions[i][0], directions[i][1], directions[i][2], 1.0)
            normal += wp.outer(row, row)
            rhs += row * value
    trace = normal[0, 0] + normal[1, 1] + normal[2, 2] + normal[3, 3]
    # relative ridge: keeps a nearly coplanar light set solvable without moving a well-posed fit
    ridge = 1.0e-6 * trace
    for k in range(4):
        normal[k, k] = normal[k, k] + ridge
    if wp.determinant(normal) <= 1.0e-12 * trace * trace * trace * trace:
        return wp.vec4(wp.nan, wp.nan, wp.nan, wp.nan)
    free = wp.inverse(normal) * rhs
    if free[3] >= 0.0 or nonnegative == 0:
        return free
    # an ambient term below zero is no light at all: a highlight or a shadow has bent the fit
    # (SegmentationSettings.nonnegative_ambient)
    block = wp.mat33(normal[0, 0], normal[0, 1], normal[0, 2], normal[1, 0], normal[1, 1], normal[1, 2],
                     normal[2, 0], normal[2, 1], normal[2, 2])
    trace3 = block[0, 0] + block[1, 1] + block[2, 2]
    if wp.determinant(block) <= 1.0e-12 * trace3 * trace3 * trace3:
        return wp.vec4(wp.nan, wp.nan, wp.nan, wp.nan)
    lit = wp.inverse(block) * wp.vec3(rhs[0], rhs[1], rhs[2])
    return wp.vec4(lit[0], lit[1], lit[2], 0.0)


@wp.func
def _halves(lo: float, hi: float, low_count: int, middle_count: int, high_count: int, rank: int) -> wp.vec2:
    """[lo, hi] after two bisection steps for the rank-th smallest residual, from the counts of residuals
    at most the interval's quarter, middle and three-quarter points (``_median_residual``'s midpoints)."""
    middle = 0.5 * (lo + hi)
    count = low_count  # at the next midpoint: the lower half's ...
    if middle_count > rank:
        hi = middle
    else:
        lo = middle
        count = high_count  # ... or the upper half's
    middle = 0.5 * (lo + hi)
    if count > rank:
        hi = middle
    else:
        lo = middle
    return wp.vec2(lo, hi)


@wp.func
def _median_residual(images: wp.array2d(dtype=float), directions: wp.array(dtype=wp.vec3), q: int, threshold: float,
                     fit: wp.vec4, valid: int,
                     largest: float) -> float:
    """The median residual |I_i - D~_i| over the ``valid`` valid lights: the mean of the ranks (valid - 1) // 2
    and valid // 2, each by ``_MEDIAN_BISECTIONS`` halvings of [0, largest].

    Both ranks are bisected together, two halvings a pass over the lights (the counts at the quarter,
    middle and three-quarter points of each interval): the same midpoints, so the same result, as one
    halving a pass per rank, in a quarter of the passes (the passes, not the comparisons, cost). Scalar
    counters: vector ones made the CPU kernel a fifth slower."""
    lo_a = float(0.0)
    hi_a = largest
    lo_b = float(0.0)
    hi_b = largest
    for _ in range(_MEDIAN_BISECTIONS // 2):
        middle_a = 0.5 * (lo_a + hi_a)
        low_a = 0.5 * (lo_a + middle_a)
        high_a = 0.5 * (middle_a + hi_a)
        middle_b = 0.5 * (lo_b + hi_b)
        low_b = 0.5 * (lo_b + middle_b)
        high_b = 0.5 * (middle_b + hi_b)
        count_low_a = int(0)
        count_middle_a = int(0)
        count_high_a = int(0)
        count_low_b = int(0)
        count_middle_b = int(0)
        count_high_b = int(0)
        for i in range(images.shape[0]):
            value = images[i, q]
            if value >= threshold:
                residual = wp.abs(value - _lambert(directions[i], fit))
                count_low_a += wp.where(residual <= low_a, 1, 0)
                count_middle_a += wp.where(residual <= middle_a, 1, 0)
                count_high_a += wp.where(residual <= high_a, 1, 0)
                count_low_b += wp.where(residual <= low_b, 1, 0)
                count_middle_b += wp.where(residual <= middle_b, 1, 0)
                count_high_b += wp.where(residual <= high_b, 1, 0)
        interval_a = _halves(lo_a, hi_a, count_low_a, count_middle_a, count_high_a, (valid - 1) // 2)
        interval_b = _halves(lo_b, hi_b, count_low_b, count_middle_b, count_high_b, valid // 2)
        lo_a = interval_a[0]
        hi_a = interval_a[1]
        lo_b = interval_b[0]
        hi_b = interval_b[1]
    return 0.5 * (hi_a + hi_b)


@wp.kernel
def segment_pixels(
    images: wp.array2d(dtype=float),
    directions: wp.array(dtype=wp.vec3),
    threshold: float,
    outlier_factor: float,
    outlier_floor: float,
    nonnegative: int,
    max_iterations: int,
    min_valid: int,
    floor: float,
    offset: float,
    write_diffuse: int,
    diffuse: wp.array2d(dtype=float),
    specular: wp.array2d(dtype=float),
    lambert: wp.array(dtype=wp.vec4),
    status: wp.array(dtype=wp.vec2i),
):
    """One (pixel, channel) column q of ``images`` (lights, columns): D (where ``write_diffuse``: D = I - S),
    S, the fit, and (valid lights, iterations)."""
    q = wp.tid()
    lights = images.shape[0]
    valid = int(0)
    total = float(0.0)
    for i in range(lights):
        value = images[i, q]
        total += value
        if value >= threshold:
            valid += 1
    if valid < min_valid:
        for i in range(lights):
            if write_diffuse != 0:
                diffuse[i, q] = images[i, q]
            specular[i, q] = 0.0
        lambert[q] = wp.vec4(0.0, 0.0, 0.0, total / float(lights))
        status[q] = wp.vec2i(valid, 0)
        return

    # the current set is the one defined by (set_fit, set_limit); limit -1 = every valid light
    set_fit = wp.vec4()
    set_limit = float(-1.0)
    fit = _solve(images, directions, q, threshold, set_fit, set_limit, nonnegative)
    iterations = int(1)
    while iterations < max_iterations and not wp.isnan(fit[0]):
        largest = float(0.0)
        for i in range(lights):
            value = images[i, q]
            if value >= threshold:
                largest = wp.max(largest, wp.abs(value - _lambert(directions[i], fit)))
        median = _median_residual(images, directions, q, threshold, fit, valid, largest)
        limit = wp.max(outlier_factor * median, outlier_floor)
        kept = int(0)
        changed = int(0)
        for i in range(lights):
            value = images[i, q]
            now = _in_set(value, directions[i], threshold, fit, limit)
            kept += now
            if now != _in_set(value, directions[i], threshold, set_fit, set_limit):
                changed = 1
        if changed == 0 or kept < min_valid:
            break
        refit = _solve(images, directions, q, threshold, fit, limit, nonnegative)
        if wp.isnan(refit[0]):
            break
        set_fit = fit
        set_limit = limit
        fit = refit
        iterations += 1

    if wp.isnan(fit[0]):  # no usable fit: all diffuse, like a pixel with too few lights
        for i in range(lights):
            if write_diffuse != 0:
                diffuse[i, q] = images[i, q]
            specular[i, q] = 0.0
        lambert[q] = wp.vec4(0.0, 0.0, 0.0, total / float(lights))
        status[q] = wp.vec2i(0, iterations)
        return
    for i in range(lights):
        value = images[i, q]
        model = wp.max(_lambert(directions[i], fit), floor) + offset
        d = wp.min(value, model)
        if write_diffuse != 0:
            diffuse[i, q] = d
        specular[i, q] = value - d
    lambert[q] = fit
    status[q] = wp.vec2i(valid, iterations)


@wp.kernel
def luminance(
    specular: wp.array3d(dtype=float),
    weights: wp.vec3,
    channels: int,
    out: wp.array2d(dtype=float),
):
    """out[light, pixel] = weighted sum of the pixel's channels (the channel axis is innermost)."""
    light, pixel = wp.tid()
    if channels == 1:
        out[light, pixel] = specular[light, pixel, 0]
    else:
        out[light, pixel] = (weights[0] * specular[light, pixel, 0] + weights[1] * specular[light, pixel, 1]
                             + weights[2] * specular[light, pixel, 2])


@wp.kernel
def count_non_finite(values: wp.array2d(dtype=float), count: wp.array(dtype=wp.int32)):
    """count[0] += the values that are not finite."""
    i, j = wp.tid()
    if not wp.isfinite(values[i, j]):
        wp.atomic_add(count, 0, 1)


@wp.kernel
def shrink_by(images: wp.array4d(dtype=float), factor: int, first_row: int, out: wp.array4d(dtype=float)):
    """out[i, first_row + r, c, k]: the mean of channel k of images[i]'s ``factor`` x ``factor`` pixels
    from (r f, c f) (an area average by a whole factor, summed in float64)."""
    i, r, c, k = wp.tid()
    total = wp.float64(0.0)
    for dy in range(factor):
        for dx in range(factor):
            total += wp.float64(images[i, r * factor + dy, c * factor + dx, k])
    out[i, first_row + r, c, k] = wp.float32(total / wp.float64(factor * factor))


def _shrunk_into(band: wp.array, factor: int, first_row: int, out: wp.array) -> None:
    """``shrink_by`` of an (n, rows, W[, C]) device band into rows ``first_row`` on of ``out`` (n, H / f, W / f[,
    C])."""
    four = band if band.ndim == 4 else band.reshape(band.shape + (1,))
    target = out if out.ndim == 4 else out.reshape(out.shape + (1,))
    wp.launch(shrink_by, dim=(four.shape[0], four.shape[1] // factor, four.shape[2] // factor, four.shape[3]),
              inputs=[four, factor, first_row],
              outputs=[target], device=band.device)


class Segmentation:
    """Result of ``segment``: device arrays shaped like the input stack, plus the per-pixel fit
    (``segment_in_bands``: NumPy arrays; ``host_array`` gives either as NumPy).

    Attributes:
        diffuse, specular: (n, H, W) or (n, H, W, C) float32 Warp arrays, D and S (D + S = I); diffuse
            None where not kept (``keep_diffuse``).
        specular_luminance: (n, H, W) float32, the fitting target of estimation: a Warp array from
            ``segment``; from ``segment_in_bands`` NumPy, shrunk where it was given ``shrink_target``,
            or an (n, H / f, W / f) Warp array on the device where it was told to keep it there.
        lambert: (H, W, C, 4) float32 NumPy: nbar_x, nbar_y, nbar_z, k_a per pixel and channel.
        valid_lights: (H, W) int32 NumPy, the fewest valid lights over the pixel's channels.
        iterations: (H, W) int32 NumPy, the most refits over the pixel's channels.
        few_light_pixels: pixels left all diffuse because a channel had too few valid lights (or, rarely,
            no solvable fit).
        shrunk_images: (n, H / f, W / f[, C]) float32 NumPy, the images themselves shrunk on the device
            where ``segment_in_bands`` was asked to (``shrink_images``), else None.
        images: (n, H, W[, C]) float32 Warp array, the images as ``segment_in_bands`` sent them up where
            it was asked to keep them (``keep_images``) and one band held them all; else None.
    """

    def __init__(self, diffuse, specular, specular_luminance, lambert, valid_lights, iterations, min_valid,
                 shrunk_images=None, images=None):
        self.shrunk_images = shrunk_images
        self.images = images
        self.diffuse = diffuse
        self.specular = specular
        self.specular_luminance = specular_luminance
        self.lambert = lambert
        self.valid_lights = valid_lights
        self.iterations = iterations
        self.few_light_pixels = int(np.count_nonzero(valid_lights < min_valid))


def segment(images, directions, *, settings: SegmentationSettings | None = None, device=None,
            workers: int | None = None,
            keep_diffuse: bool = True) -> Segmentation:
    """Split every image into diffuse and specular parts in one launch over all pixels and channels.

    On the CPU the launch is split into one range of pixels per thread (Warp runs a CPU launch on one
    thread); every pixel is independent, so the result is the same for any split.

    Args:
        images: (n, H, W) or (n, H, W, C) linear radiance, NumPy (a band of rows of a stack will do:
            on CUDA each image's rows go up straight from host memory) or a float32 Warp array.
        directions: (n, 3) unit light directions (towards the light, camera space).
        settings: thresholds and iteration cap (``SegmentationSettings``).
        device: Warp device (default: the images' device, else Warp's default).
        workers: CPU threads (default: one per core); ignored on CUDA.
        keep_diffuse: False makes no diffuse images (``diffuse`` None; D = I - S where needed).
    """
    s = settings or SegmentationSettings()
    device = wp.get_device(device if device is not None else getattr(images, "device", None))
    shape = tuple(images.shape)
    if len(shape) not in (3, 4):
        raise InputError(f"images must have shape (n, H, W) or (n, H, W, C), got {shape}")
    directions = np.asarray(directions, dtype=np.float32)
    if directions.shape != (shape[0], 3):
        raise InputError(f"{shape[0]} images need ({shape[0]}, 3) light directions, got {directions.shape}")
    n, height, width = shape[:3]
    channels = shape[3] if len(shape) == 4 else 1
    if channels not in (1, 3):
        raise InputError(f"images must have 1 or 3 channels, got {channels}")
    columns = height * width * channels
    if isinstance(images, wp.array) and images.device == device and images.dtype == wp.float32:
        stack = images
    elif device.is_cuda and not isinstance(images, wp.array):
        stack = rows_up(np.asarray(images, dtype=np.float32), device)
    else:
        stack = wp.array(np.ascontiguousarray(to_host(images), dtype=np.float32), dtype=float, device=device)
    flat = stack.reshape((n, columns))
    if device.is_cuda:  # counted there: the images need not come down
        bad = wp.zeros(1, dtype=wp.int32, device=device)
        wp.launch(count_non_finite, dim=(n, columns), inputs=[flat], outputs=[bad], device=device)
        finite = int(bad.numpy()[0]) == 0
    else:  # host memory already: NumPy's threads
        finite = all_finite(flat.numpy())
    if not finite:
        raise InputError("the images have non-finite pixels; replace them first (ReflectanceField.load(..., "
                         "replace_nonfinite=True))")
    diffuse = wp.empty((n, columns) if keep_diffuse else (0, 0), dtype=float, device=device)
    specular = wp.empty((n, columns), dtype=float, device=device)
    lambert = wp.empty(columns, dtype=wp.vec4, device=device)
    status = wp.empty(columns, dtype=wp.vec2i, device=device)
    light_directions = wp.array(directions, dtype=wp.vec3, device=device)
    constants = [s.valid_threshold, s.outlier_factor, s.outlier_floor, int(s.nonnegative_ambient),
                 int(s.max_iterations), int(s.min_valid_lights), s.diffuse_floor, s.diffuse_offset, int(keep_diffuse)]

    def run(part: slice, _stop) -> None:
        outputs = [diffuse[:, part] if keep_diffuse else diffuse, specular[:, part], lambert[part], status[part]]
        wp.launch(segment_pixels, dim=part.stop - part.start, inputs=[flat[:, part], light_directions, *constants],
                  outputs=outputs, device=device)

    map_chunks(run, problem_chunks(columns, device, workers))
    target = wp.empty((n, height * width), dtype=float, device=device)
    wp.launch(luminance, dim=(n, height * width),
              inputs=[specular.reshape((n, height * width, channels)), wp.vec3(*LUMINANCE_WEIGHTS), channels],
              outputs=[target], device=device)
    counts = status.numpy().reshape(height, width, channels, 2)
    return Segmentation(
        diffuse=diffuse.reshape(shape) if keep_diffuse else None,
        specular=specular.reshape(shape),
        specular_luminance=target.reshape((n, height, width)),
        lambert=lambert.numpy().reshape(height, width, channels, 4),
        valid_lights=counts[..., 0].min(axis=2),
        iterations=counts[..., 1].max(axis=2),
        min_valid=int(s.min_valid_lights),
    )


def host_array(array) -> np.ndarray:
    """A ``Segmentation`` array as NumPy (banded segmentations already hold NumPy arrays)."""
    return to_host(array)


def band_rows(shape: tuple, device, *, share: float = DEVICE_SHARE, host_free: int | None = None,
              keep_specular: bool = True,
              keep_diffuse: bool = True, specular_bytes: int = 4, target_share: float = 1.0) -> int:
    """Rows of an (n, H, W[, C]) stack one ``segment`` launch may take on ``device``: all of them where
    the images, the specular part, the diffuse part where kept and the specular luminance (float32)
    take at most ``share`` of the free memory, else as many as do (at least one). On CUDA: the
    device's free memory (a band's float16 copy of its specular part, where the host keeps it so, is made
    after its images are freed), less the specular luminance ``segment_in_bands`` keeps there whole
    (``target_share`` of it: 1 / f^2 shrunk by f). On the CPU: ``host_free`` bytes (the host's
    available memory; None: all rows), less what ``segment_in_bands`` holds whole: the specular part
    (``specular_bytes`` a value) and the diffuse part where kept, and the specular luminance
    (``target_share`` of it where it is kept shrunk)."""
    n, height, width = shape[:3]
    channels = shape[3] if len(shape) == 4 else 1
    device = wp.get_device(device)
    row_bytes = 4 * n * width * (channels * (2 + int(keep_diffuse)) + 1)  # images, specular, diffuse; luminance
    if device.is_cuda:
        budget = share * max(device.free_memory - 4 * n * height * width * target_share, 0)
    elif host_free is None or row_bytes * height <= share * host_free:
        return height
    else:
        held = (n * height * width
                * (channels * (specular_bytes * int(keep_specular) + 4 * int(keep_diffuse)) + 4 * target_share))
        budget = share * max(host_free - held, 0)
    return int(max(1, min(height, budget // row_bytes)))


def segment_in_bands(images: np.ndarray, directions, *, rows: int, settings: SegmentationSettings | None = None,
                     device=None,
                     workers: int | None = None, keep_specular: bool = True, keep_diffuse: bool = True,
                     specular_dtype=np.float32, shrink_target: Callable[[np.ndarray], np.ndarray] | None = None,
                     target_rows: int = 1, shrink_factor: int = 1, target_on_device: bool = False,
                     shrink_images: bool = False,
                     keep_images: bool = False) -> Segmentation:
    """``segment`` of the (n, H, W[, C]) NumPy ``images`` ``rows`` rows at a time, for stacks whose arrays
    do not fit the device (or the host) at once (``band_rows``): the same values (every pixel is
    independent), in host NumPy arrays. Each band goes up and its parts come down an image's rows at
    a time, straight between the stack and the device (``rows_up``, ``rows_down``).

    Args:
        keep_specular, keep_diffuse: False keeps no specular / diffuse images (None).
        specular_dtype: The kept specular images' type (float16 halves them; the luminance the
            Gaussians are fitted to is computed from the float32 values either way).
        shrink_target: Shrinks a band's (n, rows, W) specular luminance to (n, rows / target_rows, w):
            an area average whose output rows each cover ``target_rows`` input rows, so that the
            bands (made a multiple of ``target_rows``) shrink to exactly the whole stack's shrunk rows.
            The specular luminance is then held only shrunk.
        shrink_factor, target_on_device: The specular luminance kept on the device, shrunk there by
            this whole factor of both sides (an area average, ``shrink_by``; 1 keeps it as it is) band by
            band: ``specular_luminance`` is then an (n, H / f, W / f) device array (bands a multiple of
            f rows). A factor above 1 keeps it there without ``target_on_device``.
        shrink_images: With ``shrink_factor``: the images themselves shrunk there too, as each band is
            up, into the host array ``shrunk_images`` (no pass over the whole stack on the host).
        keep_images: Where one band holds every row on a CUDA device, the images as they went up are
            kept there (``images``) for later stages to read instead of sending them up again.
    """
    images = np.asarray(images)
    shape = images.shape
    if len(shape) not in (3, 4):
        raise InputError(f"images must have shape (n, H, W) or (n, H, W, C), got {shape}")
    n, height, width = shape[:3]
    device = wp.get_device(device)
    rows = max(1, int(rows))
    factor = int(shrink_factor)
    on_device = target_on_device or factor > 1
    if factor < 1 or (on_device and (shrink_target is not None or height % factor or width % factor)):
        raise ValueError(f"a {width}x{height} stack does not shrink by {factor} on the device (whole factors, not "
                         f"with shrink_target)")
    if shrink_target is not None:
        if height % target_rows:
            raise ValueError(f"{height} rows do not shrink by whole bands of {target_rows}")
        rows = max(target_rows, rows // target_rows * target_rows)
    if factor > 1:
        rows = max(factor, rows // factor * factor)
    specular = mapped_empty(shape, specular_dtype) if keep_specular else None
    diffuse = mapped_empty(shape, np.float32) if keep_diffuse else None
    shrunk_images = shrunk_band = None
    if on_device:
        target = wp.empty((n, height // factor, width // factor), dtype=float, device=device)
        if shrink_images and factor > 1:
            shrunk_images = mapped_empty((n, height // factor, width // factor) + shape[3:], np.float32)
    else:
        target = mapped_empty((n, height, width), np.float32) if shrink_target is None else None
    lambert, valid, iterations = None, np.empty((height, width), np.int32), np.empty((height, width), np.int32)
    kept_images = None
    minimum = int((settings or SegmentationSettings()).min_valid_lights)
    # the float32 stack's bytes: each band's transfers staged where the stack's make it pay
    whole = int(np.prod(shape)) * 4
    for top in range(0, height, rows):
        band = slice(top, min(top + rows, height))
        band_images = rows_up(np.asarray(images[:, band], np.float32), device, whole_bytes=whole)
        part = segment(band_images, directions, settings=settings, device=device, workers=workers,
                       keep_diffuse=keep_diffuse)
        if shrunk_images is not None:
            low = slice(top // factor, band.stop // factor)
            if shrunk_band is None or shrunk_band.shape[1] != low.stop - low.start:
                shrunk_band = wp.empty((n, low.stop - low.start) + shrunk_images.shape[2:], dtype=float, device=device)
            _shrunk_into(band_images, factor, 0, shrunk_band)
            rows_down(shrunk_band, shrunk_images[:, low], whole_bytes=whole)
        if keep_images and device.is_cuda and band == slice(0, height):
            kept_images = band_images
        del band_images
        if specular is not None:
            _down(part.specular, specular[:, band], whole)
        if diffuse is not None:
            _down(part.diffuse, diffuse[:, band], whole)
        if on_device:
            _shrunk_into(part.specular_luminance, factor, top // factor, target)
        elif shrink_target is None:
            _down(part.specular_luminance, target[:, band], whole)
        else:
            shrunk = shrink_target(to_host(part.specular_luminance))
            if target is None:
                target = np.empty((n, height // target_rows, shrunk.shape[2]), np.float32)
            target[:, top // target_rows : band.stop // target_rows] = shrunk
        if lambert is None:
            lambert = np.empty((height,) + part.lambert.shape[1:], np.float32)
        lambert[band], valid[band], iterations[band] = part.lambert, part.valid_lights, part.iterations
        del part
    return Segmentation(diffuse, specular, target, lambert, valid, iterations, minimum, shrunk_images, kept_images)


def _down(array: wp.array, out: np.ndarray, whole_bytes: int = 0) -> None:
    """A band's part into its rows of a host stack: straight from a CUDA device, an image's rows at a time,
    where the types agree (a float16 stack: the part made float16 there first, half the bytes to bring
    down; staged as ``rows_down`` says of ``whole_bytes``, the stack's); else through a host copy."""
    if array.device.is_cuda and out.dtype == np.float16 and array.dtype == wp.float32:
        array = as_half(array)
    if array.device.is_cuda and out.dtype == wp.dtype_to_numpy(array.dtype):
        rows_down(array, out, whole_bytes=whole_bytes)
        return
    values = to_host(array)
    # finite, as as_half keeps them (the part is dropped after)
    if out.dtype == np.float16 and values.dtype != np.float16:
        values = np.clip(values, -float(HALF_MAX), float(HALF_MAX), out=values if values.flags.writeable else None)
    out[...] = values
