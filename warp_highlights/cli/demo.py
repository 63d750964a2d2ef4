"""``warp-highlights demo``: the whole pipeline on the built-in donut, into one folder with an index."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from .args import Command, check_device, parse_size

__all__ = ["COMMANDS", "run_demo"]

ORBIT_ELEVATION_DEG = 35.0
"""Elevation of the demo's light orbit: high enough that the donut's top keeps a highlight."""


def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, nargs="?", default=Path("warp-highlights-demo"), help="output folder")
    parser.add_argument("--lights", type=int, default=64, help="number of lights (default 64)")
    parser.add_argument("--size", default="240x135", help="image size WIDTHxHEIGHT (default 240x135)")
    parser.add_argument("--frames", type=int, default=72, help="frames of each animation (default 72)")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def _run_demo(args) -> int:
    width, height = parse_size(args.size)
    device = check_device(args.device)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output {out} is a file; the demo needs a folder name")
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"output folder {out} exists and is not empty; pass --overwrite or choose another folder")
    if args.frames < 2:
        raise InputError(f"--frames must be at least 2, got {args.frames}")
    started = time.perf_counter()
    index = run_demo(out, lights=args.lights, size=(width, height), frames=args.frames, device=device, progress=not args.quiet,
                     log=(lambda line: None) if args.quiet else (lambda line: print(line, file=sys.stderr)))
    print(f"demo finished in {time.perf_counter() - started:.0f} s: see {index}")
    return 0


def run_demo(out: Path, *, lights: int = 64, size: tuple[int, int] = (240, 135), frames: int = 72, device=None, progress: bool = True, log=print) -> Path:
    """Render, fit, evaluate and animate the donut into ``out``; returns the index file.

    Args:
        out: output folder (created; must be empty or absent).
        lights: Fibonacci lights over the full sphere.
        size: (width, height) of the images.
        frames: frames of each animation.
        device: Warp device.
        progress: progress bars on stderr.
        log: receives one line per finished step.
    """
    from ..fit.pipeline import fit_field
    from ..io.dataset import ReflectanceField
    from ..io.fieldfile import save_field
    from ..io.images import atomic_target, write_image
    from ..model.lights import LightSet
    from ..relight.evaluation import evaluate_field
    from ..relight.relighter import Relighter, alpha_inputs
    from ..synth.render import RenderSettings, default_material, render_dataset
    from ..view.animation import orbit, write_animation
    from ..view.preview import save_contact_sheet
    from .relight import write_evaluation

    width, height = size
    if lights < 4:
        raise InputError(f"the demo needs at least 4 lights, got {lights}")
    out.mkdir(parents=True, exist_ok=True)
    made: list[tuple[str, str]] = []
    steps: dict[str, float] = {}
    started = time.perf_counter()

    def step(name: str, t0: float, line: str) -> None:
        steps[name] = time.perf_counter() - t0
        log(f"{name:>9} {steps[name]:6.1f} s  {line}")

    t = time.perf_counter()
    folder = render_dataset("donut", out / "donut", lights=LightSet.fibonacci_sphere(lights), material=default_material("donut"),
                            settings=RenderSettings(width=width, height=height), device=device, overwrite=True, progress=progress)
    dataset = ReflectanceField.load(folder, progress=False)
    sheet = save_contact_sheet(dataset, out / "donut-contact-sheet.png")
    made += [("donut/", f"the rendered dataset: {lights} lights + {dataset.heldout.light_count} held-out triangle centroids, {width}x{height}, with ground truth"),
             (sheet.name, "contact sheet: full, specular and diffuse images of 12 lights")]
    step("render", t, f"{folder}")

    t = time.perf_counter()
    field = fit_field(dataset, device=device, progress=progress)
    field_path = out / "donut.whf"
    save_field(field, field_path)
    made.append((field_path.name, f"the fitted highlight field ({field_path.stat().st_size / 1e6:.2f} MB; warp-highlights relight/animate/evaluate read it)"))
    step("fit", t, f"{field.estimated.counts.mean():.1f} Gaussians per light -> {field_path.name}")

    t = time.perf_counter()
    alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
    evaluation = evaluate_field(field, dataset, device=device, alpha_stacks=(alpha_specular, alpha_images))
    report = evaluation.to_dict() | {"field": str(field_path), "dataset": str(folder)}
    written = write_evaluation(out / "evaluation", evaluation, report, overwrite=True, title="donut")
    made.append(("evaluation/", "report.json and plots: " + ", ".join(written)))
    summary = report["summary"]["specular"]
    step("evaluate", t, "specular PSNR " + ", ".join(f"{m} {summary[m]['mean']:.2f} dB" for m in ("circular", "straight", "alpha")))

    t = time.perf_counter()
    relighter = Relighter(field, device=device, alpha_specular=alpha_specular, alpha_images=alpha_images)
    path = orbit(ORBIT_ELEVATION_DEG, frames)
    write_image(out / "relit.png", relighter.relight(path[0]).full)
    made.append(("relit.png", f"one relit image, light at azimuth 0, elevation {ORBIT_ELEVATION_DEG:g} deg"))
    circular = relighter.relight(path, method="circular")
    write_animation(iter(circular.full), out / "orbit.gif", fps=24, frame_count=frames, overwrite=True)
    made.append(("orbit.gif", f"{frames} frames, the light orbiting at {ORBIT_ELEVATION_DEG:g} deg elevation (circular paths, Lambertian diffuse)"))
    alpha = relighter.relight(path, method="alpha", full=False)
    straight = relighter.relight(path, method="straight", full=False)
    panels = (np.concatenate([c, s, a], axis=1) for c, s, a in zip(circular.specular, straight.specular, alpha.specular))
    write_animation(panels, out / "orbit-highlights.gif", fps=24, frame_count=frames, overwrite=True)
    made.append(("orbit-highlights.gif", "the highlights alone, side by side, left to right: circular, straight, alpha blend (watch them glide vs cross-fade)"))
    step("animate", t, f"{frames} frames x 4 renders")

    total = time.perf_counter() - started
    index = out / "index.md"
    lines = [
        "# warp-highlights demo",
        "",
        f"Made by `warp-highlights demo` in {total:.0f} s ({', '.join(f'{k} {v:.1f} s' for k, v in steps.items())}).",
        "",
        "| file | what it is |",
        "|---|---|",
        *[f"| `{name}` | {what} |" for name, what in made],
        "",
        f"Specular PSNR at the {report['heldout']} held-out centroids (dB, mean / 5th / 95th percentile):",
        "",
        "| method | mean | p5 | p95 |",
        "|---|---|---|---|",
        *[f"| {m} | {summary[m]['mean']:.2f} | {summary[m]['p5']:.2f} | {summary[m]['p95']:.2f} |" for m in ("circular", "straight", "alpha")],
        "",
        f"Circular beats the alpha blend on {100 * summary['circular_beats_alpha']:.0f}% of the held-out lights.",
        "",
        ("Next: `warp-highlights view donut.whf` (drag the light; `--screenshot view.png` without a display), "
         "`warp-highlights relight donut.whf --light 0.3,0.5,1 -o relit.exr`, "
         "`warp-highlights animate donut.whf --path orbit:20 -o orbit.gif`."),
    ]
    with atomic_target(index) as temporary:
        temporary.write_text("\n".join(lines) + "\n")
    with atomic_target(out / "demo.json") as temporary:
        temporary.write_text(json.dumps({"seconds": steps, "total_seconds": total, "files": dict(made)}, indent=2))
    return index


COMMANDS = (
    Command("demo", _demo_arguments, _run_demo, help="the built-in synthetic default, end to end",
            description="Render the built-in donut at a CPU-friendly size (with held-out ground truth), fit a highlight "
            "field, evaluate it against the ground truth, and animate the light: everything goes into one "
            "folder with an index.md."),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
