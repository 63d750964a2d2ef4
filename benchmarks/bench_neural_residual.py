"""A learned residual (NeuralRTI-style, ``kernels.neural``) on the samples, next to the field's compressed
residual, the alpha blend and RBF: full images at the held-out lights, and size per pixel.

    python benchmarks/bench_neural_residual.py --device cuda:0 --seconds 90     # full-size samples
    python benchmarks/bench_neural_residual.py --scale cpu --seconds 60          # reduced sizes (slow)

Per case the field is fitted with the defaults. Its residual's exact images R_i = I_i - c G_i (the
captured images minus their own highlights, before compression) are learned as a code of 9 numbers
per pixel and an MLP of code + light direction (``kernels.neural``, trained for ``--seconds``); the
relit image is the decoded residual plus the field's moved highlights. "neural images" learns the
captured images themselves (NeuralRTI on its own, no Gaussians). Scores: 8-bit sRGB PSNR and SSIM.
Writes $OUT/bench_neural_residual.json when OUT is set.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import SIZES, load_case  # noqa: E402
from warp_highlights.kernels import neural  # noqa: E402

from warp_highlights.fit.pipeline import fit_field  # noqa: E402
from warp_highlights.fit.residual import gaussian_bytes, render_own  # noqa: E402
from warp_highlights.io.fieldfile import save_field  # noqa: E402
from warp_highlights.io.images import linear_to_srgb, srgb_to_linear  # noqa: E402
from warp_highlights.model.residual import decode_display as neural_decode_display  # noqa: E402
from warp_highlights.relight.baselines import fit_baseline  # noqa: E402
from warp_highlights.relight.evaluation import resize_stack, srgb_scores  # noqa: E402
from warp_highlights.relight.relighter import Relighter  # noqa: E402


def run_case(name: str, scale: str, device, seconds: float, scratch: Path, models: tuple[str, ...] = ("residual", "images")) -> dict:
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
    images = resize_stack(dataset.images, width, height).astype(np.float32)
    lights = dataset.lights.directions

    relit = Relighter(field, device=device, scale=1.0 / exposure).relight(queries, method="circular", full=True)
    highlights = Relighter(field, device=device, scale=1.0 / exposure, diffuse="none").relight(queries, method="circular", full=True).full
    blend = np.zeros((len(queries), field.light_count))
    np.put_along_axis(blend, field.triangulation.faces[relit.faces], relit.barycentric, axis=1)
    alpha = np.einsum("qn,nhwc->qhwc", blend, images)
    values = linear_to_srgb(np.clip(images, 0.0, 1.0)) if dataset.display_referred else images
    rbf = fit_baseline("rbf", values, lights, device=device).relight(queries)
    rbf = srgb_to_linear(np.clip(rbf, 0.0, 1.0)) if dataset.display_referred else rbf

    own = render_own(field.estimated, height, width, raster=field.fit_settings().raster, device=device)
    colour = field.residual.highlight_colour if field.residual.highlight_colour is not None else np.ones((1, 1, 3), np.float32)
    residual = images - own[..., None] * colour[None] / exposure  # display units
    rows = {}

    def score(label: str, stack: np.ndarray, bytes_per_pixel: float, extra: dict | None = None) -> None:
        psnr, ssim = srgb_scores(np.clip(stack, 0.0, None).astype(np.float32), truth)
        rows[label] = {"psnr_srgb_mean": float(psnr.mean()), "psnr_srgb_worst": float(psnr.min()), "ssim_mean": float(ssim.mean()),
                       "ssim_worst": float(ssim.min()), "bytes_per_pixel": bytes_per_pixel, **(extra or {})}
        print(f"  {name} {label}: {psnr.mean():.2f} dB (worst {psnr.min():.2f}), SSIM {ssim.mean():.4f}", file=sys.stderr, flush=True)

    capture = field.light_count * 3
    score("circular (field)", relit.full, field_bytes / pixels)
    score("alpha", alpha, float(capture))
    score("rbf", rbf, float(3 * field.light_count))
    learned = [("neural images", images, 0.0)] if "images" in models else []
    if field.estimated.active.any() and "residual" in models:  # else the residual is the images
        learned.insert(0, ("neural residual + circular", residual, highlights))
    strips = [truth, relit.full]
    for label, target, add in learned:
        encoded = neural.encode_display(target.reshape(field.light_count, pixels, 3))
        t = time.perf_counter()
        model, history = neural.train_decoder(encoded, lights, device=device, epochs=400, seconds=seconds,
                                              log=lambda m: print(f"    {label}: {m}", file=sys.stderr, flush=True) if "0/" in m else None)
        wp.synchronize_device(device)
        train_seconds = time.perf_counter() - t
        model.codes = model.codes.astype(np.float16).astype(np.float32)  # as stored
        t = time.perf_counter()
        decoded = neural.decode(model, queries, device=device)
        decode_seconds = (time.perf_counter() - t) / len(queries)
        stack = neural_decode_display(decoded).reshape(len(queries), height, width, 3) + add
        extra = {"train_seconds": train_seconds, "epochs": len(history), "final_mse": history[-1], "decode_seconds_per_image": decode_seconds}
        gaussians = gaussian_bytes(field.estimated, field.retargeted) / pixels if label.startswith("neural residual") else 0.0
        score(label, stack, model.stored_bytes_per_pixel + gaussians, extra)
        strips.append(stack)
    _save_worst(name, strips, truth)
    return {"case": name, "size": [width, height], "lights": field.light_count, "heldout": len(queries), "fit_seconds": fit_seconds,
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
    rows = [np.concatenate([display_rgb8(np.clip(stack[q], 0.0, None)) for stack in stacks], axis=1) for q in np.argsort(psnr)[:3]]
    Path(out).mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(Path(out) / f"{name}-worst.png")


def warm_up(device) -> None:
    """Compile the learned model's kernels before anything is timed."""
    rng = np.random.default_rng(0)
    lights = rng.normal(size=(4, 3))
    neural.train_decoder(rng.uniform(size=(4, 2 * neural.BLOCK, 3)).astype(np.float32), lights / np.linalg.norm(lights, axis=1, keepdims=True),
                         device=device, epochs=1, batch=neural.BLOCK)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue")
    parser.add_argument("--scale", choices=["cpu", "gpu"], default="gpu")
    parser.add_argument("--device", default=None)
    parser.add_argument("--seconds", type=float, default=90.0, help="training time per learned model")
    parser.add_argument("--models", default="residual,images", help="learned models: residual (with the field's moving highlights), images (alone)")
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
            results.append(run_case(name, args.scale, device, args.seconds, Path(scratch), tuple(m.strip() for m in args.models.split(","))))
    out = os.environ.get("OUT")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "bench_neural_residual.json").write_text(json.dumps({"device": str(device), "scale": args.scale, "seconds": args.seconds, "cases": results}, indent=1))
    print(f"\nfull images at held-out lights, {device}, learned models trained {args.seconds:.0f} s each\n")
    print("| case | method | 8-bit PSNR mean | worst | SSIM mean | worst | bytes/pixel | train (s) | epochs |")
    print("|---|---|---|---|---|---|---|---|---|")
    for result in results:
        for label, row in result["rows"].items():
            train = f"{row['train_seconds']:.0f}" if "train_seconds" in row else ""
            epochs = str(row.get("epochs", ""))
            print(f"| {result['case']} ({result['lights']} lights, {result['size'][0]}x{result['size'][1]}) | {label} | {row['psnr_srgb_mean']:.2f} | "
                  f"{row['psnr_srgb_worst']:.2f} | {row['ssim_mean']:.4f} | {row['ssim_worst']:.4f} | {row['bytes_per_pixel']:.1f} | {train} | {epochs} |")


if __name__ == "__main__":
    main()
