"""Batched Adam: against a NumPy Adam, frozen free slots, per-slot steps, and a real recovery fit."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from gaussian_cases import random_params
from warp_highlights.kernels import losses
from warp_highlights.kernels.optim import GaussianAdam
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.model.config import AdamSettings, rpx_to_normalized
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

GROUPS = {"amplitude": "lr_amplitude", "mean": "lr_mean_rpx", "sigma": "lr_sigma_rpx", "theta": "lr_theta"}


def _numpy_adam(values, gradients, settings, steps):
    """Reference Adam on one parameter array with a fixed gradient sequence."""
    m = np.zeros_like(values)
    v = np.zeros_like(values)
    for t, g in enumerate(gradients[:steps], start=1):
        m = settings.beta1 * m + (1 - settings.beta1) * g
        v = settings.beta2 * v + (1 - settings.beta2) * g * g
        m_hat = m / (1 - settings.beta1**t)
        v_hat = v / (1 - settings.beta2**t)
        values = values - settings.lr * m_hat / (np.sqrt(v_hat) + settings.epsilon)
    return values


def test_adam_matches_numpy_per_group_and_freezes_free_slots(device):
    rng = np.random.default_rng(0)
    params = random_params(rng, 3, 4, 20, 20, inactive=0.3)
    batch = GaussianBatch.from_numpy(params, device=device)
    start = batch.numpy()
    settings = AdamSettings(lr_amplitude=0.05, lr_mean_rpx=0.7, lr_sigma_rpx=0.3, lr_theta=0.01)
    adam = GaussianAdam(batch, settings)
    history = {name: [] for name in GROUPS}
    for _ in range(5):
        for name in GROUPS:
            g = rng.normal(size=getattr(start, name).shape).astype(np.float32)
            history[name].append(g.astype(np.float64))
            getattr(batch, name).grad.assign(g)
        adam.step()
    result = batch.numpy()
    for name, lr_name in GROUPS.items():
        lr = getattr(settings, lr_name)
        if name in ("mean", "sigma"):
            lr = rpx_to_normalized(lr)

        class Constants:
            pass

        k = Constants()
        k.beta1, k.beta2, k.epsilon, k.lr = settings.beta1, settings.beta2, settings.epsilon, lr
        expected = _numpy_adam(getattr(start, name), history[name], k, 5)
        active = start.active if expected.ndim == 2 else start.active[..., None].repeat(2, axis=-1)
        np.testing.assert_allclose(getattr(result, name)[active], expected[active], rtol=1e-5, atol=1e-6, err_msg=name)
        np.testing.assert_array_equal(getattr(result, name)[~active], getattr(start, name)[~active])
    np.testing.assert_array_equal(result.weight, start.weight)
    np.testing.assert_array_equal(adam.steps.numpy(), np.where(start.active, 5, 0))


def test_reset_restarts_bias_correction_of_chosen_slots(device):
    params = random_params(np.random.default_rng(1), 1, 3, 20, 20, inactive=0.0)
    batch = GaussianBatch.from_numpy(params, device=device)
    adam = GaussianAdam(batch, AdamSettings(lr_amplitude=0.1))
    batch.amplitude.grad.fill_(1.0)
    for _ in range(3):
        adam.step()
    adam.reset(np.array([[False, True, False]]))
    np.testing.assert_array_equal(adam.steps.numpy(), [[3, 0, 3]])
    before = batch.numpy().amplitude
    adam.step()  # a fresh slot moves by one learning rate on its first step
    assert before[0, 1] - batch.numpy().amplitude[0, 1] == pytest.approx(0.1, rel=1e-4)
    with pytest.raises(InputError, match="reset mask"):
        adam.reset(np.ones((2, 3), dtype=bool))
    with pytest.raises(InputError, match="requires_grad"):
        GaussianAdam(GaussianBatch(1, 1, device=device, requires_grad=False))


def test_a_refilled_slot_restarts_without_an_explicit_reset(device):
    params = random_params(np.random.default_rng(2), 1, 3, 20, 20, inactive=0.0)
    batch = GaussianBatch.from_numpy(params, device=device)
    adam = GaussianAdam(batch, AdamSettings(lr_amplitude=0.02))
    batch.amplitude.grad.fill_(-1.0)
    for _ in range(50):
        adam.step()
    batch.remove(np.array([[False, True, False]]))
    batch.add([0], amplitude=[1.0], mean=[[0.5, 0.5]], sigma=[[0.02, 0.02]], theta=[0.0])
    batch.amplitude.grad.fill_(1.0)
    adam.step()
    after = batch.numpy().amplitude[0]
    assert after[1] == pytest.approx(1.0 - 0.02, rel=1e-5)  # a fresh first step, not the old momentum
    np.testing.assert_array_equal(adam.steps.numpy(), [[51, 1, 51]])


def _three_gaussians() -> GaussianParams:
    return GaussianParams.from_sets(
        [
            {
                "amplitude": [1.1, 0.8, 0.9],
                "mean": [[0.45, 0.40], [0.95, 0.55], [1.30, 0.35]],
                "sigma": [[rpx_to_normalized(14), rpx_to_normalized(6)], [rpx_to_normalized(9), rpx_to_normalized(9)],
                          [rpx_to_normalized(18), rpx_to_normalized(4)]],
                "theta": [0.5, 0.0, 2.2],
            }
        ]
    )


def _fitting_step(batch, raster, fit, adam):
    """One allocation-free fitting iteration as a function, and the loss array it writes."""
    loss = wp.zeros(1, dtype=float, device=batch.device, requires_grad=True)
    image = raster.new_image(1)

    def step():
        loss.zero_()
        tape = wp.Tape()
        with tape:
            fit(raster.render(batch, out=image), out=loss)
        tape.backward(loss=loss)
        adam.step()
        tape.zero()

    return step, loss


def _fit(batch, raster, fit, adam, iterations):
    step, loss = _fitting_step(batch, raster, fit, adam)
    for _ in range(iterations):
        step()
    return float(loss.numpy()[0])


def test_adam_recovers_three_known_gaussians_from_their_image(device):
    height, width = 72, 128
    truth = _three_gaussians()
    raster = Rasterizer(height, width, device=device)
    target = raster.render(GaussianBatch.from_numpy(truth, device=device, requires_grad=False))
    start = truth.copy()
    start.mean += rpx_to_normalized(4) * np.array([[[1, -1], [-1, -1], [1, 1]]]) / np.sqrt(2)
    start.sigma *= np.array([[[1.3, 0.75], [0.75, 1.3], [1.3, 1.3]]])
    start.amplitude *= [[0.8, 1.2, 0.8]]
    start.theta += [[0.25, 0.0, -0.25]]
    batch = GaussianBatch.from_numpy(start, device=device)
    fit = losses.LogL1Loss(target, device=device)
    initial = fit(raster.render(batch)).numpy()[0]
    final = _fit(batch, raster, fit, GaussianAdam(batch), 400)
    assert final < 0.03 * initial  # Adam settles within ~1% (its step-size jitter); the parameters are the real check
    got = batch.numpy()
    np.testing.assert_allclose(got.mean, truth.mean, atol=rpx_to_normalized(0.3))
    np.testing.assert_allclose(np.abs(got.sigma), truth.sigma, rtol=0.03)
    np.testing.assert_allclose(np.abs(got.amplitude), truth.amplitude, rtol=0.03)
    # orientation of the anisotropic ones, modulo pi
    for n in (0, 2):
        delta = (got.theta[0, n] - truth.theta[0, n] + np.pi / 2) % np.pi - np.pi / 2
        assert abs(delta) < 0.03


@pytest.mark.skipif(not wp.is_cuda_available(), reason="CUDA graphs need a CUDA device")
def test_fitting_step_captures_in_a_cuda_graph():
    device = "cuda:0"
    height, width = 72, 128
    truth = _three_gaussians()
    raster = Rasterizer(height, width, device=device)
    target = raster.render(GaussianBatch.from_numpy(truth, device=device, requires_grad=False))
    start = truth.copy()
    start.mean += rpx_to_normalized(3)
    eager = GaussianBatch.from_numpy(start, device=device)
    captured = GaussianBatch.from_numpy(start, device=device)
    fit = losses.LogL1Loss(target, device=device)
    _fit(eager, raster, fit, GaussianAdam(eager), 20)

    adam = GaussianAdam(captured)
    step, _ = _fitting_step(captured, raster, fit, adam)
    with wp.ScopedCapture(device=device) as capture:
        step()
    for _ in range(20):
        wp.capture_launch(capture.graph)
    np.testing.assert_allclose(captured.numpy().mean, eager.numpy().mean, atol=1e-6)
    np.testing.assert_array_equal(adam.steps.numpy()[0], [20, 20, 20])
