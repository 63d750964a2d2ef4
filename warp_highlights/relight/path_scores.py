"""A field scored along a light path against ground truth rendered at every frame: what a person sees
when the light moves (``evaluate --path``; benchmarks/bench_motion.py does the same over many scenes).

Per method and frame: 8-bit sRGB PSNR and SSIM of the whole image, and the motion scores of
``quality.motion`` (ghost share, position error of the highlights in rpx, flicker in 8-bit levels).
The ground truth comes from the renderer that made the dataset (``synth.render.renderer_from_meta``),
resized to the field's size; the alpha method blends the dataset's images, as ``evaluate_field`` does.
"""

from __future__ import annotations

import numpy as np

from ..io.resample import resize_stack
from ..model.errors import InputError
from ..quality.metrics import srgb_scores
from ..quality.motion import motion_scores
from ..synth.render import renderer_from_meta
from .relighter import Relighter, alpha_inputs, check_same_lights

__all__ = ["path_renderer", "score_path"]


def path_renderer(dataset, device=None):
    """The renderer that made ``dataset`` (its ``meta.json``), for ground truth along a path; ``InputError``
    in one line where there is none (a photograph, a mesh file's render)."""
    renderer = renderer_from_meta(dataset.meta or {}, device=device)
    if renderer is None:
        where = f"{dataset.root}" if dataset.root is not None else "the dataset"
        raise InputError(f"{where} has no ground truth along a path: --path needs a dataset made by 'warp-highlights "
                         "render' of a built-in shape (its meta.json lets the frames be rendered anew)")
    return renderer


def score_path(field, dataset, directions: np.ndarray, *, methods=("circular", "alpha"), device=None,
               renderer=None) -> dict:
    """Relight ``field`` at ``directions`` ((F, 3), a path) with each method and score every frame.

    Returns a dict: ``frames``, and per method ``psnr_db``, ``ssim``, ``ghost_share``, ``visible_ghost_share``,
    ``position_error_rpx``, ``flicker_levels`` (each ``{"mean", "per_frame"}``; flicker per step between
    frames; NaN frames, without a highlight in the truth, left out of the means as null).
    """
    renderer = renderer or path_renderer(dataset, device)
    directions = np.asarray(directions, dtype=np.float64)
    truth = renderer.render(directions)
    parts = [resize_stack(stack, field.width, field.height) for stack in (truth.full, truth.specular, truth.diffuse)]
    if parts[0].ndim == 3:
        parts = [stack[..., None] for stack in parts]
    alpha_specular = alpha_images = None
    if "alpha" in methods:
        check_same_lights(field, dataset)
        alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
    relighter = Relighter(field, device=device, scale=1.0 / field.exposure, alpha_specular=alpha_specular,
                          alpha_images=alpha_images)
    result = {"frames": len(directions)}
    for method in methods:
        frames = np.clip(relighter.relight(directions, method=method).full, 0.0, None)
        if frames.shape[-1] != parts[0].shape[-1]:
            raise InputError(f"the field relights {frames.shape[-1]} channel(s) but the dataset's renderer makes "
                             f"{parts[0].shape[-1]}: pass the dataset the field was fitted to")
        psnr, ssim = srgb_scores(frames, parts[0])
        motion = motion_scores(frames, *parts)
        result[method] = {name: _summary(values) for name, values in (
            ("psnr_db", psnr), ("ssim", ssim), ("ghost_share", motion.ghost_share),
            ("visible_ghost_share", motion.visible_ghost_share),
            ("position_error_rpx", motion.position_error_rpx), ("flicker_levels", motion.flicker))}
    return result


def _summary(values) -> dict:
    values = np.asarray(values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    return {"mean": round(float(finite.mean()), 4) if finite.size else None,
            "per_frame": [round(float(v), 4) if np.isfinite(v) else None for v in values]}
