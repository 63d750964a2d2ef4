"""``export_viewer``: a fitted field as a static web page (manifest.json, little-endian .bin arrays,
index.html and viewer.js, or all of it in one HTML file); the page relights it as ``Relighter`` does
(warp_highlights/web/PORTING.md)."""

from __future__ import annotations

import base64
import gzip
import json
import re
import shutil
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from ..model.rbf import rbf_system
from ..model.residual import (
    COLOUR_STEP,
    NEURAL_CODE_SIZE,
    colour_codes,
    colour_from_codes,
    decoder_layer_shapes,
)
from ..relight.relighter import face_edge_rows, rim_tables

__all__ = ["MANIFEST", "MAX_PAGE_GAUSSIANS", "SEEING_WEB_FORMAT", "SINGLE_FILE_LIMIT", "WEB_FORMAT", "encoded_arrays",
           "export_arrays", "export_viewer", "single_file_page"]

WEB_FORMAT = 3
"""Version of the exported layout that viewer.js reads."""
SEEING_WEB_FORMAT = 4
"""Version of the layout of a field whose learned decoder sees the highlights (``residual.sees_highlights``: w0 of
14 columns): version 3's, which a viewer that reads version 3 only refuses rather than draw it wrongly."""
MANIFEST = "manifest.json"
MAX_PAGE_GAUSSIANS = 512
"""Gaussians one query may draw: WebGL2 guarantees a 16 KiB uniform block, 32 bytes a Gaussian."""
SINGLE_FILE_LIMIT = 15 * 1024 * 1024
"""Largest ``--single-file`` page, bytes: mail services cap a message at 20-25 MB and a mailed
attachment grows by a third (base64), so 15 MiB still goes through Gmail and Outlook."""
GZIP_LEVEL = 6
"""zlib level of the gzipped arrays: several times smaller than the raw arrays (the export sizes of
benchmarks/bench_web.py); level 9 is barely smaller and much slower."""
_STATIC = Path(__file__).with_name("static")
_STATIC_FILES = ("index.html", "viewer.js")
_IMPORT_LINE = 'import { Viewer } from "./viewer.js";'
_EMBED_MARK = "<!-- embedded field -->"


def export_arrays(field) -> tuple[dict, dict[str, np.ndarray]]:
    """The manifest and the arrays (little-endian, row-major) of ``field``'s viewer."""
    residual = field.residual
    if residual is None:
        raise InputError(
            "the web viewer needs a field with a residual (fields before version 0.2 have none: fit it again)")
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
    most = 3 * int(field.estimated.active.sum(axis=1).max(initial=0))
    if most > MAX_PAGE_GAUSSIANS:
        raise InputError(f"a query of this field draws up to {most} Gaussians; the web viewer draws at most "
                         f"{MAX_PAGE_GAUSSIANS} "
                         f"(fit with a smaller estimation.capacity)")
    channels = residual.channels
    if residual.highlight_colour is not None:
        arrays["colour"] = _colour_codes(residual.highlight_colour)  # (H, W, C) u1, or f2/f4 where not codes
    if residual.scale is not None:
        arrays["scale"] = _compact(residual.scale)
    if residual.learned is not None:
        kind, details = "learned", _learned_arrays(residual.learned, arrays)
    elif residual.kind == "lowrank":
        kind, details = "lowrank", {name: _stack_arrays(name, stack, arrays)
                                    for name, stack in (("luminance", residual.luminance), ("chroma", residual.chroma))
                                    if stack is not None}
        if residual.rbf_sigma is not None:  # the page weighs every light phi(w)^T (K + lambda I)^-1 (model.rbf)
            details["rbf_sigma"] = residual.rbf_sigma
            arrays["rbf_inverse"] = np.linalg.inv(rbf_system(field.lights.directions, residual.rbf_sigma)).astype("<f8")
    else:
        kind, details = "images", {}
        arrays["images"] = np.ascontiguousarray(residual.images, dtype="<f2")  # (n, H, W, C)
    settings = field.fit_settings()
    seeing = residual.learned is not None and residual.learned.sees_highlights
    manifest = {
        "format": "warp-highlights web viewer", "version": SEEING_WEB_FORMAT if seeing else WEB_FORMAT,
        "width": field.width, "height": field.height, "channels": channels, "lights": field.light_count,
        "faces": int(tri.face_count), "capacity": field.capacity, "max_gaussians": max(most, 1),
        "is_dome": rim is not None,
        "exposure": float(field.exposure), "cutoff": float(settings.raster.cutoff),
        "sigma_eps": float(settings.raster.sigma_eps),
        "straight_below": float(settings.paths.straight_below), "colour_step": COLOUR_STEP,
        "residual": {"kind": kind, **details},
        "motion": _motion_summary(field),
        "arrays": {name: {"file": f"{name}.bin", "dtype": array.dtype.str, "shape": list(array.shape)}
                   for name, array in arrays.items()},
    }
    return manifest, arrays


