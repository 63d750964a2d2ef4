"""The learned residual trained and decoded on the CPU in NumPy (``residual.cpu_training``) against float64
references: gradients by central differences, Adam, the decode, and training as ``kernels.neural`` trains."""

from __future__ import annotations

import numpy as np
import pytest

import reference
from warp_highlights.kernels import neural, neural_training
from warp_highlights.residual import cpu_training
from warp_highlights.residual.cpu_training import decode_cpu, train_decoder_cpu
from warp_highlights.residual.opponent import encode_display


def _problem(seed=0, lights=6, pixels=70):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    targets = rng.uniform(0.0, 1.0, (lights, pixels, 3)).astype(np.float32)
    return directions.astype(np.float32), targets


def _lambertian(seed=4, lights=12, pixels=64):
    """Display-unit images of Lambertian pixels with random normals and albedos."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.3
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    normals = rng.normal(size=(pixels, 3)) * [0.4, 0.4, 1.0]
    normals[:, 2] = np.abs(normals[:, 2])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.2, 0.9, (pixels, 3))
    targets = encode_display(np.clip(directions @ normals.T, 0.0, None)[..., None] * albedo[None])
    return directions.astype(np.float32), targets.astype(np.float32)


def test_gradients_match_central_differences():
    """A batch of shuffled samples with repeated pixels (their code gradients add up) and pixels left out
    (zero gradient): every array's gradient against float64 central differences of the batch's loss."""
    directions, targets = _problem(seed=1, lights=5, pixels=40)
    model = neural.initial_model(targets, seed=2)
    rng = np.random.default_rng(3)
    samples = rng.choice(5 * 40, 40, replace=False)
    params = cpu_training._Parameters(model)
    batch = cpu_training._Batch(128, 40, params.flat.size - params.codes.size, threads=2)  # two workers' sums
    loss = batch.step(samples, params, directions, targets.reshape(-1, 3))
    np.testing.assert_array_equal(params.codes, model.codes)  # a step computes, Adam moves
    grads = [params.g_codes, params.g_w0[:, :12], params.g_w0[:, 12:], params.g_w1, params.g_b1.reshape(-1, 1),
             params.g_w2, params.g_b2.reshape(-1, 1), params.g_w3, params.g_b3.reshape(-1, 1)]
    lights, pixels = np.divmod(samples, 40)
    want_values = [model.codes.astype(np.float64)] + [w.astype(np.float64) for w in model.weights]

    def mse(values):
        decoded = reference.neural_decoder(values[0], values[1:], directions)[lights, pixels]
        return np.mean(np.sum((decoded - targets[lights, pixels]) ** 2, axis=-1))

    assert loss == pytest.approx(mse(want_values), rel=1e-5)
    unsampled = np.setdiff1d(np.arange(40), pixels)
    assert len(unsampled) and np.all(params.g_codes[unsampled] == 0.0)
    repeated = np.flatnonzero(np.bincount(pixels, minlength=40) > 1)
    for which, value in enumerate(want_values):
        picks = [tuple(rng.integers(0, s) for s in value.shape) for _ in range(4)]
        if which == 0:
            picks += [(int(repeated[0]), k) for k in range(9)]
        for index in picks:
            step = 1e-4
            plus = [v.copy() for v in want_values]
            minus = [v.copy() for v in want_values]
            plus[which][index] += step
            minus[which][index] -= step
            numeric = (mse(plus) - mse(minus)) / (2 * step)
            assert grads[which][index] == pytest.approx(numeric, rel=2e-3, abs=2e-6), (which, index)


def test_adam_matches_a_float64_reference():
    """Three steps of warp.optim.Adam's update, m^ = m / (1 - b1^t), v^ = v / (1 - b2^t), in float64."""
    rng = np.random.default_rng(5)
    start = rng.normal(size=200)
    grads = [rng.normal(size=200) * s for s in (1.0, 1e-3, 10.0)]
    grads[1][:50] = 0.0
    params = start.astype(np.float32)
    adam = cpu_training._Adam(200)
    want, m, v = start.copy(), np.zeros(200), np.zeros(200)
    for t, (g, lr) in enumerate(zip(grads, (3e-3, 1e-3, 3e-4))):
        adam.step(params, g.astype(np.float32), lr)
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        want = want - lr * (m / (1 - 0.9 ** (t + 1))) / (np.sqrt(v / (1 - 0.999 ** (t + 1))) + 1e-8)
        np.testing.assert_allclose(params, want, rtol=1e-5, atol=1e-7)
    assert adam.t == 3


def test_decode_matches_the_reference_and_warp(monkeypatch):
    """Several chunks of pixels, the last one short, against the float64 MLP and kernels.neural.decode (CPU)."""
    monkeypatch.setattr(cpu_training, "DECODE_CHUNK", 64)
    directions, targets = _problem(lights=4, pixels=150)
    model = neural.initial_model(targets, seed=3)
    model.codes[:] *= 3.0  # both signs at every layer's input
    got = decode_cpu(model.codes, model.weights, directions)
    assert got.shape == (4, 150, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, reference.neural_decoder(model.codes, model.weights, directions), atol=2e-5,
                               rtol=1e-4)
    np.testing.assert_allclose(got, neural.decode(model, directions, device="cpu"), atol=2e-5, rtol=1e-4)
    # the code part computed per chunk (a large image) gives the same values; one direction into ``out``
    monkeypatch.setattr(cpu_training, "CODE_PART_BYTES", 0)
    decoder = cpu_training.CpuDecoder(model.codes, model.weights)
    assert decoder.code_part is None
    np.testing.assert_allclose(decoder.decode(directions), got, rtol=1e-6, atol=1e-6)
    out = np.full((1, 150, 3), np.nan, np.float32)
    assert decoder.decode(directions[2], out=out) is out
    np.testing.assert_allclose(out[0], got[2], rtol=1e-6, atol=1e-6)


