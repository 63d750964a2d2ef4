"""The learned residual (``kernels.neural``, ``fit --residual learned``) against float64 NumPy: values,
training that lowers the loss, and a learned field fitted, saved, loaded and relit as the reference says
(the training step's gradients: ``test_neural_training.py``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

import reference
from conftest import FAST_FIT
from test_neural_training import highlight_decoder_reference, seeing_decoder
from warp_highlights.kernels import neural, neural_training
from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import (
    NEURAL_LAYER_SHAPES,
    NeuralResidual,
    ResidualModel,
)
from warp_highlights.quality.metrics import srgb_psnr
from warp_highlights.residual.decode import learned_images, light_images
from warp_highlights.residual.learned import learn_residual
from warp_highlights.residual.opponent import decode_display, encode_display


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


def test_query_decoder_decodes_fewer_queries_than_its_buffers_hold(device, monkeypatch):
    """After a batch of queries, one query launches the blocks of its own samples only (not the whole
    buffer: a 480x270 query on the CPU went from 1.77 s to 0.16 s), with the same values (float16 store)."""
    directions, targets = _problem(lights=5, pixels=300)
    model = neural.initial_model(targets, seed=4)
    decoder = neural.QueryDecoder(model.codes, model.weights, 2.0, device=device)
    blocks = []
    launch_tiled = wp.launch_tiled

    def counting(kernel, *args, dim, **kwargs):
        blocks.append(dim[0])
        return launch_tiled(kernel, *args, dim=dim, **kwargs)

    monkeypatch.setattr(neural.wp, "launch_tiled", counting)
    results = []
    for rows in (directions, directions[2:3]):
        out = wp.empty((len(rows), 300, 3), dtype=wp.float16, device=device)
        decoder.decode(wp.array(rows.astype(np.float32), dtype=wp.vec3, device=device), out)
        results.append(out.numpy().astype(np.float32))
    assert blocks == [neural._padded(5 * 300) // neural.BLOCK, neural._padded(300) // neural.BLOCK]
    assert decoder._buffers.size == neural._padded(5 * 300)
    np.testing.assert_array_equal(results[1][0], results[0][2])
    want = reference.neural_decoder(model.codes, model.weights, directions[2:3])[0]
    srgb = np.abs(want)
    linear = np.where(srgb > 0.04045, ((srgb + 0.055) / 1.055) ** 2.4, srgb / 12.92) * np.sign(want) * 2.0
    np.testing.assert_allclose(results[1][0], linear, rtol=2e-3, atol=1e-4)


def _display_to_field(values: np.ndarray, unit: float) -> np.ndarray:
    """Decoded display values as ``store_decoded`` turns them into field units (float64)."""
    x = np.abs(values)
    return np.sign(values) * np.where(x > 0.04045, ((x + 0.055) / 1.055) ** 2.4, x / 12.92) * unit


def test_a_decoder_that_sees_the_highlights_decodes_as_the_reference(device):
    """w0 of 14 columns: [code, direction, sqrt(g), g] per sample over several batches (the last one padded), g
    below 0 taken as 0; the highlights are required, and a decoder without their inputs refuses them."""
    directions, _ = _problem(lights=5, pixels=70)
    model = seeing_decoder(70, seed=1)
    assert model.sees_highlights and model.weights[0].shape == (neural.HIDDEN, 14)
    g = np.random.default_rng(2).uniform(-0.5, 3.0, (5, 70)).astype(np.float32)
    got = neural.decode(model, directions, device=device, batch=100, highlights=g)
    want = highlight_decoder_reference(model.codes, model.weights, directions, g)
    np.testing.assert_allclose(got, want, atol=2e-5, rtol=1e-4)
    blind = neural.decode(neural.NeuralDecoder(model.codes, [model.weights[0][:, :12], *model.weights[1:]]),
                          directions, device=device)
    assert np.abs(got - blind).max() > 0.1  # the highlights count
    with pytest.raises(ValueError, match="sees the highlights"):
        neural.decode(model, directions, device=device)
    unseeing = neural.initial_model(_problem()[1], seed=3)
    with pytest.raises(ValueError, match="without highlight inputs"):
        neural.decode(unseeing, directions, device=device, highlights=g)


def test_the_query_decoder_takes_the_highlights_in_field_units(device):
    """Highlights (Q, H, W) in field units, divided by the unit (2.5) inside: the float16 field-unit values of the
    reference; a decoder of 12 columns decodes bit for bit as the same decoder given zero weights for the highlights'
    inputs and any highlights."""
    directions, targets = _problem(lights=4, pixels=60)
    unit = 2.5
    model = seeing_decoder(60, seed=4)
    g = np.random.default_rng(5).uniform(-0.2, 2.0, (4, 60)).astype(np.float32)
    decoder = neural.QueryDecoder(model.codes, model.weights, unit, device=device, batch=100)
    assert decoder.sees_highlights
    queries = wp.array(directions.astype(np.float32), dtype=wp.vec3, device=device)
    out = wp.empty((4, 60, 3), dtype=wp.float16, device=device)
    field = wp.array((g * unit).reshape(4, 6, 10), dtype=float, device=device)
    decoder.decode(queries, out, highlights=field)
    want = _display_to_field(highlight_decoder_reference(model.codes, model.weights, directions, g), unit)
    np.testing.assert_allclose(out.numpy().astype(np.float64), want, rtol=2e-3, atol=1e-3)
    with pytest.raises(ValueError, match="sees the highlights"):
        decoder.decode(queries, out)

    plain = neural.initial_model(targets, seed=6)
    blind = neural.QueryDecoder(plain.codes, plain.weights, unit, device=device, batch=100)
    assert not blind.sees_highlights and blind.weights[0].shape == (neural.HIDDEN, neural.INPUTS)
    with pytest.raises(ValueError, match="without highlight inputs"):
        blind.decode(queries, out, highlights=field)
    blind.decode(queries, out)
    padded = [np.concatenate([plain.weights[0], np.zeros((neural.HIDDEN, 2), np.float32)], axis=1),
              *plain.weights[1:]]
    zero_weighted = wp.empty((4, 60, 3), dtype=wp.float16, device=device)
    neural.QueryDecoder(plain.codes, padded, unit, device=device, batch=100).decode(queries, zero_weighted,
                                                                                   highlights=field)
    np.testing.assert_array_equal(out.numpy(), zero_weighted.numpy())
    want = _display_to_field(reference.neural_decoder(plain.codes, plain.weights, directions), unit)
    np.testing.assert_allclose(out.numpy().astype(np.float64), want, rtol=2e-3, atol=1e-3)


def test_initial_codes_are_the_leading_components():
    directions, targets = _problem(pixels=200)
    codes = neural.initial_model(targets).codes
    assert codes.shape == (200, neural.CODE_SIZE)
    np.testing.assert_allclose(codes.std(axis=0), 1.0, rtol=1e-4)
    # uncorrelated: principal components
    np.testing.assert_allclose(codes.T @ codes / 200, np.eye(neural.CODE_SIZE), atol=1e-4)


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
    model, history = neural_training.train_decoder(targets, lights, device=device, epochs=150, batch=192, lr=1e-2,
                                                   final_lr=1e-3)
    assert len(history) == 150 and np.all(np.isfinite(history))
    variance = float(np.mean(np.sum((targets - targets.mean(axis=(0, 1))) ** 2, axis=-1)))
    assert history[-1] < 0.05 * variance
    decoded = neural.decode(model, lights, device=device)
    assert np.mean(np.sum((decoded - targets) ** 2, axis=-1)) < 0.05 * variance


def test_initial_codes_summed_in_bands_are_the_whole_stack_s_components(monkeypatch):
    """Bands of pixels on the threads give the components of the whole (n P, 3 n) float64 stack, centred."""
    directions, targets = _problem(lights=4, pixels=1000)
    targets[:, :, 1] += np.linspace(0.0, 2.0, 4)[:, None] * targets[:, :, 0]  # one leading direction
    monkeypatch.setattr(neural, "INITIAL_BAND", 64)
    codes = neural.initial_model(targets).codes
    flat = targets.transpose(1, 0, 2).reshape(1000, -1).astype(np.float64)
    flat -= flat.mean(axis=0)
    _, vectors = np.linalg.eigh(flat.T @ flat)
    want = flat @ vectors[:, ::-1][:, : neural.CODE_SIZE]
    want /= want.std(axis=0)
    # each component up to its sign
    np.testing.assert_allclose(np.abs(np.sum(codes * want, axis=0)) / 1000, 1.0, rtol=1e-4)


def test_display_encoding_in_bands_is_the_formula(monkeypatch):
    """``encode_display`` and ``decode_display`` over many bands on the threads against the float64 formula."""
    from warp_highlights.residual import opponent

    monkeypatch.setattr(opponent, "ENCODING_BAND", 1000)
    values = np.random.default_rng(2).normal(0.0, 0.4, (7, 3001)).astype(np.float32)
    values[0, :4] = [0.0, 1.5, -3.0, 0.003]
    x = np.minimum(np.abs(values.astype(np.float64)), 1.0)
    want = np.sign(values) * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    encoded = encode_display(values)
    assert encoded.dtype == np.float32 and encoded.shape == values.shape
    np.testing.assert_allclose(encoded, want, rtol=1e-6, atol=1e-7)
    y = np.abs(want)
    linear = np.sign(want) * np.where(y <= 0.04045, y / 12.92, ((y + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(decode_display(want), linear, rtol=1e-12)
    np.testing.assert_allclose(decode_display(encoded), linear, rtol=2e-6, atol=1e-8)
    assert decode_display(want).dtype == np.float64 and decode_display(encoded).dtype == np.float32
    into = np.empty((7 * 3001,), np.float32)
    assert encode_display(values, out=into) is into and np.array_equal(into.reshape(values.shape), encoded)
    with pytest.raises(ValueError, match="contiguous float32"):
        encode_display(values, out=np.empty((3001, 7), np.float32).T)


def test_display_encoding_round_trips():
    values = np.array([-2.0, -0.5, -1e-3, 0.0, 1e-4, 0.002, 0.2, 0.9])
    encoded = encode_display(values)
    assert np.all(np.diff(encoded) > 0) and encoded[3] == 0.0
    inside = np.abs(values) <= 1
    np.testing.assert_allclose(decode_display(encoded)[inside], values[inside], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("anew", [False, True])
def test_a_settled_check_s_winner_is_kept_unless_its_left_out_lights_are_many(small_donut, monkeypatch, anew):
    """Once the learned check has settled, its winner (which then learned every light) is the residual; where the
    left-out lights are a large share of the capture (``learns_anew``: 6 of 16), the decided residual learns anew
    from every light instead, from scratch: on the 16-light bumpy donut (H200) the kept winner scored 28.36 dB along
    the paths, learning anew 30.42."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=4",
                                                     "residual.learned_settle_fraction=0.5",
                                                     "residual.learned_settle_margin_db=0",
                                                     "residual.move_support=0"])
    monkeypatch.setattr(pipeline, "learns_anew", lambda *args: anew)
    calls = []
    real = pipeline.learn_residual
    monkeypatch.setattr(pipeline, "learn_residual", lambda *args, **kwargs: calls.append(kwargs) or real(*args,
                                                                                                       **kwargs))
    field = pipeline.fit_field(dataset, device="cpu", settings=settings, progress=False)
    residual = field.report["residual"]
    assert residual["learned_check"]["settled_epoch"] == 2
    assert residual["learned"]["continued_from_check"] == (not anew)
    if anew:
        assert len(calls) == 1 and calls[0]["initial"] is None and not calls[0]["tune"]
        assert residual["learned"]["epochs"] == 4
    else:
        assert calls == []