def _motion_summary(field) -> dict:
    """How much of the image moves, for the page's status line: the moving and estimated Gaussians, and the
    share of the specular energy the moving ones carry (from the fit report; None where it has none)."""
    residual = field.report.get("residual") if isinstance(field.report.get("residual"), dict) else {}
    share = residual.get("moving_specular_share")
    return {"moving": int(field.moving_mask.sum()), "gaussians": int(field.estimated.active.sum()),
            "specular_share": float(share) if isinstance(share, (int, float)) else None}


def encoded_arrays(manifest: dict, arrays: dict[str, np.ndarray]) -> dict[str, bytes]:
    """name -> the bytes written for each array: gzip (the page inflates it with the browser's
    ``DecompressionStream``) where that saves at least a tenth, else raw; records it in ``manifest``."""
    out = {}
    for name, array in arrays.items():
        raw = np.ascontiguousarray(array).tobytes()
        packed = gzip.compress(raw, compresslevel=GZIP_LEVEL, mtime=0) if len(raw) >= 4096 else raw
        spec = manifest["arrays"][name]
        if packed is not raw and len(packed) <= 0.9 * len(raw):
            spec.update(file=f"{name}.bin.gz", encoding="gzip")
            out[name] = packed
        else:
            out[name] = raw
    return out


def export_viewer(field, folder) -> dict:
    """Write the viewer of ``field`` into ``folder`` (which must exist and be empty: the caller makes
    it atomic); returns the manifest."""
    manifest, arrays = export_arrays(field)
    folder = Path(folder)
    for name, data in encoded_arrays(manifest, arrays).items():
        (folder / manifest["arrays"][name]["file"]).write_bytes(data)
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    for name in _STATIC_FILES:
        shutil.copyfile(_STATIC / name, folder / name)
    return manifest


def single_file_page(field, *, limit: int | None = None) -> bytes:
    """The viewer of ``field`` as one self-contained HTML page (viewer.js inlined into the page's module,
    the arrays in base64), UTF-8; raises ``InputError`` when it would be larger than ``limit`` bytes
    (default ``SINGLE_FILE_LIMIT``)."""
    limit = SINGLE_FILE_LIMIT if limit is None else limit
    manifest, arrays = export_arrays(field)
    encoded = encoded_arrays(manifest, arrays)
    embedded = {"manifest": manifest,
                "arrays": {name: base64.b64encode(data).decode("ascii") for name, data in encoded.items()}}
    page = (_STATIC / "index.html").read_text()
    viewer = (_STATIC / "viewer.js").read_text()
    if _IMPORT_LINE not in page or _EMBED_MARK not in page or re.search(r"</script|<!--", viewer, re.IGNORECASE):
        raise RuntimeError("web/static/index.html or viewer.js changed: single_file_page cannot inline them")
    page = page.replace(_IMPORT_LINE, viewer)
    page = page.replace(_EMBED_MARK,
                        f'<script type="application/json" id="embedded-field">{json.dumps(embedded)}</script>')
    data = page.encode("utf-8")
    if len(data) > limit:
        raise InputError(f"a single-file viewer of this field would be {len(data) / 2**20:.1f} MiB, over the "
                         f"{limit / 2**20:.0f} MiB that mail "
                         f"services take; export it as a folder (without --single-file) and serve it, or fit "
                         f"a smaller --size")
    return data


