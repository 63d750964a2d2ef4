"""Surface maps (``relight.maps``, ``warp-highlights maps``): normals against the analytic sphere's, the
albedo against the renderer's material, the files and their encodings, bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from conftest import FAST_FIT

SPHERE_ALBEDO = 0.6  # default_material("sphere")


def _analytic_normals(renderer) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) unit normals of the rendered unit sphere (centred at the origin) at each pixel's hits,
    and (H, W) the pixels every sample of which hit it."""
    samples = renderer.camera_samples_numpy()
    hit = samples["hit_mask"] > 0
    points = samples["shadow_origin"].astype(np.float64)  # the hit point moved along the normal: still radial
    radial = points / np.maximum(np.linalg.norm(points, axis=-1, keepdims=True), 1e-12)
    summed = (radial * hit[..., None]).sum(axis=2)
    length = np.linalg.norm(summed, axis=-1, keepdims=True)
    return summed / np.where(length > 0, length, 1.0), hit.all(axis=2)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def sphere_fits():
    """The rendered sphere (64x64) under 48 lights over the full sphere and under a dome of the upper
    half, each fitted on the CPU (``FAST_FIT``): {name: (renderer, field)}."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings
    from warp_highlights.model.lights import LightSet
    from warp_highlights.synth.render import (
        Renderer,
        RenderSettings,
        default_material,
        view_rotation,
    )
    from warp_highlights.synth.shapes import make_shape

    renderer = Renderer(make_shape("sphere"), material=default_material("sphere"),
                        settings=RenderSettings(width=64, height=64),
                        rotation=view_rotation("sphere"), device="cpu")
    everywhere = LightSet.fibonacci_sphere(48).directions
    dome = LightSet.fibonacci_sphere(96).directions
    fits = {}
    for name, directions in (("sphere", everywhere), ("dome", dome[dome[:, 2] > 0.05])):
        dataset = ReflectanceField(images=renderer.render(directions).full, lights=LightSet(directions))
        fits[name] = (renderer,
                      fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT), device="cpu", progress=False))
    return fits


@pytest.mark.parametrize("lights", ["sphere", "dome"])
def test_sphere_normals_within_two_degrees_of_the_analytic_ones(sphere_fits, lights):
    from warp_highlights.relight.maps import surface_maps

    renderer, field = sphere_fits[lights]
    maps = surface_maps(field, device="cpu")
    truth, covered = _analytic_normals(renderer)
    # every pixel on the sphere is estimated
    assert np.count_nonzero(covered & maps.mask) >= 0.98 * np.count_nonzero(covered)
    assert not np.any(maps.mask & ~renderer.mask & (renderer.coverage == 0))  # and none of the background
    angles = _angles_deg(maps.normals, truth)[covered & maps.mask]
    assert np.median(angles) < 2.0, f"median {np.median(angles):.2f} degrees"
    assert np.percentile(angles, 90) < 5.0
    # the orientation convention: x right, y up the image, z towards the camera
    height, width = covered.shape
    assert maps.normals[height // 2, width // 2, 2] > 0.99
    assert maps.normals[height // 6, width // 2, 1] > 0.5  # top of the image: y up
    assert maps.normals[height // 2, 5 * width // 6, 0] > 0.5  # right of the image: x right
    albedo = maps.albedo[covered & maps.mask]  # the renderer's ambient (2% of the albedo) adds to it
    assert np.allclose(np.median(albedo, axis=0), SPHERE_ALBEDO * 1.05, rtol=0.04)


def test_maps_are_finite_unit_and_non_negative(sphere_fits):
    from warp_highlights.relight.maps import surface_maps

    maps = surface_maps(sphere_fits["sphere"][1], device="cpu")
    for array in (maps.normals, maps.albedo, maps.highlight_colour):
        assert np.all(np.isfinite(array))
    assert np.allclose(np.linalg.norm(maps.normals, axis=-1), 1.0, atol=1e-5)
    assert np.all(maps.albedo >= 0) and np.all(maps.highlight_colour >= 0)
    assert np.all(maps.normals[~maps.mask] == np.array([0.0, 0.0, 1.0], np.float32))
    assert np.all(maps.albedo[~maps.mask] == 0)
    assert np.all(maps.normals[maps.mask][:, 2] > 0)


def test_flatten_removes_a_linear_trend_of_the_slopes_and_keeps_the_rest():
    from warp_highlights.relight.maps import flatten_normals

    height, width = 40, 60
    v, u = np.mgrid[0:height, 0:width]
    u = (u + 0.5) / width * 2.0 - 1.0
    v = (v + 0.5) / height * 2.0 - 1.0
    relief = np.stack([0.05 * np.sin(7 * u) * np.cos(5 * v), 0.04 * np.cos(9 * v + 1.0)], axis=-1)
    mask = np.ones((height, width), bool)
    mask[:5, :7] = False  # left alone
    design = np.stack([np.ones(u.size), u.ravel(), v.ravel()], axis=1)
    for axis in range(2):  # a relief without a linear trend over the mask ...
        trend = np.linalg.lstsq(design[mask.ravel()], relief[..., axis][mask], rcond=None)[0]
        relief[..., axis] -= (design @ trend).reshape(height, width)

    def unit(slopes):
        n = np.concatenate([slopes, np.ones((height, width, 1))], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    tilt = np.array([0.03, -0.02])  # ... on an object tilted as a whole ...
    # ... that near lights make lean away from the centre
    leaning = relief + tilt + np.stack([0.2 * u, 0.15 * v], axis=-1)
    flat = flatten_normals(unit(leaning), mask)
    np.testing.assert_allclose(flat[mask], unit(relief + tilt)[mask], atol=1e-6)
    np.testing.assert_array_equal(flat[~mask], unit(leaning).astype(np.float32)[~mask])
    # nothing to remove
    np.testing.assert_allclose(flatten_normals(unit(relief + tilt), mask), unit(relief + tilt), atol=1e-6)


def test_fit_normals_matches_per_pixel_least_squares_and_rejects_highlights_and_shadows():
    """The batched fit against NumPy's lstsq pixel by pixel over the lights it kept; a highlight
    sample and shadowed samples do not move the normal."""
    from warp_highlights.model.lights import LightSet
    from warp_highlights.relight.maps import channel_albedo, fit_normals

    rng = np.random.default_rng(5)
    directions = LightSet.fibonacci_sphere(60).directions
    directions = directions[directions[:, 2] > 0.1]
    normals = rng.normal(size=(200, 3)) * [0.4, 0.4, 0.0] + [0.0, 0.0, 1.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rho = rng.uniform(0.1, 0.9, size=(200, 3))
    shading = np.maximum(directions @ normals.T, 0.0)  # (n, P): attached shadows are 0
    images = shading[..., None] * rho[None] + rng.normal(scale=1e-4, size=(len(directions), 200, 3))
    images[3, :50] += 2.0  # a highlight
    images = np.maximum(images, 0.0)
    luminance = images @ np.array([0.2126, 0.7152, 0.0722])
    fit = fit_normals(luminance, directions)
    assert fit.mask.all()
    assert not fit.inliers[3, :50].any()  # the highlight left the fit
    assert np.degrees(np.arccos(np.clip(np.sum(fit.normals * normals, axis=1), -1, 1))).max() < 0.1
    for pixel in range(0, 200, 17):
        kept = fit.inliers[:, pixel]
        reference = np.linalg.lstsq(directions[kept], luminance[kept, pixel], rcond=None)[0]
        np.testing.assert_allclose(fit.normals[pixel], reference / np.linalg.norm(reference), atol=1e-9)
    albedo = channel_albedo(images, directions, fit.normals, fit.inliers)
    np.testing.assert_allclose(albedo, rho, rtol=2e-3)
    for pixel in range(0, 200, 23):
        kept = fit.inliers[:, pixel]
        column = (directions[kept] @ fit.normals[pixel])[:, None]
        np.testing.assert_allclose(albedo[pixel], np.linalg.lstsq(column, images[kept, pixel], rcond=None)[0][0],
                                   rtol=1e-9)


def test_a_field_without_a_diffuse_part_has_no_maps(sphere_fits):
    from warp_highlights.model.errors import InputError
    from warp_highlights.relight.maps import surface_maps

    field = dataclasses.replace(sphere_fits["sphere"][1], residual=None, diffuse=None)
    with pytest.raises(InputError, match="no normals or albedo"):
        surface_maps(field, device="cpu")


def test_maps_command_writes_every_map_in_its_encoding(tiny_sphere, tmp_path, capsys):
    from warp_highlights.cli import main
    from warp_highlights.cli.maps import MAP_FILES
    from warp_highlights.io.images import read_image

    _, field = tiny_sphere
    output = tmp_path / "maps"
    assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q"]) == 0
    assert "wrote normal, albedo and highlight-colour maps" in capsys.readouterr().out
    assert sorted(p.name for p in output.iterdir() if not p.name.startswith(".")) == sorted(MAP_FILES)
    normals = read_image(output / "normals.exr")
    encoded = read_image(output / "normals.png", linear=True)  # 16-bit levels / 65535, no sRGB curve
    assert encoded.shape == normals.shape and encoded.shape[2] == 3
    np.testing.assert_allclose(encoded * 2.0 - 1.0, normals, atol=2.0 / 65535)
    assert len(np.unique(encoded)) > 256  # 16 bits, not 8
    mask = read_image(output / "mask.png", linear=True) > 0.5
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-4)
    assert np.all(normals[~mask] == [0.0, 0.0, 1.0])
    albedo = read_image(output / "albedo.exr")
    assert np.all(albedo >= 0) and np.all(np.isfinite(albedo)) and np.any(albedo[mask] > 0)
    summary = json.loads((output / "maps.json").read_text())
    assert summary["pixels_with_normal"] == int(mask.sum())
    assert summary["normal_frame"].startswith("x right, y up the image, z towards the camera")


def test_maps_command_refuses_an_existing_folder_and_writes_nothing(tiny_sphere, tmp_path, capsys):
    from warp_highlights.cli import main

    _, field = tiny_sphere
    output = tmp_path / "maps"
    output.mkdir()
    (output / "mine.txt").write_text("keep")
    assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "maps" in error[0]
    assert sorted(p.name for p in output.iterdir()) == ["mine.txt"]
    assert main(["maps", str(tmp_path / "missing.whf"), "-o", str(tmp_path / "other"), "--device", "cpu", "-q"]) == 2
    assert not (tmp_path / "other").exists()


def test_maps_folder_is_replaced_with_overwrite(tiny_sphere, tmp_path):
    from warp_highlights.cli import main

    _, field = tiny_sphere
    output = tmp_path / "maps"
    assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q"]) == 0
    assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q"]) == 2
    assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q", "--overwrite"]) == 0
    assert (output / "normals.png").is_file()


def test_dome_sample_normals_against_its_rendered_normal_map(data_root):
    """The rendered dome sample's normals.png: a nearly flat relief (0.6 degrees from (0, 0, 1), median).
    Its dome's near lights make the estimate lean away from the centre; flattened it is within a degree."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.images import read_image
    from warp_highlights.io.resample import resize_stack
    from warp_highlights.model.config import FitSettings
    from warp_highlights.relight.maps import surface_maps

    root = data_root / "synthrti-object1-material5" / "Dome"
    if not (root / "normals.png").is_file():
        pytest.skip(f"no {root / 'normals.png'}")
    dataset = ReflectanceField.load(root, progress=False)
    field = fit_field(dataset, size=(80, 80), settings=FitSettings().with_overrides(FAST_FIT), device="cpu",
                      progress=False)
    truth = resize_stack((read_image(root / "normals.png", linear=True) * 2.0 - 1.0)[None], 80, 80)[0]
    truth /= np.linalg.norm(truth, axis=-1, keepdims=True)
    leaning, flat = (surface_maps(field, device="cpu", flatten=flatten) for flatten in (False, True))
    assert flat.mask.all()
    flat_error = np.median(_angles_deg(flat.normals, truth))
    assert flat_error < 1.0, f"median {flat_error:.2f} degrees"
    assert flat_error < np.median(_angles_deg(leaning.normals, truth)) / 4
    # flattening turns the normals only a little
    np.testing.assert_allclose(flat.albedo, leaning.albedo, rtol=0.1, atol=1e-3)


def test_maps_that_would_not_fit_in_memory_are_refused_before_any_work(sphere_fits, monkeypatch):
    from warp_highlights.model import memory
    from warp_highlights.model.errors import InputError
    from warp_highlights.relight.maps import surface_maps

    monkeypatch.setattr(memory, "available_memory", lambda: 1000)
    with pytest.raises(InputError, match=r"surface maps of 48 lights at 64x64 needs about .* smaller --size"):
        surface_maps(sphere_fits["sphere"][1], device="cpu")
