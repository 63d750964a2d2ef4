"""Sweep the retargeting loss weights and phase lengths on a synthetic dataset with held-out ground truth.

Segmentation and estimation run once; every retargeting setting is then scored the way the method is
used: at every held-out direction (by default the triangle centroids, the thesis' protocol) the
interpolated set is rendered and compared with the ground-truth specular luminance (PSNR, peak 1,
clipped to [0, 1], capped at 100 dB). The alpha blend of the segmented specular images is the baseline.

    python benchmarks/sweep_retarget.py DATASET [--device cuda:0] [--size 240x135] [--grid full|defaults|quick]

Prints one table row per setting; writes all figures to $OUT/sweep_retarget.json when OUT is set.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.fit.estimation import estimate, psnr
from warp_highlights.fit.paths import decide_paths
from warp_highlights.fit.retargeting import retarget
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.resample import resize_stack
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.kernels.segmentation import segment
from warp_highlights.model.config import FitSettings
from warp_highlights.model.field import HighlightField
from warp_highlights.model.gaussians import GaussianBatch
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.relight.evaluation import luminance
from warp_highlights.relight.interpolation import interpolate_sets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--device", default=None)
    parser.add_argument("--size", help="working size WxH (default: the images')")
    parser.add_argument("--grid", choices=["full", "defaults", "quick"], default="full",
                        help="full sweep (default), only the defaults, or a small smoke test")
    args = parser.parse_args()
    wp.config.quiet = True
    device = wp.get_device(args.device)
    data = ReflectanceField.load(args.dataset, progress=False)
    if data.heldout is None or data.heldout.specular is None:
        raise SystemExit(
            "the dataset needs held-out lights with ground-truth specular images (render it with --heldout centroids)")
    width, height = (int(v) for v in args.size.split("x")) if args.size else (data.width, data.height)
    base = FitSettings()

    started = time.perf_counter()
    seg = segment(resize_stack(data.images, width, height), data.lights.directions, settings=base.segmentation,
                  device=device)
    est = estimate(seg.specular_luminance, settings=base.estimation, raster=base.raster, device=device)
    wp.synchronize_device(device)
    estimation_seconds = time.perf_counter() - started
    triangulation = SphericalTriangulation(data.lights.directions)
    edges = triangulation.directed_edges()
    location = triangulation.locate(data.heldout.lights.directions)
    truth = luminance(resize_stack(data.heldout.specular, width, height))
    segmented = seg.specular_luminance.numpy()
    alpha = np.einsum("qk,qkhw->qhw", location.barycentric, segmented[location.vertices])
    alpha_psnr = psnr(alpha, truth)
    raster = Rasterizer(height, width, settings=base.raster, device=device)
    print(f"{data.light_count} lights, {len(edges)} directed edges, {len(truth)} held-out, {width}x{height}, {device}; "
          f"segmentation + estimation {estimation_seconds:.1f} s, {est.counts.mean():.2f} Gaussians per light")
    print(f"alpha blend: PSNR mean {alpha_psnr.mean():.2f} dB, 5th percentile {np.percentile(alpha_psnr, 5):.2f}")

    r = base.retarget
    defaults = (r.c_fit, r.c_str, r.c_ene, r.rigid_iterations, r.iterations)
    if args.grid == "quick":
        grid = [(1.0, 0.0, 0.0, 20, 40), defaults]
    elif args.grid == "defaults":
        grid = [defaults]
    else:
        weights = list(itertools.product([0.0, 0.01, 0.1, 1.0], [0.0, 1e-4, 1e-3, 1e-2]))
        grid = [(1.0, c_str, c_ene, 200, 500) for c_str, c_ene in weights]
        grid += [(1.0, 0.1, 1e-3, t1, t2) for t1, t2 in [(0, 500), (50, 150), (100, 300), (200, 200), (400, 800)]]
        grid.append(defaults)
    rows = []
    print("| c_fit | c_str | c_ene | T1 | T2 | seconds | fit loss | structure | circular PSNR | p5 | straight "
          "| circ > alpha |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c_fit, c_str, c_ene, t1, t2 in grid:
        settings = replace(base, retarget=replace(base.retarget, c_fit=c_fit, c_str=c_str, c_ene=c_ene,
                                                  rigid_iterations=t1, iterations=t2))
        t = time.perf_counter()
        result = retarget(est.params, seg.specular_luminance, edges, settings=settings.retarget, raster=settings.raster,
                          device=device)
        wp.synchronize_device(device)
        seconds = time.perf_counter() - t
        decisions = decide_paths(est.params.take(edges[:, 0]), result.params, settings.paths)
        field = HighlightField(
            lights=data.lights, triangulation=triangulation, width=width, height=height, estimated=est.params,
            directed_edges=edges, retargeted=result.params, path_delta=decisions.delta, path_centre=decisions.centre,
            settings=settings.to_dict(), report={},
        )
        scores = {}
        for method in ("circular", "straight"):
            sets = interpolate_sets(field, location.vertices, location.barycentric, method=method)
            image = raster.render(GaussianBatch.from_numpy(sets, device=device, requires_grad=False)).numpy()
            scores[method] = psnr(image, truth)
        row = {
            "c_fit": c_fit, "c_str": c_str, "c_ene": c_ene, "rigid_iterations": t1, "iterations": t2,
            "seconds": seconds,
            "fit_loss": float(result.loss.mean()), "structure_loss": float(result.structure_loss.mean()),
            "circular_mean": float(scores["circular"].mean()),
            "circular_p5": float(np.percentile(scores["circular"], 5)),
            "straight_mean": float(scores["straight"].mean()), "alpha_mean": float(alpha_psnr.mean()),
            "circular_beats_alpha": float(np.mean(scores["circular"] > alpha_psnr)),
        }
        rows.append(row)
        print(f"| {c_fit:g} | {c_str:g} | {c_ene:g} | {t1} | {t2} | {seconds:.1f} | {row['fit_loss']:.1f} | "
              f"{row['structure_loss']:.1f} | "
              f"{row['circular_mean']:.2f} | {row['circular_p5']:.2f} | {row['straight_mean']:.2f} | "
              f"{100 * row['circular_beats_alpha']:.0f}% |", flush=True)
    best = max(rows, key=lambda r: r["circular_mean"])
    print(f"best circular mean: c_str {best['c_str']:g}, c_ene {best['c_ene']:g}, T1 {best['rigid_iterations']}, T2 "
          f"{best['iterations']}: {best['circular_mean']:.2f} dB")
    if os.environ.get("OUT"):
        out = Path(os.environ["OUT"]) / "sweep_retarget.json"
        out.write_text(json.dumps({"dataset": str(args.dataset), "device": str(device), "size": [width, height],
                                   "alpha_mean": float(alpha_psnr.mean()), "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
