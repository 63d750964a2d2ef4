"""The fitted highlight field: the object that relights (docs/file-format.md).

A :class:`HighlightField` holds everything needed to relight: the lights and their triangulation, the
Gaussians estimated for every light, the Gaussians retargeted along every directed edge, the rotation
path chosen per Gaussian and edge, the fit settings and report, the image size, and optionally the
:class:`DiffuseModel`. The constructor checks that all of it is consistent.

Only the model lives here: its file (a versioned zip container) is ``warp_highlights.io.fieldfile``
(``save_field``, ``load_field``), and relighting it is ``warp_highlights.relight`` (``Relighter``,
``relight_field``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import FitSettings
from .errors import InputError, finite_array
from .gaussians import GaussianParams
from .lights import LightSet
from .residual import ResidualModel
from .triangulation import SphericalTriangulation

__all__ = ["MAX_CAPACITY", "DiffuseModel", "HighlightField"]

MAX_CAPACITY = 65535
"""Most slots a field's Gaussian sets may have (slot indices and counts are stored as 16-bit integers)."""


@dataclass(frozen=True, eq=False)
class DiffuseModel:
    """Diffuse part of a fitted field.

    Attributes:
        lambert: (H, W, C, 4) float32: per pixel and channel nbar_x, nbar_y, nbar_z, k_a of the
            Lambertian model D(omega) = max(nbar . omega, 0) + k_a (docs/method.md, Fitting step 1).
        images: (n, H, W, C) float16 diffuse images of the n lights (for barycentric blending), or None.

    Raises:
        InputError: wrong shapes, non-finite values, or values beyond float32 (lambert) or float16
            (images).
    """

    lambert: np.ndarray
    images: np.ndarray | None = None

    def __post_init__(self):
        lambert = finite_array(self.lambert, np.float32, "diffuse lambert")
        if lambert.ndim != 4 or lambert.shape[3] != 4 or min(lambert.shape) < 1:
            raise InputError(
                f"diffuse lambert must have shape (H, W, C, 4), got {lambert.shape}"
            )
        object.__setattr__(self, "lambert", lambert)
        if self.images is not None:
            images = finite_array(self.images, np.float16, "diffuse images")
            if (
                images.ndim != 4
                or images.shape[1:] != lambert.shape[:3]
                or len(images) < 1
            ):
                raise InputError(
                    f"diffuse images must have shape (n, {', '.join(map(str, lambert.shape[:3]))}) to match the "
                    f"Lambertian model, got {images.shape}"
                )
            object.__setattr__(self, "images", images)

    @property
    def height(self) -> int:
        return self.lambert.shape[0]

    @property
    def width(self) -> int:
        return self.lambert.shape[1]

    @property
    def channel_count(self) -> int:
        return self.lambert.shape[2]

    def lambertian(self, direction) -> np.ndarray:
        """The Lambertian diffuse image max(nbar . omega, 0) + k_a for one light direction, (H, W, C) float32."""
        omega = np.asarray(direction, dtype=np.float64).reshape(-1)
        if (
            omega.shape != (3,)
            or not np.all(np.isfinite(omega))
            or not np.linalg.norm(omega) > 0
        ):
            raise InputError(
                f"a light direction must be a finite non-zero 3-vector, got {omega.tolist()}"
            )
        omega = (omega / np.linalg.norm(omega)).astype(np.float32)
        return np.maximum(self.lambert[..., :3] @ omega, 0.0) + self.lambert[..., 3]