def test_learned_field_fits_saves_and_relights_as_the_reference(small_donut, tmp_path, capsys):
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.fieldfile import load_field, save_field
    from warp_highlights.model.config import FitSettings
    from warp_highlights.relight.relighter import Relighter
    from warp_highlights.residual.learned import tie_margin

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=2",
                                                     "residual.learned_tune_epochs=2"])
    field = fit_field(dataset, device="cpu", settings=settings, progress=False)
    learned = field.residual.learned
    assert learned is not None and field.residual.images is None and field.residual.luminance is None
    assert field.report["residual"]["learned"]["epochs"] == 2
    # the move check let the Gaussians move, so the learned check ran
    verdict = field.report["residual"]["learned_check"]
    assert field.report["residual"]["move_check"]["moves"] and verdict["lights"] == 6
    # the margin of a capture whose Gaussians glide, or the plain one
    margin = tie_margin(settings.residual, coherence=field.report["residual"]["motion_coherence"])
    glide = settings.residual.learned_glide_margin_db
    assert verdict["tie_margin_db"] == margin and verdict["glides"] == (margin == glide)
    keeps = verdict["with_gaussians_psnr_db"] >= verdict["images_alone_psnr_db"] - margin
    assert verdict["keeps_gaussians"] == keeps and bool(field.estimated.active.any()) == keeps
    assert (learned.unit == pytest.approx(field.exposure)
            and learned.codes.shape == (field.height, field.width, neural.CODE_SIZE))
    path = tmp_path / "learned.whf"
    save_field(field, path)
    loaded = load_field(path)
    np.testing.assert_array_equal(loaded.residual.learned.codes, learned.codes)
    for got, want in zip(loaded.residual.learned.weights, learned.weights):
        np.testing.assert_array_equal(got, want)
    # bounds: the range of what it learned (the images less their own highlights) at the captured lights, widened by
    # the images' own range on either side
    np.testing.assert_array_equal(loaded.residual.learned.bounds, learned.bounds)
    from warp_highlights.residual.inputs import render_own

    images = dataset.images.astype(np.float64) * field.exposure
    own = render_own(field.estimated, field.height, field.width, raster=settings.raster, device="cpu")
    tint = np.ones(3) if field.residual.highlight_colour is None else field.residual.highlight_colour
    residual = images - own[..., None].astype(np.float64) * tint
    span = images.max(axis=0) - images.min(axis=0)
    tolerance = 2e-3 * max(1.0, float(np.abs(residual).max() + span.max()))
    np.testing.assert_allclose(learned.bounds[0], residual.min(axis=0) - span, atol=tolerance)
    np.testing.assert_allclose(learned.bounds[1], residual.max(axis=0) + span, atol=tolerance)
    directions = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86], [0.0, -0.7, 0.71]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    relit = Relighter(loaded, device="cpu").relight(directions)
    highlights = Relighter(loaded, device="cpu", diffuse="none").relight(directions).full
    want = np.clip(learned_images(loaded.residual.learned, directions) + highlights, 0.0, None)
    assert np.all(np.isfinite(relit.full)) and relit.full.min() >= 0
    # the decoded residual passes through float16
    np.testing.assert_allclose(relit.full, want, atol=2e-3 * max(1.0, float(np.abs(want).max())))

    from warp_highlights.cli import (
        main,  # relit on the CPU, the command says once that a lowrank field would be faster here
    )

    capsys.readouterr()
    assert main(["relight", str(path), "--light", "0.3,0.2,0.93", "-o", str(tmp_path / "relit.png"), "--device",
                 "cpu"]) == 0
    assert "--residual lowrank" not in capsys.readouterr().err  # decoded by NumPy's threads: no slow-CPU note
    assert main(["relight", str(path), "--light", "0.3,0.2,0.93", "-o", str(tmp_path / "relit.png"), "--device", "cpu",
                 "-q", "--overwrite"]) == 0
    assert "--residual lowrank" not in capsys.readouterr().err

    from test_field import load_error, rewrite

    data = path.read_bytes()
    broken = tmp_path / "broken.whf"
    rewrite(data, broken,
            header=lambda h: {**h, "residual": {**h["residual"], "learned": {"unit": -1.0, "lights": 32}}})
    assert "residual.learned" in load_error(broken)
    rewrite(data, broken, drop=("residual/learned_w2.npy",))
    assert "learned_w2" in load_error(broken)
    rewrite(data, broken, drop=("residual/learned_bounds.npy",))
    assert "learned_bounds" in load_error(broken)
    # a file written before the bounds (version 6): relit unbounded
    rewrite(data, broken, drop=("residual/learned_bounds.npy",),
            header=lambda h: {**h, "format_version": 6,
                              "residual": {**h["residual"], "learned": {
                                  k: v for k, v in h["residual"]["learned"].items() if k != "bounds"}}})
    assert load_field(broken).residual.learned.bounds is None


