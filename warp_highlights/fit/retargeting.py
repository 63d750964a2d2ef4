"""Retargeting: re-fit every estimated set onto each neighbour's specular image (docs/method.md, Fitting step 5).

One problem per directed edge i -> j of the triangulation (6n - 12 on a full sphere), all in one batch:
start from G_i and fit S_j.

- Phase 1 (``rigid_iterations``): each connected component of G_i moves as a rigid body (one
  translation and rotation per component), loss L_fit only, from the offset where the component
  best lies on S_j (a grid search: ``kernels/search.py``).
- Phase 2 (``iterations``): every parameter, loss c_fit L_fit + c_str L_str + c_ene L_ene, with the
  structure and energy terms measured against G_i.

Slot p of the result is slot p of G_i moved, so the correspondence the interpolation needs is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import chunks as chunking
from ..kernels.chunks import Cancelled, chunk_progress, map_chunks, memory_chunks
from ..kernels.losses import EnergyLoss, LogL1Loss, StructureLoss
from ..kernels.optim import GaussianAdam
from ..kernels.raster import Rasterizer, problems_per_launch
from ..kernels.retarget import RigidAdam, RigidMotion, gather_images
from ..kernels.search import blurred, image_headings, search_blur_px, searched_translations
from ..kernels.tape import ReplayedStep, adam_iteration
from ..model.components import ConnectedComponents
from ..model.config import RasterSettings, RetargetSettings, rpx_to_normalized
from ..model.errors import InputError
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.threads import core_count
from .estimation import gaussian_energy_rpx

_IMAGES_PER_EDGE = 5
"""Image-sized float32 arrays retargeting holds per directed edge (its target, its rendering, their
adjoints, the loss's scratch), rounded up from the four that a 1920x1080 capture's peak device memory
gives (its Gaussians fitted at 960x540; benchmarks/bench_scale.py)."""

__all__ = ["RetargetResult", "restore_vanished", "retarget"]


@dataclass
class RetargetResult:
    """Retargeted sets and their losses, one row per directed edge.

    Attributes:
        params: (E, N) the re-fitted sets; slot p of row e is slot p of the source set.
        source_loss: (E,) fit loss of the unchanged source set against the target image.
        rigid_loss: (E,) fit loss after phase 1.
        loss: (E,) fit loss after phase 2 (the final set).
        structure_loss: (E,) structure loss of the final set against its source (rpx^2).
        restored: (E,) slots that diverged (non-finite) and were reset to the source.
    """

    params: GaussianParams
    source_loss: np.ndarray
    rigid_loss: np.ndarray
    loss: np.ndarray
    structure_loss: np.ndarray
    restored: np.ndarray


def retarget(
    estimated: GaussianParams,
    targets,
    edges: np.ndarray,
    *,
    settings: RetargetSettings | None = None,
    raster: RasterSettings | None = None,
    device=None,
    workers: int | None = None,
    progress=None,
    graphs: bool | None = None,
    directions: np.ndarray | None = None,
) -> RetargetResult:
    """Fit every source set ``estimated[i]`` to the target image ``targets[j]`` for each edge (i, j).

    Args:
        estimated: (n, N) estimated sets, one per light.
        targets: (n, H, W) specular luminance per light, a float32 Warp array or NumPy.
        edges: (E, 2) directed edges (source light, target light).
        settings: phase lengths, loss weights, learning rates.
        raster: how Gaussians are drawn.
        device: Warp device (default: the targets' device, else Warp's default).
        workers: CPU threads (default: one per core); ignored on CUDA.
        progress: optional callable ``advance(iterations)``, called with fractions when the edges run in
            parts (each part's iterations times its share of the edges).
        graphs: replay each phase's iteration captured as a CUDA graph (the same kernels in the same
            order); default: on CUDA.
        directions: (n, 3) the lights' directions: the way each edge's highlights go in the image guides
            phase 1's start (``kernels.search.image_headings``); None: any way.
    """
    s = settings or RetargetSettings()
    raster = raster or RasterSettings()
    device = wp.get_device(device if device is not None else getattr(targets, "device", None))
    graphs = device.is_cuda if graphs is None else bool(graphs)
    if graphs and not device.is_cuda:
        raise InputError("CUDA graphs need a CUDA device; retarget on the CPU with graphs=False")
    edges = np.asarray(edges)
    n = estimated.problem_count
    if edges.ndim != 2 or edges.shape[1] != 2 or len(edges) == 0 or edges.min() < 0 or edges.max() >= n:
        raise InputError(f"edges must be a non-empty (E, 2) array of light indices in 0..{n - 1}")
    if len(targets.shape) != 3 or targets.shape[0] != n:
        raise InputError(f"targets must have shape ({n}, H, W), got {tuple(targets.shape)}")
    if not np.all(estimated.finite[estimated.active]):
        raise InputError("the estimated sets have non-finite parameters")
    components = ConnectedComponents.of(estimated, level=s.components.level, sigma_eps=raster.sigma_eps)
    labels = components.labels[edges[:, 0]]
    centroids = components.centroid_of_slot()[edges[:, 0]]
    on_device = isinstance(targets, wp.array) and targets.device == device
    all_targets = (targets if on_device
                   else wp.array(np.ascontiguousarray(targets, dtype=np.float32), dtype=float, device=device))
    image_bytes = 4 * all_targets.shape[1] * all_targets.shape[2]
    headings = None if directions is None else image_headings(directions, edges)
    # phase 1's search reads each light's image blurred by its grid step, blurred once here for every edge
    smooth = (blurred(all_targets, search_blur_px(rpx_to_normalized(s.search_step_rpx), all_targets.shape[1]))
              if s.search_radius > 0 else None)
    chunks = memory_chunks(len(edges), device, workers, per_worker=chunking.CPU_PARTS_PER_WORKER,
                           bytes_each=_IMAGES_PER_EDGE * image_bytes + 1024 * estimated.capacity,
                           most_each=problems_per_launch(all_targets.shape[1], all_targets.shape[2], raster))

    def run(chunk: slice, stop) -> tuple:
        source = estimated.take(edges[chunk, 0])
        job = _Retargeting(source, all_targets, edges[chunk, 1], labels[chunk], centroids[chunk], s, raster, device,
                           headings=None if headings is None else headings[chunk], smooth=smooth)
        return job.run(stop, chunk_progress(progress, chunk, len(edges)), graphs=graphs)

    # a device's parts do not fit it together; the CPU's run on at most ``workers`` threads, taken as they come
    parts = map_chunks(run, chunks, parallel=not device.is_cuda,
                       threads=workers if workers is not None else core_count())
    params = GaussianParams.concatenate([p[0] for p in parts])
    losses = [np.concatenate([p[k] for p in parts]) for k in range(1, 6)]
    return RetargetResult(params, *losses)


class _Retargeting:
    """One batch of directed edges on one device."""

    def __init__(self, source_params: GaussianParams, all_targets: wp.array, target_rows, labels, centroids,
                 settings: RetargetSettings, raster: RasterSettings, device, *, headings=None, smooth=None):
        self.s = settings
        problems = source_params.problem_count
        _, height, width = all_targets.shape
        self.source_params = source_params
        self.source = GaussianBatch.from_numpy(source_params, device=device, requires_grad=False)
        self.moving = GaussianBatch.from_numpy(source_params, device=device)
        rows = wp.array(np.asarray(target_rows, dtype=np.int32), dtype=wp.int32, device=device)
        targets = wp.empty((problems, height, width), dtype=float, device=device)
        wp.launch(gather_images, dim=targets.shape, inputs=[all_targets, rows], outputs=[targets], device=device)
        self.raster = Rasterizer(height, width, settings=raster, device=device)
        self.fit = LogL1Loss(targets)
        self.structure = StructureLoss(self.source, settings.structure)
        self.energy = EnergyLoss(self.source, raster)
        self.rigid = RigidMotion(self.source, labels, centroids)
        # phase 1 starts where each component best lies on its target (kernels/search.py)
        if smooth is not None:
            smooth_targets = wp.empty((problems, height, width), dtype=float, device=device)
            wp.launch(gather_images, dim=targets.shape, inputs=[smooth, rows], outputs=[smooth_targets], device=device)
            searched_translations(self.source, source_params, labels, smooth_targets, self.rigid.motion,
                                  radius=settings.search_radius, step=rpx_to_normalized(settings.search_step_rpx),
                                  prior_width=settings.search_prior, gain=settings.search_gain,
                                  margin=settings.search_margin,
                                  exclusion=rpx_to_normalized(settings.search_exclusion_rpx), headings=headings,
                                  side_width=settings.search_side)
            del smooth_targets
        self.image = self.raster.new_image(problems)
        self.loss = wp.zeros(problems, dtype=float, device=device, requires_grad=True)
        self.ones = wp.ones(problems, dtype=float, device=device)

    def _fit_loss(self, batch: GaussianBatch) -> np.ndarray:
        self.loss.zero_()
        self.raster.render(batch, out=self.image)
        self.fit(self.image, out=self.loss)
        return self.loss.numpy().astype(np.float64)

    def run(self, stop, progress, *, graphs: bool = False) -> tuple:
        s = self.s
        source_loss = self._fit_loss(self.source)
        tape = wp.Tape()

        def iterate(step_count: int, losses, optimiser) -> None:
            step = ReplayedStep(adam_iteration(tape, self.loss, self.ones, losses, optimiser), self.moving.device,
                                graphs=graphs)
            for iteration in range(step_count):
                if stop.is_set():
                    raise Cancelled
                step()
                if progress is not None and (iteration + 1) % 10 == 0:
                    progress(10)
            if progress is not None:
                progress(step_count % 10)

        def rigid_losses():
            self.rigid.apply(self.moving)
            self.fit.of_render(self.raster, self.moving, image=self.image, out=self.loss, value=False)

        rigid_adam = RigidAdam(self.rigid, lr_translation_rpx=s.lr_translation_rpx, lr_rotation=s.lr_rotation,
                               beta1=s.adam.beta1, beta2=s.adam.beta2, epsilon=s.adam.epsilon)
        iterate(s.rigid_iterations, rigid_losses, rigid_adam)
        self.rigid.apply(self.moving)
        rigid_loss = self._fit_loss(self.moving)

        def full_losses():
            self.fit.of_render(self.raster, self.moving, image=self.image, out=self.loss, weight=s.c_fit, value=False)
            if s.c_str > 0:
                self.structure(self.moving, out=self.loss, weight=s.c_str)
            if s.c_ene > 0:
                self.energy(self.moving, out=self.loss, weight=s.c_ene)

        iterate(s.iterations, full_losses, GaussianAdam(self.moving, s.adam))

        params = self.moving.numpy()
        diverged = params.active & ~params.finite
        restored = diverged.sum(axis=1)
        if diverged.any():
            for name in ("amplitude", "mean", "sigma", "theta", "weight"):
                getattr(params, name)[diverged] = getattr(self.source_params, name)[diverged]
            self.moving.assign(params)
        loss = self._fit_loss(self.moving)
        structure = wp.zeros(self.source.problem_count, dtype=float, device=self.source.device)
        self.structure(self.moving, out=structure)
        return params, source_loss, rigid_loss, loss, structure.numpy().astype(np.float64), restored


def restore_vanished(sources: GaussianParams, retargeted: GaussianParams, share: float, *,
                     sigma_eps: float) -> tuple[GaussianParams, np.ndarray]:
    """Retargeted slots that kept less than ``share`` of their source's energy (``gaussian_energy_rpx``)
    put back at their source: the Gaussian found nothing to follow on the target (its highlight
    vanishes there, e.g. into a shadow) and keeps its shape along that edge instead of shrinking to a
    point. ``sources``: (E, N) each edge's source set. Returns the sets and the (E, N) mask of restored
    slots (``RetargetSettings.vanish_share``; 0 restores none)."""
    if share <= 0:
        return retargeted, np.zeros_like(retargeted.active)
    before, after = gaussian_energy_rpx(sources, sigma_eps), gaussian_energy_rpx(retargeted, sigma_eps)
    vanished = retargeted.active & sources.active & (after < share * before)
    if not vanished.any():
        return retargeted, vanished
    return sources.where(vanished, retargeted), vanished
