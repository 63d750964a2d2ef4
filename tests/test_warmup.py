"""kernels.warmup: Warp started and the device's context made in a thread."""

from __future__ import annotations

import pytest
import warp as wp

from warp_highlights.kernels.warmup import DeviceWarmup


@pytest.mark.parametrize("device", ["cpu", None])
def test_warp_is_started_and_the_device_resolved(device):
    warm = DeviceWarmup(device)
    assert warm.started(30)
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
    assert warm.started(30)
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


def test_work_in_the_background_returns_raises_or_stops():
    import threading

    from warp_highlights.kernels.warmup import InBackground

    assert InBackground(lambda stop: 42, name="answer").result() == 42
    with pytest.raises(ValueError, match="bad image"):
        InBackground(lambda stop: (_ for _ in ()).throw(ValueError("bad image")), name="fails").result()
    started = threading.Event()

    def wait_for_stop(stop):
        started.set()
        if not stop.wait(30):
            raise AssertionError("never asked to stop")
        raise RuntimeError("stopped")

    with pytest.raises(KeyError):
        with InBackground(wait_for_stop, name="stoppable") as background:
            started.wait(5)
            raise KeyError("the caller's own error")  # the with block cancels the work
    assert (background.stop.is_set()
            and not [thread for thread in threading.enumerate() if thread.name.startswith("stoppable")])
    with pytest.raises(RuntimeError, match="stopped"):
        background.result()  # what the work raised once stopped
