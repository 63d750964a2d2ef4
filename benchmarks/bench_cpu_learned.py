"""The learned residual on the CPU: NumPy training and decoding (``residual.cpu_training``) against Warp's CPU
kernels (``kernels.neural``), and the images learned alone at held-out lights.

    python benchmarks/bench_cpu_learned.py                        # speed, then the dome and the statue, 180 s each
    python benchmarks/bench_cpu_learned.py --cases synth --seconds 60 --batches 2048,8192

Speed: (light, pixel) samples a second of a few seconds of training on dome-sized targets (49 lights of 160 x
160) by ``train_decoder_cpu`` and by ``kernels.neural_training.train_decoder`` on Warp's CPU device (its kernels
compiled first), and milliseconds to decode one 480 x 270 image (``CpuDecoder``, ``CpuQueryDecoder``,
``decode_cpu``: best and median of 9).
Quality: the captured images learned alone (NeuralRTI: the residual is the image, no Gaussians), as
``fit --residual learned`` learns them (``residual.learned.learn_residual``, its ``train_decoder`` the NumPy
one), the epochs those samples a second fit in ``--seconds`` (``--seconds`` the limit too), scored in
8-bit sRGB at the held-out lights: the dome sample at 160 x 160 at its Test lights, the statue at 192 x 181
with every 5th light held out (``bench_quality.load_case``). The load average is printed beside each figure:
the machine's other work slows every figure down.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import SIZES, load_case  # noqa: E402

from warp_highlights.kernels import neural, neural_training  # noqa: E402
from warp_highlights.model.config import LEARNED_BATCH_CPU, ResidualSettings  # noqa: E402
from warp_highlights.model.threads import NUMPY_THREADS  # noqa: E402
from warp_highlights.quality.metrics import srgb_scores  # noqa: E402
from warp_highlights.relight.evaluation import resize_stack  # noqa: E402
from warp_highlights.residual import learned as learned_module  # noqa: E402
from warp_highlights.residual.cpu_training import (  # noqa: E402
    BATCH_CPU,
    CpuDecoder,
    CpuQueryDecoder,
    decode_cpu,
    train_decoder_cpu,
)
from warp_highlights.residual.decode import learned_images  # noqa: E402

REFERENCES = {"synth": "low-rank field (CPU default) 41.95 dB; Warp-CPU learned alone, 120 s: 45.8 dB",
              "statue": "low-rank field (CPU default) 33.01 dB"}
GOALS = {"synth": 44.0, "statue": 33.01}


def load() -> str:
    """The 1-minute load average and the cores, as text."""
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def dome_problem(seed: int = 0):
    """Dome-sized random targets: (49, 160 * 160, 3) display units at 49 upper-hemisphere lights."""
    rng = np.random.default_rng(seed)
    lights = rng.normal(size=(49, 3))
    lights[:, 2] = np.abs(lights[:, 2])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    return rng.uniform(0.0, 1.0, (49, 160 * 160, 3)).astype(np.float32), lights.astype(np.float32)


def training_rate(train, targets, lights, seconds: float, batch: int) -> float:
    """Samples a second of ``train`` from its second epoch to the end of the epoch after ``seconds``."""
    stamps = []

    def log(message: str) -> None:  # "... (lr x, 12.3 s)" or "... (12.3 s)": seconds since the first step
        stamps.append(float(message.rsplit("(", 1)[1].rsplit(", ", 1)[-1].split()[0]))

    train(targets, lights, epochs=1000, batch=batch, seconds=seconds, log=log)
    if len(stamps) < 2:
        return float("nan")
    return (len(stamps) - 1) * targets.shape[0] * targets.shape[1] / (stamps[-1] - stamps[0])


def speed(batches: list[int], seconds: float) -> tuple[dict, list[str]]:
    """Training samples a second (NumPy at each batch, Warp at its CPU batch) and decode ms for 480 x 270."""
    targets, lights = dome_problem()
    rows, rates = [], {}
    started = time.perf_counter()
    warp_cpu = lambda t, l, **k: neural_training.train_decoder(t, l, device="cpu", **k)  # noqa: E731
    warp_cpu(targets[:2, :128], lights[:2], epochs=1, batch=64)  # compile
    # Warp's CPU kernels run one thread: 6 of the lights (an epoch in seconds), every pixel (Adam steps them all)
    rate = training_rate(warp_cpu, targets[:6], lights[:6], seconds, LEARNED_BATCH_CPU)
    rows.append(f"| train, kernels.neural_training.train_decoder (Warp, CPU), batch {LEARNED_BATCH_CPU} | "
                f"{rate / 1e3:.1f} k samples/s | {load()} |")
    for batch in batches:
        rates[batch] = training_rate(train_decoder_cpu, targets, lights, seconds, batch)
        rows.append(f"| train, train_decoder_cpu, batch {batch} | {rates[batch] / 1e3:.1f} k samples/s "
                    f"({rates[batch] / rate:.0f}x) | {load()} |")
    model = neural.initial_model(targets[:, :1000])
    codes = np.random.default_rng(1).normal(size=(480 * 270, 9)).astype(np.float32)
    decoder = CpuDecoder(codes, model.weights)
    query = CpuQueryDecoder(codes, model.weights, 1.0)
    half = np.empty((1, len(codes), 3), np.float16)
    for label, decode in (("CpuDecoder.decode (code part kept), float32 display units",
                           lambda: decoder.decode(lights[:1])),
                          ("CpuQueryDecoder.decode (the relighter's), float16 field units",
                           lambda: query.decode(lights[:1], half)),
                          ("decode_cpu (code part computed too)", lambda: decode_cpu(codes, model.weights,
                                                                                      lights[:1]))):
        times = []
        for _ in range(9):
            t = time.perf_counter()
            decode()
            times.append(time.perf_counter() - t)
        rows.append(f"| {label}, one 480x270 image | {1e3 * min(times):.1f} ms (median "
                    f"{1e3 * np.median(times):.1f}) | {load()} |")
    rows.append(f"| (speed section: {time.perf_counter() - started:.0f} s) | | |")
    return rates, rows


def learn_alone(name: str, seconds: float, batch: int, rate: float, epochs: int | None) -> dict:
    """The case's images learned alone, scored at its held-out lights (8-bit sRGB PSNR, SSIM)."""
    dataset = load_case(name, "cpu", "cpu")
    width, height = SIZES[name][0]
    images = resize_stack(dataset.images, width, height).astype(np.float32)
    truth = resize_stack(dataset.heldout.images, width, height)
    if images.ndim == 3:
        images, truth = images[..., None].repeat(3, axis=3), truth[..., None].repeat(3, axis=3)
    samples = images.shape[0] * width * height
    if epochs is None:  # the epochs the measured rate fits in the time (the schedule then ends on its final rate)
        epochs = max(1, int(0.95 * seconds * rate / samples))
    settings = replace(ResidualSettings(), kind="learned", learned_seconds=seconds, learned_epochs=epochs,
                       learned_batch=batch)
    started = time.perf_counter()
    residual, history = learned_module.learn_residual(images, np.zeros(images.shape[:3], np.float32), None,
                                                      dataset.lights.directions, factor=1.0, settings=settings,
                                                      device="cpu")
    train_seconds = time.perf_counter() - started
    decoded = np.clip(learned_images(residual.learned, dataset.heldout.lights.directions), 0.0, None)
    psnr, ssim = srgb_scores(decoded.astype(np.float32), truth)
    return {"case": name, "lights": len(images), "heldout": len(truth), "size": f"{width}x{height}", "batch": batch,
            "epochs": f"{len(history)}/{epochs}", "seconds": train_seconds, "psnr": float(psnr.mean()),
            "worst": float(psnr.min()), "ssim": float(ssim.mean()), "mse": history[-1], "load": load()}


