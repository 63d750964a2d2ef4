"""Relighting kernels (kernels/interpolation.py, warp_highlights/relight/relighter.py) against float64 references."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import reference
from gaussian_cases import inside_params
from reference import render as reference_render
from warp_highlights.fit.paths import decide_paths
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.io.resample import (
    resample_image,
    resize_stack,
)
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.model.config import FitSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.field import DiffuseModel, HighlightField
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.relight.interpolation import interpolate_sets
from warp_highlights.relight.relighter import Relighter, face_edge_rows, relight_field

HEIGHT, WIDTH = 27, 48


def synthetic_field(lights: LightSet, *, capacity: int = 4, seed: int = 0, channels: int = 3,
                    diffuse_images: bool = False) -> HighlightField:
    """A field with random Gaussians, retargeted sets that move and turn them, and decided paths."""
    rng = np.random.default_rng(seed)
    n = len(lights)
    triangulation = SphericalTriangulation(lights.directions)
    edges = triangulation.directed_edges()
    estimated = inside_params(rng, n, capacity, HEIGHT, WIDTH, sigma_px=(1.0, 4.0))
    estimated.weight[:] = 1.0
    estimated.active[:, -1] = False  # a free slot in every set
    estimated.active[0] = False  # and one empty set
    retargeted = estimated.take(edges[:, 0])
    moved = rng.normal(scale=3.0 / HEIGHT, size=retargeted.mean.shape)
    retargeted.mean = retargeted.mean + moved
    retargeted.theta = retargeted.theta + rng.uniform(-1.2, 1.2, size=retargeted.theta.shape)
    retargeted.amplitude = retargeted.amplitude * rng.uniform(0.7, 1.3, size=retargeted.amplitude.shape)
    retargeted.sigma = retargeted.sigma * rng.uniform(0.8, 1.25, size=retargeted.sigma.shape)
    settings = FitSettings()
    decisions = decide_paths(estimated.take(edges[:, 0]), retargeted, settings.paths)
    lambert = rng.normal(scale=0.5, size=(HEIGHT, WIDTH, channels, 4)).astype(np.float32)
    lambert[..., 3] = np.abs(lambert[..., 3])
    images = rng.uniform(0, 1, size=(n, HEIGHT, WIDTH, channels)).astype(np.float16) if diffuse_images else None
    return HighlightField(
        lights=lights, triangulation=triangulation, width=WIDTH, height=HEIGHT, estimated=estimated,
        directed_edges=edges, retargeted=retargeted, path_delta=decisions.delta, path_centre=decisions.centre,
        settings=settings.to_dict(), report={}, diffuse=DiffuseModel(lambert=lambert, images=images),
    )


@pytest.fixture(scope="module")
def sphere_field():
    return synthetic_field(LightSet.fibonacci_sphere(24), diffuse_images=True)


@pytest.fixture(scope="module")
def dome_field():
    return synthetic_field(LightSet.fibonacci_dome(20, min_elevation_deg=15.0), seed=1)


def random_directions(rng, count: int) -> np.ndarray:
    directions = rng.normal(size=(count, 3))
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def render_numpy(sets: GaussianParams, height: int = HEIGHT, width: int = WIDTH) -> np.ndarray:
    return reference_render(sets, height, width, FitSettings().raster)


@pytest.mark.parametrize("which", ["sphere_field", "dome_field"])
def test_locate_kernel_matches_the_host_locate(which, request, device):
    field = request.getfixturevalue(which)
    relighter = Relighter(field, device=device)
    queries = random_directions(np.random.default_rng(3), 300)
    queries = np.concatenate([queries, field.lights.directions, 2.5 * field.triangulation.centroid_directions()])
    chunk = relighter.launch(queries, full=False)
    host = field.triangulation.locate(queries)
    faces = chunk.faces.numpy()
    weights = chunk.weights.numpy()
    assert np.array_equal(chunk.clamped.numpy() != 0, host.clamped)
    if which == "dome_field":
        assert host.clamped.sum() > 50  # the test covers directions outside the dome
    same = faces == host.faces
    assert same.mean() > 0.95  # only ties on shared edges and vertices may pick the other face
    np.testing.assert_allclose(weights[same], host.barycentric[same], atol=2e-6)
    # where another face was picked, the point lies on their shared boundary: same position either way
    corners = field.lights.directions[field.triangulation.faces]
    kernel_points = np.einsum("qk,qkc->qc", weights, corners[faces])
    host_points = np.einsum("qk,qkc->qc", host.barycentric, corners[host.faces])
    np.testing.assert_allclose(kernel_points, host_points, atol=2e-6)
    np.testing.assert_allclose(chunk.located.numpy(), host.directions, atol=1e-6)


@pytest.mark.parametrize("method", ["circular", "straight"])
def test_interpolated_sets_match_the_float64_reference(sphere_field, method, device):
    field = sphere_field
    queries = random_directions(np.random.default_rng(5), 64)
    relighter = Relighter(field, device=device)
    sets = relighter.interpolated_sets(queries, method=method)
    location = field.triangulation.locate(queries)
    expected = interpolate_sets(field, location.vertices, location.barycentric, method=method)
    drawn = expected.active & (expected.weight > 0)
    assert np.array_equal(sets.active, drawn)  # corners of weight 0 are left out, nothing else
    assert drawn.sum() > 200
    for name, tolerance in (("amplitude", 1e-5), ("mean", 2e-6), ("sigma", 1e-6), ("theta", 2e-5), ("weight", 1e-6)):
        np.testing.assert_allclose(getattr(sets, name)[drawn], getattr(expected, name)[drawn], atol=tolerance,
                                   err_msg=name)
    images = relighter.relight(queries, method=method, full=False).specular
    np.testing.assert_allclose(images, render_numpy(expected), atol=2e-4 * max(1.0, float(images.max())))


def test_circular_and_straight_differ_only_in_the_means(sphere_field):
    queries = random_directions(np.random.default_rng(6), 32)
    relighter = Relighter(sphere_field, device="cpu")
    circular = relighter.interpolated_sets(queries, method="circular")
    straight = relighter.interpolated_sets(queries, method="straight")
    for name in ("amplitude", "sigma", "theta", "weight", "active"):
        assert np.array_equal(getattr(circular, name), getattr(straight, name))
    gap = np.linalg.norm(circular.mean - straight.mean, axis=-1)[circular.active]
    assert gap.max() > 1e-3  # the paths turn, so arcs leave the chords


def test_arc_position_kernel_matches_the_path_identity(device):
    from warp_highlights.kernels.interpolation import arc_position
    from warp_highlights.model.arcs import circular_position, path_centre

    rng = np.random.default_rng(8)
    count = 500
    mean_a = rng.uniform(0, 1.5, size=(count, 2))
    mean_b = mean_a + rng.normal(scale=0.1, size=(count, 2))
    delta = rng.uniform(-np.pi, np.pi, size=count)
    delta[:20] = rng.uniform(-1e-5, 1e-5, size=20)  # straight paths
    fraction = rng.uniform(0, 1, size=count)
    fraction[-50:] = 1.0

    @wp.kernel
    def evaluate(a: wp.array(dtype=wp.vec2), b: wp.array(dtype=wp.vec2), d: wp.array(dtype=float),
                 t: wp.array(dtype=float), out: wp.array(dtype=wp.vec2)):
        i = wp.tid()
        out[i] = arc_position(a[i], b[i], d[i], t[i], 1.0e-4)

    arrays = [wp.array(x.astype(np.float32), dtype=dtype, device=device)
              for x, dtype in ((mean_a, wp.vec2), (mean_b, wp.vec2), (delta, float), (fraction, float))]
    out = wp.empty(count, dtype=wp.vec2, device=device)
    wp.launch(evaluate, dim=count, inputs=arrays, outputs=[out], device=device)
    got = out.numpy()
    np.testing.assert_allclose(got, circular_position(mean_a, mean_b, delta, fraction, 1e-4), atol=2e-6)
    # fraction 1 reaches mu_B; the arc keeps its distance to the centre O with R(delta)(mu_A - O) + O = mu_B
    np.testing.assert_allclose(got[-50:], mean_b[-50:], atol=2e-6)
    centre = path_centre(mean_a, mean_b, delta, 1e-4)
    curved = np.abs(delta) > 0.05
    radius_a = np.linalg.norm(mean_a - centre, axis=1)
    np.testing.assert_allclose(np.linalg.norm(got - centre, axis=1)[curved], radius_a[curved], rtol=1e-4, atol=2e-6)


def test_a_query_at_a_light_renders_that_lights_estimated_set(sphere_field, device):
    field = sphere_field
    relighter = Relighter(field, device=device)
    lights = np.flatnonzero(field.estimated.counts > 0)[:8]
    images = relighter.relight(field.lights.directions[lights], full=False).specular
    raster = Rasterizer(HEIGHT, WIDTH, settings=FitSettings().raster, device=device)
    expected = raster.render(GaussianBatch.from_numpy(field.estimated.take(lights), device=device,
                                                      requires_grad=False)).numpy()
    assert expected.max() > 0.1
    np.testing.assert_allclose(images, expected, rtol=1e-6, atol=1e-7)


def test_images_change_continuously_across_a_triangle_edge(sphere_field):
    field = sphere_field
    tri = field.triangulation
    relighter = Relighter(field, device="cpu")
    interior = [tuple(edge) for edge in tri.edges()]
    steps = []
    for a, b in interior[:12]:
        wa, wb = field.lights.directions[a], field.lights.directions[b]
        on_edge = (0.6 * wa + 0.4 * wb) / np.linalg.norm(0.6 * wa + 0.4 * wb)
        normal = np.cross(wa, wb) / np.linalg.norm(np.cross(wa, wb))
        offsets = np.array([-1e-3, -1e-6, 1e-6, 1e-3])
        queries = on_edge[None] + offsets[:, None] * normal[None]
        result = relighter.relight(queries, full=True)
        assert result.faces[1] != result.faces[2]  # the two queries straddle the edge
        near = np.abs(result.full[2] - result.full[1]).max()
        far = np.abs(result.full[3] - result.full[0]).max()
        steps.append((near, far))
    near, far = np.array(steps).T
    assert near.max() < 1e-3  # a 2e-6 rad step changes nothing visible...
    assert far.max() > 100 * near.max()  # ...while a 2e-3 rad step does: the image moves, it does not jump


def test_alpha_blend_is_exact(sphere_field, device):
    field = sphere_field
    rng = np.random.default_rng(11)
    specular = rng.uniform(0, 2, size=(field.light_count, HEIGHT, WIDTH)).astype(np.float32)
    images = rng.uniform(0, 2, size=(field.light_count, HEIGHT, WIDTH, 3)).astype(np.float32)
    relighter = Relighter(field, device=device, alpha_specular=specular, alpha_images=images, scale=0.5)
    queries = random_directions(rng, 40)
    result = relighter.relight(queries, method="alpha")
    vertices = field.triangulation.faces[result.faces]
    weights = result.barycentric.astype(np.float32)
    np.testing.assert_allclose(result.specular, np.einsum("qk,qkhw->qhw", weights, specular[vertices]), rtol=1e-6,
                               atol=1e-6)
    halves = images.astype(np.float16).astype(np.float32)  # full images are kept as float16 on the device
    np.testing.assert_allclose(result.full, 0.5 * np.einsum("qk,qkhwc->qhwc", weights, halves[vertices]), rtol=1e-6,
                               atol=1e-6)
    at_light = relighter.relight(field.lights.directions[3], method="alpha", full=False).specular
    np.testing.assert_allclose(at_light, specular[3], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("diffuse", ["lambert", "images", "none"])
def test_full_image_is_diffuse_plus_coloured_specular(sphere_field, diffuse, device):
    field = sphere_field
    colour = (1.0, 0.5, 0.25)
    relighter = Relighter(field, device=device, diffuse=diffuse, specular_colour=colour, scale=2.0)
    queries = random_directions(np.random.default_rng(12), 6)
    result = relighter.relight(queries)
    unit = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    if diffuse == "lambert":
        expected = np.stack([field.diffuse.lambertian(q) for q in unit])
    elif diffuse == "images":
        vertices = field.triangulation.faces[result.faces]
        stack = field.diffuse.images.astype(np.float32)
        expected = np.einsum("qk,qkhwc->qhwc", result.barycentric, stack[vertices])
    else:
        expected = np.zeros_like(result.full)
    expected = 2.0 * (expected + np.asarray(colour) * result.specular[..., None])
    np.testing.assert_allclose(result.full, expected, rtol=1e-5, atol=1e-5)


def _grown(stack: np.ndarray, width: int, height: int) -> np.ndarray:
    """Each image of ``stack`` resampled to ``width`` x ``height`` on the host, float64."""
    return np.stack([resample_image(image, width, height) for image in stack]).astype(np.float64)


@pytest.mark.parametrize("diffuse", ["lambert", "images", "none"])
def test_a_larger_output_composes_as_the_arrays_resampled_on_the_host(sphere_field, diffuse, device):
    """Relit at 2.5 x 3 times the field's size (the aspect ratio kept within a pixel) from the field's arrays
    at their own size: the Lambertian planes, the diffuse images and the highlights' colour resampled on the
    host give the same image, to float rounding."""
    field = sphere_field
    width, height = 120, 68
    colour = (1.0, 0.5, 0.25)
    relighter = Relighter(field, device=device, size=(width, height), diffuse=diffuse, specular_colour=colour,
                          scale=2.0)
    assert relighter.upsampled
    queries = random_directions(np.random.default_rng(21), 5)
    result = relighter.relight(queries)
    unit = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    if diffuse == "lambert":
        planes = resample_image(field.diffuse.lambert.reshape(HEIGHT, WIDTH, -1), width, height)
        planes = planes.reshape(height, width, 3, 4).astype(np.float64)
        expected = np.maximum(np.einsum("hwck,qk->qhwc", planes[..., :3], unit), 0.0) + planes[..., 3]
    elif diffuse == "images":
        vertices = field.triangulation.faces[result.faces]
        blended = np.einsum("qk,qkhwc->qhwc", result.barycentric, field.diffuse.images.astype(np.float64)[vertices])
        expected = _grown(blended, width, height)
    else:
        expected = np.zeros_like(result.full, dtype=np.float64)
    expected = 2.0 * np.maximum(expected + np.asarray(colour) * result.specular[..., None], 0.0)
    np.testing.assert_allclose(result.full, expected, rtol=1e-5, atol=1e-5)


def test_the_alpha_blend_at_a_larger_size_is_the_blend_resampled(sphere_field, device):
    field = sphere_field
    rng = np.random.default_rng(22)
    specular = rng.uniform(0, 2, size=(field.light_count, HEIGHT, WIDTH)).astype(np.float32)
    images = rng.uniform(0, 2, size=(field.light_count, HEIGHT, WIDTH, 3)).astype(np.float32)
    width, height = 96, 54
    relighter = Relighter(field, device=device, size=(width, height), alpha_specular=specular, alpha_images=images,
                          scale=0.5)
    result = relighter.relight(random_directions(rng, 7), method="alpha")
    vertices = field.triangulation.faces[result.faces]
    weights = result.barycentric
    blended = np.einsum("qk,qkhw->qhw", weights, specular.astype(np.float64)[vertices])
    np.testing.assert_allclose(result.specular, _grown(blended, width, height), rtol=1e-5, atol=1e-5)
    halves = images.astype(np.float16).astype(np.float64)  # full images are kept as float16 on the device
    full = np.einsum("qk,qkhwc->qhwc", weights, halves[vertices])
    np.testing.assert_allclose(result.full, 0.5 * _grown(full, width, height), rtol=1e-5, atol=1e-5)


def test_narrow_gaussians_are_widened_with_their_light_kept(device):
    """``widen_narrow_gaussians`` against its float64 reference; a widened Gaussian adds the same light (its
    integral over a fine grid), and one at least the least width is left bit for bit."""
    from warp_highlights.kernels.upsample import widen_narrow_gaussians

    rng = np.random.default_rng(23)
    params = inside_params(rng, 3, 8, HEIGHT, WIDTH, sigma_px=(0.05, 3.0))
    least, eps = 0.7 / HEIGHT, FitSettings().raster.sigma_eps
    params.sigma[0, 0] = (least, least)  # exactly the least width: unchanged
    batch = GaussianBatch.from_numpy(params, device=device, requires_grad=False)
    wp.launch(widen_narrow_gaussians, dim=batch.shape, inputs=[batch.arrays, least, eps], device=device)
    got, expected = batch.numpy(), reference.widened(params, least, eps)
    np.testing.assert_allclose(got.sigma, expected.sigma, rtol=1e-6)
    np.testing.assert_allclose(got.amplitude, expected.amplitude, rtol=1e-5)
    wide = (np.abs(params.sigma) >= least).all(axis=-1)
    assert wide.any() and (~wide).any()
    np.testing.assert_array_equal(got.amplitude[wide], params.amplitude[wide].astype(np.float32))
    fine = 16  # light added: the untruncated images' sums on a grid 16 times finer
    before = reference.render(params, fine * HEIGHT, fine * WIDTH, truncate=False).sum(axis=(1, 2))
    after = reference.render(expected, fine * HEIGHT, fine * WIDTH, truncate=False).sum(axis=(1, 2))
    np.testing.assert_allclose(after, before, rtol=0.02)


def test_other_output_sizes_render_the_same_gaussians(sphere_field):
    field = sphere_field
    queries = random_directions(np.random.default_rng(13), 5)
    big = Relighter(field, device="cpu", size=(2 * WIDTH, 2 * HEIGHT), diffuse="lambert")
    result = big.relight(queries)
    sets = Relighter(field, device="cpu").interpolated_sets(queries)
    np.testing.assert_allclose(result.specular, render_numpy(sets, 2 * HEIGHT, 2 * WIDTH),
                               atol=2e-4 * max(1.0, float(result.specular.max())))
    assert result.full.shape == (5, 2 * HEIGHT, 2 * WIDTH, 3)
    with pytest.raises(InputError, match="aspect ratio"):
        Relighter(field, size=(WIDTH, WIDTH))


@pytest.mark.parametrize(("diffuse_images", "lambert_half"), [(False, False), (True, True)])
def test_relight_of_a_saved_and_loaded_field_is_identical(tmp_path, diffuse_images, lambert_half):
    field = synthetic_field(LightSet.fibonacci_sphere(18), seed=4, diffuse_images=diffuse_images)
    path = tmp_path / "field.whf"
    if lambert_half:  # the default save rounds the Lambertian model to float16: compare two loads
        save_field(field, path)
        field = load_field(path)
        path = tmp_path / "again.whf"
    save_field(field, path, lambert_half=lambert_half)
    loaded = load_field(path)
    queries = random_directions(np.random.default_rng(14), 20)
    for method in ("circular", "straight"):
        before = Relighter(field, device="cpu").relight(queries, method=method)
        after = Relighter(loaded, device="cpu").relight(queries, method=method)
        assert np.array_equal(before.specular, after.specular)
        assert np.array_equal(before.full, after.full)
        assert before.specular.max() > 0


def test_chunks_give_the_same_images_as_one_launch(sphere_field):
    queries = random_directions(np.random.default_rng(15), 23)
    whole = Relighter(sphere_field, device="cpu").relight(queries)
    chunked = Relighter(sphere_field, device="cpu", max_batch=4)
    seen = []
    parts = chunked.relight(queries, progress=seen.append)
    assert seen == [4, 8, 12, 16, 20, 23]
    assert np.array_equal(whole.specular, parts.specular)
    assert np.array_equal(whole.full, parts.full)
    streamed = list(chunked.iter_relight(queries, full=False))
    assert [len(p.specular) for p in streamed] == [4, 4, 4, 4, 4, 3]
    assert np.array_equal(np.concatenate([p.specular for p in streamed]), whole.specular)


def test_a_launch_never_draws_more_queries_than_its_pixels_allow(sphere_field, monkeypatch):
    """``max_batch`` (given or the memory default) is capped at the rasterizer's images per launch
    (2^31 pixels), so a 4K field's batches run in parts instead of being refused."""
    from warp_highlights.kernels.raster import Rasterizer

    queries = random_directions(np.random.default_rng(16), 9)
    whole = Relighter(sphere_field, device="cpu").relight(queries)
    monkeypatch.setattr(Rasterizer, "problems_per_launch", property(lambda self: 3))
    for asked in (None, 100):
        capped = Relighter(sphere_field, device="cpu", max_batch=asked)
        assert capped.max_batch == 3
        parts = capped.relight(queries)
        assert np.array_equal(whole.specular, parts.specular) and np.array_equal(whole.full, parts.full)


