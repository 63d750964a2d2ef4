"""Estimation: few Gaussians that fit, the add/prune rounds, and chunked runs equal to one batch."""

from __future__ import annotations

import numpy as np
import pytest

from warp_highlights.fit.estimation import (
    _Estimator,
    estimate,
    gaussian_energy_rpx,
    psnr,
)
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.kernels.segmentation import segment
from warp_highlights.model.config import EstimationSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

QUICK = EstimationSettings(iterations=400, densify_every=50, densify_until=300)


def _render(sets: list[dict], height=54, width=96) -> np.ndarray:
    params = GaussianParams.from_sets(sets)
    return Rasterizer(height, width,
                      device="cpu").render(GaussianBatch.from_numpy(params, device="cpu", requires_grad=False)).numpy()


def test_recovers_known_gaussians_with_few_of_them(device):
    truth = _render(
        [
            {"amplitude": [1.4, 1.1], "mean": [[0.5, 0.4], [1.2, 0.6]], "sigma": [[0.06, 0.03], [0.04, 0.04]],
             "theta": [0.5, 0.0]},
            {"amplitude": [1.6], "mean": [[0.9, 0.5]], "sigma": [[0.08, 0.02]], "theta": [-0.3]},
            {"amplitude": [0.0], "mean": [[0.9, 0.5]], "sigma": [[0.08, 0.02]], "theta": [0.0]},  # no highlight at all
        ]
    )
    result = estimate(truth, settings=QUICK, device=device)
    assert result.counts[2] == 0 and result.psnr[2] == 100.0
    assert np.all(result.counts[:2] <= 4), result.counts
    assert np.all(result.psnr[:2] > 40.0), result.psnr
    assert result.params.finite[result.params.active].all()


def test_fits_the_segmented_donut(small_donut):
    data = ReflectanceField.load(small_donut, progress=False)
    seg = segment(data.images, data.lights.directions, device="cpu")
    result = estimate(seg.specular_luminance, settings=QUICK, device="cpu")
    # measured: 4.0 Gaussians per light, PSNR mean 48.0 dB; the worst light (a grazing highlight
    # broken into many small pieces at this 96x54 size) 29.6 dB, the next 42.4 dB
    assert result.counts.mean() <= 6.0
    assert result.psnr.mean() > 44.0 and result.psnr.min() > 25.0, (result.psnr.mean(), result.psnr.min())
    assert np.percentile(result.psnr, 10) > 38.0
    np.testing.assert_allclose(result.psnr, psnr(_render_params(result.params), seg.specular_luminance.numpy()),
                               atol=1e-4)


def _render_params(params: GaussianParams) -> np.ndarray:
    return Rasterizer(54, 96,
                      device="cpu").render(GaussianBatch.from_numpy(params, device="cpu", requires_grad=False)).numpy()


def test_chunks_on_threads_give_the_same_result_as_one_batch():
    rng = np.random.default_rng(0)
    sets = [{"amplitude": [rng.uniform(0.8, 1.5)], "mean": [rng.uniform(0.2, 0.8, 2)], "sigma": [[0.05, 0.03]],
             "theta": [rng.uniform(0, 3)]} for _ in range(5)]
    target = _render(sets)
    short = EstimationSettings(iterations=60, densify_every=20, densify_until=50)
    one = estimate(target, settings=short, device="cpu", workers=1)
    three = estimate(target, settings=short, device="cpu", workers=3)
    for name in ("amplitude", "mean", "sigma", "theta", "active"):
        np.testing.assert_array_equal(getattr(one.params, name), getattr(three.params, name))
    np.testing.assert_array_equal(one.loss, three.loss)


def test_lights_over_one_launchs_images_are_estimated_in_parts_with_the_same_sets(monkeypatch):
    """A bound of 2 images per launch (a light stage at a large working size) splits 5 lights into 3
    parts on one thread: the same sets bit for bit as one batch, and the progress bar fills once. On
    CUDA the parts run one after the other on the device."""
    import warp as wp

    import warp_highlights.fit.estimation as estimation_module

    rng = np.random.default_rng(5)
    sets = [{"amplitude": [rng.uniform(0.8, 1.5)], "mean": [rng.uniform(0.2, 0.8, 2)], "sigma": [[0.05, 0.03]],
             "theta": [rng.uniform(0, 3)]} for _ in range(5)]
    target = _render(sets)
    short = EstimationSettings(iterations=60, densify_every=20, densify_until=50)
    devices = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
    # on CUDA: the pipeline's device array, sliced
    on = {d: target if d == "cpu" else wp.array(target, dtype=float, device=d) for d in devices}
    whole = {d: estimate(on[d], settings=short, device=d, workers=1) for d in devices}
    monkeypatch.setattr(estimation_module, "problems_per_launch", lambda h, w, raster: 2)
    sizes = []
    original = estimation_module._Estimator.__init__
    monkeypatch.setattr(estimation_module._Estimator, "__init__",
                        lambda self, targets, *a, **k: sizes.append(targets.shape[0]) or original(self, targets, *a,
                                                                                                  **k))
    for device in devices:
        steps, sizes[:] = [], []
        parts = estimate(on[device], settings=short, device=device, workers=1, progress=steps.append)
        assert sizes == [2, 1, 2]
        for name in ("active", "amplitude", "mean", "sigma", "theta"):
            if device == "cpu":
                np.testing.assert_array_equal(getattr(parts.params, name), getattr(whole[device].params, name))
            else:  # the device's atomics may add in another order
                np.testing.assert_allclose(getattr(parts.params, name), getattr(whole[device].params, name), rtol=1e-4,
                                           atol=1e-5)
        assert sum(steps) == pytest.approx(short.iterations)


