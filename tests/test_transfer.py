"""kernels.transfer.to_host: the same values as ``numpy()``, on every path."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warp_highlights.kernels.transfer import rows_down, rows_up, to_host
from warp_highlights.model import threads


@pytest.mark.parametrize("dtype", [wp.float32, wp.float16, wp.int32])
@pytest.mark.parametrize("cores", [1, 4])
def test_to_host_gives_numpy_s_values(device, monkeypatch, dtype, cores):
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 1024)  # the threaded path for a small array too
    monkeypatch.setattr(threads, "NUMPY_THREADS", cores)
    values = np.random.default_rng(2).normal(size=(7, 33, 5)) * 100
    array = wp.array(values.astype(wp.dtype_to_numpy(dtype)), dtype=dtype, device=device)
    host = to_host(array)
    assert isinstance(host, np.ndarray) and host.dtype == wp.dtype_to_numpy(dtype) and host.shape == (7, 33, 5)
    assert host.tobytes() == array.numpy().tobytes()


def test_to_host_of_vectors_views_and_numpy_input(device, monkeypatch):
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 16)
    vectors = wp.array(np.arange(30, dtype=np.float32).reshape(10, 3), dtype=wp.vec3, device=device)
    np.testing.assert_array_equal(to_host(vectors), vectors.numpy())  # not a scalar type: numpy() as it is
    stack = wp.array(np.arange(60, dtype=np.float32).reshape(6, 10), dtype=float, device=device)
    strided = stack[:, 2:5]
    np.testing.assert_array_equal(to_host(strided), strided.numpy())  # not contiguous: numpy() as it is
    plain = np.ones(3)
    assert to_host(plain) is plain


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_rows_up_and_down_a_band_of_a_stack(device, dtype):
    """A band of rows of an (n, H, W, C) stack (each image's rows one run of memory) up to a contiguous
    device array and back into another stack's band, value for value; the whole stack in one copy."""
    stack = np.random.default_rng(4).normal(size=(5, 9, 4, 3)).astype(dtype)
    band = stack[:, 2:6]
    assert not band.flags.c_contiguous
    there = rows_up(band, device)
    assert there.shape == band.shape and there.is_contiguous
    np.testing.assert_array_equal(there.numpy(), band)
    back = np.zeros_like(stack)
    rows_down(there, back[:, 2:6])
    np.testing.assert_array_equal(back[:, 2:6], band)
    assert not back[:, :2].any() and not back[:, 6:].any()
    np.testing.assert_array_equal(rows_down(rows_up(stack, device), np.empty_like(stack)), stack)
    with pytest.raises(ValueError, match="cannot come down"):
        rows_down(there, np.empty((5, 3, 4, 3), dtype))
    with pytest.raises(ValueError, match="contiguous"):
        rows_down(rows_up(stack[:, :, :2], device), np.empty_like(stack)[:, :, :2])


@pytest.fixture
def small_staging(monkeypatch):
    """Every transfer staged through two or three buffers of a few hundred bytes, copied in parts of 64."""
    from warp_highlights.kernels import transfer

    monkeypatch.setattr(transfer, "STAGE_ON_CPU", True)
    monkeypatch.setattr(transfer, "STAGED_MIN_BYTES", 0)
    monkeypatch.setattr(transfer, "_PART_BYTES", 64)
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 16)
    monkeypatch.setattr(transfer.Staging, "_made", {})
    return transfer


@pytest.mark.parametrize("slot_bytes,slots", [(1000, 3), (333, 2), (1 << 16, 3)])
@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_staged_transfers_move_every_byte_in_place(device, small_staging, monkeypatch, slot_bytes, slots, dtype):
    """Runs cut across buffers (an image's rows longer and shorter than a buffer), up and down, and
    to_host: the same bytes as the direct copies."""
    monkeypatch.setattr(small_staging, "STAGING_BYTES", slot_bytes)
    monkeypatch.setattr(small_staging, "STAGING_SLOTS", slots)
    stack = np.random.default_rng(5).normal(size=(6, 11, 7, 3)).astype(dtype)
    band = stack[:, 3:9]  # each image's rows one run, the band not contiguous
    up = rows_up(band, device)
    assert up.shape == band.shape and up.is_contiguous
    np.testing.assert_array_equal(up.numpy(), band)
    out = np.zeros_like(stack)
    assert rows_down(up, out[:, 2:8]) is not None
    np.testing.assert_array_equal(out[:, 2:8], band)
    assert not out[:, :2].any() and not out[:, 8:].any()  # nothing outside the band written
    whole = wp.array(stack, dtype=wp.dtype_from_numpy(dtype), device=device)
    np.testing.assert_array_equal(to_host(whole), stack)
    staging = small_staging.Staging.of(device)
    assert len(staging.buffers) == slots and staging.slot_bytes == slot_bytes


