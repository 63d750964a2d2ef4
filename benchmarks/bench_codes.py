"""Bytes and seconds of fields' basis codes as the field file stores them (format 5, ``io.codes``:
zigzag row differences in byte planes, a Blosc chunk per image) against format 4's layout (row
differences without the zigzag, raw deflate run-length only, a sync-flushed piece per image); and
each field's bytes and ``save_field`` seconds as this version writes it.

    python benchmarks/bench_codes.py FIELD.whf [FIELD.whf ...] [--every 1] [--repeat 5]

The first table: each stack's every ``--every``-th basis image made into its stored form and
compressed as each layout stores it, one image at a time on one thread (the rate search's unit of
work), best of ``--repeat``; the totals. The second: the field loaded and saved again (best and
median of ``--repeat``), once with every image's chunk kept as the fit's rate search keeps them (the
save after a fit) and once with none (a loaded field saved again: the codes compressed in threads).
Format 4's field bytes and save seconds come from running the same save with a version that writes
format 4 (``benchmarks/README.md`` gives both).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np

from warp_highlights.io.codes import CompressedCodes, compressed_chunk, stored_codes
from warp_highlights.io.fieldfile import FORMAT_VERSION, load_field, save_field


def format_4_stored(codes: np.ndarray) -> np.ndarray:
    """Format 4's stored form of (P, H, W) codes: row differences modulo 2^bits, 16 bits as byte planes."""
    difference = codes.copy()
    difference[..., 1:, :] -= codes[..., :-1, :]  # unsigned: wraps
    if codes.dtype == np.uint8:
        return difference
    return np.stack([(difference >> 8).astype(np.uint8), (difference & 0xFF).astype(np.uint8)], axis=-3)


def format_4_bytes(codes: np.ndarray) -> int:
    """Format 4's bytes of one image: its piece, raw deflate at level 6 with ``Z_RLE``, sync-flushed."""
    compressor = zlib.compressobj(6, zlib.DEFLATED, -15, 8, zlib.Z_RLE)
    return len(compressor.compress(format_4_stored(codes)) + compressor.flush(zlib.Z_SYNC_FLUSH))


def format_5_bytes(codes: np.ndarray) -> int:
    """This version's bytes of one image: the Blosc chunk of its stored form."""
    return len(compressed_chunk(stored_codes(codes)))


def timed(function, items: list, repeat: int) -> tuple[int, float]:
    """(sum of ``function`` over ``items``, the best seconds of ``repeat`` runs)."""
    best, total = float("inf"), 0
    for _ in range(repeat):
        started = time.perf_counter()
        total = sum(function(item) for item in items)
        best = min(best, time.perf_counter() - started)
    return total, best


def with_kept_chunks(field):
    """The field with every basis image's chunk kept, as the fit's rate search leaves its stacks."""
    residual = field.residual
    if residual is None:
        return field
    stacks = {}
    for name in ("luminance", "chroma"):
        stack = getattr(residual, name)
        if stack is None:
            continue
        kept = CompressedCodes()
        stored = [stored_codes(code.transpose(2, 0, 1)) for code in stack.codes]
        kept.keep({CompressedCodes.key(image): compressed_chunk(image) for image in stored})
        stacks[name] = dataclasses.replace(stack, chunks=kept)
    return dataclasses.replace(field, residual=dataclasses.replace(residual, **stacks))


def save_seconds(field, folder: Path, repeat: int) -> tuple[float, float, int, int]:
    """(best, median seconds of ``save_field``, the file's bytes, its codes entries' bytes)."""
    target = folder / "field.whf"
    seconds = []
    for _ in range(repeat):
        started = time.perf_counter()
        save_field(field, target)
        seconds.append(time.perf_counter() - started)
    with zipfile.ZipFile(target) as archive:
        codes = sum(info.compress_size for info in archive.infolist() if "_codes.npy" in info.filename)
    return min(seconds), statistics.median(seconds), target.stat().st_size, codes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fields", nargs="+", type=Path)
    parser.add_argument("--every", type=int, default=1, help="compress every k-th basis image (default 1: all)")
    parser.add_argument("--repeat", type=int, default=5, help="runs of each measurement (default 5)")
    args = parser.parse_args()
    print("| field | stack | codes | images | format 4 bytes | format 5 bytes | share | format 4 s | "
          "format 5 s | faster |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    fields = {}
    for path in args.fields:
        field = fields[path] = load_field(path)
        for name in ("luminance", "chroma"):
            stack = None if field.residual is None else getattr(field.residual, name)
            if stack is None or stack.rank == 0:
                continue
            images = [code.transpose(2, 0, 1) for code in stack.codes[:: max(1, args.every)]]
            before, before_s = timed(format_4_bytes, images, args.repeat)
            after, after_s = timed(format_5_bytes, images, args.repeat)
            print(f"| {path.name} | {name} | {stack.bits}-bit {stack.codes.shape[1]}x{stack.codes.shape[2]} | "
                  f"{len(images)} | "
                  f"{before / 1e6:.3f} MB | {after / 1e6:.3f} MB | {after / before:.1%} | {before_s:.3f} | "
                  f"{after_s:.3f} | {before_s / after_s:.1f}x |")
    print()
    print("| field | format | field bytes | codes bytes | save, chunks kept: best / median s | save, none kept: "
          "best / median s |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for path, field in fields.items():
            kept_best, kept_median, size, codes = save_seconds(with_kept_chunks(field), Path(folder), args.repeat)
            plain_best, plain_median, _, _ = save_seconds(field, Path(folder), args.repeat)
            print(f"| {path.name} | {FORMAT_VERSION} | {size:,} | {codes:,} | {kept_best:.3f} / {kept_median:.3f} | "
                  f"{plain_best:.3f} / {plain_median:.3f} |")


if __name__ == "__main__":
    main()
