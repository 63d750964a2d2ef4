"""The ``relight``, ``animate`` and ``evaluate`` commands of ``warp-highlights`` (registered by ``cli.app``)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from ..io.images import IMAGE_EXTENSIONS
from ..model.errors import InputError
from .args import (
    Command,
    add_pixel_limit_option,
    check_device,
    check_not_capture_image,
    check_not_input,
    check_output_file,
    check_output_folder,
    in_range,
    parse_direction,
    pixel_limit,
    size_option,
    triple_option,
)

__all__ = ["COMMANDS", "parse_baselines", "print_evaluation_table", "write_evaluation"]

STAGE_BAR_PIXELS = 8_000_000
"""Output pixels from which one relit image shows a bar over its stages (preparing, relighting, writing): an 8 MP
image (3840 x 2160) takes a few seconds on a 2-core CPU (benchmarks/bench_relight_size.py)."""



def _relight_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("field", type=Path, help="highlight-field file (from warp-highlights fit), or an RTIViewer "
                        ".ptm or .rti file (relit with its own model)")
    parser.add_argument("--light", action="append", default=[], metavar="X,Y,Z",
                        help="light direction towards the light, camera space (x right, y up, z to the camera), e.g. "
                             "--light -0.5,0.2,1; repeatable")
    parser.add_argument("--lights", type=Path, metavar="FILE.lp",
                        help="also relight every direction of this light file (.lp, or relight's .dome or .relight)")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="image file (.exr linear; .png, .tif or .jpg sRGB) for one light; a folder for several "
                             "(EXR images + lights.lp)")
    parser.add_argument("--bits", choices=["auto", "8", "16"], default="auto",
                        help="bits per channel of a PNG or TIFF output (default auto: 16 where the field was fitted to "
                             "a capture of more than 8 bits)")
    _add_relight_options(parser)
    parser.add_argument("--overwrite", action="store_true", help="replace existing output")


def _animate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("field", type=Path, help="highlight-field file, or an RTIViewer .ptm or .rti file")
    parser.add_argument("--path", required=True,
                        help="light path, e.g. orbit:35, great:-1,0.2,1:1,0.2,1, list:lights.lp")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help=".gif, .webp (lossless), .apng, .mp4 (needs imageio-ffmpeg) or a folder of frames")
    parser.add_argument("--frames", type=in_range(int, 1, 100_000), default=96,
                        help="number of frames, 1..100000 (default 96)")
    parser.add_argument("--fps", type=in_range(float, 0.01, 1000.0), default=24.0,
                        help="frames per second, 0.01..1000 (default 24; GIF up to 50)")
    parser.add_argument("--compare", action="store_true",
                        help="show each method of --methods side by side in every frame")
    parser.add_argument("--methods", default="circular,alpha",
                        help="methods for --compare, comma-separated (default circular,alpha; alpha needs --dataset)")
    parser.add_argument("--exr", action="store_true", help="frames folder as linear EXR instead of PNG")
    _add_relight_options(parser, size_help="output WIDTHxHEIGHT of each panel, with the field's aspect ratio "
                                           "(default: the field's "
                         "size, at most 480 px on its longer side for GIF, WebP and APNG and 1920 px for MP4)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output")


def _evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("field", type=Path, help="highlight-field file")
    parser.add_argument("dataset", type=Path, help="the dataset folder the field was fitted to, with held-out lights")
    parser.add_argument("-o", "--output", type=Path,
                        help="output folder (default: FIELD's name + '-evaluation' beside it)")
    parser.add_argument("--heldout", type=Path,
                        help="folder with the held-out lights and images, if not inside DATASET")
    parser.add_argument("--methods", default="circular,straight,alpha",
                        help="comma-separated (default circular,straight,alpha)")
    parser.add_argument("--baselines", default="ptm,hsh2,hsh3,rbf",
                        help="classic RTI methods fitted to the same lights and scored on the full images, "
                             "comma-separated from "
                        "ptm, hsh2, hsh3, rbf, or 'none' (default ptm,hsh2,hsh3,rbf; RBF's sigma by leave-one-out)")
    parser.add_argument("--holdout-every", type=in_range(int, 2, 1000), metavar="K",
                        help="for a capture without held-out lights: hold out lights 0, K, 2K, ... of DATASET and "
                             "score them; FIELD "
                        "must be fitted to the rest (fit --holdout-every K); default: what FIELD was fitted with")
    parser.add_argument(
        "--triangle", default="auto",
        help="triangle for the PSNR-inside-a-triangle plot: a face index, 'auto' (the median one) or 'none'")
    parser.add_argument("--steps", type=in_range(int, 1, 100), default=10,
                        help="barycentric grid steps for that plot, 1..100 (default 10: 66 points)")
    parser.add_argument("--path", help="also score every frame of a light path (e.g. orbit:35, great:-1,0.2,1:1,0.2,1) "
                        "against ground truth rendered anew, with the motion of the highlights (ghosts, position, "
                        "flicker): datasets made by 'warp-highlights render' of a built-in shape")
    parser.add_argument("--frames", type=in_range(int, 2, 10_000), default=96,
                        help="frames along --path, 2..10000 (default 96)")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--linear", action="store_true", help="PNG/JPEG values are linear, not sRGB")
    _add_other_capture_option(parser, "DATASET")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    add_pixel_limit_option(parser)


def _add_relight_options(
        parser: argparse.ArgumentParser, *,
        size_help: str = "output WIDTHxHEIGHT with the field's aspect ratio (default: the field's size)") -> None:
    parser.add_argument("--method", choices=["circular", "straight", "alpha"], default="circular",
                        help="interpolation (default circular; alpha needs --dataset)")
    parser.add_argument("--size", type=size_option("output size"), help=size_help)
    parser.add_argument("--diffuse", choices=["auto", "residual", "lambert", "images", "none"], default="auto",
                        help="what the moved highlights are added to: residual transfer (the captured images minus "
                             "their own highlights, "
                        "blended), the Lambertian model, the blended diffuse images, or nothing (default auto: the "
                        "first the field stores)")
    parser.add_argument("--specular-only", action="store_true", help="write the highlights S' alone")
    parser.add_argument("--specular-colour", type=triple_option("specular colour"),
                        help="colour of the highlights R,G,B, each >= 0 (default 1,1,1: white light)")
    parser.add_argument("--dataset", type=Path, help="the dataset the field was fitted to (for --method alpha)")
    parser.add_argument("--linear", action="store_true", help="the dataset's PNG/JPEG values are linear, not sRGB")
    _add_other_capture_option(parser, "--dataset")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    add_pixel_limit_option(parser)


def _add_other_capture_option(parser: argparse.ArgumentParser, name: str) -> None:
    parser.add_argument("--other-capture", action="store_true",
                        help=f"use {name} though it differs from the capture the field was fitted to (light "
                             "directions, image names, sizes or pixels), e.g. the same capture re-encoded")


def check_same_capture(args, field, dataset, dataset_path) -> None:
    """Refuse, in one line, a dataset other than the capture ``field`` was fitted to (see
    ``io.dataset.capture_fingerprint``), unless ``--other-capture``; a field that records no capture passes."""
    from ..io.dataset import capture_differences, capture_fingerprint

    recorded = field.report.get("capture")
    if not isinstance(recorded, dict) or getattr(args, "other_capture", False):
        return
    differences = capture_differences(recorded, capture_fingerprint(dataset))
    if differences:
        raise InputError(f"{args.field} was fitted to another capture than {dataset_path}: {', '.join(differences)}; "
                         "pass the dataset it was fitted to, or --other-capture if this one holds the same images "
                         "(e.g. re-encoded)")


def _make_relighter(args, field, *, methods: tuple[str, ...], queries: int = 1):
    """A Relighter for the command's options, once the memory it and ``queries`` relit at a time take is
    known to be there; loads the dataset when a method needs it."""
    from ..model.memory import bytes_text, check_memory
    from ..relight.relighter import Relighter, alpha_inputs, default_queries, relight_bytes

    device = check_device(args.device)
    size = args.size
    width, height = size or (field.width, field.height)
    at_once = max(1, min(int(queries), default_queries(field, width, height)))
    needed = relight_bytes(field, width, height, queries=at_once, alpha="alpha" in methods)
    check_memory(needed, f"relighting at {width}x{height}", "use a smaller --size",
                 detail=f"the field's arrays, {at_once} image{'s' if at_once > 1 else ''} at a time and the writing; "
                        f"{bytes_text(needed)} in all")
    colour = args.specular_colour or (1.0, 1.0, 1.0)
    alpha_specular = alpha_images = None
    if "alpha" in methods:
        if args.dataset is None:
            raise InputError("--method alpha blends the captured images: pass --dataset DATASET (the folder the "
                             "field was fitted to)")
        from ..io.dataset import ReflectanceField

        dataset = ReflectanceField.load(args.dataset, linear=args.linear, progress=not args.quiet,
                                        max_pixels=pixel_limit(args))
        check_same_capture(args, field, dataset, args.dataset)
        alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
    exposure = field.exposure
    return Relighter(
        field, device=device, size=size, diffuse=args.diffuse, specular_colour=colour, scale=1.0 / exposure,
        alpha_specular=alpha_specular, alpha_images=alpha_images,
    )


def _output_image(relit, index: int | None, *, specular_only: bool, exposure: float) -> np.ndarray:
    """The image to write: I' (dataset units) or S' (brought back to the dataset's units too); ``index`` picks
    one of a batch, None takes a single query's images."""
    pick = (lambda array: array) if index is None else (lambda array: array[index])
    if specular_only or relit.full is None:
        return pick(relit.specular) / exposure
    image = pick(relit.full)
    return image[..., 0] if image.shape[-1] == 1 else image


NO_LIGHT = "give at least one light: --light X,Y,Z (towards the light, e.g. --light 0.3,0.5,1) or --lights FILE.lp"
HELDOUT_OR_HOLDOUT = "give either --heldout FOLDER or --holdout-every K, not both"


def _run_relight(args) -> int:
    from ..io.fieldfile import load_field
    from ..io.legacy_rti import is_legacy_rti
    from ..io.lightfile import read_lights

    directions = [parse_direction(text) for text in args.light]
    if args.lights is not None:
        directions += list(read_lights(args.lights, check_files=False).directions)
    if not directions:
        raise InputError(NO_LIGHT)
    output = Path(args.output)
    inputs = [args.field, args.lights, args.dataset]
    several = len(directions) > 1
    if several and output.suffix.lower() in IMAGE_EXTENSIONS:
        raise InputError(
            f"{len(directions)} lights make {len(directions)} images: give -o a folder name, not {output.name}")
    if not several and output.suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(f"output {output} needs an image suffix: .exr (linear radiance), .png, .tif or .jpg (sRGB)")
    if several and args.bits != "auto":
        raise InputError(f"--bits {args.bits} is for one PNG or TIFF image; {len(directions)} lights make a folder of "
                         f"EXR images (floats)")
    if several:
        check_output_folder(output, overwrite=args.overwrite, legacy=_relit_folder_entry, kind="relit images",
                            inputs=inputs)
    else:
        check_output_file(output, overwrite=args.overwrite, inputs=inputs)
    if is_legacy_rti(args.field):
        return _relight_legacy(args, np.asarray(directions, dtype=np.float64), output, several)
    if not several:
        return _relight_one(args, directions[0], output)
    field = load_field(args.field)
    relighter = _make_relighter(args, field, methods=(args.method,), queries=len(directions))
    exposure = field.exposure
    started = time.perf_counter()
    moved = _write_image_folder(output, relighter, np.asarray(directions, dtype=np.float64), method=args.method,
                                specular_only=args.specular_only, exposure=exposure, overwrite=args.overwrite,
                                progress=not args.quiet)
    seconds = time.perf_counter() - started
    print(f"wrote {len(directions)} images and lights.lp to {output} ({relighter.width}x{relighter.height}, "
          f"{args.method}, "
          f"{1000 * seconds / len(directions):.2f} ms per light with writing)")
    if moved:
        _warn_outside_many(f"{moved} of {len(directions)} lights {'lies' if moved == 1 else 'lie'}")
    return 0


def _relight_one(args, direction, output: Path) -> int:
    """``relight`` of one light into one image; the time printed is the command's, from loading the field to the
    image written, with a bar over the stages for a large image."""
    from tqdm import tqdm

    from ..io.fieldfile import load_field
    from ..io.images import write_image

    started = time.perf_counter()
    pixels = args.size[0] * args.size[1] if args.size else 0
    with tqdm(total=3, desc="relight: preparing", unit="stage", leave=False,
              disable=args.quiet or pixels < STAGE_BAR_PIXELS) as bar:
        field = load_field(args.field)
        relighter = _make_relighter(args, field, methods=(args.method,))
        bar.update()
        bar.set_description("relight: relighting")
        relit_at = time.perf_counter()
        relit = relighter.relight(np.asarray(direction, dtype=np.float64), method=args.method,
                                  full=not args.specular_only)
        bar.update()
        bar.set_description("relight: writing")
        written_at = time.perf_counter()
        write_image(output, _output_image(relit, None, specular_only=args.specular_only, exposure=field.exposure),
                    bits=_output_bits(args, field, output))
        bar.update()
    done = time.perf_counter()
    clamped = " (outside the dome: moved onto its rim)" if relit.clamped else ""
    print(f"wrote {output} ({relighter.width}x{relighter.height}, {args.method}, {done - started:.2f} s: relit in "
          f"{1000 * (written_at - relit_at):.1f} ms, written in {1000 * (done - written_at):.1f} ms){clamped}")
    if relit.clamped:
        _warn_outside_one(field, direction)
    return 0


def _direction_text(direction) -> str:
    """A unit direction as x,y,z rounded to 3 decimals (no negative zero)."""
    return ",".join(f"{round(float(v), 3) + 0.0:.3f}" for v in direction)


def _warn_outside_one(field, direction) -> None:
    """One warning line: ``direction`` lies outside the captured lights and was relit on the dome's rim."""
    location = field.triangulation.locate(np.asarray(direction, dtype=np.float64))
    given = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    logging.getLogger(__name__).warning(
        f"warning: the light {_direction_text(given)} lies outside the captured lights: moved onto the dome's rim, to "
        f"{_direction_text(location.directions)} (x,y,z); the image is that of the nearest captured direction on the "
        "rim")


def _warn_outside_many(text: str) -> None:
    """One warning line: ``text`` (how many lights or frames lay outside the captured lights), how they were relit."""
    logging.getLogger(__name__).warning(f"warning: {text} outside the captured lights: moved onto the dome's rim, "
                                        "relit as the nearest captured directions on the rim")


def _output_bits(args, field, output: Path) -> int:
    """``--bits`` for this output: 16 or 8 for PNG/TIFF (auto: 16 after a capture of more than 8 bits), else 8."""
    if output.suffix.lower() not in (".png", ".tif", ".tiff"):
        if args.bits == "16":
            raise InputError(f"--bits 16 is for PNG and TIFF outputs; {output.name} is {output.suffix} (EXR keeps "
                             f"floats, JPEG has 8 bits)")
        return 8
    if args.bits != "auto":
        return int(args.bits)
    source = (field.report or {}).get("input") or {}
    return 16 if int(source.get("bits", 8)) > 8 else 8


def _relight_legacy(args, directions: np.ndarray, output: Path, several: bool) -> int:
    """``relight`` of an RTIViewer ``.ptm`` or ``.rti`` file, with its own model: one image, or a folder of
    relit_NNNN.exr and lights.lp."""
    from ..io.atomic import atomic_folder
    from ..io.images import srgb_to_linear, write_image
    from ..io.legacy_rti import read_legacy_rti
    from ..io.lightfile import write_lp
    from ..io.resample import resize_stack, working_size
    from ..model.lights import LightSet
    from ..relight.legacy import relight_legacy

    _check_legacy_options(args)
    model = read_legacy_rti(args.field)
    images = srgb_to_linear(relight_legacy(model, directions))
    if args.size is not None:
        images = resize_stack(images, *working_size(model.width, model.height, args.size))
    if not several:
        write_image(output, images[0], **({"bits": int(args.bits)} if args.bits != "auto" else {}))
        print(f"wrote {output} ({images.shape[2]}x{images.shape[1]}, {model.source} of {args.field})")
        return 0
    digits = max(4, len(str(len(directions) - 1)))
    names = [f"relit_{i:0{digits}d}.exr" for i in range(len(directions))]
    with atomic_folder(output, kind="relit images", overwrite=args.overwrite, legacy=_relit_folder_entry) as temporary:
        for name, image in zip(names, images):
            write_image(temporary / name, image)
        write_lp(LightSet(directions), temporary / "lights.lp", filenames=names)
    print(f"wrote {len(directions)} images and lights.lp to {output} ({model.source} of {args.field})")
    return 0


def _relit_folder_entry(relative: str) -> bool:
    """A file of a relit-images folder (how one written before manifests existed is recognised)."""
    return (relative == "lights.lp"
            or (relative.startswith("relit_") and relative.endswith(".exr") and "/" not in relative))


def _write_image_folder(folder: Path, relighter, directions: np.ndarray, *, method: str, specular_only: bool,
                        exposure: float,
                        overwrite: bool, progress: bool) -> int:
    """Images relit_0000.exr ... and a lights.lp naming them: the folder is a dataset itself. Relit in
    batches of ``relighter.max_batch``, so memory stays bounded whatever the number of lights. Returns how
    many directions lay outside the captured lights (relit on the dome's rim)."""
    from tqdm import tqdm

    from ..io.atomic import atomic_folder
    from ..io.images import write_image
    from ..io.lightfile import write_lp
    from ..model.lights import LightSet

    with atomic_folder(folder, kind="relit images", overwrite=overwrite, legacy=_relit_folder_entry) as temporary, tqdm(
        total=len(directions), unit="light", desc="relight", disable=not progress, leave=False
    ) as bar:
        digits = max(4, len(str(len(directions) - 1)))
        names = [f"relit_{i:0{digits}d}.exr" for i in range(len(directions))]
        moved = 0
        for start in range(0, len(directions), relighter.max_batch):
            chunk = directions[start : start + relighter.max_batch]
            relit = relighter.relight(chunk, method=method, full=not specular_only)
            moved += int(np.count_nonzero(relit.clamped))
            for i in range(len(chunk)):
                write_image(temporary / names[start + i],
                            _output_image(relit, i, specular_only=specular_only, exposure=exposure))
            bar.update(len(chunk))
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        write_lp(LightSet(unit), temporary / "lights.lp", filenames=names)
    return moved


def _parse_methods(text: str) -> tuple[str, ...]:
    from ..relight.relighter import RELIGHT_METHODS

    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    unknown = [m for m in methods if m not in RELIGHT_METHODS]
    if not methods or unknown:
        raise InputError(f"methods '{text}': use a comma-separated list of {', '.join(RELIGHT_METHODS)}")
    return methods


def _run_animate(args) -> int:
    from ..io.fieldfile import load_field
    from ..io.legacy_rti import is_legacy_rti
    from ..view.animation import check_animation_output, default_animation_size, write_animation
    from ..view.light_paths import parse_light_path

    frames_format = "exr" if args.exr else "png"
    check_not_input(args.output, [args.field, args.dataset])
    if args.overwrite:
        check_not_capture_image(args.output)
    kind = check_animation_output(args.output, overwrite=args.overwrite, frames_format=frames_format)
    directions = parse_light_path(args.path, args.frames)
    if is_legacy_rti(args.field):
        return _animate_legacy(args, kind, directions, frames_format)
    methods = _parse_methods(args.methods) if args.compare else (args.method,)
    field = load_field(args.field)
    if args.size is None:
        args.size = default_animation_size(kind, field.width, field.height)
        if args.size != (field.width, field.height):
            logging.getLogger(__name__).info(f"animating at {args.size[0]}x{args.size[1]}, the {kind.upper()} default "
                                             f"(the field is {field.width}x{field.height}; --size sets another)")
    relighter = _make_relighter(args, field, methods=methods, queries=len(directions))
    exposure = field.exposure

    moved = 0

    def frames():
        nonlocal moved
        for start in range(0, len(directions), relighter.max_batch):
            chunk = directions[start : start + relighter.max_batch]
            panels = [relighter.relight(chunk, method=m, full=not args.specular_only) for m in methods]
            moved += int(np.count_nonzero(panels[0].clamped))
            for i in range(len(chunk)):
                images = [_output_image(p, i, specular_only=args.specular_only, exposure=exposure) for p in panels]
                yield np.concatenate(images, axis=1)

    from tqdm import tqdm

    started = time.perf_counter()
    with tqdm(total=len(directions), unit="frame", desc="animate", disable=args.quiet, leave=False) as bar:
        path = write_animation(frames(), args.output, fps=args.fps, frame_count=len(directions),
                               overwrite=args.overwrite,
                               progress=lambda done: bar.update(done - bar.n), frames_format=frames_format)
    label = " | ".join(methods)
    print(f"wrote {path}: {len(directions)} frames of {label}, {relighter.width}x{relighter.height}, "
          f"{time.perf_counter() - started:.1f} s")
    if moved:
        _warn_outside_many(f"the light of {moved} of {len(directions)} frames lies")
    return 0


def _check_legacy_options(args) -> None:
    """Refuse the options that a field's highlights or residual take and a .ptm or .rti file has no part for."""
    given = [name for name, value, default in (("--method", args.method, "circular"),
                                               ("--diffuse", args.diffuse, "auto"),
                                               ("--specular-only", args.specular_only, False),
                                               ("--specular-colour", args.specular_colour, None),
                                               ("--dataset", args.dataset, None)) if value != default]
    if given:
        raise InputError(f"{args.field} holds one classic RTI model, relit as it is: leave out {', '.join(given)} "
                         "(they choose among a field's highlights and residual)")


def _animate_legacy(args, kind: str, directions: np.ndarray, frames_format: str) -> int:
    """``animate`` of an RTIViewer ``.ptm`` or ``.rti`` file, relit with its own model (no moving highlights)."""
    from tqdm import tqdm

    from ..io.images import srgb_to_linear
    from ..io.legacy_rti import read_legacy_rti
    from ..io.resample import resize_stack, working_size
    from ..relight.legacy import relight_legacy
    from ..view.animation import default_animation_size, write_animation

    if args.compare:
        raise InputError(f"{args.field} holds one classic RTI model: it animates alone (leave out --compare)")
    _check_legacy_options(args)
    model = read_legacy_rti(args.field)
    size = working_size(model.width, model.height, args.size or default_animation_size(kind, model.width,
                                                                                       model.height))

    def frames():
        for direction in directions:
            image = srgb_to_linear(relight_legacy(model, direction[None]))
            yield resize_stack(image, *size)[0] if size != (model.width, model.height) else image[0]

    started = time.perf_counter()
    with tqdm(total=len(directions), unit="frame", desc="animate", disable=args.quiet, leave=False) as bar:
        path = write_animation(frames(), args.output, fps=args.fps, frame_count=len(directions),
                               overwrite=args.overwrite,
                               progress=lambda done: bar.update(done - bar.n), frames_format=frames_format)
    print(f"wrote {path}: {len(directions)} frames of the {model.source} in {args.field}, {size[0]}x{size[1]}, "
          f"{time.perf_counter() - started:.1f} s")
    return 0


def _triangle_choice(text: str) -> int | str:
    """--triangle: a face index, "auto" or "none"."""
    triangle = text.strip().lower()
    if triangle in ("auto", "none"):
        return triangle
    try:
        return int(triangle)
    except ValueError:
        raise InputError(f"--triangle '{text}' must be a face index, 'auto' or 'none'") from None


def _check_evaluate(args) -> None:
    _triangle_choice(args.triangle)
    if args.holdout_every and args.heldout:
        raise InputError(HELDOUT_OR_HOLDOUT)


def _check_relight(args) -> None:
    if not args.light and args.lights is None:
        raise InputError(NO_LIGHT)


def _check_animate(args) -> None:
    from ..view.animation import animation_kind
    from ..view.light_paths import parse_light_path

    kind = animation_kind(args.output)  # an unknown suffix is refused
    if args.exr and kind != "frames":
        raise InputError(f"{args.output}: --exr writes a folder of EXR frames; give a folder name")
    parse_light_path(args.path, args.frames)
    if args.compare and args.dataset is None and "alpha" in (m.strip() for m in args.methods.split(",")):
        raise InputError(f"--compare shows each method of --methods ({args.methods}), and alpha blends the captured "
                         "images: pass --dataset DATASET (the folder the field was fitted to), or --methods without "
                         "alpha, e.g. --methods circular,straight")


def _run_evaluate(args) -> int:
    from ..io.dataset import ReflectanceField, find_heldout_folder
    from ..io.fieldfile import load_field
    from ..quality.metrics import scoring_processes
    from ..relight.evaluation import evaluate_field

    methods = _parse_methods(args.methods)
    triangle = _triangle_choice(args.triangle)
    output = Path(args.output) if args.output else Path(args.field).with_name(Path(args.field).stem + "-evaluation")
    found = find_heldout_folder(args.dataset) if args.heldout is None else None
    check_output_folder(output, overwrite=args.overwrite, legacy=evaluation_folder_entry, kind="evaluation",
                        inputs=[args.field, args.dataset, args.heldout or found])
    device = check_device(args.device)
    field = load_field(args.field)
    if isinstance(triangle, int) and not 0 <= triangle < field.triangulation.face_count:
        raise InputError(f"--triangle {triangle} does not exist: the field's triangulation has faces "
                         f"0..{field.triangulation.face_count - 1}")
    baselines = parse_baselines(args.baselines)
    fitted_every = field.report.get("holdout_every")
    # with --heldout: refused by _check_evaluate
    holdout_every = args.holdout_every or fitted_every
    heldout = args.heldout or (None if holdout_every else _found_heldout(args, found))
    dataset = ReflectanceField.load(args.dataset, heldout=heldout, linear=args.linear, progress=not args.quiet,
                                    max_pixels=pixel_limit(args))
    check_same_capture(args, field, dataset, args.dataset)
    _check_holdout_every(args, field, dataset, fitted_every)
    if args.holdout_every or (holdout_every and dataset.light_count != field.light_count):
        dataset = dataset.split_every(int(holdout_every))
    path = renderer = None
    if args.path:
        from ..relight.path_scores import path_renderer
        from ..view.light_paths import parse_light_path

        path = parse_light_path(args.path, args.frames)
        renderer = path_renderer(dataset, device)  # refused in one line before any work where there is none
    with scoring_processes():  # every method's scores in the same few worker processes
        evaluation = evaluate_field(field, dataset, device=device, methods=methods,
                                    barycentric_face=None if triangle == "none" else triangle,
                                    # its steps reach stderr through the logger
                                    barycentric_steps=args.steps, baselines=baselines)
        if path is not None:
            from ..relight.path_scores import score_path

            path_scores = score_path(field, dataset, path, methods=[m for m in methods if m != "straight"] or methods,
                                     device=device, renderer=renderer)
    report = evaluation.to_dict()
    report["field"] = str(args.field)
    report["dataset"] = str(args.dataset)
    if path is not None:
        report["path"] = {"spec": args.path, **path_scores}
    written = write_evaluation(output, evaluation, report, overwrite=args.overwrite, title=Path(args.field).stem)
    print_evaluation_table(report)
    if path is not None:
        print_path_table(report["path"])
    print(f"wrote {output}: " + ", ".join(written))
    return 0


def _found_heldout(args, found: Path | None) -> Path | None:
    """The held-out folder ``evaluate`` uses without ``--heldout`` or a hold-out protocol: ``found`` (a ``Test/``
    beside or inside DATASET, said in one line), else None where DATASET holds ``heldout.lp``; ``InputError``
    naming the options that give held-out lights where it holds none."""
    from ..io.dataset import HELDOUT_FOLDER

    dataset = Path(args.dataset)
    if found is not None:
        where = "inside" if found.parent == Path(os.path.abspath(dataset)) else "beside"
        logging.getLogger(__name__).info(f"held-out lights from {found} (the {HELDOUT_FOLDER}/ folder {where} "
                                         f"{dataset}; --heldout FOLDER takes another)")
        return found
    if dataset.is_dir() and not (dataset / "heldout.lp").is_file():
        raise InputError(f"{dataset} has no held-out lights (no heldout.lp, no {HELDOUT_FOLDER}/ folder inside or "
                         f"beside it): pass --heldout FOLDER (other lights of the same capture, with their images), "
                         f"or --holdout-every K to score lights 0, K, 2K, ... with a field fitted without them "
                         f"('fit {dataset} --holdout-every K -o FIELD')")
    return None  # heldout.lp, or a missing folder that loading reports


def _check_holdout_every(args, field, dataset, fitted_every) -> None:
    """Refuse, in one line, ``--holdout-every K`` with a field that was not fitted without those lights."""
    every = args.holdout_every
    if not every:
        return
    if fitted_every and int(fitted_every) != every:
        raise InputError(f"{args.field} was fitted with --holdout-every {fitted_every}: evaluate it with "
                         f"--holdout-every {fitted_every} (or without the option, which takes the field's)")
    if not fitted_every and dataset.light_count == field.light_count:
        raise InputError(f"{args.field} was fitted to every light of {args.dataset} ({field.light_count}), so none "
                         f"is held out: refit with 'fit {args.dataset} --holdout-every {every} -o FIELD' to score it "
                         "at held-out lights (or, where the capture has held-out lights, evaluate it without "
                         "--holdout-every: a Test/ folder or --heldout FOLDER)")


def parse_baselines(text: str) -> tuple[str, ...]:
    from ..relight.baselines import BASELINE_METHODS

    if text.strip().lower() == "none":
        return ()
    names = tuple(dict.fromkeys(part.strip().lower() for part in text.split(",") if part.strip()))
    unknown = [name for name in names if name not in BASELINE_METHODS]
    if unknown or not names:
        raise InputError(f"--baselines '{text}': choose from {', '.join(BASELINE_METHODS)}, comma-separated, or 'none'")
    return names


def evaluation_folder_entry(relative: str) -> bool:
    """What ``write_evaluation`` writes: report.json and PNG plots (how a folder written before
    manifests existed is recognised)."""
    return "/" not in relative and (relative == "report.json" or relative.endswith(".png"))


_ADDED_TO_WORDS = {"residual": "residual", "images": "diffuse images", "lambert": "Lambertian diffuse"}
"""How a figure names what the full image adds the highlights to (``evaluation.highlights_added_to``)."""


def write_evaluation(folder: Path, evaluation, report: dict, *, overwrite: bool, title: str) -> list[str]:
    """report.json and the plots into ``folder`` (written beside it, then swapped in); returns the file names."""
    from ..io.atomic import atomic_folder
    from ..view import plots

    added_to = evaluation.info.get("highlights_added_to")
    base = _ADDED_TO_WORDS.get(added_to, "diffuse model")
    kept = evaluation.gaussians_per_light is not None and bool(np.any(evaluation.gaussians_per_light > 0))
    moving = kept and evaluation.info.get("moving_gaussians", 1) > 0
    with atomic_folder(folder, kind="evaluation", overwrite=overwrite, legacy=evaluation_folder_entry) as temporary:
        for kind, scores in (("specular", evaluation.specular_psnr), ("full", evaluation.full_psnr)):
            if scores:
                excluded = max(int(np.isnan(v).sum()) for v in scores.values())
                what = "specular highlights S'" if kind == "specular" else f"full images I' = {base} + highlights"
                plots.plot_psnr_distributions(
                    scores, temporary / f"psnr-{kind}.png",
                    title=f"{title}: PSNR of the {what} at {len(evaluation.directions)} held-out lights",
                    excluded=excluded, notes=_method_notes(scores, kind, base=base, kept=kept, moving=moving))
        scores = evaluation.specular_psnr or evaluation.full_psnr
        if "circular" in scores and "alpha" in scores:
            plots.plot_psnr_pairs(scores["circular"], scores["alpha"], temporary / "psnr-circular-vs-alpha.png",
                                  title=f"{title}: per held-out light")
        if evaluation.gaussians_per_light is not None:
            where = ("every light's highlights are in the residual" if added_to == "residual"
                     else "the relit images have no highlights")
            plots.plot_gaussian_counts(evaluation.gaussians_per_light, temporary / "gaussian-counts.png",
                                       per_query=evaluation.gaussians_per_query, title=f"{title}: Gaussians",
                                       none_kept=f"no Gaussians kept: {where}")
        sweep = evaluation.barycentric_sweep
        if sweep is not None and "skipped" not in sweep:
            labels = tuple(f"light {v}" for v in sweep["vertices"])
            plots.plot_barycentric_psnr(sweep["weights"], sweep["specular_psnr"], temporary / "barycentric-psnr.png",
                                        corner_labels=labels,
                                        title=f"{title}: PSNR inside triangle {sweep['face']}")
        if evaluation.examples and len(evaluation.example_queries):
            order = [k for k in ("truth", "circular", "straight", "alpha") if k in evaluation.examples]
            images, labels, notes = [], [], []
            for row, query in enumerate(evaluation.example_queries):
                for key in order:
                    images.append(evaluation.examples[key][row])
                    score = ("" if key == "truth" or key not in evaluation.specular_psnr
                             else f" {evaluation.specular_psnr[key][query]:.1f} dB")
                    labels.append(f"#{query} {key}{score}")
                    notes.append(_blank_example_note(key, images[-1], kept=kept, added_to=added_to))
            plots.plot_image_grid(images, labels, temporary / "examples.png", columns=len(order),
                                  title=f"{title}: specular highlights S' at held-out lights", blank_notes=notes)
        if (evaluation.full_examples and evaluation.full_example_queries is not None
            and len(evaluation.full_example_queries)):
            order = ["truth"] + [k for k in evaluation.full_examples if k != "truth"]
            images, labels = [], []
            for row, query in enumerate(evaluation.full_example_queries):
                for key in order:
                    images.append(evaluation.full_examples[key][row])
                    score = "" if key == "truth" else f"{evaluation.full_srgb_psnr[key][query]:.1f} dB"
                    labels.append(f"#{query} {key}\n{score}")
            plots.plot_image_grid(images, labels, temporary / "worst-lights.png", columns=len(order),
                                  title=f"{title}: full images at the worst held-out lights (8-bit sRGB PSNR)")
        (temporary / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False))
        names = sorted(p.name for p in temporary.iterdir())
    return names


