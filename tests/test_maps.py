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
    # levelled, the median slope leaves as well: the typical orientation faces the camera
    levelled = flatten_normals(unit(leaning), mask, level=True)
    median = np.median((relief + tilt)[mask], axis=0)
    np.testing.assert_allclose(levelled[mask], unit(relief + tilt - median)[mask], atol=1e-6)
    np.testing.assert_array_equal(levelled[~mask], unit(leaning).astype(np.float32)[~mask])
    assert np.allclose(np.median(levelled[mask][:, :2], axis=0), 0.0, atol=1e-6)


def test_normal_lean_measures_the_trend_at_the_corners_and_the_tilt():
    from warp_highlights.relight.maps import NormalLean, flatten_normals, normal_lean

    height, width = 30, 50
    v, u = np.mgrid[0:height, 0:width]
    u = (u + 0.5) / width * 2.0 - 1.0
    v = (v + 0.5) / height * 2.0 - 1.0
    slopes = np.stack([0.3 * u + 0.1, -0.2 * v - 0.05], axis=-1)
    normals = np.concatenate([slopes, np.ones((height, width, 1))], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    mask = np.ones((height, width), bool)
    lean = normal_lean(normals, mask)
    corner = np.hypot(0.3 * (1 - 1 / width), 0.2 * (1 - 1 / height))  # the outermost pixel centres
    assert lean.edge_deg == pytest.approx(np.degrees(np.arctan(corner)), abs=1e-6)
    assert lean.tilt_deg == pytest.approx(np.degrees(np.arctan(np.hypot(0.1, 0.05))), abs=1e-6)
    flat = normal_lean(flatten_normals(normals, mask), mask)
    assert flat.edge_deg < 1e-4 and flat.tilt_deg == pytest.approx(lean.tilt_deg, abs=1e-4)
    level = normal_lean(flatten_normals(normals, mask, level=True), mask)
    assert level.edge_deg < 1e-4 and level.tilt_deg < 1e-4
    assert normal_lean(normals, np.zeros_like(mask)) == NormalLean(0.0, 0.0)


def _near_lit_plate(size: int, distance: float, tilt_deg: float):
    """A Lambertian plate with three bumps, spanning [-1, 1] across the frame, turned ``tilt_deg``
    about the image's vertical axis, lit by point lights at ``distance`` (plate half-widths) from its
    centre along the light file's directions, with the inverse-square fall-off: (dataset, true
    normals (H, W, 3), (H, W) bool: the flat base)."""
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.lights import LightSet

    v, u = np.mgrid[0:size, 0:size]
    u = (u + 0.5) / size * 2.0 - 1.0
    v = 1.0 - (v + 0.5) / size * 2.0  # y up the image
    height, gx, gy = (np.zeros_like(u) for _ in range(3))
    for cx, cy, radius, amplitude in ((-0.4, 0.3, 0.25, 0.08), (0.35, -0.35, 0.2, 0.06), (0.3, 0.45, 0.15, -0.04)):
        bump = amplitude * np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * radius ** 2))
        height += bump
        gx -= bump * (u - cx) / radius ** 2
        gy -= bump * (v - cy) / radius ** 2
    base = np.abs(gx) + np.abs(gy) < 0.02
    angle = np.radians(tilt_deg)
    turn = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
    normals = np.stack([-gx, -gy, np.ones_like(u)], axis=-1)
    normals = (normals / np.linalg.norm(normals, axis=-1, keepdims=True)) @ turn.T
    points = np.stack([u, v, height], axis=-1) @ turn.T
    directions = LightSet.fibonacci_sphere(120).directions
    directions = directions[directions[:, 2] > 0.2]
    towards = distance * directions[:, None, None, :] - points[None]
    reach = np.linalg.norm(towards, axis=-1)
    shading = np.maximum(np.sum(towards / reach[..., None] * normals[None], axis=-1), 0.0) * (distance / reach) ** 2
    images = shading[..., None] * np.array([0.44, 0.40, 0.36]) + 0.01
    return ReflectanceField(images=images.astype(np.float32), lights=LightSet(directions)), normals, base


