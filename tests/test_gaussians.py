"""GaussianParams / GaussianBatch: conversion, slot management, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from gaussian_cases import random_params
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams


def test_numpy_round_trip_keeps_active_slots_and_zeroes_free_ones(device):
    params = random_params(np.random.default_rng(0), 3, 5, 20, 30)
    back = GaussianBatch.from_numpy(params, device=device).numpy()
    active = params.active
    np.testing.assert_array_equal(back.active, active)
    for name in ("amplitude", "mean", "sigma", "theta", "weight"):
        np.testing.assert_allclose(getattr(back, name)[active], getattr(params, name)[active], rtol=1e-6, atol=1e-7)
    assert np.all(back.amplitude[~active] == 0)
    assert np.all(back.weight[~active] == 1)


def test_from_sets_packs_slots_in_order():
    params = GaussianParams.from_sets(
        [
            {"amplitude": [1.0, 0.5], "mean": [[0.1, 0.2], [0.3, 0.4]], "sigma": [[0.01, 0.02]] * 2,
             "theta": [0.0, 1.0]},
            {"amplitude": [0.7], "mean": [[0.5, 0.5]], "sigma": [[0.03, 0.03]], "theta": [0.2], "weight": [0.5]},
        ],
        capacity=4,
    )
    assert params.capacity == 4
    np.testing.assert_array_equal(params.counts, [2, 1])
    assert params.weight[1, 0] == 0.5 and params.weight[0, 1] == 1.0
    with pytest.raises(InputError, match="capacity is 1"):
        GaussianParams.from_sets([{"amplitude": [1, 2], "mean": np.zeros((2, 2)), "sigma": np.ones((2, 2)),
                                   "theta": [0, 0]}], capacity=1)


def test_add_fills_lowest_free_slots_per_problem(device):
    params = GaussianParams.empty(3, 4)
    params.active[0, [0, 2]] = True
    params.amplitude[0, [0, 2]] = 1.0
    batch = GaussianBatch.from_numpy(params, device=device)
    problems = np.array([0, 2, 0, 2, 2])
    slots = batch.add(problems, amplitude=np.arange(5) + 1.0, mean=np.ones((5, 2)) * 0.5, sigma=np.full((5, 2), 0.01),
                      theta=np.zeros(5))
    np.testing.assert_array_equal(slots, [1, 0, 3, 1, 2])
    after = batch.numpy()
    np.testing.assert_array_equal(after.counts, [4, 0, 3])
    np.testing.assert_allclose(after.amplitude[0], [1, 1, 1, 3])
    np.testing.assert_allclose(after.amplitude[2], [2, 4, 5, 0])


def test_add_beyond_capacity_changes_nothing(device):
    batch = GaussianBatch.from_numpy(GaussianParams.empty(2, 2), device=device)
    with pytest.raises(InputError, match="problem 1 has 2 free slots of 2 but 3"):
        batch.add([1, 1, 1], amplitude=np.ones(3), mean=np.zeros((3, 2)), sigma=np.ones((3, 2)), theta=np.zeros(3))
    assert batch.counts().sum() == 0


def test_remove_frees_slots(device):
    params = random_params(np.random.default_rng(1), 2, 6, 20, 20, inactive=0.0)
    batch = GaussianBatch.from_numpy(params, device=device)
    mask = np.zeros((2, 6), dtype=bool)
    mask[0, [1, 4]] = True
    assert batch.remove(mask) == 2
    after = batch.numpy()
    assert not after.active[0, 1] and not after.active[0, 4] and after.active[1].all()
    assert after.amplitude[0, 1] == 0
    with pytest.raises(InputError, match="shape"):
        batch.remove(np.zeros((6, 2), dtype=bool))


def test_shape_and_value_errors():
    with pytest.raises(InputError, match="mean must have shape"):
        GaussianParams(amplitude=np.zeros((1, 2)), mean=np.zeros((1, 3)), sigma=np.zeros((1, 2, 2)),
                       theta=np.zeros((1, 2)), weight=np.ones((1, 2)), active=np.ones((1, 2)))
    with pytest.raises(InputError, match="non-finite"):
        GaussianParams(amplitude=np.array([[np.nan]]), mean=np.zeros((1, 1, 2)), sigma=np.zeros((1, 1, 2)),
                       theta=np.zeros((1, 1)), weight=np.ones((1, 1)), active=np.ones((1, 1)))
    with pytest.raises(InputError, match="at least one"):
        GaussianBatch(0, 4, device="cpu")
    batch = GaussianBatch(2, 3, device="cpu")
    with pytest.raises(InputError, match="cannot assign"):
        batch.assign(GaussianParams.empty(3, 3))
    with pytest.raises(InputError, match="no gradients"):
        GaussianBatch(1, 1, device="cpu", requires_grad=False).gradients()


def test_clone_is_independent(device):
    params = random_params(np.random.default_rng(2), 2, 3, 10, 10)
    batch = GaussianBatch.from_numpy(params, device=device)
    copy = batch.clone(requires_grad=False)
    batch.remove(np.ones((2, 3), dtype=bool))
    np.testing.assert_array_equal(copy.numpy().active, params.active)
    assert not copy.requires_grad


def test_a_diverged_slot_can_be_found_and_removed(device):
    params = random_params(np.random.default_rng(3), 2, 4, 20, 20, inactive=0.0)
    batch = GaussianBatch.from_numpy(params, device=device)
    sigma = batch.sigma.numpy()
    sigma[1, 2] = (np.nan, np.inf)
    batch.sigma.assign(sigma)
    copy = batch.numpy()  # shows the broken slot rather than refusing
    expected = np.ones((2, 4), dtype=bool)
    expected[1, 2] = False
    np.testing.assert_array_equal(copy.finite, expected)
    assert batch.remove(~copy.finite) == 1
    after = batch.numpy()
    assert np.all(after.finite) and not after.active[1, 2]
    assert np.all(batch.sigma.numpy()[1, 2] == 0)  # nothing non-finite left in a free slot


def test_host_writes_bump_the_generation_of_exactly_the_new_slots(device):
    batch = GaussianBatch.from_numpy(random_params(np.random.default_rng(4), 2, 3, 20, 20, inactive=0.0), device=device)
    before = batch.generation.numpy().copy()
    batch.remove(np.array([[False, True, False], [False, False, False]]))
    np.testing.assert_array_equal(batch.generation.numpy(), before)
    batch.add([0], amplitude=[1.0], mean=[[0.5, 0.5]], sigma=[[0.01, 0.01]], theta=[0.0])
    np.testing.assert_array_equal(batch.generation.numpy() - before, [[0, 1, 0], [0, 0, 0]])


def test_where_takes_the_masked_slots_from_one_batch_and_the_rest_from_the_other():
    first, second = GaussianParams.empty(2, 3), GaussianParams.empty(2, 3)
    first.amplitude[:] = 1.0
    first.mean[:] = 0.25
    first.active[:] = True
    mask = np.array([[True, False, True], [False, False, True]])
    joined = first.where(mask, second)
    np.testing.assert_array_equal(joined.amplitude, np.where(mask, 1.0, 0.0))
    np.testing.assert_array_equal(joined.mean, np.where(mask[..., None], 0.25, 0.0) * np.ones((1, 1, 2)))
    np.testing.assert_array_equal(joined.active, mask)
    np.testing.assert_array_equal(joined.weight, np.ones((2, 3)))
