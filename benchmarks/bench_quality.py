"""Full-image quality of every relighting method on the samples and the rendered donut and teapot.

    python benchmarks/bench_quality.py                          # CPU sizes: samples reduced, 64-light donut/teapot
    python benchmarks/bench_quality.py --scale gpu --device cuda:0   # full-size samples, 250-light donut/teapot
    python benchmarks/bench_quality.py --cases synth,statue     # a subset (also: coin, multi)
    python benchmarks/bench_quality.py --set residual.kind=learned   # any fit setting, as `fit --set` takes it

Per case: fit a field with the defaults (timed), save it (bytes), then ``evaluate_field`` at the
held-out lights: the field (circular, and the alpha blend of the same triangulation) next to PTM,
HSH orders 2 and 3 and RBF (sigma by leave-one-out) fitted to the same lights. Scores are 8-bit sRGB
PSNR and SSIM (scikit-image) over the whole image, as RTI users measure, and linear PSNR. Cases:

- ``synth``: the rendered dome sample (``$WARP_HIGHLIGHTS_DATA/synthrti-object1-material5``), scored
  at its 20 ``Test/`` lights;
- ``statue``: the photographed statue (``realrti-item11``), every 5th light held out;
- ``coin``: the photographed coin (``realrti-item10``), every 5th light held out, and ``multi``: the rendered
  textured multi-object dome (``synthrti-multi-object2-material5``) at its 20 ``Test/`` lights (neither among the
  default cases);
- ``donut``, ``teapot``: rendered here (Fibonacci lights, held-out triangle centroids, ground truth).

Size per pixel: the field file, the alpha blend's 8-bit images (lights x channels), a baseline's
8-bit coefficients; "share" is that over the 8-bit capture (lights x pixels x channels bytes).
Prints one Markdown table last; writes everything to $OUT/bench_quality.json when OUT is set.
Runs from a plain checkout (PYTHONPATH=$PWD); SSIM needs scikit-image (NaN without it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.fit.pipeline import fit_field
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.fieldfile import save_field
from warp_highlights.model.config import FitSettings
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.relight.evaluation import evaluate_field
from warp_highlights.synth.render import (
    Renderer,
    RenderSettings,
    default_material,
    view_rotation,
)
from warp_highlights.synth.shapes import make_shape

BASELINES = ("ptm", "hsh2", "hsh3", "rbf")
SIZES = {  # case -> (cpu size, gpu size); None: the images' own size
    "synth": ((160, 160), None),
    "statue": ((192, 181), None),
    "coin": ((166, 168), None),
    "multi": ((160, 160), None),
    "donut": ((240, 135), (480, 270)),
    "teapot": ((240, 135), (480, 270)),
}
RENDERED_LIGHTS = {"cpu": 64, "gpu": 250}


def load_case(name: str, scale: str, device) -> ReflectanceField:
    data = Path(os.environ.get("WARP_HIGHLIGHTS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    if name == "synth":
        root = data / "synthrti-object1-material5"
        return ReflectanceField.load(root / "Dome", heldout=root / "Test", progress=False)
    if name == "multi":
        root = data / "synthrti-multi-object2-material5"
        return ReflectanceField.load(root / "Dome", heldout=root / "Test", progress=False)
    if name in ("statue", "coin"):
        return ReflectanceField.load(data / ("realrti-item11" if name == "statue" else "realrti-item10"),
                                     progress=False).split_every(5)
    # rendered in memory (a GPU machine may have no EXR writer), with ground truth at the triangle centroids
    width, height = SIZES[name][1 if scale == "gpu" else 0]
    lights = LightSet.fibonacci_sphere(RENDERED_LIGHTS[scale])
    renderer = Renderer(make_shape(name), material=default_material(name),
                        settings=RenderSettings(width=width, height=height),
                        rotation=view_rotation(name), device=str(device))
    centroids = LightSet(SphericalTriangulation(lights.directions).centroid_directions())
    captured, truth = renderer.render(lights.directions), renderer.render(centroids.directions)
    heldout = ReflectanceField(images=truth.full, lights=centroids, specular=truth.specular, diffuse=truth.diffuse)
    return ReflectanceField(images=captured.full, lights=lights, specular=captured.specular, diffuse=captured.diffuse,
                            heldout=heldout,
                            meta={"heldout_protocol": "triangle centroids"})


def run_case(name: str, scale: str, device, scratch: Path, settings: FitSettings | None = None) -> dict:
    dataset = load_case(name, scale, device)
    size = SIZES[name][1 if scale == "gpu" else 0]
    started = time.perf_counter()
    field = fit_field(dataset, device=device, size=size, progress=False, settings=settings)
    wp.synchronize_device(device)
    fit_seconds = time.perf_counter() - started
    field_bytes = save_field(field, scratch / f"{name}.whf")
    evaluation = evaluate_field(field, dataset, device=device, methods=("circular", "alpha"), barycentric_face=None,
                                baselines=BASELINES)
    summary = evaluation.summary()
    pixels, channels, lights = field.width * field.height, dataset.channels, field.light_count
    capture = lights * channels  # 8-bit capture, bytes per pixel
    size_per_pixel = {"circular": field_bytes / pixels, "alpha": float(capture)}
    size_per_pixel.update({method: float(value)
                           for method, value in evaluation.info["baseline_bytes_per_pixel"].items()})
    rows = []
    for method in ("circular", "alpha", *BASELINES):
        srgb, ssim, linear = (summary.get(kind, {}).get(method) for kind in ("full_srgb", "full_ssim", "full"))
        rows.append({
            "case": name, "method": method,
            "psnr_srgb_mean": srgb["mean"], "psnr_srgb_worst": srgb["min"], "ssim_mean": ssim["mean"],
            "ssim_worst": ssim["min"],
            "psnr_linear_mean": linear["mean"], "bytes_per_pixel": size_per_pixel[method],
            "share_of_capture": size_per_pixel[method] / capture,
            "fit_seconds": fit_seconds if method == "circular" else None,
        })
    specular = summary.get("specular", {})
    return {
        "case": name, "size": [field.width, field.height], "lights": lights, "heldout": int(len(evaluation.directions)),
        "field_bytes": field_bytes, "fit_seconds": fit_seconds, "fit_stage_seconds": field.report["seconds"],
        "residual": field.report.get("residual"), "exposure": field.exposure,
        "specular_circular_beats_alpha": specular.get("circular_beats_alpha"),
        "full_circular_beats_alpha": summary.get("full_srgb", {}).get("circular_beats_alpha"),
        "rbf_sigma": evaluation.info.get("rbf_sigma"), "rows": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue,donut,teapot")
    parser.add_argument("--scale", choices=["cpu", "gpu"], default="cpu",
                        help="cpu: reduced sizes, 64 rendered lights; gpu: full sizes, 250")
    parser.add_argument("--device", default=None)
    parser.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="fit setting, repeatable")
    args = parser.parse_args()
    settings = FitSettings().with_overrides(args.set)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        for name in [c.strip() for c in args.cases.split(",") if c.strip()]:
            if name not in SIZES:
                raise SystemExit(f"unknown case '{name}'; choose from {', '.join(SIZES)}")
            print(f"{name}: fitting and evaluating on {device} ...", file=sys.stderr, flush=True)
            results.append(run_case(name, args.scale, device, Path(scratch), settings))
    out = os.environ.get("OUT")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "bench_quality.json").write_text(json.dumps({"device": str(device), "scale": args.scale,
                                                                  "settings": args.set, "cases": results}, indent=1))
    print(f"\nfull images at held-out lights, {device} ({args.scale} sizes)\n")
    print("| case | method | 8-bit PSNR mean | worst | SSIM mean | worst | linear PSNR | bytes/pixel | share of 8-bit "
          "capture | fit (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for result in results:
        for row in result["rows"]:
            fit = "" if row["fit_seconds"] is None else f"{row['fit_seconds']:.1f}"
            label = f"{result['case']} ({result['lights']} lights, {result['size'][0]}x{result['size'][1]})"
            print(f"| {label} | {row['method']} | {row['psnr_srgb_mean']:.2f} | {row['psnr_srgb_worst']:.2f} | "
                  f"{row['ssim_mean']:.3f} | "
                  f"{row['ssim_worst']:.3f} | {row['psnr_linear_mean']:.2f} | {row['bytes_per_pixel']:.1f} | "
                  f"{100 * row['share_of_capture']:.0f}% | {fit} |")
    for result in results:
        share = result["specular_circular_beats_alpha"]
        if share is not None:
            print(f"{result['case']}: on the specular part alone, circular beats alpha on {100 * share:.0f}% of "
                  f"{result['heldout']} held-out lights")


if __name__ == "__main__":
    main()
