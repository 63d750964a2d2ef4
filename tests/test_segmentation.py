"""Segmentation kernel against a float64 NumPy reference and against the renderer's ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warp_highlights.fit.estimation import psnr
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.kernels.segmentation import (
    _MEDIAN_BISECTIONS,
    _lambert,
    _median_residual,
    band_rows,
    host_array,
    segment,
    segment_in_bands,
)
from warp_highlights.model.config import SegmentationSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet


def reference_fit(rows: np.ndarray, values: np.ndarray, nonnegative: bool) -> np.ndarray:
    """Least-squares (nbar, k_a); with ``nonnegative``, the minimum under k_a >= 0 (scipy's bounded solver)."""
    if not nonnegative:
        return np.linalg.lstsq(rows, values, rcond=None)[0]
    from scipy.optimize import lsq_linear

    bounds = (np.array([-np.inf, -np.inf, -np.inf, 0.0]), np.full(4, np.inf))
    return lsq_linear(rows, values, bounds=bounds, method="bvls", tol=1e-12).x


def reference_segment(samples: np.ndarray, directions: np.ndarray, s: SegmentationSettings):
    """Float64 per-pixel reference of the segmentation (docs/method.md, Fitting step 1) for one column of samples
    (n,)."""
    rows = np.concatenate([directions, np.ones((len(directions), 1))], axis=1)
    valid = samples >= s.valid_threshold
    if valid.sum() < s.min_valid_lights:
        return samples.copy(), np.zeros_like(samples), None
    current = valid
    fit = reference_fit(rows[current], samples[current], s.nonnegative_ambient)
    for _ in range(s.max_iterations - 1):
        residual = np.abs(samples - rows @ fit)
        limit = s.outlier_factor * np.median(residual[valid])
        kept = valid & (residual <= limit)
        if np.array_equal(kept, current) or kept.sum() < s.min_valid_lights:
            break
        current = kept
        fit = reference_fit(rows[current], samples[current], s.nonnegative_ambient)
    model = np.maximum(rows @ fit, s.diffuse_floor) + s.diffuse_offset
    diffuse = np.minimum(samples, model)
    return diffuse, samples - diffuse, fit


def synthetic_columns(rng, count: int, lights: int):
    """Lambertian columns with ambient, attached shadows, cast-shadow dropouts and specular spikes."""
    directions = LightSet.fibonacci_sphere(lights).directions
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size=count)
    ambient = rng.uniform(0.0, 0.05, size=count)
    shading = np.maximum(directions @ normals.T, 0.0) * albedo + ambient  # (lights, count)
    shadowed = rng.random(shading.shape) < 0.08
    shading[shadowed] = ambient[np.nonzero(shadowed)[1]]
    spikes = rng.random(shading.shape) < 0.06
    shading[spikes] += rng.uniform(0.3, 2.0, size=spikes.sum())
    return shading.astype(np.float32), directions


@pytest.mark.parametrize("nonnegative", [True, False])
def test_kernel_matches_float64_reference(device, nonnegative):
    rng = np.random.default_rng(3)
    settings = SegmentationSettings(nonnegative_ambient=nonnegative)
    columns, directions = synthetic_columns(rng, 200, 60)
    seg = segment(columns.reshape(60, 10, 20), directions, settings=settings, device=device)
    if nonnegative:
        assert seg.lambert[..., 3].min() >= 0.0
    diffuse = seg.diffuse.numpy().reshape(60, 200)
    specular = seg.specular.numpy().reshape(60, 200)
    lambert = seg.lambert.reshape(200, 4)
    agree = 0
    for q in range(200):
        _ref_d, ref_s, ref_fit = reference_segment(columns[:, q].astype(np.float64), directions, settings)
        np.testing.assert_allclose(diffuse[:, q] + specular[:, q], columns[:, q], atol=1e-6)
        if np.allclose(specular[:, q], ref_s, atol=2e-3):
            agree += 1
            if ref_fit is not None:
                np.testing.assert_allclose(lambert[q], ref_fit, atol=2e-3)
    # the median is a float32 bisection: a residual within float32 resolution of the limit may flip
    assert agree >= 196, f"only {agree} of 200 columns match the float64 reference"


