"""Estimation with eager launches against one iteration captured as a CUDA graph and replayed.

    python benchmarks/bench_graphs.py DATASET [--device cuda:0]

Segments the dataset (the images ``fit`` loads), warms both paths up on a short run, then times the
default estimation twice each way and prints a Markdown table, with whether the runs agree bit for
bit (on large problems two eager runs differ already: the backward's float atomics add in varying
order). Needs a CUDA device.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PARAMETERS = ("amplitude", "mean", "sigma", "theta", "active")


def main() -> None:
    import warp as wp

    from warp_highlights.fit.estimation import estimate
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.kernels.segmentation import segment
    from warp_highlights.model.config import EstimationSettings

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--device", default="cuda:0")
    args = parser.parse_args()
    wp.init()
    if not wp.get_device(args.device).is_cuda:
        raise SystemExit(f"{args.device} is not a CUDA device: CUDA graphs need one")
    data = ReflectanceField.load(args.dataset, progress=False, heldout=False, components=False)
    targets = segment(data.images, data.lights.directions, device=args.device).specular_luminance
    short = EstimationSettings(iterations=120, densify_every=30, densify_until=100)
    for graphs in (True, False):  # loads every kernel
        estimate(targets, settings=short, device=args.device, graphs=graphs)
    runs: dict[bool, list] = {False: [], True: []}
    for graphs in (False, True, False, True):
        wp.synchronize_device(args.device)
        started = time.perf_counter()
        result = estimate(targets, device=args.device, graphs=graphs)
        wp.synchronize_device(args.device)
        runs[graphs].append((time.perf_counter() - started, result))
    same = lambda a, b: all(np.array_equal(getattr(a.params, n), getattr(b.params, n)) for n in PARAMETERS)
    print(f"\n{data.light_count} lights {data.width}x{data.height}, {wp.get_device(args.device).name}\n")
    print("| estimation | seconds (2 runs) | Gaussians/light | PSNR mean (dB) |")
    print("|---|---|---|---|")
    for graphs, label in ((False, "eager launches"), (True, "captured graph replayed")):
        (first, result), (second, _) = runs[graphs]
        print(f"| {label} | {first:.2f}, {second:.2f} | {result.counts.mean():.2f} | {result.psnr.mean():.2f} |")
    print(f"\ntwo eager runs the same: {same(runs[False][0][1], runs[False][1][1])}; eager and graph the same: "
          f"{same(runs[False][0][1], runs[True][0][1])}")


if __name__ == "__main__":
    main()
