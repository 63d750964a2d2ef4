"""The learned residual's training on one GPU: throughput, compile time on a fresh kernel cache, PSNR
reached, next to a PyTorch implementation of the same model and optimiser; and the whole ``fit``.

    python benchmarks/bench_learned_training.py                      # everything, CUDA device 0
    python benchmarks/bench_learned_training.py --parts kernel,torch --epochs 25,50

Parts (each a subprocess, so that each starts with its own Warp configuration and kernel cache):
- ``kernel``: the dome sample's images (``synthrti-object1-material5``, Dome/ at its own 320x320) learned
  alone (NeuralRTI: the targets are the images in display units) by ``kernels.neural_training``: on the
  tensor cores (``kernels.neural_tensor_cores``), with cuBLASDx tile products (``enable_mathdx_gemm``) and
  with Warp's own (``--tensor-cores``, ``--mathdx``): the first step on an empty kernel cache (compile and
  load), samples a second for one model and for two side by side, the decoder's first decode, and 8-bit
  sRGB PSNR at the 20 Test lights after ``--epochs`` epochs;
- ``tiles``: samples a second of each tile shape of ``--tiles`` (Warp's tile products) at batches of 65,536 and
  131,072, and the PSNR after ``--epochs`` epochs of the fastest at each batch;
- ``launches``: microseconds of each of the step's launches and of the whole step, for each tile shape of
  ``--tiles`` and each number of passes a block of ``--passes`` on the tensor cores;
- ``torch``: the same model, initial values, Adam, learning-rate schedule, batch and shuffled epochs in
  PyTorch (eager), samples a second and PSNR after the same epochs;
- ``fit``: ``warp-highlights fit`` with the defaults, timed as a command: the dome sample on an empty
  kernel cache (a fresh machine's first fit), again warm, and the statue (``realrti-item11``, every 5th
  light held out); each field's 8-bit sRGB PSNR at its held-out lights.
Prints a table last; writes $OUT/bench_learned_training.json when OUT is set.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = Path(os.environ.get("WARP_HIGHLIGHTS_DATA", ROOT.parent / "shared" / "data"))
DOME = DATA / "synthrti-object1-material5"
STATUE = DATA / "realrti-item11"


def dome_problem(size: int | None):
    """(targets (n, P, 3) display units, directions (n, 3), test directions, test images (m, H, W, 3), width,
    height) of the dome sample's images learned alone."""
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.relight.evaluation import resize_stack
    from warp_highlights.residual.opponent import encode_display

    dataset = ReflectanceField.load(DOME / "Dome", heldout=DOME / "Test", progress=False)
    width, height = (dataset.width, dataset.height) if size is None else (size, size)
    images = resize_stack(dataset.images, width, height).astype(np.float32)
    truth = resize_stack(dataset.heldout.images, width, height).astype(np.float32)
    targets = encode_display(images).reshape(len(images), width * height, 3).astype(np.float32)
    return targets, dataset.lights.directions, dataset.heldout.lights.directions, truth, width, height


def test_psnr(codes: np.ndarray, weights, directions: np.ndarray, truth: np.ndarray) -> float:
    """Mean 8-bit sRGB PSNR of a decoder (codes (P, 9)) at the test directions, as the relighter clamps."""
    from warp_highlights.model.residual import NeuralResidual
    from warp_highlights.quality.metrics import srgb_psnr
    from warp_highlights.residual.decode import learned_images

    m, height, width, _ = truth.shape
    learned = NeuralResidual(codes.reshape(height, width, -1).astype(np.float16),
                             tuple(np.asarray(w, np.float32) for w in weights), 1.0, len(directions))
    predicted = np.maximum(learned_images(learned, directions), 0.0)
    return float(np.mean([srgb_psnr(p, t) for p, t in zip(predicted, truth)]))


