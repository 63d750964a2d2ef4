"""The RTI baselines (kernels/baselines.py, warp_highlights/relight/baselines.py) against float64 references."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from reference import (
    baseline_terms,
    gaussian_rbf,
    least_squares_planes,
    rbf_loo_brute_force,
    rbf_relit,
    relit_planes,
)
from warp_highlights.kernels import baselines as kernels
from warp_highlights.model.errors import InputError
from warp_highlights.relight import (
    BASELINE_METHODS,
    BaselineModel,
    baseline_basis,
    choose_rbf_sigma,
    fit_baseline,
)
from warp_highlights.relight.baselines import (
    RBF_SIGMA_FACTORS,
    hsh_basis,
    rbf_loo_errors,
)

HEIGHT, WIDTH, CHANNELS = 5, 7, 3
COUNTS = {"ptm": 6, "hsh2": 4, "hsh3": 9}


def dome(count: int, seed: int = 0, min_z: float = 0.15) -> np.ndarray:
    """(count, 3) random unit directions of the upper hemisphere, z >= min_z."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(min_z, 1.0, count)
    phi = rng.uniform(0, 2 * np.pi, count)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def stack(count: int, seed: int = 1, shape=(HEIGHT, WIDTH, CHANNELS)) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, size=(count, *shape)).astype(np.float32)


# --- the kernels ----------------------------------------------------------------------------------


def test_project_and_evaluate_kernels_match_matrix_products(device):
    rng = np.random.default_rng(2)
    matrix = rng.normal(size=(5, 11)).astype(np.float32)
    images = rng.normal(size=(11, 37)).astype(np.float32)
    basis = rng.normal(size=(4, 5)).astype(np.float32)
    planes = kernels.project(wp.array(matrix, dtype=float, device=device), wp.array(images, dtype=float, device=device))
    expected = matrix.astype(np.float64) @ images
    np.testing.assert_allclose(planes.numpy(), expected, rtol=1e-5, atol=1e-5)
    out = kernels.evaluate(wp.array(basis, dtype=float, device=device), planes).numpy()
    np.testing.assert_allclose(out, np.maximum(basis.astype(np.float64) @ expected, 0.0), rtol=1e-4, atol=1e-4)
    assert (out == 0).any() and (out >= 0).all()  # some sums were negative: clamped