def _method_notes(scores: dict, kind: str, *, base: str, kept: bool, moving: bool) -> list[str]:
    """Footnote lines of a PSNR figure: what each method's images are."""
    from ..relight.baselines import BASELINE_METHODS

    gaussian = [m for m in ("circular", "straight") if m in scores]
    baselines = [m for m in scores if m in BASELINE_METHODS]
    notes = []
    if gaussian:
        moved = "circular or straight paths" if len(gaussian) == 2 else f"{gaussian[0]} paths"
        if kept:
            what = "the highlights" if kind == "specular" else f"the blended {base} plus the highlights"
            what += (f", the Gaussians moved along {moved}" if moving
                     else ", the corner lights' Gaussians drawn in place (none of them moves)")
        else:
            where = ": its highlights are in the residual" if base == "residual" else ""
            what = "no highlights" if kind == "specular" else f"the blended {base} alone"
            what += f" (the field keeps no Gaussians{where})"
        notes.append(f"{', '.join(gaussian)}: {what}.")
    if "alpha" in scores:
        blended = "captured images" if kind == "full" else "specular images"
        notes.append(f"alpha: the barycentric blend of the three corner lights' {blended}.")
    if baselines:
        notes.append(f"{', '.join(baselines)}: classic RTI models fitted to the same training lights.")
    return notes


