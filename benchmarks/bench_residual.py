"""The residual's compression alone (``residual.build.build_residual``): time, peak host memory, ranks and
bits, with the normalised stacks held in memory and read from the images block by block.

    python benchmarks/bench_residual.py DATASET [--size WxH] [--budget 0.24] [--modes held,streamed]

The residual is that of the images without any Gaussians (their own highlights zero, no highlight
colour): the compression's whole work at the dataset's size, without fitting first. ``held`` keeps
the normalised luminance and chroma stacks (what a fit does while they take at most
``HELD_STACK_SHARE`` of the available memory); ``streamed`` computes them from the images in each
pass (what it does beyond). Peak memory is the process's resident memory above what it held before
the call (``model.memory.PeakMemory``). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--size", default=None, help="working size WxH (default: the images' own)")
    parser.add_argument("--budget", type=float, default=0.24, help="residual.size_budget (default 0.24)")
    parser.add_argument("--modes", default="held,streamed")
    args = parser.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import warp_highlights.residual.build as residual_module
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.resample import resize_stack
    from warp_highlights.model.config import FitSettings
    from warp_highlights.model.memory import PeakMemory, resident_memory
    from warp_highlights.model.threads import NUMPY_THREADS

    dataset = ReflectanceField.load(args.dataset, heldout=False, components=False, progress=False)
    images = dataset.images
    if args.size:
        width, height = (int(part) for part in args.size.lower().split("x"))
        images = resize_stack(images, width, height)
    images = np.ascontiguousarray(images, dtype=np.float32)
    n, height, width = images.shape[:3]
    own = np.zeros((n, height, width), np.float32)
    settings = replace(FitSettings().residual, size_budget=args.budget)
    print(f"{args.dataset}: {n} lights, {width}x{height}, {NUMPY_THREADS} threads, budget {args.budget}\n")
    print("| mode | seconds | peak host above the inputs | luminance rank | chroma rank | bits |")
    print("|---|---|---|---|---|---|")
    share = residual_module.HELD_STACK_SHARE
    for mode in args.modes.split(","):
        residual_module.HELD_STACK_SHARE = {"held": float("inf"), "streamed": 0.0}[mode]
        before = resident_memory() or 0
        started = time.perf_counter()
        with PeakMemory() as peak:
            model = residual_module.build_residual(images, own, None, settings=settings)
        seconds = time.perf_counter() - started
        chroma = "" if model.chroma is None else model.chroma.rank
        grown = "" if peak.host is None else f"{(peak.host - before) / 1e9:.2f} GB"
        print(f"| {mode} | {seconds:.2f} | {grown} | {model.luminance.rank} | {chroma} | {model.luminance.bits} |",
              flush=True)
        del model
    residual_module.HELD_STACK_SHARE = share


if __name__ == "__main__":
    main()