def _route_training() -> None:
    """``learn_residual`` trains with ``train_decoder_cpu`` (the NumPy trainer; no device argument)."""
    def train(targets, lights, *, device=None, **kwargs):
        return train_decoder_cpu(targets, lights, **kwargs)

    learned_module.train_decoder = train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue")
    parser.add_argument("--seconds", type=float, default=180.0, help="training time per learned model")
    parser.add_argument("--batches", default=f"{BATCH_CPU}", help="NumPy batch sizes to learn the cases with")
    parser.add_argument("--speed-batches", default="2048,4096,8192,16384", help="NumPy batch sizes to time too")
    parser.add_argument("--epochs", type=int, default=None,
                        help="the schedule's epochs (default: those the measured rate fits in --seconds)")
    parser.add_argument("--speed-seconds", type=float, default=4.0, help="training time of each speed figure")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed figures (rate: --rate)")
    parser.add_argument("--rate", type=float, default=None, help="samples/s to fit the epochs to with --no-speed")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    batches = [int(b) for b in args.batches.split(",")]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    header = (f"{platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
              f"({NUMPY_THREADS} NumPy threads), {datetime.datetime.now():%Y-%m-%d %H:%M}, commit {commit}, "
              f"numpy {np.__version__}")
    print(header, flush=True)
    timed = sorted(set(batches) | {int(b) for b in args.speed_batches.split(",") if b.strip()})
    rates, rows = ({b: args.rate for b in batches}, []) if args.no_speed else speed(timed, args.speed_seconds)
    if rows:
        print("\n| what | figure | load |\n|---|---|---|\n" + "\n".join(rows), flush=True)
    _route_training()
    results = []
    for name in [c.strip() for c in args.cases.split(",") if c.strip()]:
        for batch in batches:
            result = learn_alone(name, args.seconds, batch, rates[batch], args.epochs)
            results.append(result)
            print(f"  {result}", file=sys.stderr, flush=True)
    if results:
        print(f"\nimages learned alone (NumPy, {NUMPY_THREADS} threads), at most {args.seconds:.0f} s each; "
              f"8-bit sRGB PSNR at the held-out lights\n")
        print("| case | batch | epochs | train (s) | PSNR mean (dB) | worst | SSIM | goal | reference | load |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in results:
            print(f"| {r['case']} ({r['lights']} lights, {r['size']}, {r['heldout']} held out) | {r['batch']} | "
                  f"{r['epochs']} | {r['seconds']:.0f} | {r['psnr']:.2f} | {r['worst']:.2f} | {r['ssim']:.4f} | "
                  f">= {GOALS[r['case']]:.2f} | {REFERENCES[r['case']]} | {r['load']} |")


if __name__ == "__main__":
    main()
