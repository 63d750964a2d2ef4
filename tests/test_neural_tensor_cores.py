"""The learned residual's training step on tensor cores (``kernels.neural_tensor_cores``, CUDA of compute capability
8.0 or newer) against float64 NumPy: the loss and every gradient (codes and the eight weight arrays, a model that sees
the highlights beside one that does not, several blocks of several passes) within TF32's precision; the weights'
gradients the same in every run; training that learns as Warp's tile products do. On a machine without such a GPU,
only the choice of the step is checked."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from test_neural_training import _one_step_gradients, _problem, seeing_decoder
from warp_highlights.kernels import neural, neural_training
from warp_highlights.kernels.neural_tensor_cores import MIN_ARCH


def _tensor_core_device() -> str | None:
    if not wp.is_cuda_available():
        return None
    device = wp.get_device("cuda:0")
    return "cuda:0" if device.arch >= MIN_ARCH else None


needs_tensor_cores = pytest.mark.skipif(_tensor_core_device() is None,
                                        reason="needs a CUDA GPU of compute capability 8.0 or newer")


def _elu(v):
    return np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))


def reference_step(codes, weights, directions, luminance, light, pixel, targets):
    """float64 loss (the mean over the samples of the squared error summed over the colour channels) and its
    gradients [codes (P, 9), w0, b0, w1, b1, w2, b2, w3, b3] for samples (light[i], pixel[i]); w0 of 14 columns takes
    sqrt(g), g of ``luminance`` (L, P) as its last two inputs."""
    w0, b0, w1, b1, w2, b2, w3, b3 = (np.asarray(w, np.float64) for w in weights)
    codes = np.asarray(codes, np.float64)
    x = [codes[pixel], np.asarray(directions, np.float64)[light]]
    if w0.shape[1] == 14:
        g = np.maximum(np.asarray(luminance, np.float64)[light, pixel], 0.0)
        x += [np.sqrt(g)[:, None], g[:, None]]
    x = np.concatenate(x, axis=1)
    h1 = _elu(x @ w0.T + b0.T)
    h2 = _elu(h1 @ w1.T + b1.T)
    h3 = _elu(h2 @ w2.T + b2.T)
    error = h3 @ w3.T + b3.T - np.asarray(targets, np.float64)[light, pixel]
    count = len(light)
    dy = 2.0 * error / count
    gradients = [None] * 9
    gradients[7], gradients[8] = dy.T @ h3, dy.sum(0)[:, None]
    d3 = (dy @ w3) * np.where(h3 > 0, 1.0, h3 + 1.0)
    gradients[5], gradients[6] = d3.T @ h2, d3.sum(0)[:, None]
    d2 = (d3 @ w2) * np.where(h2 > 0, 1.0, h2 + 1.0)
    gradients[3], gradients[4] = d2.T @ h1, d2.sum(0)[:, None]
    d1 = (d2 @ w1) * np.where(h1 > 0, 1.0, h1 + 1.0)
    gradients[1], gradients[2] = d1.T @ x, d1.sum(0)[:, None]
    gradients[0] = np.zeros_like(codes)
    np.add.at(gradients[0], pixel, (d1 @ w0)[:, :codes.shape[1]])
    return float(np.sum(error**2) / count), gradients


def test_the_reference_gradients_match_central_differences():
    """The float64 reference of this file against central differences, a few entries of every array."""
    directions, targets = _problem(seed=3, lights=4, pixels=30, models=1)
    g = np.random.default_rng(4).uniform(-0.2, 1.5, (4, 30))
    rng = np.random.default_rng(5)
    light, pixel = rng.integers(0, 4, 50), rng.integers(0, 30, 50)
    model = seeing_decoder(30, seed=6)
    params = [model.codes.astype(np.float64)] + [w.astype(np.float64) for w in model.weights]
    _, gradients = reference_step(params[0], params[1:], directions, g, light, pixel, targets[0])
    for which, values in enumerate(params):
        for _ in range(3):
            index = tuple(int(rng.integers(0, s)) for s in values.shape)
            if which == 0:
                index = (int(pixel[rng.integers(len(pixel))]), index[1])
            plus, minus = [p.copy() for p in params], [p.copy() for p in params]
            plus[which][index] += 1e-5
            minus[which][index] -= 1e-5
            numeric = (reference_step(plus[0], plus[1:], directions, g, light, pixel, targets[0])[0]
                       - reference_step(minus[0], minus[1:], directions, g, light, pixel, targets[0])[0]) / 2e-5
            assert gradients[which][index] == pytest.approx(numeric, rel=1e-5, abs=1e-9), (which, index)


def test_the_step_is_chosen_by_the_device():
    """Tensor cores by default only on a CUDA GPU that has them; asked for on the CPU, a clear error."""
    assert not neural_training.has_tensor_cores("cpu")
    directions, targets = _problem(seed=1, models=1)
    model = neural.initial_model(targets[0], seed=0)
    trainer = neural_training.DecoderTrainer(targets, directions, np.arange(5), [model], 64, 2, device="cpu")
    assert trainer.tensor_cores is False
    with pytest.raises(ValueError, match="compute capability 8.0"):
        neural_training.DecoderTrainer(targets, directions, np.arange(5), [model], 64, 2, device="cpu",
                                       tensor_cores=True)


@needs_tensor_cores
@pytest.mark.parametrize("passes", [1, 3])
def test_the_tensor_core_step_matches_the_float64_reference(passes):
    """A model that sees the highlights beside one that does not, 4 blocks of ``passes`` passes, two lights left out:
    the loss within 0.5% and each gradient array within 1% (relative to its norm) of float64; the codes' gradients
    only at the pixels the step saw; the blind model's highlight columns get none."""
    device = _tensor_core_device()
    directions, targets = _problem(seed=2, lights=7, pixels=700)
    g = np.random.default_rng(3).uniform(-0.3, 2.0, (7, 700)).astype(np.float32)
    models = [seeing_decoder(700, seed=5), neural.initial_model(targets[1], seed=3)]
    used = np.array([0, 1, 3, 4, 6])
    batch = 4 * 128 * passes
    trainer = neural_training.DecoderTrainer(targets, directions, used, models, batch, 10, device=device,
                                             highlights=g, sees=(True, False), tensor_cores=True,
                                             tensor_passes=passes)
    assert trainer.tensor_cores and trainer.blocks == 4 and trainer.batch == batch
    samples, loss, gradients = _one_step_gradients(trainer)
    light, pixel = samples // 700, samples % 700
    assert set(light) <= set(used)
    for m in range(2):
        weights = [w.astype(np.float64) for w in models[m].weights]
        expected_loss, expected = reference_step(models[m].codes, weights, directions, g, light, pixel, targets[m])
        assert loss[m] == pytest.approx(expected_loss, rel=5e-3)
        for which, reference_gradient in enumerate(expected):
            got = gradients[which][m]
            if which == 1 and m == 1:  # the blind model: no gradient for the highlights' columns
                assert not np.any(got[:, 12:])
                got = got[:, :12]
            error = np.linalg.norm(got - reference_gradient) / np.linalg.norm(reference_gradient)
            assert error < 1e-2, (m, which, error)
        unseen = np.setdiff1d(np.arange(700), pixel)
        assert np.all(gradients[0][m][unseen] == 0.0)


