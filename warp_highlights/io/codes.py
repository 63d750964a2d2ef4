"""How a field file stores a low-rank stack's basis codes (format version 4): row differences in byte
planes, deflated run-length only. The rate search counts a basis image's bytes with the same functions.

A basis image's (P, H, W) codes of 8 or 16 bits are stored as the difference of each row from the row
above (the first row as it is), wrapping modulo 2^bits, and 16-bit differences as two byte planes, the
high bytes first: (P, H, W) uint8 or (P, 2, H, W) uint8. The deflate stream uses zlib's run-length
strategy (``Z_RLE``: matches only at distance one), and is made of pieces: the ``.npy`` header's, then
each image's, each deflated on its own and ended by a sync flush (``deflated_piece``), then an empty
final block (``STREAM_END``). A match never reaches back further than one byte, so a piece costs
only its sync-flush marker and a fresh block header against one stream (+0.01% at 480x270, +4% on
20x30 test images); the pieces let each image be deflated in its own thread, and once: the rate
search's last exact measurements keep their pieces (``DeflatedCodes``) and the field writer stores them.

Against the version-3 layout (the codes as they are, 16 bits little-endian, zlib level 6), on the
basis codes of the 250-light 480x270 donut and the dome (16-bit) and the statue (8-bit): 82-98% of
the bytes, deflated 4-9 times faster (``benchmarks/bench_codes.py``). Level 6 spends its time
searching long match chains in noisy low bytes for matches that run-length coding finds at once; the
row differences make smooth images' high bytes runs of zeros.
"""

from __future__ import annotations

import hashlib
import zlib

import numpy as np

from ..model.threads import parallel_map

__all__ = ["CODES_LEVEL", "CODES_STRATEGY", "STREAM_END", "DeflatedCodes", "codes_from_stored", "deflated_piece", "deflated_size", "stored_bytes",
           "stored_codes", "stored_shape"]

CODES_LEVEL = 6
"""zlib level of the codes' deflate stream (with ``Z_RLE`` the level hardly matters: matches are runs)."""
CODES_STRATEGY = zlib.Z_RLE
"""zlib strategy of the codes' deflate stream."""


def stored_shape(rank: int, planes: int, height: int, width: int, bits: int) -> tuple:
    """Shape of a stack's stored uint8 codes entry: (k, P, H, W) for 8 bits, (k, P, 2, H, W) for 16."""
    return (rank, planes, height, width) if bits == 8 else (rank, planes, 2, height, width)


def stored_codes(codes: np.ndarray) -> np.ndarray:
    """The stored form of (..., R, W) uint8 or uint16 codes: each row less the row above, modulo
    2^bits (the first row as it is); uint16 differences split into (..., 2, R, W) byte planes, high
    bytes first. Returns uint8. (A band of rows taken with the row above it gives, from its second
    row on, the whole image's stored rows: the rate search samples bands so.) ``kernels.quantise``'s
    ``stored_rows`` makes the same bytes on a device: a change of this layout changes both."""
    codes = np.asarray(codes)
    if codes.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"basis codes must be uint8 or uint16, got {codes.dtype}")
    difference = np.empty(codes.shape, codes.dtype)
    np.subtract(codes[..., 1:, :], codes[..., :-1, :], out=difference[..., 1:, :])  # unsigned: wraps
    difference[..., :1, :] = codes[..., :1, :]
    if codes.dtype == np.uint8:
        return difference
    stored = np.empty(codes.shape[:-2] + (2,) + codes.shape[-2:], np.uint8)
    np.right_shift(difference, 8, out=stored[..., 0, :, :], casting="unsafe")
    np.bitwise_and(difference, 0xFF, out=stored[..., 1, :, :], casting="unsafe")
    return stored


def codes_from_stored(stored: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of ``stored_codes`` for whole images: (k, P, H, W) uint8 (8 bits) or (k, P, 2, H, W)
    uint8 (16 bits) stored codes to (k, P, H, W) uint8 or uint16 codes (an image at a time, in threads)."""
    stored = np.asarray(stored, np.uint8)
    shape = stored.shape if bits == 8 else stored.shape[:2] + stored.shape[3:]
    kind = np.uint8 if bits == 8 else np.uint16
    codes = np.empty(shape, kind)

    def one(index: int) -> None:
        image = stored[index]
        difference = image if bits == 8 else (image[:, 0].astype(np.uint16) << 8) | image[:, 1]
        np.cumsum(difference, axis=-2, dtype=kind, out=codes[index])  # unsigned: wraps back

    parallel_map(one, range(len(codes)))
    return codes


def stored_bytes(codes: np.ndarray) -> int:
    """Bytes of (..., R, W) codes as the field file deflates them: ``deflated_size`` of ``stored_codes``."""
    return deflated_size(stored_codes(codes))


def deflated_piece(stored) -> bytes:
    """Stored codes (or any bytes) deflated as one piece of the codes' entry: raw deflate with
    ``CODES_STRATEGY``, ended by a sync flush (byte-aligned, the stream left open)."""
    compressor = zlib.compressobj(CODES_LEVEL, zlib.DEFLATED, -15, 8, CODES_STRATEGY)
    return compressor.compress(np.ascontiguousarray(stored)) + compressor.flush(zlib.Z_SYNC_FLUSH)


def deflated_size(stored: np.ndarray) -> int:
    """Bytes of stored codes in the codes' entry: the length of their ``deflated_piece``."""
    return len(deflated_piece(stored))


STREAM_END = zlib.compressobj(CODES_LEVEL, zlib.DEFLATED, -15, 8, CODES_STRATEGY).flush()
"""The empty final block that ends the codes' deflate stream after its pieces (2 bytes)."""


class DeflatedCodes:
    """Deflated pieces of stored basis images (``deflated_piece``), found by their content (a SHA-1
    digest and the length of the stored bytes): what the rate search deflated, kept for the field
    writer, which deflates an image it does not find here. Holds the latest two ``keep``s (a search's
    answer is its last measurement or, where that went over the budget, usually the one before)."""

    KEPT = 2

    def __init__(self):
        self._kept: list[dict[tuple, bytes]] = []

    @staticmethod
    def key(stored: np.ndarray) -> tuple:
        """The content key of stored codes (hashlib lets go of the GIL: callable from threads)."""
        data = np.ascontiguousarray(stored)
        return hashlib.sha1(data, usedforsecurity=False).digest(), data.nbytes

    def keep(self, pieces: dict[tuple, bytes]) -> None:
        """Hold ``pieces`` (key -> deflated piece), the oldest held measurement dropped."""
        self._kept = [dict(pieces), *self._kept][: self.KEPT]

    def held(self, key: tuple) -> bytes | None:
        """The piece held for the content ``key`` (see ``key``), or None."""
        for pieces in self._kept:
            if key in pieces:
                return pieces[key]
        return None

    def piece(self, stored: np.ndarray) -> bytes:
        """The deflated piece of ``stored``: the one held for its content, else deflated now (nothing
        hashed where nothing is held: a field loaded and saved again)."""
        if not self._kept:
            return deflated_piece(stored)
        piece = self.held(self.key(stored))
        return deflated_piece(stored) if piece is None else piece

    def __len__(self) -> int:
        """Pieces of the latest measurement."""
        return len(self._kept[0]) if self._kept else 0