def test_one_epoch_matches_warp_training():
    """One epoch of one full-batch step (every used sample once, in any order) ends where the device's fused step
    (``kernels.neural_training.train_decoder`` on Warp's CPU) ends, within float32 rounding."""
    directions, targets = _problem(seed=6, lights=5, pixels=128)
    used = np.array([0, 2, 3, 4])  # 512 samples: one step of the device's 512-sample unit
    kwargs = {"epochs": 1, "batch": 512, "lr": 1e-2, "seed": 7, "used": used}
    model, history = train_decoder_cpu(targets, directions, **kwargs)
    want, want_history = neural_training.train_decoder(targets, directions, device="cpu", **kwargs)
    assert history[0] == pytest.approx(want_history[0], rel=1e-5)
    np.testing.assert_allclose(model.codes, want.codes, atol=1e-5)
    for got, expected in zip(model.weights, want.weights):
        np.testing.assert_allclose(got, expected, atol=1e-5)


def test_training_learns_a_smooth_reflectance():
    """Lambertian pixels: 150 epochs fit them far below their variance; the log says every epoch."""
    directions, targets = _lambertian()
    lines = []
    model, history = train_decoder_cpu(targets, directions, epochs=150, batch=192, lr=1e-2, final_lr=1e-3,
                                       log=lines.append)
    assert len(history) == 150 and np.all(np.isfinite(history)) and len(lines) == 150
    assert lines[-1].startswith("epoch 150/150: mse ")
    variance = float(np.mean(np.sum((targets - targets.mean(axis=(0, 1))) ** 2, axis=-1)))
    assert history[0] > 0.2 * variance and history[-1] < 0.05 * variance
    decoded = decode_cpu(model.codes, model.weights, directions)
    assert np.mean(np.sum((decoded - targets) ** 2, axis=-1)) < 0.05 * variance
    # going on from the model keeps its fit; one epoch
    more, again = train_decoder_cpu(targets, directions, epochs=1, batch=192, lr=1e-3, initial=model)
    assert again[0] < 0.05 * variance


def test_unused_lights_are_never_read():
    """NaN targets at the left-out lights: the model is finite and the same as with any other values there."""
    directions, targets = _lambertian(lights=8, pixels=48)
    used = np.array([0, 1, 3, 4, 6])
    poisoned = targets.copy()
    poisoned[[2, 5, 7]] = np.nan
    kwargs = {"epochs": 3, "batch": 100, "used": used}
    model, history = train_decoder_cpu(poisoned, directions, **kwargs)
    assert np.all(np.isfinite(history)) and np.all(np.isfinite(model.codes))
    assert all(np.all(np.isfinite(w)) for w in model.weights)
    other, _ = train_decoder_cpu(targets, directions, **kwargs)
    np.testing.assert_array_equal(model.codes, other.codes)
    for a, b in zip(model.weights, other.weights):
        np.testing.assert_array_equal(a, b)


def test_seconds_stop_training_and_bad_arguments_raise():
    directions, targets = _problem(lights=3, pixels=30)
    _, history = train_decoder_cpu(targets, directions, device="cpu", epochs=50, batch=16, seconds=0.0)
    assert len(history) == 1
    with pytest.raises(ValueError, match="used"):
        train_decoder_cpu(targets, directions, used=np.array([3]))
    with pytest.raises(ValueError, match="on the CPU"):
        train_decoder_cpu(targets, directions, device="cuda:0")
    with pytest.raises(ValueError, match="initial codes"):
        train_decoder_cpu(targets, directions, initial=neural.initial_model(targets[:, :20]))


def test_query_decoder_stores_field_units_as_warps():
    """CpuQueryDecoder into Warp CPU arrays: float16 field units as kernels.neural.QueryDecoder stores them."""
    import warp as wp

    directions, targets = _problem(lights=3, pixels=200)
    model = neural.initial_model(targets, seed=4)
    model.codes[:] *= 4.0
    queries = wp.array(directions, dtype=wp.vec3, device="cpu")
    got = wp.zeros((3, 200, 3), dtype=wp.float16, device="cpu")
    cpu_training.CpuQueryDecoder(model.codes, model.weights, 2.5, device="cpu").decode(queries, got)
    want = wp.zeros((3, 200, 3), dtype=wp.float16, device="cpu")
    neural.QueryDecoder(model.codes, model.weights, 2.5, device="cpu").decode(queries, want)
    got, want = got.numpy().astype(np.float32), want.numpy().astype(np.float32)
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-4)
    values = reference.neural_decoder(model.codes, model.weights, directions)
    assert np.any(values < 0) and np.any(np.abs(values) < 0.04045) and np.any(values > 0.04045)  # every branch
    linear = np.where(np.abs(values) > 0.04045, ((np.abs(values) + 0.055) / 1.055) ** 2.4, np.abs(values) / 12.92)
    np.testing.assert_allclose(got, np.sign(values) * linear * 2.5, rtol=2e-3, atol=1e-4)
