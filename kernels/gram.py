"""Products of a light stack's column blocks on a Warp device, for the residual's principal images and
weights (``model.residual``): sums A B^T of float32 rows accumulated in float64 (Gram matrices and
normal equations), and projections P B of float64 matrices onto float32 blocks, kept as float32.

A block's products of float32 values are exact in float64, so the results equal NumPy's float64
products but for the order of the sums (about 1e-16 of their size). The order is fixed: thread block
``part`` of a sum adds depth tiles part, part + PARTS, ... into its own float64 partial sum (no
atomics), and ``CrossSum.value`` adds the PARTS partial sums on the host, so a fit gives the same
bytes every run. A Gram matrix (``add(a)``) computes the tiles on and above the diagonal only.

``tile_matmul`` runs Warp's scalar GEMM (module option ``enable_mathdx_gemm`` off): cuBLASDx's
link-time compile of these mixed float32/float64 tiles takes minutes for a saving of seconds per
1080p fit. On the CPU the same kernels run (the tests' reference), but the host's BLAS is faster
there, so the package sends only CUDA work here.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .quantise import DeviceBasis

__all__ = ["HELD_SHARE", "PARTS", "TILE_DEPTH", "TILE_ROWS", "CrossSum", "DeviceProducts"]

wp.set_module_options({"enable_backward": False, "enable_mathdx_gemm": False})

TILE_ROWS = 32
"""Rows of A and B (lights, basis images) a tile holds; a stack of 250 lights is 8 tiles high."""
TILE_DEPTH = 64
"""Values along a row a tile holds."""
PARTS = 32
"""Partial sums a product keeps per output tile: thread blocks along the depth (8 x 8 x 32 for a
250-light Gram matrix, enough to fill an H100's 132 multiprocessors)."""
_BLOCK_DIM = 64
HELD_SHARE = 0.5
"""``holds``: the residual's normalised stacks (``kernels.stacks``) and then each stack's principal images
(``held_directions``) are kept on a CUDA device while each takes at most this share of its free memory
(a 3840x2160 capture of 100 lights: 10 GB for both stacks, as much for their principal images; 1,000
lights at 1920x1080: 25 GB each), so that the products read them there and the rate search
quantises there; else they are uploaded a block at a time and quantised on the host."""


@wp.func
def _single(value: wp.float64) -> wp.float32:
    return wp.float32(value)


@wp.kernel
def cross_tiles(a: wp.array2d(dtype=wp.float32), b: wp.array2d(dtype=wp.float32), symmetric: int,
                partials: wp.array2d(dtype=wp.float64)):
    """partials[part] += a b^T over depth tiles part, part + PARTS, ...: thread block (i, j, part) sums
    row tile i of a against row tile j of b (loads beyond the arrays read zeros) into its partial
    tile; ``symmetric`` (b is a): tiles below the diagonal are skipped."""
    i, j, part = wp.tid()
    if symmetric != 0 and j < i:
        return
    total = wp.tile_zeros(shape=(TILE_ROWS, TILE_ROWS), dtype=wp.float64)
    depth = a.shape[1]
    column = part * TILE_DEPTH
    while column < depth:
        left = wp.tile_load(a, shape=(TILE_ROWS, TILE_DEPTH), offset=(i * TILE_ROWS, column))
        right = wp.tile_load(b, shape=(TILE_ROWS, TILE_DEPTH), offset=(j * TILE_ROWS, column))
        wp.tile_matmul(left, wp.tile_transpose(right), total)
        column += PARTS * TILE_DEPTH
    rows = partials.shape[0] // PARTS
    offset = (part * rows + i * TILE_ROWS, j * TILE_ROWS)
    wp.tile_store(partials, wp.tile_load(partials, shape=(TILE_ROWS, TILE_ROWS), offset=offset) + total, offset=offset)


@wp.kernel
def project_tiles(matrix: wp.array2d(dtype=wp.float64), block: wp.array2d(dtype=wp.float32), inner_tiles: int,
                  out: wp.array2d(dtype=wp.float32)):
    """out = matrix @ block, float64 sums kept as float32: thread block (i, j) makes out's tile (i, j)."""
    i, j = wp.tid()
    total = wp.tile_zeros(shape=(TILE_ROWS, TILE_DEPTH), dtype=wp.float64)
    for step in range(inner_tiles):
        left = wp.tile_load(matrix, shape=(TILE_ROWS, TILE_ROWS), offset=(i * TILE_ROWS, step * TILE_ROWS))
        right = wp.tile_load(block, shape=(TILE_ROWS, TILE_DEPTH), offset=(step * TILE_ROWS, j * TILE_DEPTH))
        wp.tile_matmul(left, right, total)
    wp.tile_store(out, wp.tile_map(_single, total), offset=(i * TILE_ROWS, j * TILE_DEPTH))


def _tiles(count: int, size: int) -> int:
    return max(1, -(-count // size))


class CrossSum:
    """A running (rows, columns) float64 sum of a b^T on the device: ``add`` a pair of uploaded blocks
    (b None: a itself, a Gram matrix), ``value`` the sum so far (one copy to the host)."""

    def __init__(self, rows: int, columns: int, device):
        self.device = device
        self.shape = (rows, columns)
        self.padded = (_tiles(rows, TILE_ROWS) * TILE_ROWS, _tiles(columns, TILE_ROWS) * TILE_ROWS)
        self.partials = wp.zeros((PARTS * self.padded[0], self.padded[1]), dtype=wp.float64, device=device)
        self.symmetric: bool | None = None

    def add(self, a: wp.array, b: wp.array | None = None) -> None:
        symmetric = b is None
        b = a if b is None else b
        if (a.shape[0], b.shape[0]) != self.shape or a.shape[1] != b.shape[1]:
            raise ValueError(f"blocks of {a.shape} and {b.shape} do not add to a sum of {self.shape}")
        if self.symmetric is not None and self.symmetric != symmetric:
            raise ValueError("a sum is either of a block with itself (a Gram matrix) or of pairs of blocks, not both")
        self.symmetric = symmetric
        wp.launch_tiled(cross_tiles, dim=[_tiles(a.shape[0], TILE_ROWS), _tiles(b.shape[0], TILE_ROWS), PARTS],
                        inputs=[a, b, int(symmetric)], outputs=[self.partials], block_dim=_BLOCK_DIM,
                        device=self.device)

    def value(self) -> np.ndarray:
        """The (rows, columns) float64 sum: the partial sums added in a fixed order."""
        total = self.partials.numpy().reshape(PARTS, *self.padded).sum(axis=0)[: self.shape[0], : self.shape[1]]
        if self.symmetric:
            upper = np.triu(total)
            total = upper + np.triu(total, 1).T
        return np.ascontiguousarray(total)


class DeviceProducts:
    """Products of (rows, w) float32 column blocks on ``device``, the blocks copied there one at a time
    (``upload``): running sums of a b^T (``cross_sum``) and projections through a float64 matrix.

    On CUDA the blocks go through two page-locked host buffers used in turn: a block (a strided view
    of the stack will do) is copied into one while the other's copy to the device runs, and
    projections come back through them. A copy from page-locked memory runs several times faster than
    one from pageable memory (benchmarks/bench_transfer.py), and one thread fills a buffer faster than
    many: the host's copies are one thread's."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._buffers: list[wp.array | None] = [None, None]
        self._copied: list[wp.Event | None] = [None, None]  # recorded after a buffer's last copy to the device
        self._matrix: tuple = (None, None)  # the last projection matrix (a host copy) and its device copy
        self._turn = 0
        # the ``staging`` array not yet uploaded, and its buffer
        self._staged: tuple[int, wp.array, np.ndarray] | None = None

    def staging(self, shape: tuple) -> np.ndarray:
        """A float32 host array of ``shape`` to fill and then ``upload``, before any other upload or
        projection: on CUDA in the next page-locked buffer, so that the upload copies nothing on the host."""
        rows, width = shape
        if not self.device.is_cuda or rows * width == 0:
            return np.empty(shape, np.float32)
        which, buffer = self._buffer(rows * width)
        array = buffer.numpy()[: rows * width].reshape(rows, width)
        self._staged = (which, buffer, array)
        return array

    def _buffer(self, values: int) -> tuple[int, wp.array]:
        """(which, buffer): the next page-locked float32 buffer of at least ``values``, its last copy done."""
        if self._staged is not None:
            raise RuntimeError("a staging array must be uploaded before the next upload or projection")
        which, self._turn = self._turn, self._turn ^ 1
        if self._copied[which] is not None:
            wp.synchronize_event(self._copied[which])
        if self._buffers[which] is None or self._buffers[which].size < values:
            self._buffers[which] = wp.empty(values, dtype=wp.float32, device="cpu", pinned=True)
        return which, self._buffers[which]

    def upload(self, block: np.ndarray) -> wp.array:
        """A (rows, w) block as float32 on the device."""
        block = np.asarray(block)
        if not self.device.is_cuda or block.ndim != 2 or block.size == 0:
            return wp.array(np.ascontiguousarray(block, np.float32), dtype=wp.float32, device=self.device)
        rows, width = block.shape
        staged, self._staged = self._staged, None
        if staged is not None and block is staged[2]:
            which, buffer = staged[0], staged[1]  # filled in place
        elif staged is not None:
            raise RuntimeError("a staging array must be uploaded before the next upload or projection")
        else:
            which, buffer = self._buffer(block.size)
            np.copyto(buffer.numpy()[: block.size].reshape(rows, width), block, casting="unsafe")
        out = wp.empty((rows, width), dtype=wp.float32, device=self.device)
        wp.copy(out, buffer, count=block.size)  # asynchronous from page-locked memory
        self._copied[which] = self.device.stream.record_event(self._copied[which])  # one event a buffer, recorded again
        return out

    def cross_sum(self, rows: int, columns: int) -> CrossSum:
        return CrossSum(rows, columns, self.device)

    def holds(self, nbytes: int) -> bool:
        """Whether ``nbytes`` more may be held on the device: at most ``HELD_SHARE`` of a CUDA device's free
        memory (the CPU device, the tests' reference, holds anything)."""
        return not self.device.is_cuda or nbytes <= HELD_SHARE * self.device.free_memory

    def held_directions(self, count: int, shape: tuple) -> DeviceBasis | None:
        """A ``DeviceBasis`` for ``count`` principal images of ``shape`` (H, W, P), which ``project`` fills
        through ``keep``; None where they may not be held (``holds``)."""
        return (DeviceBasis(count, shape, self.device) if self.holds(DeviceBasis.nbytes(count, int(np.prod(shape))))
                else None)

    def project(self, matrix: np.ndarray, block: np.ndarray, out: np.ndarray | None = None, *,
                keep: DeviceBasis | None = None,
                columns: slice | None = None, host: bool = True) -> np.ndarray | None:
        """(r, w) float32 ``matrix`` (r, n) float64 @ ``block`` (n, w) float32 (on the host, or on the device
        already), summed in float64; written into ``out`` (a view will do) when given, and into
        ``keep``'s images at ``columns`` when given. ``host=False`` (with ``keep``): nothing comes back.
        The matrix is uploaded once for a run of calls with equal matrices (the blocks of one projection)."""
        if not host and keep is None:
            raise ValueError("a projection that does not come back to the host must be kept on the device")
        matrix = np.asarray(matrix, np.float64)
        if (self._matrix[0] is None or self._matrix[0].shape != matrix.shape
            or not np.array_equal(self._matrix[0], matrix)):
            self._matrix = (matrix.copy(), wp.array(np.ascontiguousarray(matrix), dtype=wp.float64, device=self.device))
        left = self._matrix[1]
        right = block if isinstance(block, wp.array) else self.upload(block)
        if left.shape[1] != right.shape[0]:
            raise ValueError(f"a ({left.shape[0]}, {left.shape[1]}) matrix cannot map a block of {right.shape[0]} rows")
        shape = (left.shape[0], right.shape[1])
        if out is not None and tuple(out.shape) != shape:
            raise ValueError(f"a projection of {shape} cannot go into {tuple(out.shape)}")
        product = wp.empty(shape, dtype=wp.float32, device=self.device)
        wp.launch_tiled(project_tiles, dim=[_tiles(left.shape[0], TILE_ROWS), _tiles(right.shape[1], TILE_DEPTH)],
                        inputs=[left, right, _tiles(left.shape[1], TILE_ROWS)], outputs=[product], block_dim=_BLOCK_DIM,
                        device=self.device)
        if keep is not None:
            if columns is None:
                raise ValueError("a projection kept on the device needs its columns")
            keep.place(product, columns)
        if not host:
            return None
        if not self.device.is_cuda or product.size == 0:
            result = product.numpy()
        else:
            which, buffer = self._buffer(product.size)
            wp.copy(buffer, product, count=product.size)
            wp.synchronize_stream(self.device.stream)
            result = buffer.numpy()[: product.size].reshape(shape)
        if out is None:
            return np.array(result)  # its own copy: the buffer is used again
        np.copyto(out, result, casting="unsafe")
        return out

