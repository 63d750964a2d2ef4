"""Time a full fit (segmentation, estimation, retargeting, paths) against the thesis' Table 4.2.

    python benchmarks/bench_fit.py                       # 250-light 480x270 donut, rendered first
    python benchmarks/bench_fit.py --lights 64 --size 240x135 --device cpu    # the CPU-sized fit
    python benchmarks/bench_fit.py --dataset data/donut  # an existing dataset
    python benchmarks/bench_fit.py --dataset ../shared/data/synthrti-object1-material5/Dome --size 160x160 \
        --device cpu --set residual.kind=lowrank --parts-per-worker 1,4   # CPU threads' parts, in one run

Prints a table of seconds per stage (best of --repeat fits after a warm-up that compiles the kernels)
and the field's file size, and with --parts-per-worker one row per value (``kernels.chunks.CPU_PARTS_PER_WORKER``);
writes the full report to $OUT/bench_fit.json when OUT is set. Runs from a plain checkout with only warp, numpy and
scipy (PYTHONPATH=$PWD), as on a GPU machine without the project installed.
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
from warp_highlights.io.fieldfile import field_size_report, save_field
from warp_highlights.kernels import chunks
from warp_highlights.model.config import FitSettings
from warp_highlights.model.lights import LightSet
from warp_highlights.synth.render import (
    RenderSettings,
    default_material,
    render_dataset,
)

# thesis Table 4.2 (donut, RTX 3080), seconds for the whole dataset of 250 lights at 480x270
THESIS_SECONDS = {"segmentation": 1.5, "estimation": 324.0, "retargeting": 3573.0, "total": 3915.0}
THESIS_FIELD_BYTES = 2.2e6  # its estimate for 256 lights x 25 Gaussians


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, help="an existing dataset folder (default: render the donut)")
    parser.add_argument("--shape", default="donut")
    parser.add_argument("--lights", type=int, default=250)
    parser.add_argument("--size", default=None,
                        help="WIDTHxHEIGHT: the render's size (default 480x270), or the size an existing --dataset is "
                             "fitted at (default its images')")
    parser.add_argument("--device", default=None)
    parser.add_argument("--workers", type=int, default=None, help="CPU threads (default: one per core)")
    parser.add_argument("--repeat", type=int, default=1, help="timed fits after the warm-up (default 1)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        help="hyper-parameter override STAGE.NAME=VALUE")
    parser.add_argument("--parts-per-worker", default=str(chunks.CPU_PARTS_PER_WORKER),
                        help="comma-separated values of kernels.chunks.CPU_PARTS_PER_WORKER to time, each in turn "
                             f"(default {chunks.CPU_PARTS_PER_WORKER})")
    args = parser.parse_args()
    parts = [int(v) for v in args.parts_per_worker.split(",") if v.strip()]
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    settings = FitSettings().with_overrides(args.overrides)
    width, height = (int(v) for v in (args.size or "480x270").split("x"))

    with tempfile.TemporaryDirectory() as scratch:
        folder = args.dataset
        if folder is None:
            folder = Path(scratch) / args.shape
            started = time.perf_counter()
            render_dataset(args.shape, folder, lights=LightSet.fibonacci_sphere(args.lights), heldout=None,
                           material=default_material(args.shape),
                           settings=RenderSettings(width=width, height=height), device=str(device), progress=False)
            print(f"rendered {args.shape}: {args.lights} lights {width}x{height} in "
                  f"{time.perf_counter() - started:.1f} s")
        started = time.perf_counter()
        data = ReflectanceField.load(folder, progress=False, heldout=False, components=False,  # what fit loads
                                     size=(width, height) if args.size and args.dataset is not None else None)
        width, height = data.width, data.height
        load_seconds = time.perf_counter() - started

        # warm-up: compiles every kernel (cached on disk afterwards) with a very short fit
        warm = settings.with_overrides(["estimation.iterations=2", "estimation.densify_until=1",
                                        "retarget.rigid_iterations=1", "retarget.iterations=1"])
        fit_field(data, settings=warm, device=device, workers=args.workers)

        by_parts = []
        for per_worker in parts:
            chunks.CPU_PARTS_PER_WORKER = per_worker
            best = None
            for _ in range(max(1, args.repeat)):
                wp.synchronize_device(device)
                started = time.perf_counter()
                field = fit_field(data, settings=settings, device=device, workers=args.workers)
                wp.synchronize_device(device)
                total = time.perf_counter() - started
                if best is None or total < best[0]:
                    best = (total, field)
            by_parts.append((per_worker, *best))
        _, total, field = by_parts[-1]
        path = Path(scratch) / "field.whf"
        size = save_field(field, path)

    report = field.report
    stages = dict(report["seconds"])
    rows = [("loading images", load_seconds, 17.0)]
    rows += [(name, stages.get(name, 0.0), THESIS_SECONDS.get(name))
             for name in ("segmentation", "estimation", "retargeting", "paths", "triangulation")]
    rows.append(("total (without loading)", total, THESIS_SECONDS["total"] - 17.0))
    counts = report["estimation"]["gaussians_per_light"]
    print(f"\n{data.light_count} lights, {report['directed_edges']} directed edges, {width}x{height}, {device} "
          f"({_device_name(device)}), "
          f"warp {wp.config.version}, workers {args.workers or 'default'}")
    print(f"Gaussians per light: mean {counts['mean']:.1f}, min {counts['min']:.0f}, max {counts['max']:.0f}; "
          f"estimation PSNR mean {report['estimation']['psnr_db']['mean']:.1f} dB; "
          f"retargeting loss {report['retargeting']['source_loss']['mean']:.0f} -> "
          f"{report['retargeting']['loss']['mean']:.0f}")
    print(f"field file: {size / 1e6:.2f} MB (thesis estimate for 256 lights x 25 Gaussians: "
          f"{THESIS_FIELD_BYTES / 1e6:.1f} MB); parts: "
          + ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in field_size_report(field).items()))
    print("\n| stage | seconds | thesis (RTX 3080, 250 lights, 480x270) | speed-up |")
    print("|---|---|---|---|")
    comparable = data.light_count == 250 and (width, height) == (480, 270)
    for name, seconds, thesis in rows:
        ratio = (f"{thesis / seconds:.0f}x" if comparable and thesis and seconds > 0
                 else ("" if comparable else "n/a (other size)"))
        print(f"| {name} | {seconds:.2f} | {thesis if thesis is not None else ''} | {ratio} |")
    if len(by_parts) > 1:
        print("\n| CPU parts per worker | estimation | retargeting | move check | total (s) |")
        print("|---|---|---|---|---|")
        for per_worker, seconds, fitted in by_parts:
            stage = fitted.report["seconds"]
            print(f"| {per_worker} | {stage.get('estimation', 0.0):.1f} | {stage.get('retargeting', 0.0):.1f} | "
                  f"{stage.get('move check', 0.0):.1f} | {seconds:.1f} |")
    if os.environ.get("OUT"):
        out = Path(os.environ["OUT"]) / "bench_fit.json"
        out.write_text(json.dumps({"device": str(device), "device_name": _device_name(device),
                                   "lights": data.light_count, "size": [width, height],
                                   "load_seconds": load_seconds, "total_seconds": total, "file_bytes": size,
                                   "report": report}, indent=2))


def _device_name(device) -> str:
    return device.name if device.is_cuda else "CPU"


if __name__ == "__main__":
    main()
