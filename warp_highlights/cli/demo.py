"""``warp-highlights demo``: the whole pipeline on the built-in donut, into one folder with an index."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from .args import Command, check_device, check_output_folder, in_range, size_option

__all__ = ["COMMANDS", "run_demo"]

ORBIT_ELEVATION_DEG = 35.0
"""Elevation of the demo's light orbit: high enough that the donut's top keeps a highlight."""


def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, nargs="?", default=Path("warp-highlights-demo"), help="output folder")
    parser.add_argument("--lights", type=in_range(int, 4, 2000), default=64,
                        help="number of lights, 4..2000 (default 64)")
    parser.add_argument("--size", type=size_option(), default="240x135",
                        help="image size WIDTHxHEIGHT (default 240x135)")
    parser.add_argument("--frames", type=in_range(int, 2, 10_000), default=72,
                        help="frames of each animation, 2..10000 (default 72)")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--residual", choices=["auto", "lowrank", "learned"], default="auto",
                        help="the fit's residual, as fit --residual takes it (default auto: learned on CUDA, minutes; "
                             "lowrank elsewhere, seconds)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def _run_demo(args) -> int:
    from ..model.config import FitSettings
    from .fit import residual_overrides

    width, height = args.size
    device = check_device(args.device)
    out = Path(args.out)
    check_output_folder(out, overwrite=args.overwrite, legacy=demo_folder_entry, kind="demo")
    settings = FitSettings().with_overrides(residual_overrides(args.residual))
    started = time.perf_counter()
    index = run_demo(out, lights=args.lights, size=(width, height), frames=args.frames, device=device,
                     progress=not args.quiet,
                     overwrite=args.overwrite, settings=settings)
    print(f"demo finished in {time.perf_counter() - started:.0f} s: see {index}")
    return 0


DEMO_FILES = frozenset({"donut-contact-sheet.png", "donut.whf", "relit.png", "orbit.gif", "orbit-highlights.gif",
                        "index.md",
                        "demo.json"})
"""The files at the top of a demo folder, beside its ``donut/`` dataset and ``evaluation/``."""


def demo_folder_entry(relative: str) -> bool:
    """Whether ``relative`` (a path inside the folder) is a file of a demo folder (how one written
    before manifests existed is recognised)."""
    from ..io.dataset import dataset_folder_entry
    from .relight import evaluation_folder_entry

    folder, _, rest = relative.partition("/")
    if folder == "donut":
        return dataset_folder_entry(rest) or rest == ".warp-highlights.json"
    if folder == "evaluation":
        return evaluation_folder_entry(rest) or rest == ".warp-highlights.json"
    return relative in DEMO_FILES


def run_demo(out: Path, *, lights: int = 64, size: tuple[int, int] = (240, 135), frames: int = 72, device=None,
             progress: bool = True,
             log=None, overwrite: bool = False, settings=None) -> Path:
    """Render, fit, evaluate and animate the donut into ``out``; returns the index file.

    Everything is made in a temporary folder beside ``out`` that takes ``out``'s place at the end, so
    an interrupted demo leaves the previous one (or nothing), never half of each.

    Args:
        out: output folder (absent or empty, or with ``overwrite`` an earlier demo).
        lights: Fibonacci lights over the full sphere.
        size: (width, height) of the images.
        frames: frames of each animation.
        device: Warp device.
        progress: progress bars on stderr.
        log: receives one line per finished step (default: this module's logger, at INFO).
        overwrite: replace an earlier demo folder (never a folder holding other files).
        settings: the fit's ``FitSettings`` (default: the defaults, which learn the residual on CUDA).
    """
    from ..io.atomic import FolderTransaction

    log = log or logging.getLogger(__name__).info
    width, height = size
    if lights < 4:
        raise InputError(f"the demo needs at least 4 lights, got {lights}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    transaction = FolderTransaction(out, kind="demo", overwrite=overwrite, legacy=demo_folder_entry)
    try:
        _make_demo(transaction.temporary, out, lights=lights, size=size, frames=frames, device=device,
                   progress=progress, log=log,
                   settings=settings)
        transaction.commit()
    finally:
        transaction.abort()
    return out / "index.md"


def _make_demo(work: Path, out: Path, *, lights: int, size: tuple[int, int], frames: int, device, progress: bool, log,
               settings) -> None:
    """The demo's files into ``work`` (the temporary folder that becomes ``out``)."""
    from ..fit.pipeline import fit_field
    from ..io.atomic import atomic_file
    from ..io.dataset import ReflectanceField
    from ..io.fieldfile import save_field
    from ..io.images import write_image
    from ..model.lights import LightSet
    from ..relight.evaluation import evaluate_field
    from ..relight.relighter import Relighter, alpha_inputs
    from ..synth.render import RenderSettings, default_material, render_dataset
    from ..view.animation import write_animation
    from ..view.light_paths import orbit
    from ..view.preview import save_contact_sheet
    from .relight import write_evaluation

    width, height = size
    made: list[tuple[str, str]] = []
    steps: dict[str, float] = {}
    started = time.perf_counter()

    def step(name: str, t0: float, line: str) -> None:
        steps[name] = time.perf_counter() - t0
        log(f"{name:>9} {steps[name]:6.1f} s  {line}")

    t = time.perf_counter()
    folder = render_dataset("donut", work / "donut", lights=LightSet.fibonacci_sphere(lights),
                            material=default_material("donut"),
                            settings=RenderSettings(width=width, height=height), device=device, overwrite=True,
                            progress=progress)
    dataset = ReflectanceField.load(folder, progress=False)
    sheet = save_contact_sheet(dataset, work / "donut-contact-sheet.png")
    made += [("donut/", f"the rendered dataset: {lights} lights + {dataset.heldout.light_count} held-out triangle "
                        f"centroids, {width}x{height}, with ground truth"),
             (sheet.name, "contact sheet: full, specular and diffuse images of 12 lights")]
    step("render", t, f"{out / folder.name}")

    t = time.perf_counter()
    field = fit_field(dataset, settings=settings, device=device, progress=progress)
    field_path = work / "donut.whf"
    save_field(field, field_path)
    made.append((field_path.name, f"the fitted highlight field ({field_path.stat().st_size / 1e6:.2f} MB; "
                                  f"warp-highlights relight/animate/evaluate read it)"))
    step("fit", t, f"{field.estimated.counts.mean():.1f} Gaussians per light -> {field_path.name}")

    t = time.perf_counter()
    alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
    evaluation = evaluate_field(field, dataset, device=device, alpha_stacks=(alpha_specular, alpha_images),
                                baselines=("ptm", "hsh3", "rbf"))
    report = evaluation.to_dict() | {"field": str(out / field_path.name), "dataset": str(out / folder.name)}
    written = write_evaluation(work / "evaluation", evaluation, report, overwrite=True, title="donut")
    made.append(("evaluation/", "report.json and plots: " + ", ".join(written)))
    summary = report["summary"]["specular"]
    full, ssim = report["summary"]["full_srgb"], report["summary"]["full_ssim"]
    # too few lights leave some out
    full_methods = [m for m in ("circular", "straight", "alpha", "ptm", "hsh3", "rbf") if m in full]
    step("evaluate", t,
         "specular PSNR " + ", ".join(f"{m} {summary[m]['mean']:.2f} dB" for m in ("circular", "straight", "alpha"))
         + "; full image 8-bit PSNR " + ", ".join(f"{m} {full[m]['mean']:.2f} dB" for m in ("circular", "alpha", "rbf")
                                                  if m in full))

    t = time.perf_counter()
    relighter = Relighter(field, device=device, alpha_specular=alpha_specular, alpha_images=alpha_images)
    path = orbit(ORBIT_ELEVATION_DEG, frames)
    write_image(work / "relit.png", relighter.relight(path[0]).full)
    made.append(("relit.png", f"one relit image, light at azimuth 0, elevation {ORBIT_ELEVATION_DEG:g} deg"))
    circular = relighter.relight(path, method="circular")
    write_animation(iter(circular.full), work / "orbit.gif", fps=24, frame_count=frames, overwrite=True)
    made.append(("orbit.gif", f"{frames} frames, the light orbiting at {ORBIT_ELEVATION_DEG:g} deg elevation (circular "
                              f"paths, residual transfer)"))
    alpha = relighter.relight(path, method="alpha", full=False)
    straight = relighter.relight(path, method="straight", full=False)
    panels = (np.concatenate([c, s, a], axis=1)
              for c, s, a in zip(circular.specular, straight.specular, alpha.specular))
    write_animation(panels, work / "orbit-highlights.gif", fps=24, frame_count=frames, overwrite=True)
    seen = ("(watch them glide vs cross-fade)" if field.moving_mask.any() else
            "(this field keeps no moving Gaussian, its checks found the images relit better without them: the first "
            "two panels are dark, and its residual carries the highlights in orbit.gif; warp-highlights info "
            "donut.whf says why)")
    made.append(("orbit-highlights.gif", "the highlights alone, side by side, left to right: circular, straight, alpha "
                                         f"blend {seen}"))
    step("animate", t, f"{frames} frames x 4 renders")

    total = time.perf_counter() - started
    index = work / "index.md"
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
        *[f"| {m} | {summary[m]['mean']:.2f} | {summary[m]['p5']:.2f} | {summary[m]['p95']:.2f} |"
          for m in ("circular", "straight", "alpha")],
        "",
        f"Circular beats the alpha blend on {100 * summary['circular_beats_alpha']:.0f}% of the held-out lights.",
        "",
        "Full images at the same lights, as RTI users score them (8-bit sRGB PSNR in dB and SSIM), next to the "
        "classic RTI fits:",
        "",
        "| method | PSNR mean | worst | SSIM mean |",
        "|---|---|---|---|",
        *[f"| {m} | {full[m]['mean']:.2f} | {full[m]['min']:.2f} | {ssim[m]['mean']:.3f} |" for m in full_methods],
        "",
        ("Next: `warp-highlights view donut.whf` (drag the light; `--screenshot view.png` without a display), "
         "`warp-highlights relight donut.whf --light 0.3,0.5,1 -o relit.exr`, "
         "`warp-highlights animate donut.whf --path orbit:20 -o orbit.gif`."),
    ]
    with atomic_file(index) as temporary:
        temporary.write_text("\n".join(lines) + "\n")
    with atomic_file(work / "demo.json") as temporary:
        temporary.write_text(json.dumps({"seconds": steps, "total_seconds": total, "files": dict(made)}, indent=2))


COMMANDS = (
    Command("demo", _demo_arguments, _run_demo, help="the built-in synthetic default, end to end",
            description="Render the built-in donut at a CPU-friendly size (with held-out ground truth), "
                        "fit a highlight "
            "field, evaluate it against the ground truth, and animate the light: everything goes into one "
            "folder with an index.md."),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
