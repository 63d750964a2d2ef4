"""Which Gaussians move: those whose retargeted selves land on the neighbours' specular images."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.support import support_fractions
from ..model.components import gaussian_covariances
from ..model.config import RasterSettings, ResidualSettings
from ..model.gaussians import GaussianBatch, GaussianParams

__all__ = ["MoveDecision", "decide_moving", "per_light_median", "travel_in_sigmas"]


@dataclass(frozen=True)
class MoveDecision:
    """Attributes: moving (n, N) bool; support (E, N) float64 per directed edge (-1 where a slot draws nothing);
    incoherent (n, N) bool the slots held back because their motion does not follow the light
    (``fit.coherence``); near (n, N) bool those held back because their highlight travels too little between
    neighbouring lights for a move to matter (``travel_in_sigmas``)."""

    moving: np.ndarray
    support: np.ndarray
    incoherent: np.ndarray
    near: np.ndarray


def decide_moving(estimated: GaussianParams, retargeted: GaussianParams, edges: np.ndarray,
                  specular_luminance: wp.array,
                  *, settings: ResidualSettings, raster: RasterSettings,
                  left_frame: np.ndarray | None = None, coherence: np.ndarray | None = None,
                  least_coherence: float | None = None, least_travel: float = 0.0) -> MoveDecision:
    """Which estimated Gaussians move: median support over the outgoing edges >= ``settings.move_support``, motion
    coherence (``fit.coherence``) at least ``least_coherence`` (None: ``settings.move_coherence``; -1: any) where it
    is known, and a median travel over the outgoing edges of at least ``least_travel`` of the Gaussian's standard
    deviations (``travel_in_sigmas``; 0: any) where it is known.
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
    least = settings.move_coherence if least_coherence is None else least_coherence
    if coherence is not None and least > -1:
        incoherent = estimated.active & (np.nan_to_num(coherence, nan=np.inf) < least)
    near = np.zeros_like(estimated.active)
    if least_travel > 0:
        travel = per_light_median(travel_in_sigmas(estimated.take(edges[:, 0]), retargeted), edges, n)
        near = estimated.active & (np.nan_to_num(travel, nan=np.inf) < least_travel)
    held = incoherent | near
    if settings.move_support <= 0:
        return MoveDecision(estimated.active & ~held, values, incoherent, near & ~incoherent)
    median = per_light_median(values, edges, n)
    moving = estimated.active & (np.nan_to_num(median, nan=0.0) >= settings.move_support)
    return MoveDecision(moving & ~held, values, incoherent & moving, near & moving & ~incoherent)


def travel_in_sigmas(sources: GaussianParams, retargeted: GaussianParams) -> np.ndarray:
    """(E, N) how far each slot's highlight travels along its directed edge, in the source Gaussian's standard
    deviations along the way: |mu_target - mu_source| / sqrt(u^T Sigma u), u the unit displacement (NaN where either
    slot is free). Under about 2 a cross-fade of the two is a single blob that merely shifts; the further beyond,
    the more a blend shows two highlights where the truth has one."""
    moved = retargeted.mean - sources.mean
    distance = np.linalg.norm(moved, axis=-1)
    unit = moved / np.maximum(distance, 1e-300)[..., None]
    sigma = np.sqrt(np.einsum("...i,...ij,...j->...", unit, gaussian_covariances(sources.sigma, sources.theta), unit))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(distance > 0, distance / sigma, 0.0)
    return np.where(sources.active & retargeted.active & np.isfinite(ratio), ratio, np.nan)


def per_light_median(values: np.ndarray, edges: np.ndarray, light_count: int) -> np.ndarray:
    """(n, N) each light's median over its outgoing directed edges (``edges`` (E, 2)) of the (E, N) ``values``
    per slot, NaN ignored (NaN where a slot has none)."""
    edges = np.asarray(edges, dtype=np.int64)
    capacity = values.shape[1]
    order = np.argsort(edges[:, 0], kind="stable")
    sources = edges[order, 0]
    starts = np.searchsorted(sources, np.arange(light_count + 1))
    # lights have 3..~8 edges, so pad to the most
    most = int(np.diff(starts).max()) if len(edges) else 0
    padded = np.full((light_count, max(most, 1), capacity), np.nan)
    position = np.arange(len(edges)) - np.repeat(starts[:-1], np.diff(starts))
    padded[sources, position] = values[order]
    return _nan_median(padded)


def _nan_median(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1)`` of an (n, k >= 1, m) array (NaN where a column holds none), without
    its warnings and many times faster on mostly empty columns: the values sorted (NaN last), the
    middle one or the mean of the middle two of each column's count."""
    ordered = np.sort(values, axis=1)
    count = np.count_nonzero(~np.isnan(values), axis=1)  # (n, m)
    low = np.take_along_axis(ordered, (np.maximum(count - 1, 0) // 2)[:, None], axis=1)[:, 0]
    high = np.take_along_axis(ordered, (count // 2)[:, None], axis=1)[:, 0]  # count // 2 <= k - 1
    return np.where(count > 0, (low + high) / 2.0, np.nan)