def _blank_example_note(key: str, image: np.ndarray, *, kept: bool, added_to: str | None) -> str:
    """What a panel of examples.png says when its S' would show as one flat value."""
    peak = float(np.nanmax(image)) if np.size(image) else 0.0
    level = "S' = 0 everywhere" if not peak > 0 else f"S' at most {peak:.1g}, under one display step"
    if key in ("circular", "straight"):
        if not kept:
            where = "; its highlights stay in the residual" if added_to == "residual" else ""
            return f"the field moves no highlights: it keeps no Gaussians{where}"
        return f"no highlight at this light ({level})"
    if key == "alpha":
        return f"no highlight in the three corner lights' specular images here ({level})"
    return f"no highlight in the ground truth at this light ({level})"


def print_path_table(scores: dict) -> None:
    """``evaluate --path``'s scores as a Markdown table on stdout (means over the frames)."""
    print(f"along {scores['spec']} ({scores['frames']} frames, ground truth rendered anew):")
    print("| method | 8-bit sRGB PSNR | SSIM | ghost share | visible ghost share | position error (rpx) | "
          "flicker (8-bit levels) |")
    print("|---|---|---|---|---|---|---|")
    names = ("psnr_db", "ssim", "ghost_share", "visible_ghost_share", "position_error_rpx", "flicker_levels")
    for method, values in scores.items():
        if isinstance(values, dict):
            cells = ["n/a" if values[k]["mean"] is None else f"{values[k]['mean']:.{3 if k == 'ssim' else 2}f}"
                     for k in names]
            print(f"| {method} | " + " | ".join(cells) + " |")


