"""Time the synthetic-data renderer: N lights at WxH, per shape and device.

Prints one table row per (device, shape): mesh + camera pass set-up, the batched shading launches
(kernel time, synchronised), the copy of the three image stacks to the host, and their total, which
is what ``Renderer.render`` costs. Full results go to $OUT/bench_render.json when OUT is set.

    python benchmarks/bench_render.py                      # 250 lights, 480x270, every device here
    python benchmarks/bench_render.py --devices cpu --lights 64 --size 240x135
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import warp as wp

from warp_highlights.model.lights import LightSet
from warp_highlights.synth.render import (
    Renderer,
    RenderSettings,
    default_material,
    view_rotation,
)
from warp_highlights.synth.shapes import make_shape


def _time(fn, device) -> tuple[float, object]:
    wp.synchronize_device(device)
    started = time.perf_counter()
    result = fn()
    wp.synchronize_device(device)
    return time.perf_counter() - started, result


def bench(shape: str, device: str, lights: np.ndarray, width: int, height: int, samples: int, repeat: int) -> dict:
    """One (shape, device) measurement; times are the best of ``repeat`` after a warm-up (compilation)."""
    settings = RenderSettings(width=width, height=height, samples_per_pixel=samples, light_chunk=len(lights))
    mesh = make_shape(shape)

    def make() -> Renderer:
        return Renderer(mesh, material=default_material(shape), settings=settings, rotation=view_rotation(shape),
                        device=device)

    make().shade_on_device(lights[:2])  # compile and load the kernels
    setup, renderer = min((_time(make, device) for _ in range(repeat)), key=lambda r: r[0])
    shade_times, copy_times = [], []
    for _ in range(repeat):
        shade, arrays = _time(lambda: renderer.shade_on_device(lights), device)
        copy, _ = _time(lambda: [a.numpy() for a in arrays], device)
        shade_times.append(shade)
        copy_times.append(copy)
    best = int(np.argmin(np.add(shade_times, copy_times)))
    return {
        "shape": shape,
        "device": device,
        "device_name": wp.get_device(device).name,
        "lights": len(lights),
        "size": f"{width}x{height}",
        "samples_per_pixel": samples,
        "faces": mesh.face_count,
        "covered_pixels": int((renderer.coverage > 0).sum()),
        "setup_s": setup,
        "shade_s": shade_times[best],
        "copy_s": copy_times[best],
        "total_s": setup + shade_times[best] + copy_times[best],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lights", type=int, default=250)
    parser.add_argument("--size", default="480x270")
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--shapes", default="donut,teapot")
    parser.add_argument("--devices", default=None,
                        help="comma-separated Warp devices (default: cpu and every CUDA device)")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    devices = args.devices.split(",") if args.devices else ["cpu"] + [str(d) for d in wp.get_cuda_devices()]
    width, height = (int(v) for v in args.size.split("x"))
    lights = LightSet.fibonacci_sphere(args.lights).directions
    rows = [
        bench(shape, device, lights, width, height, args.samples, args.repeat)
        for device in devices
        for shape in args.shapes.split(",")
    ]
    print(f"\nrender benchmark: {args.lights} lights, {args.size}, {args.samples} samples/px, "
          f"warp {wp.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    header = (f"{'device':<28} {'shape':<7} {'faces':>6} {'px hit':>7} {'setup s':>8} {'shade s':>8} {'copy s':>7} "
              f"{'total s':>8} {'ms/light':>9}")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['device'] + ' ' + r['device_name']:<28.28} {r['shape']:<7} {r['faces']:>6} {r['covered_pixels']:>7} "
            f"{r['setup_s']:>8.3f} {r['shade_s']:>8.3f} {r['copy_s']:>7.3f} {r['total_s']:>8.3f} "
            f"{1000 * (r['shade_s'] + r['copy_s']) / r['lights']:>9.2f}"
        )
    if os.environ.get("OUT"):
        out = Path(os.environ["OUT"])
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench_render.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