@dataclass(eq=False, repr=False)
class HighlightField:
    """A fitted highlight field (docs/file-format.md); treat it as immutable once made.

    Attributes:
        lights: The n lights the field was fitted to.
        triangulation: Their spherical triangulation.
        width, height: Image size the field was fitted at, pixels.
        estimated: (n, N) Gaussians fitted to each light's specular image.
        directed_edges: (E, 2) int32 (source light, target light); must equal
            ``triangulation.directed_edges()``.
        retargeted: (E, N): slot p of row e is slot p of ``estimated[directed_edges[e, 0]]`` re-fitted
            to the target's image; same active mask as that source row.
        path_delta: (E, N) float32 signed rotation per Gaussian per directed edge, radians.
        path_centre: (E, N, 2) float32 rotation centre, image heights.
        settings: The fit settings (``FitSettings.to_dict()``), JSON-able.
        report: Fit summary (times, counts, quality), JSON-able; NaN and infinite numbers are
            stored as None (null), in ``settings`` too.
        diffuse: The diffuse model (per-pixel Lambertian; an option since residual transfer), or None.
        residual: The ``ResidualModel`` of residual transfer (the default full image), or None.
        moving: (n, N) bool: the estimated Gaussians that move when relit; the others stay in place
            and blend like the alpha baseline (decided at fit time from how well their retargeting
            explains the neighbours). None: every active Gaussian moves (fields before version 2).

    The constructor validates everything and raises ``InputError`` (one line) on any inconsistency. It
    stores float32-rounded copies of the Gaussian and path values (the device works in float32; the
    ``GaussianParams`` stay float64 arrays holding float32 values), clears free slots (zeros, weight 1;
    zero path delta and centre; only active slots' path values need to be finite), and keeps ``settings`` and ``report``
    as plain JSON values, so that ``load_field(path)`` after ``save_field(field, path)`` gives back equal data. Active
    Gaussians must have weight 1. The inputs are not modified.

    ``file_path`` and ``file_sizes`` (not constructor arguments) say where the field was last saved to
    or loaded from and how many compressed bytes each part took there (``field_size_report``); both are
    None for a field that has never been in a file. ``warp_highlights.io.fieldfile`` sets them.
    """

    lights: LightSet
    triangulation: SphericalTriangulation
    width: int
    height: int
    estimated: GaussianParams
    directed_edges: np.ndarray
    retargeted: GaussianParams
    path_delta: np.ndarray
    path_centre: np.ndarray
    settings: dict
    report: dict
    diffuse: DiffuseModel | None = None
    residual: ResidualModel | None = None
    moving: np.ndarray | None = None

    def __post_init__(self):
        if not isinstance(self.lights, LightSet):
            raise InputError(
                f"lights must be a LightSet, got {type(self.lights).__name__}"
            )
        if not isinstance(self.triangulation, SphericalTriangulation):
            raise InputError(
                f"triangulation must be a SphericalTriangulation, got {type(self.triangulation).__name__}"
            )
        n = self.lights.light_count
        tri_directions = np.asarray(self.triangulation.directions)
        if tri_directions.shape != (n, 3) or not np.allclose(
            tri_directions, self.lights.directions, rtol=0, atol=1e-9
        ):
            raise InputError(
                f"the triangulation is over {len(tri_directions)} directions that are not the {n} light "
                "directions; triangulate these lights"
            )
        self.width = _positive_int(self.width, "width")
        self.height = _positive_int(self.height, "height")

        estimated = _canonical_params(self.estimated, "estimated")
        if estimated.problem_count != n:
            raise InputError(
                f"estimated has {estimated.problem_count} sets but there are {n} lights; give one set per light"
            )
        capacity = estimated.capacity
        if capacity > MAX_CAPACITY:
            raise InputError(
                f"the field has {capacity} slots per set; at most {MAX_CAPACITY} are supported"
            )

        expected_edges = self.triangulation.directed_edges().astype(np.int32)
        directed = np.asarray(self.directed_edges)
        if directed.shape != expected_edges.shape or not np.array_equal(
            directed, expected_edges
        ):
            raise InputError(
                f"directed_edges ({directed.shape}) must equal triangulation.directed_edges() "
                f"({expected_edges.shape}): every edge in both directions, sorted"
            )
        edge_count = len(expected_edges)
        self.directed_edges = expected_edges

        retargeted = _canonical_params(self.retargeted, "retargeted")
        if retargeted.problem_count != edge_count:
            raise InputError(
                f"retargeted has {retargeted.problem_count} sets but there are {edge_count} directed edges; "
                "give one set per directed edge"
            )
        if retargeted.capacity != capacity:
            raise InputError(
                f"retargeted sets have {retargeted.capacity} slots but estimated sets have {capacity}"
            )
        expected_active = estimated.active[expected_edges[:, 0]]
        differs = np.flatnonzero((retargeted.active != expected_active).any(axis=1))
        if differs.size:
            e = int(differs[0])
            source, target = (int(v) for v in expected_edges[e])
            raise InputError(
                f"retargeted set {e} (edge {source} -> {target}) uses other slots than estimated set {source}; "
                "a retargeted set keeps exactly the active slots of its source"
            )
        self.estimated, self.retargeted = estimated, retargeted

        self.path_delta = _path_array(
            self.path_delta, "path_delta", (edge_count, capacity), expected_active
        )
        self.path_centre = _path_array(
            self.path_centre, "path_centre", (edge_count, capacity, 2), expected_active
        )
        self.settings = _json_object(self.settings, "settings")
        self.report = _json_object(self.report, "report")

        if self.diffuse is not None:
            if not isinstance(self.diffuse, DiffuseModel):
                raise InputError(
                    f"diffuse must be a DiffuseModel or None, got {type(self.diffuse).__name__}"
                )
            if (self.diffuse.height, self.diffuse.width) != (self.height, self.width):
                raise InputError(
                    f"the diffuse model is {self.diffuse.width} x {self.diffuse.height} pixels but the field is "
                    f"{self.width} x {self.height}"
                )
            if self.diffuse.images is not None and len(self.diffuse.images) != n:
                raise InputError(
                    f"the diffuse model has {len(self.diffuse.images)} images for {n} lights"
                )
        if self.residual is not None:
            if not isinstance(self.residual, ResidualModel):
                raise InputError(f"residual must be a ResidualModel or None, got {type(self.residual).__name__}")
            if ((self.residual.height, self.residual.width) != (self.height, self.width)
                or self.residual.light_count != n):
                raise InputError(
                    f"the residual model has {self.residual.light_count} lights of {self.residual.width} x "
                    f"{self.residual.height} "
                    f"pixels but the field has {n} of {self.width} x {self.height}"
                )
        if self.moving is not None:
            moving = np.asarray(self.moving)
            if moving.shape != (n, capacity) or moving.dtype != bool:
                raise InputError(f"moving must be a ({n}, {capacity}) bool array, got {moving.shape} {moving.dtype}")
            self.moving = moving & estimated.active
        self.file_path: Path | None = None
        self.file_sizes: dict | None = None

    # --- summary ---------------------------------------------------------------------------------

    @property
    def light_count(self) -> int:
        """Number of lights n."""
        return self.lights.light_count

    @property
    def edge_count(self) -> int:
        """Number of directed edges E (retargeted sets)."""
        return len(self.directed_edges)

    @property
    def capacity(self) -> int:
        """Slots per Gaussian set N."""
        return self.estimated.capacity

    @property
    def counts(self) -> np.ndarray:
        """(n,) int: active Gaussians estimated for each light."""
        return self.estimated.counts

    @property
    def moving_mask(self) -> np.ndarray:
        """(n, N) bool: the active estimated Gaussians that move (all of them when ``moving`` is None)."""
        return self.estimated.active.copy() if self.moving is None else self.moving & self.estimated.active

    @property
    def gaussian_count(self) -> int:
        """Active Gaussians in all sets, estimated and retargeted."""
        return int(self.estimated.active.sum() + self.retargeted.active.sum())

    @property
    def aspect(self) -> float:
        """Image aspect ratio width / height (the Gaussians' x range is (0, aspect))."""
        return self.width / self.height

    def fit_settings(self):
        """The stored settings as a ``FitSettings`` (raises ``InputError`` for unknown keys)."""
        return FitSettings.from_dict(self.settings)

    @property
    def exposure(self) -> float:
        """The factor the fit multiplied the input radiance by (``fit --exposure``); 1 when absent."""
        value = self.report.get("exposure")
        return float(value) if isinstance(value, (int, float)) and math.isfinite(value) and value > 0 else 1.0

    def motion_line(self) -> str:
        """'N of M Gaussians move (X% of the specular energy)': how much of the image moves, as the viewers say it
        (the share from the fit report; left out where it has none)."""
        residual = self.report.get("residual") if isinstance(self.report.get("residual"), dict) else {}
        share = residual.get("moving_specular_share")
        carried = f" ({100 * share:.0f}% of the specular energy)" if isinstance(share, (int, float)) else ""
        total = int(self.estimated.active.sum())
        return f"{int(self.moving_mask.sum())} of {total} Gaussian{'' if total == 1 else 's'} move{carried}"

    def _motion_figures(self) -> str:
        """What the fit report says of the moving Gaussians: their share of the specular energy and the
        checks' scores ('' where the report has none)."""
        residual = self.report.get("residual") if isinstance(self.report.get("residual"), dict) else {}
        parts = []
        share = residual.get("moving_specular_share")
        if isinstance(share, (int, float)):
            parts.append(f"carrying {100 * share:.0f}% of the specular energy")
        coherence = residual.get("motion_coherence")
        if isinstance(coherence, (int, float)):
            parts.append(f"median motion coherence {coherence:.2f} (1: gliding, 0: glints)")
        check = residual.get("move_check") or {}
        if check.get("lights"):
            parts.append(f"move check at {check['lights']} left-out lights: moving {check['moving_psnr_db']:.2f} dB, "
                         f"blending {check['blend_psnr_db']:.2f} dB")
        learned = residual.get("learned_check") or {}
        if learned.get("lights"):
            seeing = " as the decoder's inputs" if learned.get("sees_gaussians") else ""
            exact = learned.get("exact_residual_psnr_db")
            exact = "" if not isinstance(exact, (int, float)) else f" ({exact:.2f} with its residual exact)"
            parts.append(f"learned check: with the Gaussians{seeing} {learned['with_gaussians_psnr_db']:.2f} dB"
                         f"{exact}, the images alone {learned['images_alone_psnr_db']:.2f} dB"
                         + (" (the Gaussians glide)" if learned.get("glides") else ""))
        return "".join(f"; {part}" for part in parts)

    def describe(self) -> str:
        """A short multi-line summary (lights, triangulation, Gaussians, diffuse, file size if known)."""
        counts = self.counts
        kind = "dome" if self.triangulation.is_dome else "full sphere"
        lines = [
            f"highlight field: {self.light_count} lights ({kind}), {self.width} x {self.height} px",
            f"triangulation: {self.triangulation.face_count} faces, {self.edge_count} directed edges",
            (
                f"Gaussians per light: mean {counts.mean():.1f}, min {counts.min()}, max {counts.max()} "
                f"(capacity {self.capacity}); {self.gaussian_count} in {self.light_count + self.edge_count} sets"
            ),
        ]
        if self.diffuse is None:
            lines.append("diffuse: none")
        else:
            images = (
                ""
                if self.diffuse.images is None
                else f" + {len(self.diffuse.images)} images"
            )
            lines.append(
                f"diffuse: Lambertian, {self.diffuse.channel_count} channel(s){images}"
            )
        if self.moving is not None:
            lines.append(f"moving Gaussians: {int(self.moving.sum())} of {int(self.estimated.active.sum())} (the rest "
                         f"blend in place)" + self._motion_figures())
        if self.residual is not None:
            distilled = (self.report or {}).get("distilled") if self.residual.learned is not None else None
            line = self.residual.describe()
            if isinstance(distilled, dict):  # ``warp-highlights distil``'s figures
                teacher = "-".join(map(str, distilled.get("teacher_hidden", [])))
                line += (f"; distilled from {teacher}: its images back at {distilled.get('captured_psnr_db')} dB "
                         f"at the lights, {distilled.get('between_psnr_db')} dB between")
            lines.append(line)
        if self.file_sizes is not None:
            where = f" ({self.file_path})" if self.file_path is not None else ""
            lines.append(f"file: {_format_bytes(self.file_sizes['total'])}{where}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"HighlightField({self.light_count} lights, {self.edge_count} directed edges, "
            f"{self.gaussian_count} Gaussians, {self.width}x{self.height})"
        )


# --- validation helper functions -------------------------------------------------------------------


def _positive_int(value, name: str) -> int:
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, (int, np.integer))
        or value < 1
    ):
        raise InputError(f"{name} must be a positive number of pixels, got {value!r}")
    return int(value)


