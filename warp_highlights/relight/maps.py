"""Surface maps of a fitted field: per-pixel normal, albedo and highlight colour (``warp-highlights maps``).

The field gives its captured images back (relit at the captured lights: residual plus the lights' own
highlights), and every pixel's normal is fitted to them by robust photometric stereo: least squares
of Y_i = rho n . omega_i (Y the luminance) over the lights that lit the pixel (at least
``MapSettings.lit_fraction`` of its typical lit value, so shadows stay out), refitted without the
lights whose residual is over ``MapSettings.outlier_factor`` times the median one (highlights).

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

Lights at a finite distance (every real dome) make a flat object's normals lean away from the image
centre, because the ``.lp`` file gives one direction per light for the whole object: on the dome
sample by 3.2 degrees (median, 0.38 flattened) against the normals its renderer wrote. ``flatten`` removes that trend:
it fits a plane to each slope (n_x / n_z and n_y / n_z) over the image and subtracts it, keeping the
mean tilt. It is for flat objects (coins, tablets, paintings): on a curved object it takes away true
shape.

A pixel is in the ``mask`` where it is not black (``MapSettings.black_level``), at least
``MapSettings.min_lit_lights`` lights lit it and the fitted normal faces the camera; elsewhere
(background, pixels always in shadow) the normal is (0, 0, 1) and the albedo 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.config import MapSettings
from ..model.errors import InputError
from ..model.memory import check_memory
from ..model.residual import LUMINANCE_WEIGHTS
from .relighter import Relighter

__all__ = ["NormalFit", "SurfaceMaps", "channel_albedo", "fit_normals", "flatten_normals", "surface_maps"]

_FLAT = np.array([0.0, 0.0, 1.0], dtype=np.float32)  # the normal of a pixel without an estimate
_MIN_NBAR = 1e-6  # |rho n| below this (field units) is no surface: a black or never-lit pixel
_PIXELS_PER_BLOCK = 65_536  # pixels solved at once: bounds the (lights x pixels) temporaries


@dataclass(frozen=True)
class SurfaceMaps:
    """What ``surface_maps`` estimates, at the field's working size.

    Attributes:
        normals: (H, W, 3) float32 unit normals in the light frame (x right, y up the image, z towards
            the camera); (0, 0, 1) outside ``mask``.
        albedo: (H, W, C) float32 >= 0, diffuse value under a unit light along the normal, input units.
        highlight_colour: (H, W, C) float32 >= 0, the field's c(x) (luminance 1), ones without one.
        mask: (H, W) bool, pixels with an estimated normal.
        lit_lights: (H, W) int32, lights the pixel's final fit used (lit, not outliers).
        coloured_highlights: whether the field stores a per-pixel highlight colour.
    """

    normals: np.ndarray
    albedo: np.ndarray
    highlight_colour: np.ndarray
    mask: np.ndarray
    lit_lights: np.ndarray
    coloured_highlights: bool


def surface_maps(field, *, device=None, flatten: bool = False, settings: MapSettings | None = None,
                 progress=None) -> SurfaceMaps:
    """Normal, albedo and highlight-colour maps of a ``HighlightField`` (see the module docstring).

    ``settings``: which lights light a pixel (``MapSettings``, default its defaults).
    ``flatten``: remove the slopes' linear trend over the image (``flatten_normals``; flat objects only).
    ``progress``: optional callable(lights_done) while the captured images are relit (the long part
    for a learned residual on the CPU).

    Raises:
        InputError: the field holds no diffuse part (fitted with neither a residual nor a diffuse model).
    """
    if field.residual is None and field.diffuse is None:
        raise InputError("the field holds only highlights (no residual or diffuse model), so it has no "
                         "normals or albedo; "
                         "fit it again without --residual none")
    settings = settings or MapSettings()
    channels = field.residual.channels if field.residual is not None else field.diffuse.channel_count
    pixels = field.width * field.height
    check_memory(field.light_count * pixels * (4 * channels + 9),
                 f"surface maps of {field.light_count} lights at {field.width}x{field.height}",
                 "fit the field at a smaller --size",
                 detail="the captured images as float32, their luminance as float64")
    relighter = Relighter(field, device=device, scale=1.0)  # field units; the albedo leaves them below
    directions = field.lights.directions
    # (n, H, W, C): the captured images, as the field keeps them
    captured = relighter.relight(directions, progress=progress).full
    captured = np.maximum(np.nan_to_num(captured, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    if captured.ndim == 3:
        captured = captured[..., None]
    channels = captured.shape[3]
    weights = np.asarray(LUMINANCE_WEIGHTS if channels == 3 else (1.0,), dtype=np.float32)
    luminance = (captured @ weights).reshape(len(directions), -1)  # (n, P)
    fit = fit_normals(luminance, directions, settings=settings)
    del luminance
    mask = fit.mask.reshape(field.height, field.width)
    normals = fit.normals.reshape(field.height, field.width, 3)
    if flatten:
        normals = flatten_normals(normals, mask)
    albedo = channel_albedo(captured.reshape(len(directions), -1, channels), directions, normals.reshape(-1, 3),
                            fit.inliers)
    del captured
    albedo = np.where(mask[..., None], albedo.reshape(field.height, field.width, channels), 0.0) / field.exposure
    colour = None if field.residual is None else field.residual.highlight_colour
    if colour is None:
        colour = np.ones((field.height, field.width, channels), dtype=np.float32)
    return SurfaceMaps(
        normals=normals.astype(np.float32),
        albedo=np.nan_to_num(albedo, nan=0.0, posinf=0.0).astype(np.float32),
        highlight_colour=np.maximum(np.asarray(colour, dtype=np.float32), 0.0),
        mask=mask,
        lit_lights=fit.inliers.sum(axis=0).reshape(field.height, field.width).astype(np.int32),
        coloured_highlights=field.residual is not None and field.residual.highlight_colour is not None,
    )


def flatten_normals(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals with the linear trend of their slopes over the image removed.

    The slopes n_x / n_z and n_y / n_z of the ``mask`` pixels are each fitted, by least squares, with
    a + b u + c v (u, v the pixel centre in [-1, 1] across the image) and b u + c v is subtracted:
    the mean tilt stays. Pixels outside ``mask`` are returned unchanged; fewer than 3 pixels in
    ``mask`` change nothing. float64 arithmetic, float32 result.
    """
    normals = np.asarray(normals, dtype=np.float64)
    height, width = normals.shape[:2]
    if np.count_nonzero(mask) < 3:
        return normals.astype(np.float32)
    v, u = np.mgrid[0:height, 0:width]
    u = (u + 0.5) / width * 2.0 - 1.0
    v = (v + 0.5) / height * 2.0 - 1.0
    design = np.stack([np.ones(np.count_nonzero(mask)), u[mask], v[mask]], axis=1)
    slopes = normals[..., :2] / normals[..., 2:3]  # finite: mask pixels face the camera (n_z > 0)
    flat = normals.copy()
    for axis in range(2):
        coefficients = np.linalg.lstsq(design, slopes[..., axis][mask], rcond=None)[0]
        slopes[..., axis] -= coefficients[1] * u + coefficients[2] * v
    tilted = np.concatenate([slopes, np.ones((height, width, 1))], axis=2)
    tilted /= np.linalg.norm(tilted, axis=2, keepdims=True)
    flat[mask] = tilted[mask]
    return flat.astype(np.float32)


