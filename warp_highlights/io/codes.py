"""How a field file stores a low-rank stack's basis codes (format version 5): a row-difference
predictor in NumPy, then one Blosc chunk per basis image. The rate search counts a basis image's
bytes with the same functions, so the bytes a size budget holds to are the bytes the file holds.

Predictor (``stored_codes``): a basis image's (P, H, W) codes of 8 or 16 bits less the row above
(the first row as it is), modulo 2^bits, read as signed differences and mapped to unsigned ones by
their magnitude (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...: "zigzag"); 16-bit differences then split
into two byte planes, high bytes first: (P, H, W) or (P, 2, H, W) uint8. Smooth basis images have
small differences, so the high plane is nearly all zeros, and the low plane's bytes cluster at the
small values an entropy coder takes in few bits. (Without the zigzag, a small negative difference
has the high byte 0xFF, a positive one 0x00: the high plane repeats each difference's sign, which
the low byte already holds; with it, 16-bit codes take a fifth fewer bytes.)

Coder (``compressed_chunk``): each image's stored bytes are one Blosc chunk (``numcodecs.Blosc``:
Zstandard at level ``CODES_LEVEL`` after Blosc's bit shuffle, which gathers bit k of every byte of a
block: the sparse low bits of small differences into few runs, the high bits' zeros into long ones).
The field file's codes entry, ``residual/Y_codes.npy.blosc`` (stored in the zip without compression
of its own), is the chunk of the ``.npy`` header of the whole (k, P, [2,] H, W) uint8 array and then
each image's chunk; ``residual/Y_codes.lengths.npy`` gives each chunk's bytes. Decoded one after
another, the chunks are that ``.npy`` file. A chunk per image lets the images be compressed in
threads and lets the rate search measure each image's exact share of the entry; ``CompressedCodes``
keeps the chunks that search made last, and the field writer stores those rather than compressing
the same codes again. Against zlib's run-length-only deflate of the row differences (format 4),
the 16-bit codes of the dome sample and the 250-light 480x270 donut take 76% and 82-90% of the
bytes, the 8-bit statue's 96-97%, compressed 1.6-3.4 times faster on one thread
(``benchmarks/bench_codes.py``).

Format version 4 stored the row differences without the zigzag (``codes_from_differences`` reads
them) in a deflated ``.npy`` entry, which the zip reader inflates as any other.
"""

from __future__ import annotations

import hashlib
import threading

import numpy as np

from ..model.threads import parallel_map, submit

__all__ = ["CODES_LEVEL", "CompressedCodes", "chunk_size", "codes_from_differences", "codes_from_stored",
           "compressed_chunk", "stored_bytes",
           "stored_codes", "stored_shape"]

CODES_LEVEL = 1
"""Zstandard level inside each basis image's Blosc chunk: on the samples' codes, higher levels gave about the
same bytes in several times the seconds."""


def stored_shape(rank: int, planes: int, height: int, width: int, bits: int) -> tuple:
    """Shape of a stack's stored uint8 codes entry: (k, P, H, W) for 8 bits, (k, P, 2, H, W) for 16."""
    return (rank, planes, height, width) if bits == 8 else (rank, planes, 2, height, width)


def stored_codes(codes: np.ndarray) -> np.ndarray:
    """The stored form of (..., R, W) uint8 or uint16 codes: each row less the row above, modulo
    2^bits (the first row as it is), zigzag-mapped (signed d to 2d for d >= 0, -2d - 1 below);
    uint16 values split into (..., 2, R, W) byte planes, high bytes first. Returns uint8. (A band of
    rows taken with the row above it gives, from its second row on, the whole image's stored rows:
    the rate search samples bands so.) ``kernels.quantise``'s ``stored_rows`` makes the same bytes
    on a device: a change of this layout changes both."""
    codes = np.asarray(codes)
    if codes.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"basis codes must be uint8 or uint16, got {codes.dtype}")
    difference = np.empty(codes.shape, codes.dtype)
    np.subtract(codes[..., 1:, :], codes[..., :-1, :], out=difference[..., 1:, :])  # unsigned: wraps
    difference[..., :1, :] = codes[..., :1, :]
    signed = difference.view(np.int8 if codes.dtype == np.uint8 else np.int16)
    zigzag = np.left_shift(difference, 1)  # 2d, modulo 2^bits ...
    # ... its bits flipped where d < 0: -2d - 1
    zigzag ^= np.right_shift(signed, 8 * codes.dtype.itemsize - 1).view(codes.dtype)
    if codes.dtype == np.uint8:
        return zigzag
    stored = np.empty(codes.shape[:-2] + (2,) + codes.shape[-2:], np.uint8)
    np.right_shift(zigzag, 8, out=stored[..., 0, :, :], casting="unsafe")
    np.bitwise_and(zigzag, 0xFF, out=stored[..., 1, :, :], casting="unsafe")
    return stored