def test_single_direction_has_no_query_axis(sphere_field):
    result = Relighter(sphere_field, device="cpu").relight([0.0, 0.0, 3.0])
    assert result.specular.shape == (HEIGHT, WIDTH)
    assert result.full.shape == (HEIGHT, WIDTH, 3)
    assert result.barycentric.shape == (3,)


@pytest.mark.parametrize(
    ("arguments", "call", "expected"),
    [
        ({}, {"directions": [0.0, 0.0, 0.0]}, "zero or not finite"),
        ({}, {"directions": [[1.0, np.nan, 0.0]]}, "zero or not finite"),
        ({}, {"directions": [[1.0, 0.0]]}, "shape"),
        ({}, {"directions": [0, 0, 1], "method": "cubic"}, "method must be one of"),
        ({}, {"directions": [0, 0, 1], "method": "alpha"}, "needs the specular images"),
        ({"diffuse": "sometimes"}, None, "diffuse must be one of"),
        ({"scale": 0.0}, None, "scale must be a positive"),
        ({"alpha_specular": np.zeros((3, HEIGHT, WIDTH))}, None, "alpha specular must have shape"),
        ({"max_batch": 0}, None, "max_batch"),
    ],
)
def test_bad_input_is_one_line(sphere_field, arguments, call, expected):
    with pytest.raises(InputError, match=expected) as raised:
        relighter = Relighter(sphere_field, device="cpu", **arguments)
        relighter.relight(**call)
    assert "\n" not in str(raised.value)


