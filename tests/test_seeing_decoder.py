"""A learned residual whose decoder sees the Gaussians (``model.residual.highlight_inputs``): the CPU trainer's
gradients by central differences, its decode against the float64 reference, the field file, and a fit whose learned
check trains it on every light's moved Gaussians and relights as the reference says."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import FAST_FIT
from warp_highlights.kernels import neural
from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import (
    NEURAL_HIGHLIGHT_INPUTS,
    NEURAL_INPUTS,
    NeuralResidual,
    decoder_layer_shapes,
    highlight_inputs,
    sees_highlights,
    standard_decoder,
)
from warp_highlights.residual import cpu_training
from warp_highlights.residual.cpu_training import CpuQueryDecoder, decode_cpu, seeing_model, train_decoder_cpu
from warp_highlights.residual.decode import learned_images


def _elu(v):
    return np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))


def _reference(codes, weights, directions, g):
    """(Q, P, 3) float64 decoder values at (Q, 3) directions with (Q, P) display-unit highlights g."""
    out = []
    for direction, row in zip(np.asarray(directions, np.float64), np.asarray(g, np.float64)):
        row = np.maximum(row, 0.0)
        h = np.concatenate([codes, np.broadcast_to(direction, (len(codes), 3)), np.sqrt(row)[:, None], row[:, None]],
                           axis=1).T
        for w, b in zip(weights[0:-2:2], weights[1:-2:2]):
            h = _elu(w @ h + b)
        out.append((weights[-2] @ h + weights[-1]).T)
    return np.stack(out)


def _seeing(seed=0, lights=5, pixels=40):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    targets = rng.uniform(0.0, 1.0, (lights, pixels, 3)).astype(np.float32)
    model = seeing_model(neural.initial_model(targets, seed=seed + 1))
    model.weights[0][:, NEURAL_INPUTS:] = rng.normal(0.0, 0.5, (len(model.weights[0]), NEURAL_HIGHLIGHT_INPUTS))
    g = rng.uniform(0.0, 2.0, (lights, pixels)).astype(np.float32)
    g[:, :5] = 0.0  # no highlight there
    return directions.astype(np.float32), targets, model, g


def test_highlight_inputs_and_shapes():
    np.testing.assert_allclose(highlight_inputs([4.0, -1.0, 0.25]), [[2.0, 4.0], [0.0, 0.0], [0.5, 0.25]])
    shapes = decoder_layer_shapes((48, 48, 48), True)
    assert shapes[0] == (48, NEURAL_INPUTS + 2) and shapes[1:] == decoder_layer_shapes((48, 48, 48))[1:]
    small = [np.ones(s, np.float32) for s in decoder_layer_shapes((8,), True)]
    assert sees_highlights(small) and sees_highlights(standard_decoder(small))
    assert standard_decoder(small)[0].shape == (48, NEURAL_INPUTS + 2)


def test_cpu_gradients_with_highlights_match_central_differences():
    directions, targets, model, g = _seeing(seed=1)
    rng = np.random.default_rng(3)
    samples = rng.choice(5 * 40, 40, replace=False)
    params = cpu_training._Parameters(model)
    batch = cpu_training._Batch(128, 40, params.flat.size - params.codes.size, threads=2, inputs=params.inputs)
    loss = batch.step(samples, params, directions, targets.reshape(-1, 3), g.reshape(-1))
    lights, pixels = np.divmod(samples, 40)
    values = [model.codes.astype(np.float64)] + [w.astype(np.float64) for w in model.weights]

    def mse(v):
        decoded = _reference(v[0], v[1:], directions, g)[lights, pixels]
        return np.mean(np.sum((decoded - targets[lights, pixels]) ** 2, axis=-1))

    assert loss == pytest.approx(mse(values), rel=1e-5)
    grads = {0: params.g_codes, 1: params.g_w0[:, :NEURAL_INPUTS + 2], 3: params.g_w1}
    picks = {0: [(int(pixels[0]), k) for k in range(3)], 1: [(r, c) for r in (0, 7) for c in (NEURAL_INPUTS,
                                                                                               NEURAL_INPUTS + 1, 2)],
             3: [(1, 2), (5, 9)]}
    for which, indices in picks.items():
        for index in indices:
            plus, minus = [v.copy() for v in values], [v.copy() for v in values]
            plus[which][index] += 1e-4
            minus[which][index] -= 1e-4
            numeric = (mse(plus) - mse(minus)) / 2e-4
            assert grads[which][index] == pytest.approx(numeric, rel=2e-3, abs=2e-6), (which, index)


def test_cpu_training_learns_what_only_the_highlights_tell():
    """Targets that follow the highlights, not the direction: the decoder that sees them learns them, one that does
    not cannot."""
    rng = np.random.default_rng(7)
    directions, _, _, _ = _seeing(seed=2, lights=8, pixels=64)
    g = rng.uniform(0.0, 1.0, (8, 64)).astype(np.float32)
    targets = np.repeat(g[..., None], 3, axis=2) * np.float32(0.8)
    seeing, seen_history = train_decoder_cpu(targets, directions, epochs=60, batch=128, lr=1e-2, highlights=g)
    blind, blind_history = train_decoder_cpu(targets, directions, epochs=60, batch=128, lr=1e-2)
    assert seeing.weights[0].shape[1] == NEURAL_INPUTS + 2 and blind.weights[0].shape[1] == NEURAL_INPUTS
    assert seen_history[-1] < 0.2 * blind_history[-1]
    with pytest.raises(ValueError, match="pass highlights"):
        train_decoder_cpu(targets, directions, epochs=1, initial=seeing)


def test_cpu_decode_with_highlights_matches_the_reference():
    directions, _, model, g = _seeing(seed=4, lights=3, pixels=6 * 7)
    learned = NeuralResidual(model.codes.reshape(6, 7, -1).astype(np.float16), tuple(model.weights), 1.7, 5)
    assert learned.sees_highlights
    field_units = g.reshape(3, 6, 7) * np.float32(1.7)
    want = learned_images(learned, directions, field_units)
    codes = learned.codes.reshape(42, -1).astype(np.float32)
    values = decode_cpu(codes, learned.weights, directions, g)
    np.testing.assert_allclose(values, _reference(codes.astype(np.float64), [w.astype(np.float64) for w in
                                                                              learned.weights], directions, g),
                               rtol=1e-4, atol=1e-4)
    out = np.empty((3, 42, 3), np.float16)
    decoder = CpuQueryDecoder(codes, learned.weights, learned.unit)
    assert decoder.sees_highlights
    decoder.decode(directions, out, field_units.reshape(3, 42))
    np.testing.assert_allclose(out.reshape(3, 6, 7, 3), want, rtol=2e-3, atol=2e-3)
    with pytest.raises(InputError, match="sees the highlights"):
        learned_images(learned, directions)
    with pytest.raises(ValueError, match="sees the highlights"):
        decode_cpu(codes, learned.weights, directions)


def test_field_file_keeps_a_decoder_that_sees_the_highlights(small_donut, tmp_path):
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.fieldfile import load_field, save_field
    from warp_highlights.model.config import FitSettings
    from warp_highlights.relight.relighter import Relighter

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=2",
                                                     "residual.learned_tune_epochs=2",
                                                     "residual.learned_seeing_margin_db=100",
                                                     "residual.learned_sees_gaussians=true",
                                                     "residual.move_support=0"])
    field = fit_field(dataset, device="cpu", settings=settings, progress=False)
    verdict = field.report["residual"]["learned_check"]
    # every light checked by the move check (its moved Gaussians are the decoder's inputs), the Gaussians kept
    assert field.report["residual"]["move_check"]["lights"] == dataset.light_count
    assert verdict["sees_gaussians"] and verdict["keeps_gaussians"] and field.estimated.active.any()
    learned = field.residual.learned
    assert learned.sees_highlights and learned.weights[0].shape == (48, NEURAL_INPUTS + 2)
    path = tmp_path / "seeing.whf"
    save_field(field, path)
    loaded = load_field(path)
    assert loaded.residual.learned.sees_highlights
    for got, want in zip(loaded.residual.learned.weights, learned.weights):
        np.testing.assert_array_equal(got, want)
    directions = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    relit = Relighter(loaded, device="cpu").relight(directions)
    gaussians = Relighter(loaded, device="cpu").launch(directions, full=False).specular.numpy()
    # the decoder's values are the whole image: the Gaussians are its inputs, not added to it
    want = np.clip(learned_images(loaded.residual.learned, directions, gaussians), 0.0, None)
    assert np.all(np.isfinite(relit.full)) and relit.full.min() >= 0
    np.testing.assert_allclose(relit.full, want, atol=2e-3 * max(1.0, float(np.abs(want).max())))

    from test_field import load_error, rewrite

    def learned_header(value):
        return lambda h: {**h, "residual": {**h["residual"], "learned": {**h["residual"]["learned"],
                                                                         "highlights": value}}}

    for value, words in ((False, "residual/learned_w0"), ("yes", "residual.learned.highlights")):
        rewrite(path.read_bytes(), tmp_path / "changed.whf", header=learned_header(value))
        assert words in load_error(tmp_path / "changed.whf")


def test_learned_check_weighs_a_seeing_decoder_where_the_move_check_prefers_blending(small_donut, monkeypatch):
    """The move check weighs moved Gaussians added to a blend: its verdict does not gate a decoder that sees them,
    which the learned check weighs; the residual they would be added to stays gated by it."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    real = pipeline.check_moving

    def blending_wins(*args, **kwargs):
        check = real(*args, **kwargs)
        return dataclasses.replace(check, moving_psnr=check.blend_psnr - 1.0)

    monkeypatch.setattr(pipeline, "check_moving", blending_wins)
    dataset = ReflectanceField.load(small_donut, progress=False)
    base = FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=2", "residual.learned_tune_epochs=2",
                       "residual.move_support=0", "residual.learned_seeing_margin_db=100",
                       "residual.learned_sees_gaussians=true",
                       "residual.learned_tie_margin_db=100"]
    seeing = pipeline.fit_field(dataset, device="cpu", settings=FitSettings().with_overrides(base), progress=False)
    report = seeing.report["residual"]
    assert not report["move_check"]["moves"] and report["learned_check"]["keeps_gaussians"]
    assert seeing.residual.learned.sees_highlights and seeing.estimated.active.any()
    added = pipeline.fit_field(dataset, device="cpu", progress=False,
                               settings=FitSettings().with_overrides(base + ["residual.learned_sees_gaussians=false"]))
    assert not added.report["residual"].get("learned_check") and not added.estimated.active.any()