def print_evaluation_table(report: dict) -> None:
    """The summary as a Markdown table on stdout."""
    summary = report["summary"]
    where = f"at {report['heldout']} held-out lights, {report['size'][0]}x{report['size'][1]}"
    for kind in ("specular", "full"):
        part = summary.get(kind)
        if not part:
            continue
        methods = report["methods"] + (report.get("baselines") or []) if kind == "full" else report["methods"]
        srgb, ssim = summary.get("full_srgb", {}), summary.get("full_ssim", {})
        extra = kind == "full" and bool(srgb)
        print(f"{kind} {'image' if kind == 'full' else 'highlights'} {where}:")
        print("| method | linear PSNR mean | p5 | p95 |"
              + (" 8-bit sRGB PSNR mean | worst | SSIM mean | worst |" if extra else ""))
        print("|---|---|---|---|" + ("---|---|---|---|" if extra else ""))
        for method in methods:
            s = part.get(method)
            if s and s["mean"] is not None:
                row = f"| {method} | {s['mean']:.2f} | {s['p5']:.2f} | {s['p95']:.2f} |"
                if extra and method in srgb:
                    row += (f" {srgb[method]['mean']:.2f} | {srgb[method]['min']:.2f} | {ssim[method]['mean']:.3f} | "
                            f"{ssim[method]['min']:.3f} |")
                print(row)
        share = part.get("circular_beats_alpha")
        if share is not None:
            print(f"circular beats alpha on {100 * share:.0f}% of the held-out lights")
    if report.get("baselines_left_out"):
        print(f"left out (more coefficients than the {report['lights']} lights): "
              f"{', '.join(report['baselines_left_out'])}")
    gaussians = report["gaussians"]["per_light"]
    print(f"Gaussians per light: mean {gaussians['mean']:.1f}, max {gaussians['max']}")


COMMANDS = (
    Command("relight", _relight_arguments, _run_relight, help="render a fitted field for one or more light directions",
            description="Relight a highlight field: locate each light direction in the triangulation, "
                        "move the Gaussians "
            "along their paths, rasterize the highlights and add them to the blended residual (the captured images "
            "minus their own highlights).",
            check=_check_relight),
    Command("animate", _animate_arguments, _run_animate,
            help="render a fitted field along a light path: GIF, WebP, APNG, MP4 or a folder of frames",
            description="Move the light along a path and write the relit frames. Paths: "
                        "great:X,Y,Z:X,Y,Z (great circle "
            "between two directions), orbit:ELEVATION[:START_AZIMUTH] (degrees; a full turn at that elevation), "
            "list:FILE (a .lp or x y z text file, visited in order).", check=_check_animate),
    Command("evaluate", _evaluate_arguments, _run_evaluate,
            help="score a fitted field against held-out ground truth: JSON report and plots",
            description="Relight the field at every held-out light of the dataset (the triangle centroids for rendered "
            "data) with the circular, straight and alpha-blend methods and compare with the ground truth (PSNR, "
            "peak 1). Writes report.json and PNG plots into the output folder.", check=_check_evaluate),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
