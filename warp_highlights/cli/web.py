"""``warp-highlights export`` and ``serve``: a fitted field as a static web page (or a capture in relight's web layout,
for OpenLIME), and serving it locally."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..model.errors import InputError
from .args import (
    Command,
    add_pixel_limit_option,
    check_output_file,
    check_output_folder,
    in_range,
    pixel_limit,
    size_option,
)

__all__ = ["COMMANDS"]

PAGE_SUFFIXES = (".html", ".htm")
"""The file endings ``export --single-file`` takes for its page (a name without one gets ``.html``)."""
OPENLIME_MODELS = ("ptm", "hsh", "rbf", "neural")
"""``export --format openlime --model``'s choices: ``web.openlime.OPENLIME_MODELS`` and the learned residual's
neural layer (named here so that the parser is built without NumPy or Pillow)."""


def _export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("field", type=Path, help="highlight-field file (from warp-highlights fit); with --format "
                        "openlime, a capture folder (a light file and its images), a .ptm or .rti file, or with "
                        "--model neural a learned field; with --format ptm or rti, a capture folder")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output folder (index.html, viewer.js, manifest.json and the field's arrays; with "
                             "--format openlime info.json and the planes), or with --single-file the HTML file "
                             "(.html is added to a name without a suffix), or with --format ptm or rti the file")
    parser.add_argument("--format", choices=("page", "openlime", "ptm", "rti"), default="page",
                        help="page: this project's viewer of the field, moving highlights included (default); "
                             "openlime: relight's web layout (info.json and plane_N.jpg) that OpenLIME opens, a "
                             "classic RTI model of the capture (--model); ptm, rti: the capture's PTM or HSH (order 3) "
                             "as a file for RTIViewer (-o FILE.ptm or FILE.rti)")
    parser.add_argument("--model", choices=OPENLIME_MODELS, default=None,
                        help="with --format openlime: a capture's ptm (18 planes), hsh (order 3, 27 planes, the "
                             "default) or rbf (18 principal components, interpolated over the lights); or a learned "
                             "field's neural layer (its codes and a decoder of OpenLIME's shape distilled from its); "
                             "a .ptm or .rti file goes as the model it holds")
    parser.add_argument("--seconds", type=float, default=120.0,
                        help="with --model neural: the distillation's time, seconds; longer comes closer to the "
                             "field's images (default: %(default)s)")
    parser.add_argument("--size", type=size_option("export size"),
                        help="with --format openlime, ptm or rti and a capture: WIDTHxHEIGHT, same aspect ratio, at "
                             "most the images' size (default: the images' size)")
    parser.add_argument("--linear", action="store_true",
                        help="with --format openlime, ptm or rti and a capture: its PNG/JPEG values are linear")
    add_pixel_limit_option(parser)
    parser.add_argument("--single-file", action="store_true",
                        help="write one self-contained HTML file that opens from disk, for e-mail (at most 15 MiB: "
                             "mail services cap a "
                        "message at 20-25 MB and mailing adds a third)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output written by warp-highlights")


def _viewer_entry(relative: str) -> bool:
    """A file of an exported viewer (how one written before manifests existed is recognised)."""
    return "/" not in relative and relative.endswith((".bin", ".bin.gz", ".html", ".js", ".json"))


def _run_export(args) -> int:
    from ..io.atomic import atomic_file, atomic_folder
    from ..io.fieldfile import load_field
    from ..model.memory import bytes_text
    from ..web.export import export_viewer, single_file_page

    output = Path(args.output)
    if args.format == "openlime":
        return _export_openlime(args, output)
    if args.format in ("ptm", "rti"):
        return _export_legacy(args, output)
    if args.single_file:
        added = not output.suffix
        if added:
            output = output.with_name(output.name + ".html")
        check_output_file(output, overwrite=args.overwrite, inputs=[args.field])
        field = load_field(args.field)
        page = single_file_page(field)
        with atomic_file(output, overwrite=args.overwrite) as temporary:
            temporary.write_bytes(page)
        note = f"; .html added to {args.output}" if added else ""
        print(f"wrote the viewer of {args.field} to {output} ({bytes_text(len(page))}, one file: open it in a "
              f"browser{note})")
        return 0
    check_output_folder(output, overwrite=args.overwrite, legacy=_viewer_entry, kind="web viewer",
                        inputs=[args.field])
    field = load_field(args.field)
    with atomic_folder(output, kind="web viewer", overwrite=args.overwrite, legacy=_viewer_entry) as temporary:
        export_viewer(field, temporary)
        size = sum(p.stat().st_size for p in temporary.iterdir())
    print(f"wrote the viewer of {args.field} to {output} ({bytes_text(size)}; the field file: "
          f"{bytes_text(Path(args.field).stat().st_size)}); "
          f"open it with: warp-highlights serve {output}")
    return 0


def _openlime_entry(relative: str) -> bool:
    """A file of an OpenLIME export (how one written before manifests existed is recognised)."""
    return relative == "info.json" or (relative.startswith("plane_") and relative.endswith(".jpg"))


def _export_openlime(args, output: Path) -> int:
    from ..io.atomic import atomic_folder
    from ..io.legacy_rti import is_legacy_rti
    from ..model.memory import bytes_text
    from ..web.openlime import export_openlime

    source = Path(args.field)
    if is_legacy_rti(source):
        return _export_legacy_to_openlime(args, source, output)
    args.model = args.model or "hsh"
    if args.model == "neural":
        return _export_openlime_neural(args, source, output)
    if source.is_file():
        raise InputError(f"{source}: --format openlime fits {args.model.upper()} to a capture's images: give the "
                         "capture folder (its light file and images), not a field file")
    check_output_folder(output, overwrite=args.overwrite, legacy=_openlime_entry, kind="OpenLIME export",
                        inputs=[source])
    dataset, values = _capture_values(args, source)
    with atomic_folder(output, kind="OpenLIME export", overwrite=args.overwrite, legacy=_openlime_entry) as temporary:
        info = export_openlime(values, dataset.lights.directions, temporary, model=args.model)
        size = sum(p.stat().st_size for p in temporary.iterdir())
    print(f"wrote {args.model.upper()} of {source} ({dataset.light_count} lights, {info['width']}x{info['height']}) "
          f"for OpenLIME to {output} ({bytes_text(size)}: info.json and {len(list(output.glob('plane_*.jpg')))} "
          f"planes); open its info.json in an OpenLIME layer of type 'rti'. OpenLIME's shaders draw the classic "
          f"model only: the moving highlights show in this project's own page (export FIELD)")
    return 0


def _export_legacy_to_openlime(args, source: Path, output: Path) -> int:
    """An RTIViewer .ptm or .rti file's model as OpenLIME's layer of the same model (its coefficients as they are)."""
    from ..io.atomic import atomic_folder
    from ..io.legacy_rti import read_legacy_rti
    from ..model.memory import bytes_text
    from ..web.openlime import export_openlime_coefficients, openlime_coefficients

    check_output_folder(output, overwrite=args.overwrite, legacy=_openlime_entry, kind="OpenLIME export",
                        inputs=[source])
    model = read_legacy_rti(source)
    if args.model not in (None, model.kind):
        raise InputError(f"{source} holds a {model.kind.upper()}: it goes to OpenLIME as one (leave out --model "
                         f"{args.model})")
    coefficients = openlime_coefficients(model)
    with atomic_folder(output, kind="OpenLIME export", overwrite=args.overwrite, legacy=_openlime_entry) as temporary:
        export_openlime_coefficients(coefficients, temporary, model=model.kind)
        size = sum(p.stat().st_size for p in temporary.iterdir())
    print(f"wrote the {model.kind.upper()} of {source} ({model.width}x{model.height}) for OpenLIME to {output} "
          f"({bytes_text(size)}); open its info.json in an OpenLIME layer of type 'rti'")
    return 0


def _export_legacy(args, output: Path) -> int:
    import numpy as np

    from ..io.legacy_rti import write_hsh_rti, write_ptm
    from ..model.memory import bytes_text
    from ..relight.legacy import fit_legacy

    source = Path(args.field)
    if output.suffix.lower() != f".{args.format}":
        raise InputError(f"-o {output}: --format {args.format} writes one .{args.format} file; give a name ending in "
                         f".{args.format}")
    if source.is_file():
        raise InputError(f"{source}: --format {args.format} fits the capture's images: give the capture folder, not a "
                         "file (a .ptm or .rti goes to OpenLIME with --format openlime)")
    check_output_file(output, overwrite=args.overwrite, inputs=[source])
    dataset, values = _capture_values(args, source)
    if values.ndim != 4:
        raise InputError(f"{source}: RTIViewer's .{args.format} files hold colour (RGB) captures; this one is grey")
    coefficients = fit_legacy(args.format, values, dataset.lights.directions)
    (write_ptm if args.format == "ptm" else write_hsh_rti)(output, np.asarray(coefficients))
    print(f"wrote {'PTM' if args.format == 'ptm' else 'HSH (order 3)'} of {source} ({dataset.light_count} lights, "
          f"{values.shape[2]}x{values.shape[1]}) to {output} ({bytes_text(output.stat().st_size)}) for RTIViewer; "
          f"the moving highlights show only in this project's own page (export FIELD)")
    return 0


def _capture_values(args, source: Path):
    """The capture at ``source`` (``--size``, ``--linear``) and its images' sRGB display values in [0, 1]."""
    import numpy as np

    from ..io.dataset import ReflectanceField
    from ..io.images import linear_to_srgb
    from ..io.resample import resize_stack, working_size

    dataset = ReflectanceField.load(source, linear=args.linear, progress=not args.quiet, max_pixels=pixel_limit(args))
    images = dataset.images
    if args.size is not None:
        images = resize_stack(images, *working_size(dataset.width, dataset.height, args.size))
    return dataset, linear_to_srgb(np.clip(images, 0.0, 1.0))


