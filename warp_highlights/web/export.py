"""``export_viewer``: a fitted field as a static web page (manifest.json, little-endian .bin arrays,
index.html and viewer.js); the page relights it as ``Relighter`` does (warp_highlights/web/PORTING.md)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from ..relight.relighter import face_edge_rows, rim_tables

__all__ = ["MANIFEST", "WEB_FORMAT", "export_viewer"]

WEB_FORMAT = 1
"""Version of the exported layout that viewer.js reads."""
MANIFEST = "manifest.json"
_STATIC = Path(__file__).with_name("static")
_STATIC_FILES = ("index.html", "viewer.js")


def export_viewer(field, folder) -> dict:
    """Write the viewer of ``field`` into ``folder`` (which must exist and be empty: the caller makes
    it atomic); returns the manifest."""
    residual = field.residual
    if residual is None or residual.learned is not None or not residual.compressed:
        raise InputError("the web viewer shows low-rank residual fields for now (fit --residual lowrank)")
    folder = Path(folder)
    arrays: dict[str, np.ndarray] = {}
    tri = field.triangulation
    arrays["directions"] = field.lights.directions.astype("<f8")
    arrays["faces"] = tri.faces.astype("<i4")
    arrays["face_edges"] = face_edge_rows(tri.faces, field.directed_edges, field.light_count).astype("<i4")
    tables = tri._locate_tables
    arrays["edge_normals"] = np.ascontiguousarray(tables.edge_normals.transpose(1, 0, 2), dtype="<f8")  # (F, 3, 3)
    arrays["inverses"] = tables.inverses.astype("<f8")
    rim = rim_tables(tri)
    if rim is not None:
        arrays["rims"] = np.stack(rim[:5], axis=1).astype("<f8")  # (R, 5, 3): start, end, normal, along, back
        arrays["rim_face"] = np.asarray(rim[5], dtype="<i4")
        arrays["rim_opposite"] = np.asarray(rim[6], dtype="<i4")
    arrays["estimated"] = _gaussian_table(field.estimated)
    arrays["estimated_active"] = field.estimated.active.astype("u1")
    arrays["moving"] = field.moving_mask.astype("u1")
    arrays["retargeted"] = _gaussian_table(field.retargeted)
    arrays["path_delta"] = field.path_delta.astype("<f4")
    channels = residual.channels
    planes = [np.ones((field.height, field.width), np.float32) if residual.scale is None else residual.scale]
    colour = residual.highlight_colour
    planes += [np.ones((field.height, field.width), np.float32)] * channels if colour is None else [colour[..., c] for c in range(channels)]
    stacks = {}
    for name, stack in (("luminance", residual.luminance), ("chroma", residual.chroma)):
        if stack is None:
            continue
        first = len(planes)
        planes += [stack.mean[..., p] for p in range(stack.mean.shape[2])]
        rank, count = stack.codes.shape[0], stack.mean.shape[2]
        bits = 8 if stack.codes.dtype == np.uint8 else 16
        arrays[f"{name}_codes"] = np.ascontiguousarray(stack.codes.transpose(0, 3, 1, 2).reshape(rank * count, field.height, field.width),
                                                       dtype="u1" if bits == 8 else "<u2")
        arrays[f"{name}_ranges"] = stack.ranges.astype("<f4")
        arrays[f"{name}_weights"] = stack.weights.astype("<f4")
        mean_weights = np.ones(field.light_count, np.float32) if stack.mean_weights is None else stack.mean_weights
        arrays[f"{name}_mean_weights"] = np.asarray(mean_weights, dtype="<f4")
        stacks[name] = {"rank": rank, "planes": count, "bits": bits, "mean_layer": first}
    arrays["planes"] = np.stack(planes).astype("<f4")  # scale, colour (C), the stacks' means
    settings = field.fit_settings()
    manifest = {
        "format": "warp-highlights web viewer", "version": WEB_FORMAT,
        "width": field.width, "height": field.height, "channels": channels, "lights": field.light_count,
        "faces": int(tri.face_count), "capacity": field.capacity, "is_dome": rim is not None,
        "exposure": float(field.exposure), "cutoff": float(settings.raster.cutoff), "sigma_eps": float(settings.raster.sigma_eps),
        "straight_below": float(settings.paths.straight_below), "stacks": stacks,
        "arrays": {name: {"file": f"{name}.bin", "dtype": array.dtype.str, "shape": list(array.shape)} for name, array in arrays.items()},
    }
    for name, array in arrays.items():
        (folder / f"{name}.bin").write_bytes(np.ascontiguousarray(array).tobytes())
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    for name in _STATIC_FILES:
        shutil.copyfile(_STATIC / name, folder / name)
    return manifest


def _gaussian_table(params) -> np.ndarray:
    """(B, N, 6) float32: |a|, mu_x, mu_y, |sigma_x|, |sigma_y|, theta per slot."""
    return np.concatenate([np.abs(params.amplitude)[..., None], params.mean, np.abs(params.sigma), params.theta[..., None]], axis=2).astype("<f4")
