"""``warp-highlights maps``: normal, albedo and highlight-colour maps of a fitted field (``relight.maps``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .. import __version__
from ..model.config import FLATTEN_MODES, MapSettings
from .args import Command, check_device, check_output_folder

__all__ = ["COMMANDS", "MAP_FILES"]

MAP_FILES = {
    "normals.png": "16-bit RGB = (n + 1) / 2 per axis, x right, y up the image, z towards the camera (the .lp frame); "
                   "(0.5, 0.5, 1) where no normal was estimated",
    "normals.exr": "float32 RGB = the unit normal (x, y, z) itself, components in [-1, 1]",
    "albedo.png": "16-bit sRGB: the diffuse value under a unit light along the normal (clipped to 1)",
    "albedo.exr": "float32 linear albedo, the input's units (not clipped)",
    "highlight-colour.png": "16-bit sRGB: the highlight colour c(x) scaled so its largest channel is 1 (its hue "
                            "and saturation)",
    "highlight-colour.exr": "float32 linear c(x) as relighting uses it (luminance 1; white where the field keeps none)",
    "mask.png": "8-bit grey: 255 where the maps hold a normal (the pixel's own, or its neighbours' where its own "
                "lights do not determine one), 0 elsewhere (background, never lit)",
    "maps.json": "what was written, the conventions, and counts",
}
"""The files of a maps folder and what each holds."""


def _maps_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("field", type=Path, help="highlight-field file (from warp-highlights fit), or an RTIViewer "
                        ".ptm or .rti file (its model relit at 64 dome lights)")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output folder for the maps (PNG 16-bit and EXR each, mask, maps.json)")
    parser.add_argument("--flatten", nargs="?", const="trend", choices=FLATTEN_MODES, default=None,
                        help="for flat objects and reliefs (coins, tablets, paintings, carved panels): 'trend' (the "
                             "default when given bare) removes the linear trend of the normals' slopes over the "
                             "image, the lean away from the centre that lights at a finite distance give, and keeps "
                             "the object's tilt; 'level' removes that tilt too, so the typical orientation (the "
                             "base) faces the camera. Takes shape from curved objects")
    parser.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output folder written by warp-highlights")


def _maps_folder_entry(relative: str) -> bool:
    """A file of a maps folder (how one written before manifests existed is recognised)."""
    return relative in MAP_FILES


def _run_maps(args) -> int:
    from tqdm import tqdm

    from ..io.atomic import atomic_folder
    from ..io.fieldfile import load_field
    from ..io.images import write_image
    from ..relight.maps import surface_maps

    output = Path(args.output)
    check_output_folder(output, overwrite=args.overwrite, legacy=_maps_folder_entry, kind="surface maps",
                        inputs=[args.field])
    from ..io.legacy_rti import is_legacy_rti

    if is_legacy_rti(args.field):
        from ..io.legacy_rti import read_legacy_rti
        from ..relight.legacy import MAPS_LIGHTS, legacy_surface_maps

        model = read_legacy_rti(args.field)
        maps = legacy_surface_maps(model, flatten=args.flatten)
        field = SimpleNamespace(width=model.width, height=model.height, light_count=MAPS_LIGHTS)
    else:
        field = load_field(args.field)
        device = check_device(args.device)
        with tqdm(total=field.light_count, unit="light", desc="maps", disable=args.quiet, leave=False) as bar:
            maps = surface_maps(field, device=device, flatten=args.flatten,
                                progress=lambda done: bar.update(done - bar.n))
    colour = maps.highlight_colour
    peak = colour.max(axis=2, keepdims=True)
    with atomic_folder(output, kind="surface maps", overwrite=args.overwrite, legacy=_maps_folder_entry) as temporary:
        write_image(temporary / "normals.png", (maps.normals + 1.0) / 2.0, bits=16, linear=True)
        write_image(temporary / "normals.exr", maps.normals)
        write_image(temporary / "albedo.png", np.minimum(maps.albedo, 1.0), bits=16)
        write_image(temporary / "albedo.exr", maps.albedo)
        write_image(temporary / "highlight-colour.png", colour / np.where(peak > 0, peak, 1.0), bits=16)
        write_image(temporary / "highlight-colour.exr", colour)
        write_image(temporary / "mask.png", maps.mask.astype(np.float32), linear=True)
        summary = _summary(args.field, field, maps, flattened=args.flatten or "no")
        (temporary / "maps.json").write_text(json.dumps(summary, indent=1) + "\n")
    share = summary["pixels_with_normal"] / max(field.width * field.height, 1)
    lean = maps.lean
    if not args.flatten and lean.edge_deg > MapSettings().lean_hint_deg:
        print(f"note: the normals lean {lean.edge_deg:.0f} degrees more at the frame's corners than at its centre "
              f"(near lights do this to a flat object; a curved shape does it too): for a flat object or a relief, "
              f"pass --flatten, or --flatten level to make its base face the camera as well (tilted "
              f"{lean.tilt_deg:.0f} degrees)", file=sys.stderr)
    print(f"wrote normal, albedo and highlight-colour maps to {output} ({field.width}x{field.height}; normals on "
          f"{100 * share:.0f}% of the "
          f"pixels; highlight colour "
          f"{'per pixel' if maps.coloured_highlights else 'white: the field keeps no coloured highlights'})")
    return 0


def _summary(path: Path, field, maps, *, flattened: str) -> dict:
    """maps.json: the files, the conventions and what the estimate rests on."""
    lit = maps.lit_lights[maps.mask & ~maps.filled]
    albedo = maps.albedo[maps.mask]
    return {
        "field": str(path),
        "library_version": __version__,
        "size": [field.width, field.height],
        "files": MAP_FILES,
        "normal_frame": "x right, y up the image, z towards the camera: the frame of the .lp light directions",
        "flattened": flattened,
        "lean_before_flattening_deg": {"trend_at_corners": round(maps.lean.edge_deg, 2),
                                       "tilt": round(maps.lean.tilt_deg, 2)},
        "albedo_units": "linear, the input's units (the fit's exposure undone); the diffuse value under a unit light "
                        "along the normal",
        "pixels_with_normal": int(maps.mask.sum()),
        "pixels_from_neighbours": int(maps.filled.sum()),
        "pixels_shadow_fit": int(maps.shadow_fit.sum()),
        "lit_lights_median": float(np.median(lit)) if lit.size else 0.0,
        "albedo_clipped_in_png_share": float(np.mean(np.any(albedo > 1.0, axis=-1))) if albedo.size else 0.0,
        "highlight_colour": "per pixel" if maps.coloured_highlights else "white",
        "lights": field.light_count,
    }


COMMANDS = (
    Command("maps", _maps_arguments, _run_maps,
            help="write normal, albedo and highlight-colour maps of a fitted field (PNG 16-bit and EXR)",
            description="Estimate per-pixel surface normals and albedo from the field's captured images (a robust "
                        "Lambertian fit "
            "per pixel, highlights and shadows left out) and write them with the field's highlight colour "
            "into a folder: "
            "normals.png/.exr, albedo.png/.exr, highlight-colour.png/.exr, mask.png and maps.json. Normals "
            "are in the frame "
            "of the .lp light directions (x right, y up the image, z towards the camera); the PNG "
            "encodes (n + 1) / 2."),
)
"""The subcommands of this module, in the order ``warp-highlights --help`` lists them."""