def test_flattening_a_plate_lit_by_near_lights_against_its_true_normals():
    """Near lights (3 half-widths away) turn a tilted plate's fitted normals by tens of degrees towards
    the frame's edges. ``trend`` gives back the true normals, tilt included, within a few degrees;
    ``level`` makes the base face the camera; the relief keeps its shape."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.model.config import FitSettings
    from warp_highlights.relight.maps import surface_maps

    dataset, truth, base = _near_lit_plate(64, distance=3.0, tilt_deg=8.0)
    field = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT), device="cpu", progress=False)
    facing = np.array([0.0, 0.0, 1.0])
    maps = {mode: surface_maps(field, device="cpu", flatten=mode) for mode in (False, "trend", "level")}
    assert np.median(_angles_deg(maps[False].normals, truth)[base]) > 15.0
    assert maps[False].lean.edge_deg > 20.0 and 6.0 < maps[False].lean.tilt_deg < 11.0
    assert np.median(_angles_deg(maps["trend"].normals, truth)[base]) < 3.0
    assert np.median(_angles_deg(maps["trend"].normals, truth)[~base]) < 2.5
    assert np.median(_angles_deg(maps["level"].normals, facing)[base]) < 3.0
    assert np.median(_angles_deg(maps[False].normals, facing)[base]) > 15.0
    assert all(m.lean == maps[False].lean for m in maps.values())  # measured before flattening
    with pytest.raises(ValueError, match="flatten"):
        surface_maps(field, device="cpu", flatten="sideways")


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


# --- the outlier rules: a pixel-by-pixel float64 reference and a synthetic crease ---------------------------

CREASE_ROWS, CREASE_COLUMNS = slice(4, 18), slice(10, 14)
TWO_LIGHT = ((2, 11), (2, 12))  # crease pixels sunlit by two lights only
SATURATED = (8, 4)  # a bright pixel, clipped at white under the lights near its normal
PIT = (17, 3)  # a single pixel in cast shadow like the crease's floor
GLOSSY = (slice(4, 18), slice(19, 21))  # a dark glossy strip: highlights near the mirror direction


def _crease_scene(seed: int = 3, *, highlights: bool = False):
    """A 22x24 grey relief (albedo about 0.5, ambient light 8% of it) under 42 dome lights, with a
    crease whose walls let only the lights with |x| < 0.2 (11 of them) reach its floor, two pixels
    there sunlit by two lights, a single pixel shadowed as the floor is, a pixel of albedo 1.6
    (without ambient light) clipped at 1, the capture's white, a dark glossy strip (albedo 0.03, Phong
    highlights of exponent 20) and, with ``highlights``, a bright sample on some pixels. Returns
    (directions, true normals, albedo, (n, H, W) values)."""
    from warp_highlights.model.lights import LightSet

    rng = np.random.default_rng(seed)
    height, width = 22, 24
    directions = LightSet.fibonacci_sphere(120).directions
    directions = directions[directions[:, 2] > 0.3]
    v, u = np.mgrid[0:height, 0:width] / np.array([height, width])[:, None, None]
    normals = np.stack([0.15 * np.sin(6 * u), 0.1 * np.cos(5 * v), np.ones_like(u)], axis=-1)
    rho = 0.5 + 0.05 * np.sin(3 * u + 2 * v)
    visible = np.ones((len(directions), height, width), dtype=bool)
    visible[:, CREASE_ROWS, CREASE_COLUMNS] = (np.abs(directions[:, 0]) < 0.2)[:, None, None]
    visible[(slice(None),) + PIT] = np.abs(directions[:, 0]) < 0.2
    pair = np.argsort(np.abs(directions[:, 0]))[:2]
    for y, x in TWO_LIGHT:
        visible[:, y, x] = False
        visible[pair, y, x] = True
    normals[SATURATED] = [0.42, 0.0, np.sqrt(1.0 - 0.42**2)]
    rho[SATURATED] = 1.6
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    ambient = np.full((height, width), 0.08)
    ambient[SATURATED] = 0.0
    shading = np.maximum(np.einsum("nk,hwk->nhw", directions, normals), 0.0)
    values = rho[None] * (shading * visible + ambient[None]) + rng.normal(scale=1e-3, size=visible.shape)
    rho[GLOSSY] = 0.03
    mirror = 2.0 * normals[GLOSSY][..., 2:3] * normals[GLOSSY] - [0.0, 0.0, 1.0]
    lobe = 0.8 * np.maximum(np.einsum("nk,hwk->nhw", directions, mirror), 0.0) ** 20
    values[(slice(None),) + GLOSSY] = 0.03 * shading[(slice(None),) + GLOSSY] + lobe
    if highlights:
        values[5, 14:20, 2:8] += 1.5
    return directions, normals, rho, np.clip(values, 0.0, 1.0)


def _reference_robust_fit(v, directions, start, lit, typical, settings, *, shadows):
    """One pixel's robust fit, as the module docstring states it: rho n and its lights."""
    used = start.copy()
    for _ in range(settings.iterations):
        scaled = np.linalg.lstsq(directions[used], v[used], rcond=None)[0]
        predicted = directions @ scaled
        residual = np.abs(v - predicted)
        base = used if shadows else lit
        median = np.median(residual[base]) if base.any() else 0.0
        kept = lit & (residual <= max(settings.outlier_factor * median, settings.outlier_floor * typical))
        if shadows:
            kept &= v >= settings.shadow_ratio * predicted
        if kept.sum() < settings.min_lit_lights:
            kept = used
        if np.array_equal(kept, used):
            break
        used = kept
    return np.linalg.lstsq(directions[used], v[used], rcond=None)[0], used


