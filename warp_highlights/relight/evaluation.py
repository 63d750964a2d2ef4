"""Compare a fitted field with ground truth at held-out light directions (docs/method.md, Evaluation).

For every held-out direction (the thesis' protocol: the centroid of every triangle) the field is
relit with each method and compared with the ground truth:

- ``specular``: S' against the ground-truth specular luminance (when the dataset has it), in the
  field's units (the fit's exposure applied) - the protocol's figure;
- ``full``: I' against the held-out image, in the dataset's units (when the field has a residual
  or diffuse model; the alpha method blends the dataset's images): linear PSNR, and as RTI users
  measure it, PSNR of the 8-bit sRGB images and their SSIM (scikit-image), per light and summarised.
  The classic RTI methods (``baselines``: PTM, HSH, RBF, fitted to the same training lights, on
  sRGB-encoded values for a photographic capture as RTI viewers do, on radiance otherwise) are scored
  the same way, and the worst lights' images are kept for a figure.

PSNR has peak 1 on images clipped to [0, 1]. A query whose image and ground truth are both all zero
is left out and counted (``excluded``). The alpha baseline blends the specular images that the
field's own segmentation settings give for the dataset's images.

Optionally (``barycentric_steps``), one triangle is sampled on a barycentric grid, with ground truth
rendered anew from the dataset's ``meta.json`` (synthetic datasets of the built-in shapes): PSNR
over the position inside a triangle (the thesis' Fig. 4.12).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..io.images import linear_to_srgb, srgb_to_linear
from ..io.resample import resize_stack
from ..model.errors import InputError
from ..model.residual import LUMINANCE_WEIGHTS
from ..quality.metrics import psnr_excluding_black, srgb_scores
from .baselines import BASELINE_METHODS, fit_baseline, minimum_lights
from .relighter import RELIGHT_METHODS, Relighter, alpha_inputs, check_same_lights

__all__ = ["Evaluation", "barycentric_grid", "evaluate_field", "highlights_added_to", "psnr_excluding_black",
           "srgb_scores", "summarize"]

_WORST_EXAMPLES = 3  # held-out lights (the worst of the first method) whose full images are kept



@dataclass
class Evaluation:
    """What ``evaluate_field`` measured; ``to_dict`` gives the JSON report.

    Attributes:
        directions: (Q, 3) held-out directions.
        faces, barycentric: where each fell in the triangulation.
        specular_psnr: method -> (Q,) dB, NaN where excluded; empty without specular ground truth.
        full_psnr: method -> (Q,) linear dB for full images; empty when not measured.
        full_srgb_psnr, full_ssim: method -> (Q,) PSNR (dB) and SSIM of the 8-bit sRGB full images.
        full_examples: "truth" and method -> (k, H, W, C) linear full images of ``full_example_queries``
            (the worst lights of the first method), and ``full_example_queries`` (k,).
        gaussians_per_light: (n,) active Gaussians of every estimated set.
        gaussians_per_query: (Q,) active Gaussians of every circular interpolated set.
        barycentric_sweep: None, or a dict with ``face``, ``vertices``, ``weights`` (K, 3) and
            ``specular_psnr`` (method -> (K,)), or with ``skipped`` (the reason).
        examples: method -> (k, H, W) S' of a few queries (``example_queries``), and "truth".
        seconds: wall time per step.
    """

    directions: np.ndarray
    faces: np.ndarray
    barycentric: np.ndarray
    specular_psnr: dict = field(default_factory=dict)
    full_psnr: dict = field(default_factory=dict)
    full_srgb_psnr: dict = field(default_factory=dict)
    full_ssim: dict = field(default_factory=dict)
    full_examples: dict = field(default_factory=dict)
    full_example_queries: np.ndarray | None = None
    gaussians_per_light: np.ndarray | None = None
    gaussians_per_query: np.ndarray | None = None
    barycentric_sweep: dict | None = None
    example_queries: np.ndarray | None = None
    examples: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Per kind (specular, full) and method: mean, p5, p95, ... of the PSNR; and win shares."""
        result = {}
        kinds = (("specular", self.specular_psnr), ("full", self.full_psnr), ("full_srgb", self.full_srgb_psnr),
                 ("full_ssim", self.full_ssim))
        for kind, scores in kinds:
            if not scores:
                continue
            part = {method: summarize(values) for method, values in scores.items()}
            pairs = [("circular", "alpha"), ("circular", "straight"), ("straight", "alpha")]
            pairs += [("circular", method) for method in scores if method in BASELINE_METHODS]
            for first, second in pairs:
                if first in scores and second in scores:
                    part[f"{first}_beats_{second}"] = win_share(scores[first], scores[second])
            result[kind] = part
        return result

    def to_dict(self) -> dict:
        """The JSON report: info, summary, Gaussian counts, per-query figures, the barycentric sweep."""
        per_query = {
            "directions": np.round(self.directions, 6).tolist(),
            "faces": self.faces.tolist(),
            "barycentric": np.round(self.barycentric, 6).tolist(),
            "gaussians": None if self.gaussians_per_query is None else self.gaussians_per_query.tolist(),
            "specular_psnr": {m: _rounded(v) for m, v in self.specular_psnr.items()},
            "full_psnr": {m: _rounded(v) for m, v in self.full_psnr.items()},
            "full_srgb_psnr": {m: _rounded(v) for m, v in self.full_srgb_psnr.items()},
            "full_ssim": {m: _rounded(v, 4) for m, v in self.full_ssim.items()},
        }
        sweep = self.barycentric_sweep
        if sweep is not None and "skipped" not in sweep:
            sweep = {
                "face": int(sweep["face"]),
                "vertices": [int(v) for v in sweep["vertices"]],
                "weights": np.round(sweep["weights"], 6).tolist(),
                "specular_psnr": {m: _rounded(v) for m, v in sweep["specular_psnr"].items()},
                "summary": {m: summarize(v) for m, v in sweep["specular_psnr"].items()},
            }
        return {
            **self.info,
            "summary": self.summary(),
            "gaussians": {
                "per_light": _count_stats(self.gaussians_per_light),
                "per_query": _count_stats(self.gaussians_per_query),
            },
            "barycentric_sweep": sweep,
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
            "per_query": per_query,
        }


