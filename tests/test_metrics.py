"""``quality.metrics``, the one place image quality is computed, against direct computations; and no other
module computes PSNR or SSIM itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from warp_highlights.io.images import display_rgb8
from warp_highlights.quality.metrics import (
    psnr,
    psnr_8bit,
    psnr_excluding_black,
    srgb_psnr,
    srgb_scores,
    ssim_8bit,
)

ROOT = Path(__file__).resolve().parents[1]


def test_psnr_values():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 1, (3, 8, 9)), rng.uniform(0, 1, (3, 8, 9))
    want = 10 * np.log10(1 / ((a - b) ** 2).mean(axis=(1, 2)))
    np.testing.assert_allclose(psnr(a, b), want)
    assert psnr(a[0], a[0]) == 100.0 and psnr(a[0] + 5, np.ones_like(a[0])) == 100.0  # clipped to [0, 1] first
    stack = np.concatenate([a, np.zeros((1, 8, 9))])
    got = psnr_excluding_black(stack, np.concatenate([b, np.zeros((1, 8, 9))]))
    np.testing.assert_allclose(got[:3], want)
    assert np.isnan(got[3])  # both black: no score
    x, y = rng.integers(0, 256, (2, 6, 7, 3)).astype(np.uint8)
    assert psnr_8bit(x, y) == pytest.approx(10 * np.log10(255**2 / ((x.astype(float) - y) ** 2).mean()))
    assert psnr_8bit(x, x) == 100.0
    assert srgb_psnr(a[0], b[0]) == psnr_8bit(display_rgb8(a[0]), display_rgb8(b[0]))


def test_ssim_is_scikit_images():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    x, y = rng.integers(0, 256, (2, 20, 30, 3)).astype(np.uint8)
    assert ssim_8bit(x, y) == pytest.approx(structural_similarity(y, x, channel_axis=-1, data_range=255, win_size=7))
    assert (ssim_8bit(x[:5, :5], y[:5, :5])
            == pytest.approx(structural_similarity(y[:5, :5], x[:5, :5], channel_axis=-1, data_range=255, win_size=5)))
    assert ssim_8bit(x[:2, :2], y[:2, :2]) == 1.0  # too small for any window
    images, truth = rng.uniform(0, 1, (2, 3, 20, 30, 3))
    p, s = srgb_scores(images, truth)
    assert p[1] == srgb_psnr(images[1], truth[1]) and s[1] == ssim_8bit(display_rgb8(images[1]), display_rgb8(truth[1]))


def test_quality_is_computed_in_one_module():
    """No module but ``quality/metrics.py`` takes a logarithm of an error or calls scikit-image's SSIM."""
    found = []
    for folder in ("warp_highlights", "kernels", "benchmarks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path.relative_to(ROOT).as_posix() == "warp_highlights/quality/metrics.py":
                continue
            text = path.read_text()
            found += [f"{path.relative_to(ROOT)}: {needle}"
                      for needle in ("log10(", "structural_similarity", "peak_signal_noise_ratio") if needle in text]
    assert found == []


@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_8bit_psnr_in_integers_is_the_float64_mean_exactly(data):
    shape = data.draw(st.tuples(st.integers(1, 40), st.integers(1, 40), st.sampled_from([1, 3])))
    x = data.draw(hnp.arrays(np.uint8, shape))
    y = data.draw(hnp.arrays(np.uint8, shape))
    mse = float(np.mean((x.astype(np.float64) - y) ** 2))
    assert psnr_8bit(x, y) == (100.0 if mse == 0 else min(100.0, 10.0 * np.log10(255.0**2 / mse)))
    assert psnr_8bit(x, y) == psnr_8bit(x.astype(np.float64), y.astype(np.float64))


def test_8bit_psnr_of_a_large_image_sums_past_32_bits():
    """A 480x270 colour image all 255 against all 0: 389k squares of 65025 sum past 2^31."""
    white, black = np.full((270, 480, 3), 255, np.uint8), np.zeros((270, 480, 3), np.uint8)
    assert psnr_8bit(white, black) == 0.0
    assert psnr_8bit(black[:, :, :1], white[:, :, :1]) == 0.0


def test_8bit_psnr_of_masked_images_keeps_their_mask():
    a = np.ma.masked_array(np.array([[0, 10]], np.uint8), mask=[[False, True]])
    b = np.ma.masked_array(np.array([[0, 250]], np.uint8), mask=[[False, True]])
    assert psnr_8bit(a, b) == 100.0  # the one unmasked value agrees


def _stacks(count: int, seed: int = 4):
    rng = np.random.default_rng(seed)
    truth = rng.random((count, 20, 24, 3), dtype=np.float32)
    return np.clip(truth + 0.05 * rng.standard_normal(truth.shape, dtype=np.float32), 0.0, None), truth


def test_psnr_excluding_black_image_by_image_is_the_stack_formula():
    """Scored one image at a time in threads: the same values as the whole stack in float64, NaN where both are
    black."""
    images, truth = _stacks(9)
    images[2] = truth[2] = 0.0
    images[4] = truth[4]
    a = np.clip(images.astype(np.float64), 0, 1).reshape(9, -1)
    b = np.clip(truth.astype(np.float64), 0, 1).reshape(9, -1)
    with np.errstate(divide="ignore"):
        want = np.minimum(10 * np.log10(1 / ((a - b) ** 2).mean(axis=1)), 100.0)
    got = psnr_excluding_black(images, truth)
    assert np.isnan(got[2]) and got[4] == 100.0
    np.testing.assert_array_equal(np.delete(got, 2), np.delete(want, 2))
    assert psnr_excluding_black(images[:0], truth[:0]).shape == (0,)
    with pytest.raises(ValueError, match="shape"):
        psnr_excluding_black(images, truth[:3])


def test_scores_in_worker_processes_equal_the_threads(caplog):
    """A stack past PROCESSES_FROM inside scoring_processes: scored by two spawned processes, the same
    values as in threads; the processes are gone after the scope."""
    import logging
    import multiprocessing

    from warp_highlights.model.threads import core_count
    from warp_highlights.quality import metrics

    if core_count() < 2:
        pytest.skip("one core: scoring_processes keeps to threads")
    images, truth = _stacks(metrics.PROCESSES_FROM + 3)
    threads = srgb_scores(images, truth)
    with caplog.at_level(logging.DEBUG, logger="warp_highlights"):
        with metrics.scoring_processes(2):
            with metrics.scoring_processes(4):  # nested: the outer scope's processes
                inside = srgb_scores(images, truth)
            again = srgb_scores(images, truth)
            small = srgb_scores(images[:3], truth[:3])  # below PROCESSES_FROM: threads
    messages = [r.getMessage() for r in caplog.records]
    assert "scoring in 2 worker processes" in messages, messages
    assert not any("unavailable" in m for m in messages), messages
    for got in (inside, again):
        np.testing.assert_array_equal(got[0], threads[0])
        np.testing.assert_array_equal(got[1], threads[1])
    np.testing.assert_array_equal(small[1], threads[1][:3])
    assert metrics._SCORING is None
    assert multiprocessing.active_children() == [], "worker processes left running"


def test_scores_fall_back_to_threads_without_processes(monkeypatch, caplog):
    """Where processes cannot start (a daemonic process, a main module spawn cannot import): the same scores in
    threads."""
    import concurrent.futures
    import logging

    from warp_highlights.quality import metrics

    def refuse(*args, **kwargs):
        raise AssertionError("daemonic processes are not allowed to have children")

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", refuse)
    images, truth = _stacks(metrics.PROCESSES_FROM)
    with caplog.at_level(logging.DEBUG, logger="warp_highlights"):
        with metrics.scoring_processes(2):
            first = srgb_scores(images, truth)
            second = srgb_scores(images, truth)
    assert sum("worker processes unavailable" in r.getMessage() for r in caplog.records) == 1, "said once, then threads"
    threads = srgb_scores(images, truth)
    np.testing.assert_array_equal(first[1], threads[1])
    np.testing.assert_array_equal(second[0], threads[0])
