"""io.warmup: the device's context and memory pool made ready in a thread."""

from __future__ import annotations

import pytest
import warp as wp

from warp_highlights.io import warmup as warmup_module
from warp_highlights.io.warmup import DeviceWarmup


def test_the_cpu_needs_no_warm_up():
    warm = DeviceWarmup("cpu")
    assert warm._thread is None
    warm.join()
    warm.join()  # twice: nothing to wait for


@pytest.mark.skipif(not wp.is_cuda_available(), reason="a CUDA device's context and memory pool")
def test_a_cuda_device_has_its_context_after_the_join_and_the_pool_keeps_nothing_taken():
    device = wp.get_device("cuda:0")
    used = wp.get_mempool_used_mem_current(device) if device.is_mempool_enabled else 0
    warm = DeviceWarmup(device, pool_bytes=1 << 20)
    warm.join()
    assert device.context is not None
    if device.is_mempool_enabled:
        assert wp.get_mempool_used_mem_current(device) == used  # the block went back


def test_a_failing_warm_up_is_silent(monkeypatch):
    """Its errors belong to the work that uses the device, which reports them in one line."""

    class Broken:
        is_cuda = True

        @property
        def context(self):
            raise RuntimeError("no context")

    monkeypatch.setattr(warmup_module, "threading", warmup_module.threading)
    warm = DeviceWarmup.__new__(DeviceWarmup)
    warm.device, warm.pool_bytes, warm._thread = Broken(), 1 << 20, None
    warm._warm()  # returns without raising
