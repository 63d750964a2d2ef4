"""Time the Gaussian rasterizer, the fit loss, the backward pass and one Adam step.

Cases are problems x Gaussians at 480 x 270 with realistic highlight sizes: each problem has a few
highlight clusters of Gaussians with sigma 2-20 rpx, random anisotropy and rotation, fitted against
the image of a perturbed copy (so every gradient is non-trivial).

    python benchmarks/bench_raster.py [--device cuda:0] [--cases 1x25,1x50,250x50,1488x25] [--repeat 20]

Columns (milliseconds, best of --repeat runs after a warm-up, synchronised):
  forward      rasterize (prepare, bin tiles, draw) + fit loss
  fwd+bwd      the same on a wp.Tape + tape.backward() + tape.zero()
  backward     fwd+bwd - forward
  adam         one GaussianAdam.step()
  step         fwd+bwd + adam: one fitting iteration
  graph step   the same captured once in a CUDA graph and replayed (CUDA only)
Writes the table and the machine description to $OUT/bench_raster.json when $OUT is set.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.kernels import losses, optim
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.model.config import RasterSettings, rpx_to_normalized
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

HEIGHT, WIDTH = 270, 480


def highlight_sets(problems: int, gaussians: int, seed: int) -> GaussianParams:
    """Clustered Gaussians, sigma 2-20 rpx, like the highlights of a glossy object."""
    rng = np.random.default_rng(seed)
    params = GaussianParams.empty(problems, gaussians)
    clusters = rng.integers(1, 5, size=problems)
    centres = rng.uniform([0.25, 0.2], [WIDTH / HEIGHT - 0.25, 0.8], size=(problems, 4, 2))
    which = rng.integers(0, 4, size=(problems, gaussians)) % clusters[:, None]
    centre = np.take_along_axis(centres, which[..., None].repeat(2, axis=-1), axis=1)
    params.mean[:] = centre + rng.normal(0, rpx_to_normalized(25), size=(problems, gaussians, 2))
    params.sigma[:] = (rpx_to_normalized(1) * rng.uniform(2, 20, size=(problems, gaussians, 1))
                       * rng.uniform(0.5, 1.0, size=(problems, gaussians, 2)))
    params.theta[:] = rng.uniform(0, np.pi, size=(problems, gaussians))
    params.amplitude[:] = rng.uniform(0.5, 1.2, size=(problems, gaussians))
    params.active[:] = True
    return params


def timed(function, repeat: int, device) -> float:
    """Best wall time of ``function`` over ``repeat`` calls, in ms, synchronising the device around each.

    The best, not the median: the shared machines these run on add load spikes of their own.
    """
    function()
    wp.synchronize_device(device)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - start) * 1e3)
    return min(times)


def bench_case(problems: int, gaussians: int, device, repeat: int, settings: RasterSettings,
               lanes: int | None = None) -> dict:
    truth = highlight_sets(problems, gaussians, seed=problems * 1000 + gaussians)
    start = truth.copy()
    rng = np.random.default_rng(7)
    start.mean += rng.normal(0, rpx_to_normalized(3), start.mean.shape)
    start.sigma *= rng.uniform(0.8, 1.25, start.sigma.shape)
    raster = Rasterizer(HEIGHT, WIDTH, settings=settings, device=device, backward_lanes=lanes)
    target = raster.render(GaussianBatch.from_numpy(truth, device=device, requires_grad=False))
    batch = GaussianBatch.from_numpy(start, device=device)
    fit = losses.LogL1Loss(target, device=device)
    image = raster.new_image(problems)
    loss = wp.zeros(problems, dtype=float, device=device, requires_grad=True)
    adam = optim.GaussianAdam(batch)

    def forward():
        loss.zero_()
        fit(raster.render(batch, out=image), out=loss)

    def forward_backward():
        tape = wp.Tape()
        with tape:
            forward()
        tape.backward(grads={loss: ones})
        tape.zero()

    ones = wp.ones(problems, dtype=float, device=device)
    row = {"case": f"{problems}x{gaussians}", "problems": problems, "gaussians": gaussians}
    row["forward_ms"] = timed(forward, repeat, device)
    row["fwd_bwd_ms"] = timed(forward_backward, repeat, device)
    row["backward_ms"] = row["fwd_bwd_ms"] - row["forward_ms"]
    snapshot = batch.numpy()
    row["adam_ms"] = timed(adam.step, repeat, device)
    batch.assign(snapshot)
    adam.reset()

    def step():
        forward_backward()
        adam.step()

    row["step_ms"] = timed(step, repeat, device)
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as capture:
            step()
        row["graph_step_ms"] = timed(lambda: wp.capture_launch(capture.graph), repeat, device)
    if wp.get_device(device).is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        step()
        kernels = {}
        for result in wp.timing_end():
            kernels[result.name] = kernels.get(result.name, 0.0) + result.elapsed
        row["kernel_ms"] = dict(sorted(kernels.items(), key=lambda item: -item[1]))
    raster.render(batch, out=image)
    row.update({f"tiles_{k}": v for k, v in raster.tile_statistics().items()})
    row["final_loss_mean"] = float(loss.numpy().mean())
    return row


def raster_lanes(device) -> int:
    """The backward lane count the rasterizer picks by default on ``device``."""
    return Rasterizer(1, 1, device=device).backward_lanes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default device)")
    parser.add_argument("--cases", default="1x25,1x50,250x50,1488x25", help="comma-separated problems x Gaussians")
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--tile-sizes", default="16", help="comma-separated culling tile sizes to compare")
    parser.add_argument("--lanes", default="auto",
                        help="comma-separated backward threads per Gaussian to compare (auto: 64 on CUDA, 1 on CPU)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING  # no greeting or module-load lines around the table
    wp.init()
    device = wp.get_device(args.device)
    rows = []
    lane_options = [None if text == "auto" else int(text) for text in args.lanes.split(",")]
    for tile_size, lanes in itertools.product([int(t) for t in args.tile_sizes.split(",")], lane_options):
        settings = RasterSettings(tile_size=tile_size)
        for case in args.cases.split(","):
            problems, gaussians = (int(v) for v in case.lower().split("x"))
            row = bench_case(problems, gaussians, device, args.repeat, settings, lanes)
            row["tile_size"] = tile_size
            row["lanes"] = lanes or raster_lanes(device)
            rows.append(row)
            print(f"  {row['case']:>8} tile {tile_size} lanes {row['lanes']}: fwd {row['forward_ms']:.2f} ms, fwd+bwd "
                  f"{row['fwd_bwd_ms']:.2f} ms", flush=True)
    machine = {"device": str(device), "device_name": device.name, "warp": wp.__version__,
               "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "image": f"{WIDTH}x{HEIGHT}"}
    columns = ["forward_ms", "fwd_bwd_ms", "backward_ms", "adam_ms", "step_ms", "graph_step_ms"]
    print(f"\nbench_raster on {device} ({device.name}), warp {wp.__version__}, {WIDTH}x{HEIGHT}, best of {args.repeat}")
    print(f"| case | tile | lanes | {' | '.join(c.removesuffix('_ms') + ' (ms)' for c in columns)} | bwd/fwd | "
          f"Gaussians per tile (mean/max) |")
    print("|" + "---|" * (len(columns) + 5))
    for row in rows:
        cells = [f"{row[c]:.2f}" if c in row else "-" for c in columns]
        ratio = row["backward_ms"] / row["forward_ms"]
        print(f"| {row['case']} | {row['tile_size']} | {row['lanes']} | {' | '.join(cells)} | {ratio:.2f} | "
              f"{row['tiles_mean_per_tile']:.2f}/{row['tiles_max_per_tile']} |")
    for row in rows:
        if "kernel_ms" in row and row is rows[-1]:
            print(f"kernel times of one step, {row['case']}: "
                  + ", ".join(f"{name} {ms:.2f} ms" for name, ms in row["kernel_ms"].items()))
    if os.environ.get("OUT"):
        path = Path(os.environ["OUT"]) / "bench_raster.json"
        path.write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
