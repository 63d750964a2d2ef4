"""Motion scores of relit frames along a light path (quality/motion.py), on blobs whose answers are known."""

from __future__ import annotations

import numpy as np

from warp_highlights.quality.motion import (
    NONE_LEVEL,
    REFERENCE_HEIGHT_PX,
    flicker,
    highlight_motion,
    motion_scores,
    visible_ghost_share,
)

HEIGHT, WIDTH = 90, 160


def _blob(row: float, col: float, sigma: float = 4.0, peak: float = 2.0) -> np.ndarray:
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    return peak * np.exp(-((rows - row) ** 2 + (cols - col) ** 2) / (2 * sigma**2))


def _path(cols, shift: float = 0.0, weight: float = 1.0):
    """Frames of a blob gliding along ``cols`` on a flat grey diffuse (linear RGB)."""
    diffuse = np.full((len(cols), HEIGHT, WIDTH, 3), 0.2)
    specular = np.stack([weight * _blob(45.0, c + shift) for c in cols])[..., None].repeat(3, axis=-1)
    return diffuse + specular, specular, diffuse


def test_the_truth_scores_no_ghost_no_offset_and_no_flicker():
    truth, specular, diffuse = _path(np.linspace(30, 130, 12))
    scores = motion_scores(truth, truth, specular, diffuse)
    np.testing.assert_allclose(scores.ghost_share, 0.0, atol=1e-12)
    np.testing.assert_allclose(scores.visible_ghost_share, 0.0, atol=1e-12)
    np.testing.assert_allclose(scores.position_error_rpx, 0.0, atol=1e-9)
    np.testing.assert_allclose(scores.flicker, 0.0)
    assert scores.summary() == {"ghost_share": 0.0, "visible_ghost_share": 0.0, "position_error_rpx": 0.0,
                                "flicker_levels": 0.0}


def test_a_shifted_highlight_is_off_by_its_shift_in_reference_pixels():
    cols = np.linspace(40, 120, 5)
    truth, specular, diffuse = _path(cols)
    shifted, _, _ = _path(cols, shift=6.0)
    _, error = highlight_motion(shifted, truth, specular, diffuse)
    np.testing.assert_allclose(error, 6.0 * REFERENCE_HEIGHT_PX / HEIGHT, rtol=0.02)


def test_a_cross_fade_shows_its_two_half_highlights_as_ghosts():
    """Halfway between two captured positions, the blend shows half of each: the highlight's whole energy
    appears where the truth has none, and the centroid of the two halves lands on the truth."""
    truth, specular, diffuse = _path([80.0])
    blend = 0.2 + 0.5 * (_blob(45.0, 50.0) + _blob(45.0, 110.0))[None, ..., None].repeat(3, axis=-1)
    ghost, _ = highlight_motion(blend, truth, specular, diffuse)
    np.testing.assert_allclose(ghost, 1.0, rtol=0.02)
    faded, _ = highlight_motion(truth * 0 + 0.2 + 0.5 * specular, truth, specular, diffuse)
    assert faded[0] < 1e-9  # dimmer but in place: no ghost
    # each half copy (peak 1, half the truth's 2) is seen where it is at least NONE_LEVEL of the truth's peak: a
    # Gaussian lobe holds the share 1 - level / its peak of its energy there
    np.testing.assert_allclose(visible_ghost_share(blend, truth, specular), 1.0 - NONE_LEVEL * 2.0, rtol=0.02)


def test_faint_shading_error_is_ghost_light_but_no_visible_ghost():
    """Shading a little too bright over the whole frame (1% of the highlight's peak) adds light where the truth
    has no highlight, which the ghost share counts (here several times the highlight's energy); none of it
    looks like a highlight, so the visible ghost share is 0. A highlight copy as bright as a tenth of the peak
    beside it is seen."""
    truth, specular, diffuse = _path([80.0])
    brighter = truth + 0.01 * 2.0
    ghost, _ = highlight_motion(brighter, truth, specular, diffuse)
    assert ghost[0] > 1.0
    assert visible_ghost_share(brighter, truth, specular)[0] == 0.0
    copy = brighter + 0.1 * _blob(45.0, 30.0)[None, ..., None]
    seen = visible_ghost_share(copy, truth, specular)[0]
    expected = (0.1 * _blob(45.0, 30.0) + 0.02)[0.1 * _blob(45.0, 30.0) + 0.02 >= NONE_LEVEL * 2.0].sum() / _blob(
        45.0, 80.0).sum()
    np.testing.assert_allclose(seen, expected, rtol=1e-6)


def test_a_jumping_highlight_flickers_more_than_one_that_glides_late():
    cols = np.linspace(30, 130, 21)
    truth, _, _ = _path(cols)
    late, _, _ = _path(cols, shift=-3.0)
    jumping, _, _ = _path(np.repeat(cols[::5], 5)[: len(cols)])
    assert flicker(jumping, truth).max() > 3 * flicker(late, truth).max()


def test_frames_without_a_highlight_score_nan_not_zero():
    truth, specular, diffuse = _path([80.0])
    ghost, error = highlight_motion(truth, truth, specular * 0, diffuse)
    assert np.isnan(ghost[0]) and np.isnan(error[0])
    assert np.isnan(visible_ghost_share(truth, truth, specular * 0)[0])
