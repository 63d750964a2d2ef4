"""The synthetic-data renderer against analytic shading of a sphere, and its dataset output."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.model.lights import LightSet
from warp_highlights.synth.render import (
    Material,
    Renderer,
    RenderSettings,
    render_dataset,
    view_rotation,
)
from warp_highlights.synth.shapes import sphere, teapot, torus

FRONT_LIGHTS = np.array(
    [
        [0.0, 0.0, 1.0],
        [0.5, 0.3, 0.81],
        [-0.6, 0.2, 0.77],
        [0.2, -0.7, 0.68],
        [-0.4, -0.5, 0.77],
        [0.8, 0.1, 0.59],
    ]
)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _project(renderer: Renderer, points: np.ndarray) -> np.ndarray:
    """Scene points -> (col, row) pixel coordinates, pixel centres at integers (float64)."""
    s = renderer.settings
    t = math.tan(math.radians(s.fov_y_deg) / 2.0)
    rel = points - renderer.camera_position
    depth = -rel[..., 2]
    x_ndc = rel[..., 0] / depth / (t * s.width / s.height)
    y_ndc = rel[..., 1] / depth / t
    return np.stack([(x_ndc + 1) / 2 * s.width - 0.5, (1 - y_ndc) / 2 * s.height - 0.5], axis=-1)


def _sphere_hits(renderer: Renderer) -> tuple[np.ndarray, np.ndarray]:
    """Analytic unit-sphere hit points through every pixel centre (NaN where the ray misses)."""
    s = renderer.settings
    t = math.tan(math.radians(s.fov_y_deg) / 2.0)
    cols, rows = np.meshgrid(np.arange(s.width) + 0.5, np.arange(s.height) + 0.5)
    d = _unit(np.stack([(2 * cols / s.width - 1) * t * s.width / s.height, (1 - 2 * rows / s.height) * t,
                        -np.ones_like(cols)], -1))
    o = renderer.camera_position
    b = d @ o
    disc = b * b - (o @ o - 1.0)
    hit_t = -b - np.sqrt(np.where(disc > 0, disc, np.nan))
    return o + hit_t[..., None] * d, disc > 0


def _analytic_highlight(renderer: Renderer, light: np.ndarray) -> np.ndarray:
    """Point of the unit sphere whose normal is the half-vector of the light and the view there."""
    normal = _unit(light + np.array([0.0, 0.0, 1.0]))
    for _ in range(50):
        view = _unit(renderer.camera_position - normal)
        normal = _unit(light + view)
    return normal


@pytest.fixture(scope="module")
def sphere_renderer_cpu():
    material = Material(albedo=(1.0, 1.0, 1.0), ambient=0.0, specular=1.0, shininess=600.0)
    settings = RenderSettings(width=200, height=150, samples_per_pixel=4, colour=False)
    return Renderer(sphere(subdivisions=6), material=material, settings=settings, device="cpu")


def test_specular_peak_lands_on_the_half_vector_point(sphere_renderer_cpu):
    renderer = sphere_renderer_cpu
    lights = _unit(FRONT_LIGHTS)
    specular = renderer.render(lights).specular
    for image, light in zip(specular, lights):
        expected = _project(renderer, _analytic_highlight(renderer, light))
        rows, cols = np.nonzero(image >= 0.5 * image.max())
        weights = image[rows, cols]
        measured = np.array([np.average(cols, weights=weights), np.average(rows, weights=weights)])
        assert np.linalg.norm(measured - expected) < 1.0, (light, measured, expected)
        peak_row, peak_col = np.unravel_index(np.argmax(image), image.shape)
        assert np.linalg.norm(np.array([peak_col, peak_row]) - expected) <= 1.5


def test_specular_peak_is_high_dynamic_range(sphere_renderer_cpu):
    specular = sphere_renderer_cpu.render(_unit(FRONT_LIGHTS[:1])).specular
    peak = sphere_renderer_cpu.material.peak_specular
    assert specular.max() > 1.0
    assert specular.max() == pytest.approx(peak, rel=0.1)


def test_diffuse_matches_lambert_on_sphere(sphere_renderer_cpu):
    renderer = sphere_renderer_cpu
    lights = _unit(np.concatenate([FRONT_LIGHTS, [[1.0, 0.0, 0.0], [0.0, 1.0, -0.3]]]))
    diffuse = renderer.render(lights).diffuse
    points, inside = _sphere_hits(renderer)
    interior = inside & (renderer.coverage == 1.0)
    for image, light in zip(diffuse, lights):
        expected = np.maximum(points @ light, 0.0)
        # Pixels right at the terminator mix lit and unlit samples; compare away from it.
        away = interior & (np.abs(np.nan_to_num(points @ light)) > 0.05)
        error = np.abs(image[away] - expected[away])
        assert error.mean() < 0.004, light
        assert error.max() < 0.03, light


def test_convex_sphere_never_shadows_itself(sphere_renderer_cpu):
    renderer = sphere_renderer_cpu
    lights = _unit(np.array([[1.0, 0.0, 0.05], [0.0, -1.0, 0.1], [0.7, 0.7, -0.2]]))
    diffuse = renderer.render(lights).diffuse
    points, inside = _sphere_hits(renderer)
    interior = inside & (renderer.coverage == 1.0)
    for image, light in zip(diffuse, lights):
        lit = interior & (np.nan_to_num(points @ light) > 0.05)
        assert np.all(image[lit] > 0.0)


def test_torus_under_grazing_light_shadows_itself():
    rotation = view_rotation("donut")
    settings = RenderSettings(width=160, height=90, samples_per_pixel=4, colour=False)
    material = Material(albedo=(1.0, 1.0, 1.0), ambient=0.0, specular=0.0)
    renderer = Renderer(torus(), material=material, settings=settings, rotation=rotation, device="cpu")
    # Nearly in the torus' plane: the near side of the ring shades the inside of the far side.
    light = _unit(rotation @ np.array([1.0, 0.12, 0.0]))
    diffuse = renderer.render(light[None]).diffuse[0]
    normals = renderer.camera_samples_numpy()["shading_normal"].mean(axis=2)
    facing = (renderer.coverage == 1.0) & (normals @ light > 0.2)
    shadowed = facing & (diffuse == 0.0)
    assert shadowed.sum() > 30
    # The same light straight from the ring's axis leaves no facing pixel dark.
    overhead = _unit(rotation @ np.array([0.0, 1.0, 0.0]))
    diffuse = renderer.render(overhead[None]).diffuse[0]
    facing = (renderer.coverage == 1.0) & (normals @ overhead > 0.2)
    assert np.all(diffuse[facing] > 0.0)


@pytest.mark.parametrize("shape", ["donut", "teapot"])
def test_shapes_render_finite_and_non_negative(shape):
    mesh = torus() if shape == "donut" else teapot(subdivisions=6)
    settings = RenderSettings(width=96, height=54, samples_per_pixel=4)
    renderer = Renderer(mesh, settings=settings, rotation=view_rotation(shape), device="cpu")
    lights = LightSet.fibonacci_sphere(12).directions
    images = renderer.render(lights)
    for array in (images.full, images.diffuse, images.specular):
        assert array.shape == (12, 54, 96, 3)
        assert np.all(np.isfinite(array)) and array.min() >= 0.0
    np.testing.assert_allclose(images.full, images.diffuse + images.specular, rtol=1e-6, atol=1e-7)
    assert images.specular.max() > 1.0  # HDR highlights
    assert 0.1 < renderer.mask.mean() < 0.9  # framed: the object fills a good part, not all, of the image


def _ggx_reference(normal, light, view, alpha):
    """float64 GGX lobe times n.l: D G / (4 n.v), Smith's separable shadowing; 0 facing away."""
    cos_l, cos_v = normal @ light, np.einsum("...k,...k->...", normal, view)
    half = _unit(light + view)
    cos_h = np.maximum(np.einsum("...k,...k->...", normal, half), 0.0)
    a2 = alpha**2
    d = a2 / (np.pi * (cos_h**2 * (a2 - 1.0) + 1.0) ** 2)

    def g1(c):
        return 2.0 * c / (c + np.sqrt(a2 + (1.0 - a2) * c * c))

    safe_v = np.where(cos_v > 0, cos_v, 1.0)
    return np.where((cos_l > 0) & (cos_v > 0), d * g1(np.maximum(cos_l, 0.0)) * g1(safe_v) / (4.0 * safe_v), 0.0)


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_ggx_lobe_matches_a_float64_reference(alpha):
    """The specular image of a convex sphere (no shadows) is the sample average of the GGX lobe at the
    camera samples' normals and view directions."""
    material = Material(albedo=(1.0, 1.0, 1.0), ambient=0.0, specular=1.0, roughness=alpha)
    settings = RenderSettings(width=80, height=60, samples_per_pixel=4, colour=False)
    renderer = Renderer(sphere(subdivisions=5), material=material, settings=settings, device="cpu")
    light = _unit(np.array([0.3, 0.4, 0.85]))
    specular = renderer.render(light[None]).specular[0]
    samples = renderer.camera_samples_numpy()
    hit = samples["hit_mask"].astype(bool)
    values = np.where(hit, _ggx_reference(samples["shading_normal"].astype(np.float64), light,
                                          samples["view_direction"].astype(np.float64), alpha), 0.0)
    expected = values.mean(axis=-1)
    np.testing.assert_allclose(specular, expected, rtol=2e-4, atol=2e-5 * expected.max())
    assert specular.max() > 0.5 * material.peak_specular  # a sharp lobe reaches near its peak on a sphere