def test_diffuse_images_need_a_field_that_stores_them(dome_field):
    with pytest.raises(InputError, match="--diffuse images"):
        Relighter(dome_field, diffuse="images")


def test_face_edge_rows_point_at_the_right_edges(sphere_field):
    field = sphere_field
    rows = face_edge_rows(field.triangulation.faces, field.directed_edges, field.light_count)
    faces = field.triangulation.faces
    for k in range(3):
        assert np.array_equal(field.directed_edges[rows[:, k, 0]],
                              np.stack([faces[:, k], faces[:, (k + 1) % 3]], axis=1))
        assert np.array_equal(field.directed_edges[rows[:, k, 1]],
                              np.stack([faces[:, k], faces[:, (k + 2) % 3]], axis=1))


def test_resample_image_shrinks_by_area_and_grows_linearly():
    rng = np.random.default_rng(16)
    image = rng.uniform(size=(30, 40, 2)).astype(np.float32)
    np.testing.assert_allclose(resample_image(image, 20, 15), resize_stack(image[None], 20, 15)[0], rtol=1e-5)
    ramp = np.add.outer(np.arange(10.0), 2.0 * np.arange(16.0)).astype(np.float32)
    grown = resample_image(ramp, 32, 20)
    rows = (np.arange(20) + 0.5) / 2 - 0.5
    cols = (np.arange(32) + 0.5) / 2 - 0.5
    expected = np.add.outer(np.clip(rows, 0, 9), 2.0 * np.clip(cols, 0, 15))
    np.testing.assert_allclose(grown, expected, atol=1e-5)  # a ramp is reproduced exactly inside
    assert resample_image(np.ones((5, 8)), 16, 10).shape == (10, 16)
    # one pixel grows into a flat image
    np.testing.assert_allclose(resample_image(np.full((1, 1, 3), 0.25), 4, 3), 0.25)
    mixed = resample_image(ramp, 12, 20)  # grows down the rows, shrinks across the columns
    np.testing.assert_allclose(mixed, resample_image(resample_image(ramp, 12, 10), 12, 20), atol=1e-5)