def part_kernel(args) -> dict:
    import warp as wp

    wp.init()
    from warp_highlights.kernels import neural, neural_training

    # this run's choice, in place of the project's (``LEARNED_MATHDX``), before any kernel is built
    neural_training._MODULE_OPTIONS["enable_mathdx_gemm"] = bool(args.mathdx)
    for module in (neural, neural_training):
        wp.set_module_options({"enable_mathdx_gemm": bool(args.mathdx)}, module=module)

    device = wp.get_device(args.device)
    targets, directions, test_directions, truth, width, height = dome_problem(args.size)
    n, pixels, _ = targets.shape
    tensor_cores = bool(args.tensor_cores)
    result = {"mathdx": bool(args.mathdx), "tensor_cores": tensor_cores, "size": [width, height], "lights": n,
              "batch": args.batch, "device": device.name}
    used = np.arange(n)
    model = neural.initial_model(targets, seed=0)
    t = time.perf_counter()
    trainer = neural_training.DecoderTrainer(targets[None], directions, used, [model], args.batch, 100, device=device,
                                             tensor_cores=tensor_cores)
    trainer.steps(1)
    wp.synchronize_device(device)
    result["first_step_seconds"] = time.perf_counter() - t  # compile + load on an empty cache
    for count in (1, 2):
        trainer = neural_training.DecoderTrainer(np.repeat(targets[None], count, axis=0), directions, used,
                                                 [model] * count, args.batch, 100, device=device,
                                                 tensor_cores=tensor_cores)
        trainer.steps(trainer.steps_per_epoch)  # captures the graph
        trainer.losses()
        t = time.perf_counter()
        steps = 3 * trainer.steps_per_epoch
        trainer.steps(steps)
        trainer.losses()
        seconds = time.perf_counter() - t
        result[f"samples_per_second_{count}"] = steps * trainer.batch * count / seconds
    t = time.perf_counter()
    decoder = neural.QueryDecoder(model.codes, model.weights, 1.0, device=device)
    out = wp.empty((1, pixels, 3), dtype=wp.float16, device=device)
    decoder.decode(wp.array(directions[:1].astype(np.float32), dtype=wp.vec3, device=device), out)
    wp.synchronize_device(device)
    result["first_decode_seconds"] = time.perf_counter() - t
    for epochs in args.epoch_list:
        t = time.perf_counter()
        models, history = neural_training.train_decoders(targets[None], directions, device=device, epochs=epochs,
                                                         batch=args.batch, tensor_cores=tensor_cores)
        result[f"train_seconds_{epochs}"] = time.perf_counter() - t
        result[f"psnr_{epochs}"] = test_psnr(models[0].codes, models[0].weights, test_directions, truth)
        result[f"final_mse_{epochs}"] = float(history[-1, 0])
    return result


def part_tiles(args) -> dict:
    """Samples a second of tile shapes (samples per tile, tiles per block, threads) and batches; the PSNR
    after ``--epochs`` epochs of the fastest at each batch."""
    import warp as wp

    wp.init()
    from warp_highlights.kernels import neural, neural_training

    device = wp.get_device(args.device)
    targets, directions, test_directions, truth, width, height = dome_problem(args.size)
    n = len(targets)
    model = neural.initial_model(targets, seed=0)
    result = {"size": [width, height], "lights": n}
    for batch in (1 << 16, 1 << 17):
        best = None
        for tile in args.tile_list:
            trainer = neural_training.DecoderTrainer(targets[None], directions, np.arange(n), [model], batch, 100,
                                                     device=device, tile=tile, tensor_cores=False)
            t = time.perf_counter()
            trainer.steps(trainer.steps_per_epoch)
            trainer.losses()
            compile_seconds = time.perf_counter() - t
            t = time.perf_counter()
            steps = 3 * trainer.steps_per_epoch
            trainer.steps(steps)
            trainer.losses()
            rate = steps * trainer.batch / (time.perf_counter() - t)
            result[f"{tile} batch {batch}"] = {"samples_per_second": rate, "first_epoch_seconds": compile_seconds}
            print(f"tiles {tile} batch {batch}: {rate / 1e6:.1f} M/s (first epoch {compile_seconds:.1f} s)",
                  file=sys.stderr, flush=True)
            if best is None or rate > best[1]:
                best = (tile, rate)
        for epochs in args.epoch_list:
            t = time.perf_counter()
            trainer = neural_training.DecoderTrainer(targets[None], directions, np.arange(n), [model], batch, epochs,
                                                     device=device, tile=best[0], tensor_cores=False)
            trainer.steps(epochs * trainer.steps_per_epoch)
            trained = trainer.result()[0]
            result[f"best batch {batch} epochs {epochs}"] = {
                "tile": best[0], "psnr": test_psnr(trained.codes, trained.weights, test_directions, truth),
                "seconds": time.perf_counter() - t}
            row = result[f"best batch {batch} epochs {epochs}"]
            print(f"tiles best {best[0]} batch {batch}, {epochs} epochs: {row}", file=sys.stderr, flush=True)
    return result