def summarize(values) -> dict:
    """mean, median, p5, p95, min, max over the finite values; ``count`` of those, ``excluded`` NaNs."""
    values = np.asarray(values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    stats = {"count": int(finite.size), "excluded": int(values.size - finite.size)}
    if finite.size == 0:
        return stats | {k: None for k in ("mean", "median", "p5", "p95", "min", "max")}
    return stats | {
        "mean": float(finite.mean()),
        "median": float(np.median(finite)),
        "p5": float(np.percentile(finite, 5)),
        "p95": float(np.percentile(finite, 95)),
        "min": float(finite.min()),
        "max": float(finite.max()),
    }


def win_share(first, second) -> float | None:
    """Share of the queries (finite in both) where ``first`` scores strictly higher than ``second``."""
    first, second = np.asarray(first), np.asarray(second)
    both = np.isfinite(first) & np.isfinite(second)
    return float(np.mean(first[both] > second[both])) if both.any() else None


def barycentric_grid(steps: int) -> np.ndarray:
    """(K, 3) weights (i, j, k) / steps with i + j + k = steps, corners included; K = (s+1)(s+2)/2."""
    if int(steps) < 1:
        raise InputError(f"barycentric steps must be >= 1, got {steps}")
    steps = int(steps)
    rows = [(i, j, steps - i - j) for i in range(steps, -1, -1) for j in range(steps - i, -1, -1)]
    return np.array(rows, dtype=np.float64) / steps


def evaluate_field(
    highlight_field,
    dataset,
    *,
    device=None,
    methods: tuple[str, ...] = RELIGHT_METHODS,
    barycentric_face: int | str | None = "auto",
    barycentric_steps: int = 10,
    example_count: int = 4,
    alpha_stacks: tuple[np.ndarray, np.ndarray] | None = None,
    baselines: tuple[str, ...] = (),
    progress=None,
) -> Evaluation:
    """Relight ``highlight_field`` at the held-out lights of ``dataset`` and score every method.

    Args:
        highlight_field: the fitted ``HighlightField``.
        dataset: the ``ReflectanceField`` it was fitted to, with held-out lights (``heldout``).
        device: Warp device.
        methods: any of ``RELIGHT_METHODS``.
        barycentric_face: face to sample on a grid (Fig. 4.12): an index, "auto" (the face of the
            held-out query with the median circular - alpha gain), or None to skip.
        barycentric_steps: grid resolution of that face (weights in steps of 1 / barycentric_steps).
        example_count: held-out queries whose images are kept for a comparison figure.
        alpha_stacks: ``alpha_inputs(highlight_field, dataset)`` when the caller has them already.
        baselines: any of ``BASELINE_METHODS``, fitted to the dataset's lights at the field's size and
            scored on the full images (needs full images to compare); one with more coefficients
            than the dataset has lights is left out and named in ``info["baselines_left_out"]``.
        progress: callable(str) told about each step (default: this module's logger, at INFO).
    """
    say = progress or logging.getLogger(__name__).info
    methods = tuple(methods)
    for method in methods:
        if method not in RELIGHT_METHODS:
            raise InputError(f"method must be one of {', '.join(RELIGHT_METHODS)}, got '{method}'")
    baselines = tuple(baselines)
    for method in baselines:
        if method not in BASELINE_METHODS:
            raise InputError(f"baseline must be one of {', '.join(BASELINE_METHODS)}, got '{method}'")
    f = highlight_field
    device = wp.get_device(device)
    check_same_lights(f, dataset)
    heldout = dataset.heldout
    if heldout is None or heldout.light_count == 0:
        raise InputError(
            "the dataset has no held-out lights to compare with: pass --heldout FOLDER (other lights of the same "
            "capture, with their images), or --holdout-every K with a field fitted without lights 0, K, 2K, ... "
            "(fit DATASET --holdout-every K)"
        )
    exposure = f.exposure
    seconds = {}
    started = time.perf_counter()
    alpha_specular = alpha_images = None
    if "alpha" in methods:
        say("segmenting the dataset for the alpha blend")
        alpha_specular, alpha_images = alpha_stacks or alpha_inputs(f, dataset, device=device)
    relighter = Relighter(f, device=device, scale=1.0 / exposure, alpha_specular=alpha_specular,
                          alpha_images=alpha_images)
    seconds["set_up"] = time.perf_counter() - started

    directions = heldout.lights.directions
    truth_specular = None
    if heldout.specular is not None:
        truth_specular = luminance(resize_stack(heldout.specular, f.width, f.height)) * exposure
    truth_full = resize_stack(heldout.images, f.width, f.height)
    if truth_full.ndim == 3:
        truth_full = truth_full[..., None]
    compare_full = (f.diffuse is not None or f.residual is not None) and truth_full.shape[-1] == relighter.channels
    examples_at = np.unique(np.linspace(0, len(directions) - 1,
                                        min(example_count, len(directions))).round().astype(int))

    result = Evaluation(directions=directions, faces=np.zeros(0, int), barycentric=np.zeros((0, 3)))
    for method in methods:
        say(f"relighting {len(directions)} held-out directions ({method})")
        t = time.perf_counter()
        want_full = compare_full
        specular_scores, full_scores, srgb_parts, faces, weights, examples = [], [], [], [], [], []
        start = 0
        for chunk in relighter.iter_relight(directions, method=method, full=want_full):  # one chunk in memory at a time
            stop = start + len(chunk.specular)
            _check_finite(chunk, method)
            if truth_specular is not None:
                specular_scores.append(psnr_excluding_black(chunk.specular, truth_specular[start:stop]))
            if want_full:
                full_scores.append(psnr_excluding_black(chunk.full, truth_full[start:stop]))
                srgb_parts.append(srgb_scores(chunk.full, truth_full[start:stop]))
            faces.append(chunk.faces)
            weights.append(chunk.barycentric)
            keep = examples_at[(examples_at >= start) & (examples_at < stop)] - start
            examples.append(chunk.specular[keep])
            start = stop
        seconds[f"relight_{method}"] = time.perf_counter() - t
        result.faces, result.barycentric = np.concatenate(faces), np.concatenate(weights)
        if specular_scores:
            result.specular_psnr[method] = np.concatenate(specular_scores)
        if full_scores:
            result.full_psnr[method] = np.concatenate(full_scores)
            result.full_srgb_psnr[method] = np.concatenate([p for p, _ in srgb_parts])
            result.full_ssim[method] = np.concatenate([q for _, q in srgb_parts])
        result.examples[method] = np.concatenate(examples)
    if truth_specular is not None:
        result.examples["truth"] = truth_specular[examples_at]
    result.example_queries = examples_at
    models = {}
    left_out = [method for method in baselines if dataset.light_count < minimum_lights(method)]
    baselines = tuple(method for method in baselines if method not in left_out)
    if compare_full and baselines:
        models = _score_baselines(result, baselines, dataset, truth_full, f.width, f.height, device, say, seconds)
    if compare_full and result.full_srgb_psnr:
        _keep_worst_examples(result, relighter, models, truth_full, dataset.display_referred)
    result.gaussians_per_light = f.estimated.counts
    if "circular" in methods or "straight" in methods:
        sets = relighter.interpolated_sets(directions, method="circular")
        result.gaussians_per_query = sets.counts

    if barycentric_face is not None:
        t = time.perf_counter()
        result.barycentric_sweep = _barycentric_sweep(relighter, dataset, result, methods, barycentric_face,
                                                      barycentric_steps, exposure, device, say)
        seconds["barycentric_sweep"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - started
    result.seconds = seconds
    result.info = {
        "device": str(device),
        "size": [f.width, f.height],
        "lights": f.light_count,
        "heldout": len(directions),
        "heldout_protocol": dataset.meta.get("heldout_protocol") if dataset.meta else None,
        "exposure": exposure,
        "methods": list(methods),
        "baselines": list(baselines) if compare_full else [],
        "baselines_left_out": left_out,
        "rbf_sigma": float(models["rbf"].sigma) if "rbf" in models else None,
        "baseline_bytes_per_pixel": {name: int(model.bytes_per_pixel_8bit) for name, model in models.items()},
        "measured": [kind for kind, scores in (("specular", result.specular_psnr), ("full",
                                                                                    result.full_psnr)) if scores],
        "highlights_added_to": highlights_added_to(f) if compare_full else None,
        "moving_gaussians": int(f.moving_mask.sum()),  # of the estimated sets; the others are drawn in place
    }
    return result


def highlights_added_to(highlight_field) -> str | None:
    """What the relighter's full image I' adds the highlights S' to for this field (``diffuse="auto"``,
    ``relighter.DIFFUSE_MODES``): "residual" (I' = R~ + c S', the blended residual), "images" (the
    blended diffuse images) or "lambert" (the Lambertian model); None for a field with neither."""
    if highlight_field.residual is not None:
        return "residual"
    model = highlight_field.diffuse
    if model is None:
        return None
    return "images" if model.images is not None else "lambert"


def _score_baselines(result: Evaluation, baselines, dataset, truth_full, width: int, height: int, device, say,
                     seconds) -> dict:
    """Fit each classic RTI method to the dataset's lights and score it like the field's methods."""
    images = resize_stack(dataset.images, width, height)
    if images.ndim == 3:
        images = images[..., None]
    encoded = dataset.display_referred
    values = linear_to_srgb(np.clip(images, 0.0, 1.0)) if encoded else images
    directions = dataset.heldout.lights.directions
    models = {}
    for method in baselines:
        say(f"fitting and relighting the {method.upper()} baseline")
        t = time.perf_counter()
        model = fit_baseline(method, values, dataset.lights.directions, device=device)
        relit = model.relight(directions)
        relit = srgb_to_linear(np.clip(relit, 0.0, 1.0)) if encoded else relit
        result.full_psnr[method] = psnr_excluding_black(relit, truth_full)
        result.full_srgb_psnr[method], result.full_ssim[method] = srgb_scores(relit, truth_full)
        seconds[f"baseline_{method}"] = time.perf_counter() - t
        models[method] = (model, encoded)
    return {name: model for name, (model, _) in models.items()}


def _keep_worst_examples(result: Evaluation, relighter, models: dict, truth_full, encoded: bool) -> None:
    """Full images of the first method's worst held-out lights, for every method and the truth."""
    first = next(iter(result.full_srgb_psnr))
    scores = np.nan_to_num(result.full_srgb_psnr[first], nan=np.inf)
    worst = np.argsort(scores, kind="stable")[: min(_WORST_EXAMPLES, len(scores))]
    directions = result.directions[worst]
    result.full_example_queries = worst
    result.full_examples["truth"] = truth_full[worst]
    for method in result.full_srgb_psnr:
        if method in models:
            relit = models[method].relight(directions)
            result.full_examples[method] = srgb_to_linear(np.clip(relit, 0.0, 1.0)) if encoded else relit
        else:
            result.full_examples[method] = relighter.relight(directions, method=method).full


def _check_finite(chunk, method: str) -> None:
    for name, images in (("specular", chunk.specular), ("full", chunk.full)):
        if images is not None and not np.all(np.isfinite(images)):
            raise InputError(
                f"the {method} method gave non-finite {name} images; the field file may be damaged (refit it)")


def luminance(stack: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) -> (..., H, W) Rec. 709 luminance; single-channel stacks pass through."""
    stack = np.asarray(stack, dtype=np.float32)
    return ((stack @ np.asarray(LUMINANCE_WEIGHTS, dtype=np.float32)) if stack.shape[-1] == 3 and stack.ndim == 4
            else stack)


def _barycentric_sweep(relighter, dataset, result, methods, face, steps, exposure, device, say) -> dict:
    from ..synth.render import renderer_from_meta

    f = relighter.field
    if face == "auto":
        scores = result.specular_psnr
        if "circular" not in scores or "alpha" not in scores:
            return {"skipped": "needs specular ground truth and the circular and alpha methods"}
        gain = scores["circular"] - scores["alpha"]
        finite = np.flatnonzero(np.isfinite(gain))
        if finite.size == 0:
            return {"skipped": "no held-out query with a finite PSNR"}
        median = finite[np.argsort(gain[finite])[finite.size // 2]]
        face = int(result.faces[median])
    face = int(face)
    if not 0 <= face < f.triangulation.face_count:
        raise InputError(f"triangle {face} does not exist: the triangulation has {f.triangulation.face_count} faces "
                         f"(0..{f.triangulation.face_count - 1})")
    renderer = renderer_from_meta(dataset.meta or {}, device=str(device))
    if renderer is None:
        return {
            "skipped": "ground truth inside a triangle needs a synthetic dataset of a built-in shape (its meta.json)"}
    vertices = f.triangulation.faces[face]
    weights = barycentric_grid(steps)
    points = weights @ f.lights.directions[vertices]
    directions = points / np.linalg.norm(points, axis=1, keepdims=True)
    say(f"rendering ground truth at {len(directions)} points of triangle {face}")
    rendered = renderer.render(directions).specular
    truth = luminance(resize_stack(rendered, f.width, f.height)) * exposure
    scores = {}
    for method in methods:
        relit = relighter.relight(directions, method=method, full=False)
        _check_finite(relit, method)
        scores[method] = psnr_excluding_black(relit.specular, truth)
    return {"face": face, "vertices": vertices, "weights": weights, "specular_psnr": scores}


def _rounded(values, digits: int = 3) -> list:
    return [None if not np.isfinite(v) else round(float(v), digits) for v in np.asarray(values, dtype=np.float64)]


def _count_stats(counts) -> dict | None:
    if counts is None:
        return None
    counts = np.asarray(counts)
    if counts.size == 0:
        return {"mean": 0.0, "min": 0, "max": 0, "total": 0}
    return {"mean": float(counts.mean()), "median": float(np.median(counts)), "min": int(counts.min()),
            "max": int(counts.max()), "total": int(counts.sum())}
