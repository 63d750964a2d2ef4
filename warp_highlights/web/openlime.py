"""A capture (or a legacy file's model, or a learned field's residual) as relight's web layout, the folder OpenLIME
opens (``type: 'rti'``): ``info.json`` and ``plane_0.jpg``, ``plane_1.jpg``, ... holding three coefficient planes
each; and the same folder relit here (``relight_openlime``), with OpenLIME's own formulas, as the reference its page
is compared with.

The models (fitted to the images' 8-bit sRGB display values in [0, 1], which OpenLIME shows as they are):

- ``ptm``: per pixel and channel, the biquadratic 1, x, y, x^2, xy, y^2 of the light's (x, y) (18 planes,
  colour space ``rgb``), least squares;
- ``hsh``: the 9 hemispherical harmonics of order 3 (27 planes, ``rgb``), with OpenLIME's constants (pi as
  3.1415, the light's polar angle clamped at 3.1415 / 2 - 0.15), least squares;
- ``rbf``: the images' principal components over the lights (``RBF_PLANES`` planes, colour space ``mrgb``):
  each pixel's values at every light and channel are the mean plus its coefficients times the
  components; a query blends the lights' mean and components with OpenLIME's adaptive Gaussian weights
  (exp(-k d_i^2), k = 8 / the e^(-2d)-weighted mean distance d to the lights, normalised).

A field's learned residual goes to OpenLIME's neural layer (``type: 'neural'``, ``export_openlime_neural``):
its 9 codes a pixel, each quantised to 8 bits between its minimum and maximum, in ``plane_1.jpg`` ..
``plane_3.jpg``, and a decoder of OpenLIME's shape (the 9 codes and the light's x and y, two hidden ELU
layers, sRGB out) distilled from the field's (``residual.distil.distil_display_decoder``) over the codes as
the JPEGs give them back. A decoder that sees the highlights is distilled from the field's relit image, its teacher
decoding with the moved Gaussians of each direction (``SEEING_NOTE``): OpenLIME's layer takes code and light only,
so its highlights cross-fade between the lights rather than move.

Coefficient planes are quantised as relight does: each plane between its 0.25% and 99.75% quantiles
(``scale`` = high - low, ``bias`` = -low / scale; a byte b stands for (b / 255 - bias) scale), written as
4:4:4 JPEGs of quality 95 without a colour profile (what a browser decodes as Pillow does). Lights use the
``LightSet`` frame (x right, y up the image), which is OpenLIME's ``setLight([x, y])`` too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from ..model.errors import InputError

__all__ = ["NEURAL_HIDDEN_OPENLIME", "NEURAL_SECONDS", "OPENLIME_MODELS", "RBF_PLANES", "SEEING_NOTE",
           "export_openlime", "export_openlime_coefficients", "export_openlime_neural", "openlime_coefficients",
           "openlime_weights", "relight_openlime"]

OPENLIME_MODELS = ("ptm", "hsh", "rbf")
"""The models of a capture ``export --format openlime --model`` writes (OpenLIME's RTI layer draws them); a field's
learned residual is its neural layer (``export_openlime_neural``)."""
NEURAL_HIDDEN_OPENLIME = (48, 48)
"""The hidden widths of the decoder distilled for OpenLIME's neural layer (two layers, its shape), the fitted
decoder's width: in this shape (the light's x and y only, the codes at 8 bits) the dome sample's Test lights
lost 5.2 dB and the statue's held-out lights 2.5 dB against the fields after 120 s of distillation on 2 cores
(``benchmarks/bench_openlime.py``); 48-48 students of the usual shape lost 0.50 and 1.73 (``DistilSettings``)."""
NEURAL_SECONDS = 120.0
"""The neural layer's distillation time, seconds, unless told: ``DistilSettings.seconds``'s default (on 2 cores, 60
epochs of the dome sample at 160 x 160). Longer comes closer to the field's images."""
SEEING_NOTE = ("the field's decoder sees the highlights; OpenLIME's neural layer takes code and light only, so there "
               "they cross-fade between the lights rather than move (they move in this project's own page: export "
               "FIELD)")