def _launch_seconds(wp, device, launch) -> float:
    """Seconds of one ``launch()``: on CUDA from events around a graph of ``LAUNCH_REPEATS`` of them (so that
    the host's launch cost does not count), on the CPU from the clock."""
    if not device.is_cuda:
        launch()
        t = time.perf_counter()
        for _ in range(LAUNCH_REPEATS):
            launch()
        wp.synchronize_device(device)
        return (time.perf_counter() - t) / LAUNCH_REPEATS
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        for _ in range(LAUNCH_REPEATS):
            launch()
    wp.capture_launch(capture.graph)  # warm
    start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
    wp.record_event(start)
    wp.capture_launch(capture.graph)
    wp.record_event(end)
    wp.synchronize_event(end)
    return 1e-3 * wp.get_event_elapsed_time(start, end) / LAUNCH_REPEATS


def part_launches(args) -> dict:
    """Microseconds of each of the step's launches (each replayed ``LAUNCH_REPEATS`` times in one CUDA graph)
    and of the whole step, for each tile shape of ``--tiles`` (Warp's tile products) and each number of passes of
    ``--passes`` (tensor cores); one model, the dome sample, ``--batch``."""
    import warp as wp

    wp.init()
    from warp_highlights.kernels import neural, neural_training

    device = wp.get_device(args.device)
    targets, directions, _, _, width, height = dome_problem(args.size)
    n = len(targets)
    model = neural.initial_model(targets, seed=0)
    result = {"size": [width, height], "lights": n, "batch": args.batch, "repeats": LAUNCH_REPEATS}
    shapes = [(str(tile), {"tile": tile, "tensor_cores": False}) for tile in args.tile_list]
    shapes += [(f"tensor cores, {p} passes", {"tensor_cores": True, "tensor_passes": p}) for p in args.pass_list]
    for tile, options in shapes:
        try:
            trainer = neural_training.DecoderTrainer(targets[None], directions, np.arange(n), [model], args.batch,
                                                     100, device=device, **options)
            trainer.steps(trainer.steps_per_epoch)  # compiles, captures the step's graph
            trainer.losses()
            row = {name: 1e6 * _launch_seconds(wp, device, launch)
                   for name, launch in trainer.launches() + [("step", trainer.launch_step)]}
        except Exception as error:  # a shape the device cannot run (shared memory): reported, the others go on
            result[str(tile)] = {"error": f"{type(error).__name__}: {error}"}
            print(f"launches {tile}: {result[str(tile)]}", file=sys.stderr, flush=True)
            continue
        row["samples_per_second"] = trainer.batch / (row["step"] * 1e-6)
        if device.is_cuda:  # registers a thread decide how many blocks a multiprocessor runs
            row.update(wp.get_cuda_kernel_properties(trainer.kernel, device, block_dim=trainer.threads))
        result[str(tile)] = row
        print(f"launches {tile}: " + ", ".join(f"{k} {v:.1f}" for k, v in row.items()), file=sys.stderr, flush=True)
    return result


def part_torch(args) -> dict:
    import torch

    from warp_highlights.kernels import neural

    device = torch.device("cuda")
    targets, directions, test_directions, truth, width, height = dome_problem(args.size)
    n, pixels, _ = targets.shape
    model = neural.initial_model(targets, seed=0)
    result = {"torch": torch.__version__, "size": [width, height], "lights": n, "batch": args.batch,
              "device": torch.cuda.get_device_name(0)}

    def train(epochs: int, timed_epochs: int | None = None):
        codes = torch.nn.Parameter(torch.tensor(model.codes, device=device))
        weights = [torch.nn.Parameter(torch.tensor(w, device=device)) for w in model.weights]
        optimizer = torch.optim.Adam([codes, *weights], lr=3e-3, betas=(0.9, 0.999), eps=1e-8)
        table = torch.tensor(targets.reshape(-1, 3), device=device)
        lights = torch.tensor(np.asarray(directions, np.float32), device=device)
        total, batch = n * pixels, args.batch
        started = None
        for epoch in range(epochs):
            if timed_epochs is not None and epoch == 1:
                torch.cuda.synchronize()
                started = time.perf_counter()
            for group in optimizer.param_groups:
                group["lr"] = 3e-3 * (3e-4 / 3e-3) ** (epoch / max(epochs - 1, 1))
            order = torch.randperm(total, device=device)
            for start in range(0, total, batch):
                index = order[start:start + batch]
                light, pixel = index // pixels, index % pixels
                x = torch.cat([codes[pixel], lights[light]], dim=1)
                w0, b0, w1, b1, w2, b2, w3, b3 = weights
                h = torch.nn.functional.elu(x @ w0.T + b0.T)
                h = torch.nn.functional.elu(h @ w1.T + b1.T)
                h = torch.nn.functional.elu(h @ w2.T + b2.T)
                y = h @ w3.T + b3.T
                loss = ((y - table[index]) ** 2).sum(dim=1).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        torch.cuda.synchronize()
        rate = None if started is None else (epochs - 1) * total / (time.perf_counter() - started)
        return codes.detach().cpu().numpy(), [w.detach().cpu().numpy() for w in weights], rate

    _, _, rate = train(4, timed_epochs=3)
    result["samples_per_second_1"] = rate
    for epochs in args.epoch_list:
        t = time.perf_counter()
        codes, weights, _ = train(epochs)
        result[f"train_seconds_{epochs}"] = time.perf_counter() - t
        result[f"psnr_{epochs}"] = test_psnr(codes, weights, test_directions, truth)
    return result