def _export_openlime_neural(args, source: Path, output: Path) -> int:
    import numpy as np
    from tqdm import tqdm

    from ..io.atomic import atomic_folder
    from ..io.fieldfile import load_field
    from ..model.memory import bytes_text
    from ..web.openlime import export_openlime_neural

    if source.is_dir():
        raise InputError(f"{source}: --model neural shows a field's learned residual: give the field file (fit "
                         "--residual learned), or export the capture's ptm, hsh or rbf")
    check_output_folder(output, overwrite=args.overwrite, legacy=_openlime_entry, kind="OpenLIME export",
                        inputs=[source])
    field = load_field(source)
    with atomic_folder(output, kind="OpenLIME export", overwrite=args.overwrite, legacy=_openlime_entry) as temporary, \
            tqdm(total=100, unit="%", desc="distil for OpenLIME", disable=args.quiet, leave=False) as bar:
        info, figures = export_openlime_neural(field, temporary, seconds=args.seconds,
                                               progress=lambda done: bar.update(round(100 * done) - bar.n))
        size = sum(p.stat().st_size for p in temporary.iterdir())
    moving = bool(np.asarray(field.estimated.active).any())
    print(f"wrote the learned residual of {source} for OpenLIME's neural layer to {output} ({bytes_text(size)}; "
          f"{info['width']}x{info['height']}, decoder {'-'.join(map(str, figures['hidden']))}): it gives the field's "
          f"images back at {figures['captured_psnr_db']:.1f} dB at its {figures['lights']} lights above the image "
          f"plane and "
          f"{figures['between_psnr_db']:.1f} dB between them (8-bit sRGB, after {figures['seconds']:.0f} s). "
          + ("OpenLIME cannot draw the field's moving highlights: they show in this project's own page (export "
             "FIELD)" if moving else "The field keeps no moving highlights: this is its whole image"))
    return 0