def _reference_scores(v, directions, scaled, used, settings):
    """Whether the fit explains its values: at ``min_explained``, and at all (more than their mean)."""
    mean = v[used].mean()
    spread = np.sum((v[used] - mean) ** 2)
    residual = np.sum((v[used] - directions[used] @ scaled) ** 2)
    noise = used.sum() * (settings.noise_tolerance * mean) ** 2
    return residual <= (1.0 - settings.min_explained) * spread + noise, residual <= spread + noise


def _reference_fit_normals(values, directions, usable, shape, settings):
    """``fit_normals`` pixel by pixel in float64 NumPy, from the rules in the module docstring and
    ``MapSettings``: (normals, mask, inliers, surface, shadow_fit)."""
    count, pixels = values.shape
    height, width = shape
    first = []
    for p in range(pixels):
        v, ok = values[:, p], usable[:, p]
        surface = np.percentile(v, settings.lit_percentile) >= max(settings.black_level, 1e-6)
        typical = np.percentile(v[ok], settings.lit_percentile) if ok.any() else np.nan
        with np.errstate(invalid="ignore"):
            lit = ok & surface & (v >= settings.lit_fraction * typical)
        typical = 0.0 if np.isnan(typical) else typical
        scaled, used = _reference_robust_fit(v, directions, lit, lit, typical, settings, shadows=False)
        first.append((surface, lit, typical, scaled, used) + _reference_scores(v, directions, scaled, used, settings))
    albedo = np.array([np.linalg.norm(f[3]) if f[0] else 0.0 for f in first]).reshape(height, width)
    radius = settings.neighbourhood
    padded = np.pad(albedo, radius, mode="edge")
    candidates = {}
    for p in range(pixels):
        surface, lit, typical, scaled, used, explained, _ = first[p]
        y, x = divmod(p, width)
        reference = np.percentile(padded[y:y + 2 * radius + 1, x:x + 2 * radius + 1], settings.lit_percentile)
        if not (surface and not explained and np.linalg.norm(scaled) < settings.dark_ratio * reference):
            continue
        v, ok = values[:, p], usable[:, p]
        bright = lit & (v >= settings.shadow_fraction * np.percentile(v[ok], settings.shadow_percentile))
        if bright.sum() < settings.min_lit_lights:
            bright = lit
        again, again_used = _reference_robust_fit(v, directions, bright, lit, typical, settings, shadows=True)
        level = np.linalg.norm(again)
        sunlit = np.sum(again_used & (directions @ (again / level) >= settings.shadow_fraction))
        again_explained, _ = _reference_scores(v, directions, again, again_used, settings)
        if (again_explained and sunlit >= settings.min_lit_lights
                and settings.dark_ratio * reference <= level <= reference / settings.dark_ratio):
            candidates[p] = (again, again_used)
    taken = np.zeros((height, width), dtype=bool)
    for p in candidates:
        taken[divmod(p, width)] = True
    support = np.pad(taken, settings.shadow_window)
    size = 2 * settings.shadow_window + 1
    normals = np.tile([0.0, 0.0, 1.0], (pixels, 1))
    mask, shadow, surfaces = (np.zeros(pixels, dtype=bool) for _ in range(3))
    inliers = np.zeros((count, pixels), dtype=bool)
    for p in range(pixels):
        surface, _, _, scaled, used, _, shading = first[p]
        y, x = divmod(p, width)
        surfaces[p] = surface
        if p in candidates and support[y:y + size, x:x + size].sum() >= settings.shadow_support:
            (scaled, used), shadow[p] = candidates[p], True
        length = np.linalg.norm(scaled)
        spread = np.linalg.eigvalsh(directions[used].T @ directions[used])[0] if used.any() else 0.0
        if (surface and (shading or shadow[p]) and used.sum() >= settings.min_lit_lights and length > 1e-6
                and spread >= settings.min_spread and scaled[2] > 0):
            normals[p], mask[p], inliers[:, p] = scaled / length, True, used
    return normals, mask, inliers, surfaces, shadow & mask


