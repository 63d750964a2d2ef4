"""The move check's scores on a device (``kernels.scores``) against the host's: NumPy's float32
blend and ``display_rgb8`` (what ``fit.validation`` scores with elsewhere), and a float64 reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from warp_highlights.io.images import display_rgb8, linear_to_srgb
from warp_highlights.kernels.scores import _code, prediction_errors
from warp_highlights.kernels.transfer import rows_up
from warp_highlights.quality.metrics import psnr_8bit

RNG = np.random.default_rng(31)


def _case(k=7, m=4, height=9, width=11, channels=3):
    images = (RNG.random((k, height, width, channels)) * 1.3).astype(np.float32)
    own = (RNG.random((k, height, width)) * 0.4).astype(np.float32)
    drawn = (RNG.random((m, height, width)) * 0.5).astype(np.float32)
    tint = (0.5 + RNG.random((height, width, channels))).astype(np.float32)
    corners = np.stack([RNG.choice(k, 3, replace=False) for _ in range(m)])
    weights = RNG.dirichlet(np.ones(3), size=m).astype(np.float32)
    truth = RNG.integers(0, k, size=m)
    return images, own, drawn, tint, corners, weights, truth


def _host_psnr(images, own, drawn, tint, corners, weights, truth, scale):
    """What ``check_moving`` computes on the host, light by light."""
    moving, blending = [], []
    for q in range(len(corners)):
        blend = sum(w * images[v] for v, w in zip(corners[q], weights[q]))
        highlights = sum(w * own[v] for v, w in zip(corners[q], weights[q]))
        moved = blend + (drawn[q] - highlights)[..., None] * tint
        shown = display_rgb8(images[truth[q]] * scale)
        moving.append(psnr_8bit(display_rgb8(moved * scale), shown))
        blending.append(psnr_8bit(display_rgb8(blend * scale), shown))
    return np.array(moving), np.array(blending)


def _reference64(images, own, drawn, tint, corners, weights, truth, scale):
    """The same in float64 throughout (the sRGB curve, rounding half to even)."""
    def shown(x):
        x = np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        return np.round(np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)
                        * 255.0)

    moving, blending = [], []
    images, own, weights = images.astype(np.float64), own.astype(np.float64), weights.astype(np.float64)
    for q in range(len(corners)):
        blend = np.einsum("k,khwc->hwc", weights[q], images[corners[q]])
        moved = blend + (drawn[q] - np.einsum("k,khw->hw", weights[q], own[corners[q]]))[..., None] * tint
        truth_shown = shown(images[truth[q]] * scale)
        for out, prediction in ((moving, moved), (blending, blend)):
            mse = np.mean((shown(prediction * scale) - truth_shown) ** 2)
            out.append(100.0 if mse == 0 else min(100.0, 10 * np.log10(255.0**2 / mse)))
    return np.array(moving), np.array(blending)


def _device_psnr(device, images, own, drawn, tint, corners, weights, truth, scale):
    k, height, width, channels = images.shape
    errors = prediction_errors(wp.array(images.reshape(k, -1), dtype=wp.float32, device=device),
                               wp.array(own.reshape(k, -1), dtype=wp.float32, device=device),
                               wp.array(drawn.reshape(len(drawn), -1), dtype=wp.float32, device=device),
                               tint, corners, weights, truth, scale=scale, height=height, width=width)
    mse = errors / (height * width * channels)
    with np.errstate(divide="ignore"):
        return tuple(np.minimum(10 * np.log10(255.0**2 / mse[:, i]), 100.0) for i in range(2))


@pytest.mark.parametrize("scale", [1.0, 0.37])
def test_device_scores_are_the_hosts_and_the_float64_reference(device, scale):
    case = _case()
    host = _host_psnr(*case, np.float32(scale))
    there = _device_psnr(device, *case, scale)
    reference = _reference64(*case, scale)
    for ours, theirs, exact in zip(there, host, reference):
        np.testing.assert_allclose(ours, theirs, atol=0.02)  # a code moved by one at an edge: a few thousandths of a dB
        np.testing.assert_allclose(ours, exact, atol=0.05)
    assert np.all(there[0] != there[1])  # the two predictions are scored apart


def test_a_tint_of_one_colour_and_one_channel(device):
    images, own, drawn, tint, corners, weights, truth = _case(channels=1)
    tint = np.ones((1, 1, 1), np.float32)
    host = _host_psnr(images, own, drawn, np.broadcast_to(tint, images.shape[1:]), corners, weights, truth,
                      np.float32(1.0))
    there = _device_psnr(device, images, own, drawn, tint, corners, weights, truth, 1.0)
    for ours, theirs in zip(there, host):
        np.testing.assert_allclose(ours, theirs, atol=0.02)


@wp.kernel
def _codes_of(values: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    out[i] = _code(values[i])


def test_codes_are_display_rgb8s(device):
    """NaN black, +inf white, clipped, the sRGB curve, halves to even; the device's pow may move a code
    by one only where the value sits on a code's edge."""
    values = np.concatenate([np.array([np.nan, np.inf, -np.inf, -0.5, 0.0, 0.0031308, 0.0031309, 0.5, 1.0, 7.0],
                                      np.float32),
                             RNG.random(4000).astype(np.float32)])
    out = wp.zeros(len(values), dtype=wp.float32, device=device)
    wp.launch(_codes_of, dim=len(values), inputs=[wp.array(values, dtype=wp.float32, device=device)], outputs=[out],
              device=device)
    codes = out.numpy()
    expected = display_rgb8(values.reshape(-1, 1, 1))[:, 0, 0].astype(np.float32)
    np.testing.assert_array_equal(codes[:10], expected[:10])
    off = np.flatnonzero(codes != expected)
    assert np.all(np.abs(codes[off] - expected[off]) == 1)
    # distance of the exact code to a rounding edge
    edge = np.abs(linear_to_srgb(values[off].astype(np.float64)) * 255.0 % 1.0 - 0.5)
    assert np.all(edge < 1e-4)


