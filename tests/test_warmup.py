"""io.warmup: the device's context made in a thread."""

from __future__ import annotations

import pytest
import warp as wp

from warp_highlights.io.warmup import DeviceWarmup


def test_the_cpu_needs_no_warm_up():
    warm = DeviceWarmup("cpu")
    assert warm._thread is None
    warm.join()
    warm.join()  # twice: nothing to wait for


@pytest.mark.skipif(not wp.is_cuda_available(), reason="a CUDA device's context")
def test_a_cuda_device_has_its_context_after_the_join():
    warm = DeviceWarmup("cuda:0")
    warm.join()
    assert warm.device._context is not None


def test_a_failing_warm_up_is_silent():
    """Its errors belong to the work that uses the device, which reports them in one line."""

    class Broken:
        is_cuda = True

        @property
        def context(self):
            raise RuntimeError("no context")

    warm = DeviceWarmup.__new__(DeviceWarmup)
    warm.device, warm._thread = Broken(), None
    warm._warm()  # returns without raising
