"""Which Gaussians move: those whose retargeted selves land on the neighbours' specular images."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.support import support_fractions
from ..model.config import RasterSettings, ResidualSettings
from ..model.gaussians import GaussianBatch, GaussianParams

__all__ = ["MoveDecision", "decide_moving"]


@dataclass(frozen=True)
class MoveDecision:
    """Attributes: moving (n, N) bool; support (E, N) float64 per directed edge (-1 where a slot draws nothing);
    incoherent (n, N) bool the slots held back because their motion does not follow the light
    (``fit.coherence``)."""

    moving: np.ndarray
    support: np.ndarray
    incoherent: np.ndarray


def decide_moving(estimated: GaussianParams, retargeted: GaussianParams, edges: np.ndarray,
                  specular_luminance: wp.array,
                  *, settings: ResidualSettings, raster: RasterSettings,
                  left_frame: np.ndarray | None = None, coherence: np.ndarray | None = None) -> MoveDecision:
    """Which estimated Gaussians move: median support over the outgoing edges >= ``settings.move_support``, and
    motion coherence (``fit.coherence``) at least ``settings.move_coherence`` where it is known.
    ``left_frame``: (E, N) bool slots sent out of the frame (``fit.lost``), which have nothing to land on and
    leave the median (NaN support). ``coherence``: (n, N) the slots' motion coherence (NaN: no verdict)."""
    n, capacity = estimated.active.shape
    device = specular_luminance.device
    batch = GaussianBatch.from_numpy(retargeted, device=device, requires_grad=False)
    values = support_fractions(batch, edges[:, 1], specular_luminance, settings=raster)
    values = np.where(retargeted.active, values, np.nan)
    values[values < 0] = 0.0  # a retargeted Gaussian that draws nothing explains nothing
    if left_frame is not None:
        values[left_frame] = np.nan
    incoherent = np.zeros_like(estimated.active)
    if coherence is not None and settings.move_coherence > -1:
        incoherent = estimated.active & (np.nan_to_num(coherence, nan=np.inf) < settings.move_coherence)
    if settings.move_support <= 0:
        return MoveDecision(estimated.active & ~incoherent, values, incoherent)
    order = np.argsort(edges[:, 0], kind="stable")
    sources = edges[order, 0]
    starts = np.searchsorted(sources, np.arange(n + 1))
    for_light = values[order]
    # median over each light's outgoing edges, per slot: lights have 3..~8 edges, so pad to the most
    most = int(np.diff(starts).max()) if len(edges) else 0
    padded = np.full((n, max(most, 1), capacity), np.nan)
    position = np.arange(len(edges)) - np.repeat(starts[:-1], np.diff(starts))
    padded[sources, position] = for_light
    median = _nan_median(padded)
    moving = estimated.active & (np.nan_to_num(median, nan=0.0) >= settings.move_support)
    return MoveDecision(moving & ~incoherent, values, incoherent & moving)


def _nan_median(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1)`` of an (n, k >= 1, m) array (NaN where a column holds none), without
    its warnings and many times faster on mostly empty columns: the values sorted (NaN last), the
    middle one or the mean of the middle two of each column's count."""
    ordered = np.sort(values, axis=1)
    count = np.count_nonzero(~np.isnan(values), axis=1)  # (n, m)
    low = np.take_along_axis(ordered, (np.maximum(count - 1, 0) // 2)[:, None], axis=1)[:, 0]
    high = np.take_along_axis(ordered, (count // 2)[:, None], axis=1)[:, 0]  # count // 2 <= k - 1
    return np.where(count > 0, (low + high) / 2.0, np.nan)
