"""The ``render``, ``info`` and ``sheet`` commands of ``warp-highlights``: make, check and look at datasets."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from ..model.errors import InputError
from .args import (
    Command,
    add_pixel_limit_option,
    check_device,
    check_output_file,
    check_output_folder,
    in_range,
    pixel_limit,
    size_option,
    triple_option,
)

MAX_RENDER_LIGHTS = 20_000
"""Most lights ``render`` takes: light stages have up to a few thousand; beyond that the hundreds of
thousands of image files are a mistake rather than a capture."""

__all__ = ["COMMANDS"]


def _render_arguments(parser: argparse.ArgumentParser) -> None:
    from ..synth.settings import TEXTURES, Material, RenderSettings

    parser.add_argument("shape", help="donut, teapot, sphere, coin (a relief plate seen from above), bumpy (a donut "
                        "with small bumps), or a mesh file pyvista reads (PLY/OBJ/STL)")
    parser.add_argument("out", type=Path, help="dataset folder to create")

    material, settings = Material(), RenderSettings()
    lights = parser.add_argument_group("lights")
    lights.add_argument("--lights", type=in_range(int, 4, MAX_RENDER_LIGHTS), default=250,
                        help=f"number of Fibonacci-lattice lights, 4..{MAX_RENDER_LIGHTS} (default 250)")
    lights.add_argument("--dome", action="store_true", help="lights on the upper hemisphere only (an RTI dome)")
    lights.add_argument("--min-elevation", type=in_range(float, 0.0, 80.0, unit="degrees"), default=10.0,
                        help="lowest dome light, 0..80 degrees (default 10)")
    lights.add_argument("--lights-file", type=Path,
                        help="take the light directions from this light file instead (.lp, .dome or .relight)")
    lights.add_argument(
        "--heldout",
        default="centroids",
        help="held-out ground truth: 'centroids' (every triangle centroid, the default), 'none', or a .lp file",
    )
    image = parser.add_argument_group("image")
    image.add_argument("--size", type=size_option(), default=f"{settings.width}x{settings.height}",
                       help="WIDTHxHEIGHT (default 480x270)")
    image.add_argument("--samples", type=in_range(int, 1, 1024), default=settings.samples_per_pixel,
                       help="samples per pixel, a square number up to 1024 (default 4)")
    image.add_argument("--fov", type=in_range(float, 1.0, 169.0, unit="degrees"), default=settings.fov_y_deg,
                       help="vertical field of view, 1..169 degrees (default 30)")
    image.add_argument("--gray", action="store_true", help="single-channel luminance images instead of RGB")
    image.add_argument("--half", action="store_true", help="store EXR as half floats (smaller files)")
    image.add_argument("--seed", type=in_range(int, 0, 2**32 - 1), default=settings.seed,
                       help="seed of the pixel-sample jitter")
    surface = parser.add_argument_group("material (defaults depend on the shape)")
    surface.add_argument("--albedo", type=triple_option("albedo"), help="diffuse colour R,G,B, linear, each in [0, 1]")
    surface.add_argument("--ambient", type=in_range(float, 0.0, 100.0),
                         help=f"ambient radiance, 0..100 (donut: {material.ambient})")
    surface.add_argument("--specular", type=in_range(float, 0.0, 100.0),
                         help=f"specular strength, 0..100 (donut: {material.specular})")
    surface.add_argument("--shininess", type=in_range(float, 1.0, 1e6),
                         help=f"Blinn-Phong exponent, 1..1e6 (donut: {material.shininess:g})")
    surface.add_argument("--roughness", type=in_range(float, 0.0, 1.0),
                         help="GGX microfacet roughness alpha, 0..1, in place of the Blinn-Phong lobe: 0.05 is "
                         "polished metal, 0.3 satin (0: Blinn-Phong; coin: 0.15)")
    surface.add_argument("--texture", choices=TEXTURES,
                         help="albedo pattern: none, or tiles (a checkerboard of two materials, the second pale "
                         "and nearly matte)")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")


def _info_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="dataset folder (a .lp light file and its images), or a highlight-"
                        "field file (.whf): its lights, Gaussians, how many move and what they carry, its residual; "
                        "or an RTIViewer .ptm or .rti file")
    parser.add_argument("--heldout", type=Path, help="folder with held-out lights and images, if not inside DATASET")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON (a field: its fit report)")
    add_pixel_limit_option(parser)


def _sheet_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="dataset folder")
    parser.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    parser.add_argument("--count", type=in_range(int, 1, 100), default=12,
                        help="number of lights shown, 1..100 (default 12)")
    parser.add_argument("--thumb-height", type=in_range(int, 16, 1024, unit="pixels"), default=135,
                        help="height of each tile, 16..1024 pixels (default 135)")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing PNG file")
    add_pixel_limit_option(parser)


def _light_sets(args) -> tuple:
    from ..io.lightfile import read_lights
    from ..model.lights import LightSet

    if args.lights_file is not None:
        lights = read_lights(args.lights_file, check_files=False)
    elif args.dome:
        lights = LightSet.fibonacci_dome(args.lights, min_elevation_deg=args.min_elevation)
    else:
        lights = LightSet.fibonacci_sphere(args.lights)
    lights = LightSet(lights.directions)  # rendered images get our own file names
    heldout = args.heldout
    if heldout.lower() == "none":
        heldout = None
    elif heldout.lower() != "centroids":
        heldout = LightSet(read_lights(Path(heldout), check_files=False).directions)
    else:
        heldout = "centroids"
    return lights, heldout


def _material(args):
    from dataclasses import replace

    from ..synth.render import default_material

    material = default_material(args.shape)
    changes = {k: getattr(args, k) for k in ("ambient", "specular", "shininess", "roughness", "texture")
               if getattr(args, k) is not None}
    if args.albedo is not None:
        changes["albedo"] = args.albedo
    return replace(material, **changes)


def _run_render(args) -> int:
    from ..io.dataset import dataset_folder_entry
    from ..synth.render import RenderSettings, render_dataset

    width, height = args.size
    settings = RenderSettings(
        width=width, height=height, samples_per_pixel=args.samples, fov_y_deg=args.fov, colour=not args.gray,
        seed=args.seed
    )
    inputs = [p for p in (args.lights_file, Path(args.shape), Path(args.heldout)) if p and p.is_file()]
    check_output_folder(args.out, overwrite=args.overwrite, legacy=dataset_folder_entry, kind="dataset", inputs=inputs)
    material = _material(args)
    lights, heldout = _light_sets(args)
    _check_disk_space(args.out, lights, heldout, settings, half=args.half, quiet=args.quiet)
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


RENDER_COMPRESSION_ALLOWANCE = 2.0
"""The factor by which EXR's ZIP compression is assumed to shrink rendered images when checking the
free disk space up front (rendered objects on black backgrounds compress 2-10x; 2 keeps the check
from refusing renders that would fit)."""


def _check_disk_space(out: Path, lights, heldout, settings, *, half: bool, quiet: bool) -> None:
    """Refuse a render whose images cannot fit on the disk, with the figures; announce a large one."""
    import shutil

    from ..model.lights import LightSet
    from ..model.memory import bytes_text

    held = 2 * len(lights) if heldout == "centroids" else (len(heldout) if isinstance(heldout, LightSet) else 0)
    images = 3 * (len(lights) + held)  # full, specular and diffuse per light; at most 2n-4 triangle centroids
    raw = images * settings.width * settings.height * (3 if settings.colour else 1) * (2 if half else 4)
    needed = raw / RENDER_COMPRESSION_ALLOWANCE
    parent = out.parent if str(out.parent) else Path(".")
    free = shutil.disk_usage(parent).free
    if needed > free:
        raise InputError(
            f"rendering {images} images of {settings.width}x{settings.height} into {out} needs about "
            f"{bytes_text(needed)} "
            f"but the disk has {bytes_text(free)} free; choose fewer lights, a smaller --size, --half, or another disk"
        )
    if not quiet and images * settings.width * settings.height > 2e8:
        logging.getLogger(__name__).info(f"render: {images} images of {settings.width}x{settings.height} (about "
                                         f"{bytes_text(needed)}); "
                                         "this takes a while")


def _run_info(args) -> int:
    from ..io.dataset import ReflectanceField
    from ..io.legacy_rti import is_legacy_rti, read_legacy_rti

    if args.dataset.is_file() and is_legacy_rti(args.dataset):
        model = read_legacy_rti(args.dataset)
        figures = {"format": model.source, "model": model.kind, "width": model.width, "height": model.height,
                   "coefficients_per_channel": int(model.coefficients.shape[2])}
        print(json.dumps(figures, indent=2) if args.json else
              f"{args.dataset}: {model.source} ({model.kind.upper()}), {model.width}x{model.height}, "
              f"{figures['coefficients_per_channel']} coefficients a channel; relight it with warp-highlights relight "
              f"{args.dataset.name} --light X,Y,Z -o OUT.png (no moving highlights: a classic RTI model)")
        return 0
    if args.dataset.is_file():
        from ..io.fieldfile import load_field

        field = load_field(args.dataset)
        print(json.dumps(field.report, indent=2) if args.json else field.describe())
        return 0

    field = ReflectanceField.load(args.dataset, heldout=args.heldout, linear=args.linear, progress=not args.quiet,
                                  max_pixels=pixel_limit(args))
    summary = field.summary()
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print("\n".join(format_summary(summary)))
    return 0


_SUMMARY_LABELS = {"elevation_deg": "elevation", "value_range": "values", "mean_value": "mean value",
                   "ground_truth": "ground truth",
                   "mask_pixels": "mask", "heldout_lights": "held-out lights"}
_SUMMARY_UNITS = {"elevation_deg": " deg", "mask_pixels": " pixels"}


def format_summary(summary: dict) -> list[str]:
    """``info``'s lines for people: labels in words, numbers to 4 significant digits, ranges as
    'a to b', nothing as 'none' (``--json`` gives the values as they are)."""
    def text(key, value) -> str:
        if value is None or value == []:
            return "none"
        unit = _SUMMARY_UNITS.get(key, "")
        if isinstance(value, float):
            return f"{value:.4g}{unit}"
        if isinstance(value, list) and len(value) == 2 and all(isinstance(v, (int, float)) for v in value):
            return f"{value[0]:.4g} to {value[1]:.4g}{unit}"
        if isinstance(value, list):
            return ", ".join(str(v) for v in value)
        return f"{value}{unit}"

    labels = {key: _SUMMARY_LABELS.get(key, key.replace("_", " ")) for key in summary}
    width = max(map(len, labels.values()))
    return [f"{labels[key]:>{width}}: {text(key, value)}" for key, value in summary.items()]


def _run_sheet(args) -> int:
    from ..io.dataset import ReflectanceField
    from ..view.preview import save_contact_sheet

    if args.output.suffix.lower() != ".png":
        raise InputError(f"contact sheet '{args.output}' must be a .png file")
    check_output_file(args.output, overwrite=args.overwrite, inputs=[args.dataset])
    field = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet,
                                  max_pixels=pixel_limit(args))
    path = save_contact_sheet(field, args.output, count=args.count, thumb_height=args.thumb_height)
    print(f"wrote {path}")
    return 0


COMMANDS = (
    Command("render", _render_arguments, _run_render, help="render a synthetic reflectance field with ground truth",
            description="Ray-trace a shape under many distant lights and write a dataset folder (images/, specular/, "
            "diffuse/, lights.lp, held-out ground truth, mask.png, meta.json)."),
    Command("info", _info_arguments, _run_info, help="check a dataset folder, or a field file, and summarise it"),
    Command("sheet", _sheet_arguments, _run_sheet,
            help="contact sheet PNG of a dataset: full, specular, diffuse per light"),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
