"""The ``warp-highlights`` command line (also ``python -m warp_highlights``).

User mistakes end with one line on stderr and exit status 2; Ctrl-C with status 130. Nothing is left
half-written: every output goes to a temporary name first.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from . import __version__
from .cli_args import check_device as _check_device
from .cli_args import check_output_file, parse_size, parse_triple
from .errors import InputError

__all__ = ["main"]

EXIT_INPUT_ERROR = 2
EXIT_INTERRUPTED = 130


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    argv = _attach_negative_values(sys.argv[1:] if argv is None else list(argv))
    _quiet_warp(verbose="-v" in argv or "--verbose" in argv)
    parser = _build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help(sys.stderr)
        return EXIT_INPUT_ERROR
    try:
        return args.run(args) or 0
    except InputError as error:
        print(f"warp-highlights {args.command}: error: {error}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except KeyboardInterrupt:
        print(f"warp-highlights {args.command}: interrupted; nothing partial was left behind", file=sys.stderr)
        return EXIT_INTERRUPTED


def _attach_negative_values(argv: list[str]) -> list[str]:
    """'--light -0.5,0.2,1' -> '--light=-0.5,0.2,1': argparse takes a value starting with '-' for an option."""
    result = []
    values = iter(argv)
    for token in values:
        if token == "--light":
            value = next(values, None)
            if value is not None and len(value) > 1 and value[0] == "-" and (value[1].isdigit() or value[1] == "."):
                result.append(f"--light={value}")
                continue
            result.append(token)
            if value is not None:
                result.append(value)
            continue
        result.append(token)
    return result


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="warp-highlights",
        description="Relight reflectance fields with moving specular highlights (NVIDIA Warp).",
    )
    parser.add_argument("--version", action="version", version=f"warp-highlights {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    render = commands.add_parser(
        "render",
        help="render a synthetic reflectance field with ground truth",
        description="Ray-trace a shape under many distant lights and write a dataset folder "
        "(images/, specular/, diffuse/, lights.lp, held-out ground truth, mask.png, meta.json).",
    )
    render.add_argument("shape", help="donut, teapot, sphere, or a mesh file pyvista reads (PLY/OBJ/STL)")
    render.add_argument("out", type=Path, help="dataset folder to create")
    _add_render_options(render)
    render.set_defaults(run=_run_render)

    info = commands.add_parser("info", help="check a dataset folder and summarise it")
    info.add_argument("dataset", type=Path, help="dataset folder (a .lp light file and its images)")
    info.add_argument("--heldout", type=Path, help="folder with held-out lights and images, if not inside DATASET")
    info.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_common_options(info)
    info.set_defaults(run=_run_info)

    sheet = commands.add_parser("sheet", help="contact sheet PNG of a dataset: full, specular, diffuse per light")
    sheet.add_argument("dataset", type=Path, help="dataset folder")
    sheet.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    sheet.add_argument("--count", type=int, default=12, help="number of lights shown (default 12)")
    sheet.add_argument("--thumb-height", type=int, default=135, help="height of each tile in pixels (default 135)")
    sheet.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    _add_common_options(sheet)
    sheet.set_defaults(run=_run_sheet)

    fit = commands.add_parser(
        "fit",
        help="fit a highlight field to a dataset (segmentation, estimation, retargeting)",
        description="Segment every image into diffuse and specular parts, fit a few Gaussians to each specular "
        "image, re-fit every set onto its neighbours in the light triangulation, decide the Gaussians' paths, and "
        "write everything to one highlight-field file.",
    )
    fit.add_argument("dataset", type=Path, nargs="?", help="dataset folder (a .lp light file and its images)")
    fit.add_argument("-o", "--output", type=Path, help="highlight-field file to write (e.g. donut.whf); required")
    fit.add_argument("--size", help="working resolution WIDTHxHEIGHT, same aspect ratio, at most the images' size (default: the images' size)")
    fit.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="STAGE.NAME=VALUE",
        help="override a hyper-parameter, e.g. --set retarget.c_str=0.01 --set estimation.iterations=600 "
        "(repeatable; --list-settings shows them all)",
    )
    fit.add_argument("--list-settings", action="store_true", help="print every hyper-parameter with its default and exit")
    fit.add_argument("--diffuse", choices=["lambert", "images", "none"], default="lambert", help="diffuse part to store: per-pixel Lambertian fit (default), that plus the diffuse images, or none")
    fit.add_argument(
        "--exposure",
        default="1",
        help="multiply the radiance by this before fitting, or 'auto' (99.9th percentile -> 1); the thresholds assume "
        "display white is 1, so dim photographs want 'auto' (default 1: rendered data)",
    )
    fit.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    fit.add_argument("--workers", type=int, help="CPU threads for the fitting stages (default: one per core)")
    fit.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    fit.add_argument("--report", type=Path, help="also write the fit report as JSON to this file")
    fit.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    _add_common_options(fit)
    fit.set_defaults(run=_run_fit)

    from .cli_relight import add_relight_commands

    add_relight_commands(commands, common=_add_common_options)

    from .cli_view import add_view_command

    add_view_command(commands, common=_add_common_options)

    demo = commands.add_parser(
        "demo",
        help="the built-in synthetic default, end to end",
        description="Render the built-in donut at a CPU-friendly size (with held-out ground truth), fit a highlight field, "
        "evaluate it against the ground truth, and animate the light: everything goes into one folder with an index.md.",
    )
    demo.add_argument("out", type=Path, nargs="?", default=Path("warp-highlights-demo"), help="output folder")
    demo.add_argument("--lights", type=int, default=64, help="number of lights (default 64)")
    demo.add_argument("--size", default="240x135", help="image size WIDTHxHEIGHT (default 240x135)")
    demo.add_argument("--frames", type=int, default=72, help="frames of each animation (default 72)")
    demo.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    demo.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    _add_common_options(demo)
    demo.set_defaults(run=_run_demo)
    return parser


def _add_common_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("-v", "--verbose", action="store_true", help="let Warp report kernel compilation")


def _add_render_options(parser: argparse.ArgumentParser) -> None:
    from .render import Material, RenderSettings

    material, settings = Material(), RenderSettings()
    lights = parser.add_argument_group("lights")
    lights.add_argument("--lights", type=int, default=250, help="number of Fibonacci-lattice lights (default 250)")
    lights.add_argument("--dome", action="store_true", help="lights on the upper hemisphere only (an RTI dome)")
    lights.add_argument("--min-elevation", type=float, default=10.0, help="lowest dome light, degrees (default 10)")
    lights.add_argument("--lights-file", type=Path, help="take the light directions from this .lp file instead")
    lights.add_argument(
        "--heldout",
        default="centroids",
        help="held-out ground truth: 'centroids' (every triangle centroid, the default), 'none', or a .lp file",
    )
    image = parser.add_argument_group("image")
    image.add_argument("--size", default=f"{settings.width}x{settings.height}", help="WIDTHxHEIGHT (default 480x270)")
    image.add_argument("--samples", type=int, default=settings.samples_per_pixel, help="samples per pixel, a square (default 4)")
    image.add_argument("--fov", type=float, default=settings.fov_y_deg, help="vertical field of view, degrees (default 30)")
    image.add_argument("--gray", action="store_true", help="single-channel luminance images instead of RGB")
    image.add_argument("--half", action="store_true", help="store EXR as half floats (smaller files)")
    image.add_argument("--seed", type=int, default=settings.seed, help="seed of the pixel-sample jitter")
    surface = parser.add_argument_group("material (defaults depend on the shape)")
    surface.add_argument("--albedo", help="diffuse colour R,G,B, linear, each in [0, 1]")
    surface.add_argument("--ambient", type=float, help=f"ambient radiance (donut: {material.ambient})")
    surface.add_argument("--specular", type=float, help=f"specular strength (donut: {material.specular})")
    surface.add_argument("--shininess", type=float, help=f"Blinn-Phong exponent (donut: {material.shininess:g})")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    _add_common_options(parser)


def _quiet_warp(*, verbose: bool) -> None:
    """Hide Warp's greeting and per-module compile lines unless asked for; keep its warnings."""
    import warp as wp

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING


def _light_sets(args) -> tuple:
    from .lights import LightSet

    if args.lights_file is not None:
        lights = LightSet.read_lp(args.lights_file, check_files=False)
    elif args.lights < 4:
        raise InputError(f"--lights must be at least 4 to triangulate, got {args.lights}")
    elif args.dome:
        lights = LightSet.fibonacci_dome(args.lights, min_elevation_deg=args.min_elevation)
    else:
        lights = LightSet.fibonacci_sphere(args.lights)
    lights = LightSet(lights.directions)  # rendered images get our own file names
    heldout = args.heldout
    if heldout.lower() == "none":
        heldout = None
    elif heldout.lower() != "centroids":
        heldout = LightSet(LightSet.read_lp(Path(heldout), check_files=False).directions)
    else:
        heldout = "centroids"
    return lights, heldout


def _material(args):
    from dataclasses import replace

    from .render import default_material

    material = default_material(args.shape)
    changes = {k: getattr(args, k) for k in ("ambient", "specular", "shininess") if getattr(args, k) is not None}
    if args.albedo is not None:
        changes["albedo"] = parse_triple(args.albedo, "albedo")
    return replace(material, **changes)


def _run_render(args) -> int:
    from .render import RenderSettings, render_dataset

    width, height = parse_size(args.size)
    settings = RenderSettings(
        width=width, height=height, samples_per_pixel=args.samples, fov_y_deg=args.fov, colour=not args.gray, seed=args.seed
    )
    material = _material(args)
    lights, heldout = _light_sets(args)
    device = _check_device(args.device)
    started = time.perf_counter()
    folder = render_dataset(
        args.shape,
        args.out,
        lights=lights,
        heldout=heldout,
        material=material,
        settings=settings,
        device=device,
        overwrite=args.overwrite,
        half=args.half,
        progress=not args.quiet,
    )
    meta = json.loads((folder / "meta.json").read_text())
    print(
        f"wrote {folder}: {meta['light_count']} lights + {meta['heldout_count']} held-out, "
        f"{width}x{height}, {args.samples} samples/px, on {meta['device']}, {time.perf_counter() - started:.1f} s"
    )
    return 0


