"""Time relighting: one query at a time (the interactive case) and a batch (the thesis' 496 centroids).

    python benchmarks/bench_relight.py [--field FIELD --dataset DATASET] [--device cuda:0] [--size 480x270]

Without ``--field`` it renders and fits the demo's donut (64 lights, 240x135, low-rank residual) first,
and relights it at ``--size`` (Gaussians are resolution-independent; the diffuse model is resampled).
Per method it times:

- ``one, on device``: locate + interpolate + rasterize + compose I' for one new direction, then
  synchronize (what an interactive viewer waits for before drawing);
- ``one, to host``: the same plus copying I' to NumPy (``relight(direction)``: on CUDA one captured
  graph launch, the direction in and the images out through page-locked memory; ``--no-graphs``:
  the separate launches);
- on CUDA with graphs, the device time of one query by CUDA events: the single-query graph with its
  copies into page-locked memory, and its kernels alone;
- ``batch``: ``--batch`` directions (default 496) in as few launches as memory allows, per query,
  on the device and with the copy to the host.

Prints a table (median of ``--repeat`` runs, milliseconds per query) and writes every figure to
$OUT/bench_relight.json when OUT is set. The alpha method needs the dataset's images (``--dataset``).
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
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.fieldfile import load_field
from warp_highlights.model.field import HighlightField
from warp_highlights.relight.relighter import Relighter, alpha_inputs


def demo_field(device) -> tuple[HighlightField, ReflectanceField]:
    """Render (in memory: no EXR writer needed) and fit the demo's donut: 64 lights, 240x135."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.model.config import FitSettings
    from warp_highlights.model.lights import LightSet
    from warp_highlights.synth.render import (
        Renderer,
        RenderSettings,
        default_material,
        view_rotation,
    )
    from warp_highlights.synth.shapes import make_shape

    lights = LightSet.fibonacci_sphere(64)
    renderer = Renderer(make_shape("donut"), material=default_material("donut"),
                        settings=RenderSettings(width=240, height=135),
                        rotation=view_rotation("donut"), device=str(device))
    dataset = ReflectanceField(images=renderer.render(lights.directions).full, lights=lights)
    # the low-rank residual: a learned one trains for minutes on CUDA
    settings = FitSettings().with_overrides(["residual.kind=lowrank"])
    return fit_field(dataset, settings=settings, device=device, progress=False), dataset


def random_directions(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions[:, 2] = np.abs(directions[:, 2])  # lights on the camera's side, where highlights are
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def time_calls(function, count: int) -> np.ndarray:
    """Seconds of each of ``count`` calls of function(i)."""
    seconds = np.empty(count)
    for i in range(count):
        started = time.perf_counter()
        function(i)
        seconds[i] = time.perf_counter() - started
    return seconds


def graph_device_ms(relighter: Relighter, directions: np.ndarray, method: str = "circular") -> dict[str, float]:
    """Median device milliseconds of one query as the designer replays it, timed by CUDA events around
    the replay (no host overhead): ``graph``, the single-query graph (direction in, locate, interpolate,
    rasterize, compose, both images out to page-locked memory); ``kernels``, the same kernels captured
    without the copies. Empty on the CPU or without graphs."""
    if not (relighter.device.is_cuda and relighter.graphs):
        return {}
    device = relighter.device
    relighter.relight(directions[0], method=method)  # captures the single-query graph
    # private: the graph relight(direction) replays, and how it sets its direction
    query = relighter._graphs[(method, True)]
    buffers = relighter.launch(directions[:1], method=method)
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        relighter._run(buffers, relighter.raster, method=method, full=True)
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)

    def set_kernels_direction(direction: np.ndarray) -> None:
        buffers.directions.assign(direction[None])
        buffers.unit.assign(direction[None].astype(np.float32))

    stream = device.stream
    start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
    medians = {}
    for name, graph, set_direction in (("graph", query.slots[0].graph, query._set),
                                       ("kernels", capture.graph, set_kernels_direction)):
        times = []
        for direction in unit:
            set_direction(direction)  # each replay at a new direction, set outside the timed span
            wp.synchronize_device(device)
            stream.record_event(start)
            wp.capture_launch(graph, stream=stream)
            stream.record_event(end)
            wp.synchronize_event(end)
            times.append(wp.get_event_elapsed_time(start, end))
        medians[name] = float(np.median(times))
    return medians