def test_exact_halves_round_to_even(device):
    """Values of the sRGB curve's linear segment (no pow: exact on every device) whose code sits exactly on a half."""
    low, high = np.float32(1e-5).view(np.int32), np.float32(0.0031308).view(np.int32)
    values = np.arange(low, high, dtype=np.int32).view(np.float32)
    halves = values[(values * np.float32(12.92)) * np.float32(255.0) % 1 == 0.5]
    assert len(halves) >= 4
    out = wp.zeros(len(halves), dtype=wp.float32, device=device)
    wp.launch(_codes_of, dim=len(halves), inputs=[wp.array(halves, dtype=wp.float32, device=device)], outputs=[out],
              device=device)
    np.testing.assert_array_equal(out.numpy(), display_rgb8(halves.reshape(-1, 1, 1))[:, 0, 0])


@pytest.mark.parametrize("held", [False, True])
@pytest.mark.parametrize("channels", [1, 3])
def test_the_checks_device_scores_are_the_hosts(device, held, channels):
    """``fit.validation``'s scorer (the CPU device here: the host's arithmetic) over a chunk of the lights, the images
    it needs sent up or held there already, against the host's scores."""
    from warp_highlights.fit.validation import _DeviceScores
    from warp_highlights.residual.inputs import HeldImages

    images, own, drawn, tint, corners, weights, truth = _case(k=9, m=5, channels=channels)
    tint = np.ones((1, 1, 1), np.float32) if channels == 1 else tint
    n, height, width, _ = images.shape
    there = HeldImages(wp.array(images.reshape(n, height * width, channels), dtype=wp.float32, device=device),
                       wp.array(own.reshape(n, -1), dtype=wp.float32, device=device)) if held else None
    scorer = _DeviceScores(images, own, tint, corners, truth, np.float32(0.6), wp.get_device(device), held=there)
    rows = np.array([1, 3, 4])
    moving, blending = scorer.psnr(rows, wp.array(drawn[rows], dtype=wp.float32, device=device), weights[rows])
    host = _host_psnr(images, own, drawn, np.broadcast_to(tint, images.shape[1:]), corners, weights, truth,
                      np.float32(0.6))
    # a code moved by one at an edge (a CPU's own pow or FMA too)
    np.testing.assert_allclose(moving, host[0][rows], atol=0.02)
    np.testing.assert_allclose(blending, host[1][rows], atol=0.02)


@pytest.mark.parametrize("staged", [False, True])
def test_selected_rows_go_up_in_their_order(device, staged, monkeypatch):
    import warp_highlights.kernels.transfer as transfer

    if staged:  # through small page-locked buffers (or the CPU device's stand-ins), a row across two of them
        monkeypatch.setattr(transfer, "staged", lambda device, nbytes: True)
        monkeypatch.setattr(transfer.Staging, "of",
                            classmethod(lambda cls, device: cls(device, slot_bytes=37, slots=2)))
    host = RNG.random((6, 5, 3)).astype(np.float32)
    rows = np.array([4, 0, 4, 2])
    np.testing.assert_array_equal(rows_up(host, device, rows=rows).numpy(), host[rows])
    assert rows_up(host, device, rows=np.zeros(0, np.int64)).shape == (0, 5, 3)
    with pytest.raises(ValueError, match="two or more axes"):
        rows_up(np.zeros(4, np.float32), device, rows=[1])


