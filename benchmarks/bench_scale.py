"""The whole ``fit`` command at growing capture sizes: wall time, stage times, peak memory, field size
and the query time of the field it wrote.

    python benchmarks/bench_scale.py [--cases 250x480x270,250x1920x1080,1000x1920x1080,100x3840x2160]
                                     [--work DIR] [--device cuda:0] [--residual lowrank] [--json FILE]

Each case is LIGHTSxWIDTHxHEIGHT: the donut rendered under that many Fibonacci lights (float16 EXR, no
held-out lights; rendered once into ``--work`` and reused), then ``warp-highlights fit`` run as a
separate process, as a user runs it (Python start, Warp's start and the kernel cache warm from the
first case). Peak memory is the largest stage's (``fit --report``: resident host memory, Warp's CUDA
memory pool). The query is one relit image of the field at its own size, the median of ``--repeat``
random directions: the image made on the device (CUDA: the single-query graph's kernels alone, timed by
CUDA events), the same graph with its copies into page-locked memory (CPU: launch to synchronise),
and into host memory (``relight(direction)``).

Prints a Markdown table (and ``--json`` the figures).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_CASES = "250x480x270,250x1920x1080,1000x1920x1080,100x3840x2160"
STAGES = ("loading", "segmentation", "estimation", "retargeting", "move check", "residual compression",
          "learned residual", "saving")


def parse_case(text: str) -> tuple[int, int, int]:
    lights, width, height = (int(part) for part in text.lower().split("x"))
    return lights, width, height


def render(folder: Path, lights: int, width: int, height: int, device: str | None) -> float | None:
    """Render the case unless ``folder`` holds it already; seconds taken (None: reused)."""
    if (folder / "lights.lp").is_file():
        return None
    command = [sys.executable, "-m", "warp_highlights", "render", "donut", str(folder), "--lights", str(lights),
               "--size", f"{width}x{height}",
               "--heldout", "none", "--half", "-q"]
    if device:
        command += ["--device", device]
    started = time.perf_counter()
    subprocess.run(command, check=True)
    return time.perf_counter() - started


def fit(folder: Path, field: Path, report: Path, device: str | None, residual: str, extra: list[str]) -> float:
    """Wall seconds of the whole ``fit`` command (load + fit + save)."""
    command = [sys.executable, "-m", "warp_highlights", "fit", str(folder), "-o", str(field), "--report", str(report),
               "--overwrite",
               "--residual", residual, "-q", *extra]
    if device:
        command += ["--device", device]
    started = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)  # its summary: the report has it all
    return time.perf_counter() - started


def query_times(field_path: Path, device: str | None, repeat: int) -> tuple[float, float, float | None]:
    """Median milliseconds of one relit image of the field: the single-query graph with its copies into
    page-locked memory (CUDA; elsewhere launch to synchronise), into host memory (``relight``), and
    the graph's kernels alone, the image made on the device (CUDA only, else None)."""
    import numpy as np
    import warp as wp

    from benchmarks.bench_relight import graph_device_ms, random_directions, time_calls
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.relight.relighter import Relighter

    field = load_field(field_path)
    relighter = Relighter(field, device=device)
    directions = random_directions(repeat + 2, seed=3)

    def on_device(i):
        relighter.launch(directions[i : i + 1])
        wp.synchronize_device(relighter.device)

    def to_host(i):
        relighter.relight(directions[i])

    on_device(0)
    to_host(0)
    host = float(np.median(time_calls(to_host, repeat))) * 1e3
    events = graph_device_ms(relighter, directions)
    device = events["graph"] if events else float(np.median(time_calls(on_device, repeat))) * 1e3
    return device, host, events.get("kernels")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=DEFAULT_CASES,
                        help=f"LIGHTSxWIDTHxHEIGHT, comma-separated (default {DEFAULT_CASES})")
    parser.add_argument("--work", type=Path, default=Path("bench-scale"),
                        help="folder for the rendered captures and the fields")
    parser.add_argument("--device", default=None,
                        help="Warp device for rendering, fitting and the query (default: CUDA when present)")
    parser.add_argument("--residual", default="lowrank",
                        help="fit --residual (default lowrank: the learned one trains for minutes by design)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="fit --set, repeatable")
    parser.add_argument("--repeat", type=int, default=100, help="queries timed per field (default 100)")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    extra = [arg for item in args.overrides for arg in ("--set", item)]
    rows = []
    print(f"{os.cpu_count()} cores, device {args.device or 'default'}, residual {args.residual}\n", flush=True)
    for text in args.cases.split(","):
        lights, width, height = parse_case(text)
        name = f"donut-{lights}x{width}x{height}"
        folder, field, report_path = args.work / name, args.work / f"{name}.whf", args.work / f"{name}.json"
        rendered = render(folder, lights, width, height, args.device)
        seconds = fit(folder, field, report_path, args.device, args.residual, extra)
        report = json.loads(report_path.read_text())
        memory = report["memory"]
        host = max((v["host_peak_bytes"] or 0 for v in memory.values()), default=0)
        device_peak = max((v["device_peak_bytes"] or 0 for v in memory.values()), default=0)
        on_device, to_host, kernels = query_times(field, args.device, args.repeat)
        row = {
            "case": text, "lights": lights, "width": width, "height": height, "render_seconds": rendered,
            "fit_command_seconds": round(seconds, 2), "stages": report["seconds"],
            "gaussian_size": report.get("gaussian_size"),
            "host_peak_bytes": host, "device_peak_bytes": device_peak or None, "memory": memory,
            "field_bytes": field.stat().st_size, "query_on_device_ms": round(on_device, 3),
            "query_to_host_ms": round(to_host, 3),
            "query_kernels_ms": None if kernels is None else round(kernels, 3),
            "residual": report.get("residual", {}) and {k: report["residual"][k]
                                                        for k in ("luminance_rank", "chroma_rank", "basis_bits")},
        }
        rows.append(row)
        stages = ", ".join(f"{k} {report['seconds'][k]:.1f}" for k in STAGES if k in report["seconds"])
        print(f"{text}: fit {seconds:.1f} s ({stages}); host {host / 1e9:.1f} GB, device "
              f"{device_peak / 1e9 if device_peak else float('nan'):.1f} GB; "
              f"field {row['field_bytes'] / 1e6:.1f} MB; query {kernels if kernels is not None else float('nan'):.3f} "
              f"ms of kernels on the device, "
              f"{on_device:.3f} ms with the copies into page-locked memory, {to_host:.3f} ms to host", flush=True)
    print("\n| lights x size | whole fit | loading | segmentation | estimation | retargeting | residual "
          "compression | saving | "
          "peak host | peak device | field | query (kernels / with copies / to host) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        stage = lambda key: f"{row['stages'][key]:.1f} s" if key in row["stages"] else "-"
        device_text = f"{row['device_peak_bytes'] / 1e9:.1f} GB" if row["device_peak_bytes"] else "-"
        print(f"| {row['lights']} x {row['width']}x{row['height']} | {row['fit_command_seconds']:.1f} s | "
              f"{stage('loading')} | {stage('segmentation')} | "
              f"{stage('estimation')} | {stage('retargeting')} | {stage('residual compression')} | {stage('saving')} | "
              f"{row['host_peak_bytes'] / 1e9:.1f} GB | {device_text} | {row['field_bytes'] / 1e6:.1f} MB | "
              f"{row['query_kernels_ms'] if row['query_kernels_ms'] is not None else '-'} / "
              f"{row['query_on_device_ms']:.3f} / {row['query_to_host_ms']:.3f} ms |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
