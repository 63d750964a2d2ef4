"""The residual's basis images quantised on a Warp device (``kernels.quantise``) against the host's
float64 rounding (``codes_in_place``) and stored form (``io.codes.stored_codes``), bit for bit; and the
rate search's bytes, pieces and the stacks' codes the same whether the images are held there or not."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
import warp as wp

import warp_highlights.kernels.quantise as quantise
import warp_highlights.kernels.rows as rows_module
import warp_highlights.residual.rate as residual_module
from warp_highlights.io.codes import CompressedCodes, stored_codes
from warp_highlights.kernels.gram import DeviceProducts
from warp_highlights.kernels.quantise import DeviceBasis
from warp_highlights.model.residual import code_levels
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import codes_in_place, quantised_stack
from warp_highlights.residual.rate import RateSample, quantised_bytes

RNG = np.random.default_rng(33)


def _host_codes(images: np.ndarray, low: np.ndarray, step: np.ndarray, bits: int) -> np.ndarray:
    """(c, M) codes as the host makes them: float64, round halves to even, clipped."""
    values = images.astype(np.float64)
    codes = codes_in_place(values, low[:, None], step[:, None], code_levels(bits))
    return codes.astype(np.uint8 if bits == 8 else np.uint16)


def _basis_with_ties(count: int, shape: tuple, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(count, M) float32 images, their lows and steps (float64), with values exactly on half steps
    (both roundings of a tie), at the ends of the range and beyond it (clipped)."""
    values = int(np.prod(shape))
    images = RNG.normal(size=(count, values)).astype(np.float32)
    low = images.min(axis=1).astype(np.float64)
    step = np.full(count, 0.125 if bits == 16 else 0.5)  # powers of two: low + (k + 1/2) step is a float32 tie
    ties = RNG.integers(0, 7, size=(count, values // 3))
    images[:, : values // 3] = (low[:, None] + (ties + 0.5) * step[:, None]).astype(np.float32)
    images[:, -2] = low - 3 * step  # below the range: code 0
    images[:, -1] = low + (code_levels(bits) + 5) * step  # above it: the top code
    return images, low, step


@pytest.mark.parametrize("bits", [8, 16])
def test_device_codes_and_stored_rows_are_the_host_s_bit_for_bit(device, bits, monkeypatch):
    """Images placed in column blocks over several parts (``PART_BYTES`` made small), quantised there:
    the host's codes (ties to even, clipping) and, at every row and at a band sample, the stored form."""
    shape = (9, 7, 2)
    count = 5
    images, low, step = _basis_with_ties(count + 1, shape, bits)
    monkeypatch.setattr(rows_module, "PART_BYTES", 2 * 4 * int(np.prod(shape)))  # two images a part ...
    monkeypatch.setattr(quantise, "LAUNCH_BYTES", 2 * int(np.prod(shape)))  # ... and at most one or two a launch
    held = DeviceBasis(count + 1, shape, device)
    assert len(held.parts) == 3
    for start in range(0, images.shape[1], 40):  # the projection's column blocks
        columns = slice(start, min(start + 40, images.shape[1]))
        held.place(wp.array(np.ascontiguousarray(images[:, columns]), dtype=wp.float32, device=device), columns)
    kind = np.uint8 if bits == 8 else np.uint16
    codes = held.codes(1, low[1:], step[1:], bits, out=np.empty((count, images.shape[1]), kind))
    expected = _host_codes(images[1:], low[1:], step[1:], bits)
    np.testing.assert_array_equal(codes, expected)
    assert np.any(expected == 0) and np.any(expected == code_levels(bits))
    planes = expected.reshape((count,) + shape).transpose(0, 3, 1, 2)  # (c, P, H, W)
    height, width = shape[0], shape[1]
    rows = np.arange(height)
    whole = held.stored(1, low[1:], step[1:], bits, rows, rows - 1,
                        out=np.empty((count, shape[2]) + ((2,) if bits == 16 else ()) + (height, width), np.uint8))
    np.testing.assert_array_equal(whole, stored_codes(planes))
    # rows 3, 4 counted with row 2 above them; rows 7, 8 after a gap, 7 less row 4 (as the host subtracts)
    band = np.array([2, 3, 4, 7, 8])
    above = np.array([-1, 2, 3, 4, 7])
    sampled = held.stored(1, low[1:], step[1:], bits, band, above,
                          out=np.empty((count, shape[2]) + ((2,) if bits == 16 else ()) + (len(band), width), np.uint8))
    np.testing.assert_array_equal(sampled, stored_codes(planes[:, :, band]))
    columns = slice(5, 61)
    decoded_low, decoded_step = low[1:].astype(np.float32), (step[1:] * 0.75).astype(np.float32)
    mean = RNG.normal(size=columns.stop - columns.start).astype(np.float32)
    design = held.design(1, low[1:], step[1:], bits, decoded_low, decoded_step, mean, columns).numpy()
    reference = np.vstack([mean[None],
                           decoded_low[:, None] + expected[:, columns].astype(np.float32) * decoded_step[:, None]])
    if wp.get_device(device).is_cuda:
        # within a rounding: CUDA may fuse the multiply-add
        np.testing.assert_allclose(design, reference, rtol=2**-23, atol=0)
    else:
        np.testing.assert_array_equal(design, reference)
    np.testing.assert_array_equal(held.rows(0, count + 1), images)  # every part copied down
    np.testing.assert_array_equal(held.rows(2, 2), images[2:4])  # across a part's end
    lows, highs = held.extremes(1)  # min and max are exact in any order
    np.testing.assert_array_equal(lows, images[1:].min(axis=1))
    np.testing.assert_array_equal(highs, images[1:].max(axis=1))
    with pytest.raises(ValueError, match="uint8 array"):
        held.stored(1, low[1:], step[1:], bits, band, above, out=np.empty((count, 3), np.uint8))
    with pytest.raises(ValueError, match="contiguous"):  # a copy would be written, not ``out``
        held.codes(1, low[1:], step[1:], bits, out=np.empty((images.shape[1], count), kind).T)


def _principal_pair(device) -> tuple[PrincipalImages, PrincipalImages]:
    """A stack's principal images with their products summed on ``device`` (held there) and the same
    images without the held copy (quantised on the host)."""
    n, height, width, planes = 14, 120, 30, 2
    smooth = np.cumsum(np.cumsum(RNG.normal(size=(n, height, width, planes)), axis=1), axis=2)
    stack = (smooth / np.abs(smooth).max()).astype(np.float32)
    there = PrincipalImages.of(stack, products=DeviceProducts(device))
    assert there.held is not None and there.directions is None, "held there, no host copy"
    host = dataclasses.replace(there, held=None, directions=there.host_directions())
    np.testing.assert_array_equal(there.lows, host.lows)  # the extremes found there are the host's
    np.testing.assert_array_equal(there.highs, host.highs)
    np.testing.assert_allclose(there.mean, _mean_image(host), rtol=1e-12)  # the first direction came down
    return there, host


def _mean_image(principal: PrincipalImages) -> np.ndarray:
    """``PrincipalImages.of_source``'s mean: the first direction at the images' RMS (float64 on the host;
    the RMS from the energies here, from the Gram matrix's trace there)."""
    first = principal.directions[0].astype(np.float64)
    pixels = principal.values
    rms = np.sqrt(principal.energies.sum() / (principal.light_count * pixels))
    return first * np.sign(first.sum() or 1.0) * rms * np.sqrt(pixels) / np.linalg.norm(first)


@pytest.mark.parametrize("bits", [8, 16])
def test_the_rate_search_and_the_stack_quantise_held_images_as_the_host_does(device, bits, monkeypatch):
    """Sampled and whole-image bytes, the kept pieces and the stack's codes: the same whether the
    principal images are quantised on the device or on the host (the same directions: the host's are
    the device's, copied down). The sample is two bands of rows with a gap between them; two images
    a group (a fresh measurement of six: three groups in two slots of host memory used in turn, each
    slot's compressions slowed so that one filled again before they end would be caught)."""
    monkeypatch.setattr(residual_module, "_RATE_MIN_VALUES", 64)
    monkeypatch.setattr(residual_module, "_RATE_SHARE", 0.125)  # two bands of these images' rows
    monkeypatch.setattr(residual_module, "NUMPY_THREADS", 2)
    monkeypatch.setattr(residual_module, "_STORED_GROUP_BYTES", 1)  # groups of NUMPY_THREADS images
    there, host = _principal_pair(device)
    levels = code_levels(bits)
    steps = host.spans[:6] / levels * np.array([1.0, 3.0, 7.5, 20.0, 60.0, 1.0])
    for whole in (False, True):
        a, b = RateSample(there, 6, whole=whole), RateSample(host, 6, whole=whole)
        assert a.held is not None and b.held is None and a.exact == whole
        if not whole:
            # a gap between the bands, each row with the one above
            assert np.any(np.diff(a.stored_rows) > 1) and np.all(a.above[1:] >= 0)
        subset = np.array([0, 2, 4, 5])  # runs of one and two images, the first two in one group
        np.testing.assert_array_equal(a.chunk_bytes(steps, bits=bits, images=subset),
                                      b.chunk_bytes(steps, bits=bits, images=subset))
        assert a.bytes(steps, bits=bits) == b.bytes(steps, bits=bits)
        # fewer images into the memory kept
        assert a.bytes(steps[:3] * 2, bits=bits) == b.bytes(steps[:3] * 2, bits=bits)
        # compressions that read their slot late: a slot filled again too early gives other bytes
        with monkeypatch.context() as slow:
            real = residual_module.compressed_chunk
            slow.setattr(residual_module, "compressed_chunk", lambda data: time.sleep(0.02) or real(data))
            fresh = RateSample(there, 6, whole=whole)  # three groups of two images in two slots, each measured once
            np.testing.assert_array_equal(fresh.chunk_bytes(steps * 1.5, bits=bits),
                                          b.chunk_bytes(steps * 1.5, bits=bits))
    kept_there, kept_host = CompressedCodes(), CompressedCodes()
    assert (quantised_bytes(there, steps, bits=bits, keep=kept_there)
            == quantised_bytes(host, steps, bits=bits, keep=kept_host))
    assert kept_there._kept == kept_host._kept
    a, b = quantised_stack(there, steps, bits=bits), quantised_stack(host, steps, bits=bits)
    np.testing.assert_array_equal(a.codes, b.codes)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    if wp.get_device(device).is_cuda:  # the decoded planes within a rounding
        np.testing.assert_allclose(a.weights, b.weights, rtol=0, atol=1e-6 * np.abs(b.weights).max())
    else:
        np.testing.assert_array_equal(a.weights, b.weights)


def test_no_room_on_the_device_keeps_the_images_on_the_host(device, monkeypatch):
    """Where the held images would take more than ``HELD_SHARE`` of a CUDA device's free memory, none
    are held (the host quantises); the CPU device (the tests' reference) always holds them."""
    import warp_highlights.kernels.gram as gram

    products = DeviceProducts(device)
    if not products.device.is_cuda:
        assert products.held_directions(3, (4, 5, 1)) is not None
        return
    monkeypatch.setattr(gram, "HELD_SHARE", 0.0)
    assert products.held_directions(3, (4, 5, 1)) is None
