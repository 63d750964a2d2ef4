"""The learned residual (``kernels.neural``, ``fit --residual learned``) against float64 NumPy: values,
tape gradients against central differences, training that lowers the loss, and a learned field fitted,
saved, loaded and relit as the reference says."""

from __future__ import annotations

import numpy as np
import pytest
import reference
import warp as wp
from conftest import FAST_FIT
from warp_highlights.kernels import neural

from warp_highlights.fit.residual import learn_residual
from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import NEURAL_LAYER_SHAPES, NeuralResidual, ResidualModel, decode_display, encode_display


def _problem(seed=0, lights=6, pixels=70):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    targets = rng.uniform(0.0, 1.0, (lights, pixels, 3)).astype(np.float32)
    return directions, targets


def test_decode_matches_reference(device):
    directions, targets = _problem()
    model = neural.initial_model(targets, seed=3)
    got = neural.decode(model, directions, device=device, batch=100)  # several batches, the last one padded
    want = reference.neural_decoder(model.codes, model.weights, directions)
    np.testing.assert_allclose(got, want, atol=2e-5, rtol=1e-4)


def test_initial_codes_are_the_leading_components():
    directions, targets = _problem(pixels=200)
    codes = neural.initial_model(targets).codes
    assert codes.shape == (200, neural.CODE_SIZE)
    np.testing.assert_allclose(codes.std(axis=0), 1.0, rtol=1e-4)
    np.testing.assert_allclose(codes.T @ codes / 200, np.eye(neural.CODE_SIZE), atol=1e-4)  # uncorrelated: principal components


def test_tape_gradients_match_central_differences(device):
    directions, targets = _problem(seed=1, lights=5, pixels=40)
    model = neural.initial_model(targets, seed=2)
    codes, weights = neural._arrays(model, device, True)
    pixels = len(model.codes)
    total = len(directions) * pixels
    batch = neural._Batch(neural._padded(total), device, True)
    samples = wp.array(np.arange(total, dtype=np.int32), dtype=wp.int32, device=device)
    loss = wp.zeros(1, dtype=float, device=device, requires_grad=True)
    target_array = wp.array(targets, dtype=wp.vec3, device=device)
    light_array = wp.array(directions.astype(np.float32), dtype=wp.vec3, device=device)
    tape = wp.Tape()
    with tape:
        batch.run(samples, total, pixels, codes, light_array, weights, device)
        wp.launch(neural.squared_error, dim=total, inputs=[samples, total, pixels, batch.values, target_array, 1.0 / total], outputs=[loss], device=device)
    tape.backward(loss)

    params = [model.codes.astype(np.float64)] + [w.astype(np.float64) for w in model.weights]

    def mse(values):
        return np.mean(np.sum((reference.neural_decoder(values[0], values[1:], directions) - targets) ** 2, axis=-1))

    assert loss.numpy()[0] == pytest.approx(mse(params), rel=1e-5)
    arrays = [codes, *weights]
    rng = np.random.default_rng(0)
    for which in range(len(params)):
        gradient = arrays[which].grad.numpy()
        for _ in range(2):
            index = tuple(rng.integers(0, s) for s in params[which].shape)
            step = 1e-4
            plus = [p.copy() for p in params]
            minus = [p.copy() for p in params]
            plus[which][index] += step
            minus[which][index] -= step
            numeric = (mse(plus) - mse(minus)) / (2 * step)
            assert gradient[index] == pytest.approx(numeric, rel=2e-3, abs=2e-6), (which, index)


