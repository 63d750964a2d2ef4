"""Contact sheets: a quick look at a reflectance field, several lights side by side.

Each tile shows one light's full image, specular part and diffuse part (when the dataset has them),
tone-mapped by clipping to [0, 1] and sRGB encoding, with the light's index and direction as a label.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.atomic import atomic_file
from ..io.images import display_rgb8
from ..model.errors import InputError

__all__ = ["contact_sheet", "save_contact_sheet", "spread_indices"]

_GAP = 4
_LABEL_HEIGHT = 14


def spread_indices(count: int, total: int) -> np.ndarray:
    """``count`` indices spread evenly over ``total`` lights (all of them when there are fewer)."""
    if count < 1:
        raise InputError(f"a contact sheet needs at least one light, got count={count}")
    return np.unique(np.round(np.linspace(0, total - 1, min(count, total))).astype(int))


def contact_sheet(field, *, count: int = 12, thumb_height: int = 135, columns: int = 2) -> np.ndarray:
    """An (H, W, 3) uint8 sRGB picture of ``count`` lights of a ReflectanceField.

    Args:
        field: a ``ReflectanceField``; its specular/diffuse ground truth is shown when present.
        count: number of lights shown, spread over the light list.
        thumb_height: tile height in pixels; widths keep the aspect ratio.
        columns: light cells per row; each cell holds full | specular | diffuse.
    """
    from PIL import Image, ImageDraw

    indices = spread_indices(count, field.light_count)
    layers = [field.images] + [a for a in (field.specular, field.diffuse) if a is not None]
    thumb_width = max(1, round(field.width * thumb_height / field.height))
    cell_width = len(layers) * thumb_width + (len(layers) - 1) * _GAP
    cell_height = thumb_height + _LABEL_HEIGHT
    rows = -(-len(indices) // columns)
    canvas = Image.new("RGB", (columns * cell_width + (columns + 1) * _GAP * 3, rows * cell_height + (rows + 1) * _GAP),
                       (24, 24, 24))
    draw = ImageDraw.Draw(canvas)
    for slot, light in enumerate(indices):
        x0 = _GAP * 3 + (slot % columns) * (cell_width + _GAP * 3)
        y0 = _GAP + (slot // columns) * (cell_height + _GAP)
        direction = field.lights.directions[light]
        draw.text((x0, y0), f"#{light}  ({direction[0]:+.2f}, {direction[1]:+.2f}, {direction[2]:+.2f})",
                  fill=(220, 220, 220))
        for k, layer in enumerate(layers):
            tile = Image.fromarray(display_rgb8(layer[light])).resize((thumb_width, thumb_height),
                                                                      Image.Resampling.LANCZOS)
            canvas.paste(tile, (x0 + k * (thumb_width + _GAP), y0 + _LABEL_HEIGHT))
    return np.asarray(canvas)


def save_contact_sheet(field, path: str | Path, **options) -> Path:
    """Write :func:`contact_sheet` to a PNG atomically; returns the path."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"contact sheet '{path}' must be a .png file")
    path.parent.mkdir(parents=True, exist_ok=True)
    picture = contact_sheet(field, **options)
    with atomic_file(path) as temporary:
        Image.fromarray(picture).save(temporary, format="PNG")
    return path
