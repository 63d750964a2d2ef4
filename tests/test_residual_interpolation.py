"""Radial basis weights over the lights (``model.rbf``) and a low-rank residual's interpolation chosen at fit time
(``residual.interpolation``): brute force for the closed forms, the choice's rule, the field file and relighting."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import FAST_FIT
from warp_highlights.fit.validation import leave_one_out, spread_lights
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.model.config import FitSettings, ResidualSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.model.rbf import RBF_REGULARISATION, loo_sigma, rbf_kernel, rbf_weights
from warp_highlights.model.residual import ResidualModel
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.relight.relighter import Relighter
from warp_highlights.residual.decode import light_images, light_weights
from warp_highlights.residual.device import decode_on_load
from warp_highlights.residual.interpolation import (
    choose_interpolation,
    loo_rbf_weights,
    residual_sigma,
    stack_values_at,
)
from warp_highlights.residual.quantise import fit_stack


def _lights(n: int = 24) -> np.ndarray:
    return LightSet.fibonacci_sphere(n).directions


def _lobe_images(directions, size=(12, 16), width=0.6) -> np.ndarray:
    """(n, H, W) a broad lobe whose centre moves with the light: smooth in the light direction."""
    height, wide = size
    y, x = np.mgrid[0:height, 0:wide] / np.array([height, wide])[:, None, None]
    images = []
    for d in directions:
        cx, cy = 0.5 + 0.35 * d[0], 0.5 + 0.35 * d[1]
        images.append(0.2 + np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width**2)) * (0.5 + 0.5 * d[2]))
    return np.asarray(images)


def _interpolant(lights, values, queries, sigma):
    """Brute force: the radial basis interpolant of ``values`` (n, S) at ``lights``, (K + lambda I) a = y solved,
    evaluated at ``queries``."""
    system = rbf_kernel(lights, lights, sigma) + RBF_REGULARISATION * np.eye(len(lights))
    return rbf_kernel(queries, lights, sigma) @ np.linalg.solve(system, values)


def test_rbf_weights_interpolate_the_lights_and_match_the_solve():
    lights = _lights()
    values = np.random.default_rng(0).normal(size=(len(lights), 5))
    weights = rbf_weights(lights, lights, 0.5)
    np.testing.assert_allclose(weights @ values, values, atol=1e-4)  # lambda misses them by a little
    queries = np.array([[0.1, 0.2, 0.97], [0.6, -0.6, 0.53], [0.0, 0.0, -1.0]])
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    np.testing.assert_allclose(rbf_weights(queries, lights, 0.5) @ values, _interpolant(lights, values, queries, 0.5),
                               atol=1e-9)


def test_leave_one_out_weights_are_the_interpolant_of_the_other_lights():
    """Row j of ``loo_rbf_weights`` predicts light j from the others as a fit without j does (brute force), and
    ``loo_sigma`` scores those predictions' errors (Rippa's closed form)."""
    lights = _lights(16)
    values = np.random.default_rng(1).normal(size=(len(lights), 3))
    sigma = 0.6
    weights = loo_rbf_weights(lights, sigma)
    for j in range(len(lights)):
        others = np.delete(np.arange(len(lights)), j)
        brute = _interpolant(lights[others], values[others], lights[j : j + 1], sigma)
        assert weights[j, j] == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose(weights[j] @ values, brute[0], atol=1e-6)
    _, _, errors = loo_sigma(values, lights, candidates=[sigma])
    assert errors[0] == pytest.approx(np.mean((values - weights @ values) ** 2), rel=1e-6)


def test_loo_sigma_takes_the_least_error_among_the_candidates():
    lights = _lights(20)
    values = _lobe_images(lights).reshape(len(lights), -1)
    sigma, candidates, errors = loo_sigma(values, lights)
    assert sigma == candidates[np.argmin(errors)]
    for k in range(0, len(candidates), 10):
        predicted = np.stack([_interpolant(np.delete(lights, j, 0), np.delete(values, j, 0), lights[j : j + 1],
                                           candidates[k])[0] for j in range(len(lights))])
        assert errors[k] == pytest.approx(np.mean((values - predicted) ** 2), rel=1e-5)
    with pytest.raises(InputError, match="at least 2 lights"):
        loo_sigma(values[:1], lights[:1])


def _lowrank(images: np.ndarray) -> ResidualModel:
    return ResidualModel(luminance=fit_stack(images[..., None].astype(np.float32), 6, bits=16))


def test_stack_values_at_are_the_decoded_images_there():
    lights = _lights(12)
    residual = _lowrank(_lobe_images(lights))
    rows, columns = np.array([0, 3, 11, 5]), np.array([15, 0, 7, 7])
    decoded = light_images(residual, np.eye(len(lights)))
    np.testing.assert_allclose(stack_values_at(residual.luminance, rows, columns)[..., 0], decoded[:, rows, columns, 0],
                               atol=1e-5)


def _choose(residual, images, lights, wanted: str, margin: float = 0.1):
    loo = leave_one_out(lights, spread_lights(lights, 10))
    own = np.zeros(images.shape[:3], np.float32)
    settings = ResidualSettings(interpolation=wanted, interpolation_margin_db=margin)
    return choose_interpolation(residual, images[..., None], own, None, lights, loo.lights, loo.vertices,
                                loo.barycentric, factor=1.0, settings=settings)


def test_a_broad_smooth_residual_on_few_lights_takes_radial_basis_weights():
    """A broad lobe seen by 16 lights: the radial basis predicts the left-out lights better than their triangles,
    and "auto" keeps it with the sigma of least leave-one-out error; a margin beyond the gap keeps the triangle."""
    lights = _lights(16)
    images = _lobe_images(lights)
    residual = _lowrank(images)
    chosen, choice = _choose(residual, images, lights, "auto")
    assert choice.chosen == "rbf" and chosen.rbf_sigma == choice.sigma == residual_sigma(residual, lights)
    assert np.mean(choice.rbf_psnr) > np.mean(choice.triangle_psnr) + 0.1
    report = choice.report()
    assert report["chosen"] == "rbf" and report["lights"] == len(choice.lights) == 10
    gap = float(np.mean(choice.rbf_psnr) - np.mean(choice.triangle_psnr))
    kept, choice = _choose(residual, images, lights, "auto", margin=gap + 0.01)
    assert choice.chosen == "triangle" and kept.rbf_sigma is None
    forced, choice = _choose(residual, images, lights, "rbf", margin=1000.0)
    assert choice.chosen == "rbf" and forced.rbf_sigma is not None
    same, choice = _choose(residual, images, lights, "triangle")
    assert same is residual and choice.report() == {"chosen": "triangle", "lights": 0}


def test_the_scores_are_the_predictions_psnr():
    """The reported scores are 8-bit sRGB PSNR of each left-out light predicted from its triangle and from the
    other lights' radial basis interpolant (float64 brute force)."""
    from warp_highlights.io.images import display_rgb8
    from warp_highlights.quality.metrics import psnr_8bit

    lights = _lights(16)
    images = _lobe_images(lights)
    residual = _lowrank(images)
    _, choice = _choose(residual, images, lights, "auto")
    loo = leave_one_out(lights, spread_lights(lights, 10))
    decoded = light_images(residual, np.eye(len(lights)))
    for k, j in enumerate(choice.lights):
        triangle = np.tensordot(loo.barycentric[k], decoded[loo.vertices[k]], axes=1)
        others = np.delete(np.arange(len(lights)), j)
        flat = decoded[others].reshape(len(others), -1)
        rbf = _interpolant(lights[others], flat, lights[j : j + 1], choice.sigma).reshape(decoded.shape[1:])
        truth = display_rgb8(images[j])
        expected = psnr_8bit(display_rgb8(np.maximum(triangle, 0)), truth)
        assert choice.triangle_psnr[k] == pytest.approx(expected, abs=1e-9)
        assert choice.rbf_psnr[k] == pytest.approx(psnr_8bit(display_rgb8(np.maximum(rbf, 0)), truth), abs=0.05)


