"""The Gaussian rasterizer against float64 NumPy: forward, culling, and the backward pass."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import reference
from gaussian_cases import central_differences, inside_params, random_params
from warp_highlights.kernels.raster import (
    LAUNCH_PIXELS,
    Rasterizer,
    problems_per_launch,
)
from warp_highlights.model.config import RasterSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

PARAMETERS = ("amplitude", "mean", "sigma", "theta", "weight")


def _render_and_backward(batch, height, width, device):
    """Render on a tape and backpropagate an all-ones image gradient; returns the image."""
    tape = wp.Tape()
    with tape:
        image = Rasterizer(height, width, device=device).render(batch)
    tape.backward(grads={image: wp.ones(image.shape, dtype=float, device=device)})
    return image.numpy()


def _render_without(params, problem, slot, height, width, device):
    """NumPy reference image of ``params`` with one slot freed."""
    without = params.copy()
    without.active[problem, slot] = False
    return _render(without, height, width, device)[0]


def _render(params, height, width, device, **kwargs):
    batch = GaussianBatch.from_numpy(params, device=device)
    return Rasterizer(height, width, device=device, **kwargs).render(batch).numpy(), batch.numpy()


@pytest.mark.parametrize("size", [(1, 1), (7, 5), (37, 61), (64, 48), (33, 100)])
def test_forward_matches_numpy_on_random_batches(device, size):
    height, width = size
    params = random_params(np.random.default_rng(height * 7 + width), 4, 9, height, width,
                           sigma_px=(0.05, 3 * max(size)))
    image, stored = _render(params, height, width, device)
    expected = reference.render(stored, height, width)
    assert image.shape == (4, height, width) and image.dtype == np.float32
    np.testing.assert_allclose(image, expected, rtol=2e-5, atol=2e-5 * max(1.0, expected.max()))


@pytest.mark.parametrize("tile_size", [4, 8, 16, 32])
def test_culling_changes_nothing(device, tile_size):
    params = random_params(np.random.default_rng(tile_size), 3, 16, 45, 70, sigma_px=(0.2, 25))
    settings = RasterSettings(tile_size=tile_size)
    culled, _ = _render(params, 45, 70, device, settings=settings)
    everything, _ = _render(params, 45, 70, device, settings=settings, culling=False)
    np.testing.assert_array_equal(culled, everything)


@pytest.mark.parametrize("tile_size", [8, 16])
def test_drawn_only_redraws_the_reached_tiles_and_keeps_the_rest(device, tile_size):
    """``render(drawn_only=True)``: every pixel of a tile some Gaussian reaches as a full render draws it
    (so every pixel a Gaussian draws), every other pixel as it was; the launch covers more listed
    tiles than one sweep holds."""
    import warp_highlights.kernels.raster as raster_module

    height, width = 45, 70
    params = random_params(np.random.default_rng(tile_size + 1), 5, 6, height, width, sigma_px=(0.3, 6), inactive=0.5)
    settings = RasterSettings(tile_size=tile_size)
    batch = GaussianBatch.from_numpy(params, device=device)
    raster = Rasterizer(height, width, settings=settings, device=device)
    full = raster.render(batch).numpy()
    counts = raster.tile_counts.numpy().reshape(5, raster.tiles_y, raster.tiles_x)
    reached = np.repeat(np.repeat(counts > 0, tile_size, axis=1), tile_size, axis=2)[:, :height, :width]
    assert reached.any() and not reached.all()
    stale = np.random.default_rng(0).uniform(5.0, 6.0, full.shape).astype(np.float32)
    sweep = raster_module.DRAWN_TILES_PER_SWEEP
    for per_sweep in (sweep, 3):  # one sweep, and several sweeps of 3 tiles
        raster_module.DRAWN_TILES_PER_SWEEP = per_sweep
        try:
            out = wp.array(stale, device=device, requires_grad=True)
            drawn = raster.render(batch, out=out, drawn_only=True).numpy()
        finally:
            raster_module.DRAWN_TILES_PER_SWEEP = sweep
        np.testing.assert_array_equal(drawn[reached], full[reached])
        np.testing.assert_array_equal(drawn[~reached], stale[~reached])
        assert (full[~reached] == 0).all()


def test_the_drawn_tiles_kernel_sweeps_its_list_on_any_device(device):
    """``rasterize_drawn_tiles`` launched as the CUDA path launches it, on this device too: a list of
    tiles in any order, fewer threads than listed tiles (several sweeps), a count below the list's length."""
    from warp_highlights.kernels.raster import rasterize_drawn_tiles

    height, width = 45, 70
    params = random_params(np.random.default_rng(4), 3, 6, height, width, sigma_px=(0.3, 6), inactive=0.3)
    settings = RasterSettings(tile_size=8)
    batch = GaussianBatch.from_numpy(params, device=device)
    raster = Rasterizer(height, width, settings=settings, device=device)
    full = raster.render(batch).numpy()
    counts = raster.tile_counts.numpy()
    listed = np.flatnonzero(counts.reshape(-1) > 0)[::-1].astype(np.int32)  # reversed: any order
    drawn = listed[:-2]  # the count leaves the last two out
    stale = np.full(full.shape, 9.0, np.float32)
    out = wp.array(stale, device=device)
    launched = 3 * 64  # three tiles of 8 x 8 a sweep
    wp.launch(rasterize_drawn_tiles, dim=launched,
              inputs=[raster.frames, batch.mean, raster.scales, raster.tile_lists, raster.tile_counts,
                      wp.array(listed, dtype=wp.int32, device=device),
                      wp.array([len(drawn)], dtype=wp.int32, device=device), 3, raster.tiles_x, settings.cutoff**2,
                      settings.cutoff_level, launched],
              outputs=[out], device=device)
    tiles = np.zeros(counts.size, bool)
    tiles[drawn] = True
    per_pixel = np.repeat(np.repeat(tiles.reshape(3, raster.tiles_y, raster.tiles_x), 8, axis=1), 8,
                          axis=2)[:, :height, :width]
    np.testing.assert_array_equal(out.numpy()[per_pixel], full[per_pixel])
    np.testing.assert_array_equal(out.numpy()[~per_pixel], stale[~per_pixel])


