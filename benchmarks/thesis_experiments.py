"""The thesis' experiments 4.2 and 4.5.4 on our data: render, fit and evaluate donut and teapot.

    python benchmarks/thesis_experiments.py WORK [--shapes donut teapot] [--lights 250] [--size 480x270] [--device
    cuda:0] [--set STAGE.NAME=VALUE ...]

For every shape this runs the three commands a user would run, in WORK:

    warp-highlights render SHAPE WORK/SHAPE --lights N --size WxH       (held-out: every triangle centroid)
    warp-highlights fit WORK/SHAPE -o WORK/SHAPE.whf --report WORK/SHAPE-fit.json
    warp-highlights evaluate WORK/SHAPE.whf WORK/SHAPE -o WORK/SHAPE-evaluation

then prints one table (PSNR mean, 5th and 95th percentile per method at the centroids; share of
triangles where circular beats alpha; Gaussians per light; seconds per stage). The evaluation folders
(report.json and plots) and the fit reports are copied to $OUT when it is set. The thesis' settings are
250 Fibonacci lights over the whole sphere at 480x270 (496 triangles); ``--lights 64 --size 240x135``
is the version a 2-core CPU runs in about a minute per shape.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.cli import main as cli


def run(argv: list[str]) -> float:
    print("$ warp-highlights " + " ".join(argv), flush=True)
    started = time.perf_counter()
    status = cli(argv)
    if status != 0:
        raise SystemExit(f"warp-highlights {argv[0]} failed with status {status}")
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="folder for the datasets, fields and evaluations")
    parser.add_argument("--shapes", nargs="+", default=["donut", "teapot"])
    parser.add_argument("--lights", type=int, default=250)
    parser.add_argument("--size", default="480x270")
    parser.add_argument("--device", default=None)
    parser.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="fit setting, repeatable (warp-highlights fit --list-settings)")
    args = parser.parse_args()
    device = ["--device", args.device] if args.device else []
    settings = [part for setting in args.set for part in ("--set", setting)]
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for shape in args.shapes:
        data = args.work / shape
        field = args.work / f"{shape}.whf"
        evaluation = args.work / f"{shape}-evaluation"
        seconds = {
            "render": run(["render", shape, str(data), "--lights", str(args.lights), "--size", args.size, "--overwrite",
                           "-q", *device]),
            "fit": run(["fit", str(data), "-o", str(field), "--report", str(args.work / f"{shape}-fit.json"),
                        "--overwrite", "-q", *device, *settings]),
            "evaluate": run(["evaluate", str(field), str(data), "-o", str(evaluation), "--overwrite", "-q", *device]),
        }
        report = json.loads((evaluation / "report.json").read_text())
        fit = json.loads((args.work / f"{shape}-fit.json").read_text())
        rows.append((shape, report, fit, seconds))
        if os.environ.get("OUT"):
            out = Path(os.environ["OUT"])
            shutil.copytree(evaluation, out / evaluation.name, dirs_exist_ok=True)
            shutil.copy(args.work / f"{shape}-fit.json", out / f"{shape}-fit.json")

    print()
    print(f"{args.lights} Fibonacci lights, {args.size}, specular PSNR (dB) at every triangle centroid"
          + (f", fitted with {' '.join(args.set)}" if args.set else "") + "; full image: 8-bit sRGB PSNR:")
    print("| shape | triangles | method | mean | p5 | p95 | circular > alpha | full image | moving / Gaussians | "
          "Gaussians / light | fit s | evaluate s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for shape, report, _fit, seconds in rows:
        specular = report["summary"]["specular"]
        for method in ("circular", "straight", "alpha"):
            s = specular[method]
            share = f"{100 * specular['circular_beats_alpha']:.0f}%" if method == "circular" else ""
            per_light = f"{report['gaussians']['per_light']['mean']:.1f}" if method == "circular" else ""
            times = (f"{seconds['fit']:.1f}", f"{seconds['evaluate']:.1f}") if method == "circular" else ("", "")
            full = report["summary"]["full_srgb"].get(method)
            full = f"{full['mean']:.2f}" if full else ""
            moving = (f"{report['moving_gaussians']} / {report['gaussians']['per_light']['total']}"
                      if method == "circular" else "")
            print(f"| {shape} | {report['heldout']} | {method} | {s['mean']:.2f} | {s['p5']:.2f} | {s['p95']:.2f} | "
                  f"{share} | {full} | {moving} | {per_light} | {times[0]} | {times[1]} |")


if __name__ == "__main__":
    main()