"""The line a neural export of a decoder that sees the highlights adds to its figures (``note``) and its log."""
_PTM_TO_OPENLIME = (5, 3, 4, 0, 2, 1)  # a .ptm file's coefficients, picked in OpenLIME's order
_UNBOUNDED_EPOCHS = 1_000_000  # the distillation's epochs when its time ends it
_CODE_PLANES = 9  # OpenLIME's neural layer takes 9 codes a pixel, three a JPEG
RBF_PLANES = 18
"""Principal components an ``rbf`` export keeps: relight's default for its rbf and bilinear fits (6 JPEGs)."""
QUANTILES = (0.0025, 0.9975)
"""Each plane's quantisation range, as relight's ``rangeQuantile`` 0.995 (outliers clamp to it)."""
JPEG_QUALITY = 95
"""relight's JPEG quality for the planes."""
_PI = 3.1415  # OpenLIME's value of pi in its HSH weights
_HSH_MIN_ELEVATION = 0.15  # OpenLIME clamps the light's polar angle at _PI / 2 - this (radians)
_RBF_ALPHA, _RBF_BETA = 8.0, 2.0  # OpenLIME's adaptive RBF: k = alpha / (d weighted by e^(-beta d))
_BAND_VALUES = 1 << 24  # float64 values of one band of rows in the least-squares fit and the projections


def export_openlime(values: np.ndarray, directions: np.ndarray, folder, *, model: str,
                    planes: int = RBF_PLANES) -> dict:
    """Write ``values`` (n, H, W, 3) display values in [0, 1] at the (n, 3) light directions as ``model``
    (``OPENLIME_MODELS``) into ``folder`` (existing and empty): ``info.json`` and the plane JPEGs. Returns the
    info.json object."""
    if model not in OPENLIME_MODELS:
        raise InputError(f"OpenLIME model {model!r}: one of {', '.join(OPENLIME_MODELS)}")
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 4 or values.shape[3] != 3:
        raise InputError("OpenLIME's RTI layer shows colour (RGB) captures; this capture has one channel")
    directions = _unit(directions)
    n, height, width, _ = values.shape
    info: dict = {"width": int(width), "height": int(height), "format": "jpg", "type": model, "quality": JPEG_QUALITY,
                  "lights": [round(float(v), 6) for v in directions.ravel()]}
    if model != "rbf":
        basis = openlime_weights(model, directions)
        if n < basis.shape[1]:
            raise InputError(f"a {model.upper()} fit needs at least {basis.shape[1]} lights; the capture has {n}")
        # (H, W, M, 3): plane 3j + c is coefficient j of channel c
        return export_openlime_coefficients(_least_squares(values, basis), folder, model=model, extra=info)
    coefficients, extra = _principal_planes(values, planes)
    info.update(colorspace="mrgb", nplanes=int(coefficients.shape[-1]))
    scale, bias = _write_planes(coefficients, Path(folder))
    info["materials"] = [{"scale": scale, "bias": bias, "range": extra.pop("range")}]
    info.update(extra)
    Path(folder, "info.json").write_text(json.dumps(info))
    return info


def export_openlime_coefficients(coefficients: np.ndarray, folder, *, model: str, extra: dict | None = None) -> dict:
    """Write (H, W, M, 3) ``ptm`` (M = 6 in OpenLIME's order 1, x, y, x^2, xy, y^2) or ``hsh`` (M = 4 or 9)
    coefficients of display values into ``folder`` (existing and empty) as OpenLIME's ``rgb`` layer; ``extra``:
    more info.json entries (the lights). Returns the info.json object."""
    coefficients = np.asarray(coefficients, np.float32)
    height, width, terms, _ = coefficients.shape
    info = {"width": int(width), "height": int(height), "format": "jpg", "type": model, "quality": JPEG_QUALITY,
            **(extra or {}), "colorspace": "rgb", "nplanes": int(3 * terms)}
    scale, bias = _write_planes(coefficients.reshape(height, width, -1), Path(folder))
    info["materials"] = [{"scale": scale, "bias": bias}]
    Path(folder, "info.json").write_text(json.dumps(info))
    return info