@pytest.mark.parametrize(("source", "target"),
                         [((30, 40), (15, 20)), ((29, 41), (7, 10)), ((17, 23), (16, 22)), ((9, 13), (1, 1))])
def test_resize_stack_is_the_exact_area_average(source, target):
    """Against a brute-force float64 overlap integral, integer and fractional factors, grey and colour."""
    rng = np.random.default_rng(sum(source))
    stack = rng.uniform(size=(2, *source, 3)).astype(np.float32)
    height, width = target
    resized = resize_stack(stack, width, height)
    assert resized.dtype == np.float32 and resized.shape == (2, height, width, 3)
    for image, got in zip(stack, resized):
        np.testing.assert_allclose(got, reference.area_resize(image, width, height), rtol=1e-5, atol=1e-6)
    grey = resize_stack(stack[..., 0], width, height)
    np.testing.assert_allclose(grey, resized[..., 0], rtol=1e-6)


def test_field_relight_shortcut_matches_the_relighter(sphere_field):
    queries = random_directions(np.random.default_rng(17), 3)
    shortcut = relight_field(sphere_field, queries, device="cpu")
    direct = Relighter(sphere_field, device="cpu").relight(queries)
    assert np.array_equal(shortcut.full, direct.full)
    again = relight_field(sphere_field, queries, method="straight", device="cpu", diffuse="lambert")
    assert np.array_equal(again.specular,
                          Relighter(sphere_field, device="cpu").relight(queries, method="straight").specular)