def _check_against_reference(luminance, directions, usable, shape, settings) -> None:
    from warp_highlights.relight.maps import fit_normals

    fit = fit_normals(luminance, directions, usable=usable, shape=shape, settings=settings)
    normals, mask, inliers, surface, shadow = _reference_fit_normals(luminance, directions, usable, shape, settings)
    np.testing.assert_array_equal(fit.surface, surface)
    np.testing.assert_array_equal(fit.shadow_fit, shadow)
    np.testing.assert_array_equal(fit.mask, mask)
    np.testing.assert_array_equal(fit.inliers, inliers)
    np.testing.assert_allclose(fit.normals, normals, atol=1e-7)


@pytest.mark.parametrize("highlights", [False, True])
def test_fit_normals_matches_its_pixel_by_pixel_float64_reference(highlights):
    """Every decision of the batched fit (lit, shadowed and clipped lights, the shadow fit, its checks,
    the determined pixels) and every normal, against the reference above on the synthetic crease."""
    from warp_highlights.model.config import MapSettings

    directions, _, _, values = _crease_scene(highlights=highlights)
    count, height, width = values.shape
    luminance, usable = values.reshape(count, -1), (values < 0.98).reshape(count, -1)
    shadow = _reference_fit_normals(luminance, directions, usable, (height, width), MapSettings())[4]
    assert np.count_nonzero(shadow) >= 20  # the crease's floor
    _check_against_reference(luminance, directions, usable, (height, width), MapSettings())


@pytest.mark.parametrize("support", [1, 5])
def test_fit_normals_matches_its_reference_on_the_coin_samples_rim(data_root, support):
    """On a 24x24 patch of the coin sample (its rim: dark metal beside the brighter paper, clipped
    highlights), where shadow fits are tried and most are refused; with a support of 1 the checks
    before it decide."""
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import MapSettings

    root = data_root / "realrti-item10"
    if not (root / "dirs.lp").is_file():
        pytest.skip(f"no {root}")
    dataset = ReflectanceField.load(root, progress=False)
    patch = np.asarray(dataset.images[:, 300:324, 150:174], dtype=np.float64)
    count = patch.shape[0]
    luminance = (patch @ np.array([0.2126, 0.7152, 0.0722])).reshape(count, -1)
    usable = ~np.any(patch >= 0.98, axis=3).reshape(count, -1)
    _check_against_reference(luminance, dataset.lights.directions, usable, (24, 24),
                             MapSettings(shadow_support=support))