def _fit(dataset: Path, out: Path, extra: list[str], cache: str | None) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    if cache:
        env["WARP_CACHE_PATH"] = cache
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "warp_highlights", "fit", str(dataset), "-o", str(out), "-q",
                           "--overwrite", *extra], env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t
    if done.returncode:
        return {"error": done.stderr[-2000:], "seconds": seconds}
    return {"seconds": seconds}


def _score(field_path: Path, dataset) -> dict:
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.relight.evaluation import resize_stack, srgb_scores
    from warp_highlights.relight.relighter import Relighter

    field = load_field(field_path)
    truth = resize_stack(dataset.heldout.images, field.width, field.height).astype(np.float32)
    relit = Relighter(field, device="cuda", scale=1.0 / field.exposure).relight(dataset.heldout.lights.directions)
    psnr, ssim = srgb_scores(relit.full, truth)
    report = field.report
    return {"psnr": float(psnr.mean()), "ssim": float(ssim.mean()), "moving": int(field.moving_mask.sum()),
            "stages": {k: round(v, 2) for k, v in report.get("seconds", {}).items()},
            "learned_check": report.get("residual", {}).get("learned_check")}


def part_fit(args) -> dict:
    from warp_highlights.io.dataset import ReflectanceField

    result = {}
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        dome = ReflectanceField.load(DOME / "Dome", heldout=DOME / "Test", progress=False)
        statue = ReflectanceField.load(STATUE, progress=False).split_every(5)
        runs = [("dome, empty kernel cache", DOME / "Dome", [], str(scratch / "cache"), dome),
                ("dome, warm", DOME / "Dome", [], None, dome),
                ("statue, warm", STATUE, ["--holdout-every", "5"], None, statue)]
        if not args.fit_cold:
            runs = runs[1:]
        for label, folder, extra, cache, dataset in runs:
            out = scratch / "field.whf"
            sets = [word for item in args.fit_set.split() for word in ("--set", item)]
            row = _fit(folder, out, extra + sets, cache)
            if "error" not in row:
                row.update(_score(out, dataset))
            result[label] = row
            print(f"fit {label}: {row}", file=sys.stderr, flush=True)
    return result


PARTS = {"kernel": part_kernel, "tiles": part_tiles, "launches": part_launches, "torch": part_torch, "fit": part_fit}
LAUNCH_REPEATS = 50
DEFAULT_TILES = "64,1,64;64,4,64;64,4,128;64,8,128;64,8,256;32,8,64"