def _check_export(args) -> None:
    allowed = {"page": {"single_file"}, "openlime": {"model", "seconds", "size", "linear"}, "ptm": {"size", "linear"},
               "rti": {"size", "linear"}}[args.format]
    given = {"single_file": args.single_file, "model": args.model is not None, "seconds": args.seconds != 120.0,
             "size": args.size is not None, "linear": args.linear}
    stray = [name for name, set_ in given.items() if set_ and name not in allowed]
    if stray:
        options = ", ".join("--" + name.replace("_", "-") for name in stray)
        raise InputError(f"{options} {'does' if len(stray) == 1 else 'do'} not apply to --format {args.format}; "
                         "leave it out or choose the format it is for (export --help)")
    if args.model not in (None, "neural") and args.seconds != 120.0:
        raise InputError("--seconds is the neural layer's distillation time: it applies to --model neural only")
    if not args.seconds > 0 or args.seconds == float("inf"):
        raise InputError(f"--seconds must be a positive number of seconds, got {args.seconds}")
    suffix = Path(args.output).suffix
    if args.single_file and suffix and suffix.lower() not in PAGE_SUFFIXES:
        raise InputError(f"-o {args.output}: --single-file writes an HTML page; give a name ending in .html (or no "
                         "suffix: .html is added)")


def _serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "folder", type=Path,
        help="a folder written by warp-highlights export, or a collection's output folder (its gallery)")
    parser.add_argument("--port", type=in_range(int, 0, 65535), default=8000,
                        help="port on 127.0.0.1 (default 8000; 0: any free one)")


def _run_serve(args) -> int:
    from ..web.serve import HOST, make_server

    server = make_server(args.folder, args.port)
    port = server.server_address[1]
    print(f"serving {args.folder} at http://{HOST}:{port}/ (this computer only); Ctrl-C stops", flush=True)
    try:
        server.serve_forever()
    finally:
        server.server_close()
    return 0


def _stopped_serving(args) -> str:
    """What Ctrl-C ends ``serve`` with: it wrote nothing, so nothing was removed either."""
    return f"stopped serving {args.folder}"


COMMANDS = (
    Command("export", _export_arguments, _run_export,
            help="write a fitted field as a static web page that relights it in the browser (WebGL2), or a capture "
                 "for OpenLIME or RTIViewer",
            description="Write a viewer of the field into a folder: index.html, viewer.js, manifest.json and the "
                        "field's arrays "
            "(little-endian binaries). The page locates the light in the triangulation, moves the "
            "Gaussians along their "
            "circular paths and adds the residual, as relight does. Browsers refuse to load it from "
            "file://: serve it with "
            "warp-highlights serve, or write one file that opens from disk with --single-file. Every residual "
            "kind (low rank, "
            "uncompressed, learned); the alpha blend is the blend of the field's own images of its captured lights. "
            "--format openlime writes relight's web layout for OpenLIME instead (a capture's PTM, HSH or RBF, a .ptm "
            "or .rti file's model, or a learned field's neural layer), --format ptm or rti a capture's PTM or HSH "
            "for RTIViewer; neither viewer can move the highlights.",
            check=_check_export),
    Command("serve", _serve_arguments, _run_serve, help="serve an exported viewer on 127.0.0.1 (this computer only)",
            description="Serve a folder written by warp-highlights export over HTTP on 127.0.0.1 only: never reachable "
                        "from other hosts.",
            stopped=_stopped_serving),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
