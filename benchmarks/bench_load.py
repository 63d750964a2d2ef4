"""Loading a capture: every image decoded on one thread against the threads of
``ReflectanceField.load`` and what ``fit`` loads (no held-out lights, no ground-truth components,
each image shrunk to the working size as it is decoded).

    python benchmarks/bench_load.py DATASET [DATASET ...] [--size WxH] [--repeat 3]

Prints a Markdown table: seconds (best of ``--repeat``, the files in the page cache after the first
read), images decoded, and the float32 bytes held.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.io.dataset import LOAD_WORKERS, ReflectanceField  # noqa: E402


def _held(field) -> int:
    parts = [field.images, field.specular, field.diffuse]
    if field.heldout is not None:
        parts += [field.heldout.images, field.heldout.specular, field.heldout.diffuse]
    return sum(part.nbytes for part in parts if part is not None)


def _count(field) -> int:
    return sum(len(part) for part in (field.images, field.specular, field.diffuse) if part is not None) + (
        _count(field.heldout) if field.heldout is not None else 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--size", help="working size WxH for the last row (default: half the images' size)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"{os.cpu_count()} cores, LOAD_WORKERS = {LOAD_WORKERS}\n")
    print("| dataset | how | images decoded | held (MB) | seconds |")
    print("|---|---|---|---|---|")
    for folder in args.datasets:
        probe = ReflectanceField.load(folder, progress=False, heldout=False, components=False)
        size = (tuple(int(v) for v in args.size.split("x")) if args.size
                else (probe.width // 2, round(probe.width // 2 * probe.height / probe.width)))
        cases = [
            ("everything, 1 thread", dict(workers=1)),
            (f"everything, {LOAD_WORKERS} threads", dict()),
            (f"what fit uses, {LOAD_WORKERS} threads", dict(heldout=False, components=False)),
            (f"what fit uses at {size[0]}x{size[1]}", dict(heldout=False, components=False, size=size)),
        ]
        for label, options in cases:
            best, field = float("inf"), None
            for _ in range(args.repeat):
                started = time.perf_counter()
                field = ReflectanceField.load(folder, progress=False, **options)
                best = min(best, time.perf_counter() - started)
            print(f"| {folder.name} | {label} | {_count(field)} | {_held(field) / 1e6:.0f} | {best:.2f} |")


if __name__ == "__main__":
    main()
