"""Large arrays between host and device memory at the copy's speed.

``wp.array.numpy()`` copies a CUDA array into a fresh NumPy array, and the copy then stops at every
page of it the first time it writes there (the kernel maps the page), so a large stack comes down
slowly. ``to_host`` first writes every page of the new array from threads, which the kernel maps in
parallel, then copies into it, several times faster in all.

A band of rows of an (n, H, W[, C]) stack is n separate runs of host memory: ``rows_up`` and
``rows_down`` copy each run straight between host and device memory (no contiguous copy of the band
on the host first).

From ``STAGED_MIN_BYTES`` on (a 250-light 1080p stack and larger), a CUDA transfer goes through a few
page-locked buffers (``Staging``): threads copy the host memory into one while the device copies
another. Copies from and to page-locked memory run several times faster than from and to pageable
memory (``benchmarks/bench_transfer.py`` measures both), but page-locking memory costs time per GiB
too, so only a few small buffers are locked, once per process, and a large stack never is.
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp

from warp_highlights.model import threads

__all__ = ["STAGED_MIN_BYTES", "STAGING_BYTES", "STAGING_SLOTS", "Staging", "as_half", "rows_down", "rows_up",
           "to_host"]

STAGED_MIN_BYTES = 1 << 30
"""Transfers of this many bytes or more (1 GiB) go through ``Staging``: a process whose transfers are
all smaller (a 480x270 capture's, 0.4 GB) would pay more for locking the buffers than they save at the
copy rates ``benchmarks/bench_transfer.py`` measures."""
STAGING_BYTES = 1 << 26
"""Bytes of each page-locked staging buffer (64 MiB: a copy into it split over the threads is a few MB each)."""
STAGING_SLOTS = 3
"""Staging buffers (at least 2): going up, the host fills one while the device copies the others;
coming down, the host empties one while the device fills the next."""
_PART_BYTES = 1 << 22  # a host copy into or out of a buffer is split into parts of this many bytes, one per thread


def to_host(array) -> np.ndarray:
    """A Warp array as a NumPy array in host memory (a CPU array's own view, as ``numpy()`` gives it).
    A large contiguous CUDA array of a scalar type is copied into pages written from threads first
    (``mapped_empty``), through ``Staging`` from ``STAGED_MIN_BYTES``."""
    if not isinstance(array, wp.array):
        return np.asarray(array)
    if not (array.device.is_cuda
            or STAGE_ON_CPU) or not wp.types.type_is_scalar(array.dtype) or not array.is_contiguous \
            or array.capacity < threads.PREFAULT_BYTES or threads.NUMPY_THREADS == 1:
        return array.numpy()
    host = threads.mapped_empty(array.shape, wp.dtype_to_numpy(array.dtype))
    staging = Staging.of(array.device) if staged(array.device, host.nbytes) else None
    if staging is not None:
        staging.down(_runs(array.ptr, host))
        return host
    wp.copy(wp.array(host, dtype=array.dtype, device="cpu", copy=False), array)
    return host


def rows_up(host: np.ndarray, device, *, whole_bytes: int = 0, rows=None) -> wp.array:
    """An (n, ...) host array (a band of a stack will do: each ``host[i]`` contiguous) as a new
    contiguous array on ``device``, of the same scalar type: one copy per ``host[i]``, or one for all
    where the whole is contiguous; through ``Staging`` from ``STAGED_MIN_BYTES`` (of this array, or of
    ``whole_bytes``: the whole stack whose band this is, which goes up band by band). ``rows``: only
    these ``host[i]``, in their order (never gathered on the host first)."""
    host = np.asarray(host)
    kind = wp.dtype_from_numpy(host.dtype)
    if rows is not None:
        if host.ndim < 2:
            raise ValueError(
                f"rows of an (n, ...) array of two or more axes are sent up, not of a {host.ndim}-axis one")
        rows = np.asarray(rows, np.int64).reshape(-1)
        out = wp.empty((len(rows),) + host.shape[1:], dtype=kind, device=device)
        if not len(rows):
            return out
        row_bytes = host[0].nbytes
        staging = Staging.of(out.device) if staged(out.device, max(len(rows) * row_bytes, whole_bytes)) else None
        if staging is not None and host[0].flags.c_contiguous:
            staging.up([(out.ptr + i * row_bytes, _bytes_of(host[row])) for i, row in enumerate(rows.tolist())])
            return out
        for i, row in enumerate(rows.tolist()):
            wp.copy(out[i], wp.array(np.ascontiguousarray(host[row]), dtype=kind, device="cpu", copy=False))
        return out
    out = wp.empty(host.shape, dtype=kind, device=device)
    staging = Staging.of(out.device) if len(host) and staged(out.device, max(host.nbytes, whole_bytes)) else None
    if staging is not None and (host.flags.c_contiguous or (host.ndim > 1 and host[0].flags.c_contiguous)):
        staging.up(_runs(out.ptr, host))
        return out
    if host.flags.c_contiguous or len(host) == 0:
        wp.copy(out, wp.array(np.ascontiguousarray(host), dtype=kind, device="cpu", copy=False))
        return out
    for i in range(len(host)):
        wp.copy(out[i], wp.array(np.ascontiguousarray(host[i]), dtype=kind, device="cpu", copy=False))
    return out


def rows_down(array: wp.array, out: np.ndarray, *, whole_bytes: int = 0) -> np.ndarray:
    """Copy a contiguous (n, ...) device array into the host array ``out`` of its shape and type (a band
    of a stack will do: each ``out[i]`` contiguous), a copy per ``out[i]`` (through ``Staging`` from
    ``STAGED_MIN_BYTES`` of ``out`` or of ``whole_bytes``, as ``rows_up``); returns ``out``. Copies into
    pages not written yet stop at each: give ``out`` from ``mapped_empty``."""
    if tuple(out.shape) != tuple(array.shape) or out.dtype != wp.dtype_to_numpy(array.dtype) or not array.is_contiguous:
        raise ValueError(
            f"a contiguous {array.dtype.__name__} {array.shape} array cannot come down into {out.dtype} {out.shape}")
    if len(out) and not out[0].flags.c_contiguous:  # the rows share their strides: one is all of them
        raise ValueError("each row of the host array must be contiguous")
    staging = Staging.of(array.device) if len(out) and staged(array.device, max(out.nbytes, whole_bytes)) else None
    if staging is not None and (out.flags.c_contiguous or out.ndim > 1):
        staging.down(_runs(array.ptr, out))
        return out
    if out.flags.c_contiguous or len(out) == 0:
        wp.copy(wp.array(out, dtype=array.dtype, device="cpu", copy=False), array)
        wp.synchronize_device(array.device)
        return out
    for i in range(len(out)):
        wp.copy(wp.array(out[i], dtype=array.dtype, device="cpu", copy=False), array[i])
    wp.synchronize_device(array.device)
    return out


HALF_MAX = wp.constant(65504.0)
"""The largest finite float16: ``as_half`` clamps to it (a value beyond stays finite, not inf)."""


@wp.kernel
def _to_half(source: wp.array2d(dtype=float), out: wp.array2d(dtype=wp.float16)):
    i, j = wp.tid()
    out[i, j] = wp.float16(wp.clamp(source[i, j], -HALF_MAX, HALF_MAX))


def as_half(array: wp.array) -> wp.array:
    """A contiguous float32 (n, ...) array as a new float16 one on its device: clamped to +-``HALF_MAX``,
    then rounded to nearest as NumPy's ``astype`` rounds; half the bytes to bring down. One launch
    over (n, the rest)."""
    if array.dtype != wp.float32 or not array.is_contiguous:
        raise ValueError(f"as_half takes a contiguous float32 array, got {array.dtype.__name__}")
    out = wp.empty(array.shape, dtype=wp.float16, device=array.device)
    if array.size:
        rows = array.shape[0] if array.ndim > 1 else 1
        flat = (rows, array.size // rows)
        wp.launch(_to_half, dim=flat, inputs=[array.reshape(flat)], outputs=[out.reshape(flat)], device=array.device)
    return out


def staged(device, nbytes: int) -> bool:
    """Whether a transfer of ``nbytes`` to or from ``device`` goes through ``Staging`` (on CUDA; the
    CPU's tests lower ``STAGED_MIN_BYTES`` and set ``STAGE_ON_CPU``)."""
    return (device.is_cuda or STAGE_ON_CPU) and nbytes >= STAGED_MIN_BYTES


STAGE_ON_CPU = False
"""Tests only: stage CPU transfers too (the same chunking and order, with plain buffers)."""


def _bytes_of(host: np.ndarray) -> np.ndarray:
    """A contiguous host array's bytes as a flat uint8 view."""
    return host.reshape(-1).view(np.uint8)


class Staging:
    """``STAGING_SLOTS`` page-locked host buffers of ``STAGING_BYTES`` for one device, made on first use
    and kept for the process (``of``). ``up`` and ``down`` move runs of host bytes to and from device
    addresses: the host's part of each buffer in threads (``parallel_map``), the device's as
    asynchronous copies on the device's stream (read once a transfer), each buffer touched again only
    once its last copy has ended (an event kept per buffer, across transfers and after an error or
    Ctrl-C). One transfer at a time per device. On the CPU (tests) the same steps run with plain buffers."""

    _made: dict = {}
    _made_lock = threading.Lock()

    def __init__(self, device, *, slot_bytes: int | None = None, slots: int | None = None):
        slot_bytes = STAGING_BYTES if slot_bytes is None else int(slot_bytes)
        slots = STAGING_SLOTS if slots is None else int(slots)
        if slots < 2 or slot_bytes < 1:
            raise ValueError(f"staging needs at least 2 buffers of at least a byte, got {slots} of {slot_bytes}")
        self.device = wp.get_device(device)
        pinned = self.device.is_cuda
        self.buffers = [wp.empty(slot_bytes, dtype=wp.uint8, device="cpu", pinned=pinned) for _ in range(slots)]
        self.views = [buffer.numpy() for buffer in self.buffers]
        self.events = [None] * slots  # each buffer's last copy
        self.slot_bytes = slot_bytes
        self.lock = threading.Lock()
        self._stream = None

    @classmethod
    def of(cls, device) -> Staging | None:
        """The device's staging buffers, made on first use; None where they cannot be page-locked (a
        memory-lock limit): the transfers then go as they went without."""
        device = wp.get_device(device)
        with cls._made_lock:
            if device.alias not in cls._made:
                try:
                    cls._made[device.alias] = cls(device)
                except (RuntimeError, MemoryError):
                    cls._made[device.alias] = None
            return cls._made[device.alias]

    def _chunks(self, runs: list) -> list:
        """[(slot bytes used, [(device address, host bytes, offset in the slot)])]: the runs cut into
        pieces that fill the buffers one after another."""
        chunks, pieces, used = [], [], 0
        for address, data in runs:
            start = 0
            while start < data.size:
                size = min(data.size - start, self.slot_bytes - used)
                pieces.append((address + start, data[start : start + size], used))
                used += size
                start += size
                if used == self.slot_bytes:
                    chunks.append((used, pieces))
                    pieces, used = [], 0
        if pieces:
            chunks.append((used, pieces))
        return chunks

    def _device_view(self, address: int, size: int) -> wp.array:
        return wp.array(ptr=address, dtype=wp.uint8, shape=(size,), device=self.device)

    def _slot_view(self, slot: int, offset: int, size: int) -> wp.array:
        return self.buffers[slot][offset : offset + size]

    def _host_copies(self, copies: list) -> None:
        """(destination, source) byte arrays copied in threads, about ``_PART_BYTES`` a task: a large
        array cut in parts, small ones (a band's rows of a light: a few hundred kB) a few to a task."""
        tasks, task, size = [], [], 0
        for out, data in copies:
            for start in range(0, data.size, _PART_BYTES):
                task.append((out[start : start + _PART_BYTES], data[start : start + _PART_BYTES]))
                size += task[-1][1].size
                if size >= _PART_BYTES:
                    tasks.append(task)
                    task, size = [], 0
        if task:
            tasks.append(task)
        threads.parallel_map(lambda parts: [np.copyto(*part) for part in parts], tasks)

    @staticmethod
    def _device_copies(pieces: list) -> list:
        """(device address, offset in the slot, bytes) of each copy a chunk's pieces need: pieces next to
        each other both on the device and in the slot (the rows of a band of consecutive lights) in one."""
        copies = []
        for address, data, offset in pieces:
            if copies and copies[-1][0] + copies[-1][2] == address and copies[-1][1] + copies[-1][2] == offset:
                copies[-1] = (copies[-1][0], copies[-1][1], copies[-1][2] + data.size)
            else:
                copies.append((address, offset, data.size))
        return copies

    def _copy(self, destination: wp.array, source: wp.array) -> None:
        wp.copy(destination, source, stream=self._stream)

    def _record(self, slot: int) -> None:
        self.events[slot] = self._stream.record_event() if self._stream is not None else None

    def _wait(self, slot: int) -> None:
        """Until the buffer's last copy has ended."""
        event, self.events[slot] = self.events[slot], None
        if event is not None:
            wp.synchronize_event(event)

    def _settle(self) -> None:
        """Every buffer's copies ended (also when a transfer stopped midway), the stream let go."""
        try:
            for slot in range(len(self.buffers)):
                self._wait(slot)
        finally:
            self._stream = None

    def up(self, runs: list) -> None:
        """Copy each (device address, host uint8 bytes) run to the device; returns once the copies have
        ended (the host bytes may then change, and later launches on the stream see them)."""
        with self.lock:
            self._stream = self.device.stream if self.device.is_cuda else None
            try:
                for index, (_, pieces) in enumerate(self._chunks(runs)):
                    slot = index % len(self.buffers)
                    self._wait(slot)  # the buffer's last copy up has ended
                    self._host_copies([(self.views[slot][offset : offset + data.size], data)
                                       for _, data, offset in pieces])
                    for address, offset, size in self._device_copies(pieces):
                        self._copy(self._device_view(address, size), self._slot_view(slot, offset, size))
                    self._record(slot)
            finally:
                self._settle()

    def down(self, runs: list) -> None:
        """Copy device bytes into each (device address, host uint8 bytes) run's host bytes, after the
        device's work before them on its stream; returns once they are all in host memory."""
        with self.lock:
            self._stream = self.device.stream if self.device.is_cuda else None
            try:
                pending = None  # the chunk whose copy down is under way: (slot, pieces)
                for index, (_, pieces) in enumerate(self._chunks(runs)):
                    slot = index % len(self.buffers)
                    self._wait(slot)  # emptied already (two buffers at least): nothing of it left to come
                    for address, offset, size in self._device_copies(pieces):
                        self._copy(self._slot_view(slot, offset, size), self._device_view(address, size))
                    self._record(slot)
                    if pending is not None:
                        self._drain(*pending)
                    pending = (slot, pieces)
                if pending is not None:
                    self._drain(*pending)
            finally:
                self._settle()

    def _drain(self, slot: int, pieces: list) -> None:
        self._wait(slot)
        self._host_copies([(data, self.views[slot][offset : offset + data.size]) for _, data, offset in pieces])


def _runs(address: int, host: np.ndarray) -> list:
    """(device address, host bytes) runs of an (n, ...) host array whose ``host[i]`` are each contiguous,
    for a contiguous device array at ``address``: one run where the whole is contiguous. The bytes are
    views (a copy down lands in ``host``): a strided 1-D array is refused."""
    if host.flags.c_contiguous:
        return [(address, _bytes_of(host))]
    if host.ndim < 2:
        raise ValueError("a strided 1-D host array cannot be staged in place; give a contiguous one")
    run = host[0].nbytes
    return [(address + i * run, _bytes_of(host[i])) for i in range(len(host))]