def test_tiles_alternate_two_materials_and_keep_the_lighting():
    """With tiles, each pixel's albedo is the mix of the two materials' by its samples on each, and its
    specular lobe is scaled the same way; the lighting itself does not change."""
    base = Material(albedo=(0.8, 0.3, 0.2), ambient=0.0, specular=0.5)
    tiled = Material(albedo=(0.8, 0.3, 0.2), ambient=0.0, specular=0.5, texture="tiles", tile_albedo=(0.1, 0.6, 0.9),
                     tile_specular=0.2, tile_size=0.25)
    settings = RenderSettings(width=96, height=54, samples_per_pixel=4)
    lights = LightSet.fibonacci_sphere(6).directions
    plain = Renderer(torus(), material=base, settings=settings, rotation=view_rotation("donut"), device="cpu")
    checked = Renderer(torus(), material=tiled, settings=settings, rotation=view_rotation("donut"), device="cpu")
    one, two = plain.render(lights), checked.render(lights)
    samples = checked.camera_samples_numpy()
    cells = np.floor(samples["shadow_origin"].astype(np.float64) / 0.25).astype(int).sum(axis=-1)
    hit = samples["hit_mask"].astype(bool)
    share = ((cells % 2 == 1) & hit).sum(-1) / np.maximum(hit.sum(-1), 1)  # (H, W)
    assert 0.2 < share[plain.mask].mean() < 0.8  # both materials are seen
    # diffuse = albedo(share) * irradiance: compared to the plain albedo's channel ratios
    albedo = (1 - share)[..., None] * np.array(base.albedo) + share[..., None] * np.array(tiled.tile_albedo)
    lit = one.diffuse > 1e-3
    ratio = np.where(lit, two.diffuse / np.where(lit, one.diffuse, 1.0), 0.0)
    expected = np.broadcast_to(albedo / np.array(base.albedo), ratio.shape)
    np.testing.assert_allclose(ratio[lit], expected[lit], rtol=1e-4)
    scale = 1.0 - share + share * tiled.tile_specular
    lit = one.specular[..., 0] > 1e-4
    np.testing.assert_allclose(two.specular[..., 0][lit], (one.specular[..., 0] * scale)[lit], rtol=1e-4)


