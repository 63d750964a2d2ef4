"""model.threads: the threaded finite check against NumPy's."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from warp_highlights.model import threads
from warp_highlights.model.threads import all_finite, mapped_empty


@settings(max_examples=60, deadline=None)
@given(length=st.integers(0, 70), bad=st.sampled_from([np.nan, np.inf, -np.inf, None]), where=st.floats(0, 1),
       dtype=st.sampled_from([np.float16, np.float32, np.float64]))
def test_all_finite_is_numpy_s_check_wherever_the_bad_value_is(length, bad, where, dtype):
    array = np.ones((length, 3, 2), dtype)
    if bad is not None and length:
        array.reshape(-1)[min(int(where * array.size), array.size - 1)] = bad
    assert all_finite(array) == bool(np.isfinite(array).all())


@pytest.mark.parametrize("cores", [1, 3])
def test_all_finite_on_one_core_and_a_few(monkeypatch, cores):
    monkeypatch.setattr(threads, "NUMPY_THREADS", cores)
    array = np.zeros((25, 4), np.float32)
    assert all_finite(array) and all_finite(np.float32(1.0)) and all_finite(array[:1])
    array[24, 3] = np.nan
    assert not all_finite(array)
    assert not all_finite(np.float64(np.inf))


@pytest.mark.parametrize("cores", [1, 3])
@pytest.mark.parametrize("limit", [1 << 40, 64])
def test_mapped_empty_is_an_empty_array_of_the_shape_and_type(monkeypatch, cores, limit):
    """Pages written from threads (a small limit here: every part's fill runs) or left as they are; the
    array is writable and whole either way (odd sizes: the last part is short)."""
    monkeypatch.setattr(threads, "NUMPY_THREADS", cores)
    monkeypatch.setattr(threads, "PREFAULT_BYTES", limit)
    # memory that is not zero already
    monkeypatch.setattr(threads.np, "empty", lambda shape, dtype: np.full(shape, 0xAB, dtype))
    filled = []
    real_map = threads.parallel_map
    monkeypatch.setattr(threads, "parallel_map",
                        lambda function, items: filled.extend(items) or real_map(function, items))
    array = mapped_empty((7, 13, 3), np.uint16)
    assert array.shape == (7, 13, 3) and array.dtype == np.uint16 and array.flags.c_contiguous and array.flags.writeable
    threaded = limit == 64 and cores > 1
    assert bool(filled) == threaded and (not array.any()) == threaded  # every part written from the threads, or none
    array[...] = 5
    assert int(array.sum()) == 5 * array.size


def test_parallel_map_keeps_order_and_raises_the_first_error_once_all_have_finished():
    import threading
    import time

    finished = []
    lock = threading.Lock()

    def work(item):
        if item == 2:
            raise ValueError("two")
        if item == 5:
            raise KeyError("five")
        time.sleep(0.01 * (item % 3))
        with lock:
            finished.append(item)
        return item * item

    assert threads.parallel_map(lambda item: item * item, range(40)) == [item * item for item in range(40)]
    with pytest.raises(ValueError, match="two"):
        threads.parallel_map(work, range(12))
    assert sorted(finished) == [item for item in range(12) if item not in (2, 5)]  # every other call ran to its end


def test_nested_parallel_maps_run_in_place_on_a_worker_and_do_not_wait_for_ever(monkeypatch):
    """Outer calls fill every worker; their inner maps must not queue behind them."""
    monkeypatch.setattr(threads, "NUMPY_THREADS", max(threads.NUMPY_THREADS, 2))
    outer = 4 * threads.shared_pool()._max_workers

    def inner(item):
        assert threads.in_worker()
        return sum(threads.parallel_map(lambda x: x + item, range(5)))

    assert threads.parallel_map(inner, range(outer)) == [10 + 5 * item for item in range(outer)]
    assert not threads.in_worker()
    done = threads.submit(lambda: threads.submit(lambda: 7).result() + 1)  # a worker's submit runs in place
    assert done.result(timeout=10) == 8


def test_the_shared_pool_is_made_once():
    assert threads.shared_pool() is threads.shared_pool()


def test_in_place_maps_make_every_call_before_raising_the_first_error(monkeypatch):
    """One core (or a nested map): the same promise as the threaded map."""
    monkeypatch.setattr(threads, "NUMPY_THREADS", 1)
    made = []

    def work(item):
        made.append(item)
        if item in (1, 3):
            raise ValueError(f"bad {item}")
        return item

    with pytest.raises(ValueError, match="bad 1"):
        threads.parallel_map(work, range(6))
    assert made == list(range(6))
    assert threads.parallel_map(lambda item: 2 * item, range(4)) == [0, 2, 4, 6]


def test_a_pool_started_on_a_worker_marks_its_threads_as_workers():
    from concurrent.futures import ThreadPoolExecutor

    assert threads.child_initializer() is None  # here: not a worker

    def on_worker(_):
        with ThreadPoolExecutor(2, initializer=threads.child_initializer()) as pool:
            return pool.submit(threads.in_worker).result()

    assert threads.submit(on_worker, 0).result(timeout=30) is True