def bench_method(relighter: Relighter, method: str, *, repeat: int, batch: int) -> dict:
    device = relighter.device
    singles = random_directions(repeat + 3, seed=1)
    queries = random_directions(batch, seed=2)

    def one_on_device(i):
        relighter.launch(singles[i : i + 1], method=method)
        wp.synchronize_device(device)

    def one_to_host(i):
        relighter.relight(singles[i], method=method)

    def batch_on_device(_):
        for start in range(0, batch, relighter.max_batch):
            relighter.launch(queries[start : start + relighter.max_batch], method=method)
        wp.synchronize_device(device)

    def batch_to_host(_):
        relighter.relight(queries, method=method)

    for warm in (one_on_device, one_to_host, batch_on_device):
        warm(0)  # compile, allocate
    batch_repeat = max(2, repeat // 40)
    figures = {
        "one_on_device_ms": 1e3 * time_calls(one_on_device, repeat),
        "one_to_host_ms": 1e3 * time_calls(one_to_host, repeat),
        "batch_on_device_ms_per_query": 1e3 * time_calls(batch_on_device, batch_repeat) / batch,
        "batch_to_host_ms_per_query": 1e3 * time_calls(batch_to_host, batch_repeat) / batch,
    }
    sets = relighter.interpolated_sets(queries[: min(batch, 64)]) if method != "alpha" else None
    events = graph_device_ms(relighter, singles, method)
    return {
        **{k: {"median": float(np.median(v)), "p10": float(np.percentile(v, 10)), "p90": float(np.percentile(v, 90))}
           for k, v in figures.items()},
        **{f"one_{k}_device_events_ms": v for k, v in events.items()},
        "gaussians_per_query": None if sets is None else float(sets.counts.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--field", type=Path, help="highlight field (default: fit the demo donut first)")
    parser.add_argument("--dataset", type=Path, help="its dataset, for the alpha method")
    parser.add_argument("--device", default=None)
    parser.add_argument("--size", default="480x270", help="output WIDTHxHEIGHT (default 480x270, the thesis' size)")
    parser.add_argument("--batch", type=int, default=496,
                        help="queries in the batch (default 496: the thesis' centroids)")
    parser.add_argument("--repeat", type=int, default=200, help="single queries timed per method (default 200)")
    parser.add_argument("--methods", default="circular,straight,alpha")
    parser.add_argument("--diffuse", default="auto", help="diffuse part of I' (default auto)")
    parser.add_argument("--no-graphs", action="store_true",
                        help="single queries as separate launches, not one captured CUDA graph")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    width, height = (int(v) for v in args.size.lower().split("x"))

    if args.field is None:
        field, dataset = demo_field(device)
        source = "demo donut (64 lights, fitted at 240x135)"
    else:
        field = load_field(args.field)
        dataset = ReflectanceField.load(args.dataset, progress=False) if args.dataset else None
        source = str(args.field)
    methods = [m for m in args.methods.split(",") if m]
    alpha_specular = alpha_images = None
    if "alpha" in methods:
        if dataset is None:
            methods.remove("alpha")
        else:
            alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
    relighter = Relighter(field, device=device, size=(width, height), diffuse=args.diffuse,
                          graphs=False if args.no_graphs else None,
                          alpha_specular=alpha_specular, alpha_images=alpha_images)
    results = {m: bench_method(relighter, m, repeat=args.repeat, batch=args.batch) for m in methods}

    name = device.name if device.is_cuda else (platform.processor() or platform.machine())
    cores = os.cpu_count()
    print(f"relight {source}: {field.light_count} lights, {field.estimated.counts.mean():.1f} Gaussians per light, "
          f"output {width}x{height} x {relighter.channels} channels, {device} ({name}, {cores} cores), warp "
          f"{wp.config.version}")
    print(f"max batch per launch {relighter.max_batch}; medians in ms per query")
    print(f"| method | Gaussians / query | one (launches, device) | one graph: kernels / with copies (CUDA events) | "
          f"one (to host) | batch of {args.batch} (device) | batch (to host) |")
    print("|---|---|---|---|---|---|---|")
    for method, r in results.items():
        g = "-" if r["gaussians_per_query"] is None else f"{r['gaussians_per_query']:.1f}"
        events = (f"{r['one_kernels_device_events_ms']:.3f} / {r['one_graph_device_events_ms']:.3f}"
                  if "one_graph_device_events_ms" in r else "-")
        print(f"| {method} | {g} | {r['one_on_device_ms']['median']:.3f} | {events} | "
              f"{r['one_to_host_ms']['median']:.3f} | "
              f"{r['batch_on_device_ms_per_query']['median']:.3f} | {r['batch_to_host_ms_per_query']['median']:.3f} |")
    print("thesis (RTX 3080, 480x270): 12 ms per interpolated image (donut), 11 ms (teapot)")
    if os.environ.get("OUT"):
        out = Path(os.environ["OUT"]) / "bench_relight.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({
            "source": source, "device": str(device), "device_name": name, "cpu_count": cores, "warp": wp.config.version,
            "size": [width, height], "batch": args.batch, "repeat": args.repeat, "lights": field.light_count,
            "gaussians_per_light": float(field.estimated.counts.mean()), "max_batch": relighter.max_batch,
            "results": results,
        }, indent=2))


if __name__ == "__main__":
    main()
