"""How the field file stores basis codes (``io.codes``): row differences in byte planes, run-length
deflate; the rate search counts the bytes the file holds."""

from __future__ import annotations

import dataclasses
import io
import zipfile
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from warp_highlights.fit.residual import RateSample, component_bytes
from warp_highlights.io.codes import (
    CODES_LEVEL,
    CODES_STRATEGY,
    codes_from_stored,
    deflated_size,
    stored_bytes,
    stored_codes,
    stored_shape,
)
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.model.residual import LowRankStack, PrincipalImages, ResidualModel, code_levels

RNG = np.random.default_rng(14)


def _reference_stored(codes: np.ndarray) -> np.ndarray:
    """The stored form in plain integer arithmetic: (P, R, W) codes -> row differences mod 2^bits, byte planes."""
    bits = 8 * codes.dtype.itemsize
    values = codes.astype(np.int64)
    above = np.concatenate([np.zeros_like(values[..., :1, :]), values[..., :-1, :]], axis=-2)
    difference = (values - above) % (1 << bits)
    if bits == 8:
        return difference.astype(np.uint8)
    return np.stack([difference // 256, difference % 256], axis=-3).astype(np.uint8)


@settings(max_examples=60, deadline=None)
@given(bits=st.sampled_from([8, 16]), data=st.data())
def test_stored_codes_are_row_differences_in_byte_planes_and_come_back_exactly(bits, data):
    kind = np.uint8 if bits == 8 else np.uint16
    shape = data.draw(st.tuples(st.integers(1, 3), st.integers(1, 2), st.integers(1, 9), st.integers(1, 7)))
    codes = data.draw(hnp.arrays(kind, shape, elements=st.integers(0, code_levels(bits))))  # extremes included: differences wrap
    stored = np.stack([stored_codes(image) for image in codes])
    assert stored.dtype == np.uint8 and stored.shape == stored_shape(*shape, bits)
    np.testing.assert_array_equal(stored, np.stack([_reference_stored(image) for image in codes]))
    back = codes_from_stored(stored, bits)
    assert back.dtype == kind
    np.testing.assert_array_equal(back, codes)


@pytest.mark.parametrize("kind", [np.uint8, np.uint16])
def test_a_band_of_rows_with_the_row_above_it_is_stored_as_the_whole_image_stores_it(kind):
    """What the rate search samples: a band taken with the row above it, its first stored row dropped."""
    codes = RNG.integers(0, np.iinfo(kind).max + 1, size=(2, 30, 11)).astype(kind)
    whole = stored_codes(codes)
    band = stored_codes(codes[:, 11:20])[..., 1:, :]
    np.testing.assert_array_equal(band, whole[..., 12:20, :])
    assert deflated_size(band) == deflated_size(whole[..., 12:20, :])


def test_smooth_16_bit_codes_store_smaller_and_faster_than_as_they_are():
    """The point of the layout: a smooth basis image with a little noise (what the residual's basis
    images look like) takes fewer bytes than its codes deflated as they are at zlib's default level."""
    yy, xx = np.mgrid[0:200, 0:300] / 200.0
    image = np.sin(5 * xx + 2 * yy) * np.exp(-((xx - 0.7) ** 2 + (yy - 0.5) ** 2) * 3) + 2e-4 * RNG.normal(size=xx.shape)
    codes = np.round((image - image.min()) / (image.max() - image.min()) * 65535).astype(np.uint16)[None]
    assert stored_bytes(codes) < 0.9 * len(zlib.compress(codes.tobytes(), 6))


def _smooth_stack(n: int, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 3 * xx + i) * np.cos((i % 5 + 1) * 2 * yy) for i in range(8)])
    stack = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 8)) * 0.8 ** np.arange(8), patterns)[..., None] + 1.0
    return stack + 1e-3 * RNG.normal(size=stack.shape)


@pytest.mark.parametrize("bits", [8, 16])
def test_the_sampled_bytes_are_the_whole_images_stored_bytes_at_the_sampled_rows(bits):
    """A sampled ``RateSample`` deflates each band of rows as the file stores those rows (the first row
    of a band less the row above it, not as it is)."""
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    sample = RateSample(principal, 3)
    assert not sample.exact
    steps = principal.spans[:3] / code_levels(bits) * 7.0
    counted = sample.rows[sample.counted]
    stack = LowRankStack.quantised(principal, steps, bits=bits)
    expected = sum(deflated_size(stored_codes(code.transpose(2, 0, 1))[..., counted, :]) for code in stack.codes)
    assert sample.bytes(steps, bits=bits) == expected * 320 / len(counted) + sample.per_image * 3
    assert RateSample(principal, 3, whole=True).bytes(steps, bits=bits) == float(component_bytes(stack).sum())


@pytest.mark.parametrize("bits", [8, 16])
def test_the_file_holds_the_stored_codes_in_the_bytes_the_budget_counted(bits, tmp_path):
    """``numpy.load`` reads the codes entry as the stored form, deflated as one run-length stream; and its compressed size is at most what ``component_bytes`` counts
    (and close to it); the field loads the same codes back."""
    from test_field import make_field

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    stack = LowRankStack.quantised(principal, principal.spans / code_levels(bits) * 3.0, bits=bits)
    field = dataclasses.replace(field, residual=ResidualModel(luminance=stack))
    path = tmp_path / "f.whf"
    save_field(field, path)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("residual/Y_codes.npy")
        raw = archive.read(info)
        stored = np.load(io.BytesIO(raw))
    compressor = zlib.compressobj(CODES_LEVEL, zlib.DEFLATED, -15, 8, CODES_STRATEGY)
    assert info.compress_size == len(compressor.compress(raw) + compressor.flush())  # one run-length stream (small: no threads)
    np.testing.assert_array_equal(stored, np.stack([stored_codes(code.transpose(2, 0, 1)) for code in stack.codes]))
    counted = float(component_bytes(stack).sum()) - stack.rank * (8 + 4 * len(stack.weights))
    assert 0.95 * counted <= info.compress_size <= counted + 64  # one stream shares its code tables between these tiny images
    np.testing.assert_array_equal(load_field(path).residual.luminance.codes, stack.codes)