def _gaussian_table(params) -> np.ndarray:
    """(B, N, 6) float32: |a|, mu_x, mu_y, |sigma_x|, |sigma_y|, theta per slot."""
    return np.concatenate([np.abs(params.amplitude)[..., None], params.mean, np.abs(params.sigma),
                           params.theta[..., None]], axis=2).astype("<f4")


def _compact(values: np.ndarray) -> np.ndarray:
    """``values`` as little-endian float16 where that loses nothing (the field stored float16), else float32."""
    values = np.asarray(values, dtype=np.float32)
    half = values.astype("<f2")
    return half if np.array_equal(half.astype(np.float32), values) else values.astype("<f4")


def _colour_codes(colour: np.ndarray) -> np.ndarray:
    """c(x) as the field file's uint8 codes of ``COLOUR_STEP`` where it is exactly that, else compact floats."""
    codes = colour_codes(colour)
    return codes if np.array_equal(colour_from_codes(codes), colour) else _compact(colour)


def _stack_arrays(name: str, stack, arrays: dict) -> dict:
    """Add a low-rank stack's arrays: the mean (H, W, P), the codes packed four to a texel
    (G, H, W, 4), item ``4 g + t`` = code of basis ``(4 g + t) // P``, plane ``(4 g + t) % P``."""
    rank, planes = stack.codes.shape[0], stack.mean.shape[2]
    height, width = stack.mean.shape[:2]
    arrays[f"{name}_mean"] = _compact(stack.mean)
    items = stack.codes.transpose(1, 2, 0, 3).reshape(height, width, rank * planes)
    groups = max(1, -(-rank * planes // 4))
    packed = np.zeros((height, width, 4 * groups), dtype=stack.codes.dtype)
    packed[..., : rank * planes] = items
    bits = 8 if stack.codes.dtype == np.uint8 else 16
    arrays[f"{name}_codes"] = np.ascontiguousarray(packed.reshape(height, width, groups, 4).transpose(2, 0, 1, 3),
                                                   dtype="u1" if bits == 8 else "<u2")
    arrays[f"{name}_ranges"] = stack.ranges.astype("<f4")
    arrays[f"{name}_weights"] = stack.weights.astype("<f4")
    mean_weights = np.ones(len(stack.weights), np.float32) if stack.mean_weights is None else stack.mean_weights
    arrays[f"{name}_mean_weights"] = np.asarray(mean_weights, dtype="<f4")
    return {"rank": rank, "planes": planes, "bits": bits, "groups": groups}


def _learned_arrays(learned, arrays: dict) -> dict:
    """Add a learned residual's codes, three to a texel (3, H, W, 3) float16, and its decoder's weight arrays, each
    hidden layer padded with zero units to a multiple of 4 (the page's vec4s; the same values); w0 has 14 columns
    where the decoder sees the highlights (``sees_highlights`` in the details), else 12."""
    height, width, _ = learned.codes.shape
    arrays["learned_codes"] = np.ascontiguousarray(learned.codes.reshape(height, width, NEURAL_CODE_SIZE // 3,
                                                                         3).transpose(2, 0, 1, 3), dtype="<f2")
    if learned.bounds is not None:  # (2, H, W, 3) float16: the lowest and the highest value a pixel takes
        arrays["learned_bounds"] = np.ascontiguousarray(learned.bounds, dtype="<f2")
    padded = [-(-w // 4) * 4 for w in learned.hidden]
    seeing = learned.sees_highlights
    for index, (weights, shape) in enumerate(zip(learned.weights, decoder_layer_shapes(padded, seeing))):
        wide = np.zeros(shape, dtype="<f4")
        wide[:weights.shape[0], :weights.shape[1]] = weights
        arrays[f"learned_{'wb'[index % 2]}{index // 2}"] = wide
    return {"unit": float(learned.unit), "hidden": padded, **({"sees_highlights": True} if seeing else {})}
