"""The CRC-32 of joined data from its parts' CRCs (``io.crc``) against zlib's CRC of the joined bytes."""

from __future__ import annotations

import zlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from warp_highlights.io.crc import Crc32Appender, crc32_combine


@settings(max_examples=200, deadline=None)
@given(first=st.binary(max_size=300), second=st.binary(max_size=300))
def test_the_combined_crc_is_the_crc_of_the_joined_bytes(first, second):
    assert crc32_combine(zlib.crc32(first), zlib.crc32(second), len(second)) == zlib.crc32(first + second)


@settings(max_examples=30, deadline=None)
@given(parts=st.lists(st.binary(min_size=37, max_size=37), max_size=12), start=st.binary(max_size=50))
def test_parts_of_one_length_appended_in_turn(parts, start):
    appender = Crc32Appender(37)
    crc = zlib.crc32(start)
    for part in parts:
        crc = appender.append(crc, zlib.crc32(part))
    assert crc == zlib.crc32(start + b"".join(parts))


def test_long_parts_and_the_empty_part():
    rng_bytes = bytes(range(256)) * 4099  # over a MiB: x^(8n) from many powers of x
    assert crc32_combine(zlib.crc32(b"abc"), zlib.crc32(rng_bytes), len(rng_bytes)) == zlib.crc32(b"abc" + rng_bytes)
    assert crc32_combine(zlib.crc32(b"abc"), zlib.crc32(b""), 0) == zlib.crc32(b"abc")
    assert crc32_combine(0, zlib.crc32(b"abc"), 3) == zlib.crc32(b"abc")


def test_a_negative_length_is_refused():
    with pytest.raises(ValueError, match=">= 0"):
        Crc32Appender(-1)


def _zlib_combine():
    """zlib's own crc32_combine64 from the C library, where it can be loaded (a reference for lengths no test can
    hold)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("z")
    try:
        combine = getattr(ctypes.CDLL(name or "libz.so.1"), "crc32_combine64")
    except (OSError, AttributeError):
        return None
    combine.restype, combine.argtypes = ctypes.c_ulong, [ctypes.c_ulong, ctypes.c_ulong, ctypes.c_int64]
    return combine


@pytest.mark.skipif(_zlib_combine() is None, reason="zlib's C library (crc32_combine64) cannot be loaded here")
@pytest.mark.parametrize("length", [2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**32 + 1, 5 * 2**30 + 12345, 2**40 + 7, 10**18])
def test_lengths_past_32_bits_as_zlib_combines_them(length):
    combine = _zlib_combine()
    for first, second in ((0, 0), (0xFFFFFFFF, 0x80000005), (zlib.crc32(b"head"), zlib.crc32(b"tail"))):
        assert crc32_combine(first, second, length) == combine(first, second, length)