def test_truncation_error_is_bounded_by_the_documented_cutoff_level(device):
    params = random_params(np.random.default_rng(3), 2, 12, 40, 60, sigma_px=(0.5, 20))
    settings = RasterSettings(cutoff=3.0)
    image, stored = _render(params, 40, 60, device, settings=settings)
    full = reference.render(stored, 40, 60, settings, truncate=False)
    bound = (stored.weight * stored.amplitude**2 * stored.active).sum(axis=1) * settings.cutoff_level
    error = np.abs(image - full).max(axis=(1, 2))
    assert np.all(error <= bound * (1 + 1e-3) + 1e-6)
    assert np.all(error > 0.1 * bound)  # the cut-off really applies


def test_truncated_gaussian_is_continuous_and_exact_at_the_peak(device):
    params = GaussianParams.from_sets([{"amplitude": [1.5], "mean": [[5.5 / 11, 5.5 / 11]], "sigma": [[2 / 11, 1 / 11]],
                                        "theta": [0.3]}])
    image, _ = _render(params, 11, 11, device)
    assert image[0, 5, 5] == pytest.approx(2.25, rel=1e-6)
    stored = GaussianBatch.from_numpy(params, device=device).numpy()
    x, y = reference.pixel_grid(11, 11)
    d2 = reference.distance2(stored, 0, 0, x, y, RasterSettings().sigma_eps)
    near_edge = np.abs(np.sqrt(d2) - 4.0) < 0.3
    assert near_edge.any() and image[0][near_edge].max() < 2.25 * 3 * np.exp(-0.5 * 3.7**2)


def test_zero_weights_and_off_image_gaussians_draw_nothing(device):
    params = random_params(np.random.default_rng(4), 1, 6, 30, 30, inactive=0.0)
    params.weight[0, :] = 0.0
    params.weight[0, 1] = 1.0
    params.mean[0, 1] = (5.0, 5.0)  # far outside
    params.sigma[0, 1] = (0.01, 0.01)
    image, _ = _render(params, 30, 30, device)
    assert np.all(image == 0)


def test_free_slot_with_leftover_values_draws_nothing_and_gets_no_gradient(device):
    params = inside_params(np.random.default_rng(16), 1, 3, 20, 20)
    batch = GaussianBatch.from_numpy(params, device=device)
    active = batch.active.numpy()
    active[0, 1] = 0  # free the slot on the device without clearing its parameters
    batch.active.assign(active)
    image = _render_and_backward(batch, 20, 20, device)
    assert batch.numpy().amplitude[0, 1] != 0
    np.testing.assert_allclose(image, _render_without(params, 0, 1, 20, 20, device), atol=1e-6)
    assert all(np.all(g[0, 1] == 0) for g in batch.gradients().values())


