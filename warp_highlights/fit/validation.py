"""Leave-one-out check that moving the highlights beats blending the images on this capture (docs/method.md, Fitting
step 7).

Moving wins where the Gaussians sit on real highlights that retarget reliably (the rendered dome sample)
and loses where they model broad sheen and shading (the statue sample). Held-out lights cannot tell at
fit time, so the captured ones do, one at a time: each
checked light j is located in the triangulation of the *other* lights, and its triangle's corners
predict image j twice,

- moving: the corners' residuals blended plus their Gaussians moved to l_j along their paths (the
  moving ones; the others drawn in place with their corner's weight), as the relighter would;
- blending: the corners' images blended with the same weights (the alpha blend).

The directed edges of those triangles that the capture's own triangulation lacks are retargeted first
(one batch). Both predictions are scored against image j in 8-bit sRGB (``srgb_psnr``'s arithmetic); if moving's mean
is lower, no Gaussian moves. Only the prediction leaves j out: the Gaussians, their move decisions, the
highlight colour and the segmentation were fitted with image j among the others, which favours moving
a little (the check is conservative about blending). For a learned residual, the moved highlights of
a few checked lights are kept (``keep``): ``residual.learned.check_learned`` leaves those lights out together
and scores the learned residual with them there, so they are lights that lie between captured neighbours
(``apart_inside``). Units: images in the field's units (``factor`` divides them back to display units,
1 = white).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..io.images import display_rgb8
from ..kernels.raster import Rasterizer
from ..kernels.scores import device_tint, prediction_errors
from ..kernels.transfer import rows_up, to_host
from ..model.config import FitSettings
from ..model.errors import InputError
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.interpolation import move_sets
from ..model.threads import NUMPY_THREADS, parallel_map
from ..model.triangulation import SphericalTriangulation
from ..quality.metrics import psnr_8bit, psnr_of_mse
from .lost import lost_slots, place_lost
from .paths import decide_paths
from .retargeting import restore_vanished, retarget

__all__ = ["CheckPlan", "LeaveOneOut", "MoveCheck", "apart_inside", "check_moving", "leave_one_out", "plan_check",
           "spread_lights"]

_RENDER_BYTES = 256 * 2**20  # the left-out lights' highlights are drawn in batches of at most this many bytes
_SCORE_BYTES = 2 * 2**30  # the lights scored at once take at most this much memory for their images ...
_SCORE_COPIES = 8  # ... each about this many image-sized temporaries (the blend, the moved image, the truth, sRGB)
# on a CUDA device the lights are scored there where the images they need take at most this share of its free memory (48
# lights of a 480x270 capture: 192 images, 0.3 GB), where the host's threads would take a large part of the check
_DEVICE_SCORE_SHARE = 0.25


@dataclass(frozen=True)
class LeaveOneOut:
    """Checked lights and their triangles in the other lights' triangulations.

    Attributes:
        lights: (m,) int the left-out lights; vertices: (m, 3) int their triangles' corners (indices
        into all lights); barycentric: (m, 3) float64 the weights of l_j (of its rim projection where it
        lies outside the others' dome, as the relighter would clamp it); inside: (m,) bool, True where
        l_j lies inside the others' dome (not clamped onto its rim).
    """

    lights: np.ndarray
    vertices: np.ndarray
    barycentric: np.ndarray
    inside: np.ndarray


@dataclass(frozen=True)
class MoveCheck:
    """What ``check_moving`` measured: (m,) 8-bit sRGB PSNR (dB) of both predictions per checked light,
    and where asked (``keep``), the moved highlights c(x) G'(l_j) drawn at some of them: (h, H, W, C)
    field units at the lights ``kept_lights`` (h,) (indices into all lights); where asked (``draw_all``),
    ``moved_luminance`` (m, H, W): every checked light's moved Gaussians G'(l_j), field units, untinted."""

    lights: np.ndarray
    moving_psnr: np.ndarray
    blend_psnr: np.ndarray
    extra_edges: int
    kept_lights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    kept_highlights: np.ndarray | None = None
    moved_luminance: np.ndarray | None = None

    @property
    def moves(self) -> bool:
        """True unless moving scored lower than blending on average (no light checked: True)."""
        return not len(self.lights) or float(np.mean(self.moving_psnr)) >= float(np.mean(self.blend_psnr))

    def report(self) -> dict:
        """Plain figures for the fit report."""
        if not len(self.lights):
            return {"lights": 0, "moves": True}
        return {
            "lights": int(len(self.lights)),
            "extra_edges": int(self.extra_edges),
            "moving_psnr_db": round(float(np.mean(self.moving_psnr)), 3),
            "blend_psnr_db": round(float(np.mean(self.blend_psnr)), 3),
            "moving_ahead_share": round(float(np.mean(self.moving_psnr > self.blend_psnr)), 3),
            "moves": self.moves,
        }


def spread_lights(directions: np.ndarray, count: int) -> np.ndarray:
    """(min(count, n),) sorted indices of lights spread over the sphere: farthest-point sampling from the
    light nearest the lights' mean direction (deterministic)."""
    directions = np.asarray(directions, dtype=np.float64)
    n = len(directions)
    if count >= n:
        return np.arange(n)
    if count <= 0:
        return np.zeros(0, dtype=np.int64)
    centre = directions.sum(axis=0)
    first = int(np.argmax(directions @ centre)) if np.linalg.norm(centre) > 1e-12 else 0
    chosen = [first]
    closest = directions @ directions[first]  # cosine to the nearest chosen light
    for _ in range(count - 1):
        pick = int(np.argmin(closest))
        chosen.append(pick)
        closest = np.maximum(closest, directions @ directions[pick])
    return np.sort(np.asarray(chosen, dtype=np.int64))


def leave_one_out(directions: np.ndarray, lights: np.ndarray) -> LeaveOneOut:
    """Each of ``lights`` located in the triangulation of all the other lights (those whose others
    cannot be triangulated are skipped)."""
    directions = np.asarray(directions, dtype=np.float64)
    n = len(directions)
    kept, vertices, weights, inside = [], [], [], []
    for light in np.asarray(lights, dtype=np.int64):
        others = np.delete(np.arange(n), light)
        try:
            location = SphericalTriangulation(directions[others]).locate(directions[light])
        except InputError:
            continue  # too few or degenerate lights without this one
        kept.append(light)
        vertices.append(others[location.vertices])
        weights.append(location.barycentric)
        inside.append(not bool(location.clamped))
    if not kept:
        return LeaveOneOut(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros(0, bool))
    return LeaveOneOut(np.asarray(kept), np.asarray(vertices), np.asarray(weights), np.asarray(inside))


def apart_inside(loo: LeaveOneOut, triangulation: SphericalTriangulation) -> np.ndarray:
    """Rows of ``loo`` that can be left out together, in the order to take them: lights inside the other
    lights' dome, no two joined by an edge of the capture's ``triangulation``, spread by farthest-point
    sampling from its rim (on a sphere, from the light nearest the lights' mean direction), so that they
    fill the dome's inside rather than ring it.

    Left out together, such lights keep the triangles they have when left out one at a time (only their own
    stars are filled anew, from corners that stay), so each lies between captured neighbours, as a query
    between the lights would: a light on the rim of a dome, or beside another left-out light, would be
    extrapolated from far away instead."""
    directions = np.asarray(triangulation.directions, dtype=np.float64)
    lights = np.asarray(loo.lights, dtype=np.int64)
    free = np.asarray(loo.inside, bool).copy()
    if not free.any():
        return np.zeros(0, np.int64)
    row_of = np.full(len(directions), -1, np.int64)
    row_of[lights] = np.arange(len(lights))
    edges = np.asarray(triangulation.directed_edges(), dtype=np.int64)
    rim = np.unique(np.asarray(triangulation.boundary_edges(), dtype=np.int64))
    if len(rim):  # cosine to the nearest rim light
        closest = (directions[lights] @ directions[rim].T).max(axis=1)
    else:
        centre = directions.sum(axis=0)
        closest = -(directions[lights] @ centre) if np.linalg.norm(centre) > 1e-12 else np.zeros(len(lights))
    chosen = []
    while free.any():
        row = int(np.flatnonzero(free)[np.argmin(closest[free])])
        chosen.append(row)
        free[row] = False
        touching = row_of[edges[edges[:, 0] == lights[row], 1]]
        free[touching[touching >= 0]] = False
        reached = directions[lights] @ directions[lights[row]]
        closest = reached if not len(rim) and len(chosen) == 1 else np.maximum(closest, reached)
    return np.asarray(chosen, dtype=np.int64)


@dataclass(frozen=True)
class CheckPlan:
    """The left-out lights and the directed edges (k, 2) their triangles need beyond the capture's own;
    ``apart``: the rows of ``loo`` that a check leaving several lights out at once may take, in order
    (``apart_inside``)."""

    loo: LeaveOneOut
    missing: np.ndarray
    apart: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def plan_check(directions: np.ndarray, edges: np.ndarray, count: int) -> CheckPlan:
    """Up to ``count`` spread lights left out (``leave_one_out``) and the edges to retarget for them."""
    n = len(directions)
    loo = leave_one_out(directions, spread_lights(directions, count) if count > 0 and n >= 5 else np.zeros(0, np.int64))
    if not len(loo.lights):
        return CheckPlan(loo, np.zeros((0, 2), np.int32))
    apart = apart_inside(loo, SphericalTriangulation(directions))
    corners = loo.vertices
    wanted = np.concatenate([corners[:, [a, b]] for a in range(3) for b in range(3) if a != b]).astype(np.int64)
    have = edges[:, 0].astype(np.int64) * n + edges[:, 1]
    missing = np.setdiff1d(np.unique(wanted[:, 0] * n + wanted[:, 1]), have)
    return CheckPlan(loo, np.stack([missing // n, missing % n], axis=1).astype(np.int32), apart)


def check_moving(
    plan: CheckPlan,
    estimated: GaussianParams,
    retargeted: GaussianParams,
    edges: np.ndarray,
    path_delta: np.ndarray,
    moving: np.ndarray,
    specular_luminance: wp.array,
    images: np.ndarray,
    own: np.ndarray,
    colour: np.ndarray | None,
    *,
    factor: float,
    settings: FitSettings,
    device=None,
    workers: int | None = None,
    progress=None,
    keep: int = 0,
    held=None,
    directions: np.ndarray | None = None,
    draw_all: bool = False,
    motion: np.ndarray | None = None,
) -> MoveCheck:
    """Score moving against blending at the left-out lights of ``plan``.

    Args:
        plan: ``plan_check``'s lights and missing edges.
        estimated, retargeted, edges, path_delta: the fit's sets, directed edges (sorted) and path
            rotations (float32, as the field keeps them).
        moving: (n, N) bool which estimated Gaussians move (the rest are drawn in place).
        specular_luminance: (n, H, W) the segmentation's specular part (the retargeting targets).
        images: (n, H, W, C) the captured images; own: (n, H, W) their own Gaussians drawn; field units.
        colour: (H, W, C) the highlight colour c(x), or None for white.
        factor: the fit's exposure factor (field units per display unit).
        progress: optional ``advance(steps)`` for the retargeting of the missing edges.
        keep: keep the moved highlights of up to this many checked lights, the first of ``plan.apart`` (lights
            inside the others' dome, none beside another: the learned residual's check leaves them out together,
            ``residual.learned.check_learned``).
        held: ``images`` and ``own`` on the CUDA device already (``residual.inputs.HeldImages``), scored there.
        directions: (n, 3) the lights' directions, for retargeting's start (``fit.retargeting.retarget``).
        draw_all: keep every checked light's moved Gaussians (``MoveCheck.moved_luminance``): the inputs a learned
            residual that sees the highlights trains with (``residual.learned``).
        motion: (n, N, 2, 2) the Gaussians' ``fit.lost.expected_motion``: the missing edges' lost Gaussians are placed
            as the fit's own edges' are (``fit.lost.place_lost``; None: left as retargeting left them).
    """
    loo, missing = plan.loo, plan.missing
    if not len(loo.lights) or not moving.any():
        return MoveCheck(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), 0)
    _, height, width = own.shape
    all_edges, all_sets, all_delta = edges, retargeted, np.asarray(path_delta, np.float64)
    if len(missing):
        extra = retarget(estimated, specular_luminance, missing, settings=settings.retarget, raster=settings.raster,
                         device=device, directions=directions,
                         workers=workers, progress=progress)
        extra_sources = estimated.take(missing[:, 0])
        extra_sets, vanished = restore_vanished(extra_sources, extra.params, settings.retarget.vanish_share,
                                                sigma_eps=settings.raster.sigma_eps)
        if motion is not None and directions is not None:
            lost = lost_slots(extra_sources, extra_sets, vanished, specular_luminance.shape[2]
                              / specular_luminance.shape[1], settings.retarget.lost_share)
            extra_sets, _, _ = place_lost(extra_sources, extra_sets, lost, missing, directions, motion,
                                          specular_luminance, landing=settings.residual.move_support,
                                          raster=settings.raster)
        extra_delta = decide_paths(extra_sources, extra_sets, settings.paths).delta.astype(np.float32)
        joined = np.concatenate([edges, missing])
        order = np.lexsort((joined[:, 1], joined[:, 0]))
        all_edges = joined[order]
        all_sets = GaussianParams.concatenate([retargeted, extra_sets], axis=0).take(order)
        all_delta = np.concatenate([all_delta, extra_delta.astype(np.float64)])[order]
    corners = loo.vertices
    sets = move_sets(estimated, all_sets, all_edges, all_delta, corners, loo.barycentric,
                     method="circular", straight_below=settings.paths.straight_below, moving=moving)
    raster = Rasterizer(height, width, settings=settings.raster, device=device)
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 3:
        images = images[..., None]
    tint = np.ones((1, 1, images.shape[-1]), np.float32) if colour is None else np.asarray(colour, np.float32)
    scale = np.float32(1.0 / factor)
    moving_psnr, blend_psnr = np.empty(len(loo.lights)), np.empty(len(loo.lights))
    kept_rows = np.sort(plan.apart[:keep]) if keep > 0 else np.zeros(0, np.int64)
    kept = np.zeros((len(kept_rows), height, width, images.shape[-1]), np.float32)
    moved_luminance = np.zeros((len(loo.lights), height, width), np.float32) if draw_all else None
    chunk = max(1, _RENDER_BYTES // (4 * height * width))
    # lights scored at once, in threads
    at_once = max(1, min(NUMPY_THREADS, _SCORE_BYTES // (_SCORE_COPIES * images[0].nbytes)))
    scored = None
    # scored there where the images the lights need are there or fit beside the rest
    if raster.device.is_cuda and not len(kept_rows):
        there = held is not None and held.own is not None
        needed = np.arange(len(images)) if there else np.unique(np.concatenate([corners.ravel(), loo.lights]))
        if (there
            or len(needed) * (images[0].nbytes + own[0].size * 4) <= _DEVICE_SCORE_SHARE * raster.device.free_memory):
            scored = _DeviceScores(images, own, tint, corners, loo.lights, scale, raster.device, needed=needed,
                                   held=held)
    for start in range(0, len(loo.lights), chunk):
        rows = np.arange(start, min(start + chunk, len(loo.lights)))
        drawn_there = raster.render(GaussianBatch.from_numpy(sets.take(rows), device=device, requires_grad=False))
        if moved_luminance is not None:
            moved_luminance[rows] = to_host(drawn_there)
        # scored there (``kernels.scores``): 48 lights in one launch, not 144 sRGB images in host threads
        if scored is not None:
            moving_psnr[rows], blend_psnr[rows] = scored.psnr(rows, drawn_there, loo.barycentric[rows])
            continue
        drawn = to_host(drawn_there)

        def score(q: int, drawn_q: np.ndarray) -> None:  # the lights in threads (NumPy lets go of the GIL)
            weights = loo.barycentric[q].astype(np.float32)
            blend = sum(w * images[v] for v, w in zip(corners[q], weights))
            highlights = sum(w * own[v] for v, w in zip(corners[q], weights))
            moved = blend + (drawn_q - highlights)[..., None] * tint  # the blended residual plus the moved highlights
            # shown once for both scores (``srgb_psnr`` shows both its images)
            truth = display_rgb8(images[loo.lights[q]] * scale)
            moving_psnr[q] = psnr_8bit(display_rgb8(moved * scale), truth)
            blend_psnr[q] = psnr_8bit(display_rgb8(blend * scale), truth)
            if q in kept_rows:
                kept[np.searchsorted(kept_rows, q)] = drawn_q[..., None] * tint

        for group in range(0, len(rows), at_once):
            parallel_map(lambda q, drawn=drawn, start=start: score(q, drawn[q - start]), rows[group : group + at_once])
    return MoveCheck(loo.lights, moving_psnr, blend_psnr, len(missing), loo.lights[kept_rows],
                     kept if len(kept_rows) else None, moved_luminance)


class _DeviceScores:
    """``check_moving``'s scores on a CUDA device: the images and own highlights the checked lights need
    (their corners and themselves) go up once; ``psnr`` scores a chunk of lights in one launch
    (``kernels.scores.prediction_errors``), to a few thousandths of a dB of the host's ``psnr_8bit``."""

    def __init__(self, images: np.ndarray, own: np.ndarray, tint: np.ndarray, corners: np.ndarray, lights: np.ndarray,
                 scale, device, *,
                 needed: np.ndarray | None = None, held=None):
        n, self.height, self.width, _ = images.shape
        if held is not None and held.own is not None:  # every image there already
            self.needed = np.arange(n)
            self.images, self.own = held.images.reshape((n, -1)), held.own
        else:  # the lights' corners and the lights themselves (sorted indices), given or found here
            self.needed = (np.unique(np.concatenate([np.asarray(corners).ravel(), np.asarray(lights)]))
                           if needed is None else needed)
            self.images = rows_up(images.reshape(n, -1), device, rows=self.needed)
            self.own = rows_up(np.asarray(own, np.float32).reshape(n, -1), device, rows=self.needed)
        self.channels = int(np.shape(tint)[-1])
        self.tint = device_tint(tint, self.height, self.width, device)  # once for every chunk of lights
        self.corners, self.lights, self.scale = np.asarray(corners), np.asarray(lights), float(scale)

    def psnr(self, rows: np.ndarray, drawn: wp.array, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(len(rows),) 8-bit sRGB PSNR (dB) of the moved and the blended predictions of checked lights ``rows``,
        ``drawn`` (len(rows), H, W) their moved highlights there."""
        errors = prediction_errors(self.images, self.own, drawn.reshape((len(rows), self.height * self.width)),
                                   self.tint,
                                   np.searchsorted(self.needed, self.corners[rows]), weights,
                                   np.searchsorted(self.needed, self.lights[rows]), scale=self.scale,
                                   height=self.height, width=self.width)
        values = self.height * self.width * self.channels * 255.0**2
        return psnr_of_mse(errors[:, 0] / values), psnr_of_mse(errors[:, 1] / values)