def _canonical_params(params, name: str) -> GaussianParams:
    """A float32-rounded copy of ``params`` with free slots cleared; active weights must be 1."""
    if not isinstance(params, GaussianParams):
        raise InputError(f"{name} must be GaussianParams, got {type(params).__name__}")
    try:
        checked = (
            params.copy()
        )  # re-validates shapes and finiteness (the object may have been edited)
    except (InputError, AttributeError, TypeError, ValueError) as exc:
        raise InputError(f"{name} Gaussians: {exc}") from None
    active = checked.active
    if np.any(checked.weight[active] != 1.0):
        raise InputError(
            f"{name} Gaussians must have weight 1 (a fitted set is unweighted)"
        )
    values = {}
    for key in ("amplitude", "mean", "sigma", "theta"):
        value = finite_array(
            getattr(checked, key), np.float32, f"{name} {key}"
        ).astype(np.float64)
        values[key] = np.where(
            active if value.ndim == 2 else active[..., None], value, 0.0
        )
    return GaussianParams(**values, weight=np.ones(active.shape), active=active.copy())


def _path_array(value, name: str, shape: tuple, active: np.ndarray) -> np.ndarray:
    """A float32 copy with free slots zeroed; the values of active slots must be finite."""
    try:
        array = np.asarray(value)
        if not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
            raise TypeError(array.dtype)
        with np.errstate(over="ignore", invalid="ignore"):
            array = array.astype(np.float32)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real numeric array") from None
    if array.shape != shape:
        tail = ", 2" if len(shape) == 3 else ""
        raise InputError(
            f"{name} must have shape {shape} (directed edges, slots{tail}), got {array.shape}"
        )
    mask = active if array.ndim == 2 else active[..., None]
    array = np.where(mask, array, np.float32(0.0)).astype(np.float32)
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name} has non-finite values or beyond the float32 range")
    return array


def _json_object(value, name: str) -> dict:
    """A plain-JSON copy of a dict: NumPy scalars and arrays become numbers and lists, tuples
    lists, paths strings, and NaN or infinite numbers null (strict JSON has no NaN)."""
    if not isinstance(value, dict):
        raise InputError(f"{name} must be a dict, got {type(value).__name__}")
    try:
        text = json.dumps(_plain(value), default=_json_default, allow_nan=False)
    except (TypeError, ValueError, RecursionError) as exc:
        raise InputError(
            f"{name} is not JSON-able ({exc}); use numbers, strings, lists and dicts"
        ) from None
    return json.loads(text)


def _plain(value):
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _json_default(value):
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"a {type(value).__name__} value is not JSON-able")


def _format_bytes(count: int) -> str:
    if count < 1000:
        return f"{count} B"
    if count < 1000**2:
        return f"{count / 1000:.1f} kB"
    return f"{count / 1000**2:.2f} MB"