def test_light_weights_are_the_triangle_or_the_radial_basis():
    lights = _lights(16)
    residual = _lowrank(_lobe_images(lights))
    triangulation = SphericalTriangulation(lights)
    queries = np.array([[0.2, 0.1, 0.97], [-0.5, 0.5, 0.7]])
    triangle = light_weights(residual, triangulation, queries)
    location = triangulation.locate(queries)
    assert np.count_nonzero(triangle, axis=1).max() <= 3
    np.testing.assert_allclose(triangle.sum(axis=1), 1.0)
    np.testing.assert_allclose(np.take_along_axis(triangle, location.vertices.astype(np.int64), axis=1),
                               location.barycentric)
    rbf = dataclasses.replace(residual, rbf_sigma=0.5)
    np.testing.assert_allclose(light_weights(rbf, triangulation, queries),
                               rbf_weights(location.directions, lights, 0.5))


def test_a_radial_basis_width_needs_a_low_rank_residual():
    images = np.zeros((4, 2, 3, 1), np.float16)
    with pytest.raises(InputError, match="radial basis"):
        ResidualModel(images=images, rbf_sigma=0.5)
    residual = _lowrank(_lobe_images(_lights(8)))
    for bad in (0.0, -1.0, float("nan"), 5.0):
        with pytest.raises(InputError, match="radial basis"):
            dataclasses.replace(residual, rbf_sigma=bad)
    with pytest.raises(InputError, match="interpolation must be one of"):
        ResidualSettings(interpolation="nearest")