@wp.func
def _bisected_rank(images: wp.array2d(dtype=float), directions: wp.array(dtype=wp.vec3), q: int, threshold: float,
                   fit: wp.vec4, rank: int,
                   largest: float) -> float:
    """The rank-th smallest residual by one halving a pass (the kernel's former median, kept as the reference)."""
    lo = float(0.0)
    hi = largest
    for _ in range(_MEDIAN_BISECTIONS):
        mid = 0.5 * (lo + hi)
        below = int(0)
        for i in range(images.shape[0]):
            value = images[i, q]
            if value >= threshold and wp.abs(value - _lambert(directions[i], fit)) <= mid:
                below += 1
        if below > rank:
            hi = mid
        else:
            lo = mid
    return hi


@wp.kernel
def _medians(images: wp.array2d(dtype=float), directions: wp.array(dtype=wp.vec3), fits: wp.array(dtype=wp.vec4),
             threshold: float,
             together: wp.array(dtype=float), apart: wp.array(dtype=float), residuals: wp.array2d(dtype=float),
             valid: wp.array(dtype=int)):
    q = wp.tid()
    fit = fits[q]
    count = int(0)
    largest = float(0.0)
    for i in range(images.shape[0]):
        value = images[i, q]
        residual = wp.abs(value - _lambert(directions[i], fit))
        residuals[i, q] = residual
        if value >= threshold:
            count += 1
            largest = wp.max(largest, residual)
    valid[q] = count
    together[q] = _median_residual(images, directions, q, threshold, fit, count, largest)
    apart[q] = 0.5 * (_bisected_rank(images, directions, q, threshold, fit, (count - 1) // 2, largest)
                      + _bisected_rank(images, directions, q, threshold, fit, count // 2, largest))


def test_median_two_halvings_a_pass_equals_one_a_pass_and_the_exact_median(device):
    """The kernel's median (both ranks, two halvings a pass) is bit for bit the one-halving-a-pass bisection,
    and within float32 resolution of NumPy's median of the same residuals."""
    rng = np.random.default_rng(11)
    columns, directions = synthetic_columns(rng, 500, 61)
    # odd and even valid counts, ties at zero
    columns[:, :40] = np.where(rng.random((61, 40)) < 0.5, 0.0, columns[:, :40])
    fits = np.concatenate([rng.normal(size=(500, 3)) * 0.5, rng.uniform(0.0, 0.1, (500, 1))], axis=1).astype(np.float32)
    threshold = SegmentationSettings().valid_threshold
    together, apart = wp.zeros(500, dtype=float, device=device), wp.zeros(500, dtype=float, device=device)
    residuals, valid = wp.zeros((61, 500), dtype=float, device=device), wp.zeros(500, dtype=int, device=device)
    wp.launch(_medians, dim=500, inputs=[wp.array(columns, dtype=float, device=device),
                                         wp.array(directions.astype(np.float32), dtype=wp.vec3, device=device),
                                         wp.array(fits, dtype=wp.vec4, device=device), threshold],
              outputs=[together, apart, residuals, valid], device=device)
    assert together.numpy().tobytes() == apart.numpy().tobytes()
    counts = valid.numpy()
    assert len(set(counts % 2)) == 2  # both parities of the valid count were tried
    residual, kept = residuals.numpy(), columns >= threshold
    exact = np.array([np.median(residual[kept[:, q], q].astype(np.float64)) if counts[q] else 0.0 for q in range(500)])
    largest = np.array([residual[kept[:, q], q].max() if counts[q] else 0.0 for q in range(500)])
    error = np.abs(together.numpy() - exact)
    # each rank within one final interval
    assert np.all(error <= 2.0 * 2.0**-_MEDIAN_BISECTIONS * largest + 2e-7 * exact), error.max()


def test_any_split_over_cpu_threads_gives_the_same_result():
    rng = np.random.default_rng(5)
    columns, directions = synthetic_columns(rng, 3 * 77, 40)
    images = columns.reshape(40, 11, 7, 3)
    one = segment(images, directions, device="cpu", workers=1)
    for workers in (2, 5):
        split = segment(images, directions, device="cpu", workers=workers)
        for name in ("diffuse", "specular", "specular_luminance"):
            np.testing.assert_array_equal(getattr(split, name).numpy(), getattr(one, name).numpy(), err_msg=name)
        for name in ("lambert", "valid_lights", "iterations"):
            np.testing.assert_array_equal(getattr(split, name), getattr(one, name), err_msg=name)


def test_row_bands_give_the_whole_stack_s_segmentation(device):
    """``segment_in_bands`` (any band height, the last band shorter) = ``segment`` of the whole stack,
    bit for bit, in host arrays; without the diffuse part when not asked to keep it."""
    rng = np.random.default_rng(6)
    columns, directions = synthetic_columns(rng, 3 * 13 * 9, 40)
    images = columns.reshape(40, 13, 9, 3)
    whole = segment(images, directions, device=device)
    for rows in (1, 4, 13, 50):
        banded = segment_in_bands(images, directions, rows=rows, device=device)
        for name in ("diffuse", "specular", "specular_luminance"):
            assert isinstance(getattr(banded, name), np.ndarray)
            np.testing.assert_array_equal(getattr(banded, name), host_array(getattr(whole, name)),
                                          err_msg=f"{name}, {rows} rows")
        for name in ("lambert", "valid_lights", "iterations"):
            np.testing.assert_array_equal(getattr(banded, name), getattr(whole, name), err_msg=name)
        assert banded.few_light_pixels == whole.few_light_pixels
    assert segment_in_bands(images, directions, rows=5, device=device, keep_diffuse=False).diffuse is None


def test_no_diffuse_part_made_leaves_the_rest_as_it_was(device):
    rng = np.random.default_rng(5)
    columns, directions = synthetic_columns(rng, 3 * 6 * 7, 30)
    images = columns.reshape(30, 6, 7, 3)
    whole, lean = (segment(images, directions, device=device),
                   segment(images, directions, device=device, keep_diffuse=False))
    assert lean.diffuse is None
    for name in ("specular", "specular_luminance"):
        np.testing.assert_array_equal(host_array(getattr(lean, name)), host_array(getattr(whole, name)))
    np.testing.assert_array_equal(lean.lambert, whole.lambert)


def test_shrink_by_is_the_float64_mean_of_each_block(device):
    import warp as wp

    from warp_highlights.kernels.segmentation import shrink_by

    values = np.random.default_rng(8).uniform(0, 3, (3, 12, 18)).astype(np.float32)
    out = wp.zeros((3, 8, 6), dtype=float, device=device)
    four = out.reshape((3, 8, 6, 1))
    # rows 0..3
    wp.launch(shrink_by, dim=(3, 4, 6, 1), inputs=[wp.array(values[:, 4:, :, None], device=device), 2, 0],
              outputs=[four], device=device)
    wp.launch(shrink_by, dim=(3, 4, 6, 1), inputs=[wp.array(values[:, :12, :, None], device=device), 3, 4],
              outputs=[four], device=device)
    reference = values.astype(np.float64)
    np.testing.assert_allclose(out.numpy()[:, :4], reference[:, 4:12, :12].reshape(3, 4, 2, 6, 2).mean(axis=(2, 4)),
                               rtol=1e-7)
    np.testing.assert_allclose(out.numpy()[:, 4:], reference[:, :12, :18].reshape(3, 4, 3, 6, 3).mean(axis=(2, 4)),
                               rtol=1e-7)


def test_bands_keep_the_luminance_on_the_device_shrunk_there(device):
    """``target_on_device`` / ``shrink_factor``: the luminance (and with ``shrink_images`` the images) made
    and shrunk on the device band by band (bands of whole factors, the last one shorter) is the whole
    stack's, shrunk to its block means; a factor that does not divide the size is refused."""
    import warp as wp

    rng = np.random.default_rng(9)
    columns, directions = synthetic_columns(rng, 3 * 12 * 8, 30)
    images = columns.reshape(30, 12, 8, 3)
    whole = host_array(segment(images, directions, device=device).specular_luminance)
    kept = segment_in_bands(images, directions, rows=5, device=device, target_on_device=True)
    assert isinstance(kept.specular_luminance, wp.array)
    np.testing.assert_array_equal(kept.specular_luminance.numpy(), whole)
    expected = whole.astype(np.float64).reshape(30, 6, 2, 4, 2).mean(axis=(2, 4))
    shrunk = images.astype(np.float64).reshape(30, 6, 2, 4, 2, 3).mean(axis=(2, 4))
    for rows in (1, 5, 12):
        banded = segment_in_bands(images, directions, rows=rows, device=device, shrink_factor=2,
                                  shrink_images=rows == 5)
        assert isinstance(banded.specular_luminance, wp.array)
        np.testing.assert_allclose(banded.specular_luminance.numpy(), expected, rtol=1e-6, atol=1e-7)
        if rows == 5:  # the images themselves, shrunk as each band went up
            np.testing.assert_allclose(banded.shrunk_images, shrunk, rtol=1e-6)
        else:
            assert banded.shrunk_images is None
    with pytest.raises(ValueError, match="does not shrink"):
        segment_in_bands(images, directions, rows=4, device=device, shrink_factor=5)


def test_non_finite_pixels_are_counted_on_the_device(device):
    import warp as wp

    from warp_highlights.kernels.segmentation import count_non_finite

    values = np.ones((4, 50), np.float32)
    values[1, 3], values[2, 7], values[3, 49] = np.nan, np.inf, -np.inf
    count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(count_non_finite, dim=values.shape, inputs=[wp.array(values, device=device)], outputs=[count],
              device=device)
    assert int(count.numpy()[0]) == 3


def test_bands_short_of_memory_keep_float16_specular_parts_and_shrink_the_luminance_band_by_band():
    """With the specular part kept as float16 and the specular luminance shrunk band by band (bands made
    whole multiples of the shrink), the parts are the whole stack's: the luminance shrunk as a whole,
    the specular part rounded to float16."""
    from warp_highlights.io.resample import resize_stack

    rng = np.random.default_rng(7)
    columns, directions = synthetic_columns(rng, 3 * 16 * 10, 40)
    images = columns.reshape(40, 16, 10, 3)
    whole = segment(images, directions, device="cpu")
    shrunk = resize_stack(host_array(whole.specular_luminance), 5, 4)
    for rows in (1, 5, 8, 16):
        banded = segment_in_bands(images, directions, rows=rows, device="cpu", keep_diffuse=False,
                                  specular_dtype=np.float16,
                                  shrink_target=lambda band: resize_stack(band, 5, band.shape[1] // 4), target_rows=4)
        np.testing.assert_array_equal(banded.specular_luminance, shrunk, err_msg=f"{rows} rows")
        assert banded.specular.dtype == np.float16
        np.testing.assert_array_equal(banded.specular, host_array(whole.specular).astype(np.float16))
    with pytest.raises(ValueError, match="whole bands"):
        segment_in_bands(images, directions, rows=4, device="cpu", shrink_target=lambda band: band, target_rows=3)
    assert segment_in_bands(images, directions, rows=4, device="cpu", keep_specular=False).specular is None


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_the_images_sent_up_in_one_band_are_kept_where_asked(device):
    """``keep_images``: on CUDA, where one band holds every row, the images as they went up (bit for bit);
    in several bands, on the CPU, or unasked: None. The parts are the same either way."""
    if device.startswith("cuda") and not wp.is_cuda_available():
        pytest.skip("CUDA devices only")
    rng = np.random.default_rng(5)
    directions = LightSet.fibonacci_sphere(12).directions
    for images in (rng.uniform(0.0, 2.0, (12, 8, 10, 3)).astype(np.float32),
                   rng.uniform(0.0, 2.0, (12, 8, 10)).astype(np.float32)):
        whole = segment_in_bands(images, directions, rows=8, device=device, keep_images=True)
        assert (whole.images is not None) == device.startswith("cuda")
        if whole.images is not None:
            np.testing.assert_array_equal(whole.images.numpy(), images)
        assert segment_in_bands(images, directions, rows=3, device=device, keep_images=True).images is None
        plain = segment_in_bands(images, directions, rows=8, device=device)
        assert plain.images is None
        np.testing.assert_array_equal(plain.specular, whole.specular)
        np.testing.assert_array_equal(plain.specular_luminance, whole.specular_luminance)


def test_band_rows_fit_the_device_s_free_memory():
    import warp as wp

    assert band_rows((1000, 1080, 1920, 3), "cpu") == 1080  # the host's free memory not given: no bands
    # images, diffuse, specular, luminance a row; specular and luminance whole
    row_bytes, held = 4 * 100 * 3840 * 10, 4 * 100 * 2160 * 3840 * 4
    assert band_rows((100, 2160, 3840, 3), "cpu", host_free=2160 * row_bytes * 2) == 2160  # fits in half of it
    # a 100-light 4K capture on a 24 GiB machine
    rows = band_rows((100, 2160, 3840, 3), "cpu", host_free=24 << 30, keep_diffuse=False)
    row_bytes = 4 * 100 * 3840 * 7  # no diffuse part made: images, specular, luminance
    assert rows * row_bytes <= 0.5 * ((24 << 30) - held) < (rows + 1) * row_bytes
    assert band_rows((100, 2160, 3840, 3), "cpu", host_free=held // 2) == 1  # at least one row
    if wp.is_cuda_available():
        free = wp.get_device("cuda:0").free_memory
        rows = band_rows((1000, 1080, 1920, 3), "cuda:0", share=0.5)
        budget = 0.5 * (free - 4 * 1000 * 1080 * 1920)  # less the luminance kept there whole
        assert rows * 4 * 1000 * 1920 * 10 <= budget < (rows + 1) * 4 * 1000 * 1920 * 10 or rows == 1080


def test_pure_lambertian_pixels_have_no_specular_and_recover_the_normal():
    directions = LightSet.fibonacci_sphere(50).directions
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    shading = (np.maximum(directions @ normal, 0.0) * 0.7 + 0.02).astype(np.float32)
    seg = segment(np.tile(shading[:, None, None], (1, 2, 3)), directions, device="cpu")
    fit = seg.lambert[0, 0, 0]
    np.testing.assert_allclose(fit[:3] / np.linalg.norm(fit[:3]), normal, atol=0.02)
    assert seg.specular.numpy().max() < 1e-5
    # rounding noise is not an outlier: an exact Lambertian pixel is done after one refit at most
    assert seg.iterations.max() <= 2


def test_dark_pixels_are_all_diffuse_and_counted():
    directions = LightSet.fibonacci_sphere(20).directions
    images = np.full((20, 3, 4), 0.01, dtype=np.float32)  # below the 0.05 threshold everywhere
    images[:, 0, 0] = np.maximum(directions @ np.array([0.0, 0.0, 1.0]), 0.0) + 0.1
    seg = segment(images, directions, device="cpu")
    assert seg.few_light_pixels == 11
    np.testing.assert_array_equal(seg.specular.numpy()[:, 1:, :], 0.0)
    np.testing.assert_array_equal(seg.diffuse.numpy()[:, 1:, :], images[:, 1:, :])


def test_colour_channels_are_segmented_independently():
    rng = np.random.default_rng(9)
    columns, directions = synthetic_columns(rng, 3 * 12, 40)
    colour = columns.reshape(40, 3, 4, 3)
    seg = segment(colour, directions, device="cpu")
    for channel in range(3):
        alone = segment(np.ascontiguousarray(colour[..., channel]), directions, device="cpu")
        np.testing.assert_array_equal(seg.specular.numpy()[..., channel], alone.specular.numpy())
    weights = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    np.testing.assert_allclose(seg.specular_luminance.numpy(), seg.specular.numpy() @ weights, atol=1e-6)


def test_recovers_the_renderers_specular_ground_truth(small_donut):
    data = ReflectanceField.load(small_donut, progress=False)
    seg = segment(data.images, data.lights.directions, device="cpu")
    n = data.light_count
    value = psnr(seg.specular.numpy().reshape(n, data.height, -1), data.specular.reshape(n, data.height, -1))
    # measured here (32 lights, 96x54): mean 52.6 dB, worst light 41.7 dB (64 lights at 240x135: mean
    # 57.0, worst 51.7); the floors leave about 4-5 dB of margin
    assert value.min() > 36.0 and value.mean() > 48.0, (value.min(), value.mean())


def test_bad_input():
    directions = LightSet.fibonacci_sphere(8).directions
    with pytest.raises(InputError, match="light directions"):
        segment(np.zeros((8, 4, 4), dtype=np.float32), directions[:5], device="cpu")
    with pytest.raises(InputError, match="shape"):
        segment(np.zeros((8, 4), dtype=np.float32), directions, device="cpu")
    with pytest.raises(InputError, match="channels"):
        segment(np.zeros((8, 4, 4, 2), dtype=np.float32), directions, device="cpu")
    bad = np.ones((8, 4, 4), dtype=np.float32)
    bad[3, 1, 1] = np.inf
    with pytest.raises(InputError, match="non-finite"):
        segment(bad, directions, device="cpu")


def _textured_shadowed_scene(seed: int = 3):
    """A bumped plane on a dome of lights: two-tone colour texture, a cast-shadow band, Blinn-Phong
    highlights (exponent 60). Returns (images, directions, true S), linear float32."""
    from warp_highlights.model.lights import LightSet

    rng = np.random.default_rng(seed)
    h, w = 24, 32
    lights = LightSet.fibonacci_sphere(120).directions
    lights = lights[lights[:, 2] > 0.15]
    yy, xx = np.mgrid[0:h, 0:w] / h
    normal = np.stack([0.4 * np.sin(6 * xx), 0.3 * np.cos(5 * yy), np.ones_like(xx)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    albedo = 0.25 + 0.5 * (rng.random((h, w, 3)) > 0.5) * rng.random(3)
    cos = np.clip(np.einsum("hwc,nc->nhw", normal, lights), 0, None)
    shadow = (xx[None] > 0.6) & (lights[:, 0] < -0.3)[:, None, None]
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    specular = (0.8 * np.clip(np.einsum("hwc,nc->nhw", normal, half), 0, None) ** 60 * ~shadow)[..., None] * np.ones(3)
    images = albedo[None] * cos[..., None] * ~shadow[..., None] + specular
    return images.astype(np.float32), lights, specular


@pytest.mark.parametrize("eight_bit", [False, True])
def test_segmentation_recovers_the_specular_part_of_a_textured_shadowed_scene(eight_bit):
    """Known S and D: S is recovered to 15% (relative L1; 8.5% measured on radiance, about the same
    from 8-bit sRGB), and less than 2% of S's energy shows up where there is no highlight (texture,
    shadow edges)."""
    from warp_highlights.io.images import linear_to_srgb, srgb_to_linear

    images, lights, truth = _textured_shadowed_scene()
    if eight_bit:  # as a JPEG/PNG capture stores it
        images = srgb_to_linear(np.round(linear_to_srgb(np.clip(images, 0, 1)) * 255) / 255).astype(np.float32)
        truth = np.minimum(truth, 1.0)
    found = segment(images, lights, device="cpu").specular.numpy()
    assert found.min() >= 0.0
    assert np.abs(found - truth).sum() / truth.sum() < 0.15
    weights = np.array([0.2126, 0.7152, 0.0722])
    no_highlight = truth @ weights < 1e-3
    assert (found @ weights)[no_highlight].sum() / (truth @ weights).sum() < 0.02


def test_float16_specular_parts_come_down_finite_and_rounded_as_numpy_rounds(device):
    """The specular part kept as float16 (on CUDA made so on the device, ``as_half``): the float32 part
    rounded as NumPy rounds, a value beyond the largest half clamped to it (never inf)."""
    rng = np.random.default_rng(11)
    columns, directions = synthetic_columns(rng, 3 * 8 * 6, 30)
    images = columns.reshape(30, 8, 6, 3)
    images[3, 2, 1] = 1e6  # a highlight brighter than a half holds
    whole = segment(images, directions, device=device)
    banded = segment_in_bands(images, directions, rows=3, device=device, keep_diffuse=False, specular_dtype=np.float16)
    assert host_array(whole.specular).max() > 65504  # the clamp is exercised
    expected = np.clip(host_array(whole.specular), -65504, 65504).astype(np.float16)
    assert banded.specular.dtype == np.float16 and np.isfinite(banded.specular).all()
    np.testing.assert_array_equal(banded.specular, expected)


def _sparse_dome_with_a_broad_lobe():
    """A bumped plane under 16 dome lights (rings of 8, 2 and 5 at 10, 30 and 50 degrees, and the zenith), as a
    sparse RTI dome is: a dark albedo that leaves most of the rim's samples under the valid threshold (8-11 lit
    samples a pixel), and a broad Blinn-Phong lobe (exponent 40) around the high lights. Returns (images (16, 6,
    6), lights, true S)."""
    def ring(elevation, count, phase):
        azimuth, e = np.radians(np.arange(count) * 360.0 / count + phase), np.radians(elevation)
        return np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.full(count, np.sin(e))], 1)

    lights = np.concatenate([ring(10, 8, 0), ring(30, 2, 45), ring(50, 5, 10), [[0.0, 0.0, 1.0]]])
    tilt = np.linspace(-0.15, 0.15, 6)
    normal = np.stack(np.broadcast_arrays(tilt[None, :], tilt[:, None], 1.0), -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    specular = 0.8 * np.clip(np.einsum("hwc,nc->nhw", normal, half), 0, None) ** 40
    images = 0.2 * np.clip(np.einsum("hwc,nc->nhw", normal, lights), 0, None) + 0.005 + specular
    return images.astype(np.float32), lights, specular


def test_a_nonnegative_ambient_keeps_a_sparse_dome_s_broad_highlight_specular(device):
    """With 8-11 lit samples a pixel, the free fit bends the normal up and the ambient below zero to take in
    the high lights' highlight; bounded at k_a >= 0 it cannot, and the highlight stays specular (the reason
    for ``SegmentationSettings.nonnegative_ambient``). Measured: 44% of the specular energy found free, 78%
    bounded."""
    images, lights, truth = _sparse_dome_with_a_broad_lobe()
    found = {}
    for nonnegative in (False, True):
        seg = segment(images, lights, settings=SegmentationSettings(nonnegative_ambient=nonnegative), device=device)
        found[nonnegative] = seg.specular.numpy().sum() / truth.sum()
        if nonnegative:
            assert seg.lambert[..., 3].min() >= 0.0
        else:
            assert np.median(seg.lambert[..., 3]) < -0.1  # the bent fit
    assert found[True] > 0.7 and found[False] < found[True] - 0.25, found


@pytest.mark.parametrize("nonnegative", [True, False])
def test_the_bound_on_the_ambient_matches_the_float64_reference(device, nonnegative):
    """Columns whose free fits have a negative ambient (the sparse dome's): the kernel against ``reference_segment``,
    whose bounded fit is scipy's bounded least squares."""
    images, lights, _ = _sparse_dome_with_a_broad_lobe()
    settings = SegmentationSettings(nonnegative_ambient=nonnegative)
    seg = segment(images, lights, settings=settings, device=device)
    columns = images.reshape(len(lights), -1)
    for q in range(columns.shape[1]):
        _, specular, fit = reference_segment(columns[:, q].astype(np.float64), lights, settings)
        # float32 normal equations: a set of lights at two elevations leaves n_z and k_a nearly collinear
        np.testing.assert_allclose(seg.specular.numpy().reshape(len(lights), -1)[:, q], specular, rtol=0.01, atol=2e-3)
        np.testing.assert_allclose(seg.lambert.reshape(-1, 4)[q], fit, atol=5e-3)
