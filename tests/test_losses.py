"""Fit, structure and energy losses against float64 NumPy, values and gradients through wp.Tape."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import reference
from gaussian_cases import central_differences, inside_params
from warp_highlights.kernels import losses
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.model.config import StructureLossSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch

PARAMETERS = ("amplitude", "mean", "sigma", "theta", "weight")


def _pair(device, seed=0, problems=3, capacity=5, height=24, width=30, spread_rpx=None):
    """A reference batch and a perturbed copy (the current retargeted set), both host and device.

    ``spread_rpx`` clusters the means (standard deviation in rpx) so the structure loss sees them.
    """
    rng = np.random.default_rng(seed)
    original = inside_params(rng, problems, capacity, height, width, sigma_px=(1.0, 5.0))
    if spread_rpx is not None:
        original.mean = np.array([0.6, 0.5]) + rng.normal(0, spread_rpx / 270, original.mean.shape)
    original.active[1, 3] = False
    original.active[2, 1:] = False  # a problem with one Gaussian: no pairs
    current = original.copy()
    current.mean += rng.normal(0, 2.0 / height, current.mean.shape)
    current.sigma *= rng.uniform(0.7, 1.4, current.sigma.shape)
    current.amplitude *= rng.uniform(0.8, 1.2, current.amplitude.shape)
    current.theta += rng.normal(0, 0.3, current.theta.shape)
    fixed = GaussianBatch.from_numpy(original, device=device, requires_grad=False)
    moving = GaussianBatch.from_numpy(current, device=device)
    return fixed, moving


def _gradients_of(total_loss, batch):
    tape = wp.Tape()
    with tape:
        value = total_loss()
        scalar = losses.total(value)
    tape.backward(loss=scalar)
    assert scalar.numpy()[0] == pytest.approx(value.numpy().sum(), rel=1e-6)
    return value.numpy(), batch.gradients()


def test_log_l1_matches_numpy_and_uses_the_pixel_area(device):
    rng = np.random.default_rng(1)
    image = rng.uniform(0, 3, (2, 9, 13)).astype(np.float32)
    target = rng.uniform(-0.5, 3, (2, 9, 13)).astype(np.float32)
    fit = losses.LogL1Loss(target, device=device)
    value = fit(wp.array(image, device=device)).numpy()
    np.testing.assert_allclose(value, reference.log_l1(image.astype(np.float64), target, 9), rtol=1e-5)
    # the same images at twice the height measure the same
    doubled = losses.LogL1Loss(np.repeat(np.repeat(target, 2, axis=1), 2, axis=2), device=device)
    big = doubled(wp.array(np.repeat(np.repeat(image, 2, axis=1), 2, axis=2), device=device)).numpy()
    np.testing.assert_allclose(big, value, rtol=1e-5)


def test_log_l1_image_gradient_takes_each_problems_own_upstream_gradient(device):
    rng = np.random.default_rng(4)
    image = rng.uniform(0, 3, (3, 5, 7)).astype(np.float32)
    image[:, 1, :] = 0.0  # empty pixels take the no-logarithm path
    target = rng.uniform(0, 3, (3, 5, 7)).astype(np.float32)
    target[:, 1, :3] = 0.0
    fit = losses.LogL1Loss(target, device=device)
    pixels = wp.array(image, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        value = fit(pixels)
    upstream = np.array([1.0, -2.0, 0.5], dtype=np.float32)
    tape.backward(grads={value: wp.array(upstream, device=device)})
    area = reference.pixel_area(5)
    difference = np.log2(1 + image.astype(np.float64)) - np.log2(1 + target.astype(np.float64))
    expected = upstream[:, None, None] * area * np.sign(difference) / ((1 + image) * np.log(2))
    np.testing.assert_allclose(pixels.grad.numpy(), expected, rtol=1e-5, atol=1e-6)


def test_log_l1_without_its_value_records_the_same_gradient(device):
    rng = np.random.default_rng(6)
    image = rng.uniform(0, 3, (2, 6, 9)).astype(np.float32)
    image[:, 2, :] = 0.0
    target = rng.uniform(-0.5, 3, (2, 6, 9)).astype(np.float32)
    target[:, 3, :4] = image[:, 3, :4]  # R = S: no gradient
    fit = losses.LogL1Loss(target, device=device)
    gradients = []
    for value in (True, False):
        pixels = wp.array(image, device=device, requires_grad=True)
        out = wp.array([5.0, 7.0], dtype=float, device=device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            fit(pixels, out=out, weight=0.5, value=value)
        tape.backward(grads={out: wp.array([1.0, -3.0], dtype=float, device=device)})
        if not value:
            np.testing.assert_array_equal(out.numpy(), [5.0, 7.0])  # left as it was
        gradients.append(pixels.grad.numpy())
    np.testing.assert_array_equal(gradients[0], gradients[1])
    r, s = image.astype(np.float64), np.maximum(target, 0.0).astype(np.float64)
    expected = (np.array([1.0, -3.0])[:, None, None] * 0.5 * reference.pixel_area(6) * np.sign(r - s)
                / ((1 + r) * np.log(2)))
    np.testing.assert_allclose(gradients[0], expected, rtol=1e-5, atol=1e-6)
    assert np.all(gradients[0][:, 3, :4] == 0.0)


def test_fit_loss_gradient_through_the_rasterizer(device):
    height, width = 21, 27
    _, batch = _pair(device, seed=2, height=height, width=width)
    target = np.random.default_rng(3).uniform(0, 2, (3, height, width)).astype(np.float32)
    raster = Rasterizer(height, width, device=device)
    fit = losses.LogL1Loss(target, device=device)
    value, got = _gradients_of(lambda: fit(raster.render(batch)), batch)
    current = batch.numpy()
    np.testing.assert_allclose(value, reference.log_l1(reference.render(current, height, width), target, height),
                               rtol=1e-5)
    expected = central_differences(lambda p: reference.log_l1(reference.render(p, height, width), target, height).sum(),
                                   current)
    for name in PARAMETERS:
        np.testing.assert_allclose(got[name], expected[name], atol=3e-4 * np.abs(expected[name]).max(), err_msg=name)


def test_fit_loss_of_a_render_has_one_adjoint_with_the_same_gradients(device):
    """``of_render`` never stores the image gradient; the parameter gradients match the two-step tape
    (bit for bit on the CPU, where the sums run in the same order; CUDA's atomics may reorder them)."""
    height, width = 21, 27
    _, batch = _pair(device, seed=5, height=height, width=width)
    params = batch.numpy()
    target = np.random.default_rng(6).uniform(-0.2, 2, (3, height, width)).astype(np.float32)
    raster = Rasterizer(height, width, device=device)
    fit = losses.LogL1Loss(target, device=device)
    results = []
    for fused in (False, True):
        moving = GaussianBatch.from_numpy(params, device=device)
        image = raster.new_image(3)
        out = wp.zeros(3, dtype=float, device=device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            if fused:
                fit.of_render(raster, moving, image=image, out=out, weight=0.7)
            else:
                fit(raster.render(moving, out=image), out=out, weight=0.7)
        tape.backward(grads={out: wp.array([1.0, -2.0, 0.5], dtype=float, device=device)})
        results.append((out.numpy(), image.numpy(), moving.gradients()))
    (value, image, plain), (fused_value, fused_image, fused_gradients) = results
    np.testing.assert_array_equal(fused_value, value)
    np.testing.assert_array_equal(fused_image, image)
    for name in PARAMETERS:
        assert np.abs(plain[name]).max() > 0, name
        if wp.get_device(device).is_cuda:
            np.testing.assert_allclose(fused_gradients[name], plain[name], rtol=1e-5,
                                       atol=1e-6 * np.abs(plain[name]).max(), err_msg=name)
        else:
            np.testing.assert_array_equal(fused_gradients[name], plain[name], err_msg=name)


def test_a_fitting_step_reads_the_image_only_where_gaussians_draw(device):
    """``of_render(value=False)`` draws only the tiles Gaussians reach and leaves stale pixels elsewhere
    (here 7.0): the parameter gradients, the weight's of a slot of weight 0 among them, are those of a
    step that drew every pixel (bit for bit on the CPU)."""
    height, width = 40, 90  # most tiles empty
    _, batch = _pair(device, seed=8, height=height, width=width)
    params = batch.numpy()
    # drawn, scale 0: its tiles are listed all the same, though no other Gaussian reaches them
    params.weight[0, 0] = 0.0
    params.active[0, 2:] = False
    params.mean[0, 0], params.mean[0, 1] = (0.3, 0.3), (1.9, 0.7)
    params.sigma[0, :2] = 3.0 / height
    target = np.random.default_rng(9).uniform(0, 2, (3, height, width)).astype(np.float32)
    raster = Rasterizer(height, width, device=device)
    fit = losses.LogL1Loss(target, device=device)
    results = []
    for value in (True, False):
        moving = GaussianBatch.from_numpy(params, device=device)
        image = wp.array(np.full((3, height, width), 7.0, np.float32), device=device, requires_grad=True)
        out = wp.zeros(3, dtype=float, device=device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            fit.of_render(raster, moving, image=image, out=out, value=value)
        tape.backward(grads={out: wp.array([1.0, -2.0, 0.5], dtype=float, device=device)})
        results.append(moving.gradients())
        if not value:
            assert (image.numpy() == 7.0).any(), "some tiles were left as they were"
    full, drawn = results
    assert full["weight"][0, 0] != 0.0
    for name in (*PARAMETERS, "weight"):
        if wp.get_device(device).is_cuda:
            np.testing.assert_allclose(drawn[name], full[name], rtol=1e-5, atol=1e-6 * np.abs(full[name]).max(),
                                       err_msg=name)
        else:
            np.testing.assert_array_equal(drawn[name], full[name], err_msg=name)


def test_structure_loss_value_and_gradient(device):
    fixed, batch = _pair(device, seed=4, spread_rpx=15)
    settings = StructureLossSettings(gamma_per_rpx=0.4, threshold_rpx=40.0)  # smooth h: exercise every pair
    structure = losses.StructureLoss(fixed, settings)
    value, got = _gradients_of(lambda: structure(batch), batch)
    current, original = batch.numpy(), fixed.numpy()
    args = (settings.gamma_per_rpx, settings.threshold_rpx, settings.scale_eps_rpx)
    np.testing.assert_allclose(value, reference.structure_loss(current, original, *args), rtol=1e-4)
    assert value[2] == 0 and value[0] > 1 and value[1] > 1
    expected = central_differences(lambda p: reference.structure_loss(p, original, *args).sum(), current, step=1e-7)
    np.testing.assert_allclose(got["mean"], expected["mean"], atol=1e-3 * np.abs(expected["mean"]).max())
    for name in ("amplitude", "sigma", "theta", "weight"):
        assert np.all(got[name] == 0)


def test_structure_loss_is_zero_for_a_uniformly_scaled_set_only(device):
    fixed, batch = _pair(device, seed=5, spread_rpx=5)
    params = fixed.numpy()
    structure = losses.StructureLoss(fixed)
    scaled = params.copy()
    centre = np.array([0.6, 0.5])
    scaled.mean = centre + 1.3 * (params.mean - centre)
    batch.assign(scaled)
    assert np.all(np.abs(structure(batch).numpy()) < 1e-5)
    # the data can tell: the thesis' printed form (rho s - rho^)^2 is far from zero on it
    assert reference.structure_loss(scaled, params, thesis_form=True)[:2].min() > 1
    stretched = params.copy()
    stretched.mean[..., 0] = centre[0] + 1.3 * (params.mean[..., 0] - centre[0])  # x only: shape changes
    batch.assign(stretched)
    value = structure(batch).numpy()
    assert value[0] > 1 and value[1] > 1


def test_energy_loss_value_and_gradient(device):
    fixed, batch = _pair(device, seed=6)
    energy = losses.EnergyLoss(fixed)
    value, got = _gradients_of(lambda: energy(batch), batch)
    current, original = batch.numpy(), fixed.numpy()
    np.testing.assert_allclose(value, reference.energy_loss(current, original), rtol=1e-4)
    expected = central_differences(lambda p: reference.energy_loss(p, original).sum(), current, step=1e-7)
    for name in ("amplitude", "sigma"):
        np.testing.assert_allclose(got[name], expected[name], atol=1e-3 * np.abs(expected[name]).max(), err_msg=name)
    for name in ("mean", "theta", "weight"):
        assert np.all(got[name] == 0)


def test_weighted_sum_of_all_three_losses(device):
    height, width = 20, 26
    fixed, batch = _pair(device, seed=7, height=height, width=width, spread_rpx=12)
    target = np.random.default_rng(8).uniform(0, 1.5, (3, height, width)).astype(np.float32)
    raster = Rasterizer(height, width, device=device)
    fit, structure, energy = (losses.LogL1Loss(target, device=device), losses.StructureLoss(fixed),
                              losses.EnergyLoss(fixed))
    weights = (1.0, 0.05, 2e-3)

    def retarget_loss():
        out = wp.zeros(3, dtype=float, device=device, requires_grad=True)
        fit(raster.render(batch), out=out, weight=weights[0])
        structure(batch, out=out, weight=weights[1])
        energy(batch, out=out, weight=weights[2])
        return out

    value, got = _gradients_of(retarget_loss, batch)
    original = fixed.numpy()

    def expected_loss(p):
        return (
            weights[0] * reference.log_l1(reference.render(p, height, width), target, height)
            + weights[1] * reference.structure_loss(p, original)
            + weights[2] * reference.energy_loss(p, original)
        )

    current = batch.numpy()
    np.testing.assert_allclose(value, expected_loss(current), rtol=1e-4)
    expected = central_differences(lambda p: expected_loss(p).sum(), current)
    for name in PARAMETERS:
        np.testing.assert_allclose(got[name], expected[name], atol=5e-4 * np.abs(expected[name]).max(), err_msg=name)


def test_loss_errors_are_clear(device):
    fixed, batch = _pair(device)
    with pytest.raises(InputError, match="non-finite"):
        losses.LogL1Loss(np.full((1, 4, 4), np.nan, dtype=np.float32), device=device)
    with pytest.raises(InputError, match="shape"):
        losses.LogL1Loss(np.zeros((4, 4), dtype=np.float32), device=device)
    fit = losses.LogL1Loss(np.zeros((3, 4, 4), dtype=np.float32), device=device)
    with pytest.raises(InputError, match="does not match"):
        fit(wp.zeros((3, 4, 5), dtype=float, device=device))
    other = GaussianBatch(2, 5, device=device)
    with pytest.raises(InputError, match="must match"):
        losses.EnergyLoss(fixed)(other)
    with pytest.raises(InputError, match="out must be"):
        losses.StructureLoss(fixed)(batch, out=wp.zeros(2, dtype=float, device=device))
    with wp.Tape(), pytest.raises(InputError, match="requires_grad"):
        losses.EnergyLoss(fixed)(batch, out=wp.zeros(3, dtype=float, device=device))