@pytest.mark.skipif(not wp.is_cuda_available(), reason="the move check scores on CUDA devices only")
def test_the_check_scores_on_the_device_as_on_the_host(monkeypatch):
    """``check_moving`` on CUDA (scored by ``kernels.scores``) against the host's scoring of the same lights."""
    import test_validation as scene
    import warp_highlights.fit.validation as validation

    directions, edges, estimated, own, images = scene._scene()
    retargeted = scene._one_gaussian_sets(np.array([scene._highlight_at(directions[b]) for b in edges[:, 1]]))
    defaults = validation.FitSettings()
    retarget = dataclasses.replace(defaults.retarget, rigid_iterations=0, iterations=0)
    settings = dataclasses.replace(defaults, retarget=retarget)
    plan = validation.plan_check(directions, edges, 16)
    args = (plan, estimated, retargeted, edges, np.zeros(retargeted.active.shape, np.float32), estimated.active.copy())
    checks = []
    for device in ("cuda:0", "cpu"):
        checks.append(validation.check_moving(*args, wp.array(own, dtype=float, device=device), images, own, None,
                                              factor=1.0, settings=settings,
                                              device=device))
    np.testing.assert_allclose(checks[0].moving_psnr, checks[1].moving_psnr, atol=0.02)
    np.testing.assert_allclose(checks[0].blend_psnr, checks[1].blend_psnr, atol=0.02)
    assert checks[0].moves == checks[1].moves
    held = validation_hold(images, own)
    with_held = validation.check_moving(*args, wp.array(own, dtype=float, device="cuda:0"), images, own, None,
                                        factor=1.0, settings=settings,
                                        device="cuda:0", held=held)
    # the same images there: the same scores
    np.testing.assert_array_equal(with_held.moving_psnr, checks[0].moving_psnr)
    np.testing.assert_array_equal(with_held.blend_psnr, checks[0].blend_psnr)


def validation_hold(images, own):
    from warp_highlights.residual.inputs import hold_images

    held = hold_images(images, own, "cuda:0")
    assert held is not None and held.images.shape == (len(images), images.shape[1] * images.shape[2], images.shape[3])
    return held


def test_images_are_held_on_cuda_devices_only_and_within_their_bound(monkeypatch):
    import warp_highlights.residual.inputs as residual_module

    images, own = np.zeros((3, 4, 5, 3), np.float32), np.zeros((3, 4, 5), np.float32)
    assert residual_module.hold_images(images, own, "cpu") is None
    if wp.is_cuda_available():
        assert residual_module.hold_images(images, own, "cuda:0") is not None
        # the own highlights no longer fit beside
        monkeypatch.setattr(residual_module, "HELD_IMAGES_BYTES", images.nbytes)
        assert residual_module.hold_images(images, own, "cuda:0") is None
        assert not residual_module.holds_images(images.shape, "cuda:0")
    assert not residual_module.holds_images(images.shape, "cpu")


@pytest.mark.skipif(not wp.is_cuda_available(), reason="images are held on CUDA devices only")
def test_images_already_up_are_held_as_they_are(monkeypatch):
    """``hold_images(images_up=, own_up=)``: the arrays given are held (the same memory, not sent up again),
    even where the bound asked before they went up would not hold them now; ``own`` alone is sent up."""
    import warp_highlights.residual.inputs as residual_module

    images, own = RNG.random((3, 4, 5, 3)).astype(np.float32), RNG.random((3, 4, 5)).astype(np.float32)
    images_up, own_up = wp.array(images, dtype=float, device="cuda:0"), wp.array(own, dtype=float, device="cuda:0")
    monkeypatch.setattr(residual_module, "HELD_IMAGES_BYTES", 0)
    assert residual_module.hold_images(images, own, "cuda:0") is None
    held = residual_module.hold_images(images, own, "cuda:0", images_up=images_up, own_up=own_up)
    assert held.images.ptr == images_up.ptr and held.own.ptr == own_up.ptr
    assert held.images.shape == (3, 20, 3) and held.own.shape == (3, 20)
    held = residual_module.hold_images(images, own, "cuda:0", images_up=images_up)
    assert held.images.ptr == images_up.ptr
    np.testing.assert_array_equal(held.own.numpy(), own.reshape(3, 20))