def test_inside_a_tape_an_output_without_gradient_is_an_error(device):
    batch = GaussianBatch.from_numpy(inside_params(np.random.default_rng(17), 1, 2, 10, 10), device=device)
    raster = Rasterizer(10, 10, device=device)
    with wp.Tape(), pytest.raises(InputError, match="requires_grad"):
        raster.render(batch, out=wp.zeros((1, 10, 10), dtype=float, device=device))
    raster.render(batch, out=wp.zeros((1, 10, 10), dtype=float, device=device))  # fine outside a tape


def test_non_finite_gaussian_draws_nothing_and_gets_no_gradient(device):
    params = inside_params(np.random.default_rng(5), 1, 3, 20, 20)
    batch = GaussianBatch.from_numpy(params, device=device)
    good = Rasterizer(20, 20, device=device).render(batch).numpy()
    sigma = batch.sigma.numpy()
    sigma[0, 1] = (np.nan, 0.1)
    batch.sigma.assign(sigma)
    image = _render_and_backward(batch, 20, 20, device)
    assert np.all(np.isfinite(image)) and not np.array_equal(image, good)
    np.testing.assert_allclose(image, _render_without(params, 0, 1, 20, 20, device), atol=1e-6)
    gradients = batch.gradients()
    assert all(np.all(np.isfinite(g)) for g in gradients.values())
    assert gradients["amplitude"][0, 1] == 0


@pytest.mark.parametrize("lanes", [None, 1, 3, 32])
def test_backward_matches_central_differences(device, lanes):
    rng = np.random.default_rng(11)
    height, width = 23, 31
    params = inside_params(rng, 2, 4, height, width)
    params.active[1, 2] = False
    batch = GaussianBatch.from_numpy(params, device=device)
    stored = batch.numpy()
    incoming = rng.normal(size=(2, height, width))
    raster = Rasterizer(height, width, device=device, backward_lanes=lanes)
    tape = wp.Tape()
    with tape:
        image = raster.render(batch)
    tape.backward(grads={image: wp.array(incoming.astype(np.float32), device=device)})
    got = batch.gradients()
    expected = central_differences(lambda p: np.sum(reference.render(p, height, width) * incoming), stored)
    for name in PARAMETERS:
        scale = np.abs(expected[name]).max()
        np.testing.assert_allclose(got[name], expected[name], atol=2e-4 * scale, err_msg=name)
    assert got["amplitude"][1, 2] == 0 and np.all(got["mean"][1, 2] == 0)


def test_backward_with_tiny_huge_and_partly_outside_gaussians(device):
    rng = np.random.default_rng(12)
    params = random_params(rng, 1, 8, 19, 27, sigma_px=(0.3, 30), inactive=0.0)
    params.amplitude[:] = rng.uniform(0.5, 1.2, params.amplitude.shape)
    batch = GaussianBatch.from_numpy(params, device=device)
    stored = batch.numpy()
    incoming = rng.normal(size=(1, 19, 27))
    tape = wp.Tape()
    with tape:
        image = Rasterizer(19, 27, device=device).render(batch)
    tape.backward(grads={image: wp.array(incoming.astype(np.float32), device=device)})
    got = batch.gradients()
    expected = central_differences(lambda p: np.sum(reference.render(p, 19, 27) * incoming), stored, step=1e-7)
    for name in PARAMETERS:
        scale = np.abs(expected[name]).max()
        np.testing.assert_allclose(got[name], expected[name], atol=5e-4 * scale + 1e-6, err_msg=name)


def test_gradients_accumulate_like_warp_arrays(device):
    params = inside_params(np.random.default_rng(13), 1, 2, 16, 16)
    batch = GaussianBatch.from_numpy(params, device=device)
    raster = Rasterizer(16, 16, device=device)
    tape = wp.Tape()
    with tape:
        first = raster.render(batch)
        second = raster.render(batch)
    ones = wp.ones(first.shape, dtype=float, device=device)
    tape.backward(grads={first: ones, second: ones})
    twice = batch.gradients()["amplitude"]
    tape.zero()
    assert np.all(batch.gradients()["amplitude"] == 0)
    with wp.Tape() as once:
        image = raster.render(batch)
    once.backward(grads={image: ones})
    np.testing.assert_allclose(twice, 2 * batch.gradients()["amplitude"], rtol=1e-6)


