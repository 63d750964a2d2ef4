"""Sweep Adam's learning rates on a recovery task; the source of the defaults in AdamSettings.

Task: per trial, three Gaussians (sigma 2-20 rpx, random anisotropy and rotation, amplitude
0.6-1.2) in a 240 x 135 image; the fit starts with every mean 4 rpx off, sigma and amplitude
30% off, theta 0.25 rad off, and minimises the log-L1 fit loss. All trials of one setting run as one
batch. A trial has converged when every mean is within 0.5 rpx, every sigma and amplitude within 5%
and every orientation of an anisotropic Gaussian within 0.05 rad.

    python benchmarks/tune_adam.py [--device cuda:0] [--trials 64] [--iterations 1000]

Prints, per setting, the share of trials within the tolerances at iterations 100/200/400/last and
the median iteration at which a trial first got there; writes $OUT/tune_adam.json when $OUT is set.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.kernels import losses
from warp_highlights.kernels.optim import GaussianAdam
from warp_highlights.kernels.raster import Rasterizer
from warp_highlights.model.config import AdamSettings, rpx_to_normalized
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams

HEIGHT, WIDTH = 135, 240


def trials(count: int, seed: int = 0) -> tuple[GaussianParams, GaussianParams]:
    """(truth, start) for ``count`` three-Gaussian problems."""
    rng = np.random.default_rng(seed)
    truth = GaussianParams.empty(count, 3)
    truth.active[:] = True
    truth.amplitude[:] = rng.uniform(0.6, 1.2, (count, 3))
    truth.mean[:] = rng.uniform([0.3, 0.25], [WIDTH / HEIGHT - 0.3, 0.75], (count, 3, 2))
    truth.sigma[:] = rpx_to_normalized(1) * rng.uniform(2, 20, (count, 3, 1)) * rng.uniform(0.4, 1.0, (count, 3, 2))
    truth.theta[:] = rng.uniform(0, np.pi, (count, 3))
    start = truth.copy()
    angle = rng.uniform(0, 2 * np.pi, (count, 3))
    start.mean += rpx_to_normalized(4) * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    start.sigma *= rng.choice([0.7, 1.3], (count, 3, 2))
    start.amplitude *= rng.choice([0.7, 1.3], (count, 3))
    start.theta += rng.choice([-0.25, 0.25], (count, 3))
    return truth, start


def converged(got: GaussianParams, truth: GaussianParams) -> np.ndarray:
    """(B,) whether every Gaussian of a trial is recovered within the tolerances of the docstring."""
    mean_ok = np.linalg.norm(got.mean - truth.mean, axis=-1) < rpx_to_normalized(0.5)
    sigma_ok = np.all(np.abs(np.abs(got.sigma) / truth.sigma - 1) < 0.05, axis=-1)
    amplitude_ok = np.abs(np.abs(got.amplitude) / truth.amplitude - 1) < 0.05
    anisotropic = np.abs(truth.sigma[..., 0] / truth.sigma[..., 1] - 1) > 0.2
    delta = (got.theta - truth.theta + np.pi / 2) % np.pi - np.pi / 2
    theta_ok = ~anisotropic | (np.abs(delta) < 0.05)
    return np.all(mean_ok & sigma_ok & amplitude_ok & theta_ok, axis=1)


def run_setting(settings: AdamSettings, truth, start, device, iterations: int, checkpoints: list[int],
                check_every: int = 20) -> tuple[np.ndarray, dict]:
    """Iteration at which each trial first converged (inf when never), and the share converged at each checkpoint."""
    count = truth.problem_count
    raster = Rasterizer(HEIGHT, WIDTH, device=device)
    target = raster.render(GaussianBatch.from_numpy(truth, device=device, requires_grad=False))
    fit = losses.LogL1Loss(target, device=device)
    batch = GaussianBatch.from_numpy(start, device=device)
    adam = GaussianAdam(batch, settings)
    image = raster.new_image(count)
    loss = wp.zeros(count, dtype=float, device=device, requires_grad=True)
    ones = wp.ones(count, dtype=float, device=device)
    first = np.full(count, np.inf)
    shares = {}
    for iteration in range(1, iterations + 1):
        loss.zero_()
        tape = wp.Tape()
        with tape:
            fit(raster.render(batch, out=image), out=loss)
        tape.backward(grads={loss: ones})
        adam.step()
        tape.zero()
        if iteration % check_every == 0:
            done = converged(batch.numpy(), truth)
            first[done & np.isinf(first)] = iteration
        if iteration in checkpoints:
            shares[iteration] = float(np.mean(converged(batch.numpy(), truth)))
    return first, shares


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--trials", type=int, default=64)
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--lengths", default="0.1,0.25,0.5,1.0", help="lr_mean_rpx = lr_sigma_rpx values")
    parser.add_argument("--amplitudes", default="0.01,0.02,0.05")
    parser.add_argument("--thetas", default="0.01,0.02,0.05")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    truth, start = trials(args.trials)
    checkpoints = [c for c in (100, 200, 400) if c < args.iterations] + [args.iterations]
    rows = []
    grid = itertools.product(*(map(float, text.split(",")) for text in (args.lengths, args.amplitudes, args.thetas)))
    for length, amplitude, theta in grid:
        settings = AdamSettings(lr_amplitude=amplitude, lr_mean_rpx=length, lr_sigma_rpx=length, lr_theta=theta)
        first, shares = run_setting(settings, truth, start, device, args.iterations, checkpoints)
        row = {"lr_length_rpx": length, "lr_amplitude": amplitude, "lr_theta": theta}
        row.update({f"converged_{c}": shares[c] for c in checkpoints})
        row["median_iterations"] = float(np.median(first))
        rows.append(row)
        print(f"  length {length} amplitude {amplitude} theta {theta}: " + ", ".join(f"{row[f'converged_{c}']:.2f}@{c}"
                                                                                     for c in checkpoints), flush=True)
    print(f"\ntune_adam on {device} ({device.name}): {args.trials} trials, {WIDTH}x{HEIGHT}")
    print("| lr mean/sigma (rpx) | lr amplitude | lr theta | " + " | ".join(f"converged @{c}" for c in checkpoints)
          + " | median iterations |")
    print("|" + "---|" * (len(checkpoints) + 4))
    for row in sorted(rows, key=lambda r: (-r[f"converged_{args.iterations}"], r["median_iterations"])):
        cells = " | ".join(f"{row[f'converged_{c}']:.2f}" for c in checkpoints)
        print(f"| {row['lr_length_rpx']} | {row['lr_amplitude']} | {row['lr_theta']} | {cells} | "
              f"{row['median_iterations']:.0f} |")
    if os.environ.get("OUT"):
        path = Path(os.environ["OUT"]) / "tune_adam.json"
        path.write_text(json.dumps({"device": str(device), "trials": args.trials, "rows": rows}, indent=2))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
