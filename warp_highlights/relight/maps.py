"""Surface maps of a fitted field: per-pixel normal, albedo and highlight colour (``warp-highlights maps``).

The field gives its captured images back (relit at the captured lights: residual plus the lights' own
highlights), and every pixel's normal is fitted to them by robust photometric stereo: least squares
of Y_i = rho n . omega_i (Y the luminance) over the lights that lit the pixel (at least
``MapSettings.lit_fraction`` of its typical lit value, so shadows stay out), refitted without the
lights whose residual is over ``MapSettings.outlier_factor`` times the median one (highlights).

Outliers, and how they are kept out (``MapSettings`` holds every threshold):

- **Clipped lights.** A light whose value reaches the capture's white in any channel (``saturation``;
  8- and 16-bit captures, ``white_level``) is left out of the pixel's fit: its shading is unknown.
- **Cast shadows under most lights** (a deep crease). The pixel's typical value is then the room's
  ambient light: its shadowed lights pass as lit, its sunlit ones leave as highlights, and the fit
  finds an albedo at the ambient level and a normal near the mean light direction (the statue's dark
  dots). Such a fit is *suspect* when it explains little of its values' variance (R^2 under
  ``min_explained``) and its albedo is under ``dark_ratio`` of its neighbourhood's (the
  ``lit_percentile`` of the first fits' albedos within ``neighbourhood`` pixels). A suspect pixel is
  fitted again from its brightest lights (``shadow_fraction`` of its ``shadow_percentile``), leaving
  out the lights below ``shadow_ratio`` of the fitted shading; this *shadow fit* replaces the first
  where it explains its values (at least ``min_explained``), rests on ``min_lit_lights``
  sunlit lights (n . w at least ``shadow_fraction``), finds an albedo within a factor 1 / ``dark_ratio``
  of the neighbourhood's, and ``shadow_support`` pixels of its (2 ``shadow_window`` + 1)^2 window took it
  too (a cast shadow covers a region; on a metal's rim single pixels fitted their highlights).
- **Undetermined pixels.** A pixel's own lights determine its normal when its fit uses at least
  ``min_lit_lights`` lights whose directions spread (``min_spread``: the smallest eigenvalue of the
  normal equations' sum of w w^T, so they are well conditioned), explains more than the values' mean
  does (R^2 over 0, beyond ``noise_tolerance``) and faces the camera. Other pixels of the object (not
  black) take the mean normal and albedo of their determined 8-neighbours, a ring at a time up to
  ``neighbourhood`` rings (``SurfaceMaps.filled``), rather than an outlier; farther ones have none.

- the **normal** n: unit vectors in the light frame of the ``.lp`` file (x right, y up the image,
  z towards the camera), so a surface facing the camera is (0, 0, 1);
- the **albedo** per channel: the least-squares rho_c of I_c = rho_c n . omega over the same lights,
  the pixel's diffuse value under a unit light along its normal, in the input's linear units (the
  fit's exposure undone); ambient light adds to it (the rendered sphere's ambient of 2%: 0.63 for
  its 0.6);
- the **highlight colour** is the field's c(x) (luminance 1; white where the field keeps none).

Why not segmentation's fit, which has nbar too: its ambient term k_a trades off against n_z when the
lights' elevations span little (the statue's 0.38-0.99), and its normals leant far over (8.6
degrees median from these, 1.3% facing away from the camera), with one threshold for the whole image.

Lights at a finite distance (every real dome, a handheld light) make a flat object's normals lean
away from the image centre, because the ``.lp`` file gives one direction per light for the whole
object: on the dome sample by 3.2 degrees (median, 0.38 flattened) against the normals its renderer
wrote; on a plate lit from 3 half-widths away, by tens of degrees (tests/test_maps.py). ``flatten``
removes that trend: it fits a plane to each slope (n_x / n_z and n_y / n_z) over the image and
subtracts it, keeping the mean tilt; ``level`` also subtracts the median slope left, so that the
object's typical orientation (a relief's or a coin's base) faces the camera: a whole-object tilt, or
a bias in the light directions, cannot be told apart from a tilted object, so this is the user's
call. Both are for flat objects and reliefs (coins, tablets, paintings, carved panels): on a curved
object they take away true shape. ``SurfaceMaps.lean`` says how much there was (``normal_lean``).

A pixel is in the ``mask`` where its own lights determine its normal or its neighbours' fill it;
elsewhere (black background, pixels farther than ``neighbourhood`` from any determined one) the normal
is (0, 0, 1) and the albedo 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.config import FLATTEN_MODES, MapSettings
from ..model.errors import InputError
from ..model.memory import check_memory
from ..model.residual import LUMINANCE_WEIGHTS
from .relighter import Relighter

__all__ = ["NormalFit", "NormalLean", "SurfaceMaps", "channel_albedo", "fill_from_neighbours", "fit_normals",
           "flatten_normals", "maps_from_images", "normal_lean", "surface_maps", "white_level"]

_FLAT = np.array([0.0, 0.0, 1.0], dtype=np.float32)  # the normal of a pixel without an estimate
_MIN_NBAR = 1e-6  # |rho n| below this (field units) is no surface: a black or never-lit pixel
_PIXELS_PER_BLOCK = 65_536  # pixels solved at once: bounds the (lights x pixels) temporaries
_CLIPPED_FORMATS = ("PNG", "JPEG")  # integer files whose 1 is white (sRGB TIFFs too: ``white_level``)


@dataclass(frozen=True)
class NormalLean:
    """How a normal map leans as a whole (``normal_lean``), in degrees.

    Attributes:
        edge_deg: how much farther from the camera axis the slopes' linear trend turns a normal at the
            frame's farthest corner than at its centre (near lights make a flat object's normals lean
            away from the centre; a curved object's own shape has such a trend too).
        tilt_deg: the median normal's angle to the camera axis once that trend is removed (the object
            tilted as a whole, or a bias in the light directions).
    """

    edge_deg: float
    tilt_deg: float


@dataclass(frozen=True)
class SurfaceMaps:
    """What ``surface_maps`` estimates, at the field's working size.

    Attributes:
        normals: (H, W, 3) float32 unit normals in the light frame (x right, y up the image, z towards
            the camera); (0, 0, 1) outside ``mask``.
        albedo: (H, W, C) float32 >= 0, diffuse value under a unit light along the normal, input units.
        highlight_colour: (H, W, C) float32 >= 0, the field's c(x) (luminance 1), ones without one.
        mask: (H, W) bool, pixels with a normal (their own, or their neighbours' where ``filled``).
        lit_lights: (H, W) int32, lights the pixel's final fit used (lit, not outliers); 0 where filled.
        coloured_highlights: whether the field stores a per-pixel highlight colour.
        filled: (H, W) bool, pixels whose own lights determine no normal, with their neighbours' mean
            normal and albedo (in ``mask``).
        shadow_fit: (H, W) bool, pixels whose normal and albedo come from the shadow fit (cast shadows
            under most lights).
        lean: how the normals leaned as a whole before any flattening (``NormalLean``).
    """

    normals: np.ndarray
    albedo: np.ndarray
    highlight_colour: np.ndarray
    mask: np.ndarray
    lit_lights: np.ndarray
    coloured_highlights: bool
    filled: np.ndarray
    shadow_fit: np.ndarray
    lean: NormalLean


def white_level(field) -> float | None:
    """The capture's white in the field's units (the fit's exposure) when its files clip there (8- or
    16-bit PNG, JPEG or sRGB TIFF, from the field's report), else None (EXR, float or unknown input)."""
    source = (getattr(field, "report", None) or {}).get("input") or {}
    clipped = source.get("format") in _CLIPPED_FORMATS or (
        source.get("format") == "TIFF" and source.get("values") == "sRGB" and int(source.get("bits", 32)) <= 16)
    return float(field.exposure) if clipped else None


def surface_maps(field, *, device=None, flatten: bool | str = False, settings: MapSettings | None = None,
                 progress=None) -> SurfaceMaps:
    """Normal, albedo and highlight-colour maps of a ``HighlightField`` (see the module docstring).

    ``settings``: which lights light a pixel (``MapSettings``, default its defaults).
    ``flatten``: False, or one of ``FLATTEN_MODES`` (True: ``trend``): remove the slopes' linear trend
    over the image, and with ``level`` the median tilt too (``flatten_normals``; flat objects and reliefs).
    ``progress``: optional callable(lights_done) while the captured images are relit (the long part
    for a learned residual on the CPU).

    Raises:
        InputError: the field holds no diffuse part (fitted with neither a residual nor a diffuse model).
    """
    if field.residual is None and field.diffuse is None:
        raise InputError("the field holds only highlights (no residual or diffuse model), so it has no "
                         "normals or albedo; "
                         "fit it again without --residual none")
    if flatten is True:
        flatten = "trend"
    if flatten not in (False, None, *FLATTEN_MODES):
        raise ValueError(f"flatten must be False or one of {FLATTEN_MODES}, not {flatten!r}")
    settings = settings or MapSettings()
    channels = field.residual.channels if field.residual is not None else field.diffuse.channel_count
    pixels = field.width * field.height
    check_memory(field.light_count * pixels * (4 * channels + 10),
                 f"surface maps of {field.light_count} lights at {field.width}x{field.height}",
                 "fit the field at a smaller --size",
                 detail="the captured images as float32, their luminance as float64, the clipped lights")
    relighter = Relighter(field, device=device, scale=1.0)  # field units; the albedo leaves them below
    directions = field.lights.directions
    # (n, H, W, C): the captured images, as the field keeps them
    captured = relighter.relight(directions, progress=progress).full
    colour = None if field.residual is None else field.residual.highlight_colour
    return maps_from_images(captured, directions, exposure=field.exposure, white=white_level(field),
                            highlight_colour=colour, flatten=flatten, settings=settings)


def maps_from_images(captured: np.ndarray, directions: np.ndarray, *, exposure: float = 1.0,
                     white: float | None = None, highlight_colour: np.ndarray | None = None,
                     flatten: bool | str = False, settings: MapSettings | None = None) -> SurfaceMaps:
    """``surface_maps`` of (n, H, W[, C]) images (linear, in units of which ``exposure`` is one display white) at
    the (n, 3) light ``directions``: what a field's captured lights give, or a classic RTI model relit at any
    lights. ``white``: the saturation level of the images (None: none clip); ``highlight_colour``: (H, W, C), or
    None for white."""
    if flatten is True:
        flatten = "trend"
    settings = settings or MapSettings()
    captured = np.maximum(np.nan_to_num(captured, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    if captured.ndim == 3:
        captured = captured[..., None]
    count, height, width, channels = captured.shape
    usable = None
    if white is not None:
        usable = ~np.any(captured >= settings.saturation * white, axis=3).reshape(len(directions), -1)
    weights = np.asarray(LUMINANCE_WEIGHTS if channels == 3 else (1.0,), dtype=np.float32)
    luminance = (captured @ weights).reshape(len(directions), -1)  # (n, P)
    shape = (height, width)
    fit = fit_normals(luminance, directions, settings=settings, usable=usable, shape=shape)
    del luminance, usable
    determined = fit.mask.reshape(shape)
    normals = fit.normals.reshape(height, width, 3)
    albedo = channel_albedo(captured.reshape(len(directions), -1, channels), directions, fit.normals, fit.inliers)
    del captured
    albedo = np.where(determined[..., None], albedo.reshape(height, width, channels), 0.0)
    known = np.concatenate([normals.astype(np.float64), albedo], axis=2)
    known, mask = fill_from_neighbours(known, determined, fit.surface.reshape(shape), settings.neighbourhood)
    filled = mask & ~determined
    normals, albedo = known[..., :3], known[..., 3:]
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    mask &= length[..., 0] > 0
    normals = np.where(mask[..., None], normals / np.where(length > 0, length, 1.0), _FLAT)
    lean = normal_lean(normals, mask)
    if flatten:
        normals = flatten_normals(normals, mask, level=flatten == "level")
    albedo = np.where(mask[..., None], albedo, 0.0) / exposure
    colour = highlight_colour
    if colour is None:
        colour = np.ones((height, width, channels), dtype=np.float32)
    return SurfaceMaps(
        normals=normals.astype(np.float32),
        albedo=np.nan_to_num(albedo, nan=0.0, posinf=0.0).astype(np.float32),
        highlight_colour=np.maximum(np.asarray(colour, dtype=np.float32), 0.0),
        mask=mask,
        lit_lights=fit.inliers.sum(axis=0).reshape(shape).astype(np.int32),
        coloured_highlights=highlight_colour is not None,
        filled=filled & mask,
        shadow_fit=fit.shadow_fit.reshape(shape) & mask,
        lean=lean,
    )


def fill_from_neighbours(values: np.ndarray, known: np.ndarray, targets: np.ndarray,
                         radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, K) ``values`` with the ``targets`` pixels that are not ``known`` set to the mean of their
    known 8-neighbours, a ring at a time (each ring's new values count for the next), at most
    ``radius`` rings. Returns (float64 values, (H, W) bool: known or filled); pixels neither keep
    their values."""
    values = np.array(values, dtype=np.float64)
    known = np.asarray(known, dtype=bool).copy()
    targets = np.asarray(targets, dtype=bool)
    for _ in range(int(radius)):
        todo = targets & ~known
        if not todo.any():
            break
        weight = _sum_3x3(known.astype(np.float64))
        new = todo & (weight > 0)
        if not new.any():
            break
        sums = _sum_3x3(np.where(known[..., None], values, 0.0))
        values[new] = sums[new] / weight[new][:, None]
        known |= new
    return values, known


def _sum_3x3(image: np.ndarray) -> np.ndarray:
    """Each pixel's sum over its 3x3 neighbourhood (itself included), zero outside the image."""
    padded = np.pad(image, [(1, 1), (1, 1)] + [(0, 0)] * (image.ndim - 2))
    height, width = image.shape[:2]
    return sum(padded[dy:dy + height, dx:dx + width] for dy in range(3) for dx in range(3))


def _slope_trend(normals: np.ndarray, mask: np.ndarray):
    """The slopes (n_x / n_z, n_y / n_z) of (H, W, 3) ``normals``, their least-squares linear trend
    b u + c v over the ``mask`` pixels (u, v the pixel centre in [-1, 1] across the image; the constant
    a absorbs the mean) and the median of what is left there: (slopes (H, W, 2), trend (H, W, 2),
    median (2,)), float64."""
    normals = np.asarray(normals, dtype=np.float64)
    height, width = normals.shape[:2]
    v, u = np.mgrid[0:height, 0:width]
    u = (u + 0.5) / width * 2.0 - 1.0
    v = (v + 0.5) / height * 2.0 - 1.0
    design = np.stack([np.ones(np.count_nonzero(mask)), u[mask], v[mask]], axis=1)
    slopes = normals[..., :2] / normals[..., 2:3]  # finite: mask pixels face the camera (n_z > 0)
    trend = np.zeros_like(slopes)
    for axis in range(2):
        coefficients = np.linalg.lstsq(design, slopes[..., axis][mask], rcond=None)[0]
        trend[..., axis] = coefficients[1] * u + coefficients[2] * v
    return slopes, trend, np.median((slopes - trend)[mask], axis=0)


def _unit_from_slopes(slopes: np.ndarray) -> np.ndarray:
    """(..., 3) unit normals whose n_x / n_z and n_y / n_z are the (..., 2) ``slopes`` (n_z > 0)."""
    normals = np.concatenate([slopes, np.ones(slopes.shape[:-1] + (1,))], axis=-1)
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def flatten_normals(normals: np.ndarray, mask: np.ndarray, *, level: bool = False) -> np.ndarray:
    """(H, W, 3) unit normals with the linear trend of their slopes over the image removed.

    The slopes n_x / n_z and n_y / n_z of the ``mask`` pixels are each fitted, by least squares, with
    a + b u + c v (u, v the pixel centre in [-1, 1] across the image) and b u + c v is subtracted:
    the mean tilt stays. ``level``: the median of the slopes left is subtracted as well, so the
    object's typical orientation (a relief's or a coin's base) faces the camera. Pixels outside
    ``mask`` are returned unchanged; fewer than 3 pixels in ``mask`` change nothing. float64
    arithmetic, float32 result.
    """
    normals = np.asarray(normals, dtype=np.float64)
    if np.count_nonzero(mask) < 3:
        return normals.astype(np.float32)
    slopes, trend, median = _slope_trend(normals, mask)
    flat = normals.copy()
    flat[mask] = _unit_from_slopes(slopes - trend - (median if level else 0.0))[mask]
    return flat.astype(np.float32)


def normal_lean(normals: np.ndarray, mask: np.ndarray) -> NormalLean:
    """How (H, W, 3) unit ``normals`` lean as a whole over the ``mask`` pixels (``NormalLean``); zeros
    with fewer than 3 pixels."""
    if np.count_nonzero(mask) < 3:
        return NormalLean(0.0, 0.0)
    _, trend, median = _slope_trend(normals, mask)
    corners = trend[[0, 0, -1, -1], [0, -1, 0, -1]]  # the trend is zero at the centre
    edge = float(np.degrees(np.arctan(np.linalg.norm(corners, axis=-1).max())))
    tilt = float(np.degrees(np.arctan(np.linalg.norm(median))))
    return NormalLean(edge_deg=edge, tilt_deg=tilt)


@dataclass(frozen=True)
class NormalFit:
    """What ``fit_normals`` found per pixel: ``normals`` (P, 3) float64 unit vectors ((0, 0, 1) outside
    ``mask``), ``mask`` (P,) bool: pixels whose own lights determine the normal, ``inliers`` (n, P)
    bool: the lights of the final fit, ``surface`` (P,) bool: pixels that are not black (a surface,
    determined or not), ``shadow_fit`` (P,) bool: pixels whose normal comes from the shadow fit."""

    normals: np.ndarray
    mask: np.ndarray
    inliers: np.ndarray
    surface: np.ndarray
    shadow_fit: np.ndarray


def fit_normals(luminance: np.ndarray, directions: np.ndarray, *, settings: MapSettings | None = None,
                usable: np.ndarray | None = None, shape: tuple[int, int] | None = None) -> NormalFit:
    """Robust photometric stereo of (n, P) luminance stacks (linear, >= 0) under (n, 3) unit light
    directions, all pixels at once (float64; see the module docstring for the rule).

    ``usable``: (n, P) bool, the samples that may enter a fit (False: clipped); all where None.
    ``shape``: (H, W) with H * W = P when the pixels are an image's, row by row: a fit is judged dark
    against its neighbourhood and a shadow fit needs its neighbours' support; None: a fit is judged
    against all pixels and a shadow fit needs no support.
    """
    settings = settings or MapSettings()
    luminance = np.asarray(luminance, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    count, pixels = luminance.shape
    if usable is not None and np.shape(usable) != (count, pixels):
        raise ValueError(f"usable must be ({count}, {pixels}), got {np.shape(usable)}")
    if shape is not None and int(shape[0]) * int(shape[1]) != pixels:
        raise ValueError(f"shape {tuple(shape)} does not hold {pixels} pixels")
    usable = np.ones((count, pixels), dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    scaled, used = np.zeros((pixels, 3)), np.zeros((count, pixels), dtype=bool)
    surface, explained, shading = (np.zeros(pixels, dtype=bool) for _ in range(3))
    for block in _blocks(np.arange(pixels)):
        values = luminance[:, block]
        lit, typical, surface[block] = _lit(values, usable[:, block], settings)
        scaled[block], used[:, block] = _robust_fit(values, directions, lit, lit, typical, settings, shadows=False)
        explained[block] = _explained(values, directions, scaled[block], used[:, block], settings.min_explained,
                                      settings.noise_tolerance)
        shading[block] = _explained(values, directions, scaled[block], used[:, block], 0.0, settings.noise_tolerance)
    # a dark fit that explains little: a pixel in cast shadow under most lights, fitted to the ambient light
    albedo = np.linalg.norm(scaled, axis=1)
    reference = _neighbourhood(albedo, surface, shape, settings)
    suspect = surface & ~explained & (albedo < settings.dark_ratio * reference)
    columns = np.flatnonzero(suspect)
    again, again_used = np.zeros((len(columns), 3)), np.zeros((count, len(columns)), dtype=bool)
    better = np.zeros(len(columns), dtype=bool)
    for start in range(0, len(columns), _PIXELS_PER_BLOCK):
        part = slice(start, start + _PIXELS_PER_BLOCK)
        block = columns[part]
        again[part], again_used[:, part], better[part] = _shadow_fit(
            luminance[:, block], usable[:, block], directions, reference[block], settings)
    shadow = np.zeros(pixels, dtype=bool)
    shadow[columns[better]] = True
    if shape is not None:  # a cast shadow covers a region: a shadow fit its neighbours did not take stays out
        shadow &= _window_count(shadow, shape, settings.shadow_window) >= settings.shadow_support
    taken = shadow[columns]
    scaled[columns[taken]], used[:, columns[taken]] = again[taken], again_used[:, taken]
    length = np.linalg.norm(scaled, axis=1)
    # a fit that explains less than the values' mean does finds no shading: no normal of its own
    mask = (surface & (shading | shadow) & (used.sum(axis=0) >= settings.min_lit_lights) & np.isfinite(length)
            & (length > _MIN_NBAR))
    for block in _blocks(np.flatnonzero(mask)):
        mask[block] = _spread(directions, used[:, block]) >= settings.min_spread
    normals = np.where(mask[:, None], scaled / np.where(length > 0, length, 1.0)[:, None], _FLAT)
    mask &= normals[:, 2] > 0.0  # a camera sees no surface facing away from it
    normals[~mask] = _FLAT
    return NormalFit(normals=normals, mask=mask, inliers=used & mask[None, :], surface=surface,
                     shadow_fit=shadow & mask)


def _shadow_fit(values: np.ndarray, usable: np.ndarray, directions: np.ndarray, reference: np.ndarray,
                settings: MapSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fit of suspect pixels from their brightest lights, cast shadows left out: (P, 3) rho n, (n, P)
    its lights, (P,) bool whether it may replace the first fit: it explains its values (``min_explained``;
    the first did not), on at least ``min_lit_lights`` sunlit lights (n . w at least ``shadow_fraction``),
    with an albedo within a factor 1 / ``dark_ratio`` of the neighbourhood's (``reference``)."""
    lit, typical, _ = _lit(values, usable, settings)
    with np.errstate(invalid="ignore"):
        bright = lit & (values >= settings.shadow_fraction
                        * _percentile(values, usable, settings.shadow_percentile)[None, :])
    few = bright.sum(axis=0) < settings.min_lit_lights
    bright[:, few] = lit[:, few]
    scaled, used = _robust_fit(values, directions, bright, lit, typical, settings, shadows=True)
    level = np.linalg.norm(scaled, axis=1)
    facing = directions @ (scaled / np.where(level > 0, level, 1.0)[:, None]).T
    sunlit = np.sum(used & (facing >= settings.shadow_fraction), axis=0)
    better = (_explained(values, directions, scaled, used, settings.min_explained, settings.noise_tolerance)
              & (sunlit >= settings.min_lit_lights)
              & (level >= settings.dark_ratio * reference) & (level * settings.dark_ratio <= reference))
    return scaled, used, better


def _blocks(columns: np.ndarray):
    """``columns`` in runs of at most ``_PIXELS_PER_BLOCK``."""
    for start in range(0, len(columns), _PIXELS_PER_BLOCK):
        yield columns[start:start + _PIXELS_PER_BLOCK]


def _lit(values: np.ndarray, usable: np.ndarray, settings: MapSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, P) the lights that light each pixel, (P,) its typical lit value, (P,) whether it is a surface
    (not black)."""
    surface = np.percentile(values, settings.lit_percentile, axis=0) >= max(settings.black_level, _MIN_NBAR)
    typical = _percentile(values, usable, settings.lit_percentile)  # the same where every light is usable
    with np.errstate(invalid="ignore"):
        lit = usable & surface[None, :] & (values >= settings.lit_fraction * typical[None, :])
    return lit, np.nan_to_num(typical, nan=0.0), surface


def _neighbourhood(albedo: np.ndarray, surface: np.ndarray, shape, settings: MapSettings) -> np.ndarray:
    """(P,) the typical albedo around each pixel: the ``lit_percentile`` (NumPy's linear percentile) of
    the ``albedo`` of the (2 r + 1)^2 pixels around it, r = ``neighbourhood``, the image's edge pixels
    repeated beyond it and black pixels counting as 0; of all surface pixels where ``shape`` is None."""
    values = np.where(surface, albedo, 0.0)
    if shape is None:
        level = np.percentile(values[surface], settings.lit_percentile) if surface.any() else 0.0
        return np.full(albedo.shape, level)
    radius = int(settings.neighbourhood)
    height, width = int(shape[0]), int(shape[1])
    padded = np.pad(values.reshape(height, width), radius, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * radius + 1, 2 * radius + 1))
    out = np.empty((height, width))
    rows = max(1, _PIXELS_PER_BLOCK // max(width * (2 * radius + 1), 1))  # bounds the window copies
    for top in range(0, height, rows):
        part = windows[top:top + rows].reshape(-1, width, (2 * radius + 1) ** 2)
        out[top:top + rows] = np.percentile(part, settings.lit_percentile, axis=2)
    return out.ravel()


def _window_count(flags: np.ndarray, shape, radius: int) -> np.ndarray:
    """(P,) how many of the (2 radius + 1)^2 pixels around each pixel (itself included) are ``flags``."""
    image = flags.reshape(int(shape[0]), int(shape[1])).astype(np.int64)
    padded = np.pad(image, int(radius))
    summed = np.pad(padded.cumsum(axis=0).cumsum(axis=1), [(1, 0), (1, 0)])
    size = 2 * int(radius) + 1
    height, width = image.shape
    total = (summed[size:size + height, size:size + width] - summed[:height, size:size + width]
             - summed[size:size + height, :width] + summed[:height, :width])
    return total.ravel()


def _percentile(values: np.ndarray, usable: np.ndarray, percentile: float) -> np.ndarray:
    """(P,) NumPy's linear percentile of each column's usable values; NaN where it has none."""
    count = usable.sum(axis=0)
    if count.min(initial=values.shape[0]) == values.shape[0]:
        return np.percentile(values, percentile, axis=0)
    ordered = np.sort(np.where(usable, values, np.nan), axis=0)  # NaN last
    position = np.maximum(count - 1, 0) * (percentile / 100.0)
    low = np.floor(position).astype(np.int64)
    high = np.minimum(low + 1, np.maximum(count - 1, 0))
    columns = np.arange(values.shape[1])
    below, above = ordered[low, columns], ordered[high, columns]
    weight = position - low
    with np.errstate(invalid="ignore"):  # as numpy.percentile interpolates: from the nearer end
        out = np.where(weight >= 0.5, above - (above - below) * (1.0 - weight), below + (above - below) * weight)
    return np.where(count > 0, out, np.nan)


def _robust_fit(values: np.ndarray, directions: np.ndarray, start: np.ndarray, lit: np.ndarray, typical: np.ndarray,
                settings: MapSettings, *, shadows: bool) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) rho n and (n, P) its lights: fits from the ``start`` lights, each refit over the ``lit``
    lights within the outlier limit of the median residual over ``lit``; with ``shadows``, over the
    fit's own lights (the lit lights in cast shadow would raise it), and not below ``shadow_ratio``
    of the fitted shading."""
    used = start
    scaled, current = None, False  # current: ``scaled`` is the fit over ``used``
    for _ in range(settings.iterations):
        scaled, current = _solve(values, directions, used), True
        predicted = directions @ scaled.T
        residual = np.abs(values - predicted)
        median = np.zeros(values.shape[1])
        base = used if shadows else lit
        some = base.any(axis=0)
        median[some] = np.nanmedian(np.where(base[:, some], residual[:, some], np.nan), axis=0)
        limit = np.maximum(settings.outlier_factor * median, settings.outlier_floor * typical)
        kept = lit & (residual <= limit[None, :])
        if shadows:
            kept &= values >= settings.shadow_ratio * predicted
        enough = kept.sum(axis=0) >= settings.min_lit_lights
        kept[:, ~enough] = used[:, ~enough]  # too few left: keep the previous set
        if np.array_equal(kept, used):
            break
        used, current = kept, False
    if not current:
        scaled = _solve(values, directions, used)
    return scaled, used


def _sums(values: np.ndarray, directions: np.ndarray, scaled: np.ndarray,
          used: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel over its ``used`` lights: their count, mean value, sum of squares about the mean and
    sum of squared residuals of the fit ``scaled``."""
    weights = used.astype(np.float64)
    count = weights.sum(axis=0)
    mean = (weights * values).sum(axis=0) / np.maximum(count, 1.0)
    spread = (weights * (values - mean[None, :]) ** 2).sum(axis=0)
    residual = (weights * (values - directions @ scaled.T) ** 2).sum(axis=0)
    return count, mean, spread, residual


def _explained(values, directions, scaled, used, required: float, tolerance: float) -> np.ndarray:
    """(P,) bool: the fit leaves at most (1 - ``required``) of its values' variance unexplained, beyond a
    noise allowance of ``tolerance`` times their mean per value."""
    count, mean, spread, residual = _sums(values, directions, scaled, used)
    return residual <= (1.0 - required) * spread + count * (tolerance * mean) ** 2


def _spread(directions: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(P,) the smallest eigenvalue of sum w w^T over each pixel's used light directions w."""
    normal = np.einsum("np,ni,nj->pij", used.astype(np.float64), directions, directions)
    return np.linalg.eigvalsh(normal)[:, 0]


def _solve(values: np.ndarray, directions: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(P, 3) least-squares rho n per pixel over its ``used`` lights; zeros where singular."""
    weights = used.astype(np.float64)
    normal = np.einsum("np,ni,nj->pij", weights, directions, directions)
    rhs = np.einsum("np,np,ni->pi", weights, values, directions)
    trace = np.trace(normal, axis1=1, axis2=2)
    normal += (1e-9 * trace + 1e-30)[:, None, None] * np.eye(3)  # a relative ridge: lights in a plane stay solvable
    solvable = np.linalg.det(normal) > 1e-9 * trace**3
    out = np.zeros((len(trace), 3))
    out[solvable] = np.linalg.solve(normal[solvable], rhs[solvable][..., None])[..., 0]
    return out


def channel_albedo(images: np.ndarray, directions: np.ndarray, normals: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """(P, C) least-squares rho_c >= 0 of (n, P, C) images = rho_c n . omega over each pixel's (n, P)
    ``inliers``, for (P, 3) unit ``normals``; 0 where no inlier lights it (float64, block by block)."""
    directions = np.asarray(directions, dtype=np.float64)
    pixels, channels = images.shape[1], images.shape[2]
    albedo = np.zeros((pixels, channels))
    for start in range(0, pixels, _PIXELS_PER_BLOCK):
        block = slice(start, min(start + _PIXELS_PER_BLOCK, pixels))
        # (n, p)
        shading = np.maximum(directions @ np.asarray(normals[block], dtype=np.float64).T, 0.0) * inliers[:, block]
        energy = np.sum(shading**2, axis=0)
        sums = np.einsum("np,npc->pc", shading, np.asarray(images[:, block], dtype=np.float64))
        albedo[block] = np.where(energy[:, None] > 0,
                                 np.maximum(sums, 0.0) / np.where(energy > 0, energy, 1.0)[:, None], 0.0)
    return albedo
