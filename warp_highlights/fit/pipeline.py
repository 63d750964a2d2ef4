"""The whole precomputation: reflectance field -> highlight field (docs/method.md, Fitting; docs/file-format.md).

segment -> estimate -> triangulate -> retarget (components, phase 1, phase 2) -> decide paths ->
decide which Gaussians move -> check at left-out captured lights that moving beats blending (else the
field keeps no Gaussians) -> the residual (images minus their highlights, for residual transfer).
Each stage runs batched over all lights or all directed edges; ``fit_field`` times them and collects
the figures the ``fit`` command prints.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from contextlib import contextmanager

import numpy as np
import warp as wp

from .. import __version__
from ..io.dataset import ReflectanceField
from ..io.resample import resample_image, resize_stack, working_size
from ..kernels.segmentation import band_rows, host_array, segment, segment_in_bands
from ..kernels.transfer import to_host
from ..kernels.warmup import InBackground
from ..model.config import FitSettings
from ..model.errors import InputError
from ..model.field import DiffuseModel, HighlightField
from ..model.gaussians import GaussianParams
from ..model.memory import PeakMemory, available_memory
from ..model.triangulation import SphericalTriangulation
from ..residual.build import build_residual
from ..residual.inputs import (
    highlight_colour,
    hold_images,
    holds_images,
    render_own,
    render_own_on_device,
)
from ..residual.interpolation import choose_interpolation
from ..residual.kind import cpu_epochs, resolve_kind
from ..residual.learned import (
    bounded,
    check_learned,
    learn_residual,
    learned_epochs,
    learned_seconds,
    learns_anew,
)
from ..residual.rate import gaussian_bytes
from .coherence import motion_coherence
from .estimation import estimate
from .lost import expected_motion, follow_lost
from .moving import decide_moving
from .paths import decide_paths
from .retargeting import restore_vanished, retarget
from .validation import check_moving, leave_one_out, plan_check, spread_lights

__all__ = ["DIFFUSE_CHOICES", "default_exposure", "exposure_factor", "fit_field", "moving_energy_share"]

_LOG = logging.getLogger(__name__)

DIFFUSE_CHOICES = ("lambert", "images", "none")

_SHARE_BYTES = 256 * 2**20  # the moving Gaussians' energy share draws their lights' images in parts of this size


def fit_field(
    dataset: ReflectanceField,
    *,
    settings: FitSettings | None = None,
    device=None,
    size: tuple[int, int] | None = None,
    diffuse: str = "none",
    exposure: float | str | None = None,
    workers: int | None = None,
    progress: bool = False,
    log=None,
) -> HighlightField:
    """Fit a highlight field to a reflectance field.

    Args:
        dataset: images and light directions.
        settings: every hyper-parameter (``FitSettings``).
        device: Warp device (default: Warp's default, CUDA when present).
        size: working resolution (width, height) of the same aspect ratio, or None for the images' own.
        diffuse: the optional Lambertian diffuse model: "lambert" (per-pixel nbar and k_a), "images"
            (that plus the diffuse images, float16) or "none" (default: residual transfer needs none).
        exposure: factor applied to the radiance before fitting, or "auto": the factor that maps the
            99.9th percentile of all samples to 1 (display white). The method's thresholds (lit sample
            0.05, new Gaussian 0.2) assume display white is 1, as in rendered data; a dim photographic
            capture needs "auto" (or its own factor) or its highlights stay under the thresholds. The
            fitted field is in the scaled units and records the factor (``report["exposure"]``);
            relighting divides by it. None (default): ``default_exposure(dataset)``.
        workers: CPU threads (default: one per core); ignored on CUDA.
        progress: show a progress bar per stage (tqdm, on stderr).
        log: callable receiving one line per finished stage (default: this module's logger, at INFO).
    """
    settings = settings or FitSettings()
    if diffuse not in DIFFUSE_CHOICES:
        raise InputError(f"diffuse must be one of {', '.join(DIFFUSE_CHOICES)}, got '{diffuse}'")
    device = wp.get_device(device)
    log = log or _LOG.info
    timer = _StageTimer(log, device)
    width, height = working_size(dataset.width, dataset.height, size)
    requested_kind = settings.residual.kind
    # once: the stages read it
    kind = resolve_kind(requested_kind, device, light_count=dataset.light_count, size=(width, height),
                        channels=dataset.channels)
    # on the CPU: the epochs a learned residual would get in its training time at this machine's pace
    epochs_in_time = cpu_epochs(requested_kind, kind, device, settings.residual, light_count=dataset.light_count,
                                size=(width, height), channels=dataset.channels)
    if epochs_in_time is not None:
        wanted = settings.residual.cpu_learned_epochs
        pace = (f"about {epochs_in_time:.0f} epochs in {learned_seconds(settings.residual, False):g} s at this CPU's "
                f"pace")
        if epochs_in_time >= wanted:
            kind = "learned"
            log(f"the residual is learned ({pace})")
        else:
            log(f"the residual is low rank ({pace}, under residual.cpu_learned_epochs={wanted})")
    settings = dataclasses.replace(settings, residual=dataclasses.replace(settings.residual, kind=kind))
    residual = kind != "none"
    learned = kind == "learned"

    with timer.stage("triangulation"):
        triangulation = SphericalTriangulation(dataset.lights.directions)
        edges = triangulation.directed_edges()
    planning = None
    # the move check's left-out lights, host work that depends on the lights alone, planned in a thread while the device
    # fits (the fit's thread mostly waits for it)
    # a decoder that sees the Gaussians learns every light with its moved ones (every light is checked), or with its
    # own, the learned check's lights with the moved ones (``residual.learned_seeing_inputs``)
    sees = learned and settings.residual.learned_sees_gaussians
    sees_own = sees and settings.residual.learned_seeing_inputs == "own"
    check_count = dataset.light_count if sees and not sees_own else settings.residual.check_lights
    if residual and device.is_cuda:
        planning = InBackground(lambda stop: plan_check(dataset.lights.directions, edges, check_count),
                                name="check-plan")
    try:
        with timer.stage("segmentation"):
            images = resize_stack(dataset.images, width, height)
            factor = exposure_factor(images, default_exposure(dataset) if exposure is None else exposure)
            if factor != 1.0:
                images = images * np.float32(factor)
            # for the highlight colour
            # and for a learned residual's diffuse part under the highlights
            under = learned and not sees and settings.residual.diffuse_under_highlights > 0
            keep_specular = residual and images.ndim == 4 and (settings.residual.highlight_colour or under)
            gaussian_width, gaussian_height = settings.estimation.gaussian_size(width, height)
            # the specular part kept as float16 (for the highlight colour alone: half the host memory, and on CUDA half
            # the bytes to bring down); short of host memory (CPU): bands whose specular luminance is shrunk band by
            # band where the Gaussians' rows divide the working rows
            on_host = not device.is_cuda
            shrink_rows = (height // gaussian_height
                           if on_host and height % gaussian_height == 0 and gaussian_height < height else 1)
            # on CUDA: the Gaussians' targets shrunk there where the sizes divide by one whole factor
            whole = height // gaussian_height
            shrink_factor = (whole if not on_host and whole > 1 and height == whole * gaussian_height
                             and width == whole * gaussian_width else 1)
            rows = band_rows(images.shape, device, host_free=available_memory() if on_host else None,
                             keep_specular=keep_specular,
                             keep_diffuse=diffuse == "images", specular_bytes=2,
                             target_share=1.0 / max(shrink_rows, shrink_factor) ** 2)
            # a small capture's images, sent up for the segmentation in one band, stay there for the move check and the
            # residual's stacks
            holds_up = (residual and not learned
                        and holds_images(images.shape if images.ndim == 4 else images.shape + (1,), device))
            # row bands (one where it fits), the parts in host memory: on CUDA each image's rows go up and come down as
            # they are
            if rows < height or not on_host:
                shrink = ((lambda band: resize_stack(band, gaussian_width, band.shape[1] // shrink_rows))
                          if shrink_rows > 1 else None)
                seg = segment_in_bands(images, dataset.lights.directions, rows=rows, settings=settings.segmentation,
                                       device=device, workers=workers,
                                       keep_specular=keep_specular, keep_diffuse=diffuse == "images",
                                       specular_dtype=np.float16, shrink_target=shrink, target_rows=shrink_rows,
                                       shrink_factor=shrink_factor, target_on_device=not on_host,
                                       # the move check's images
                                       shrink_images=shrink_factor > 1 and residual and not learned,
                                       keep_images=holds_up)
            else:
                seg = segment(images, dataset.lights.directions, settings=settings.segmentation, device=device,
                              workers=workers, keep_diffuse=diffuse == "images")
            # what the Gaussians are fitted to, shrunk where the images are large
            specular_luminance = seg.specular_luminance
            # not shrunk band by band already
            if tuple(specular_luminance.shape[1:3]) != (gaussian_height, gaussian_width):
                specular_luminance = resize_stack(host_array(seg.specular_luminance), gaussian_width, gaussian_height)
            if not isinstance(specular_luminance, wp.array):
                specular_luminance = wp.array(specular_luminance, dtype=float, device=device)
            # what the later stages need of the full-size parts, in host memory; the device keeps none of them
            # float16 in every case, as the bands keep it (``specular_dtype``): the highlight colour is the same whether
            # the stack was segmented whole or in bands
            specular = host_array(seg.specular).astype(np.float16, copy=False) if keep_specular else None
            # as the field keeps them
            diffuse_images = host_array(seg.diffuse).astype(np.float16) if diffuse == "images" else None
            shrunk_images = seg.shrunk_images  # the images at the Gaussians' size, where made on the device
            images_up = seg.images  # the images as sent up, where kept there (``holds_up``)
            seg.diffuse = seg.specular = seg.specular_luminance = seg.shrunk_images = seg.images = None
            wp.synchronize_device(device)
        with timer.stage("estimation"), _bar(progress, "estimation", settings.estimation.iterations,
                                             dataset.light_count) as advance:
            estimated = estimate(specular_luminance, settings=settings.estimation, raster=settings.raster,
                                 device=device, workers=workers, progress=advance)
        with timer.stage("retargeting"), _bar(progress, "retargeting",
                                              settings.retarget.rigid_iterations + settings.retarget.iterations,
                                              len(edges)) as advance:
            retargeted = retarget(estimated.params, specular_luminance, edges, settings=settings.retarget,
                                  directions=dataset.lights.directions,
                                  raster=settings.raster, device=device, workers=workers, progress=advance)
        with timer.stage("paths"):
            source = estimated.params
            edge_sources = source.take(edges[:, 0])
            sets, vanished = restore_vanished(edge_sources, retargeted.params, settings.retarget.vanish_share,
                                              sigma_eps=settings.raster.sigma_eps)
            left_frame = followed = np.zeros_like(vanished)
            motion = None
            if settings.retarget.follow_lost:
                placed = follow_lost(edge_sources, sets, vanished, edges, dataset.lights.directions,
                                     specular_luminance, share=settings.retarget.lost_share,
                                     ridge=settings.retarget.motion_ridge, landing=settings.residual.move_support,
                                     raster=settings.raster)
                sets, left_frame, followed, motion = placed.sets, placed.left_frame, placed.followed, placed.motion
                found = placed.found
            else:
                found = edge_sources.active & sets.active & ~vanished
            # whether each Gaussian's motion follows the light (reported; holds back glints where asked)
            fitted = motion if motion is not None else expected_motion(
                edge_sources, sets, found, edges, dataset.lights.directions, ridge=settings.retarget.motion_ridge)
            coherence = motion_coherence(edge_sources, sets, found, edges, dataset.lights.directions, fitted)
            decisions = decide_paths(edge_sources, sets, settings.paths)

        moving = source.active.copy()
        kept, kept_retargeted = source, sets  # the Gaussians the field keeps
        path_delta, path_centre = decisions.delta.astype(np.float32), decisions.centre.astype(np.float32)
        residual_model = None
        learned_history = None
        specular_under = None  # the specular part, where a learned residual learns the diffuse part under them
        compression: dict = {}  # the low-rank residual's budget and captured-light score
        anew = False  # the learned residual learned anew from every light rather than go on from the check's winner
        support_median = None
        incoherent = 0  # Gaussians held in place because their motion does not follow the light (``fit.coherence``)
        near = 0  # Gaussians held in place because their highlight travels too little to be moved (``fit.moving``)
        left = 0  # Gaussians that do not move, left to a decoder that sees the others (``residual.learned_seeing_*``)
        decided = np.isfinite(coherence) & source.active
        coherence_median = round(float(np.median(coherence[decided])), 3) if decided.any() else None
        check = learned_check = interpolation = None
        if residual:
            with timer.stage("residual"):
                decision = decide_moving(source, sets, edges, specular_luminance, settings=settings.residual,
                                         left_frame=left_frame, coherence=coherence,
                                         least_coherence=(settings.residual.learned_seeing_coherence if sees
                                                          else settings.residual.move_coherence),
                                         least_travel=settings.residual.learned_seeing_travel if sees else 0.0,
                                         raster=settings.raster)
                moving = decision.moving
                if sees:
                    # a decoder that sees the moving Gaussians learns the highlights that stay as it learns the images:
                    # only the moving ones are its inputs and kept
                    left = int((source.active & ~moving).sum())
                    source = source.where(moving, GaussianParams.empty(*moving.shape))
                    sets = sets.where(moving[edges[:, 0]], GaussianParams.empty(*sets.active.shape))
                    kept, kept_retargeted = source, sets
                incoherent = int(decision.incoherent.sum())
                near = int(decision.near.sum())
                support_median = float(np.nanmedian(decision.support)) if np.isfinite(decision.support).any() else 0.0
                own_up = render_own_on_device(source, height, width, raster=settings.raster, device=device)
                own = to_host(own_up)
                if images_up is None:
                    own_up = None  # nothing held: the device lets it go
                colour = None
                if specular is not None and settings.residual.highlight_colour:
                    colour = highlight_colour(specular, own, prior=settings.residual.colour_prior)
                # what a learned residual learns under the highlights (``residual.inputs.diffuse_under_highlights``)
                specular_under = specular if under else None
                specular = None
            with timer.stage("move check"):
                # held there, where small (the segmentation's upload, the own highlights' render), for the check's
                # scores and the compressed residual's stacks
                held = None if learned else hold_images(images if images.ndim == 4 else images[..., None], own, device,
                                                        images_up=images_up, own_up=own_up)
                images_up = own_up = None  # held (or not needed): the stages after read them through ``held`` alone
                if planning is not None and moving.any():
                    plan = planning.result()
                else:
                    lights = check_count if moving.any() else 0
                    plan = plan_check(dataset.lights.directions, edges, lights)
                iterations = settings.retarget.rigid_iterations + settings.retarget.iterations
                check_images, check_own, check_colour = images, own, colour
                if (gaussian_width, gaussian_height) != (width, height) and not learned:
                    # a decision, not an output: scored where the Gaussians were fitted (a 4K capture: 16 times fewer
                    # pixels)
                    check_images = (shrunk_images if shrunk_images is not None
                                    else resize_stack(images, gaussian_width, gaussian_height))
                    check_own = render_own(source, gaussian_height, gaussian_width, raster=settings.raster,
                                           device=device)
                    check_colour = None if colour is None else resample_image(colour, gaussian_width, gaussian_height)
                with _bar(progress, "move check", iterations, len(plan.missing)) as advance:
                    check = check_moving(plan, source, sets, edges, path_delta, moving, specular_luminance,
                                         check_images, check_own, check_colour,
                                         factor=factor, settings=settings, device=device, workers=workers,
                                         progress=advance,
                                         keep=settings.residual.learned_check if learned else 0,
                                         held=held if check_images is images else None,
                                         directions=dataset.lights.directions, draw_all=sees, motion=motion)
                seen = None  # the Gaussians a decoder that sees them learns each light with (and is checked with)
                if sees and check.moved_luminance is not None:
                    seen = own.copy()  # a light the others cannot locate sees its own
                    # its own at every light, the moved ones at the learned check's; or the moved ones at every light
                    if sees_own:
                        row = {int(light): k for k, light in enumerate(check.lights)}
                        seen[check.kept_lights] = check.moved_luminance[[row[int(k)] for k in check.kept_lights]]
                    else:
                        seen[check.lights] = check.moved_luminance
            # a decoder that sees the Gaussians is weighed by the learned check alone: the move check weighs moving
            # against blending the images, which it does not do
            weighed = check.moves or (seen is not None and moving.any() and len(check.kept_lights) > 0)
            if learned and weighed and len(check.kept_lights):
                on_cuda = wp.get_device(device).is_cuda
                epochs = learned_epochs(settings.residual, on_cuda)
                # where the check's left-out lights are a large share of the capture (on CUDA: always), its winner
                # (fitted without them for a while) is not kept, the decided residual learns anew from every light:
                # the check stops once settled
                anew = learns_anew(settings.residual, len(check.kept_lights), dataset.light_count, on_cuda)
                with timer.stage("learned check"), _bar(progress, "learned check", 2 * epochs,
                                                        1) as advance:
                    learned_check = check_learned(images, own, colour, dataset.lights.directions, check.kept_lights,
                                                  check.kept_highlights,
                                                  factor=factor, settings=settings.residual, device=device,
                                                  progress=advance, seen=seen, winner_kept=not anew,
                                                  specular=specular_under, coherence=coherence_median)
                verdict = learned_check.report()
                settled = learned_check.settled_epoch
                log(f"learned check at {verdict['lights']} lights: with the Gaussians"
                    + (" as the decoder's inputs " if verdict["sees_gaussians"] else " ")
                    + f"{verdict['with_gaussians_psnr_db']:.2f} dB"
                    + (f" ({verdict['exact_residual_psnr_db']:.2f} with its residual exact)"
                       if "exact_residual_psnr_db" in verdict else "")
                    + f", the images alone {verdict['images_alone_psnr_db']:.2f} dB"
                    + ("" if settled is None else f" (settled after {settled} epochs)"))
            if (not moving.any() or not weighed
                    or (learned_check is not None and not learned_check.keeps_gaussians)):
                # no Gaussian moves (each would only be blended in place, as the residual is, and a learned
                # residual would learn the images less their highlights), or blending beat moving at the left-out
                # lights, or the images learned alone beat the learned residual with its Gaussians: the
                # highlights stay in the residual (the images themselves) and the field keeps no Gaussians,
                # which leaves their bytes to the residual
                # one free slot each
                kept, kept_retargeted = GaussianParams.empty(len(source.active), 1), GaussianParams.empty(len(edges), 1)
                moving = np.zeros((len(source.active), 1), dtype=bool)
                incoherent = near = left = 0  # none kept: none held back either
                path_delta, path_centre = (np.zeros((len(edges), 1), np.float32),
                                           np.zeros((len(edges), 1, 2), np.float32))
                own, colour, seen, specular_under = np.zeros_like(own), None, None, None
                if held is not None:
                    held.own = None  # the residual's stacks read the zeros from the host
            if kind == "images":
                held = None  # the residual keeps the images themselves: nothing more reads them there
            cuda = wp.get_device(device).is_cuda
            if seen is not None and sees_own:
                seen = own  # the field's decoder learns every light with its own Gaussians
            if learned and learned_check is not None and learned_check.learned_every_light and not anew:
                # the check's winner learned from every light once its verdict settled
                residual_model, learned_history = learned_check.winner, list(learned_check.history)
            elif learned:
                # the check's winner goes on learning from every light (the ones it left out too), or learns anew
                # (above); without a check, one model learns every light
                winner = None if learned_check is None or anew else learned_check.winner.learned
                epochs = (settings.residual.learned_tune_epochs if winner is not None
                          else learned_epochs(settings.residual, cuda))
                with timer.stage("learned residual"), _bar(progress, "learned residual", epochs, 1) as advance:
                    residual_model, learned_history = learn_residual(images, own, colour, dataset.lights.directions,
                                                                     factor=factor,
                                                                     settings=settings.residual, device=device, log=log,
                                                                     progress=advance,
                                                                     initial=winner, tune=winner is not None,
                                                                     highlights=seen, specular=specular_under)
            specular_under = None
            if learned and settings.residual.learned_bounds:  # the decided residual, whichever way it was learned
                # a decoder that sees the Gaussians learned the images themselves
                taken = (own, colour) if seen is None else (np.zeros_like(own), None)
                residual_model = bounded(residual_model, images, *taken)
            if not learned:
                with timer.stage("residual compression"):
                    residual_model = build_residual(images, own, colour, settings=settings.residual,
                                                    other_bytes=gaussian_bytes(kept, kept_retargeted),
                                                    device=device, held_images=held, display_scale=1.0 / factor,
                                                    report=compression)
                budget = settings.residual.size_budget
                if compression.get("size_budget", budget) > budget:
                    log(f"the residual gave the captured lights back at under "
                        f"{settings.residual.min_captured_psnr_db:g} dB within {100 * budget:.0f}% of the capture; "
                        f"it takes {100 * compression['size_budget']:.0f}% ({compression['captured_psnr_db']:.1f} dB)")
            if kind == "lowrank" and settings.residual.interpolation != "triangle":
                with timer.stage("residual interpolation"):
                    directions = dataset.lights.directions
                    loo = (plan.loo if len(plan.loo.lights) or dataset.light_count < 5
                           else leave_one_out(directions, spread_lights(directions, settings.residual.check_lights)))
                    residual_model, interpolation = choose_interpolation(
                        residual_model, images if images.ndim == 4 else images[..., None], own, colour, directions,
                        loo.lights, loo.vertices, loo.barycentric, factor=factor, settings=settings.residual)
                verdict = interpolation.report()
                if "rbf_psnr_db" in verdict:
                    log(f"residual interpolation at {verdict['lights']} lights: the triangle's "
                        f"{verdict['triangle_psnr_db']:.2f} dB, radial basis {verdict['rbf_psnr_db']:.2f} dB: "
                        f"{verdict['chosen']}")
            held = None
    finally:  # an error or Ctrl-C meanwhile: the plan not left running (it is host work of a fraction of a second)
        if planning is not None:
            planning.cancel()

    diffuse_model = None
    if diffuse != "none":
        lambert = np.nan_to_num(seg.lambert, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
        if diffuse_images is not None:
            diffuse_images = diffuse_images if diffuse_images.ndim == 4 else diffuse_images[..., None]
        diffuse_model = DiffuseModel(lambert=lambert, images=diffuse_images)

    counts = estimated.counts
    moving_share = (moving_energy_share(kept, moving, specular_luminance, raster=settings.raster, device=device)
                    if residual_model is not None else None)
    report = {
        "version": __version__,
        "device": str(device),
        # the files' size, before any shrink at load
        "source_size": (dataset.source or {}).get("size", [dataset.width, dataset.height]),
        "input": dataset.source,  # format, bits per channel, sRGB or linear, ICC profile of the capture's files
        "size": [width, height],
        "gaussian_size": [gaussian_width, gaussian_height],  # where the Gaussians were estimated and retargeted
        "lights": dataset.light_count,
        "exposure": factor,
        "residual_kind": {"requested": requested_kind, "resolved": kind},  # ResidualSettings.kind, resolved once
        "directed_edges": len(edges),
        "dome": bool(triangulation.is_dome),
        "seconds": timer.seconds,
        # per stage: peak resident host bytes and peak bytes of Warp's CUDA memory pool (None off CUDA)
        "memory": timer.memory,
        "segmentation": {"few_light_pixels": seg.few_light_pixels, "mean_iterations": float(seg.iterations.mean())},
        "estimation": {
            "gaussians_per_light": _stats(counts),
            "psnr_db": _stats(estimated.psnr),
            "loss": _stats(estimated.loss),
            "added": int(estimated.added.sum()),
            "pruned": int(estimated.pruned.sum()),
        },
        "retargeting": {
            "source_loss": _stats(retargeted.source_loss),
            "rigid_loss": _stats(retargeted.rigid_loss),
            "loss": _stats(retargeted.loss),
            "structure_loss": _stats(retargeted.structure_loss),
            "improved_share": float(np.mean(retargeted.loss <= retargeted.source_loss + 1e-6)),
            "restored_slots": int(retargeted.restored.sum()),
            "vanished_slots": int(vanished.sum()),
            "left_frame_slots": int(left_frame.sum()),
            "followed_slots": int(followed.sum()),
        },
        "residual": None if residual_model is None else {
            "moving_gaussians": int(moving.sum()),
            "staying_gaussians": int(kept.active.sum() - moving.sum()),
            "incoherent_gaussians": incoherent,
            "near_gaussians": near,
            "left_gaussians": left,
            # the median motion coherence of the Gaussians that have one (``fit.coherence``): near 1 where highlights
            # glide with the light, near 0 where glints twinkle in place
            "motion_coherence": coherence_median,
            "kept_gaussians": int(kept.active.sum()),
            # what the moving Gaussians carry of the specular part the segmentation found
            "moving_specular_share": moving_share,
            "median_support": support_median,
            "move_check": check.report() if check is not None else None,
            "learned_check": learned_check.report() if learned_check is not None else None,
            # "auto" on the CPU: the epochs its training time held, which chose learned or low rank
            "cpu_epochs": None if epochs_in_time is None else round(float(epochs_in_time), 1),
            "residual_interpolation": interpolation.report() if interpolation is not None else None,
            "luminance_rank": residual_model.luminance.rank if kind == "lowrank" else None,
            "chroma_rank": residual_model.chroma.rank if residual_model.chroma is not None else None,
            "basis_bits": residual_model.luminance.bits if kind == "lowrank" else None,
            # the share of the 8-bit capture the low-rank residual was given, and its captured lights' score
            "size_budget": compression.get("size_budget"),
            "captured_psnr_db": compression.get("captured_psnr_db"),
            "highlight_colour": residual_model.highlight_colour is not None,
            "learned": None if learned_history is None else {"epochs": len(learned_history),
                                                             "final_mse": float(learned_history[-1]),
                                                             "continued_from_check": learned_check is not None
                                                             and not anew},
        },
        "paths": {"negative_share": float(decisions.negative[source.active[edges[:, 0]]].mean()) if counts.sum()
                  else 0.0},
        "per_light": {"gaussians": counts.tolist(), "psnr_db": np.round(estimated.psnr, 3).tolist()},
    }
    return HighlightField(
        lights=dataset.lights,
        triangulation=triangulation,
        width=width,
        height=height,
        estimated=kept,
        directed_edges=edges,
        retargeted=kept_retargeted,
        path_delta=path_delta,
        path_centre=path_centre,
        settings=settings.to_dict(),
        report=report,
        diffuse=diffuse_model,
        residual=residual_model,
        moving=moving if residual_model is not None else None,
    )


def moving_energy_share(gaussians: GaussianParams, moving: np.ndarray, specular_luminance: wp.array, *,
                        raster, device) -> float:
    """Share of the segmented specular energy (the sum of ``specular_luminance``, (n, H, W), over every
    light and pixel) that the moving Gaussians draw there, in [0, 1]."""
    total = float(wp.utils.array_sum(specular_luminance.flatten())) if specular_luminance.size else 0.0
    if total <= 0.0 or not moving.any():
        return 0.0
    only_moving = dataclasses.replace(gaussians, amplitude=np.where(moving, gaussians.amplitude, 0.0))
    lights = np.flatnonzero(moving.any(axis=1))
    _, height, width = specular_luminance.shape
    step = max(1, _SHARE_BYTES // (4 * height * width))  # lights drawn at once: a bounded image stack
    drawn = 0.0
    for start in range(0, len(lights), step):
        part = render_own_on_device(only_moving.take(lights[start:start + step]), height, width, raster=raster,
                                    device=device)
        drawn += float(wp.utils.array_sum(part.flatten()))
    return float(np.clip(drawn / total, 0.0, 1.0))


def default_exposure(dataset: ReflectanceField) -> float | str:
    """"auto" for display-referred captures (every image a JPEG/PNG/TIFF/... file), else 1.0 (linear
    radiance such as EXR renders, or images made in memory, whose 1 is display white already)."""
    return "auto" if dataset.display_referred else 1.0


_EXPOSURE_VALUES = 1 << 27
"""Values the automatic exposure's percentile reads at most (512 MB of float32 copied; a 54-image 567x534
capture is 49 million, a 100-image 3840x2160 one 2.5 billion: every 5th pixel of every 5th row)."""


def exposure_factor(images: np.ndarray, exposure: float | str) -> float:
    """The radiance factor for ``exposure``: a positive number as it is, or "auto" (99.9th percentile -> 1)."""
    if isinstance(exposure, str):
        if exposure.strip().lower() != "auto":
            try:
                exposure = float(exposure)
            except ValueError:
                raise InputError(f"exposure must be a positive number or 'auto', got '{exposure}'") from None
        else:
            sample = images[:: max(1, len(images) // 64)]  # at most about 64 images ...
            stride = 1
            while sample[:, ::stride, ::stride].size > _EXPOSURE_VALUES:  # ... and values: the percentile copies them
                stride += 1
            level = float(np.percentile(sample[:, ::stride, ::stride], 99.9))
            if not np.isfinite(level) or level <= 0:
                raise InputError(
                    "cannot pick an exposure automatically: the images are black; pass --exposure with a factor")
            return 1.0 / level
    if not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure must be a positive number or 'auto', got {exposure}")
    return float(exposure)


def _stats(values) -> dict:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return {"mean": 0.0, "min": 0.0, "max": 0.0, "p5": 0.0, "p95": 0.0}
    return {
        "mean": float(values.mean()),
        "min": float(values.min()),
        "max": float(values.max()),
        "p5": float(np.percentile(values, 5)),
        "p95": float(np.percentile(values, 95)),
    }


class _StageTimer:
    """Each stage's seconds and peak host and device memory (``PeakMemory``), and a log line per stage."""

    def __init__(self, log, device=None):
        self.log = log
        self.device = device
        self.seconds: dict[str, float] = {}
        self.memory: dict[str, dict] = {}

    @contextmanager
    def stage(self, name: str):
        started = time.perf_counter()
        with PeakMemory(self.device) as peak:
            yield
        self.seconds[name] = round(time.perf_counter() - started, 3)
        self.memory[name] = peak.report()
        if self.log is not None:
            self.log(f"{name}: {self.seconds[name]:.1f} s")


@contextmanager
def _bar(enabled: bool, name: str, iterations: int, problems: int):
    """A tqdm bar over the stage's ``iterations`` and a thread-safe ``advance(k)`` for its chunks.

    Every chunk (one per CPU thread, or one of a device's parts) reports its steps times its share of
    the problems (``kernels.chunks.chunk_progress``), so the bar fills once whatever the split.
    """
    if not enabled:
        yield None
        return
    from tqdm import tqdm

    lock = threading.Lock()
    desc = f"{name} ({problems} sets)" if problems > 1 else name
    with tqdm(total=iterations, desc=desc, unit="step", leave=False, mininterval=0.5,
              bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}]") as bar:

        def advance(steps: float) -> None:
            with lock:
                bar.update(steps)

        yield advance
