"""Which residual a fit builds: ``ResidualSettings.kind`` resolved once, when the fit starts, from "auto" to
the concrete kind for the device, the capture's size and, on the CPU, the pace it trains at."""

from __future__ import annotations

import logging

import warp as wp

from ..model.config import RESIDUAL_KINDS, ResidualSettings
from ..model.errors import InputError

__all__ = ["CONCRETE_KINDS", "cpu_epochs", "resolve_kind"]

CONCRETE_KINDS = tuple(kind for kind in RESIDUAL_KINDS if kind != "auto")
"""The kinds a fitted field can have: "lowrank", "learned", "images", "none"."""

_LOG = logging.getLogger(__name__)


def resolve_kind(kind: str, device, *, light_count: int | None = None, size: tuple[int, int] | None = None,
                 channels: int | None = None) -> str:
    """The concrete kind for ``kind`` (``RESIDUAL_KINDS``) on a Warp ``device``: "auto" is "learned" on a CUDA
    device and "lowrank" elsewhere (where ``cpu_epochs`` may then choose "learned"). Given ``light_count`` and the
    working ``size`` (width, height), a learned residual past the decoder's 2^31 (light, pixel) samples is refused
    where asked for (``InputError``) and replaced by "lowrank", with a warning, where "auto" chose it. A capture of
    one ``channels`` (grey, infrared, one band) has a low-rank residual under "auto": the learned decoder draws
    colour."""
    if kind not in RESIDUAL_KINDS:
        raise InputError(f"residual kind must be one of {', '.join(RESIDUAL_KINDS)}, got '{kind}'")
    if kind != "auto" and kind != "learned":
        return kind
    if channels == 1:
        if kind == "learned":
            raise InputError("a learned residual needs colour (RGB) images; fit grey captures with --residual lowrank "
                             "(or auto)")
        return "lowrank"
    concrete = kind if kind == "learned" else "learned" if wp.get_device(device).is_cuda else "lowrank"
    if concrete == "learned" and light_count is not None and size is not None:
        from ..kernels.neural import samples_fit

        if not samples_fit(light_count, size[0] * size[1]):
            too_many = (f"{light_count} lights of {size[0]}x{size[1]} pass the learned residual's 2^31 samples "
                        f"(lights x pixels)")
            if kind == "learned":
                raise InputError(f"{too_many}; use --residual lowrank, or a smaller --size")
            _LOG.warning("%s: the residual is compressed to low rank instead", too_many)
            return "lowrank"
    return concrete


def cpu_epochs(requested: str, resolved: str, device, settings: ResidualSettings, *, light_count: int,
               size: tuple[int, int], channels: int, rate: float | None = None) -> float | None:
    """Where "auto" (``requested``) resolved to "lowrank" on the CPU for a colour capture: the epochs a learned
    residual would run, those of its lights x pixels samples that the CPU's training time (``settings.learned_seconds``
    or its default) holds at ``rate`` samples a second (default: measured now, ``residual.cpu_training.training_rate``
    at the capture's pixel count up to ``_RATE_PIXELS``), at most its schedule's (``learned_epochs``); the fit learns
    its residual instead where they are at least ``settings.cpu_learned_epochs``. None where the question does not
    arise (another kind asked for or chosen, a CUDA device, one channel, the setting at 0, more samples than the
    decoder indexes)."""
    if requested != "auto" or resolved != "lowrank" or wp.get_device(device).is_cuda or channels != 3:
        return None
    if settings.cpu_learned_epochs <= 0:
        return None
    from ..kernels.neural import samples_fit
    from .cpu_training import training_rate
    from .learned import learned_epochs, learned_seconds

    pixels = size[0] * size[1]
    if not samples_fit(light_count, pixels):
        return None
    if rate is None:
        rate = training_rate(pixels=min(pixels, _RATE_PIXELS))
    return min(float(learned_epochs(settings, False)), rate * learned_seconds(settings, False) / (light_count * pixels))


_RATE_PIXELS = 1 << 18
"""``cpu_epochs`` times the CPU's training on at most this many pixels (the codes' Adam step grows with them)."""
