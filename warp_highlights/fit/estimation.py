"""Estimation: a few Gaussians per specular image, for every light in one batch (docs/method.md, Fitting step 2).

All sets are fitted together: one rasterizer launch, one loss and one Adam step per iteration cover
every light. The number of Gaussians changes in add/prune rounds (every ``densify_every`` iterations
until ``densify_until``, plus a final prune): the residual S - R of every image is labelled into
connected regions above ``residual_threshold`` on the device (``kernels.regions``: a union-find over
the whole stack at once; only the regions' sizes and moments come to the host), and each large region
gets one Gaussian placed from its residual-weighted moments. The images never leave the device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import chunks as chunking
from ..kernels.chunks import Cancelled, chunk_progress, map_chunks, problem_chunks
from ..kernels.losses import LogL1Loss, clipped_mse
from ..kernels.optim import GaussianAdam
from ..kernels.raster import Rasterizer, problems_per_launch
from ..kernels.regions import Regions, ResidualRegions
from ..kernels.tape import ReplayedStep, adam_iteration
from ..model.config import (
    REFERENCE_HEIGHT_PX,
    EstimationSettings,
    RasterSettings,
    pixel_area_rpx2,
)
from ..model.errors import InputError
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.threads import core_count
from ..quality.metrics import psnr, psnr_of_mse

__all__ = ["EstimationResult", "estimate", "gaussian_energy_rpx", "psnr"]

_MIN_SIGMA_PX = 0.5  # a new Gaussian is at least half a pixel wide, so it draws on a pixel centre
_COLLAPSED_SIGMA_PX = 0.05  # pruned below this width (pixels of the working image)


@dataclass
class EstimationResult:
    """Fitted sets and how well they fit.

    Attributes:
        params: (n, capacity) fitted Gaussians.
        loss: (n,) final fit loss per light (log2-L1, rpx^2-weighted).
        psnr: (n,) PSNR (dB, peak 1, images clipped to [0, 1], capped at 100) of R(G) against S.
        added, pruned: Gaussians added and removed over the whole fit, per light.
    """

    params: GaussianParams
    loss: np.ndarray
    psnr: np.ndarray
    added: np.ndarray
    pruned: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Gaussians per light."""
        return self.params.counts


def gaussian_energy_rpx(params: GaussianParams, sigma_eps: float) -> np.ndarray:
    """(B, N) energy 2 pi a^2 sqrt((sx^2 + eps)(sy^2 + eps)) of every slot in intensity x rpx^2 (0 when free)."""
    sx2 = params.sigma[..., 0] ** 2 + sigma_eps
    sy2 = params.sigma[..., 1] ** 2 + sigma_eps
    energy = 2.0 * math.pi * params.amplitude**2 * np.sqrt(sx2 * sy2) * REFERENCE_HEIGHT_PX**2
    return np.where(params.active, energy, 0.0)