def test_evaluate_never_returns_negative_nan_or_inf(device):
    planes = np.array([[1.0, -1.0, np.nan, 3e38]], dtype=np.float32)
    basis = np.array([[1.0], [10.0]], dtype=np.float32)
    out = kernels.evaluate(wp.array(basis, dtype=float, device=device),
                           wp.array(planes, dtype=float, device=device)).numpy()
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    np.testing.assert_array_equal(out[:, :3], [[1.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    assert out[1, 3] == np.finfo(np.float32).max


# --- basis functions ------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["ptm", "hsh2", "hsh3"])
def test_basis_matches_reference_including_lights_below_the_horizon(method):
    directions = np.concatenate([dome(20), [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, -0.8], [0.0, 0.0, -1.0]]])
    basis = baseline_basis(method, directions)
    assert basis.shape == (len(directions), COUNTS[method]) and np.all(np.isfinite(basis))
    np.testing.assert_allclose(basis, baseline_terms(method, directions), atol=1e-12)


def test_hsh_orders_nest_and_are_orthonormal_on_the_hemisphere():
    """Gautron's basis is orthonormal over the hemisphere (solid angle): checked by a fine quadrature."""
    steps = 400  # midpoint rule in theta and phi
    theta, phi = np.meshgrid((np.arange(steps) + 0.5) * (np.pi / 2 / steps),
                             (np.arange(2 * steps) + 0.5) * (np.pi / steps), indexing="ij")
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1).reshape(-1, 3)
    weight = (np.sin(theta) * (np.pi / 2 / steps) * (np.pi / steps)).reshape(-1)
    basis = hsh_basis(d, 3)
    np.testing.assert_allclose(hsh_basis(d, 2), basis[:, :4])
    gram = basis.T @ (basis * weight[:, None])
    np.testing.assert_allclose(gram, np.eye(9), atol=2e-3)


# --- fits against the references ------------------------------------------------------------------


@pytest.mark.parametrize("method", ["ptm", "hsh2", "hsh3"])
def test_least_squares_fit_and_relight_match_reference(method, device):
    lights, images = dome(24), stack(24)
    model = fit_baseline(method, images, lights, device=device)
    expected = least_squares_planes(baseline_terms(method, lights), images)
    np.testing.assert_allclose(model.coefficients(), expected, rtol=1e-4, atol=1e-4)
    queries = dome(9, seed=5, min_z=-0.2)
    relit = model.relight(queries)
    assert relit.shape == (9, HEIGHT, WIDTH, CHANNELS) and relit.dtype == np.float32
    np.testing.assert_allclose(relit, relit_planes(baseline_terms(method, queries), expected), atol=2e-4)


@pytest.mark.parametrize("method", ["ptm", "hsh2", "hsh3"])
def test_images_in_the_span_are_reproduced_exactly(method, device):
    """Images made from random coefficients (a positive constant term) come back, at the lights and anywhere."""
    rng = np.random.default_rng(3)
    lights = dome(30, seed=4)
    truth = rng.normal(scale=0.3, size=(COUNTS[method], HEIGHT, WIDTH, CHANNELS))
    truth[5 if method == "ptm" else 0] = 4.0  # the constant term keeps every image positive
    images = relit_planes(baseline_terms(method, lights), truth)
    assert images.min() > 0
    model = fit_baseline(method, images.astype(np.float32), lights, device=device)
    np.testing.assert_allclose(model.coefficients(), truth, atol=2e-5)
    queries = dome(6, seed=6)
    np.testing.assert_allclose(model.relight(queries), relit_planes(baseline_terms(method, queries), truth), rtol=1e-5,
                               atol=1e-5)
    np.testing.assert_allclose(model.relight(lights), images, rtol=1e-5, atol=1e-5)


def test_rbf_relight_matches_reference(device):
    lights, images = dome(15), stack(15)
    model = fit_baseline("rbf", images, lights, device=device, sigma=0.5)
    queries = dome(8, seed=7, min_z=-0.3)
    expected = rbf_relit(images, lights, queries, 0.5, model.regularisation)
    np.testing.assert_allclose(model.relight(queries), expected, atol=1e-4)
    np.testing.assert_array_equal(model.coefficients(), images)  # the planes are the light images


def test_rbf_interpolates_the_training_lights(device):
    lights, images = dome(20), stack(20)
    model = fit_baseline("rbf", images, lights, device=device, sigma=0.4, regularisation=1e-10)
    np.testing.assert_allclose(model.relight(lights), images, atol=1e-4)


def test_rbf_loo_closed_form_equals_brute_force():
    lights = dome(9, seed=8)
    values = np.random.default_rng(9).normal(size=(9, 4))
    for sigma, regularisation in [(0.3, 1e-6), (0.8, 1e-3)]:
        matrix = gaussian_rbf(lights, lights, sigma) + regularisation * np.eye(9)
        np.testing.assert_allclose(rbf_loo_errors(matrix, values),
                                   rbf_loo_brute_force(lights, values, sigma, regularisation), rtol=1e-6, atol=1e-9)


def test_rbf_sigma_is_the_loo_minimum_over_the_grid():
    lights, images = dome(16, seed=10), stack(16, seed=11)
    model = fit_baseline("rbf", images, lights, device="cpu")
    candidates, errors = model.loo
    assert len(candidates) == len(RBF_SIGMA_FACTORS) and model.sigma == candidates[np.argmin(errors)]
    values = images.reshape(16, -1).astype(np.float64)  # fewer pixels than the subsample: all of them
    k = len(candidates) // 2
    np.testing.assert_allclose(errors[k],
                               np.mean(rbf_loo_brute_force(lights, values, candidates[k], model.regularisation) ** 2),
                               rtol=1e-6)
    sigma, _, _ = choose_rbf_sigma(images, lights, candidates=[0.2, candidates[np.argmin(errors)], 3.0])
    assert sigma == model.sigma


def test_rbf_loo_subsamples_large_images():
    lights = dome(6, seed=12)
    images = stack(6, shape=(80, 80))
    sigma, candidates, errors = choose_rbf_sigma(images, lights, pixels=100)
    assert sigma in candidates and np.all(np.isfinite(errors))


# --- outputs and attributes -----------------------------------------------------------------------


@pytest.mark.parametrize("method", BASELINE_METHODS)
def test_outputs_are_non_negative_finite_and_shaped(method, device):
    lights, images = dome(12, seed=13), stack(12, seed=14, shape=(HEIGHT, WIDTH))  # grayscale
    model = fit_baseline(method, images, lights, device=device)
    assert isinstance(model, BaselineModel) and model.method == method
    queries = np.concatenate([dome(30, seed=15, min_z=-1.0), [[0, 0, 1], [0, 0, -1], [1e-30, 0, 1e-30]]])
    relit = model.relight(queries)
    assert relit.shape == (len(queries), HEIGHT, WIDTH, 1)
    assert np.all(np.isfinite(relit)) and relit.min() >= 0
    assert model.relight(np.array([0.0, 0.0, 5.0])).shape == (HEIGHT, WIDTH, 1)
    m = 12 if method == "rbf" else COUNTS[method]
    assert (model.coefficient_count, model.bytes_per_pixel_8bit) == (m, m)
    assert (model.sigma is not None) == (method == "rbf")


def test_bytes_per_pixel_count_channels():
    lights, images = dome(10), stack(10)
    assert fit_baseline("hsh3", images, lights, device="cpu").bytes_per_pixel_8bit == 27
    assert fit_baseline("rbf", images, lights, device="cpu", sigma=0.5).bytes_per_pixel_8bit == 30


def test_relight_in_chunks_equals_one_launch(device):
    model = fit_baseline("hsh3", stack(12), dome(12), device=device)
    queries = dome(7, seed=16)
    whole = model.relight(queries)
    model.max_batch = 2
    np.testing.assert_array_equal(model.relight(queries), whole)
    assert (max(1, 256 * 2**20 // (4 * HEIGHT * WIDTH * CHANNELS))
            == fit_baseline("ptm", stack(12), dome(12), device=device).max_batch)


def test_fits_are_linear_in_the_values():
    lights, images = dome(14), stack(14)
    for method in BASELINE_METHODS:
        a = fit_baseline(method, images, lights, device="cpu", **({"sigma": 0.6} if method == "rbf" else {}))
        b = fit_baseline(method, 3 * images, lights, device="cpu", **({"sigma": 0.6} if method == "rbf" else {}))
        queries = dome(5, seed=17)
        np.testing.assert_allclose(b.relight(queries), 3 * a.relight(queries), rtol=1e-5, atol=1e-5)


# --- bad input ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("method", "images", "directions", "options", "match"),
    [
        ("pca", stack(8), dome(8), {}, "method must be one of"),
        ("ptm", stack(5), dome(5), {}, "6 coefficients but only 5 lights"),
        ("hsh3", stack(8), dome(8), {}, "9 coefficients but only 8 lights"),
        ("ptm", stack(8)[0], dome(8), {}, "shape"),
        ("ptm", np.zeros((8, 0, 3)), dome(8), {}, "shape"),
        ("ptm", stack(8), dome(7), {}, "light directions must have shape"),
        ("ptm", stack(8), dome(8)[:, :2], {}, "light directions must have shape"),
        ("ptm", np.where(np.arange(8)[:, None, None, None] == 3, np.nan, stack(8)), dome(8), {},
         "image 3 has non-finite"),
        ("ptm", stack(8).astype(np.float64) * 1e40, dome(8), {}, "non-finite"),
        ("ptm", stack(8), np.where(np.arange(8)[:, None] == 2, 0.0, dome(8)), {}, "light direction 2 is zero"),
        ("ptm", stack(8), np.where(np.arange(8)[:, None] == 1, np.inf, dome(8)), {},
         "light direction 1 is zero or not finite"),
        ("ptm", stack(8), dome(8), {"sigma": 0.5}, "only to the rbf method"),
        ("rbf", stack(8), dome(8), {"sigma": 0.0}, "sigma must be a positive"),
        ("rbf", stack(8), dome(8), {"sigma": float("nan")}, "sigma must be a positive"),
        ("rbf", stack(8), dome(8), {"regularisation": 0.0}, "regularisation must be a positive"),
        ("rbf", stack(1), dome(1), {}, "at least 2 lights"),
        ("ptm", "images", dome(8), {}, "images must be"),
    ],
)
def test_bad_inputs_raise_one_line_input_errors(method, images, directions, options, match):
    with pytest.raises(InputError, match=match) as error:
        fit_baseline(method, images, directions, device="cpu", **options)
    assert "\n" not in str(error.value)


def test_bad_query_directions_raise_input_errors():
    model = fit_baseline("ptm", stack(8), dome(8), device="cpu")
    for queries in ([0.0, 0.0, 0.0], [[1.0, 2.0]], [[np.nan, 0, 1]]):
        with pytest.raises(InputError):
            model.relight(queries)


# --- the real sample ------------------------------------------------------------------------------


@pytest.mark.realdata
@pytest.mark.slow
def test_baselines_on_the_synthrti_dome_score_as_published(data_root):
    """SynthRTI at 80x80, fitted on sRGB-encoded values, scored at the 20 Test lights (8-bit sRGB PSNR)."""
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.resample import resize_stack

    sample = data_root / "synthrti-object1-material5"
    dome_set = ReflectanceField.load(sample / "Dome", heldout=sample / "Test", linear=True, progress=False)
    images = resize_stack(dome_set.images, 80, 80)
    truth = np.round(resize_stack(dome_set.heldout.images, 80, 80) * 255)
    scores = {}
    for method in BASELINE_METHODS:
        model = fit_baseline(method, images, dome_set.lights.directions, device="cpu")
        relit = np.round(np.clip(model.relight(dome_set.heldout.lights.directions), 0, 1) * 255)
        mse = ((relit - truth) ** 2).reshape(20, -1).mean(axis=1)
        scores[method] = float(np.mean(10 * np.log10(255**2 / mse)))
    assert 24 < scores["ptm"] < 32 and 24 < scores["hsh3"] < 32 and scores["hsh2"] < scores["hsh3"], scores
    assert scores["rbf"] > scores["hsh3"] + 5, scores
