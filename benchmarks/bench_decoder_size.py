"""The learned residual's decoder against smaller ones distilled from it (``residual.distil``): quality, size and
CPU decoding speed, on the two samples.

    python benchmarks/bench_decoder_size.py                   # the dome and the statue; about 30 minutes on 2 cores
    python benchmarks/bench_decoder_size.py --cases synth --teacher-seconds 60 --students "24,24 16"
    python benchmarks/bench_decoder_size.py --cases statue --students 24,24 --epochs 40 --fixed-codes

For each case the captured images are learned alone (NeuralRTI: the residual is the image) as
``fit --residual learned`` learns them on the CPU (``--teacher-seconds``), then each student decoder is
distilled from that teacher for ``--epochs`` (``DistilSettings``; no time limit unless ``--seconds``, so that the
figures do not depend on the machine's load), and every decoder is scored in 8-bit
sRGB PSNR / SSIM at the held-out lights (the dome sample at 160 x 160 at its Test lights, the statue at
192 x 181 with every 5th light held out: ``bench_quality.load_case``), and against the teacher's images
at the captured lights and between them (``distil.agreement``). Size: the decoder's weights (float32)
and multiply-adds per pixel; speed: milliseconds to decode one 480 x 270 image on this machine's CPU
(``CpuDecoder``, best and median of 9). Each student's per-pixel codes (9 numbers a pixel, float16 in the field
file) start as the teacher's and learn along; ``--fixed-codes`` distils each student once more with the teacher's
codes kept.
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

from bench_cpu_learned import _route_training, load  # noqa: E402
from bench_quality import SIZES, load_case  # noqa: E402

from warp_highlights.model.config import DistilSettings, ResidualSettings  # noqa: E402
from warp_highlights.model.residual import decoder_layer_shapes  # noqa: E402
from warp_highlights.model.threads import NUMPY_THREADS  # noqa: E402
from warp_highlights.model.triangulation import SphericalTriangulation  # noqa: E402
from warp_highlights.quality.metrics import srgb_scores  # noqa: E402
from warp_highlights.relight.evaluation import resize_stack  # noqa: E402
from warp_highlights.residual import learned as learned_module  # noqa: E402
from warp_highlights.residual.cpu_training import CpuDecoder  # noqa: E402
from warp_highlights.residual.decode import learned_images  # noqa: E402
from warp_highlights.residual.distil import decoder_multiply_adds, distil_decoder, parse_hidden  # noqa: E402


def decode_ms(weights, repeats: int = 9) -> tuple[float, float]:
    """(best, median) milliseconds to decode one 480 x 270 image of random codes through ``weights``."""
    codes = np.random.default_rng(0).normal(size=(480 * 270, 9)).astype(np.float32)
    decoder = CpuDecoder(codes, weights)
    direction = np.array([[0.3, 0.4, 0.866]], np.float32)
    decoder.decode(direction)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        decoder.decode(direction)
        times.append(1000 * (time.perf_counter() - started))
    return float(np.min(times)), float(np.median(times))


def scored(learned, dataset, truth) -> tuple[float, float, float]:
    """(mean PSNR, worst PSNR, mean SSIM) of the decoder's images at the held-out lights."""
    decoded = np.clip(learned_images(learned, dataset.heldout.lights.directions), 0.0, None)
    psnr, ssim = srgb_scores(decoded.astype(np.float32), truth)
    return float(psnr.mean()), float(psnr.min()), float(ssim.mean())


