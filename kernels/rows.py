"""Stacks of long float32 rows (a light's image, a principal image) held on a Warp device: (count, M)
values in parts of whole rows, each part at most ``PART_BYTES`` (Warp's strides and a part's byte
offsets are 32-bit), written and read a block of columns at a time. The residual's normalised stacks
(``kernels.stacks``) and principal images (``kernels.quantise``) live so on CUDA while they fit."""

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = ["PART_BYTES", "DeviceRows", "gather_rows", "place_rows"]

wp.set_module_options({"enable_backward": False})

PART_BYTES = (1 << 31) - 1
"""The most bytes one device array of ``DeviceRows`` holds."""


@wp.kernel
def place_rows(block: wp.array2d(dtype=wp.float32), first_row: int, column: int, out: wp.array2d(dtype=wp.float32)):
    """out[i, column + x] = block[first_row + i, x]: a column block of every row into a part."""
    i, x = wp.tid()
    out[i, column + x] = block[first_row + i, x]


@wp.kernel
def gather_rows(part: wp.array2d(dtype=wp.float32), column: int, first_row: int, out: wp.array2d(dtype=wp.float32)):
    """out[first_row + i, x] = part[i, column + x]: a part's rows at a column block into a block of every row."""
    i, x = wp.tid()
    out[first_row + i, x] = part[i, column + x]


class DeviceRows:
    """(count, values) float32 rows held on ``device`` in parts of whole rows of at most ``PART_BYTES``
    (and at most ``part_rows`` rows: two stacks of rows of different lengths split alike)."""

    def __init__(self, count: int, values: int, device, *, part_rows: int | None = None):
        self.device = wp.get_device(device)
        self.count, self.values = int(count), int(values)
        if DeviceRows.nbytes(1, self.values) > PART_BYTES:
            raise ValueError(f"a row of {self.values} float32 values is larger than a part ({PART_BYTES} bytes)")
        self.part_rows = max(1, min(PART_BYTES // max(4 * self.values, 1), part_rows or self.count))
        self.parts = [wp.empty((min(self.part_rows, self.count - start),
                                self.values), dtype=wp.float32, device=self.device)
                      for start in range(0, self.count, self.part_rows)]

    @staticmethod
    def nbytes(count: int, values: int) -> int:
        """Device bytes that ``count`` rows of ``values`` take."""
        return 4 * int(count) * int(values)

    def place(self, block: wp.array, columns: slice) -> None:
        """Write a (count, w) device block of every row's values ``columns`` into the parts."""
        if block.shape[0] != self.count or block.shape[1] != columns.stop - columns.start:
            raise ValueError(
                f"a block of {block.shape} does not fill {self.count} rows at columns {columns.start}..{columns.stop}")
        for index, part in enumerate(self.parts):
            wp.launch(place_rows, dim=(part.shape[0], block.shape[1]),
                      inputs=[block, index * self.part_rows, columns.start], outputs=[part],
                      device=self.device)

    def block(self, columns: slice) -> wp.array:
        """(count, w) float32 device copy of every row's values ``columns``."""
        out = wp.empty((self.count, columns.stop - columns.start), dtype=wp.float32, device=self.device)
        for index, part in enumerate(self.parts):
            wp.launch(gather_rows, dim=(part.shape[0], out.shape[1]),
                      inputs=[part, columns.start, index * self.part_rows], outputs=[out],
                      device=self.device)
        return out

    def pieces(self, first: int, count: int, most: int):
        """(part's rows, rows taken, offset into the request) covering rows first .. first + count, at most
        ``most`` rows a piece."""
        done = 0
        while done < count:
            index, local = divmod(first + done, self.part_rows)
            part = self.parts[index]
            take = min(count - done, part.shape[0] - local, max(1, most))
            yield part[local : local + take], take, done
            done += take

    def float64(self, values: np.ndarray) -> wp.array:
        """A small host array as float64 on the device."""
        return wp.array(np.ascontiguousarray(values, np.float64), dtype=wp.float64, device=self.device)

    def float32(self, values: np.ndarray) -> wp.array:
        """A small host array as float32 on the device."""
        return wp.array(np.ascontiguousarray(values, np.float32), dtype=wp.float32, device=self.device)