@needs_tensor_cores
def test_the_tensor_core_weights_gradients_are_the_same_in_every_run():
    """The blocks' partial sums added in block order: two runs give the weights' gradients bit for bit."""
    device = _tensor_core_device()
    directions, targets = _problem(seed=4, pixels=400)
    models = [neural.initial_model(targets[m], seed=m) for m in range(2)]
    runs = []
    for _ in range(2):
        trainer = neural_training.DecoderTrainer(targets, directions, np.arange(5), models, 1024, 10, device=device,
                                                 tensor_cores=True, tensor_passes=1)
        assert trainer.blocks == 8
        runs.append(_one_step_gradients(trainer)[2][1:])
    for first, second in zip(*runs):
        assert np.any(first != 0.0)
        np.testing.assert_array_equal(first, second)


@needs_tensor_cores
def test_training_on_tensor_cores_learns_as_with_tile_products():
    """The same problem, schedule and samples trained on tensor cores and through Warp's tile products: every epoch's
    mean loss within 3% of the other's."""
    device = _tensor_core_device()
    directions, targets = _problem(seed=6, lights=8, pixels=1024, models=1)
    histories = []
    for tensor_cores in (True, False):
        _, history = neural_training.train_decoders(targets, directions, device=device, epochs=12, batch=2048,
                                                    tensor_cores=tensor_cores)
        histories.append(history[:, 0])
    np.testing.assert_allclose(histories[0], histories[1], rtol=3e-2)
    assert histories[0][-1] < 0.5 * histories[0][0]