def _child(args, part: str, mathdx: int | None = None, tensor_cores: int | None = None) -> dict:
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as cache:
        if part == "kernel" and not args.warm_cache:
            env["WARP_CACHE_PATH"] = cache  # an empty kernel cache: a fresh machine's compile
        command = [sys.executable, __file__, "--child", part, "--device", args.device, "--batch", str(args.batch),
                   "--epochs", ",".join(map(str, args.epoch_list)), "--mathdx", str(mathdx or 0), "--tiles", args.tiles,
                   "--passes", args.passes]
        tensor_cores = args.tensor_cores if tensor_cores is None else tensor_cores
        if tensor_cores is not None:
            command += ["--tensor-cores", str(tensor_cores)]
        if args.size:
            command += ["--size", str(args.size)]
        done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:
        return {"error": done.stderr[-3000:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="kernel,torch,fit")
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--size", type=int, default=None, help="square size of the dome's images (default: their own)")
    parser.add_argument("--batch", type=int, default=1 << 16)
    parser.add_argument("--epochs", default="25,50,100", help="epochs of the PSNR runs, comma-separated")
    parser.add_argument("--mathdx", type=int, default=None, help="kernel part: 1 or 0 (default: both)")
    parser.add_argument("--tensor-cores", type=int, default=None,
                        help="kernel and launches parts: 1 (the tensor cores' step) or 0 (Warp's tile products; "
                             "--mathdx says which) (default: both)")
    parser.add_argument("--passes", default="1,2,4", help="launches part: passes a block of the tensor cores' step")
    parser.add_argument("--warm-cache", action="store_true", help="kernel part: the usual kernel cache")
    parser.add_argument("--fit-set", default="", help="fit part: --set overrides, space-separated STAGE.NAME=VALUE")
    parser.add_argument("--no-fit-cold", dest="fit_cold", action="store_false",
                        help="fit part: leave out the fit on an empty kernel cache")
    parser.add_argument("--tiles", default=DEFAULT_TILES,
                        help="tiles and launches parts: samples per tile, tiles per block, threads[, blocks per SM "
                             "(launch bounds)]; ';' between shapes")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.epoch_list = [int(e) for e in args.epochs.split(",") if e]
    args.tile_list = [tuple(int(v) for v in shape.split(",")) for shape in args.tiles.split(";") if shape]
    args.pass_list = [int(p) for p in args.passes.split(",") if p]
    if args.child == "launches" and args.tensor_cores == 0:
        args.pass_list = []
    elif args.child == "launches" and args.tensor_cores == 1:
        args.tile_list = []
    if args.child:
        print(json.dumps(PARTS[args.child](args)))
        return
    commit = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    results = {"machine": platform.node(), "date": datetime.date.today().isoformat(), "commit": commit}
    for part in args.parts.split(","):
        if part == "kernel":
            variants = [("kernel tensor cores", 0, 1)] if args.tensor_cores in (None, 1) else []
            if args.tensor_cores in (None, 0):
                variants += [(f"kernel mathdx={m}", m, 0) for m in ([1, 0] if args.mathdx is None else [args.mathdx])]
            for label, mathdx, tensor_cores in variants:
                results[label] = _child(args, "kernel", mathdx, tensor_cores)
                print(label, results[label], file=sys.stderr, flush=True)
        elif part in ("torch", "fit", "tiles", "launches"):
            results[part] = part_fit(args) if part == "fit" else _child(args, part)
            print(part, results[part], file=sys.stderr, flush=True)
    if os.environ.get("OUT"):
        Path(os.environ["OUT"], "bench_learned_training.json").write_text(json.dumps(results, indent=1))
    print(f"\n{results['machine']}, {results['date']}, commit {results['commit']}, batch {args.batch}")
    print("| implementation | first step (s, empty cache) | samples/s, 1 model | 2 side by side | "
          + " | ".join(f"PSNR {e} ep (dB) / s" for e in args.epoch_list) + " |")
    print("|---|---|---|---|" + "---|" * len(args.epoch_list))
    for label, row in results.items():
        if not isinstance(row, dict) or label in ("fit", "tiles", "launches") or "error" in row:
            if isinstance(row, dict) and "error" in row:
                print(f"| {label} | error: {row['error'].splitlines()[-1] if row['error'] else '?'} |")
            continue
        cells = [f"{row.get('first_step_seconds', float('nan')):.1f}",
                 f"{row.get('samples_per_second_1', float('nan')) / 1e6:.1f} M",
                 f"{row.get('samples_per_second_2', float('nan')) / 1e6:.1f} M"]
        cells += [f"{row.get(f'psnr_{e}', float('nan')):.2f} / {row.get(f'train_seconds_{e}', float('nan')):.1f}"
                  for e in args.epoch_list]
        print(f"| {label} | " + " | ".join(cells) + " |")
    for label, row in results.get("launches", {}).items():
        if isinstance(row, dict) and "error" not in row:
            cells = [f"{k} {v:.1f} us" if k != "samples_per_second" else f"{v / 1e6:.1f} M samples/s"
                     for k, v in row.items()]
            print(f"| launches {label} | " + " | ".join(cells) + " |")
    for label, row in results.get("fit", {}).items():
        print(f"| fit {label} | {row.get('seconds', float('nan')):.1f} s | PSNR {row.get('psnr', float('nan')):.2f} dB "
              f"| moving {row.get('moving')} | {row.get('error', '')[-200:]} |")


if __name__ == "__main__":
    main()
