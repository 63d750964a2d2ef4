"""Motion coherence (``fit.coherence``): against a per-slot float64 reference; a glide scores about 1 and random hops
about 0; too few edges or a slot that barely moves give no verdict; ``decide_moving`` holds back the incoherent."""

import numpy as np
import pytest

from conftest import centred_blob_sets
from warp_highlights.fit.coherence import motion_coherence
from warp_highlights.fit.lost import expected_motion
from warp_highlights.fit.moving import decide_moving
from warp_highlights.kernels.search import half_vector_changes
from warp_highlights.model.config import RasterSettings, ResidualSettings
from warp_highlights.model.gaussians import GaussianParams


def _dome(count: int, rng) -> np.ndarray:
    elevation = rng.uniform(0.3, 1.4, count)
    azimuth = rng.uniform(0, 2 * np.pi, count)
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], 1)


def _neighbours(directions: np.ndarray, each: int) -> np.ndarray:
    """(n * each, 2) directed edges from every light to its ``each`` nearest others."""
    closest = np.argsort(-(directions @ directions.T), axis=1)[:, 1:each + 1]
    return np.array([(i, int(j)) for i in range(len(directions)) for j in closest[i]], dtype=np.int64)


def _sets(count: int, capacity: int, rng) -> GaussianParams:
    sets = GaussianParams.empty(count, capacity)
    sets.active[:] = True
    sets.amplitude[:] = 1.0
    sets.mean[:] = rng.uniform(0.3, 0.7, (count, capacity, 2))
    sets.sigma[:] = 0.01
    return sets


def _reference(sources, retargeted, found, edges, directions, motion) -> np.ndarray:
    """Per light and slot in float64, one at a time: the adjusted share explained, NaN where undecided."""
    change = half_vector_changes(directions, edges)
    out = np.full(motion.shape[:2], np.nan)
    for light in range(motion.shape[0]):
        for slot in range(motion.shape[1]):
            rows = [e for e in range(len(edges)) if edges[e, 0] == light and found[e, slot]]
            if len(rows) < 3:
                continue
            moved = np.array([retargeted.mean[e, slot] - sources.mean[e, slot] for e in rows])
            predicted = np.array([motion[light, slot] @ change[e] for e in rows])
            size = np.mean([np.sqrt(sources.sigma[e, slot, 0] * sources.sigma[e, slot, 1]) for e in rows])
            total = float(np.sum(moved**2))
            if total / len(rows) < (0.25 * size) ** 2:
                continue
            residual = float(np.sum((moved - predicted) ** 2))
            out[light, slot] = 1.0 - (residual / (2 * len(rows) - 4)) / (total / (2 * len(rows)))
    return out


def _fitted(sources, retargeted, found, edges, directions):
    motion = expected_motion(sources, retargeted, found, edges, directions, ridge=0.25)
    return motion, motion_coherence(sources, retargeted, found, edges, directions, motion)


def test_coherence_matches_a_per_slot_float64_reference():
    rng = np.random.default_rng(11)
    directions = _dome(9, rng)
    edges = _neighbours(directions, 5)
    sources = _sets(9, 4, rng).take(edges[:, 0])
    retargeted = sources.copy()
    retargeted.mean += rng.normal(0, 0.04, retargeted.mean.shape)
    retargeted.mean[:, 3] = sources.mean[:, 3] + 1e-4  # slot 3 barely moves: no verdict
    found = rng.uniform(size=sources.active.shape) > 0.2
    found[edges[:, 0] == 4, 2] = False  # found nowhere: no verdict
    motion, coherence = _fitted(sources, retargeted, found, edges, directions)
    reference = _reference(sources, retargeted, found, edges, directions, motion)
    np.testing.assert_array_equal(np.isnan(coherence), np.isnan(reference))
    np.testing.assert_allclose(coherence[~np.isnan(reference)], reference[~np.isnan(reference)], rtol=1e-9, atol=1e-12)
    assert np.isnan(coherence[:, 3]).all() and np.isnan(coherence[4, 2])


def test_a_glide_is_coherent_and_random_hops_are_not():
    """Highlights that follow a linear map of the half-vector's change (slot 0, a little noise) score near 1;
    glints that hop to a random neighbour's place by the same distances (slot 1) score about 0."""
    rng = np.random.default_rng(7)
    directions = _dome(40, rng)
    edges = _neighbours(directions, 6)
    change = half_vector_changes(directions, edges)
    sources = _sets(40, 2, rng).take(edges[:, 0])
    retargeted = sources.copy()
    glide = change @ np.array([[-0.8, 0.1], [0.2, -1.1]]).T
    retargeted.mean[:, 0] += glide + rng.normal(0, 0.05 * np.sqrt(np.mean(glide**2)), glide.shape)
    retargeted.mean[:, 1] += rng.normal(0, np.sqrt(np.mean(glide**2) / 2), glide.shape)
    _, coherence = _fitted(sources, retargeted, sources.active, edges, directions)
    assert np.min(coherence[:, 0]) > 0.9
    assert abs(float(np.mean(coherence[:, 1]))) < 0.2 and np.median(coherence[:, 1]) < 0.3


def test_decide_moving_holds_back_incoherent_gaussians_and_lets_the_undecided_move():
    """Three slots that land on their target: coherent, incoherent, undecided (NaN). At a threshold of 0.5 the
    incoherent one stays and is reported; at -1 (off) all three move."""
    sources, targets = centred_blob_sets(2, 3)
    edges = np.array([[0, 1], [1, 0]])
    retargeted = sources.take(edges[:, 0])
    coherence = np.array([[0.9, 0.1, np.nan], [0.9, 0.1, np.nan]])
    held = decide_moving(sources, retargeted, edges, targets, settings=ResidualSettings(move_coherence=0.5),
                         raster=RasterSettings(), coherence=coherence)
    assert held.moving.tolist() == [[True, False, True]] * 2
    assert held.incoherent.tolist() == [[False, True, False]] * 2
    free = decide_moving(sources, retargeted, edges, targets, settings=ResidualSettings(move_coherence=-1.0),
                         raster=RasterSettings(), coherence=coherence)
    assert free.moving.all() and not free.incoherent.any()


@pytest.mark.parametrize("value", [-1.5, 1.5, float("nan")])
def test_move_coherence_outside_its_range_is_refused(value):
    from warp_highlights.model.errors import InputError

    with pytest.raises(InputError, match="move_coherence"):
        ResidualSettings(move_coherence=value)
