"""What a CUDA device's start and host<->device copies cost: the figures behind ``kernels.warmup`` and
``kernels.transfer.Staging``.

    python benchmarks/bench_transfer.py [--device cuda:0] [--gib 8]

Prints a Markdown table: ``wp.init``, the device's context, the memory pool's first allocations (and
its release threshold), page-locking ``--gib`` GiB, filling it from threads, and the copy rates up and
down from page-locked and from pageable memory, then ``rows_up`` / ``rows_down`` of a stack band of
that size (through ``Staging`` from ``STAGED_MIN_BYTES``). Needs a CUDA device.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--gib", type=int, default=8, help="GiB copied each way (default 8)")
    args = parser.parse_args()
    import numpy as np
    import warp as wp

    rows = []
    started = time.perf_counter()
    wp.init()
    rows.append(("`wp.init`", f"{time.perf_counter() - started:.3f} s"))
    device = wp.get_device(args.device)
    if not device.is_cuda:
        raise SystemExit("bench_transfer.py needs a CUDA device")
    started = time.perf_counter()
    device.context  # noqa: B018 (made on first use)
    rows.append(("the device's context", f"{time.perf_counter() - started:.3f} s"))
    firsts = []
    for size in (1 << 20, 400 << 20, 1600 << 20):
        started = time.perf_counter()
        block = wp.empty(size, dtype=wp.uint8, device=device)
        wp.synchronize_device(device)
        firsts.append(f"{(time.perf_counter() - started) * 1e3:.1f} ms")
        del block
    rows.append(("the memory pool's first 1 MB / 400 MB / 1.6 GB",
                 " / ".join(firsts) + f" (release threshold {wp.get_mempool_release_threshold(device)})"))

    values = (args.gib << 30) // 4
    shape = (8, values // 8)  # Warp's dimensions stay under 2^31
    started = time.perf_counter()
    pinned = wp.empty(shape, dtype=float, device="cpu", pinned=True)
    rows.append((f"page-locking {args.gib} GiB", f"{time.perf_counter() - started:.2f} s"))
    flat = pinned.numpy().reshape(-1)
    parts = 16
    started = time.perf_counter()
    with ThreadPoolExecutor(parts) as pool:
        list(pool.map(lambda i: flat[i * (flat.size // parts) : (i + 1) * (flat.size // parts)].fill(1.0),
                      range(parts)))
    rows.append((f"filling it from {parts} threads", f"{time.perf_counter() - started:.2f} s"))
    pageable = np.ones(shape, np.float32)
    on_device = wp.empty(shape, dtype=float, device=device)
    for name, host in (("page-locked", pinned),
                       ("pageable", wp.array(pageable, dtype=float, device="cpu", copy=False))):
        for direction in ("up", "down"):
            best = np.inf
            for _ in range(2):
                wp.synchronize_device(device)
                started = time.perf_counter()
                wp.copy(on_device, host) if direction == "up" else wp.copy(host, on_device)
                wp.synchronize_device(device)
                best = min(best, time.perf_counter() - started)
            rows.append((f"{args.gib} GiB {direction}, {name}", f"{(args.gib << 30) / best / 1e9:.1f} GB/s"))
    del pinned, on_device

    from warp_highlights.kernels.transfer import STAGED_MIN_BYTES, rows_down, rows_up

    stack = np.ones((64, (args.gib << 30) // (64 * 4 * 2)), np.float32)  # a band: half of each row
    band = stack[:, : stack.shape[1] // 2]
    for _ in range(2):
        started = time.perf_counter()
        up = rows_up(band, device)
        wp.synchronize_device(device)
        seconds_up = time.perf_counter() - started
        started = time.perf_counter()
        rows_down(up, band)
        seconds_down = time.perf_counter() - started
        del up
    staged = "staged" if band.nbytes >= STAGED_MIN_BYTES else "direct"
    rows.append((f"`rows_up` / `rows_down` of a {band.nbytes / 1e9:.1f} GB band ({staged})",
                 f"{band.nbytes / seconds_up / 1e9:.1f} / {band.nbytes / seconds_down / 1e9:.1f} GB/s"))
    print(f"device {device} ({device.name})\n")
    print("| what | measured |\n|---|---|")
    for what, figure in rows:
        print(f"| {what} | {figure} |")


if __name__ == "__main__":
    main()
