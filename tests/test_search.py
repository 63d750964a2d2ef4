"""Retargeting's coarse start (kernels/search.py): the blur, the offsets, the headings and the search,
against float64 NumPy references; and a far move that the rigid phase finds only with it."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warp_highlights.fit.retargeting import retarget
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.kernels.search import (
    blurred,
    candidate_offsets,
    component_members,
    image_headings,
    searched_translations,
)
from warp_highlights.model.config import RetargetSettings
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams


def _blur_reference(images: np.ndarray, sigma: float) -> np.ndarray:
    radius = max(1, int(np.ceil(3 * sigma)))
    taps = np.exp(-0.5 * np.arange(-radius, radius + 1) ** 2 / sigma**2)
    taps /= taps.sum()
    out = np.zeros_like(images, dtype=np.float64)
    padded = np.pad(images.astype(np.float64), ((0, 0), (0, 0), (radius, radius)))
    for k, tap in enumerate(taps):
        out += tap * padded[:, :, k:k + images.shape[2]]
    across, out = out, np.zeros_like(out)
    padded = np.pad(across, ((0, 0), (radius, radius), (0, 0)))
    for k, tap in enumerate(taps):
        out += tap * padded[:, k:k + images.shape[1], :]
    return out


def test_blur_matches_a_float64_reference(device):
    images = np.random.default_rng(1).random((2, 17, 23)).astype(np.float32)
    got = blurred(wp.array(images, dtype=float, device=device), 1.7).numpy()
    np.testing.assert_allclose(got, _blur_reference(images, 1.7), rtol=1e-5, atol=1e-6)


def test_component_members_list_each_components_active_slots():
    labels = np.array([[2, 0, 2, 1, 0], [0, 0, 0, 0, 0]])
    active = np.array([[True, True, True, False, True], [False, False, False, False, False]])
    members, starts, counts = component_members(labels, active)
    np.testing.assert_array_equal(counts, [[2, 0, 2, 0, 0], [0, 0, 0, 0, 0]])
    for c in range(5):
        slots = members[0, starts[0, c]:starts[0, c] + counts[0, c]]
        assert sorted(slots.tolist()) == sorted(np.flatnonzero(active[0] & (labels[0] == c)).tolist())


def test_offsets_fill_the_disc_nearest_first():
    offsets = candidate_offsets(0.1, 0.02)
    lengths = np.hypot(offsets[:, 0], offsets[:, 1])
    assert np.all(offsets[0] == 0) and np.all(np.diff(lengths) >= -1e-7) and lengths.max() <= 0.1 + 1e-6
    assert len(offsets) == sum(1 for i in range(-5, 6) for j in range(-5, 6) if i * i + j * j <= 25)


def test_headings_follow_the_half_vector_on_the_image():
    """A light moving to the right (+x) moves a convex highlight to the right; up (+y) moves it up the
    image (-y in rows); along the view axis nothing changes."""
    directions = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, np.sqrt(0.75)], [0.0, 0.5, np.sqrt(0.75)]])
    headings = image_headings(directions, np.array([[0, 1], [0, 2], [1, 0], [0, 0]]))
    np.testing.assert_allclose(headings, [[1, 0], [0, -1], [-1, 0], [0, 0]], atol=1e-6)
    rng = np.random.default_rng(3)
    lights = rng.normal(size=(6, 3))
    lights[:, 2] = np.abs(lights[:, 2])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    edges = np.array([[a, b] for a in range(6) for b in range(6) if a != b])
    half = lights + [0, 0, 1]
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    change = half[edges[:, 1]] - half[edges[:, 0]]
    expected = np.stack([change[:, 0], -change[:, 1]], axis=1)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(image_headings(lights, edges), expected, atol=1e-6)


def _search_reference(params: GaussianParams, labels, targets, offsets, headings, prior, side, gain, margin,
                      exclusion):
    """float64 reference of search_translations (nearest-pixel samples of the blurred targets)."""
    problems, capacity = params.active.shape
    height = targets.shape[1]
    motion = np.zeros((problems, capacity, 3))

    def sample(b, point):
        col, row = int(np.floor(point[0] * height)), int(np.floor(point[1] * height))
        inside = 0 <= row < targets.shape[1] and 0 <= col < targets.shape[2]
        return targets[b, row, col] if inside else 0.0

    def weight(offset, heading):
        if np.linalg.norm(heading) > 0:
            along = offset @ heading
            return np.exp(-0.5 * (along**2 / prior**2 + (offset @ offset - along**2) / side**2))
        return np.exp(-0.5 * (offset @ offset) / prior**2)

    for b in range(problems):
        for c in range(capacity):
            members = [p for p in range(capacity) if params.active[b, p] and labels[b, p] == c]
            if not members:
                continue
            peaks = [params.weight[b, p] * params.amplitude[b, p] ** 2 for p in members]

            def score(offset, b=b, members=members, peaks=peaks):
                return sum(k * sample(b, params.mean[b, p] + offset) for k, p in zip(peaks, members))

            scores = np.array([score(o) * weight(o, headings[b]) for o in offsets])
            best = int(np.argmax(scores))
            if scores[best] <= 0 or scores[best] <= gain * score(np.zeros(2)):
                continue
            far = np.linalg.norm(offsets - offsets[best], axis=1) > exclusion
            rival = scores[far].max() if far.any() else 0.0
            if scores[best] > margin * rival:
                motion[b, c, :2] = offsets[best]
    return motion


def test_search_matches_a_float64_reference(device):
    """Three edges: a component whose highlight moved 8 px (found), one already in place (kept), and one
    whose target shows two equal highlights either side (ambiguous: kept)."""
    height, width = 40, 72
    sets = GaussianParams.from_sets(
        [{"amplitude": [1.0, 0.8], "mean": [[0.6, 0.5], [0.66, 0.52]], "sigma": [[0.03, 0.03], [0.02, 0.03]],
          "theta": [0.0, 0.4]}] * 3, capacity=3)
    labels = np.zeros((3, 3), np.int32)
    raster = Rasterizer(height, width, device="cpu")

    def drawn(shift):
        moved = sets.take([0])
        moved.mean = moved.mean + np.array(shift)
        return raster.render(GaussianBatch.from_numpy(moved, device="cpu", requires_grad=False)).numpy()[0]

    targets = np.stack([drawn([8 / height, 0.0]), drawn([0.0, 0.0]),
                        drawn([-0.3, 0.0]) + drawn([0.3, 0.0])]).astype(np.float32)
    step, radius = 2.0 / height, 0.35
    headings = np.array([[1.0, 0.0], [0.0, 0.0], [1.0, 0.0]], np.float32)
    motion = wp.zeros((3, 3), dtype=wp.vec3, device=device)
    batch = GaussianBatch.from_numpy(sets, device=device, requires_grad=False)
    targets_up = wp.array(targets, dtype=float, device=device)
    searched_translations(batch, sets, labels, blurred(targets_up, step * height), motion, radius=radius,
                          step=step, prior_width=0.5, gain=4.0, margin=1.5, exclusion=0.1, headings=headings,
                          side_width=0.05)
    smooth = _blur_reference(targets, step * height)
    expected = _search_reference(sets, labels, smooth, candidate_offsets(radius, step).astype(np.float64),
                                 headings.astype(np.float64), 0.5, 0.05, 4.0, 1.5, 0.1)
    got = motion.numpy()
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert got[0, 0, 0] == pytest.approx(8 / height, abs=step) and not got[1].any() and not got[2].any()


def test_a_highlight_further_than_its_size_is_followed_only_with_the_search():
    """Target = the source moved 81 rpx: the rigid phase from the source finds nothing to follow; from the
    searched start it lands on the target."""
    params = GaussianParams.from_sets([{"amplitude": [1.2, 1.0], "mean": [[0.5, 0.45], [0.53, 0.46]],
                                        "sigma": [[0.02, 0.015], [0.015, 0.015]], "theta": [0.3, 0.0]}], capacity=3)
    raster = Rasterizer(54, 96, device="cpu")
    target_params = params.copy()
    target_params.mean[0, :2] += np.array([80 / 270, -10 / 270])
    targets = np.stack([np.zeros((54, 96), np.float32),
                        raster.render(GaussianBatch.from_numpy(target_params, device="cpu",
                                                               requires_grad=False)).numpy()[0]])
    two = params.take([0, 0])
    edges = np.array([[0, 1]])
    without = retarget(two, targets, edges, settings=RetargetSettings(search_radius=0.0, iterations=0), device="cpu")
    found = retarget(two, targets, edges, settings=RetargetSettings(iterations=0), device="cpu")
    assert np.abs(without.params.mean[0, :2] - target_params.mean[0, :2]).max() > 20 / 270
    np.testing.assert_allclose(found.params.mean[0, :2], target_params.mean[0, :2], atol=1.0 / 270)
    assert found.rigid_loss[0] < 0.05 * found.source_loss[0]