def run_case(name: str, teacher_seconds: float, students: list[tuple[int, ...]], seconds: float,
             epochs: int, fixed_codes: bool) -> list[dict]:
    dataset = load_case(name, "cpu", "cpu")
    width, height = SIZES[name][0]
    images = resize_stack(dataset.images, width, height).astype(np.float32)
    truth = resize_stack(dataset.heldout.images, width, height)
    directions = dataset.lights.directions
    settings = replace(ResidualSettings(), kind="learned", learned_seconds=teacher_seconds)
    started = time.perf_counter()
    residual, history = learned_module.learn_residual(images, np.zeros(images.shape[:3], np.float32), None,
                                                      directions, factor=1.0, settings=settings, device="cpu")
    teacher = residual.learned
    rows = [{"case": name, "hidden": teacher.hidden, "codes": "its own", "train": time.perf_counter() - started,
             "epochs": f"{len(history)}", "scores": scored(teacher, dataset, truth), "captured": None,
             "between": None, "load": load()}]
    print(f"  {rows[-1]}", file=sys.stderr, flush=True)
    faces = SphericalTriangulation(directions).faces
    for hidden in students:
        for learn_codes in (True, False) if fixed_codes else (True,):
            student, report = distil_decoder(teacher, hidden, directions, faces,
                                             settings=DistilSettings(hidden=hidden, seconds=seconds, epochs=epochs,
                                                                     learn_codes=learn_codes))
            rows.append({"case": name, "hidden": hidden, "codes": "learning" if learn_codes else "the teacher's",
                         "train": report.seconds, "epochs": f"{report.epochs:.1f}",
                         "scores": scored(student, dataset, truth), "captured": report.captured_psnr_db,
                         "between": report.between_psnr_db, "load": load()})
            print(f"  {rows[-1]}", file=sys.stderr, flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue")
    parser.add_argument("--teacher-seconds", type=float, default=180.0, help="training time of the fitted decoder")
    parser.add_argument("--seconds", type=float, default=0.0,
                        help="distillation time at most each (default 0: --epochs alone, the same on any machine)")
    parser.add_argument("--epochs", type=int, default=DistilSettings().epochs, help="distillation epochs each")
    parser.add_argument("--fixed-codes", action="store_true",
                        help="each student once more with the teacher's codes kept (DistilSettings.learn_codes off)")
    parser.add_argument("--students", default="48,48 32,32 24,24 16,16 32",
                        help="the students' hidden widths, space-separated (e.g. '24,24 16')")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    students = [parse_hidden(text) for text in args.students.split()]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    print(f"{platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
          f"({NUMPY_THREADS} NumPy threads), {datetime.datetime.now():%Y-%m-%d %H:%M}, commit {commit}, "
          f"numpy {np.__version__}", flush=True)
    _route_training()
    speeds = {}
    for hidden in [(48, 48, 48), *students]:
        rng = np.random.default_rng(0)
        weights = [rng.normal(size=shape).astype(np.float32) * 0.2 for shape in decoder_layer_shapes(hidden)]
        speeds[hidden] = decode_ms(weights)
    rows = [row for name in args.cases.split(",") if name.strip()
            for row in run_case(name.strip(), args.teacher_seconds, students, args.seconds, args.epochs,
                                args.fixed_codes)]
    limit = f"{args.epochs} epochs" + (f" or {args.seconds:.0f} s" if args.seconds else "")
    print(f"\nthe images learned alone ({args.teacher_seconds:.0f} s), then each student distilled for "
          f"{limit}; 8-bit sRGB PSNR / SSIM at the held-out lights; agreement with the "
          f"fitted decoder at the captured lights and between them; CPU decode of one 480x270 image "
          f"({NUMPY_THREADS} threads)\n")
    print("| case | hidden layers | codes | weights | multiply-adds / pixel | train (s) | epochs | PSNR (dB) | worst "
          "| SSIM | vs fitted decoder: captured / between (dB) | decode 480x270 best / median (ms) | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        hidden = r["hidden"]
        count = sum(a * b for a, b in decoder_layer_shapes(hidden))
        psnr, worst, ssim = r["scores"]
        versus = "the fitted decoder" if r["between"] is None else f"{r['captured']:.2f} / {r['between']:.2f}"
        best, median = speeds[tuple(hidden)]
        print(f"| {r['case']} | {'-'.join(map(str, hidden))} | {r['codes']} | {count} | "
              f"{decoder_multiply_adds(hidden)} | "
              f"{r['train']:.0f} | {r['epochs']} | {psnr:.2f} | {worst:.2f} | {ssim:.4f} | {versus} | "
              f"{best:.1f} / {median:.1f} | {r['load']} |")


if __name__ == "__main__":
    main()
