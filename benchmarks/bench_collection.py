"""A collection on one GPU against several: the wall time of ``warp-highlights collection``.

    python benchmarks/bench_collection.py [--captures 20] [--lights 64] [--size 480x270] [--gpus 1,2] [--work DIR]
                                          [--residual lowrank] [--baselines none] [--no-evaluate] [--json FILE]
                                          [--slice A:B] [--no-warm-up]
    python benchmarks/bench_collection.py --combine PART.json... [--json FILE]

Renders ``--captures`` captures (the donut, teapot and sphere in turn, each under its own Fibonacci lights and
held-out centroids, float16 EXR) into ``--work`` once, then runs the whole ``collection`` command (fit, evaluate
against PTM/HSH/RBF and the alpha blend, export the viewer, thumbnail) with ``--force`` on each GPU count, as a
user runs it: a separate process, a fresh local cluster. A one-capture collection first compiles the kernels
into the shared cache, so no timed run pays for that. Prints a Markdown table (and ``--json`` the figures);
``--gpus 0`` times CPU workers instead.

Where one run is longer than a time limit allows (20 captures take minutes on one GPU), ``--slice A:B`` times the sorted
captures A..B-1 alone (the captures are still rendered once, all of them), ``--no-warm-up`` skips the compiling run on a
machine that did it, and ``--combine`` sums the parts' ``--json`` files per GPU count into the whole collection's table.
Each part is a whole command, so a sum counts one start of the command and its cluster per part (``--json`` records
each). ``--json`` is written again after each GPU count, so a call cut off by its limit keeps the counts it finished.
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
        command = [sys.executable, "-m", "warp_highlights", "render", SHAPES[k % len(SHAPES)], str(folder), "--lights",
                   str(lights + k % 5),
                   "--size", size, "--half", "-q"] + (["--device", device] if device else [])
        subprocess.run(command, check=True)
    return captures


def collection(captures: list[Path], output: Path, gpus: int, residual: str, extra: list[str]) -> tuple[float, dict]:
    command = [sys.executable, "-m", "warp_highlights", "collection", *map(str, captures), "-o", str(output), "--force",
               "-q",
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
    parser.add_argument("--residual", default="lowrank",
                        help="fit --residual (default lowrank: the learned one trains for minutes by design)")
    parser.add_argument("--device", default=None, help="device for rendering (default: CUDA when present)")
    parser.add_argument(
        "--baselines", default=None,
        help="collection --baselines (default: its own, ptm,hsh2,hsh3,rbf; 'none' for the field and the blend alone)")
    parser.add_argument("--no-evaluate", action="store_true",
                        help="collection --no-evaluate: fit, export and thumbnail only")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--slice", default=None, metavar="A:B",
                        help="time the sorted captures A..B-1 alone (one part of a run)")
    parser.add_argument("--no-warm-up", action="store_true",
                        help="skip the compiling one-capture run (the cache is warm)")
    parser.add_argument("--combine", type=Path, nargs="+", metavar="PART",
                        help="sum these parts' --json files per GPU count")
    args = parser.parse_args()
    if args.combine:
        report = combine([json.loads(path.read_text()) for path in args.combine])
        print_table(report["rows"])
        if args.json:
            write_json(args.json, report)
        return
    extra = ((["--baselines", args.baselines] if args.baselines else [])
             + (["--no-evaluate"] if args.no_evaluate else []))
    start, stop = parse_slice(args.slice, args.captures)
    started = time.perf_counter()
    folder = render(args.work, args.captures, args.lights, args.size, args.device)
    captures = sorted(p for p in folder.iterdir() if p.is_dir())
    print(f"{args.captures} captures of {args.lights}-{args.lights + 4} lights at {args.size} in {folder} "
          f"({time.perf_counter() - started:.1f} s); "
          f"timing captures {start}..{stop - 1}; {os.cpu_count()} cores", flush=True)
    counts = [int(g) for g in args.gpus.split(",")]
    if not args.no_warm_up:
        # kernels compiled into the cache
        collection(captures[:1], args.work / "warm-up", max(counts[0], 0), args.residual, extra)
    rows = []
    for gpus in counts:
        seconds, data = collection(captures[start:stop], args.work / f"out-{gpus}gpu-{start}-{stop}", gpus,
                                   args.residual, extra)
        records = [r for r in data["captures"] if r["status"] == "ok"]
        rows.append({"gpus": gpus, "seconds": round(seconds, 2), "finished": len(records),
                     "captures": len(data["captures"]),
                     "capture_seconds": sorted(r["seconds"]["total"] for r in records),
                     "fit_seconds_total": data["summary"]["fit_seconds"],
                     "mean_psnr_db": data["summary"]["mean_psnr_db"], "parts": 1})
        print(f"--gpus {gpus}: {seconds:.1f} s, {len(records)} of {len(data['captures'])} finished", flush=True)
        if args.json:  # after each GPU count, so a run cut off by a time limit keeps the counts it finished
            write_json(args.json, {"captures": args.captures, "lights": args.lights, "size": args.size,
                                   "residual": args.residual,
                                   "collection_options": extra, "slice": [start, stop], "rows": rows})
    print_table(rows)


def write_json(path: Path, report: dict) -> None:
    """``report`` into ``path`` through the project's atomic writer: a reader never sees half a file."""
    from warp_highlights.io.atomic import atomic_file

    with atomic_file(path) as temporary:
        temporary.write_text(json.dumps(report, indent=1))


