"""A collection on one GPU against several: the wall time of ``warp-highlights collection``.

    python benchmarks/bench_collection.py [--captures 20] [--lights 64] [--size 480x270] [--gpus 1,2] [--work DIR]
                                          [--residual lowrank] [--baselines none] [--no-evaluate] [--json FILE]

Renders ``--captures`` captures (the donut, teapot and sphere in turn, each under its own Fibonacci lights and
held-out centroids, float16 EXR) into ``--work`` once, then runs the whole ``collection`` command (fit, evaluate
against PTM/HSH/RBF and the alpha blend, export the viewer, thumbnail) with ``--force`` on each GPU count, as a
user runs it: a separate process, a fresh local cluster. A one-capture collection first compiles the kernels
into the shared cache, so no timed run pays for that. Prints a Markdown table (and ``--json`` the figures);
``--gpus 0`` times CPU workers instead.
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

SHAPES = ("donut", "teapot", "sphere")


def render(work: Path, count: int, lights: int, size: str, device: str | None) -> Path:
    captures = work / f"captures-{count}x{lights}x{size}"
    captures.mkdir(parents=True, exist_ok=True)
    for k in range(count):
        folder = captures / f"{SHAPES[k % len(SHAPES)]}-{k:03d}"
        if (folder / "lights.lp").is_file():
            continue
        command = [sys.executable, "-m", "warp_highlights", "render", SHAPES[k % len(SHAPES)], str(folder), "--lights", str(lights + k % 5),
                   "--size", size, "--half", "-q"] + (["--device", device] if device else [])
        subprocess.run(command, check=True)
    return captures


def collection(captures: Path, output: Path, gpus: int, residual: str, extra: list[str]) -> tuple[float, dict]:
    command = [sys.executable, "-m", "warp_highlights", "collection", str(captures), "-o", str(output), "--force", "-q",
               "--gpus", str(gpus), "--residual", residual, *extra]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"collection with --gpus {gpus} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return seconds, json.loads((output / "collection.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--captures", type=int, default=20)
    parser.add_argument("--lights", type=int, default=64, help="lights of the first capture (the others: up to 4 more)")
    parser.add_argument("--size", default="480x270")
    parser.add_argument("--gpus", default="1,2", help="GPU counts to time, comma-separated (0: CPU workers)")
    parser.add_argument("--work", type=Path, default=Path("bench-collection"))
    parser.add_argument("--residual", default="lowrank", help="fit --residual (default lowrank: the learned one trains for minutes by design)")
    parser.add_argument("--device", default=None, help="device for rendering (default: CUDA when present)")
    parser.add_argument("--baselines", default=None, help="collection --baselines (default: its own, ptm,hsh2,hsh3,rbf; 'none' for the field and the blend alone)")
    parser.add_argument("--no-evaluate", action="store_true", help="collection --no-evaluate: fit, export and thumbnail only")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    extra = (["--baselines", args.baselines] if args.baselines else []) + (["--no-evaluate"] if args.no_evaluate else [])
    started = time.perf_counter()
    captures = render(args.work, args.captures, args.lights, args.size, args.device)
    print(f"{args.captures} captures of {args.lights}-{args.lights + 4} lights at {args.size} in {captures} ({time.perf_counter() - started:.1f} s); "
          f"{os.cpu_count()} cores", flush=True)
    counts = [int(g) for g in args.gpus.split(",")]
    first = sorted(captures.iterdir())[0]
    collection(first, args.work / "warm-up", max(counts[0], 0), args.residual, extra)  # kernels compiled into the cache
    rows = []
    for gpus in counts:
        seconds, data = collection(captures, args.work / f"out-{gpus}gpu", gpus, args.residual, extra)
        records = [r for r in data["captures"] if r["status"] == "ok"]
        per_capture = sorted(r["seconds"]["total"] for r in records)
        rows.append({"gpus": gpus, "seconds": round(seconds, 2), "finished": len(records), "captures": len(data["captures"]),
                     "capture_seconds_median": per_capture[len(per_capture) // 2] if per_capture else None,
                     "fit_seconds_total": data["summary"]["fit_seconds"], "mean_psnr_db": data["summary"]["mean_psnr_db"]})
        print(f"--gpus {gpus}: {seconds:.1f} s, {len(records)} of {len(data['captures'])} finished", flush=True)
    base = rows[0]["seconds"]
    print("\n| workers | whole command | captures finished | per capture (median) | fits summed | speed-up |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        what = f"{row['gpus']} GPU" + ("s" if row["gpus"] > 1 else "") if row["gpus"] else "CPU workers"
        print(f"| {what} | {row['seconds']:.1f} s | {row['finished']} of {row['captures']} | {row['capture_seconds_median']:.1f} s | "
              f"{row['fit_seconds_total']:.1f} s | {base / row['seconds']:.2f}x |")
    if args.json:
        args.json.write_text(json.dumps({"captures": args.captures, "lights": args.lights, "size": args.size, "residual": args.residual,
                                         "collection_options": extra, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
