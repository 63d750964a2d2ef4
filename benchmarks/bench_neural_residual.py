"""A learned residual (NeuralRTI-style, ``kernels.neural``) on the samples, next to the field's compressed
residual, the alpha blend, PTM, HSH and RBF: full images at the held-out lights, and size per pixel.

    python benchmarks/bench_neural_residual.py --device cuda:0 --seconds 90     # full-size samples
    python benchmarks/bench_neural_residual.py --scale cpu --seconds 60          # reduced sizes (slow)

Per case the field is fitted with the defaults and scored by ``evaluate_field`` with the baselines.
Its residual's exact images R_i = I_i - c G_i (the captured images minus their own highlights, before
compression) are then learned as ``fit --residual learned`` learns them (``residual.learned.learn_residual``:
a code of 9 numbers per pixel and an MLP of code + light direction, trained for ``--seconds``) and
relit by the relighter with the field's moving highlights. "learned images" learns the captured
images themselves (NeuralRTI on its own, no Gaussians). Scores: 8-bit sRGB PSNR and SSIM.
Writes $OUT/bench_neural_residual.json when OUT is set.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import BASELINES, SIZES, load_case  # noqa: E402

from warp_highlights.fit.pipeline import fit_field  # noqa: E402
from warp_highlights.io.fieldfile import save_field  # noqa: E402
from warp_highlights.kernels import neural, neural_training  # noqa: E402
from warp_highlights.relight.evaluation import evaluate_field, resize_stack, srgb_scores  # noqa: E402
from warp_highlights.relight.relighter import Relighter
from warp_highlights.residual.decode import learned_images  # noqa: E402
from warp_highlights.residual.inputs import render_own  # noqa: E402
from warp_highlights.residual.learned import learn_residual  # noqa: E402
from warp_highlights.residual.rate import gaussian_bytes  # noqa: E402


def run_case(name: str, scale: str, device, seconds: float, scratch: Path,
             models: tuple[str, ...] = ("residual", "images")) -> dict:
    dataset = load_case(name, scale, device)
    size = SIZES[name][1 if scale == "gpu" else 0]
    started = time.perf_counter()
    field = fit_field(dataset, device=device, size=size, progress=False)
    fit_seconds = time.perf_counter() - started
    width, height, exposure = field.width, field.height, field.exposure
    pixels = width * height
    field_bytes = save_field(field, scratch / f"{name}.whf")
    queries = dataset.heldout.lights.directions
    truth = resize_stack(dataset.heldout.images, width, height)
    evaluation = evaluate_field(field, dataset, device=device, methods=("circular", "alpha"), barycentric_face=None,
                                baselines=BASELINES)
    rows = {}

    def add_row(label: str, psnr: np.ndarray, ssim: np.ndarray, bytes_per_pixel: float,
                extra: dict | None = None) -> None:
        rows[label] = {"psnr_srgb_mean": float(psnr.mean()), "psnr_srgb_worst": float(psnr.min()),
                       "ssim_mean": float(ssim.mean()),
                       "ssim_worst": float(ssim.min()), "bytes_per_pixel": bytes_per_pixel, **(extra or {})}
        print(f"  {name} {label}: {psnr.mean():.2f} dB (worst {psnr.min():.2f}), SSIM {ssim.mean():.4f}",
              file=sys.stderr, flush=True)

    capture = field.light_count * dataset.channels
    sizes = {"circular": field_bytes / pixels, "alpha": float(capture), **evaluation.info["baseline_bytes_per_pixel"]}
    for method in ("circular", "alpha", *BASELINES):
        add_row(method, evaluation.full_srgb_psnr[method], evaluation.full_ssim[method], float(sizes[method]))

    # the learned residual exactly as ``fit --residual learned`` makes it (residual.learned.learn_residual), relit by
    # the relighter
    images = resize_stack(dataset.images, width, height).astype(np.float32) * np.float32(exposure)
    own = render_own(field.estimated, height, width, raster=field.fit_settings().raster, device=device)
    settings = replace(field.fit_settings().residual, kind="learned", learned_seconds=seconds)
    strips = [truth, Relighter(field, device=device, scale=1.0 / exposure).relight(queries).full]
    learned = [("learned images", np.zeros_like(own), None)] if "images" in models else []
    if field.estimated.active.any() and "residual" in models:  # else the residual is the images
        learned.insert(0, ("learned residual + circular", own, field.residual.highlight_colour))
    for label, highlights, colour in learned:
        t = time.perf_counter()
        residual, history = learn_residual(images, highlights, colour, dataset.lights.directions, factor=exposure,
                                           settings=settings, device=device,
                                           log=lambda m: print(f"    {label}: {m}", file=sys.stderr, flush=True))
        train_seconds = time.perf_counter() - t
        if label.startswith("learned residual"):
            relighter = Relighter(replace(field, residual=residual), device=device, scale=1.0 / exposure)
            relighter.relight(queries[:1])
            t = time.perf_counter()
            stack = relighter.relight(queries).full
            gaussians = gaussian_bytes(field.estimated, field.retargeted) / pixels
        else:  # no Gaussians: the decoded residual is the image (float64 reference decode)
            t = time.perf_counter()
            stack = np.clip(learned_images(residual.learned, queries) / exposure, 0.0, None).astype(np.float32)
            gaussians = 0.0
        decode_seconds = (time.perf_counter() - t) / len(queries)
        psnr, ssim = srgb_scores(stack, truth)
        code_bytes = (2.0 * residual.learned.codes.shape[2]
                      + 4.0 * sum(w.size for w in residual.learned.weights) / pixels)
        add_row(label, psnr, ssim, code_bytes + gaussians,
                {"train_seconds": train_seconds, "epochs": len(history), "final_mse": history[-1],
                 "decode_seconds_per_image": decode_seconds})
        strips.append(stack)
    _save_worst(name, strips, truth)
    return {"case": name, "size": [width, height], "lights": field.light_count, "heldout": len(queries),
            "fit_seconds": fit_seconds,
            "kept_gaussians": bool(field.estimated.active.any()), "rows": rows}


def _save_worst(name: str, stacks: list, truth: np.ndarray) -> None:
    """$OUT/<case>-worst.png: the three held-out lights where the field scores lowest, one row each:
    truth, the field (circular), then each learned model."""
    out = os.environ.get("OUT")
    if not out:
        return
    from PIL import Image

    from warp_highlights.io.images import display_rgb8

    psnr, _ = srgb_scores(np.clip(stacks[1], 0.0, None).astype(np.float32), truth)
    rows = [np.concatenate([display_rgb8(np.clip(stack[q], 0.0, None)) for stack in stacks], axis=1)
            for q in np.argsort(psnr)[:3]]
    Path(out).mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(Path(out) / f"{name}-worst.png")


def warm_up(device) -> None:
    """Compile the learned model's kernels before anything is timed."""
    rng = np.random.default_rng(0)
    lights = rng.normal(size=(4, 3))
    neural_training.train_decoder(rng.uniform(size=(4, 2 * neural.BLOCK, 3)).astype(np.float32),
                         lights / np.linalg.norm(lights, axis=1, keepdims=True),
                         device=device, epochs=1, batch=neural.BLOCK)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue")
    parser.add_argument("--scale", choices=["cpu", "gpu"], default="gpu")
    parser.add_argument("--device", default=None)
    parser.add_argument("--seconds", type=float, default=90.0, help="training time per learned model")
    parser.add_argument("--models", default="residual,images",
                        help="learned models: residual (with the field's moving highlights), images (alone)")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    started = time.perf_counter()
    warm_up(device)
    print(f"kernels compiled in {time.perf_counter() - started:.1f} s", file=sys.stderr, flush=True)
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        for name in [c.strip() for c in args.cases.split(",") if c.strip()]:
            results.append(run_case(name, args.scale, device, args.seconds, Path(scratch),
                                    tuple(m.strip() for m in args.models.split(","))))
    out = os.environ.get("OUT")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "bench_neural_residual.json").write_text(json.dumps({"device": str(device), "scale": args.scale,
                                                                          "seconds": args.seconds, "cases": results},
                                                                         indent=1))
    print(f"\nfull images at held-out lights, {device}, learned models trained {args.seconds:.0f} s each\n")
    print("| case | method | 8-bit PSNR mean | worst | SSIM mean | worst | bytes/pixel | train (s) | epochs |")
    print("|---|---|---|---|---|---|---|---|---|")
    for result in results:
        for label, row in result["rows"].items():
            train = f"{row['train_seconds']:.0f}" if "train_seconds" in row else ""
            epochs = str(row.get("epochs", ""))
            print(f"| {result['case']} ({result['lights']} lights, {result['size'][0]}x{result['size'][1]}) | {label} "
                  f"| {row['psnr_srgb_mean']:.2f} | "
                  f"{row['psnr_srgb_worst']:.2f} | {row['ssim_mean']:.4f} | {row['ssim_worst']:.4f} | "
                  f"{row['bytes_per_pixel']:.1f} | {train} | {epochs} |")


if __name__ == "__main__":
    main()
