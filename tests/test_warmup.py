"""io.warmup: Warp started and the device's context made in a thread."""

from __future__ import annotations

import pytest
import warp as wp

from warp_highlights.io.warmup import DeviceWarmup


@pytest.mark.parametrize("device", ["cpu", None])
def test_warp_is_started_and_the_device_resolved(device):
    warm = DeviceWarmup(device)
    warm.started()
    assert warm.device == wp.get_device(device)
    warm.join()
    warm.join()  # twice: nothing to wait for


@pytest.mark.skipif(not wp.is_cuda_available(), reason="a CUDA device's context")
def test_a_cuda_device_has_its_context_after_the_join():
    warm = DeviceWarmup("cuda:0")
    warm.join()
    assert warm.device._context is not None


def test_an_unknown_device_is_left_to_the_caller():
    """Its errors belong to the caller, which reports them in one line (``check_device``)."""
    warm = DeviceWarmup("cuda:99")
    warm.started()
    warm.join()
    assert warm.device is None


def test_a_failing_context_is_silent(monkeypatch):
    """The device's own work reports a context that cannot be made."""

    class Broken:
        is_cuda = True

        @property
        def context(self):
            raise RuntimeError("no context")

    monkeypatch.setattr(wp, "get_device", lambda requested: Broken())
    warm = DeviceWarmup("cuda:0")
    warm.join()
    assert isinstance(warm.device, Broken)