def test_staging_chunks_cover_every_run_once_and_fill_each_buffer(device, small_staging):
    staging = small_staging.Staging(device, slot_bytes=10, slots=2)
    runs = [(1000, np.arange(25, dtype=np.uint8)), (5000, np.arange(3, dtype=np.uint8)),
            (7000, np.arange(12, dtype=np.uint8))]
    chunks = staging._chunks(runs)
    assert [used for used, _ in chunks] == [10, 10, 10, 10]
    pieces = [(address, data.size, offset) for _, chunk in chunks for address, data, offset in chunk]
    assert (pieces[0] == (1000, 10, 0) and pieces[2] == (1020, 5, 0) and pieces[3] == (5000, 3, 5)
            and pieces[4] == (7000, 2, 8))
    assert sum(size for _, size, _ in pieces) == 40


def test_as_half_rounds_as_numpy_does(device):
    """float32 -> float16 on the device: clamped to the largest half, then NumPy's astype (round to nearest even), any
    rank."""
    from warp_highlights.kernels.transfer import as_half

    rng = np.random.default_rng(9)
    values = np.concatenate([rng.normal(size=500) * 10.0 ** rng.integers(-9, 6, 500),
                             [0.0, -0.0, 65504.0, 65520.0, 1e9, 2.0**-25, 1 + 2.0**-11]])
    for shape in [(values.size,), (7, values.size // 7)]:
        part = values[: int(np.prod(shape))].astype(np.float32).reshape(shape)
        half = as_half(wp.array(part, dtype=float, device=device))
        assert half.dtype == wp.float16 and half.shape == shape
        # finite: 1e9 and 65520 -> 65504
        np.testing.assert_array_equal(half.numpy(), np.clip(part, -65504, 65504).astype(np.float16))
    with pytest.raises(ValueError, match="float32"):
        as_half(wp.zeros(3, dtype=wp.float16, device=device))


class _DelayedCopies:
    """A stream for ``Staging`` on the CPU that holds each copy until an event after it is waited for,
    as a CUDA stream runs them later: a buffer refilled or read too early shows as wrong bytes."""

    def __init__(self, staging):
        self.queue, self.done = [], 0
        staging._copy = lambda destination, source: self.queue.append((destination, source))
        staging._record = lambda slot: staging.events.__setitem__(slot, len(self.queue))
        original_wait = staging._wait

        def wait(slot):
            token = staging.events[slot]
            if token is not None:
                self.run(token)
            staging.events[slot] = None
            if token is None:
                original_wait(slot)

        staging._wait = wait

    def run(self, upto):
        while self.done < upto:
            destination, source = self.queue[self.done]
            wp.copy(destination, source)
            self.done += 1


@pytest.mark.parametrize("slots", [2, 3])
@pytest.mark.parametrize("slot_bytes", [7, 64, 1000])
def test_staging_reuses_a_buffer_only_after_its_copies_have_run(slots, slot_bytes):
    from warp_highlights.kernels.transfer import Staging

    rng = np.random.default_rng(slots * 1000 + slot_bytes)
    staging = Staging("cpu", slot_bytes=slot_bytes, slots=slots)
    delayed = _DelayedCopies(staging)
    host = rng.integers(0, 256, (5, 301), dtype=np.uint8)
    device = wp.zeros(host.shape, dtype=wp.uint8, device="cpu")
    staging.up([(device.ptr + i * 301, host[i]) for i in range(5)])
    assert delayed.done == len(delayed.queue)  # every copy ran before up returned
    np.testing.assert_array_equal(device.numpy(), host)
    back = np.zeros_like(host)
    staging.down([(device.ptr + i * 301, back[i]) for i in range(5)])
    np.testing.assert_array_equal(back, host)
    assert all(event is None for event in staging.events)


def test_a_transfer_stopped_midway_leaves_no_copy_pending_and_the_next_one_is_whole():
    from warp_highlights.kernels.transfer import Staging

    staging = Staging("cpu", slot_bytes=16, slots=2)
    delayed = _DelayedCopies(staging)
    calls = []
    real = staging._host_copies

    def interrupted(copies):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real(copies)

    staging._host_copies = interrupted
    host = np.arange(200, dtype=np.uint8)
    device = wp.zeros(200, dtype=wp.uint8, device="cpu")
    with pytest.raises(KeyboardInterrupt):
        staging.up([(device.ptr, host)])
    assert delayed.done == len(delayed.queue) and all(event is None for event in staging.events)
    staging._host_copies = real
    staging.up([(device.ptr, host)])
    np.testing.assert_array_equal(device.numpy(), host)


def test_staging_needs_two_buffers_and_a_strided_vector_is_not_staged_in_place():
    from warp_highlights.kernels.transfer import Staging, _runs

    with pytest.raises(ValueError, match="2 buffers"):
        Staging("cpu", slot_bytes=64, slots=1)
    with pytest.raises(ValueError, match="strided"):
        _runs(0, np.zeros(10, np.float32)[::2])
    assert len(_runs(0, np.zeros((3, 4), np.float32))) == 1 and len(_runs(0, np.zeros((3, 4), np.float32)[:, :2])) == 3


def test_staged_transfers_of_vectors(device, small_staging, monkeypatch):
    """A 1-D array is one run (not one per element)."""
    monkeypatch.setattr(small_staging, "STAGING_BYTES", 100)
    values = np.random.default_rng(3).normal(size=1001).astype(np.float32)
    up = rows_up(values, device)
    np.testing.assert_array_equal(up.numpy(), values)
    out = np.zeros_like(values)
    rows_down(up, out)
    np.testing.assert_array_equal(out, values)


def test_a_band_is_staged_by_its_whole_stack_s_bytes(device, small_staging, monkeypatch):
    """A band under ``STAGED_MIN_BYTES`` goes through the buffers when the stack it belongs to does not
    (``whole_bytes``), up and down, with the same values; without it, the plain copy."""
    stack = np.random.default_rng(6).normal(size=(4, 10, 5)).astype(np.float32)
    band = stack[:, 2:5]
    monkeypatch.setattr(small_staging, "STAGED_MIN_BYTES", stack.nbytes)
    used = []
    for name in ("up", "down"):
        original = getattr(small_staging.Staging, name)

        def counted(self, runs, original=original, name=name):
            used.append(name)
            return original(self, runs)

        monkeypatch.setattr(small_staging.Staging, name, counted)
    out = np.zeros_like(stack)
    rows_down(rows_up(band, device), out[:, 2:5])
    assert used == []
    up = rows_up(band, device, whole_bytes=stack.nbytes)
    rows_down(up, out[:, 2:5], whole_bytes=stack.nbytes)
    assert used == ["up", "down"]
    np.testing.assert_array_equal(out[:, 2:5], band)


def test_a_band_s_rows_go_in_one_device_copy_a_buffer(device, small_staging, monkeypatch):
    """The rows of a band of many lights (runs of a few bytes each, next to each other on the device)
    cross in one device copy per buffer filled, each way, with the same values."""
    monkeypatch.setattr(small_staging, "STAGING_BYTES", 1000)
    stack = np.random.default_rng(7).normal(size=(40, 9, 7)).astype(np.float32)
    band = stack[:, 2:5]  # 40 runs of 84 bytes: 3360 bytes, 4 buffers' worth
    copies = []
    real = small_staging.Staging._copy
    monkeypatch.setattr(small_staging.Staging, "_copy",
                        lambda self, destination, source: copies.append(source.size) or real(self, destination, source))
    up = rows_up(band, device)
    assert copies == [1000, 1000, 1000, 360]
    copies.clear()
    out = np.zeros_like(stack)
    rows_down(up, out[:, 2:5])
    assert copies == [1000, 1000, 1000, 360]
    np.testing.assert_array_equal(out[:, 2:5], band)
    assert not out[:, :2].any() and not out[:, 5:].any()


def test_only_pieces_next_to_each_other_on_both_sides_share_a_copy():
    """``Staging._device_copies``: a piece joins the copy before it only where it follows it both on the
    device and in the buffer."""
    from warp_highlights.kernels.transfer import Staging

    data = np.zeros(10, np.uint8)
    pieces = [(1000, data[:4], 0), (1004, data[:2], 4), (2000, data[:3], 6), (2003, data[:1], 20), (2004, data[:5], 21)]
    assert Staging._device_copies(pieces) == [(1000, 0, 6), (2000, 6, 3), (2003, 20, 6)]
    assert Staging._device_copies([]) == []


def test_the_host_s_peak_memory_needs_no_warp():
    """``PeakMemory("cpu")`` (the fit command's loading thread, before Warp has started) starts no Warp."""
    import subprocess
    import sys

    probe = ("from warp_highlights.model.memory import PeakMemory\n"
             "with PeakMemory('cpu') as peak:\n    x = bytearray(1 << 20)\n"
             "from warp._src import context\nprint(context.runtime is None, peak.host is not None, "
             "peak.device is None)")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["True", "True", "True"], run.stderr
