"""Deflate in threads: one raw deflate stream (what a zip entry holds) made of pieces compressed in
parallel, each primed with the 32 KiB before it, so the stream is as small as a serial one (as pigz
makes it). The field file's large arrays are written through it (``fieldfile``)."""

from __future__ import annotations

import zlib

from ..model.threads import NUMPY_THREADS, parallel_map

__all__ = ["PIECE_BYTES", "ParallelDeflate"]

PIECE_BYTES = 1 << 22
"""Bytes each thread deflates at a time (4 MiB: a piece's own cost, a sync flush of a few bytes and a
fresh Huffman table, is under 0.01% of it)."""
_WINDOW = 1 << 15  # deflate's window: a piece may refer this far back into the one before


class ParallelDeflate:
    """A stand-in for ``zlib.compressobj(level, zlib.DEFLATED, -15, 8, strategy)``: ``compress(data)`` returns the
    deflated bytes of every whole group of pieces gathered so far, ``flush()`` the rest and the final
    block. The output inflates (``zlib.decompressobj(-15)``) to the input, bit for bit, and does not
    depend on how the input was split into ``compress`` calls."""

    def __init__(self, level: int = zlib.Z_DEFAULT_COMPRESSION, *, strategy: int = zlib.Z_DEFAULT_STRATEGY, threads: int = NUMPY_THREADS):
        self.level = level
        self.strategy = strategy
        self.threads = max(1, int(threads))
        self.pending = bytearray()
        self.before = b""  # the 32 KiB of input before the pending bytes

    def _piece(self, job: tuple) -> bytes:
        data, dictionary = job
        compressor = self._compressor(dictionary)
        return compressor.compress(data) + compressor.flush(zlib.Z_SYNC_FLUSH)  # byte-aligned, not the last block

    def _compressor(self, dictionary: bytes = b""):
        if dictionary:
            return zlib.compressobj(self.level, zlib.DEFLATED, -15, 8, self.strategy, zdict=dictionary)
        return zlib.compressobj(self.level, zlib.DEFLATED, -15, 8, self.strategy)

    def _deflate(self, end: int) -> bytes:
        """Deflate ``pending[:end]`` in pieces of ``PIECE_BYTES``, in threads (one copy of the input:
        the pieces are views of it)."""
        with memoryview(self.pending) as pending:
            data = bytes(pending[:end])
        del self.pending[:end]
        view = memoryview(data)
        starts = range(0, len(data), PIECE_BYTES)
        jobs = [(view[start : start + PIECE_BYTES], self._window(data, start)) for start in starts]
        self.before = (self.before + data[-_WINDOW:])[-_WINDOW:]
        return b"".join(parallel_map(self._piece, jobs))

    def _window(self, data: bytes, start: int) -> bytes:
        """The 32 KiB of input before ``data[start]`` (reaching back into ``before``): copies no more than that."""
        if start >= _WINDOW:
            return data[start - _WINDOW : start]
        return (self.before + data[:start])[-_WINDOW:]

    def compress(self, data) -> bytes:
        self.pending += data
        group = PIECE_BYTES * self.threads
        whole = len(self.pending) // group * group
        return self._deflate(whole) if whole else b""

    def flush(self) -> bytes:
        tail = self._deflate(len(self.pending)) if self.pending else b""
        return tail + self._compressor().flush()  # an empty final block ends the stream
