"""Time the light designer (``warp-highlights view``): what one move of the light costs.

    python benchmarks/bench_view.py FIELD [--device cpu] [--moves 40] [--window-size 1680x520]

Renders off screen (VTK through EGL or the platform's OpenGL), so it runs without a display, with 8
and with 0 MSAA samples (the designer's choice for a window on a software OpenGL). The light
moves in small steps along an orbit at 35 degrees elevation, crossing triangles, as a drag would. Per
panel set it prints the median milliseconds of:

- ``relight``: the relit image for the new direction, on ``--device``, copied to the host;
- ``scene``: the meshes of the query, triangle, paths and Gaussian outlines refilled, and the texts;
- ``draw``: VTK drawing the window (``plotter.render``, synchronous);
- ``move``: all three, i.e. what one drag event costs; 1000 / move is the frame rate.

Writes the figures to $OUT/bench_view.json when OUT is set.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.io.fieldfile import load_field
from warp_highlights.view.designer import LightDesigner
from warp_highlights.view.light_paths import orbit

PANEL_SETS = (("sphere", "image", "paths"), ("sphere",), ("image",), ("paths",))


def time_moves(field, panels, *, device, moves: int, window_size, multi_samples: int) -> dict[str, float]:
    size = (window_size[0] * len(panels) // 3, window_size[1])
    designer = LightDesigner(field, device=device, off_screen=True, panels=panels, window_size=size,
                             multi_samples=multi_samples)
    try:
        designer.screenshot()  # the first draw builds VTK's buffers and shaders
        window = list(designer.plotter.window_size)
        rows = []
        for direction in orbit(35.0, moves, turns=0.25):
            started = time.perf_counter()
            designer.set_direction(direction, render=False)
            drawn = time.perf_counter()
            designer.plotter.render()
            finished = time.perf_counter()
            rows.append((designer.timings["relight"], designer.timings["scene"], 1e3 * (finished - drawn),
                         1e3 * (finished - started)))
        faces = len({int(field.triangulation.locate(d).faces) for d in orbit(35.0, moves, turns=0.25)})
    finally:
        designer.close()
    median = np.median(np.array(rows), axis=0)
    return {"relight": median[0], "scene": median[1], "draw": median[2], "move": median[3], "triangles": faces,
            "window": window}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("field", type=Path)
    parser.add_argument("--device", default=None)
    parser.add_argument("--moves", type=int, default=40)
    parser.add_argument("--window-size", default="1680x520",
                        help="window for three panels; a single panel gets a third of the width")
    args = parser.parse_args()
    import warp as wp

    wp.config.quiet = True
    field = load_field(args.field)
    window = tuple(int(v) for v in args.window_size.lower().split("x"))
    device = str(wp.get_device(args.device))
    import vtk

    print(f"# bench_view: {args.field.name} ({field.light_count} lights, {field.width}x{field.height}), "
          f"relight on {device}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, VTK {vtk.vtkVersion.GetVTKVersion()}")
    results = {}
    from warp_highlights.view.viz import software_opengl

    print(f"# OpenGL: {'software (CPU)' if software_opengl() else 'hardware'}")
    print("| panels | window | MSAA | relight ms | scene ms | draw ms | move ms | moves/s |")
    print("|---|---|---|---|---|---|---|---|")
    for panels in PANEL_SETS:
        for samples in (8, 0):
            r = time_moves(field, panels, device=device, moves=args.moves, window_size=window, multi_samples=samples)
            results[f"{','.join(panels)} msaa{samples}"] = r
            print(f"| {', '.join(panels)} | {r['window'][0]}x{r['window'][1]} | {samples} | {r['relight']:.1f} | "
                  f"{r['scene']:.1f} | "
                  f"{r['draw']:.1f} | {r['move']:.1f} | {1e3 / r['move']:.1f} |")
    out = os.environ.get("OUT")
    if out:
        Path(out, "bench_view.json").write_text(json.dumps({"field": str(args.field), "device": device,
                                                            "results": results}, indent=2))


if __name__ == "__main__":
    main()
