"""CPU chunking: slices cover the problems, a failing chunk stops the others at once, the device default is
untouched."""

from __future__ import annotations

import time

import numpy as np
import pytest
import warp as wp

from warp_highlights.kernels.chunks import (
    Cancelled,
    map_chunks,
    memory_chunks,
    problem_chunks,
)


def test_chunks_cover_every_problem_once():
    for count in (1, 2, 7, 100):
        for workers in (1, 2, 3, 16):
            chunks = problem_chunks(count, "cpu", workers)
            covered = np.concatenate([np.arange(count)[c] for c in chunks])
            np.testing.assert_array_equal(covered, np.arange(count))
            assert len(chunks) == min(workers, count)


def test_parts_per_worker_cut_a_threaded_batch_finer():
    """Several workers take ``per_worker`` parts each as they come (problems differ in cost); one worker keeps one
    part; a part still holds at most ``most_each`` problems."""
    for count in (1, 5, 49, 252):
        for workers in (1, 2, 3):
            chunks = problem_chunks(count, "cpu", workers, per_worker=8)
            covered = np.concatenate([np.arange(count)[c] for c in chunks])
            np.testing.assert_array_equal(covered, np.arange(count))
            assert len(chunks) == (min(8 * workers, count) if workers > 1 else 1)
    assert sorted(c.stop - c.start for c in problem_chunks(49, "cpu", 2, per_worker=8)) == [3] * 15 + [4]
    assert len(problem_chunks(100, "cpu", 2, per_worker=8, most_each=5)) == 20
    assert memory_chunks(49, "cpu", 2, bytes_each=1.0, per_worker=8) == problem_chunks(49, "cpu", 2, per_worker=8)


def test_a_failing_chunk_stops_the_others_and_its_error_wins():
    started = time.perf_counter()

    def work(chunk, stop):
        if chunk.start == 1:
            time.sleep(0.05)
            raise ValueError("chunk 1 failed")
        for _ in range(500):  # 5 s unless stopped
            if stop.is_set():
                raise Cancelled
            time.sleep(0.01)
        return chunk.start

    with pytest.raises(ValueError, match="chunk 1 failed"):
        map_chunks(work, [slice(0, 1), slice(1, 2), slice(2, 3)])
    assert time.perf_counter() - started < 2.0


def test_results_keep_chunk_order():
    assert map_chunks(lambda chunk, stop: chunk.start, [slice(0, 2), slice(2, 5), slice(5, 6)]) == [0, 2, 5]


def test_threaded_cpu_fit_leaves_the_default_device_alone():
    from warp_highlights.fit.estimation import estimate
    from warp_highlights.model.config import EstimationSettings

    before = wp.get_device()
    target = np.zeros((4, 16, 16), dtype=np.float32)
    target[:, 6:9, 6:9] = 1.0
    estimate(target, settings=EstimationSettings(iterations=30, densify_every=10, densify_until=20), device="cpu",
             workers=4)
    assert wp.get_device() == before


def test_memory_chunks_split_a_cuda_batch_to_fit_the_free_memory():
    # host memory: the threads' chunks
    assert memory_chunks(10, "cpu", 3, bytes_each=1e15) == problem_chunks(10, "cpu", 3)
    if not wp.is_cuda_available():
        pytest.skip("the split by device memory needs a CUDA device")
    free = wp.get_device("cuda:0").free_memory
    assert memory_chunks(1000, "cuda:0", bytes_each=1.0) == [slice(0, 1000)]
    parts = memory_chunks(1000, "cuda:0", bytes_each=free / 7, share=1.0)
    assert parts[0].start == 0 and parts[-1].stop == 1000 and all(a.stop == b.start for a, b in zip(parts, parts[1:]))
    assert len(parts) >= 143 and max(p.stop - p.start for p in parts) <= 7


def test_chunks_not_in_parallel_run_in_order_on_this_thread():
    import threading

    seen = []
    results = map_chunks(lambda chunk, stop: seen.append((chunk.start, threading.get_ident())) or chunk.start,
                         problem_chunks(9, "cpu", 3), parallel=False)
    assert results == [0, 3, 6] and [s for s, _ in seen] == [0, 3, 6]
    assert {t for _, t in seen} == {threading.get_ident()}


@pytest.mark.parametrize("count,workers,most", [(10, 2, 3), (7, 16, 2), (100, 1, 100), (100, 3, 1), (5, 2, None)])
def test_chunks_hold_at_most_one_launchs_problems(count, workers, most):
    """``most_each`` (the rasterizer's bound per launch) splits a thread's or a device's chunk further; the
    slices still cover every problem once, in order, and are as equal as they can be."""
    for chunks in (problem_chunks(count, "cpu", workers, most_each=most),
                   memory_chunks(count, "cpu", workers, bytes_each=1.0, most_each=most)):
        covered = np.concatenate([np.arange(count)[c] for c in chunks])
        np.testing.assert_array_equal(covered, np.arange(count))
        sizes = [c.stop - c.start for c in chunks]
        assert max(sizes) <= (most or count) and max(sizes) - min(sizes) <= 1
        assert len(chunks) == max(min(workers, count), -(-count // (most or count)))
    if wp.is_cuda_available():
        assert problem_chunks(10, "cuda:0", most_each=4) == [slice(0, 3), slice(3, 7), slice(7, 10)]
        assert memory_chunks(10, "cuda:0", bytes_each=1.0, most_each=4) == [slice(0, 3), slice(3, 7), slice(7, 10)]


def test_chunk_progress_reports_each_chunks_share_so_a_bar_fills_once():
    from warp_highlights.kernels.chunks import chunk_progress

    assert chunk_progress(None, slice(0, 3), 10) is None
    steps = []
    chunks = problem_chunks(11, "cpu", 2, most_each=3)
    for chunk in chunks:
        advance = chunk_progress(steps.append, chunk, 11)
        for _ in range(20):  # every chunk runs the stage's 20 iterations
            advance(1)
    sizes = [c.stop - c.start for c in chunks]
    assert sizes == [3, 3, 2, 3] and sum(steps) == pytest.approx(20.0)
    np.testing.assert_allclose(steps, np.repeat(np.array(sizes) / 11, 20))  # each chunk's share, not an equal one


def test_chunks_past_the_threads_run_at_most_that_many_at_once():
    import threading

    running, most, lock = [0], [0], threading.Lock()

    def work(chunk, stop):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.05)
        with lock:
            running[0] -= 1
        return chunk.start

    chunks = problem_chunks(12, "cpu", 2, most_each=2)
    assert len(chunks) == 6 and map_chunks(work, chunks, threads=2) == [0, 2, 4, 6, 8, 10]
    assert most[0] == 2