def estimate(
    targets,
    *,
    settings: EstimationSettings | None = None,
    raster: RasterSettings | None = None,
    device=None,
    workers: int | None = None,
    progress=None,
    graphs: bool | None = None,
) -> EstimationResult:
    """Fit Gaussians to every specular image.

    Args:
        targets: (n, H, W) specular luminance, a float32 Warp array or NumPy.
        settings: iterations, add/prune schedule and thresholds, Adam rates.
        raster: how Gaussians are drawn.
        device: Warp device (default: the targets' device, else Warp's default).
        workers: CPU threads (default: one per core); ignored on CUDA.
        progress: optional callable ``advance(iterations)`` called as the fit goes (with fractions when
            the lights run in parts: each part's iterations times its share of the lights).
        graphs: replay one iteration captured as a CUDA graph instead of launching its kernels one by
            one from Python (the same kernels in the same order: the same result); default: on CUDA.
    """
    s = settings or EstimationSettings()
    raster = raster or RasterSettings()
    device = wp.get_device(device if device is not None else getattr(targets, "device", None))
    if isinstance(targets, wp.array) and targets.device == device and targets.dtype == wp.float32:
        source = targets  # used where it is (sliced per CPU chunk); LogL1Loss checks it is finite
    else:
        source = np.ascontiguousarray(targets.numpy() if isinstance(targets, wp.array) else targets, dtype=np.float32)
    if source.ndim != 3:
        raise InputError(f"estimation targets must have shape (lights, height, width), got {tuple(source.shape)}")
    chunks = problem_chunks(source.shape[0], device, workers, per_worker=chunking.CPU_PARTS_PER_WORKER,
                            most_each=problems_per_launch(source.shape[1], source.shape[2], raster))
    graphs = device.is_cuda if graphs is None else bool(graphs)
    if graphs and not device.is_cuda:
        raise InputError("CUDA graphs need a CUDA device; estimate on the CPU with graphs=False")

    def run(chunk: slice, stop) -> tuple:
        if isinstance(source, wp.array):
            device_targets = source if len(chunks) == 1 else source[chunk]
        else:
            device_targets = wp.array(source[chunk], dtype=float, device=device)
        return _Estimator(device_targets, s, raster, device).run(stop, chunk_progress(progress, chunk, source.shape[0]),
                                                                 graphs=graphs)

    # a device's parts (over one launch's pixels) run in turn; the CPU's on at most ``workers`` threads, taken as they
    # come
    parts = map_chunks(run, chunks, parallel=not device.is_cuda,
                       threads=workers if workers is not None else core_count())
    params = GaussianParams.concatenate([p[0] for p in parts])
    loss, psnr_db, added, pruned = (np.concatenate([p[k] for p in parts]) for k in range(1, 5))
    return EstimationResult(params=params, loss=loss, psnr=psnr_db, added=added, pruned=pruned)