@pytest.mark.parametrize("height", [54, 270, 541])
def test_same_set_has_the_same_integral_at_any_resolution(device, height):
    """Coordinates are normalised by height: the image integral (sum x pixel area) is resolution-free."""
    params = inside_params(np.random.default_rng(14), 1, 3, 270, 480, sigma_px=(10, 25))
    width = round(height * 16 / 9)
    image, stored = _render(params, height, width, device)
    settings = RasterSettings()
    c2, tau = settings.cutoff**2, settings.cutoff_level
    root_det = np.sqrt((stored.sigma[..., 0] ** 2 + settings.sigma_eps)
                       * (stored.sigma[..., 1] ** 2 + settings.sigma_eps))
    # integral of (exp(-d^2/2) - tau) / (1 - tau) over the cut-off ellipse
    integral = stored.weight * stored.amplitude**2 * 2 * np.pi * root_det * (1 - tau - tau * c2 / 2) / (1 - tau)
    assert image.sum() / height**2 == pytest.approx(integral.sum(), rel=2e-3)


@pytest.mark.parametrize("tile_size", [4, 16, 32])
@pytest.mark.parametrize("height,width", [(1, 1), (54, 96), (540, 960), (2160, 3840), (4097, 4095)])
def test_problems_per_launch_is_the_most_images_whose_padded_pixels_index_below_2_31(height, width, tile_size):
    """Brute force over the padded image: k images fit, k + 1 do not."""
    settings = RasterSettings(tile_size=tile_size)
    k = problems_per_launch(height, width, settings)
    padded = len(range(0, height, tile_size)) * tile_size * len(range(0, width, tile_size)) * tile_size
    assert k * padded < LAUNCH_PIXELS <= (k + 1) * padded
    assert Rasterizer(height, width, settings=settings, device="cpu").problems_per_launch == k


def test_render_refuses_one_image_over_a_launch_and_draws_the_most_it_allows(monkeypatch):
    raster = Rasterizer(4096, 4096, device="cpu")  # 127 images per launch
    assert raster.problems_per_launch == 127
    with pytest.raises(InputError, match="128 images of 4096 x 4096 exceed one launch"):
        raster.render(GaussianBatch(128, 1, device="cpu"))
    import warp_highlights.kernels.raster as raster_module

    # three 8x8 images (a 16-pixel tile each) per launch
    monkeypatch.setattr(raster_module, "LAUNCH_PIXELS", 3 * 16 * 16 + 1)
    small = Rasterizer(8, 8, device="cpu")
    assert small.problems_per_launch == 3
    assert small.render(GaussianBatch(3, 1, device="cpu")).shape == (3, 8, 8)
    with pytest.raises(InputError, match="4 images of 8 x 8 exceed one launch"):
        small.render(GaussianBatch(4, 1, device="cpu"))
    huge = Rasterizer(32, 32, device="cpu")  # one image alone past the bound: refused, not drawn
    assert huge.problems_per_launch == 1
    with pytest.raises(InputError, match="1 images of 32 x 32 exceed one launch"):
        huge.render(GaussianBatch(1, 1, device="cpu"))


def test_render_rejects_mismatched_inputs():
    raster = Rasterizer(10, 12, device="cpu")
    batch = GaussianBatch(2, 3, device="cpu")
    with pytest.raises(InputError, match="out must be"):
        raster.render(batch, out=wp.zeros((2, 12, 10), dtype=float, device="cpu"))
    with pytest.raises(InputError, match="at least 1 x 1"):
        Rasterizer(0, 10)
    if wp.is_cuda_available():
        with pytest.raises(InputError, match="batch is on"):
            Rasterizer(10, 12, device="cuda:0").render(batch)


def test_tile_lists_cover_every_pixel_within_the_cutoff(device):
    """Binning against brute force: every Gaussian reaching a pixel of a tile is listed for it."""
    height, width, tile = 50, 70, 8
    params = random_params(np.random.default_rng(15), 2, 10, height, width, sigma_px=(0.3, 15))
    settings = RasterSettings(tile_size=tile)
    batch = GaussianBatch.from_numpy(params, device=device)
    raster = Rasterizer(height, width, settings=settings, device=device)
    raster.render(batch)
    lists, counts = raster.tile_lists.numpy(), raster.tile_counts.numpy()
    stored = batch.numpy()
    x, y = reference.pixel_grid(height, width)
    listed_total = 0
    for b in range(2):
        for n in np.flatnonzero(stored.active[b] & (stored.weight[b] * stored.amplitude[b] ** 2 > 0)):
            inside = reference.distance2(stored, b, n, x, y, settings.sigma_eps) < settings.cutoff**2
            for ty, tx in {(r // tile, c // tile) for r, c in zip(*np.nonzero(inside), strict=True)}:
                t = ty * raster.tiles_x + tx
                assert n in lists[b, t, : counts[b, t]], (b, n, t)
        listed_total += counts[b].sum()
    assert listed_total < 2 * 10 * raster.tile_count / 3  # culling really culls