def test_a_gaussian_whose_fit_flipped_its_amplitude_sign_does_not_fade_through_zero():
    """Only a^2 is drawn, so a_A = +0.4 and a_AB = -0.4 are the same highlight: |a| is blended."""
    field = synthetic_field(LightSet.fibonacci_sphere(12), capacity=2, seed=7)
    flipped = field.retargeted.copy()
    flipped.amplitude = -flipped.amplitude
    mirrored = HighlightField(
        lights=field.lights, triangulation=field.triangulation, width=WIDTH, height=HEIGHT, estimated=field.estimated,
        directed_edges=field.directed_edges, retargeted=flipped, path_delta=field.path_delta,
        path_centre=field.path_centre,
        settings=field.settings, report={}, diffuse=field.diffuse,
    )
    queries = field.triangulation.centroid_directions()
    before = Relighter(field, device="cpu").relight(queries, full=False).specular
    after = Relighter(mirrored, device="cpu").relight(queries, full=False).specular
    np.testing.assert_allclose(after, before, rtol=1e-6, atol=1e-7)
    assert before.max() > 0.1
    location = field.triangulation.locate(queries)
    reference = interpolate_sets(mirrored, location.vertices, location.barycentric)
    assert np.all(reference.amplitude[reference.active] > 0)


def test_kept_results_survive_later_calls(sphere_field):
    relighter = Relighter(sphere_field, device="cpu", max_batch=4)
    first_queries = random_directions(np.random.default_rng(18), 4)
    first = relighter.relight(first_queries)
    kept = first.full.copy(), first.specular.copy()
    relighter.relight(random_directions(np.random.default_rng(19), 4))  # same count: same device buffers
    relighter.relight(random_directions(np.random.default_rng(20), 1))
    assert np.array_equal(first.full, kept[0]) and np.array_equal(first.specular, kept[1])
    assert np.array_equal(relighter.relight(first_queries).full, kept[0])


