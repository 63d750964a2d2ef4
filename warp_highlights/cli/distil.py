"""``warp-highlights distil``: a field whose learned residual decodes through a smaller decoder
(``residual.distil``); a decoder that sees the highlights gets a student that sees them too, both decoding with the
Gaussians moved to each direction (the relighter's S')."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..model.config import DistilSettings
from ..model.errors import InputError
from ..model.residual import parse_hidden
from .args import Command, check_output_file

__all__ = ["COMMANDS"]


def _distil_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = DistilSettings()
    parser.add_argument("field", type=Path,
                        help="highlight-field file with a learned residual (fit --residual learned)")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="field file to write, the same but for the smaller decoder")
    parser.add_argument("--hidden", default=",".join(map(str, defaults.hidden)),
                        help="the smaller decoder's hidden layers' widths, 1 to 3 of 1 to 48 (default: %(default)s; "
                             "the fitted one's: 48,48,48)")
    parser.add_argument("--seconds", type=float, default=defaults.seconds,
                        help="training time at most, seconds (default: %(default)s)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")


def _check(args) -> None:
    parse_hidden(args.hidden)
    if not args.seconds > 0 or args.seconds == float("inf"):
        raise InputError(f"--seconds must be a positive number of seconds, got {args.seconds}")


def _run_distil(args) -> int:
    import dataclasses

    from tqdm import tqdm

    from ..io.fieldfile import load_field, save_field
    from ..residual.distil import distil_decoder

    check_output_file(args.output, overwrite=args.overwrite, inputs=[args.field])
    field = load_field(args.field)
    residual = field.residual
    if residual is None or residual.learned is None:
        kind = "no residual" if residual is None else f"a {residual.kind} residual"
        raise InputError(f"{args.field} holds {kind}, not a learned one: distil shrinks a learned residual's decoder; "
                         f"fit the capture with --residual learned first")
    hidden = parse_hidden(args.hidden)
    settings = dataclasses.replace(DistilSettings(), hidden=hidden, seconds=float(args.seconds))
    seeing = residual.learned.sees_highlights
    with tqdm(total=100, unit="%", desc="distil", disable=args.quiet, leave=False) as bar:
        student, report = distil_decoder(residual.learned, None, field.lights.directions, field.triangulation.faces,
                                         settings=settings, progress=lambda done: bar.update(round(100 * done) - bar.n),
                                         highlights=_moved_highlights(field) if seeing else None)
    smaller = dataclasses.replace(field, residual=dataclasses.replace(residual, learned=student),
                                  report={**(field.report or {}), "distilled": report.to_dict()})
    save_field(smaller, args.output)
    layers = "-".join(map(str, hidden))
    print(f"wrote {args.output}: decoder {layers} ({report.multiply_adds} multiply-adds a pixel against "
          f"{report.teacher_multiply_adds}, {report.teacher_multiply_adds / report.multiply_adds:.1f} times fewer); "
          f"it gives the fitted decoder's images back at {report.captured_psnr_db:.1f} dB at the {field.light_count} "
          f"lights and {report.between_psnr_db:.1f} dB between them (8-bit sRGB, after {report.seconds:.0f} s)"
          + ("; it sees the highlights, as the fitted decoder does" if seeing else ""))
    return 0


def _moved_highlights(field):
    """(D, 3) directions -> (D, H, W) float32 the luminance of ``field``'s Gaussians moved to them (field units: the
    relighter's S', which a decoder that sees the highlights takes)."""
    import dataclasses

    import numpy as np

    from ..relight.relighter import Relighter

    relighter = Relighter(dataclasses.replace(field, residual=None), diffuse="none")
    return lambda directions: relighter.relight(np.asarray(directions, np.float64).reshape(-1, 3), full=False).specular


COMMANDS = (
    Command("distil", _distil_arguments, _run_distil,
            help="write a field whose learned residual decodes through a smaller decoder (faster on the CPU)",
            description="Distil the learned residual's decoder into one of fewer or narrower layers, trained (its "
                        "per-pixel codes learning along) to give the fitted decoder's images back at the captured "
                        "lights and between them; writes a new field file and says how close it came (8-bit sRGB "
                        "PSNR against the fitted decoder). A decoder that sees the highlights gets a smaller one that "
                        "sees them too, both taking the Gaussians moved to each direction. The CPU and the web page "
                        "decode the smaller decoder at its own size (faster); a GPU decodes it through the fitted "
                        "decoder's kernels.",
            check=_check),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