def test_relit_learned_residual_stays_within_its_bounds(device):
    """``bound_decoded`` keeps every decoded value within its pixel's bounds (the float64 reference:
    ``learned_images``), on a decoder whose values pass the bounds on purpose."""
    directions, targets = _problem(seed=8, lights=4, pixels=60)
    model = neural.initial_model(targets, seed=5)
    codes = model.codes.reshape(6, 10, neural.CODE_SIZE).astype(np.float16)
    learned = NeuralResidual(codes, tuple(model.weights), 1.5, 4)
    free = learned_images(learned, directions)
    rng = np.random.default_rng(2)
    low = np.quantile(free, 0.3, axis=0) + rng.uniform(-0.01, 0.01, free.shape[1:])
    bounds = np.stack([low, low + rng.uniform(0.0, 0.05, low.shape)]).astype(np.float16)
    bounded = NeuralResidual(codes, tuple(model.weights), 1.5, 4, bounds)
    want = learned_images(bounded, directions)
    assert np.any(want != free)  # the bounds bind somewhere
    decoder = neural.QueryDecoder(codes.reshape(60, -1).astype(np.float32), model.weights, 1.5, device=device)
    out = wp.empty((4, 60, 3), dtype=wp.float16, device=device)
    decoder.decode(wp.array(directions.astype(np.float32), dtype=wp.vec3, device=device), out)
    wp.launch(neural.bound_decoded, dim=(4, 60), inputs=[wp.array(bounds.reshape(2, 60, 3), dtype=wp.float16,
                                                                    device=device)], outputs=[out], device=device)
    got = out.numpy().astype(np.float64).reshape(want.shape)
    assert np.all(got >= bounds[0].astype(np.float64)) and np.all(got <= bounds[1].astype(np.float64))
    np.testing.assert_allclose(got, want, atol=2e-3)


def test_learned_residual_needs_colour_images():
    from warp_highlights.model.config import ResidualSettings

    with pytest.raises(InputError, match="colour"):
        learn_residual(np.zeros((4, 8, 8, 1), np.float32), np.zeros((4, 8, 8), np.float32), None,
                       np.eye(3)[[0, 1, 2, 2]], factor=1.0,
                       settings=ResidualSettings(kind="learned"), device="cpu")


def test_learned_residual_checks_its_arrays():
    weights = tuple(np.zeros(shape, np.float32) for shape in NEURAL_LAYER_SHAPES)
    good = NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, 2.0, 7)
    model = ResidualModel(learned=good)
    assert (model.height, model.width, model.channels, model.light_count, model.kind) == (4, 5, 3, 7, "learned")
    with pytest.raises(InputError, match="codes"):
        NeuralResidual(np.zeros((4, 5, 8), np.float16), weights, 2.0, 7)
    with pytest.raises(InputError, match="weight arrays"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights[:-1], 2.0, 7)
    with pytest.raises(InputError, match="unit"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, -1.0, 7)
    with pytest.raises(InputError, match="bounds"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, 2.0, 7, np.zeros((2, 4, 4, 3), np.float16))
    with pytest.raises(InputError, match="bounds"):
        NeuralResidual(np.zeros((4, 5, 9), np.float16), weights, 2.0, 7, np.stack([np.ones((4, 5, 3)),
                                                                                   np.zeros((4, 5, 3))]))
    with pytest.raises(InputError, match="exactly one"):
        ResidualModel(images=np.zeros((7, 4, 5, 3), np.float16), learned=good)
    with pytest.raises(InputError, match="per query"):
        light_images(model, np.eye(7)[:1])


def test_training_never_reads_the_lights_left_out(device):
    """``used`` leaves lights out of the codes' start and of every step: other targets there change nothing."""
    directions, targets = _problem(seed=6, lights=7, pixels=50)
    used = np.array([0, 2, 3, 5, 6])
    first, history = neural_training.train_decoder(targets, directions, device=device, epochs=3, batch=64, used=used)
    changed = targets.copy()
    changed[[1, 4]] = np.random.default_rng(1).uniform(-3.0, 3.0, changed[[1, 4]].shape)
    second, again = neural_training.train_decoder(changed, directions, device=device, epochs=3, batch=64, used=used)
    np.testing.assert_allclose(second.codes, first.codes, rtol=1e-5, atol=1e-6)
    for got, want in zip(second.weights, first.weights):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(again, history, rtol=1e-5)
    # all lights: the changed ones count
    whole, _ = neural_training.train_decoder(changed, directions, device=device, epochs=3, batch=64)
    assert not np.allclose(whole.codes, first.codes, atol=1e-3)
    with pytest.raises(ValueError, match="used"):
        neural_training.train_decoder(targets, directions, device=device, epochs=1, used=np.array([7]))
    _, fresh = neural_training.train_decoder(targets, directions, device=device, epochs=1, batch=64)
    _, going_on = neural_training.train_decoder(targets, directions, device=device, epochs=1, batch=64, initial=first,
                                                lr=3e-4,
                                       final_lr=3e-4)
    assert going_on[0] < fresh[0]  # ``initial`` goes on from the trained model
    with pytest.raises(ValueError, match="codes of 40 pixels"):
        neural_training.train_decoder(targets[:, :40], directions, device=device, epochs=1, initial=first)