def openlime_coefficients(model) -> np.ndarray:
    """(H, W, M, 3) a legacy file's (``io.legacy_rti.LegacyRTI``) coefficients in the order of OpenLIME's basis:
    a PTM's lu^2, lv^2, lu lv, lu, lv, 1 as 1, x, y, x^2, xy, y^2; an HSH's as they are."""
    return model.coefficients[:, :, list(_PTM_TO_OPENLIME)] if model.kind == "ptm" else model.coefficients


def export_openlime_neural(field, folder, *, hidden=NEURAL_HIDDEN_OPENLIME, seconds: float = NEURAL_SECONDS,
                           settings=None, log=None, progress=None) -> tuple[dict, dict]:
    """Write ``field``'s learned residual as OpenLIME's neural layer into ``folder`` (existing and empty): the codes
    as ``plane_1.jpg`` .. ``plane_3.jpg`` and ``info.json`` with the distilled decoder (``hidden`` widths, padded
    to multiples of 4 with zero units), distilled for ``seconds`` (its learning rate falling over them), or as
    ``settings`` (a ``DistilSettings``) say. Returns the info.json object and the distillation's figures
    (``residual.distil.distil_display_decoder``; ``note``: ``SEEING_NOTE`` where the field's decoder sees the
    highlights, its teacher then the field's relit image, which ``log`` is told too)."""
    from ..model.config import DistilSettings
    from ..residual.distil import distil_display_decoder

    if settings is None:  # the time, not an epoch count, ends it: a longer distillation comes closer
        settings = DistilSettings(hidden=tuple(hidden), seconds=float(seconds), epochs=_UNBOUNDED_EPOCHS)

    residual = field.residual
    if residual is None or residual.learned is None:
        kind = "no residual" if residual is None else f"a {residual.kind} residual"
        raise InputError(f"the field holds {kind}: OpenLIME's neural layer shows a learned one (fit with --residual "
                         "learned), or export the capture's PTM, HSH or RBF with --model")
    learned = residual.learned
    codes = np.asarray(learned.codes, np.float32)
    height, width, count = codes.shape
    if count != _CODE_PLANES:
        raise InputError(f"the field's learned residual has {count} codes a pixel; OpenLIME's neural layer takes 9")
    low, high = codes.reshape(-1, count).min(axis=0), codes.reshape(-1, count).max(axis=0)
    high = np.where(high > low, high, low + 1e-6)
    folder = Path(folder)
    quantised = np.clip(np.round(255.0 * (codes - low) / (high - low)), 0, 255).astype(np.uint8)
    for k in range(3):
        Image.fromarray(quantised[..., 3 * k : 3 * k + 3], "RGB").save(
            folder / f"plane_{k + 1}.jpg", quality=JPEG_QUALITY, subsampling=0)
    stored = np.concatenate([np.asarray(Image.open(folder / f"plane_{k + 1}.jpg").convert("RGB"), np.float64)
                             for k in range(3)], axis=2) / 255.0 * (high - low) + low
    directions, faces = _upper_lights(field)
    highlights = _moved_highlights(field) if learned.sees_highlights else None
    weights, figures = distil_display_decoder(learned, stored.astype(np.float32), hidden, directions, faces,
                                              exposure=field.exposure, settings=settings, log=log, progress=progress,
                                              highlights=highlights)
    if learned.sees_highlights:
        figures["note"] = SEEING_NOTE
        if log is not None:
            log(SEEING_NOTE)
    samples = -(-max(int(w) for w in hidden) // 4) * 4
    padded_inputs = (_CODE_PLANES + 2 + 3) // 4 * 4  # the codes, x, y and a zero: 12
    layers, biases = [], []
    inputs = padded_inputs
    for index in range(0, len(weights), 2):
        w, b = weights[index], weights[index + 1][:, 0]
        outputs = 3 if index == len(weights) - 2 else samples
        block = np.zeros((outputs, inputs), np.float64)
        block[: w.shape[0], : w.shape[1]] = w
        bias = np.zeros(outputs)
        bias[: len(b)] = b
        layers.append([round(float(v), 7) for v in block.ravel()])
        biases.append([round(float(v), 7) for v in bias])
        inputs = samples
    info = {"width": int(width), "height": int(height), "format": "jpg", "type": "neural", "quality": JPEG_QUALITY,
            "planes": _CODE_PLANES, "samples": samples, "colorspace": "rgb",
            "min": [float(v) for v in low], "max": [float(v) for v in high], "weights": layers, "biases": biases}
    (folder / "info.json").write_text(json.dumps(info))
    return info, figures


def _moved_highlights(field):
    """(D, 3) directions -> (D, H, W) float32 the luminance of ``field``'s Gaussians moved to them (circular paths,
    field units: the relighter's S', which a decoder that sees the highlights takes)."""
    import dataclasses

    from ..relight.relighter import Relighter

    relighter = Relighter(dataclasses.replace(field, residual=None), diffuse="none")
    return lambda directions: relighter.relight(np.asarray(directions, np.float64).reshape(-1, 3), full=False).specular


def _upper_lights(field) -> tuple[np.ndarray, np.ndarray]:
    """The field's lights above the image plane and the triangles among them: OpenLIME's neural layer takes the
    light's (x, y) only, which cannot tell a light below the plane from its mirror image above."""
    directions = np.asarray(field.lights.directions, np.float64)
    upper = directions[:, 2] > 0
    faces = np.asarray(field.triangulation.faces, np.int64)
    faces = faces[upper[faces].all(axis=1)]
    if not len(faces):
        raise InputError("the field has no triangle of lights above the image plane (z > 0): OpenLIME's neural "
                         "layer relights from the upper hemisphere only")
    renumbered = np.cumsum(upper) - 1
    return directions[upper], renumbered[faces]


def openlime_weights(model: str, directions, *, info: dict | None = None) -> np.ndarray:
    """(Q, M) float64 the basis values OpenLIME gives the (Q, 3) light directions (only x and y count: z is
    sqrt(1 - x^2 - y^2), (x, y) scaled to unit length beyond it): ``ptm`` (M = 6), ``hsh`` (M = 9); for
    ``rbf``, the (Q, n) adaptive weights of the n lights of ``info``."""
    xy = np.asarray(directions, dtype=np.float64).reshape(-1, 3)[:, :2].copy()
    radius = np.hypot(xy[:, 0], xy[:, 1])
    xy[radius > 1] /= radius[radius > 1, None]
    x, y = xy[:, 0], xy[:, 1]
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    if model == "ptm":
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    if model == "hsh":
        phi = np.arctan2(y, x)
        phi = np.where(phi < 0, 2 * _PI + phi, phi)
        theta = np.minimum(np.arccos(np.clip(z, -1, 1)), _PI / 2 - _HSH_MIN_ELEVATION)
        ct = np.cos(theta)
        s = np.sqrt(np.maximum(ct - ct * ct, 0.0))
        cp, sp = np.cos(phi), np.sin(phi)
        return np.stack([
            np.full_like(x, 1 / math.sqrt(2 * _PI)),
            math.sqrt(6 / _PI) * cp * s,
            math.sqrt(3 / (2 * _PI)) * (2 * ct - 1),
            math.sqrt(6 / _PI) * s * sp,
            math.sqrt(30 / _PI) * np.cos(2 * phi) * (ct * ct - ct),
            math.sqrt(30 / _PI) * cp * (2 * ct - 1) * s,
            math.sqrt(5 / (2 * _PI)) * (1 - 6 * ct + 6 * ct * ct),
            math.sqrt(30 / _PI) * (2 * ct - 1) * s * sp,
            math.sqrt(30 / _PI) * (ct * ct - ct) * np.sin(2 * phi),
        ], axis=1)
    if model == "rbf":
        if info is None:
            raise ValueError("rbf weights need the export's info (its lights)")
        lights = np.asarray(info["lights"], dtype=np.float64).reshape(-1, 3)
        queries = np.stack([x, y, z], axis=1)
        distance = np.linalg.norm(queries[:, None, :] - lights[None], axis=2)
        falloff = np.exp(-_RBF_BETA * distance)
        spread = (distance * falloff).sum(axis=1) / falloff.sum(axis=1)
        weights = np.exp(-(_RBF_ALPHA / spread)[:, None] * distance ** 2)
        return weights / weights.sum(axis=1, keepdims=True)
    raise InputError(f"OpenLIME model {model!r}: one of {', '.join(OPENLIME_MODELS)}")


def relight_openlime(folder, directions) -> np.ndarray:
    """(Q, H, W, 3) float64 display values: the export in ``folder`` relit at the (Q, 3) directions as OpenLIME's
    shader computes them (before its 8-bit output), from the planes as decoded from their JPEGs."""
    folder = Path(folder)
    try:
        info = json.loads((folder / "info.json").read_text())
        if info.get("type") == "neural":
            return _relight_neural(folder, info, directions)
        model, nplanes = info["type"], int(info["nplanes"])
        material = info["materials"][0]
        scale, bias = np.asarray(material["scale"], np.float64), np.asarray(material["bias"], np.float64)
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise InputError(f"{folder}: not an OpenLIME RTI export ({exc})") from exc
    jpegs = [np.asarray(Image.open(folder / f"plane_{j}.jpg").convert("RGB"), np.float64) / 255.0
             for j in range(math.ceil(nplanes / 3))]
    planes = np.concatenate(jpegs, axis=2)[..., :nplanes]
    coefficients = (planes - bias) * scale  # (H, W, nplanes)
    if model == "rbf":
        weights = openlime_weights("rbf", directions, info=info)  # (Q, n)
        lights = weights.shape[1]
        basis = np.asarray(info["basis"], np.float64).reshape(nplanes + 1, lights, 3)
        ranges = np.asarray(material["range"], np.float64)
        components = np.concatenate([basis[:1] / 255.0, (basis[1:] - 127.0) / ranges[:, None, None]])
        blended = np.einsum("qi,tic->qtc", weights, components)  # (Q, nplanes + 1, 3)
        return blended[:, None, None, 0, :] + np.einsum("hwp,qpc->qhwc", coefficients, blended[:, 1:, :])
    weights = openlime_weights(model, directions)[:, : nplanes // 3]
    height, width = coefficients.shape[:2]
    return np.einsum("qm,hwmc->qhwc", weights, coefficients.reshape(height, width, -1, 3))


def _relight_neural(folder: Path, info: dict, directions) -> np.ndarray:
    """OpenLIME's neural layer: the codes from the JPEGs between ``min`` and ``max``, the decoder over the codes and
    the light's (x, y), ELU hidden layers, its output the display values."""
    low, high = np.asarray(info["min"], np.float64), np.asarray(info["max"], np.float64)
    codes = np.concatenate([np.asarray(Image.open(folder / f"plane_{k + 1}.jpg").convert("RGB"), np.float64)
                            for k in range(3)], axis=2) / 255.0 * (high - low) + low
    height, width, _ = codes.shape
    samples = int(info["samples"])
    shapes = [(samples, -1), (samples, samples), (3, samples)]
    layers = [np.asarray(w, np.float64).reshape(shape) for w, shape in zip(info["weights"], shapes)]
    biases = [np.asarray(b, np.float64) for b in info["biases"]]
    flat = codes.reshape(-1, _CODE_PLANES)
    images = []
    for x, y, _ in np.asarray(directions, np.float64).reshape(-1, 3):
        values = np.concatenate([flat, np.tile([x, y], (len(flat), 1)), np.zeros((len(flat), layers[0].shape[1]
                                                                                   - _CODE_PLANES - 2))], axis=1)
        for w, b in zip(layers[:-1], biases[:-1]):
            z = values @ w.T + b
            values = np.where(z > 0, z, np.expm1(np.minimum(z, 0.0)))
        images.append((values @ layers[-1].T + biases[-1]).reshape(height, width, 3))
    return np.stack(images)


def _unit(directions) -> np.ndarray:
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _least_squares(values: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(H, W, M, 3) float32 the least-squares coefficients of the (n, H, W, 3) values in the (n, M) basis, a band
    of rows at a time."""
    n, height, width, _ = values.shape
    solve = np.linalg.pinv(basis)  # (M, n)
    out = np.empty((height, width, basis.shape[1], 3), np.float32)
    rows = max(1, _BAND_VALUES // max(1, n * width * 3))
    for top in range(0, height, rows):
        band = values[:, top : top + rows].astype(np.float64)
        out[top : top + rows] = np.einsum("mn,nhwc->hwmc", solve, band)
    return out


def _principal_planes(values: np.ndarray, planes: int) -> tuple[np.ndarray, dict]:
    """(H, W, P) float32 each pixel's coefficients on the first P principal components of its 3n values (every
    light and channel), and the info entries: ``basis`` (the mean as bytes, each component at 127 + range
    times its values, (P + 1) x n x 3 integers in 0..255) and ``range`` (P,)."""
    n, height, width, _ = values.shape
    planes = max(1, min(int(planes), 3 * n, height * width))
    rows = max(1, _BAND_VALUES // max(1, n * width * 3))
    total = np.zeros(3 * n)
    products = np.zeros((3 * n, 3 * n))
    for top in range(0, height, rows):
        band = values[:, top : top + rows].transpose(1, 2, 0, 3).reshape(-1, 3 * n).astype(np.float64)
        total += band.sum(axis=0)
        products += band.T @ band
    count = height * width
    mean = total / count
    covariance = products / count - np.outer(mean, mean)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    components = eigenvectors[:, ::-1][:, :planes].T  # (P, 3n), largest variance first
    ranges = 127.0 / np.maximum(np.abs(components).max(axis=1), 1e-12)
    mean_bytes = np.clip(np.round(255.0 * mean), 0, 255)
    component_bytes = np.clip(np.round(127.0 + ranges[:, None] * components), 0, 255)
    # project on the components as the page will decode them: the quantised mean and components
    decoded_mean = mean_bytes / 255.0
    decoded = (component_bytes - 127.0) / ranges[:, None]
    solve = np.linalg.pinv(decoded.T)  # (P, 3n): least squares on the decoded components
    coefficients = np.empty((height, width, planes), np.float32)
    for top in range(0, height, rows):
        band = values[:, top : top + rows].transpose(1, 2, 0, 3).astype(np.float64)
        shape = band.shape[:2]
        centred = band.reshape(-1, 3 * n) - decoded_mean
        coefficients[top : top + rows] = (centred @ solve.T).reshape(*shape, planes)
    basis = np.concatenate([mean_bytes[None], component_bytes]).reshape(planes + 1, n, 3)
    return coefficients, {"basis": [int(v) for v in basis.ravel()], "range": [float(r) for r in ranges]}


def _write_planes(coefficients: np.ndarray, folder: Path) -> tuple[list[float], list[float]]:
    """Quantise the (H, W, P) planes (each between its ``QUANTILES``) into ``plane_j.jpg`` (planes 3j..3j+2 in its
    R, G, B; a last JPEG's missing channels 0) in ``folder``; returns each plane's scale and bias."""
    height, width, count = coefficients.shape
    scale, bias = [], []
    padded = math.ceil(count / 3) * 3
    quantised = np.zeros((height, width, padded), np.uint8)
    for p in range(count):
        plane = coefficients[..., p]
        low, high = (float(v) for v in np.quantile(plane, QUANTILES))
        if not high > low:
            high = low + 1e-6
        quantised[..., p] = np.clip(np.round(255.0 * ((plane - low) / (high - low))), 0, 255)
        scale.append(high - low)
        bias.append(-low / (high - low))
    for j in range(padded // 3):
        Image.fromarray(quantised[..., 3 * j : 3 * j + 3], "RGB").save(
            folder / f"plane_{j}.jpg", quality=JPEG_QUALITY, subsampling=0)
    return scale, bias