def test_training_learns_a_smooth_reflectance(device):
    """Lambertian pixels with random normals and albedos: 150 epochs fit them far below their variance."""
    rng = np.random.default_rng(4)
    lights = rng.normal(size=(12, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.3
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    normals = rng.normal(size=(64, 3)) * [0.4, 0.4, 1.0]
    normals[:, 2] = np.abs(normals[:, 2])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.2, 0.9, (64, 3))
    targets = encode_display(np.clip(lights @ normals.T, 0.0, None)[..., None] * albedo[None]).astype(np.float32)
    model, history = neural.train_decoder(targets, lights, device=device, epochs=150, batch=192, lr=1e-2, final_lr=1e-3)
    assert len(history) == 150 and np.all(np.isfinite(history))
    variance = float(np.mean(np.sum((targets - targets.mean(axis=(0, 1))) ** 2, axis=-1)))
    assert history[-1] < 0.05 * variance
    decoded = neural.decode(model, lights, device=device)
    assert np.mean(np.sum((decoded - targets) ** 2, axis=-1)) < 0.05 * variance


def test_display_encoding_round_trips():
    values = np.array([-2.0, -0.5, -1e-3, 0.0, 1e-4, 0.002, 0.2, 0.9])
    encoded = encode_display(values)
    assert np.all(np.diff(encoded) > 0) and encoded[3] == 0.0
    inside = np.abs(values) <= 1
    np.testing.assert_allclose(decode_display(encoded)[inside], values[inside], rtol=1e-5, atol=1e-7)


def test_learned_field_fits_saves_and_relights_as_the_reference(small_donut, tmp_path):
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.fieldfile import load_field, save_field
    from warp_highlights.model.config import FitSettings
    from warp_highlights.relight.relighter import Relighter

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.learned=true", "residual.learned_epochs=2"])
    field = fit_field(dataset, device="cpu", settings=settings, progress=False)
    learned = field.residual.learned
    assert learned is not None and field.residual.images is None and field.residual.luminance is None
    assert field.report["residual"]["learned"]["epochs"] == 2
    assert learned.unit == pytest.approx(field.exposure) and learned.codes.shape == (field.height, field.width, neural.CODE_SIZE)
    path = tmp_path / "learned.whf"
    save_field(field, path)
    loaded = load_field(path)
    np.testing.assert_array_equal(loaded.residual.learned.codes, learned.codes)
    for got, want in zip(loaded.residual.learned.weights, learned.weights):
        np.testing.assert_array_equal(got, want)
    directions = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86], [0.0, -0.7, 0.71]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    relit = Relighter(loaded, device="cpu").relight(directions)
    highlights = Relighter(loaded, device="cpu", diffuse="none").relight(directions).full
    want = np.clip(loaded.residual.learned.images(directions) + highlights, 0.0, None)
    assert np.all(np.isfinite(relit.full)) and relit.full.min() >= 0
    np.testing.assert_allclose(relit.full, want, atol=2e-3 * max(1.0, float(np.abs(want).max())))  # the decoded residual passes through float16

    from test_field import load_error, rewrite

    data = path.read_bytes()
    broken = tmp_path / "broken.whf"
    rewrite(data, broken, header=lambda h: {**h, "residual": {**h["residual"], "learned": {"unit": -1.0, "lights": 32}}})
    assert "residual.learned" in load_error(broken)
    rewrite(data, broken, drop=("residual/learned_w2.npy",))
    assert "learned_w2" in load_error(broken)


def test_learned_residual_needs_colour_images():
    from warp_highlights.model.config import ResidualSettings

    with pytest.raises(InputError, match="colour"):
        learn_residual(np.zeros((4, 8, 8, 1), np.float32), np.zeros((4, 8, 8), np.float32), None, np.eye(3)[[0, 1, 2, 2]], factor=1.0,
                       settings=ResidualSettings(learned=True), device="cpu")


def test_learned_residual_checks_its_arrays():
    weights = tuple(np.zeros(shape, np.float32) for shape in NEURAL_LAYER_SHAPES)
    good = NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, 2.0, 7)
    model = ResidualModel(learned=good)
    assert (model.height, model.width, model.channels, model.light_count, model.compressed) == (4, 5, 3, 7, False)
    with pytest.raises(InputError, match="codes"):
        NeuralResidual(np.zeros((4, 5, 8), np.float16), weights, 2.0, 7)
    with pytest.raises(InputError, match="weight arrays"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights[:-1], 2.0, 7)
    with pytest.raises(InputError, match="unit"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, -1.0, 7)
    with pytest.raises(InputError, match="exactly one"):
        ResidualModel(images=np.zeros((7, 4, 5, 3), np.float16), learned=good)
    with pytest.raises(InputError, match="per query"):
        model.light_images(np.eye(7)[:1])


def test_training_time_counts_from_the_first_step():
    """``seconds`` bounds training after the first step (which compiles the kernels): a tiny bound runs one epoch."""
    directions, targets = _problem(seed=5)
    _, history = neural.train_decoder(targets, directions, device="cpu", epochs=50, batch=128, seconds=1e-9)
    assert len(history) == 1
