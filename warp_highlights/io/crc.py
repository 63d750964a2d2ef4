"""The CRC-32 of joined data from its parts' CRCs (zlib's CRC-32, as zip files keep it).

Python's ``zlib`` computes a CRC over bytes it is given but does not expose zlib's ``crc32_combine``;
the field writer needs it to sum a codes entry's CRC from the CRCs its threads took of each basis
image (``io.fieldfile``), instead of reading every image's bytes again on one thread (the zip
writer's own CRC: 0.09-0.15 s of the 480x270 command's 0.3 s of saving on the lent H100).

Arithmetic: CRC-32 is the remainder of the data's bits (reflected, the register started and ended
inverted) modulo the polynomial P; appending ``n`` bytes multiplies the first part's remainder by
x^(8n) mod P before the second part's CRC is added (XOR). Products mod P are taken in the reflected
bit order zlib uses, x^(8n) from the powers x^(2^k) by the binary digits of 8n.
"""

from __future__ import annotations

__all__ = ["Crc32Appender", "crc32_combine"]

_POLYNOMIAL = 0xEDB88320  # P, reflected (zlib's CRC-32)
_ONE = 1 << 31  # the polynomial 1, reflected
_X = 1 << 30  # the polynomial x, reflected


def _product(a: int, b: int) -> int:
    """a(x) b(x) mod P, both reflected 32-bit polynomials."""
    result = 0
    bit = _ONE
    while a:
        if a & bit:
            result ^= b
            a ^= bit
        bit >>= 1
        b = (b >> 1) ^ _POLYNOMIAL if b & 1 else b >> 1  # b(x) x mod P
    return result


def _power_of_x(exponent: int) -> int:
    """x^exponent mod P, reflected."""
    result, square = _ONE, _X  # square: x^(2^k)
    while exponent:
        if exponent & 1:
            result = _product(result, square)
        square = _product(square, square)
        exponent >>= 1
    return result


class Crc32Appender:
    """Appends parts of one length: ``append(crc, part_crc)`` is the CRC-32 of data whose CRC is ``crc``
    followed by ``length`` bytes whose CRC is ``part_crc`` (x^(8 length) mod P computed once)."""

    def __init__(self, length: int):
        if length < 0:
            raise ValueError(f"a part's length must be >= 0, got {length}")
        self.length = int(length)
        self._shift = _power_of_x(8 * self.length)

    def append(self, crc: int, part_crc: int) -> int:
        return _product(self._shift, crc & 0xFFFFFFFF) ^ (part_crc & 0xFFFFFFFF)


def crc32_combine(first: int, second: int, second_length: int) -> int:
    """The CRC-32 (``zlib.crc32``) of A followed by B from A's CRC ``first``, B's CRC ``second`` and B's
    length in bytes."""
    return Crc32Appender(second_length).append(first, second)
