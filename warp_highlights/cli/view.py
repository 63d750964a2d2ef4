"""The ``view`` command of ``warp-highlights``: the light designer in a window, or a screenshot of it."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..model.errors import InputError
from .args import Command, check_device, check_output_file, parse_direction, size_option

__all__ = ["COMMANDS"]


def _view_arguments(parser: argparse.ArgumentParser) -> None:
    from ..view.panels import PANELS

    parser.add_argument("field", type=Path, help="highlight-field file (from warp-highlights fit)")
    parser.add_argument("--light", metavar="X,Y,Z",
                        help="first light direction (default: the centroid of the triangle (0.3, 0.4, 1) falls in)")
    parser.add_argument("--method", choices=["circular", "straight"], default="circular",
                        help="interpolation (default circular)")
    parser.add_argument("--size", type=size_option("relit image size"),
                        help="relit image WIDTHxHEIGHT with the field's aspect ratio (default: the field's size)")
    parser.add_argument("--diffuse", choices=["auto", "lambert", "images", "none"], default="auto",
                        help="what the highlights S' are added to: auto (the field's residual when it has one, "
                             "else its diffuse model), lambert, images or none (default auto)")
    parser.add_argument("--specular-only", action="store_true", help="show the highlights S' alone")
    parser.add_argument("--panels", default=",".join(PANELS),
                        help=f"panels left to right, comma-separated (default {','.join(PANELS)})")
    parser.add_argument("--window-size", type=size_option("window size"),
                        help="window WIDTHxHEIGHT in pixels (default 560x520 per panel)")
    parser.add_argument("--screenshot", type=Path, metavar="PNG", help="render off screen into this PNG and exit")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing screenshot")
    parser.add_argument("--device", default=None,
                        help="Warp device for relighting: cpu, cuda, cuda:N (default: CUDA when present)")


def _run_view(args) -> int:
    from ..io.fieldfile import load_field
    from ..view.designer import LightDesigner, check_panels
    from ..view.viz import has_display

    direction = parse_direction(args.light) if args.light else None
    size, window_size = args.size, args.window_size
    panels = check_panels(p.strip() for p in args.panels.split(",") if p.strip())
    screenshot = args.screenshot
    if screenshot is not None:
        if screenshot.suffix.lower() != ".png":
            raise InputError(f"screenshot '{screenshot}' must be a .png file")
        check_output_file(screenshot, overwrite=args.overwrite, inputs=[args.field])
    elif not has_display():
        raise InputError(
            "there is no display for a window (DISPLAY is not set): pass --screenshot out.png to render off screen")
    device = check_device(args.device)
    field = load_field(args.field)
    started = time.perf_counter()
    designer = LightDesigner(field, direction=direction, method=args.method, device=device, size=size,
                             diffuse=args.diffuse,
                             specular_only=args.specular_only, panels=panels, window_size=window_size,
                             off_screen=screenshot is not None)
    try:
        if screenshot is not None:
            picture = designer.screenshot(screenshot)
            print(f"wrote {screenshot} ({picture.shape[1]}x{picture.shape[0]}, {time.perf_counter() - started:.1f} s; "
                  f"relight {designer.timings['relight']:.1f} ms)")
        else:
            designer.show()
    finally:
        designer.close()
    return 0


COMMANDS = (
    Command("view", _view_arguments, _run_view,
            help="look at a fitted field: light sphere, relit image, Gaussian paths; drag the light",
            description="Open the light designer: the light sphere with the triangulation (a dome's rim in red), the "
            "current light and its triangle; the object relit for that light; and the paths of the triangle's "
            "Gaussians over the image plane (thick: circular, thin: straight, one colour per Gaussian). Drag "
            "the yellow handle to move the light; keys: m switches circular/straight, h the full "
            "image/highlights alone. With --screenshot it renders off screen into a PNG instead (no display "
            "needed)."),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