def test_a_synthetic_crease_no_longer_makes_outliers():
    """The crease floor sunlit by a quarter of the lights, two pixels sunlit by two, a single shadowed
    pixel, a clipped pixel: with the earlier rules (no shadow fit, no clipped lights left out, every fit
    trusted) they were dark dots with bent normals; now the floor is fitted from its sunlit lights, the
    other shadowed pixels take their neighbours' normal and albedo, the clipped lights leave the fit,
    and a dark glossy strip keeps its fits."""
    from warp_highlights.model.config import MapSettings
    from warp_highlights.relight.maps import channel_albedo, fill_from_neighbours, fit_normals

    directions, truth, rho, values = _crease_scene()
    count, height, width = values.shape
    luminance, usable = values.reshape(count, -1), (values < 0.98).reshape(count, -1)

    def maps(fit):
        albedo = channel_albedo(values.reshape(count, -1, 1), directions, fit.normals, fit.inliers)
        known = np.concatenate([fit.normals, albedo], axis=1).reshape(height, width, 4)
        known, mask = fill_from_neighbours(known, fit.mask.reshape(height, width), fit.surface.reshape(height, width),
                                           MapSettings().neighbourhood)
        normals = known[..., :3] / np.linalg.norm(known[..., :3], axis=-1, keepdims=True)
        return _angles_deg(normals, truth), known[..., 3] / rho, mask

    earlier = MapSettings(dark_ratio=0.0, min_spread=0.0, noise_tolerance=1e6)
    before_angles, before_albedo, before_mask = maps(fit_normals(luminance, directions, settings=earlier))
    fit = fit_normals(luminance, directions, usable=usable, shape=(height, width))
    angles, albedo, mask = maps(fit)
    floor = (CREASE_ROWS, CREASE_COLUMNS)
    assert before_mask.all() and mask.all()
    # the crease floor: albedo at the ambient level before (0.12 of the true one), now the true one
    # (plus the 8% ambient light)
    assert before_albedo[floor].max() < 0.2 and before_angles[floor].max() > 6.0
    assert np.all(np.abs(albedo[floor] - 1.08) < 0.05) and angles[floor].max() < 5.0
    for pixel in TWO_LIGHT:
        assert before_albedo[pixel] < 0.2
        assert abs(albedo[pixel] - 1.08) < 0.1 and angles[pixel] < 5.0
    # the clipped pixel: bent towards the lights that do not clip before, now fitted to those alone
    assert before_angles[SATURATED] > 5.0 and before_albedo[SATURATED] < 0.9
    assert angles[SATURATED] < 0.5 and abs(albedo[SATURATED] - 1.0) < 0.01
    # the single shadowed pixel: no shadow fit without shadowed neighbours, and its first fit finds no
    # shading (it explains less than the mean): its neighbours' normal
    assert before_angles[PIT] > 5.0 and angles[PIT] < 2.0 and not fit.shadow_fit[PIT[0] * width + PIT[1]]
    # the glossy strip, dark beside brighter pixels and poorly explained by its first fit, keeps it:
    # its shadow fits found its highlights, not sunlit lights
    assert not fit.shadow_fit.reshape(height, width)[GLOSSY].any()
    # everything else is as it was
    rest = np.ones((height, width), dtype=bool)
    for pixel in (floor, SATURATED, PIT) + TWO_LIGHT:
        rest[pixel] = False
    np.testing.assert_allclose(angles[rest], before_angles[rest], atol=1e-6)


def test_lights_close_together_determine_no_normal():
    """A pixel lit only by 20 lights within 3 degrees of each other (a third of the capture's; no ambient
    light): its normal equations are ill conditioned, so it has no normal of its own; a pixel lit by
    every light has one."""
    from warp_highlights.model.config import MapSettings
    from warp_highlights.model.lights import LightSet
    from warp_highlights.relight.maps import fit_normals

    rng = np.random.default_rng(2)
    spread = LightSet.fibonacci_sphere(100).directions
    spread = spread[spread[:, 2] > 0.3][:40]
    centre = np.array([0.3, 0.1, 0.95]) / np.linalg.norm([0.3, 0.1, 0.95])
    cluster = centre + rng.normal(scale=0.02, size=(20, 3))
    directions = np.concatenate([spread, cluster / np.linalg.norm(cluster, axis=1, keepdims=True)])
    values = np.zeros((len(directions), 2))
    values[:, 0] = 0.5 * directions[:, 2]  # lit by all
    values[40:, 1] = 0.5 * directions[40:, 2]  # lit by the cluster only
    fit = fit_normals(values, directions)
    assert fit.surface.all() and fit.mask.tolist() == [True, False]
    assert fit_normals(values, directions, settings=MapSettings(min_spread=0.0)).mask.all()