def test_learned_check_scores_both_models_at_the_left_out_lights():
    """No highlights: the residual is the images, so both models learn the same and score the same
    (the Gaussians kept); moved highlights that add a wrong bright blob lose to the images alone, whose
    model is the winner; the scores are 8-bit sRGB PSNR of each model at the left-out lights."""
    from warp_highlights.model.config import LEARNED_RESIDUAL_RATE, ResidualSettings
    from warp_highlights.quality.metrics import srgb_psnr
    from warp_highlights.residual.learned import bounded, check_learned

    rng = np.random.default_rng(7)
    directions = rng.normal(size=(9, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.2
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    normals = np.dstack([rng.normal(0, 0.3, (6, 8)), rng.normal(0, 0.3, (6, 8)), np.ones((6, 8))])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    images = (0.6 * np.clip(np.einsum("nc,hwc->nhw", directions, normals), 0, None)[..., None]
              * [1.0, 0.8, 0.6]).astype(np.float32)
    own = np.zeros(images.shape[:3], np.float32)
    left_out = np.array([2, 6])
    # settling never cuts in (its epoch is the last): both models learn as ``learn_residual`` would, the images
    # alone at the check's rate
    settings = ResidualSettings(kind="learned", learned_epochs=4, learned_seconds=60.0, learned_settle_fraction=1.0,
                                learned_rate=LEARNED_RESIDUAL_RATE, learned_tie_margin_db=0.0)
    same = check_learned(images, own, None, directions, left_out, np.zeros((2, 6, 8, 3), np.float32), factor=2.0,
                         settings=settings, device="cpu")
    np.testing.assert_array_equal(same.lights, left_out)
    np.testing.assert_allclose(same.with_gaussians, same.images_alone)
    assert same.keeps_gaussians and same.report()["keeps_gaussians"]
    used = np.array([0, 1, 3, 4, 5, 7, 8])
    model, _ = learn_residual(images, own, None, directions, factor=2.0, settings=settings, device="cpu", used=used)
    # scored as relit: within the bounds of what it learned, from its own lights
    within = bounded(model, images[used], own[used], None).learned
    want = [srgb_psnr(np.maximum(p, 0) / 2.0, t / 2.0)
            for p, t in zip(learned_images(within, directions[left_out]), images[left_out])]
    np.testing.assert_allclose(same.images_alone, want, rtol=1e-6)
    blob = np.zeros((2, 6, 8, 3), np.float32)
    blob[:, 2:4, 3:6] = 1.5
    wrong = check_learned(images, own, None, directions, left_out, blob, factor=2.0, settings=settings, device="cpu")
    assert np.all(wrong.with_gaussians < wrong.images_alone) and not wrong.keeps_gaussians
    # with its residual exact (the images: no highlights of their own) the first model shows image + blob
    np.testing.assert_allclose(same.exact_residual, [100.0, 100.0])
    np.testing.assert_allclose(wrong.exact_residual, [srgb_psnr((images[j] + b) / 2.0, images[j] / 2.0)
                                                      for j, b in zip(left_out, blob)], rtol=1e-6)
    assert wrong.report()["exact_residual_psnr_db"] == pytest.approx(np.mean(wrong.exact_residual), abs=1e-3)
    per_light = wrong.report()["per_light"]
    assert per_light["light"] == left_out.tolist()
    for name, values in (("with_gaussians_psnr_db", wrong.with_gaussians), ("images_alone_psnr_db", wrong.images_alone),
                         ("exact_residual_psnr_db", wrong.exact_residual)):
        np.testing.assert_allclose(per_light[name], values, atol=0.005)
    gap = float(np.mean(wrong.images_alone) - np.mean(wrong.with_gaussians))
    assert gap > settings.learned_tie_margin_db
    # a margin beyond the gap keeps the Gaussians: the residual's model is the winner
    tied = check_learned(images, own, None, directions, left_out, blob, factor=2.0, device="cpu",
                         settings=dataclasses.replace(settings, learned_tie_margin_db=gap + 0.1))
    assert tied.keeps_gaussians and tied.report()["keeps_gaussians"] and tied.tie_margin_db == gap + 0.1
    np.testing.assert_allclose(tied.images_alone, wrong.images_alone, rtol=1e-6)
    # where the capture's Gaussians glide (its median motion coherence at the threshold or above) the glide's margin
    # decides: beyond the gap it keeps them; below the threshold the plain margin drops them
    gliding = dataclasses.replace(settings, learned_glide_coherence=0.9, learned_glide_margin_db=gap + 0.1)
    glide = check_learned(images, own, None, directions, left_out, blob, factor=2.0, device="cpu", settings=gliding,
                          coherence=0.9)
    assert glide.keeps_gaussians and glide.glides and glide.report()["glides"]
    assert glide.report()["tie_margin_db"] == pytest.approx(gap + 0.1)
    hops = check_learned(images, own, None, directions, left_out, blob, factor=2.0, device="cpu", settings=gliding,
                         coherence=0.89)
    assert not hops.keeps_gaussians and not hops.glides and hops.tie_margin_db == settings.learned_tie_margin_db
    np.testing.assert_allclose(hops.with_gaussians, wrong.with_gaussians, rtol=1e-6)
    # the images alone, learned without the left-out lights
    np.testing.assert_array_equal(wrong.winner.learned.codes, model.learned.codes)
    assert wrong.settled_epoch is None and wrong.report()["settled_epoch"] is None


def test_learned_check_scores_each_model_within_the_bounds_of_what_it_learned():
    """The check scores a model as the field relights it: within the range of its targets at the lights it learned
    from (``learned_bounds``), so a column that every light leaves black stays black at the left-out lights, where
    the decoder alone would light it; without the bounds (``learned_bounds=False``) it is scored as decoded."""
    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual.learned import bounded, check_learned

    rng = np.random.default_rng(5)
    directions = rng.normal(size=(8, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.2
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    images = rng.uniform(0.2, 0.7, (8, 6, 8, 3)).astype(np.float32)
    images[:, :, :2] = 0.0  # a background no light reaches
    own = np.zeros(images.shape[:3], np.float32)
    left_out, used = np.array([3, 5]), np.array([0, 1, 2, 4, 6, 7])
    settings = ResidualSettings(kind="learned", learned_epochs=3, learned_seconds=60.0, learned_settle_fraction=1.0,
                                learned_batch=64, learned_residual_rate=3e-3)
    none = np.zeros((2, 6, 8, 3), np.float32)
    check = check_learned(images, own, None, directions, left_out, none, factor=1.0, settings=settings, device="cpu")
    free = check_learned(images, own, None, directions, left_out, none, factor=1.0, device="cpu",
                         settings=dataclasses.replace(settings, learned_bounds=False))
    model, _ = learn_residual(images, own, None, directions, factor=1.0, settings=settings, device="cpu", used=used)
    decoded = learned_images(model.learned, directions[left_out])
    within = learned_images(bounded(model, images[used], own[used], None).learned, directions[left_out])
    assert np.abs(decoded[:, :, :2]).max() > 1e-3  # the decoder alone lights the background a little
    np.testing.assert_array_equal(within[:, :, :2], 0.0)  # the bounds keep it black
    np.testing.assert_allclose(check.images_alone, [srgb_psnr(np.maximum(p, 0), t) for p, t in
                                                    zip(within, images[left_out])], rtol=1e-6)
    np.testing.assert_allclose(free.images_alone, [srgb_psnr(np.maximum(p, 0), t) for p, t in
                                                   zip(decoded, images[left_out])], rtol=1e-6)
    # the residual's model (here the images too, at its own, slower rate) lit the background: kept black, it scores
    # higher
    assert np.all(check.with_gaussians > free.with_gaussians)
    assert np.all(check.images_alone >= free.images_alone)


def test_the_gaussians_are_kept_within_the_tie_margin():
    """The images alone must lead by more than ``learned_tie_margin_db`` for the check to drop the Gaussians; a
    negative margin (the default, -0.5) drops them unless their model leads by at least its magnitude."""
    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual.learned import LearnedCheck

    lights = np.array([1, 4])
    assert ResidualSettings().learned_tie_margin_db == -0.5
    for alone, margin, keeps in ((20.4, 0.5, True), (20.4, 0.0, False), (20.8, 0.5, False), (19.0, 0.0, True),
                                 (19.7, -0.5, False), (19.5, -0.5, True), (20.1, -0.5, False)):
        check = LearnedCheck(lights, np.array([20.0, 20.2]), np.array([alone, alone]), tie_margin_db=margin)
        assert check.keeps_gaussians == keeps, (alone, margin)
    assert LearnedCheck(np.zeros(0, np.int64), np.zeros(0), np.zeros(0)).keeps_gaussians


def test_the_tie_margin_is_the_glides_where_the_gaussians_follow_the_light():
    """``tie_margin``: a decoder that sees the Gaussians gets ``learned_seeing_margin_db``; a capture whose median
    motion coherence reaches ``learned_glide_coherence`` (default 0.9) ``learned_glide_margin_db`` (0.5); below it,
    unmeasured (None, NaN) or with the threshold above 1 (off), ``learned_tie_margin_db``."""
    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual.learned import glides, tie_margin

    settings = ResidualSettings()
    assert (settings.learned_glide_coherence, settings.learned_glide_margin_db) == (0.9, 0.5)
    for coherence, want in ((0.96, 0.5), (0.9, 0.5), (0.899, -0.5), (0.3, -0.5), (-0.2, -0.5), (None, -0.5),
                            (float("nan"), -0.5)):
        assert tie_margin(settings, coherence=coherence) == want, coherence
        assert glides(settings, coherence) == (want == 0.5)
    assert tie_margin(settings, sees=True, coherence=0.99) == settings.learned_seeing_margin_db
    off = dataclasses.replace(settings, learned_glide_coherence=1.5)
    assert tie_margin(off, coherence=1.0) == -0.5 and not glides(off, 1.0)
    for name, bad in (("learned_glide_coherence", 2.5), ("learned_glide_coherence", float("nan")),
                      ("learned_glide_margin_db", float("inf"))):
        with pytest.raises(ValueError, match=name):
            ResidualSettings(**{name: bad})


def test_the_learned_check_on_the_cpu_stops_the_loser_once_the_order_has_settled():
    """On the CPU the check's models learn one after the other, each from its own first rate (the residual's
    ``learned_residual_rate``, the images' ``learned_rate``): both the first half of the schedule, then, their
    order settled (a margin of 0 dB), the winner alone the second half from where it was, at its schedule's rates,
    from every light (the verdict is taken); both are scored as they were at the half."""
    from warp_highlights.model.config import LEARNED_RATE_CPU, ResidualSettings
    from warp_highlights.residual import cpu_training
    from warp_highlights.residual.learned import _targets, bounded, check_learned

    residual_rate = LEARNED_RATE_CPU / 2  # unlike the images', so that each model's own rate tells

    rng = np.random.default_rng(8)
    directions = rng.normal(size=(9, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.2
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    images = rng.uniform(0.1, 0.6, (9, 6, 8, 3)).astype(np.float32)
    own = np.zeros(images.shape[:3], np.float32)
    left_out = np.array([2, 6])
    blob = np.zeros((2, 6, 8, 3), np.float32)
    blob[:, 2:4, 3:6] = 1.5  # the Gaussians' highlights where there are none: the images alone win
    settings = ResidualSettings(kind="learned", learned_epochs=4, learned_seconds=60.0, learned_settle_fraction=0.5,
                                learned_settle_margin_db=0.0, learned_batch=64, learned_residual_rate=residual_rate)
    check = check_learned(images, own, None, directions, left_out, blob, factor=2.0, settings=settings, device="cpu")
    assert check.settled_epoch == 2 and not check.keeps_gaussians
    used = np.setdiff1d(np.arange(9), left_out)
    options = dict(device="cpu", batch=64, used=used, seconds=60.0)
    # each from its own first rate (the residual's and the images'), down to 3e-4 over the 4 epochs
    def rate_at(lr, epoch):
        return lr * (3e-4 / lr) ** (epoch / 3)

    first, _ = cpu_training.train_decoder_cpu(_targets(images, own, None, 2.0), directions, epochs=2,
                                              lr=residual_rate, final_lr=rate_at(residual_rate, 1),
                                              **{**options, "seconds": 60.0 / 6 * 2})
    alone = _targets(images, np.zeros_like(own), None, 2.0)
    start, _ = cpu_training.train_decoder_cpu(alone, directions, epochs=2, lr=LEARNED_RATE_CPU,
                                              final_lr=rate_at(LEARNED_RATE_CPU, 1),
                                              **{**options, "seconds": 60.0 / 6 * 2})
    end, _ = cpu_training.train_decoder_cpu(alone, directions, epochs=2, lr=rate_at(LEARNED_RATE_CPU, 2),
                                            final_lr=3e-4, initial=start, **{**options, "used": None})
    np.testing.assert_allclose(check.winner.learned.codes.reshape(-1, 9).astype(np.float32),
                               end.codes.astype(np.float16).astype(np.float32), atol=1e-3)
    assert check.learned_every_light and len(check.history) == 4
    # where the winner will not be kept (the field learns anew), both stop once settled, the scores the same
    stopped = check_learned(images, own, None, directions, left_out, blob, factor=2.0, settings=settings,
                            device="cpu", winner_kept=False)
    assert stopped.settled_epoch == 2 and not stopped.keeps_gaussians and not stopped.learned_every_light
    assert len(stopped.history) == 2
    np.testing.assert_allclose(stopped.winner.learned.codes.reshape(-1, 9).astype(np.float32),
                               start.codes.astype(np.float16).astype(np.float32), atol=1e-3)
    np.testing.assert_allclose(stopped.with_gaussians, check.with_gaussians, rtol=1e-6)
    np.testing.assert_allclose(stopped.images_alone, check.images_alone, rtol=1e-6)

    def scores(model, added):
        learned = NeuralResidual(model.codes.reshape(6, 8, -1).astype(np.float16), tuple(model.weights), 2.0, 9)
        learned = bounded(ResidualModel(learned=learned), images[used], own[used], None).learned
        relit = learned_images(learned, directions[left_out])
        return [srgb_psnr(np.maximum(p + b, 0) / 2.0, t / 2.0) for p, b, t in zip(relit, added, images[left_out])]

    np.testing.assert_allclose(check.with_gaussians, scores(first, blob), rtol=1e-4)
    np.testing.assert_allclose(check.images_alone, scores(start, np.zeros_like(blob)), rtol=1e-4)


def test_training_time_counts_from_the_first_step():
    """``seconds`` bounds training after the first step (which compiles the kernels): a tiny bound runs one epoch."""
    directions, targets = _problem(seed=5)
    _, history = neural_training.train_decoder(targets, directions, device="cpu", epochs=50, batch=128, seconds=1e-9)
    assert len(history) == 1


def test_the_residual_kind_is_resolved_for_the_device_and_the_capture():
    """"auto" learns on CUDA and compresses elsewhere and for one-channel captures; a concrete kind stays as it is; a
    learned residual past the decoder's 2^31 samples is refused where asked for and falls back to low rank where
    "auto" chose it."""
    from warp_highlights.residual.kind import CONCRETE_KINDS, resolve_kind

    assert resolve_kind("auto", "cpu") == "lowrank"
    for kind in CONCRETE_KINDS:
        assert resolve_kind(kind, "cpu") == kind
    if wp.is_cuda_available():
        assert resolve_kind("auto", "cuda:0") == "learned"
        assert resolve_kind("auto", "cuda:0", light_count=1 << 16, size=(1 << 8, 1 << 8)) == "lowrank"
    assert resolve_kind("learned", "cpu", light_count=8, size=(4, 4)) == "learned"
    with pytest.raises(InputError, match=r"65536 lights of 256x256 pass .* use --residual lowrank"):
        resolve_kind("learned", "cpu", light_count=1 << 16, size=(1 << 8, 1 << 8))
    with pytest.raises(InputError, match="residual kind must be one of"):
        resolve_kind("compressed", "cpu")
    # one channel (grey, infrared, a band): "auto" compresses on every device, "learned" is refused before any work
    for device in ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else []):
        assert resolve_kind("auto", device, channels=1) == "lowrank"
        assert resolve_kind("auto", device, channels=3) == ("learned" if device.startswith("cuda") else "lowrank")
        with pytest.raises(InputError, match="fit grey captures with --residual lowrank"):
            resolve_kind("learned", device, channels=1)


def test_a_small_capture_takes_smaller_batches_on_cuda_so_that_an_epoch_holds_enough_steps():
    """On CUDA the batch is cut where an epoch would hold under LEARNED_STEPS_PER_EPOCH steps, never below the CPU's
    batch; large captures keep the device's batch; a set batch and the CPU's are never changed."""
    from warp_highlights.model.config import (
        LEARNED_BATCH_CPU,
        LEARNED_BATCH_CUDA,
        LEARNED_STEPS_PER_EPOCH,
        ResidualSettings,
    )
    from warp_highlights.residual.learned import learned_batch

    settings = ResidualSettings()
    dome_sample = 49 * 320 * 320
    assert learned_batch(settings, True, dome_sample) == LEARNED_BATCH_CUDA  # 77 steps an epoch
    assert dome_sample // LEARNED_BATCH_CUDA >= LEARNED_STEPS_PER_EPOCH
    small = 16 * 160 * 90  # 4 steps an epoch at the device's batch
    batch = learned_batch(settings, True, small)
    assert LEARNED_BATCH_CPU <= batch < LEARNED_BATCH_CUDA
    assert small / batch >= min(LEARNED_STEPS_PER_EPOCH, small / LEARNED_BATCH_CPU)
    middle = 49 * 160 * 90
    assert learned_batch(settings, True, middle) == middle // LEARNED_STEPS_PER_EPOCH
    assert learned_batch(settings, True, 100) == LEARNED_BATCH_CPU  # a tiny capture: not below the CPU's batch
    for samples in (100, small, dome_sample):
        assert learned_batch(settings, False, samples) == LEARNED_BATCH_CPU
        assert learned_batch(dataclasses.replace(settings, learned_batch=1000), True, samples) == 1000


def test_a_learned_residual_trains_on_cuda_with_the_batch_of_its_capture(monkeypatch):
    """The device's trainer gets ``learned_batch`` of the samples it learns from: every light, or the ``used`` ones
    (the learned check's)."""
    import types

    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual import learned

    seen = []

    def trainer(targets, directions, *, batch, **options):
        seen.append(batch)
        return [None] * len(targets), np.zeros((1, len(targets)))

    monkeypatch.setattr(learned, "train_decoders", trainer)
    monkeypatch.setattr(learned.wp, "get_device", lambda device=None: types.SimpleNamespace(is_cuda=True))
    lights, pixels = 16, 100_000
    targets = np.zeros((lights, pixels, 3), np.float32)
    directions = np.tile([0.0, 0.0, 1.0], (lights, 1))
    settings = ResidualSettings()
    learned._train([targets], directions, settings=settings, device="cuda:0")
    learned._train([targets, targets], directions, settings=settings, device="cuda:0", used=np.arange(8))
    assert seen == [learned.learned_batch(settings, True, lights * pixels),
                    learned.learned_batch(settings, True, 8 * pixels)] == [25_000, 12_500]


def test_auto_on_the_cpu_counts_the_epochs_its_training_time_holds():
    """Where "auto" resolved to low rank on the CPU for a colour capture, the epochs of its samples
    (lights x pixels) that the training time holds at the CPU's pace: measured where not given; no answer for a
    concrete kind, a grey capture, a CUDA device's choice, the setting at 0 or past the decoder's 2^31 samples."""
    from warp_highlights.model.config import LEARNED_EPOCHS_CPU, LEARNED_SECONDS_CPU, ResidualSettings
    from warp_highlights.residual.cpu_training import training_rate
    from warp_highlights.residual.kind import cpu_epochs

    settings = ResidualSettings()
    capture = dict(light_count=40, size=(300, 200), channels=3)
    assert cpu_epochs("auto", "lowrank", "cpu", settings, **capture, rate=1e6) == pytest.approx(
        1e6 * LEARNED_SECONDS_CPU / (40 * 300 * 200))
    # never more than the schedule's epochs
    assert cpu_epochs("auto", "lowrank", "cpu", settings, **capture, rate=1e12) == LEARNED_EPOCHS_CPU
    assert cpu_epochs("auto", "lowrank", "cpu", ResidualSettings(learned_epochs=7), **capture, rate=1e12) == 7
    assert cpu_epochs("auto", "lowrank", "cpu", ResidualSettings(learned_seconds=60.0), **capture,
                        rate=1e6) == pytest.approx(1e6 * 60.0 / (40 * 300 * 200))
    for requested, resolved in (("lowrank", "lowrank"), ("auto", "learned"), ("images", "images")):
        assert cpu_epochs(requested, resolved, "cpu", settings, **capture, rate=1e6) is None
    assert cpu_epochs("auto", "lowrank", "cpu", settings, **dict(capture, channels=1), rate=1e6) is None
    assert cpu_epochs("auto", "lowrank", "cpu", ResidualSettings(cpu_learned_epochs=0), **capture) is None
    assert cpu_epochs("auto", "lowrank", "cpu", settings, light_count=1 << 16, size=(1 << 8, 1 << 8),
                        channels=3, rate=1e15) is None
    if wp.is_cuda_available():
        assert cpu_epochs("auto", "lowrank", "cuda:0", settings, **capture) is None
    # measured: more samples a second than zero, and a pace whose time holds a small capture's whole schedule
    assert training_rate(steps=2) > 0
    small = dict(light_count=8, size=(16, 16), channels=3)
    assert cpu_epochs("auto", "lowrank", "cpu", settings, **small) == LEARNED_EPOCHS_CPU


def test_fields_stored_with_the_residual_booleans_read_as_their_kind():
    """Settings of fields written before ``residual.kind`` (``compressed``, ``learned``, ``learned_on_cuda``) load as
    the kind each combination stood for."""
    from warp_highlights.model.config import FitSettings

    cases = [((True, False, True), "auto"), ((True, False, False), "lowrank"), ((True, True, True), "learned"),
             ((False, False, True), "images"), ((False, True, False), "learned")]
    for (compressed, learned, on_cuda), kind in cases:
        values = FitSettings().to_dict()
        del values["residual"]["kind"]
        values["residual"].update(compressed=compressed, learned=learned, learned_on_cuda=on_cuda)
        assert FitSettings.from_dict(values).residual.kind == kind


def test_fields_stored_with_a_renamed_residual_setting_read_under_its_new_name():
    """``residual.still_learned_epochs`` of older field files reads as ``residual.cpu_learned_epochs``."""
    from warp_highlights.model.config import FitSettings

    values = FitSettings().to_dict()
    del values["residual"]["cpu_learned_epochs"]
    values["residual"]["still_learned_epochs"] = 17
    assert FitSettings.from_dict(values).residual.cpu_learned_epochs == 17


def test_more_samples_than_a_32_bit_index_are_refused_before_any_work(small_donut, monkeypatch):
    """The training samples are indexed light x pixels + pixel in int32: past 2^31 (1,036 lights of 1920x1080) the
    training refuses (it would read the wrong samples), and a fit that asks for the learned residual says so before its
    first stage; on CUDA, where it is only the default, the fit compresses the residual to low rank instead."""
    import warp as wp

    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    monkeypatch.setattr(neural, "MAX_SAMPLES", 4 * 10 - 1)
    targets = np.zeros((4, 10, 3), np.float32)
    with pytest.raises(ValueError, match="4 lights of 10 pixels pass the learned residual's 32-bit sample index"):
        neural_training.train_decoder(targets, np.tile([[0.0, 0.0, 1.0]], (4, 1)), device="cpu", epochs=1)
    assert neural.samples_fit(3, 13) and not neural.samples_fit(4, 10)
    data = ReflectanceField.load(small_donut, progress=False)
    stages = []
    learned = FitSettings().with_overrides(["residual.kind=learned"])
    with pytest.raises(InputError,
                       match=r"32 lights of 96x54 pass the learned residual's 2\^31 samples .* use --residual lowrank"):
        fit_field(data, settings=learned, device="cpu", log=stages.append)
    assert stages == []  # refused before the first stage
    if wp.is_cuda_available():
        field = fit_field(data, settings=FitSettings().with_overrides(FAST_FIT), device="cuda:0")
        assert field.residual is not None and field.residual.learned is None and field.residual.luminance is not None


def test_images_learned_alone_start_at_the_faster_rate(monkeypatch):
    """``learn_residual`` starts images without highlights taken out (``own`` all zero) at ``learned_rate`` (by device
    where 0) and a residual with highlights taken out at ``learned_residual_rate`` (``LEARNED_RESIDUAL_RATE`` where 0),
    whatever ``learned_rate`` says; tuning at the final rate."""
    from warp_highlights.model.config import (
        LEARNED_FINAL_RATE,
        LEARNED_RATE_CPU,
        LEARNED_RESIDUAL_RATE,
        ResidualSettings,
    )
    from warp_highlights.residual import learned as learned_module

    starts = []
    train = learned_module.train_decoder_cpu
    monkeypatch.setattr(learned_module, "train_decoder_cpu",
                        lambda *args, **kwargs: starts.append(kwargs["lr"]) or train(*args, **kwargs))
    directions, targets = _problem(lights=5, pixels=12)
    images = targets.reshape(5, 3, 4, 3)
    own = np.zeros((5, 3, 4), np.float32)
    settings = ResidualSettings(kind="learned", learned_epochs=1)
    learn_residual(images, own, None, directions, factor=1.0, settings=settings, device="cpu")
    learn_residual(images, own, None, directions, factor=1.0, device="cpu",
                   settings=dataclasses.replace(settings, learned_rate=0.02))
    own[:, 1, 2] = 0.1
    model, _ = learn_residual(images, own, None, directions, factor=1.0, settings=settings, device="cpu")
    learn_residual(images, own, None, directions, factor=1.0, settings=settings, device="cpu", initial=model.learned,
                   tune=True)
    learn_residual(images, own, None, directions, factor=1.0, device="cpu",
                   settings=dataclasses.replace(settings, learned_rate=0.02, learned_residual_rate=0.005))
    assert starts == [LEARNED_RATE_CPU, 0.02, LEARNED_RESIDUAL_RATE, LEARNED_FINAL_RATE, 0.005]


def test_the_residual_learns_the_diffuse_part_under_a_light_s_own_highlights():
    """Where a light's own highlights are at least ``level`` of their brightest, the residual's target is the image less
    its specular part; elsewhere, at a light without highlights, or with level 0, the image less its own highlights
    (float64 reference of the display-encoded targets)."""
    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual.learned import _targets

    rng = np.random.default_rng(4)
    n, height, width = 3, 5, 6
    images = rng.uniform(0.2, 2.0, (n, height, width, 3)).astype(np.float32)
    specular = rng.uniform(0.0, 1.0, (n, height, width, 3)).astype(np.float32)
    yy, xx = np.mgrid[0:height, 0:width]
    own = np.stack([np.exp(-((xx - 2.0) ** 2 + (yy - 2.0) ** 2) / 2.0),
                    0.5 * np.exp(-((xx - 4.0) ** 2 + (yy - 1.0) ** 2) / 0.5),
                    np.zeros((height, width))]).astype(np.float32)
    colour = rng.uniform(0.5, 1.5, (height, width, 3)).astype(np.float32)
    factor, level = 2.0, 0.3
    got = _targets(images, own, colour, factor, specular, level)
    want = images.astype(np.float64) - own[..., None].astype(np.float64) * colour
    for i in range(n):
        under = own[i] >= level * own[i].max() if own[i].max() > 0 else np.zeros_like(own[i], bool)
        want[i][under] = images[i][under].astype(np.float64) - specular[i][under]
    assert 0 < np.count_nonzero(own[0] >= level * own[0].max()) < height * width  # some pixels under, some not
    want_display = encode_display((want / factor).astype(np.float32)).reshape(n, -1, 3)
    np.testing.assert_allclose(got, want_display, rtol=1e-5, atol=1e-6)
    plain = encode_display(((images - own[..., None] * colour) / factor).astype(np.float32)).reshape(n, -1, 3)
    np.testing.assert_allclose(_targets(images, own, colour, factor, specular, 0.0), plain, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_targets(images, own, colour, factor), plain, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got[2], plain[2], rtol=1e-5, atol=1e-6)  # no highlight at that light: unchanged
    with pytest.raises(InputError, match="diffuse_under_highlights"):
        ResidualSettings(diffuse_under_highlights=1.5)


@pytest.mark.parametrize("overrides, passes", [([], True), (["residual.diffuse_under_highlights=0"], False),
                                               (["residual.highlight_colour=false"], True),
                                               (["residual.learned_sees_gaussians=true",
                                                 "residual.learned_seeing_margin_db=100"], False)])
def test_a_fit_hands_the_specular_part_to_the_learned_residual_where_it_learns_the_diffuse_part(
        small_donut, monkeypatch, overrides, passes):
    """The learned check's residual and the field's learned residual get the segmentation's specular part (the
    images' shape) where ``diffuse_under_highlights`` is on, with the highlight colour off too, and not where it is
    0 or where the decoder sees the Gaussians (it learns the images themselves)."""
    from warp_highlights.fit import pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    handed = {}
    for name in ("check_learned", "learn_residual"):
        real = getattr(pipeline, name)

        def recording(*args, _real=real, _name=name, **kwargs):
            handed[_name] = kwargs.get("specular")
            return _real(*args, **kwargs)

        monkeypatch.setattr(pipeline, name, recording)
    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=1",
                                                     "residual.learned_tune_epochs=1", "residual.move_support=0",
                                                     "residual.learned_tie_margin_db=100",
                                                     "residual.learned_glide_margin_db=100"] + overrides)
    field = pipeline.fit_field(dataset, device="cpu", settings=settings, progress=False)
    assert set(handed) == {"check_learned", "learn_residual"}
    for name, specular in handed.items():
        if passes:
            assert specular is not None and specular.shape == dataset.images.shape, name
            assert np.all(np.isfinite(specular.astype(np.float32))) and specular.min() >= 0
        else:
            assert specular is None, name
    assert (field.residual.highlight_colour is None) == ("residual.highlight_colour=false" in overrides)


def test_learned_target_is_the_image_less_its_own_highlights_and_the_diffuse_part_under_them():
    """Float64 reference: the image less its own highlights in colour c, and where they are at least ``level`` of
    their brightest the image less its specular part; without the specular part (or at level 0) no such region."""
    from warp_highlights.residual.inputs import learned_target

    rng = np.random.default_rng(5)
    image = rng.uniform(0.0, 1.6, (6, 7, 3)).astype(np.float32)
    own = np.zeros((6, 7), np.float32)
    own[1:4, 2:6] = rng.uniform(0.1, 1.0, (3, 4))
    own[2, 3] = 1.5
    colour = rng.uniform(0.5, 1.0, (6, 7, 3)).astype(np.float32)
    specular = rng.uniform(0.0, 0.8, (6, 7, 3)).astype(np.float32)
    want = image.astype(np.float64) - own[..., None].astype(np.float64) * colour
    under = own >= 0.4 * own.max()
    assert 0 < under.sum() < (own > 0).sum()
    diffuse = want.copy()
    diffuse[under] = image[under].astype(np.float64) - specular[under]
    got = learned_target(image, own, colour, specular, 0.4)
    assert got.dtype == np.float32 and got.shape == image.shape
    np.testing.assert_allclose(got, diffuse, atol=1e-6)
    np.testing.assert_allclose(learned_target(image, own, colour), want, atol=1e-6)
    np.testing.assert_allclose(learned_target(image, own, colour, specular, 0.0), want, atol=1e-6)


def test_exact_residual_scores_are_the_image_less_its_own_highlights_plus_the_moved_ones():
    """Float64 reference: at each left-out light, the image less its own highlights in colour c (the diffuse part
    where they are at least ``level`` of their brightest), plus the moved highlights, clipped at 0 and shown in 8-bit
    sRGB, against the image."""
    from warp_highlights.io.images import display_rgb8
    from warp_highlights.residual.learned import exact_residual_scores

    rng = np.random.default_rng(3)
    images = rng.uniform(0.0, 1.6, (5, 6, 7, 3)).astype(np.float32)
    own = np.zeros((5, 6, 7), np.float32)
    own[:, 2:4, 1:5] = rng.uniform(0.2, 1.0, (5, 2, 4))
    own[:, 2, 1] = 1.2  # the brightest: the diffuse part is learned where own >= 0.5 * 1.2
    colour = rng.uniform(0.5, 1.0, (6, 7, 3)).astype(np.float32)
    specular = rng.uniform(0.0, 0.8, (5, 6, 7, 3)).astype(np.float32)
    lights = np.array([1, 4])
    moved = rng.uniform(-0.1, 1.0, (2, 6, 7, 3)).astype(np.float32)
    factor, level = 1.7, 0.5
    got = exact_residual_scores(images, own, colour, lights, moved, factor=factor, specular=specular, level=level)
    want = []
    for k, j in enumerate(lights):
        image = images[j].astype(np.float64)
        residual = image - own[j][..., None].astype(np.float64) * colour
        under = own[j] >= level * own[j].max()
        residual[under] = image[under] - specular[j][under]
        shown = np.maximum(residual + moved[k], 0.0) / factor
        a, b = display_rgb8(shown).astype(np.float64), display_rgb8(image / factor).astype(np.float64)
        want.append(10 * np.log10(255.0**2 / np.mean((a - b) ** 2)))
    np.testing.assert_allclose(got, want, atol=0.02)
    # without the specular part: the image less its own highlights alone
    plain = exact_residual_scores(images, own, None, lights, moved, factor=factor)
    for k, j in enumerate(lights):
        shown = np.maximum(images[j] - own[j][..., None] + moved[k], 0.0) / factor
        assert plain[k] == pytest.approx(srgb_psnr(shown, images[j] / factor), abs=1e-9)
