"""The ``render``, ``info`` and ``sheet`` commands of ``warp-highlights``: make, check and look at datasets."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..model.errors import InputError
from .args import Command, check_device, parse_size, parse_triple

__all__ = ["COMMANDS"]


def _render_arguments(parser: argparse.ArgumentParser) -> None:
    from ..synth.render import Material, RenderSettings

    parser.add_argument("shape", help="donut, teapot, sphere, or a mesh file pyvista reads (PLY/OBJ/STL)")
    parser.add_argument("out", type=Path, help="dataset folder to create")

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


def _info_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="dataset folder (a .lp light file and its images)")
    parser.add_argument("--heldout", type=Path, help="folder with held-out lights and images, if not inside DATASET")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def _sheet_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="dataset folder")
    parser.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    parser.add_argument("--count", type=int, default=12, help="number of lights shown (default 12)")
    parser.add_argument("--thumb-height", type=int, default=135, help="height of each tile in pixels (default 135)")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")


def _light_sets(args) -> tuple:
    from ..io.lightfile import read_lp
    from ..model.lights import LightSet

    if args.lights_file is not None:
        lights = read_lp(args.lights_file, check_files=False)
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
        heldout = LightSet(read_lp(Path(heldout), check_files=False).directions)
    else:
        heldout = "centroids"
    return lights, heldout


def _material(args):
    from dataclasses import replace

    from ..synth.render import default_material

    material = default_material(args.shape)
    changes = {k: getattr(args, k) for k in ("ambient", "specular", "shininess") if getattr(args, k) is not None}
    if args.albedo is not None:
        changes["albedo"] = parse_triple(args.albedo, "albedo")
    return replace(material, **changes)


def _run_render(args) -> int:
    from ..synth.render import RenderSettings, render_dataset

    width, height = parse_size(args.size)
    settings = RenderSettings(
        width=width, height=height, samples_per_pixel=args.samples, fov_y_deg=args.fov, colour=not args.gray, seed=args.seed
    )
    material = _material(args)
    lights, heldout = _light_sets(args)
    device = check_device(args.device)
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
    from ..io.dataset import ReflectanceField

    field = ReflectanceField.load(args.dataset, heldout=args.heldout, linear=args.linear, progress=not args.quiet)
    summary = field.summary()
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():
            print(f"{key:>18}: {value}")
    return 0


def _run_sheet(args) -> int:
    from ..io.dataset import ReflectanceField
    from ..view.preview import save_contact_sheet

    if args.output.suffix.lower() != ".png":
        raise InputError(f"contact sheet '{args.output}' must be a .png file")
    field = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet)
    path = save_contact_sheet(field, args.output, count=args.count, thumb_height=args.thumb_height)
    print(f"wrote {path}")
    return 0


COMMANDS = (
    Command("render", _render_arguments, _run_render, help="render a synthetic reflectance field with ground truth",
            description="Ray-trace a shape under many distant lights and write a dataset folder (images/, specular/, "
            "diffuse/, lights.lp, held-out ground truth, mask.png, meta.json)."),
    Command("info", _info_arguments, _run_info, help="check a dataset folder and summarise it"),
    Command("sheet", _sheet_arguments, _run_sheet, help="contact sheet PNG of a dataset: full, specular, diffuse per light"),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