def test_fill_from_neighbours_takes_the_mean_a_ring_at_a_time():
    from warp_highlights.relight.maps import fill_from_neighbours

    values = np.zeros((5, 7, 2))
    values[..., 0] = np.arange(7)[None, :]
    values[..., 1] = 1.0
    known = np.zeros((5, 7), dtype=bool)
    known[:, 0] = True
    targets = np.ones((5, 7), dtype=bool)
    targets[0, :] = False  # not the object: stays unknown
    filled, mask = fill_from_neighbours(values, known, targets, radius=2)
    np.testing.assert_array_equal(mask[1:, :3], True)
    assert not mask[1:, 3:].any() and not mask[0, 1:].any()
    np.testing.assert_allclose(filled[mask][:, 1], 1.0)
    np.testing.assert_allclose(filled[2, 1, 0], 0.0)  # the mean of its known neighbours (column 0)
    np.testing.assert_allclose(filled[2, 6, 0], 6.0)  # unknown: as it was


def test_white_level_is_the_exposure_for_files_that_clip():
    from types import SimpleNamespace

    from warp_highlights.relight.maps import white_level

    def field(source):
        return SimpleNamespace(exposure=4.0, report={"input": source})

    assert white_level(field({"format": "JPEG", "bits": 8, "values": "sRGB"})) == 4.0
    assert white_level(field({"format": "TIFF", "bits": 16, "values": "sRGB"})) == 4.0
    assert white_level(field({"format": "EXR", "bits": 32, "values": "linear"})) is None
    assert white_level(field({"format": "TIFF", "bits": 32, "values": "linear"})) is None
    assert white_level(field(None)) is None


def test_map_settings_refuse_values_outside_their_range():
    from warp_highlights.model.config import MapSettings
    from warp_highlights.model.errors import InputError

    for name, value in (("saturation", 0.0), ("min_explained", 1.5), ("shadow_ratio", 1.0), ("dark_ratio", -1.0),
                        ("min_spread", -0.1), ("shadow_support", 0), ("neighbourhood", -1)):
        with pytest.raises(InputError, match=name):
            MapSettings(**{name: value})


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
    assert 0 <= summary["pixels_from_neighbours"] <= summary["pixels_with_normal"]
    assert 0 <= summary["pixels_shadow_fit"] <= summary["pixels_with_normal"]
    assert summary["normal_frame"].startswith("x right, y up the image, z towards the camera")
    assert summary["flattened"] == "no" and summary["lean_before_flattening_deg"]["trend_at_corners"] > 4.0


def test_maps_command_suggests_flatten_where_the_normals_lean_and_flattens_when_asked(tiny_sphere, tmp_path, capsys):
    """The sphere's normals lean (its shape): without --flatten the command says how much and names
    the option; with it, maps.json says which flattening was done and the command says nothing more."""
    from warp_highlights.cli import main

    _, field = tiny_sphere
    assert main(["maps", str(field), "-o", str(tmp_path / "plain"), "--device", "cpu", "-q"]) == 0
    note = capsys.readouterr().err.strip().splitlines()
    assert len(note) == 1 and "--flatten" in note[0] and "degrees" in note[0]
    for given, mode in ((["--flatten"], "trend"), (["--flatten", "level"], "level")):
        output = tmp_path / mode
        assert main(["maps", str(field), "-o", str(output), "--device", "cpu", "-q", *given]) == 0
        assert capsys.readouterr().err == ""
        assert json.loads((output / "maps.json").read_text())["flattened"] == mode
    bad = tmp_path / "bad"
    assert main(["maps", str(field), "-o", str(bad), "--device", "cpu", "-q", "--flatten", "sideways"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "--flatten" in error[0] and not bad.exists()


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


@pytest.mark.slow
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