def codes_from_stored(stored: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of ``stored_codes`` for whole images: (k, P, H, W) uint8 (8 bits) or (k, P, 2, H, W)
    uint8 (16 bits) stored codes to (k, P, H, W) uint8 or uint16 codes (an image at a time, in threads)."""
    return _summed_rows(stored, bits, zigzag=True)


def codes_from_differences(stored: np.ndarray, bits: int) -> np.ndarray:
    """The codes of a format-4 entry (row differences modulo 2^bits in byte planes, no zigzag), in
    ``codes_from_stored``'s shapes."""
    return _summed_rows(stored, bits, zigzag=False)


def _summed_rows(stored: np.ndarray, bits: int, *, zigzag: bool) -> np.ndarray:
    stored = np.asarray(stored, np.uint8)
    shape = stored.shape if bits == 8 else stored.shape[:2] + stored.shape[3:]
    kind = np.uint8 if bits == 8 else np.uint16
    codes = np.empty(shape, kind)

    def one(index: int) -> None:
        image = stored[index]
        value = image.copy() if bits == 8 else (image[:, 0].astype(np.uint16) << 8) | image[:, 1]
        if zigzag:  # 2d -> d, -2d - 1 -> d (modulo 2^bits)
            low = np.bitwise_and(value, 1)
            np.right_shift(value, 1, out=value)
            value ^= np.negative(low)  # 0 or all ones
        np.cumsum(value, axis=-2, dtype=kind, out=codes[index])  # unsigned: wraps back

    parallel_map(one, range(len(codes)))
    return codes


def codes_codec():
    """The ``numcodecs.Blosc`` codec of the codes' chunks (Zstandard at ``CODES_LEVEL``, bit shuffle)."""
    from numcodecs import Blosc  # the codec, imported where codes are written, measured or read

    return Blosc(cname="zstd", clevel=CODES_LEVEL, shuffle=Blosc.BITSHUFFLE)


def compressed_chunk(stored) -> bytes:
    """Stored codes (or any bytes) as one Blosc chunk of the codes' entry (``codes_codec``), made on a
    thread other than the main one: there Blosc compresses on the calling thread alone and lets go of
    the GIL, and a chunk is the same bytes each time (on the main thread, Blosc's own threads place the
    chunk's blocks in the order they finish)."""
    if threading.current_thread() is threading.main_thread():
        return submit(_encoded, stored).result()
    return _encoded(stored)


def _encoded(stored) -> bytes:
    return bytes(codes_codec().encode(np.ascontiguousarray(stored).reshape(-1).view(np.uint8)))


def chunk_size(stored: np.ndarray) -> int:
    """Bytes of stored codes in the codes' entry: the length of their ``compressed_chunk``."""
    return len(compressed_chunk(stored))


def stored_bytes(codes: np.ndarray) -> int:
    """Bytes of (..., R, W) codes as the field file stores them: ``chunk_size`` of ``stored_codes``."""
    return chunk_size(stored_codes(codes))


class CompressedCodes:
    """Chunks of stored basis images (``compressed_chunk``), found by their content (a SHA-1 digest
    and the length of the stored bytes): what the rate search compressed, kept for the field writer,
    which compresses an image it does not find here. Holds the latest two ``keep``s (a search's answer
    is its last measurement or, where that went over the budget, usually the one before)."""

    KEPT = 2

    def __init__(self):
        self._kept: list[dict[tuple, bytes]] = []

    @staticmethod
    def key(stored: np.ndarray) -> tuple:
        """The content key of stored codes (hashlib lets go of the GIL: callable from threads)."""
        data = np.ascontiguousarray(stored)
        return hashlib.sha1(data, usedforsecurity=False).digest(), data.nbytes

    def keep(self, chunks: dict[tuple, bytes]) -> None:
        """Hold ``chunks`` (key -> chunk), the oldest held measurement dropped."""
        self._kept = [dict(chunks), *self._kept][: self.KEPT]

    def held(self, key: tuple) -> bytes | None:
        """The chunk held for the content ``key`` (see ``key``), or None."""
        for chunks in self._kept:
            if key in chunks:
                return chunks[key]
        return None

    def chunk(self, stored: np.ndarray) -> bytes:
        """The chunk of ``stored``: the one held for its content, else compressed now (nothing hashed
        where nothing is held: a field loaded and saved again)."""
        if not self._kept:
            return compressed_chunk(stored)
        chunk = self.held(self.key(stored))
        return compressed_chunk(stored) if chunk is None else chunk

    def __len__(self) -> int:
        """Chunks of the latest measurement."""
        return len(self._kept[0]) if self._kept else 0
