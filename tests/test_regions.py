"""The residual's connected regions labelled and measured on a Warp device (``kernels.regions``) against
``scipy.ndimage.label`` and float64 NumPy sums, and the device PSNR
(``kernels.losses.clipped_mse``) against ``quality.metrics.psnr``.

A CPU launch runs its threads one after the other, so there ``_unite`` never finds a root moved by
another thread; its retry runs only in the CUDA variants, which need a CUDA device."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from warp_highlights.kernels.losses import clipped_mse
from warp_highlights.kernels.regions import ResidualRegions
from warp_highlights.model.errors import InputError
from warp_highlights.quality.metrics import psnr, psnr_of_mse

THRESHOLD = 0.2


def _reference(target: np.ndarray, image: np.ndarray, threshold: float) -> dict:
    """The regions as the estimation measured them on the host: scipy labels, numpy.bincount sums in float64."""
    residual = target - image
    structure = np.zeros((3, 3, 3), dtype=bool)
    structure[1] = True  # 8-connected within an image, never across images
    labels, count = ndimage.label(residual > np.float32(threshold), structure=structure)
    problem, row, col = np.nonzero(labels)
    label = labels[problem, row, col] - 1
    weight = residual[problem, row, col].astype(np.float64)
    height = target.shape[1]
    x, y = (col + 0.5) / height, (row + 0.5) / height
    mass = np.bincount(label, weights=weight, minlength=count)
    mx = np.bincount(label, weights=weight * x, minlength=count) / mass
    my = np.bincount(label, weights=weight * y, minlength=count) / mass
    dx, dy = x - mx[label], y - my[label]
    covariance = np.stack([np.bincount(label, weights=weight * a * b, minlength=count) / mass
                           for a, b in ((dx, dx), (dx, dy), (dy, dy))], axis=1)
    peak = np.zeros(count)
    np.maximum.at(peak, label, weight)
    by_value = np.lexsort((weight, label))  # grouped by label, ascending residual: each group's last is its peak
    last = by_value[np.flatnonzero(np.r_[np.diff(label[by_value]) != 0, True])] if count else by_value
    flat = (problem * height + row) * target.shape[2] + col
    peak_pixel = np.zeros(count, dtype=np.int64)
    peak_pixel[label[last]] = flat[last]
    region_problem = np.zeros(count, dtype=np.int64)
    region_problem[label] = problem
    return {
        "labels": labels,
        "problem": region_problem,
        "area": np.bincount(label, minlength=count),
        "mass": mass,
        "peak": peak,
        "peak_pixel": peak_pixel,
        "centroid": np.stack([mx, my], axis=1),
        "covariance": covariance,
    }


def _check(target: np.ndarray, image: np.ndarray, device: str, threshold: float = THRESHOLD) -> ResidualRegions:
    regions = ResidualRegions(target.shape, device)
    found = regions.label(wp.array(target, device=device), wp.array(image, device=device), threshold)
    expected = _reference(target, image, threshold)
    assert len(found) == len(expected["area"])
    for name in ("problem", "area", "peak", "peak_pixel"):
        np.testing.assert_array_equal(getattr(found, name), expected[name], err_msg=name)
    exact = wp.get_device(device).is_cpu  # the CPU sums in pixel order, as bincount does; CUDA's atomics in any order
    for name in ("mass", "centroid", "covariance"):
        if exact:
            np.testing.assert_array_equal(getattr(found, name), expected[name], err_msg=name)
        else:
            np.testing.assert_allclose(getattr(found, name), expected[name], rtol=1e-12, atol=1e-15, err_msg=name)
    # every pixel's region number, read back through regions_at
    flat = np.arange(target.size)
    np.testing.assert_array_equal(regions.regions_at(flat), expected["labels"].reshape(-1) - 1)
    return regions


def _random_case(rng, problems: int, height: int, width: int, density: float) -> tuple[np.ndarray, np.ndarray]:
    target = (rng.random((problems, height, width)) < density) * rng.uniform(0.25, 2.0, (problems, height, width))
    image = rng.uniform(0.0, 0.1, (problems, height, width)) * (rng.random((problems, height, width)) < 0.5)
    return target.astype(np.float32), image.astype(np.float32)


@pytest.mark.parametrize("density", [0.05, 0.3, 0.45, 0.6, 0.95])
def test_random_regions_match_scipy_and_numpy(device, density):
    """Sparse specks, percolating clusters and one big region, over several images."""
    rng = np.random.default_rng(int(density * 100))
    _check(*_random_case(rng, 4, 37, 53, density), device)


@settings(max_examples=30, deadline=None)
@given(problems=st.integers(1, 3), height=st.integers(1, 12), width=st.integers(1, 12), density=st.floats(0.0, 1.0),
       seed=st.integers(0, 2**31))
def test_any_shape_matches_scipy(problems, height, width, density, seed):
    """Single rows and columns, empty and full images (CPU: exact)."""
    _check(*_random_case(np.random.default_rng(seed), problems, height, width, density), "cpu")


def test_snakes_and_diagonals_join(device):
    """A serpentine path (one region whose union-find joins from both ends) and a checkerboard (8-connected: one
    region)."""
    height, width = 41, 61
    snake = np.zeros((height, width), np.float32)
    snake[::2, :] = 1.0  # full rows 0, 2, 4, ... joined at alternate ends
    snake[1::4, -1] = 1.0
    snake[3::4, 0] = 1.0
    checker = ((np.add.outer(np.arange(height), np.arange(width)) % 2) == 0).astype(np.float32)
    target = np.stack([snake, checker, snake[::-1, ::-1].copy()])
    regions = _check(target, np.zeros_like(target), device)
    assert len(regions._ordered) == 3, "each image is one region"


def test_regions_never_cross_images(device):
    """The last row of one image and the first row of the next are neighbours in memory, not in the image."""
    target = np.zeros((3, 4, 5), np.float32)
    target[0, -1, :] = 1.0
    target[1, 0, :] = 1.0
    target[1, :, -1] = 1.0
    target[2, 0, 0] = 1.0
    target[1, -1, -1] = 1.0
    found = _check(target, np.zeros_like(target), device)
    assert found.regions_at(np.array([19, 20, 40])).tolist() == [0, 1, 2]


def test_more_regions_than_the_first_list_holds(device):
    """Isolated pixels two apart: 2,500 regions, beyond the 1,024 roots listed at first."""
    target = np.zeros((1, 100, 100), np.float32)
    target[0, ::2, ::2] = np.linspace(0.5, 1.5, 2500, dtype=np.float32).reshape(50, 50)
    _check(target, np.zeros_like(target), device)


def test_nothing_above_the_threshold(device):
    target = np.full((2, 8, 9), 0.1, np.float32)
    found = ResidualRegions(target.shape, device).label(wp.array(target, device=device),
                                                        wp.zeros_like(wp.array(target, device=device)), THRESHOLD)
    assert len(found) == 0 and found.centroid.shape == (0, 2) and found.covariance.shape == (0, 3)


def test_bad_arguments_are_refused():
    regions = ResidualRegions((1, 4, 4), "cpu")
    with pytest.raises(InputError, match="must be a float32"):
        regions.label(wp.zeros((1, 4, 5), dtype=float, device="cpu"), wp.zeros((1, 4, 4), dtype=float, device="cpu"),
                      THRESHOLD)
    with pytest.raises(InputError, match="out of range"):
        regions.regions_at(np.array([16]))
    with pytest.raises(InputError, match="shape"):
        ResidualRegions((4, 4), "cpu")


def test_clipped_mse_gives_the_host_psnr(device):
    rng = np.random.default_rng(3)
    target = rng.uniform(-0.2, 1.3, (3, 17, 23)).astype(np.float32)
    image = (target + rng.normal(0, 0.05, target.shape)).astype(np.float32)
    image[2] = target[2]  # identical: the cap
    found = psnr_of_mse(clipped_mse(wp.array(image, device=device), wp.array(target, device=device)))
    np.testing.assert_allclose(found, psnr(image, target), rtol=1e-12)
    assert found[2] == 100.0