def test_one_query_as_a_cuda_graph_is_the_launches_bit_for_bit(sphere_field):
    """A single direction replayed from a captured graph (the interactive path) against the launches,
    also after a batch of another size has run on the same relighter; the CPU refuses graphs."""
    with pytest.raises(InputError, match="CUDA graphs need a CUDA device"):
        Relighter(sphere_field, device="cpu", graphs=True)
    if not wp.is_cuda_available():
        pytest.skip("CUDA graphs need a CUDA device (the CPU refusal above was checked)")
    eager = Relighter(sphere_field, device="cuda:0", graphs=False)
    graphed = Relighter(sphere_field, device="cuda:0")
    assert graphed.graphs and not eager.graphs
    queries = random_directions(np.random.default_rng(5), 4)
    for method in ("circular", "straight"):
        for round_ in range(2):
            for direction in queries:
                got, want = graphed.relight(direction, method=method), eager.relight(direction, method=method)
                for name in ("specular", "full", "faces", "barycentric", "clamped"):
                    np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
            graphed.relight(queries[:3], method=method)  # a batch between: the graph keeps its own buffers


@pytest.mark.parametrize("copies", [(9, 40, 70), (40, 70, 3)])
def test_the_sliced_face_search_keeps_the_first_deepest_face(copies, device):
    """``deepest_faces`` splits the faces over threads; ``locate_directions`` must still pick the first
    face of the largest margin, as one loop would (here several faces in different slices tie
    exactly), and the float64 NumPy argmax where nothing ties."""
    from warp_highlights.kernels import interpolation as kernels

    rng = np.random.default_rng(22)
    face_count = 75
    normals = rng.normal(size=(face_count, 3, 3))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    queries = random_directions(rng, 40)
    normals[list(copies)] = queries[0]  # margin 1 in each copy: the largest any face can have
    depths = wp.empty((len(queries), kernels.FACE_SLICES), dtype=wp.float64, device=device)
    best = wp.empty((len(queries), kernels.FACE_SLICES), dtype=wp.int32, device=device)
    as_vec3d = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.vec3d, device=device)
    directions = as_vec3d(queries)
    wp.launch(kernels.deepest_faces, dim=depths.shape, inputs=[directions, as_vec3d(normals)], outputs=[depths, best],
              device=device)
    rims = [as_vec3d(np.zeros((1, 3)))] * 5 + [wp.zeros(1, dtype=wp.int32, device=device)] * 2
    inverses = wp.array(np.tile(np.eye(3), (face_count, 1, 1)), dtype=wp.mat33d, device=device)
    out = [wp.empty(len(queries), dtype=t, device=device) for t in (wp.int32, wp.vec3, wp.vec3, wp.int32)]
    wp.launch(kernels.locate_directions, dim=len(queries), inputs=[directions, depths, best, inverses, *rims, 0, 1e-12],
              outputs=out, device=device)
    faces = out[0].numpy()
    assert faces[0] == min(copies)
    margins = np.einsum("qc,fkc->qfk", queries, normals).min(axis=2)
    top_two = np.sort(margins, axis=1)[:, -2:]
    clear = top_two[:, 1] - top_two[:, 0] > 1e-9
    expected = np.argmax(margins, axis=1)  # the first face on ties
    assert np.all(clear | np.isin(expected, copies)) and (~clear).sum() > 3  # ties only among the copies
    np.testing.assert_array_equal(faces, expected)