@pytest.fixture(scope="module")
def rbf_field(small_donut, tmp_path_factory):
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.interpolation=rbf"])
    return fit_field(dataset, settings=settings, device="cpu", progress=False)


def test_a_fit_asked_for_radial_basis_weights_keeps_them_and_reports_both_scores(rbf_field, tmp_path):
    field = rbf_field
    assert field.residual.rbf_sigma is not None
    report = field.report["residual"]["residual_interpolation"]
    assert report["chosen"] == "rbf" and report["rbf_sigma"] == pytest.approx(field.residual.rbf_sigma, abs=1e-5)
    assert report["lights"] > 0 and np.isfinite([report["triangle_psnr_db"], report["rbf_psnr_db"]]).all()
    assert "radial basis" in field.residual.describe()
    path = tmp_path / "rbf.whf"
    save_field(field, path)
    loaded = load_field(path)
    assert loaded.residual.rbf_sigma == field.residual.rbf_sigma
    directions = np.array([[0.3, 0.2, 0.9], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(Relighter(loaded, device="cpu").relight(directions).full,
                                  Relighter(field, device="cpu").relight(directions).full)
    with pytest.raises(InputError, match="radial basis"):
        decode_on_load(field.residual, field.width * field.height, "load", "cpu")
    assert not decode_on_load(field.residual, field.width * field.height, "auto", "cpu")


def test_a_field_file_refuses_a_bad_radial_basis_width_and_reads_older_files_without_one(rbf_field, tmp_path):
    import json
    import zipfile

    path = tmp_path / "rbf.whf"
    save_field(rbf_field, path)

    def rewritten(sigma, name):
        out = tmp_path / name
        with zipfile.ZipFile(path) as source, zipfile.ZipFile(out, "w") as target:
            for item in source.infolist():
                data = source.read(item.filename)
                if item.filename == "header.json":
                    header = json.loads(data)
                    if sigma == "absent":
                        header["format_version"] = 7
                        del header["residual"]["rbf_sigma"]
                    else:
                        header["residual"]["rbf_sigma"] = sigma
                    data = json.dumps(header).encode()
                target.writestr(item, data)
        return out

    assert load_field(rewritten("absent", "v7.whf")).residual.rbf_sigma is None
    for k, bad in enumerate(("wide", -0.5, 9.0, True)):
        with pytest.raises(InputError, match="rbf_sigma"):
            load_field(rewritten(bad, f"bad{k}.whf"))