@pytest.mark.parametrize("shape", ["coin", "bumpy"])
def test_relief_shapes_render_and_move_their_highlights_in_steps(shape):
    """The relief plate and the bumpy donut render finite, non-negative HDR images, and their bumps
    break a highlight into many glints: more separate specular peaks than the smooth donut shows."""
    from scipy import ndimage

    from warp_highlights.synth.render import default_material
    from warp_highlights.synth.shapes import make_shape

    settings = RenderSettings(width=160, height=90, samples_per_pixel=4, colour=False)
    light = _unit(np.array([0.3, 0.4, 0.85]))[None]

    def glints(name):
        renderer = Renderer(make_shape(name), material=default_material(name), settings=settings,
                            rotation=view_rotation(name), device="cpu")
        images = renderer.render(light)
        assert np.all(np.isfinite(images.full)) and images.full.min() >= 0.0
        specular = images.specular[0]
        return ndimage.label(specular > 0.3 * specular.max())[1]

    assert glints(shape) > glints("donut")


def test_render_is_deterministic_and_chunking_changes_nothing():
    lights = LightSet.fibonacci_sphere(7).directions
    whole = Renderer(torus(), settings=RenderSettings(width=64, height=36, light_chunk=64), device="cpu").render(lights)
    chunked = Renderer(torus(), settings=RenderSettings(width=64, height=36, light_chunk=3),
                       device="cpu").render(lights)
    np.testing.assert_array_equal(whole.full, chunked.full)


