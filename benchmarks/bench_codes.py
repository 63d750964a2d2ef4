"""Bytes and deflate seconds of fields' basis codes: the file's layout (``io.codes``: row differences in
byte planes, run-length deflate) against the codes as they are at zlib's default level (format 3).

    python benchmarks/bench_codes.py FIELD.whf [FIELD.whf ...] [--every 6]

Each stack's every ``--every``-th basis image is deflated as each layout stores it, one image at a time
on one thread (the rate search's unit of work); the table gives the totals.
"""

from __future__ import annotations

import argparse
import time
import zlib
from pathlib import Path

import numpy as np

from warp_highlights.io.codes import stored_bytes
from warp_highlights.io.fieldfile import load_field


def as_they_are(code: np.ndarray) -> int:
    """Format 3: the (P, H, W) codes little-endian, zlib level 6."""
    return len(zlib.compress(np.ascontiguousarray(code).tobytes(), 6))


def timed(function, images: list) -> tuple[int, float]:
    started = time.perf_counter()
    total = sum(function(image) for image in images)
    return total, time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fields", nargs="+", type=Path)
    parser.add_argument("--every", type=int, default=6, help="deflate every k-th basis image (default 6)")
    args = parser.parse_args()
    print("| field | stack | codes | images | format 3 bytes | format 4 bytes | share | format 3 s | format 4 s | faster |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in args.fields:
        residual = load_field(path).residual
        for name in ("luminance", "chroma"):
            stack = None if residual is None else getattr(residual, name)
            if stack is None or stack.rank == 0:
                continue
            images = [code.transpose(2, 0, 1) for code in stack.codes[:: max(1, args.every)]]
            before, before_s = timed(as_they_are, images)
            after, after_s = timed(stored_bytes, images)
            print(f"| {path.name} | {name} | {stack.bits}-bit {stack.codes.shape[1]}x{stack.codes.shape[2]} | {len(images)} | "
                  f"{before / 1e6:.3f} MB | {after / 1e6:.3f} MB | {after / before:.1%} | {before_s:.2f} | {after_s:.2f} | {before_s / after_s:.1f}x |")


if __name__ == "__main__":
    main()