def test_single_query_results_on_page_locked_memory_are_not_overwritten_while_held(sphere_field):
    """A graph query's images view page-locked buffers: a later query writes only a slot whose arrays
    are all gone (a slice of one keeps its slot), and once every slot is held, results are copies."""
    from warp_highlights.relight.relighter import RESULT_SLOTS, result_slots

    assert (result_slots(270, 480, 3) == RESULT_SLOTS and result_slots(2160, 3840, 3) == 1
            and result_slots(20000, 20000, 3) == 1)
    if not wp.is_cuda_available():
        pytest.skip("page-locked single-query results need CUDA graphs")
    eager = Relighter(sphere_field, device="cuda:0", graphs=False)
    graphed = Relighter(sphere_field, device="cuda:0")
    queries = random_directions(np.random.default_rng(21), RESULT_SLOTS + 3)
    want = [eager.relight(direction) for direction in queries]
    held = [graphed.relight(direction) for direction in queries]  # every slot held, then copies
    for got, expected in zip(held, want):
        np.testing.assert_array_equal(got.full, expected.full)
        np.testing.assert_array_equal(got.specular, expected.specular)
    query = graphed._graphs[("circular", True)]
    assert len(query.slots) == RESULT_SLOTS and query._copying is not None
    height, width = want[0].specular.shape
    middle = np.s_[height // 2 - 3 : height // 2 + 3, width // 2 - 3 : width // 2 + 3]
    assert not np.array_equal(want[0].full[middle], want[-1].full[middle])  # an overwrite would show
    kept = held[0].full[middle]  # a view of the first result only
    del held, got
    for direction in queries[::-1]:
        graphed.relight(direction)  # reuses the free slots
    np.testing.assert_array_equal(kept, want[0].full[middle])
    assert len(query.slots) == RESULT_SLOTS