def test_the_light_chunk_fits_the_available_memory(monkeypatch):
    """Short of memory, fewer lights are shaded per launch (a quarter of the available memory for
    their three images; at least one), with the same images."""
    import warp_highlights.model.memory as memory

    lights = LightSet.fibonacci_sphere(7).directions
    renderer = Renderer(torus(), settings=RenderSettings(width=64, height=36, light_chunk=64), device="cpu")
    per_light = 3 * 4 * 64 * 36 * 3
    whole = renderer.render(lights)
    monkeypatch.setattr(memory, "available_memory", lambda: 4 * 2.5 * per_light)
    assert renderer.light_chunk() == 2
    np.testing.assert_array_equal(renderer.render(lights).full, whole.full)
    monkeypatch.setattr(memory, "available_memory", lambda: 10)
    assert renderer.light_chunk() == 1
    monkeypatch.setattr(memory, "available_memory", lambda: None)
    assert renderer.light_chunk() == 64


def test_device_variants_agree(device):
    lights = LightSet.fibonacci_sphere(5).directions
    settings = RenderSettings(width=64, height=36)
    reference = Renderer(torus(), settings=settings, rotation=view_rotation("donut"), device="cpu").render(lights)
    other = Renderer(torus(), settings=settings, rotation=view_rotation("donut"), device=device).render(lights)
    # Same samples; a handful of silhouette or shadow-edge samples may flip with float rounding.
    assert np.mean(np.abs(other.full - reference.full) > 1e-3) < 0.01


def test_render_dataset_writes_the_dataset_layout(tmp_path):
    lights = LightSet.fibonacci_sphere(12)
    folder = render_dataset(
        "sphere",
        tmp_path / "ds",
        lights=lights,
        settings=RenderSettings(width=48, height=32),
        device="cpu",
        progress=False,
    )
    field = ReflectanceField.load(folder, progress=False)
    assert field.light_count == 12 and field.images.shape == (12, 32, 48, 3)
    assert field.heldout is not None and field.heldout.light_count == 2 * 12 - 4
    np.testing.assert_allclose(field.lights.directions, lights.directions, atol=1e-6)
    np.testing.assert_allclose(field.images, field.specular + field.diffuse, rtol=1e-6, atol=1e-6)
    assert field.heldout.specular is not None and field.mask is not None and field.mask.any()
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["shape"] == "sphere" and meta["light_count"] == 12 and meta["heldout_count"] == 20
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporary folder left