def parse_slice(text: str | None, count: int) -> tuple[int, int]:
    """``A:B`` (either side may be empty) -> (start, stop) within ``count`` captures; the whole when None."""
    if text is None:
        return 0, count
    try:
        first, last = text.split(":")
        start, stop = int(first or 0), int(last or count)
    except ValueError:
        sys.exit(f"--slice {text!r}: give A:B, e.g. 0:10")
    if not 0 <= start < stop <= count:
        sys.exit(f"--slice {text!r}: needs 0 <= A < B <= {count}")
    return start, stop


def combine(parts: list[dict]) -> dict:
    """The parts' rows summed per GPU count (seconds, captures, fits; PSNR means weighted by finished captures).

    The parts must be of one benchmark (captures, lights, size, residual, options) and cover disjoint
    slices; each GPU count must cover every capture once.
    """
    keys = ("captures", "lights", "size", "residual", "collection_options")
    if any(tuple(p[k] for k in keys) != tuple(parts[0][k] for k in keys) for p in parts):
        sys.exit(
            "--combine: the parts come from different benchmarks (captures, lights, size, residual or options differ)")
    rows = {}
    for part in parts:
        for row in part["rows"]:
            total = rows.setdefault(row["gpus"], {"gpus": row["gpus"], "seconds": 0.0, "finished": 0, "captures": 0,
                                                  "capture_seconds": [],
                                                  "fit_seconds_total": 0.0, "mean_psnr_db": {}, "parts": 0,
                                                  "slices": []})
            for method, value in (row["mean_psnr_db"] or {}).items():
                total["mean_psnr_db"][method] = total["mean_psnr_db"].get(method, 0.0) + value * row["finished"]
            total["seconds"] += row["seconds"]
            total["finished"] += row["finished"]
            total["captures"] += row["captures"]
            total["capture_seconds"] = sorted(total["capture_seconds"] + row["capture_seconds"])
            total["fit_seconds_total"] += row["fit_seconds_total"]
            total["parts"] += 1
            total["slices"].append(part["slice"])
    for total in rows.values():
        covered = sorted(i for a, b in total["slices"] for i in range(a, b))
        if covered != list(range(parts[0]["captures"])):
            sys.exit(f"--combine: the parts for --gpus {total['gpus']} cover captures {covered}, not each of "
                     f"0..{parts[0]['captures'] - 1} once")
        total["seconds"] = round(total["seconds"], 2)
        total["mean_psnr_db"] = {m: round(v / max(total["finished"], 1), 2) for m, v in total["mean_psnr_db"].items()}
    return {**{k: parts[0][k] for k in keys}, "rows": [rows[g] for g in sorted(rows)]}


def print_table(rows: list[dict]) -> None:
    base = rows[0]["seconds"]
    print("\n| workers | whole command | parts | captures finished | per capture (median) | fits summed | speed-up |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        what = f"{row['gpus']} GPU" + ("s" if row["gpus"] > 1 else "") if row["gpus"] else "CPU workers"
        times = row["capture_seconds"]
        median = f"{times[len(times) // 2]:.1f} s" if times else "-"
        print(f"| {what} | {row['seconds']:.1f} s | {row['parts']} | {row['finished']} of "
              f"{row['captures']} | {median} | "
              f"{row['fit_seconds_total']:.1f} s | {base / row['seconds']:.2f}x |")


if __name__ == "__main__":
    main()