class _Estimator:
    """One batch of estimation problems on one device (a chunk of the lights)."""

    def __init__(self, targets: wp.array, settings: EstimationSettings, raster: RasterSettings, device):
        self.s = settings
        self.raster_settings = raster
        problems, self.height, self.width = targets.shape
        self.fit = LogL1Loss(targets, device=device)  # refuses non-finite targets
        self.batch = GaussianBatch(problems, settings.capacity, device=device)
        self.raster = Rasterizer(self.height, self.width, settings=raster, device=device)
        self.regions = ResidualRegions(targets.shape, device)
        self.adam = GaussianAdam(self.batch, settings.adam)
        self.image = self.raster.new_image(problems)
        self.loss = wp.zeros(problems, dtype=float, device=device, requires_grad=True)
        self.ones = wp.ones(problems, dtype=float, device=device)
        self.added = np.zeros(problems, dtype=np.int64)
        self.pruned = np.zeros(problems, dtype=np.int64)

    def run(self, stop, progress, *, graphs: bool = False) -> tuple:
        s = self.s
        step = ReplayedStep(adam_iteration(wp.Tape(), self.loss, self.ones, self._losses, self.adam), self.batch.device,
                            graphs=graphs)
        for iteration in range(s.iterations):
            if stop.is_set():
                raise Cancelled
            if iteration % s.densify_every == 0 and iteration < s.densify_until:
                if iteration > 0:
                    self._prune()
                self._densify(self._regions())  # in place: a captured graph stays valid
            step()
            if progress is not None and (iteration + 1) % 10 == 0:
                progress(10)
        if progress is not None:
            progress(s.iterations % 10)
        self._prune()
        self.loss.zero_()
        self.raster.render(self.batch, out=self.image)
        self.fit(self.image, out=self.loss)
        return (self.batch.numpy(), self.loss.numpy().astype(np.float64),
                psnr_of_mse(clipped_mse(self.image, self.fit.target)), self.added, self.pruned)

    def _losses(self) -> None:
        self.fit.of_render(self.raster, self.batch, image=self.image, out=self.loss, value=False)

    def _regions(self) -> Regions:
        """The regions where S - R(G) exceeds the residual threshold, R drawn now."""
        self.raster.render(self.batch, out=self.image)
        return self.regions.label(self.fit.target, self.image, self.s.residual_threshold)

    def _prune(self) -> None:
        """Remove Gaussians with too little energy, collapsed to a line, far off the image, or non-finite."""
        params = self.batch.numpy()
        energy = gaussian_energy_rpx(params, self.raster_settings.sigma_eps)
        reach = self.s.prune_outside_sigmas * np.abs(params.sigma).max(axis=2)
        x, y = params.mean[..., 0], params.mean[..., 1]
        aspect = self.width / self.height
        outside = (x < -reach) | (x > aspect + reach) | (y < -reach) | (y > 1.0 + reach)
        # narrower than this across, a Gaussian reaches almost no pixel centre within its cut-off and
        # so gets (almost) no gradient: it would sit there with energy but no effect
        collapsed = np.abs(params.sigma).min(axis=2) * self.height < _COLLAPSED_SIGMA_PX
        with np.errstate(invalid="ignore"):
            drop = params.active & (~params.finite | (energy < self.s.prune_energy) | outside | collapsed)
        if drop.any():
            self.pruned += drop.sum(axis=1)
            self.batch.remove(drop)

    def _densify(self, regions: Regions) -> None:
        """Add one Gaussian per large region where the residual exceeds the threshold, largest first."""
        s = self.s
        count = len(regions)
        if count == 0:
            return
        area, mass, region_problem = regions.area, regions.mass, regions.problem
        min_pixels = s.min_region_area_rpx2 / pixel_area_rpx2(self.height)
        free = self.batch.capacity - self.batch.counts()
        allowed = np.minimum(free, s.max_new_per_round)
        candidates = np.flatnonzero(area >= min_pixels)
        # largest first within each problem: sort by problem, then by mass descending
        order = candidates[np.lexsort((-mass[candidates], region_problem[candidates]))]
        problems = region_problem[order]
        first = np.searchsorted(problems, problems, side="left")
        rank = np.arange(len(order)) - first
        chosen = order[rank < allowed[problems]]
        if chosen.size == 0:
            return

        # principal axes of the weighted second moments: sigma_x along theta (the major axis)
        mx, my = regions.centroid[chosen, 0], regions.centroid[chosen, 1]
        cxx, cxy, cyy = (regions.covariance[chosen, k] for k in range(3))
        half_trace = 0.5 * (cxx + cyy)
        root = np.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy**2)
        major, minor = half_trace + root, np.maximum(half_trace - root, 0.0)
        theta = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
        floor = _MIN_SIGMA_PX / self.height
        sigma = np.stack([np.maximum(np.sqrt(major), floor), np.maximum(np.sqrt(minor), floor)], axis=1)
        mean = np.stack([mx, my], axis=1)
        # A curved region (the arc of a ring highlight) has its centroid off the highlight, where a
        # Gaussian would only fade away: there, start a round Gaussian at the region's peak, as wide
        # as the band is thick (area / length for a band whose length is sqrt(12) x its spread along
        # the major axis; a uniform band of thickness t has a standard deviation of t / sqrt(12)
        # across it). Later rounds cover the rest of the arc.
        centre_row = np.clip(np.floor(my * self.height).astype(np.int64), 0, self.height - 1)
        centre_col = np.clip(np.floor(mx * self.height).astype(np.int64), 0, self.width - 1)
        centre = (region_problem[chosen] * self.height + centre_row) * self.width + centre_col
        off_region = self.regions.regions_at(centre) != chosen
        if off_region.any():
            at = regions.peak_pixel[chosen[off_region]]
            row, col = (at // self.width) % self.height, at % self.width
            mean[off_region] = np.stack([(col + 0.5) / self.height, (row + 0.5) / self.height], axis=1)
            pixel = 1.0 / self.height
            thickness = area[chosen[off_region]] * pixel**2 / (np.sqrt(12.0) * np.sqrt(major[off_region]) + pixel)
            sigma[off_region] = np.maximum(thickness / np.sqrt(12.0), floor)[:, None]
        self.batch.add(region_problem[chosen], amplitude=np.sqrt(regions.peak[chosen]), mean=mean, sigma=sigma,
                       theta=theta)
        self.added += np.bincount(region_problem[chosen], minlength=self.batch.problem_count)