@pytest.mark.parametrize("inputs", ["moved", "own"])
def test_a_seeing_decoder_learns_with_the_moved_or_its_own_gaussians(small_donut, monkeypatch, inputs):
    """``residual.learned_seeing_inputs``: "moved" trains the check's decoder with every light's Gaussians moved there
    from the other lights; "own" with each light's own, but the check's left-out lights with the moved ones (as a
    query between the lights gets them), and the field's decoder learns every light with its own."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    seen = {}
    real_moving, real_check, real_learn = pipeline.check_moving, pipeline.check_learned, pipeline.learn_residual

    def check_moving(*args, **kwargs):
        seen["move"] = real_moving(*args, **kwargs)
        return seen["move"]

    def check_learned(images, own, *args, **kwargs):
        seen["check"] = (own.copy(), np.array(kwargs["seen"]))
        return real_check(images, own, *args, **kwargs)

    def learn_residual(images, own, *args, **kwargs):
        seen["learn"] = (own.copy(), None if kwargs.get("highlights") is None else np.array(kwargs["highlights"]))
        return real_learn(images, own, *args, **kwargs)

    monkeypatch.setattr(pipeline, "check_moving", check_moving)
    monkeypatch.setattr(pipeline, "check_learned", check_learned)
    monkeypatch.setattr(pipeline, "learn_residual", learn_residual)
    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + [
        "residual.kind=learned", "residual.learned_epochs=2", "residual.learned_tune_epochs=1",
        "residual.move_support=0", "residual.learned_seeing_margin_db=100", "residual.learned_sees_gaussians=true",
        "residual.learned_anew_share=0", f"residual.learned_seeing_inputs={inputs}"])
    field = pipeline.fit_field(dataset, device="cpu", settings=settings, progress=False)
    assert field.report["residual"]["learned_check"]["keeps_gaussians"] and field.residual.learned.sees_highlights
    move = seen["move"]
    own, checked = seen["check"]
    kept = np.asarray(move.kept_lights)
    assert len(kept) and np.any(own > 0)
    rows = [list(map(int, move.lights)).index(int(light)) for light in kept]
    # the check's left-out lights: the Gaussians moved there, whichever the setting
    np.testing.assert_array_equal(checked[kept], move.moved_luminance[rows])
    others = np.setdiff1d(np.arange(len(own)), kept)
    learned_own, learned_with = seen["learn"]
    if inputs == "own":
        np.testing.assert_array_equal(checked[others], own[others])
        np.testing.assert_array_equal(learned_with, learned_own)
    else:
        assert move.lights.size == dataset.light_count
        moved = np.setdiff1d(np.asarray(move.lights), kept)
        rows = [list(map(int, move.lights)).index(int(light)) for light in moved]
        np.testing.assert_array_equal(checked[moved], move.moved_luminance[rows])
        assert not np.array_equal(checked[moved], own[moved])
        np.testing.assert_array_equal(learned_with, checked)


def test_seeing_inputs_are_moved_or_own():
    from warp_highlights.model.config import ResidualSettings

    assert ResidualSettings().learned_seeing_inputs == "own"
    with pytest.raises(InputError, match="learned_seeing_inputs must be one of moved, own, got 'both'"):
        ResidualSettings(learned_seeing_inputs="both")