def _run_info(args) -> int:
    from .dataset import ReflectanceField

    field = ReflectanceField.load(args.dataset, heldout=args.heldout, linear=args.linear, progress=not args.quiet)
    summary = field.summary()
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():
            print(f"{key:>18}: {value}")
    return 0


def _run_sheet(args) -> int:
    from .dataset import ReflectanceField
    from .preview import save_contact_sheet

    if args.output.suffix.lower() != ".png":
        raise InputError(f"contact sheet '{args.output}' must be a .png file")
    field = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet)
    path = save_contact_sheet(field, args.output, count=args.count, thumb_height=args.thumb_height)
    print(f"wrote {path}")
    return 0


def _run_fit(args) -> int:
    from .config import FitSettings

    settings = FitSettings().with_overrides(args.overrides)
    if args.list_settings:
        _print_settings(settings.to_dict())
        return 0
    if args.dataset is None or args.output is None:
        raise InputError("fit needs a DATASET folder and -o FIELD, e.g. warp-highlights fit data/donut -o donut.whf")
    output = Path(args.output)
    check_output_file(output, overwrite=args.overwrite)
    if args.report is not None:
        if Path(args.report).resolve() == output.resolve():
            raise InputError(f"--report {args.report} is the field file itself; give the report its own name")
        check_output_file(Path(args.report), overwrite=True)
    size = parse_size(args.size) if args.size else None
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    device = _check_device(args.device)
    from .dataset import ReflectanceField
    from .fit import fit_field

    started = time.perf_counter()
    dataset = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet)
    load_seconds = time.perf_counter() - started
    log = None if args.quiet else (lambda line: print(f"  {line}", file=sys.stderr))
    field = fit_field(
        dataset, settings=settings, device=device, size=size, diffuse=args.diffuse, exposure=args.exposure, workers=args.workers, progress=not args.quiet, log=log
    )
    field.report["seconds"] = {"loading": round(load_seconds, 3), **field.report["seconds"]}
    written = field.save(output)
    field.report["file_bytes"] = written
    if args.report is not None:
        from .images import atomic_target

        with atomic_target(Path(args.report)) as temporary:
            temporary.write_text(json.dumps(field.report, indent=2))
    _print_fit_summary(field, output, written, time.perf_counter() - started)
    return 0


def _print_settings(values: dict, prefix: str = "") -> None:
    for key, value in values.items():
        if isinstance(value, dict):
            _print_settings(value, prefix + key + ".")
        else:
            print(f"{prefix}{key}={value}")


def _print_fit_summary(field, output: Path, written: int, seconds: float) -> None:
    report = field.report
    est, ret = report["estimation"], report["retargeting"]
    count, quality = est["gaussians_per_light"], est["psnr_db"]
    print(f"wrote {output} ({written / 1e6:.2f} MB) in {seconds:.1f} s on {report['device']}")
    print(
        f"  lights {report['lights']} ({'dome' if report['dome'] else 'full sphere'}), directed edges {report['directed_edges']}, "
        f"working size {report['size'][0]}x{report['size'][1]}, exposure x{report['exposure']:.3g}"
    )
    print("  stage times: " + ", ".join(f"{name} {value:.1f} s" for name, value in report["seconds"].items()))
    print(f"  Gaussians per light: mean {count['mean']:.1f}, min {count['min']:.0f}, max {count['max']:.0f}")
    print(f"  estimation PSNR (dB): mean {quality['mean']:.1f}, 5th percentile {quality['p5']:.1f}, min {quality['min']:.1f}")
    print(f"  retargeting fit loss: source {ret['source_loss']['mean']:.1f} -> rigid {ret['rigid_loss']['mean']:.1f} -> final {ret['loss']['mean']:.1f} (mean); improved on {100 * ret['improved_share']:.0f}% of edges")
    print(f"  segmentation: {report['segmentation']['few_light_pixels']} pixels left all diffuse (fewer than 4 lit samples)")
    parts = field.size_report()
    print("  file: " + ", ".join(f"{name} {value / 1e6:.2f} MB" for name, value in parts.items()))


def _run_demo(args) -> int:
    from .demo import run_demo

    width, height = parse_size(args.size)
    device = _check_device(args.device)
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