@dataclass(frozen=True)
class NormalFit:
    """What ``fit_normals`` found per pixel: ``normals`` (P, 3) float64 unit vectors ((0, 0, 1) outside
    ``mask``), ``mask`` (P,) bool, ``inliers`` (n, P) bool: the lights of the final fit."""

    normals: np.ndarray
    mask: np.ndarray
    inliers: np.ndarray


def fit_normals(luminance: np.ndarray, directions: np.ndarray, *, settings: MapSettings | None = None) -> NormalFit:
    """Robust photometric stereo of (n, P) luminance stacks (linear, >= 0) under (n, 3) unit light
    directions, all pixels at once (float64; see the module docstring for the rule)."""
    settings = settings or MapSettings()
    luminance = np.asarray(luminance, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    count, pixels = luminance.shape
    normals = np.tile(_FLAT.astype(np.float64), (pixels, 1))
    mask = np.zeros(pixels, dtype=bool)
    inliers = np.zeros((count, pixels), dtype=bool)
    for start in range(0, pixels, _PIXELS_PER_BLOCK):
        block = slice(start, min(start + _PIXELS_PER_BLOCK, pixels))
        normals[block], mask[block], inliers[:, block] = _fit_block(luminance[:, block], directions, settings)
    return NormalFit(normals=normals, mask=mask, inliers=inliers)


def _fit_block(values: np.ndarray, directions: np.ndarray,
               settings: MapSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    typical = np.percentile(values, settings.lit_percentile, axis=0)
    black = typical < max(settings.black_level, _MIN_NBAR)
    lit = values >= settings.lit_fraction * typical[None, :]
    lit[:, black] = False
    used = lit
    scaled, current = None, False  # current: ``scaled`` is the fit over ``used``
    for _ in range(settings.iterations):
        scaled, current = _solve(values, directions, used), True
        residual = np.abs(values - directions @ scaled.T)
        median = np.zeros(values.shape[1])
        some = lit.any(axis=0)
        median[some] = np.nanmedian(np.where(lit[:, some], residual[:, some], np.nan), axis=0)
        limit = np.maximum(settings.outlier_factor * median, settings.outlier_floor * typical)
        kept = lit & (residual <= limit[None, :])
        enough = kept.sum(axis=0) >= settings.min_lit_lights
        kept[:, ~enough] = used[:, ~enough]  # too few left: keep the previous set
        if np.array_equal(kept, used):
            break
        used, current = kept, False
    if not current:
        scaled = _solve(values, directions, used)
    length = np.linalg.norm(scaled, axis=1)
    mask = ~black & (used.sum(axis=0) >= settings.min_lit_lights) & np.isfinite(length) & (length > _MIN_NBAR)
    normals = np.where(mask[:, None], scaled / np.where(length > 0, length, 1.0)[:, None], _FLAT)
    mask &= normals[:, 2] > 0.0  # a camera sees no surface facing away from it
    normals[~mask] = _FLAT
    return normals, mask, used & mask[None, :]


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