def test_graph_replay_gives_the_eager_result_bit_for_bit():
    """On CUDA, one iteration captured as a graph and replayed (across the add/prune rounds) against
    the same iterations launched one by one; on the CPU, graphs are refused in one line."""
    import warp as wp

    rng = np.random.default_rng(3)
    sets = [{"amplitude": [rng.uniform(0.8, 1.5)], "mean": [rng.uniform(0.2, 0.8, 2)], "sigma": [[0.05, 0.03]],
             "theta": [rng.uniform(0, 3)]} for _ in range(4)]
    target = _render(sets)
    short = EstimationSettings(iterations=120, densify_every=30, densify_until=100)
    with pytest.raises(InputError, match="CUDA graphs need a CUDA device"):
        estimate(target, settings=short, device="cpu", graphs=True)
    if not wp.is_cuda_available():
        pytest.skip("CUDA graphs need a CUDA device (the CPU refusal above was checked)")
    eager = estimate(target, settings=short, device="cuda:0", graphs=False)
    replayed = estimate(target, settings=short, device="cuda:0", graphs=True)
    for name in ("amplitude", "mean", "sigma", "theta", "active"):
        np.testing.assert_array_equal(getattr(replayed.params, name), getattr(eager.params, name))
    np.testing.assert_array_equal(replayed.loss, eager.loss)


def test_densify_places_a_gaussian_on_a_curved_highlight():
    """The centroid of a ring-arc region lies off the highlight; the new Gaussian must start on it."""
    height, width = 54, 96
    rows, cols = np.mgrid[0:height, 0:width]
    radius = np.hypot(cols - 48.0, rows - 50.0)
    arc = np.where((np.abs(radius - 30.0) < 2.0) & (rows < 50), 1.5, 0.0).astype(np.float32)[None]
    estimator = _Estimator(_device_array(arc), EstimationSettings(), QUICK_RASTER, "cpu")
    estimator._densify(estimator._regions())
    params = estimator.batch.numpy()
    assert params.counts[0] == 1
    col, row = params.mean[0, params.active[0]][0] * height - 0.5
    assert arc[0, round(row), round(col)] > 0, "the new Gaussian starts off the highlight"
    assert params.sigma[0, params.active[0]].max() * height < 3.0


def test_densify_places_a_gaussian_on_a_rendered_one():
    """Pixel centres sit at (col + 0.5) / H: the moments of a rendered Gaussian give back its parameters."""
    truth = GaussianParams.from_sets([{"amplitude": [1.5], "mean": [[0.83, 0.41]], "sigma": [[0.06, 0.035]],
                                       "theta": [0.5]}])
    image = _render([{"amplitude": [1.5], "mean": [[0.83, 0.41]], "sigma": [[0.06, 0.035]], "theta": [0.5]}])
    estimator = _Estimator(_device_array(image), EstimationSettings(residual_threshold=0.01), QUICK_RASTER, "cpu")
    estimator._densify(estimator._regions())
    placed = estimator.batch.numpy()
    slot = np.flatnonzero(placed.active[0])
    assert len(slot) == 1
    np.testing.assert_allclose(placed.mean[0, slot[0]], truth.mean[0, 0], atol=0.2 / 54)
    assert abs(placed.theta[0, slot[0]] - 0.5) < 0.05
    assert placed.amplitude[0, slot[0]] == pytest.approx(np.sqrt(image.max()))


def test_densify_serves_the_largest_regions_first():
    image = np.zeros((1, 54, 96), dtype=np.float32)
    image[0, 5:8, 5:8] = 1.0  # 9 pixels
    image[0, 20:40, 50:70] = 1.0  # 400 pixels
    image[0, 40:45, 10:15] = 1.0  # 25 pixels
    estimator = _Estimator(_device_array(image), EstimationSettings(max_new_per_round=2), QUICK_RASTER, "cpu")
    estimator._densify(estimator._regions())
    placed = estimator.batch.numpy()
    means = placed.mean[0, placed.active[0]] * 54 - 0.5
    assert len(means) == 2
    np.testing.assert_allclose(sorted(means[:, 0]), [12.0, 59.5], atol=0.01)


def test_prune_drops_dim_offscreen_and_nonfinite_gaussians():
    target = np.zeros((1, 54, 96), dtype=np.float32)
    estimator = _Estimator(_device_array(target), EstimationSettings(prune_energy=1.0), QUICK_RASTER, "cpu")
    estimator.batch.add(
        np.zeros(5, dtype=int),
        amplitude=[1.0, 0.01, 1.0, 1.0, 1.0],
        mean=[[0.8, 0.5], [0.8, 0.5], [5.0, 0.5], [0.8, 0.5], [0.8, 0.5]],
        sigma=[[0.05, 0.05]] * 4 + [[0.2, 0.0001]],  # the last: 0.005 px across, between pixel centres
        theta=[0.0] * 5,
    )
    params = estimator.batch.numpy()
    params.amplitude[0, 3] = np.nan
    estimator.batch.assign(params)
    energy = gaussian_energy_rpx(params, QUICK_RASTER.sigma_eps)
    assert energy[0, 0] > 1.0 > energy[0, 1]
    estimator._prune()
    assert estimator.batch.numpy().active[0].tolist()[:5] == [True, False, False, False, False]
    assert estimator.pruned[0] == 4


def test_bad_targets():
    with pytest.raises(InputError, match="shape"):
        estimate(np.zeros((3, 4), dtype=np.float32), device="cpu")
    bad = np.zeros((1, 8, 8), dtype=np.float32)
    bad[0, 2, 2] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        estimate(bad, device="cpu")


def _device_array(values):
    import warp as wp

    return wp.array(values, dtype=float, device="cpu")


from warp_highlights.model.config import RasterSettings

QUICK_RASTER = RasterSettings()
