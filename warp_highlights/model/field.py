"""The fitted highlight field and its file format (method.md section 8).

A :class:`HighlightField` holds everything needed to relight: the lights and their triangulation, the
Gaussians estimated for every light, the Gaussians retargeted along every directed edge, the rotation
path chosen per Gaussian and edge, the fit settings and report, the image size, and optionally the
diffuse model.

File format (version 1; any file name, ``.whf`` suggested): a zip archive, deflate-compressed, written
atomically (temporary file in the same folder, fsync, rename). Its first entry is ``header.json``; every
other entry is a standard little-endian ``.npy`` array, so ``numpy.load`` can open the file too.

==============================  ===============  =================================================
entry                           dtype, shape     contents
==============================  ===============  =================================================
``header.json``                 UTF-8 JSON       magic ``"warp-highlights field"``, format version,
                                                 library version, counts, image size, dome flag,
                                                 diffuse layout, light file names, settings, report
``lights/directions.npy``       <f8 (n, 3)       unit light directions (exact)
``triangulation/faces.npy``     <i4 (F, 3)       faces, wound outwards
``gaussians/estimated_counts``  <u2 (n,)         active Gaussians per light
``gaussians/estimated_slots``   <u2 (K,)         slot of each active Gaussian, light-major, increasing
``gaussians/estimated.npy``     <f4 (K, 6)       a, mu_x, mu_y, sigma_x, sigma_y, theta per Gaussian
``gaussians/retargeted.npy``    <f4 (K_r, 6)     the same for the retargeted sets, edge-major; the
                                                 slots of edge (i, j) are those of light i
``paths/delta.npy``             <f4 (K_r,)       signed rotation per retargeted Gaussian (radians)
``paths/centre.npy``            <f4 (K_r, 2)     rotation centre (image heights)
``diffuse/lambert.npy``         <f2 (C, 4, H, W) optional: nbar_x, nbar_y, nbar_z, k_a planes per
                                or <f4           channel (float16 by default, see ``save``)
``diffuse/images.npy``          <f2 (n, C, H, W) optional: diffuse image of every light
==============================  ===============  =================================================

(The ``gaussians/`` count and slot entries end in ``.npy`` too.) The diffuse arrays are stored as
planes (channel-first), which compresses smooth images several times better than the interleaved
in-memory layout. Only active Gaussians are stored.
The directed edges are not stored: they are ``triangulation.directed_edges()``. Weights are not stored:
a fitted set has weight 1 everywhere. Free slots are not stored: they read back as zeros (weight 1), and
the constructor clears them in the same way, so a saved and loaded field equals the original exactly
(except the Lambertian diffuse model, which is stored as float16 unless ``save(lambert_half=False)``).
"""

from __future__ import annotations

import json
import math
import os
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError
from .gaussians import GaussianParams
from .lights import LightSet
from .triangulation import SphericalTriangulation

__all__ = ["DiffuseModel", "HighlightField"]

MAGIC = "warp-highlights field"
"""The ``magic`` string in every field file's header."""

_HEADER = "header.json"
_DIRECTIONS = "lights/directions.npy"
_FACES = "triangulation/faces.npy"
_ESTIMATED_COUNTS = "gaussians/estimated_counts.npy"
_ESTIMATED_SLOTS = "gaussians/estimated_slots.npy"
_ESTIMATED = "gaussians/estimated.npy"
_RETARGETED = "gaussians/retargeted.npy"
_PATH_DELTA = "paths/delta.npy"
_PATH_CENTRE = "paths/centre.npy"
_LAMBERT = "diffuse/lambert.npy"
_IMAGES = "diffuse/images.npy"

_PARAMETER_COLUMNS = ("amplitude", "mean_x", "mean_y", "sigma_x", "sigma_y", "theta")
_PARTS = ("header", "lights", "triangulation", "gaussians", "paths", "diffuse")
_MAX_SLOTS = 65535  # slot indices and counts are stored as uint16
_MAX_HEADER_BYTES = 64 * 2**20
_FLOAT16_MAX = float(np.finfo(np.float16).max)
_UNIT_TOLERANCE = 1e-6  # stored light directions must be unit vectors to this accuracy
_ZIP_LOCAL_HEADER = b"PK\x03\x04"
_ZIP_NAME_OFFSET = 30  # a zip local file header is 30 bytes, then the entry name
# entry dates are fixed, so that the same field always gives the same bytes
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


@dataclass(frozen=True, eq=False)
class DiffuseModel:
    """Diffuse part of a fitted field.

    Attributes:
        lambert: (H, W, C, 4) float32: per pixel and channel nbar_x, nbar_y, nbar_z, k_a of the
            Lambertian model D(omega) = max(nbar . omega, 0) + k_a (method.md section 2).
        images: (n, H, W, C) float16 diffuse images of the n lights (for barycentric blending), or None.

    Raises:
        InputError: wrong shapes, non-finite values, or values beyond float32 (lambert) or float16
            (images).
    """

    lambert: np.ndarray
    images: np.ndarray | None = None

    def __post_init__(self):
        lambert = _finite_array(self.lambert, np.float32, "diffuse lambert")
        if lambert.ndim != 4 or lambert.shape[3] != 4 or min(lambert.shape) < 1:
            raise InputError(
                f"diffuse lambert must have shape (H, W, C, 4), got {lambert.shape}"
            )
        object.__setattr__(self, "lambert", lambert)
        if self.images is not None:
            images = _finite_array(self.images, np.float16, "diffuse images")
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
    """A fitted highlight field (method.md section 8); treat it as immutable once made.

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
        diffuse: The diffuse model, or None.

    The constructor validates everything and raises ``InputError`` (one line) on any inconsistency. It
    stores float32-rounded copies of the Gaussian and path values (the device works in float32; the
    ``GaussianParams`` stay float64 arrays holding float32 values), clears free slots (zeros, weight 1;
    zero path delta and centre; only active slots' path values need to be finite), and keeps ``settings`` and ``report`` as plain JSON values, so that
    ``HighlightField.load(path)`` after ``save(path)`` gives back equal data. Active Gaussians must have
    weight 1. The inputs are not modified.
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

    FORMAT_VERSION = 1
    """Version of the file format that ``save`` writes; ``load`` reads this and older versions."""

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
        if capacity > _MAX_SLOTS:
            raise InputError(
                f"the field has {capacity} slots per set; at most {_MAX_SLOTS} are supported"
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
        self._stored_sizes: dict | None = None
        self._stored_path: Path | None = None

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
    def gaussian_count(self) -> int:
        """Active Gaussians in all sets, estimated and retargeted."""
        return int(self.estimated.active.sum() + self.retargeted.active.sum())

    @property
    def aspect(self) -> float:
        """Image aspect ratio width / height (the Gaussians' x range is (0, aspect))."""
        return self.width / self.height

    def fit_settings(self):
        """The stored settings as a ``FitSettings`` (raises ``InputError`` for unknown keys)."""
        from .config import FitSettings

        return FitSettings.from_dict(self.settings)

    @property
    def exposure(self) -> float:
        """The factor the fit multiplied the input radiance by (``fit --exposure``); 1 when absent."""
        value = self.report.get("exposure")
        return float(value) if isinstance(value, (int, float)) and math.isfinite(value) and value > 0 else 1.0

    def relight(self, directions, *, method: str = "circular", device=None, size: tuple[int, int] | None = None, diffuse: str = "auto"):
        """Images for light direction(s): a ``RelitImages`` (S' in the field's units, I' = D' + S' in
        the input's: divided by ``exposure``), NumPy float32.

        A shortcut for ``Relighter(self, device=..., size=..., diffuse=..., scale=1 / exposure)
        .relight(directions, method=...)``; the relighter (the field's arrays on the device) is kept for
        the next call with the same options (not thread-safe: use one ``Relighter`` per thread). Build
        a ``Relighter`` yourself for the alpha method or batch control.
        """
        import warp as wp

        from .relight import Relighter

        key = (str(wp.get_device(device)), None if size is None else tuple(size), diffuse)
        cache = self.__dict__.setdefault("_relighters", {})
        if key not in cache:
            cache.clear()
            cache[key] = Relighter(self, device=device, size=size, diffuse=diffuse, scale=1.0 / self.exposure)
        return cache[key].relight(directions, method=method)

    def size_report(self) -> dict:
        """Bytes per part as stored (compressed): header, lights, triangulation, gaussians, paths,
        diffuse, container (zip headers and directory) and total.

        The sizes of the last ``save`` or ``load``; for a field never saved or loaded, the sizes that
        ``save()`` would write, measured without writing a file.
        """
        if self._stored_sizes is None:
            return self._write_archive(_CountingSink(), lambert_half=True)
        return dict(self._stored_sizes)

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
        if self._stored_sizes is not None:
            where = f" ({self._stored_path})" if self._stored_path is not None else ""
            lines.append(f"file: {_format_bytes(self._stored_sizes['total'])}{where}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"HighlightField({self.light_count} lights, {self.edge_count} directed edges, "
            f"{self.gaussian_count} Gaussians, {self.width}x{self.height})"
        )

    # --- storage ---------------------------------------------------------------------------------

    def save(self, path, *, lambert_half: bool = True) -> int:
        """Write the field to one file, atomically; returns the bytes written.

        The file is first written to a hidden temporary file in the target's folder, flushed to disk,
        then renamed over ``path``; on any error (or Ctrl-C) the temporary file is removed and an
        existing file at ``path`` is left as it was. Missing parent folders are created.

        Args:
            path: Target file (any name; ``.whf`` suggested).
            lambert_half: Store the Lambertian diffuse model as float16 (half the size; about 3
                significant digits, so it loads back rounded to float16). False stores it exactly.
                Values beyond the float16 range are always stored as float32.

        Raises:
            InputError: ``path`` is a folder, or the file cannot be written (permissions, disk full).
        """
        path = Path(path)
        if path.is_dir():
            raise InputError(f"{path} is a folder; give a file name such as field.whf")
        folder = path.parent
        tmp = folder / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with open(tmp, "xb") as stream:
                sizes = self._write_archive(stream, lambert_half=lambert_half)
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            raise InputError(
                f"{path}: cannot write the field file ({exc.strerror or exc})"
            ) from None
        finally:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
        _fsync_folder(folder)
        self._stored_sizes, self._stored_path = sizes, path
        return sizes["total"]

    @classmethod
    def load(cls, path) -> HighlightField:
        """Read a field written by ``save``.

        Raises:
            InputError: one line naming the file: missing or unreadable, not a field file, written by
                a newer version, truncated, or corrupt (failed checksum, missing entry, wrong dtype or
                shape, out-of-range index, non-finite value, inconsistent counts).
        """
        path = Path(path)
        try:
            stream = open(path, "rb")  # noqa: SIM115 (closed below; open errors reported apart from read errors)
        except FileNotFoundError:
            raise InputError(f"{path}: field file not found") from None
        except IsADirectoryError:
            raise InputError(f"{path} is a folder, not a field file") from None
        except OSError as exc:
            raise InputError(
                f"{path}: cannot read the field file ({exc.strerror or exc})"
            ) from None
        with stream:
            try:
                field = _read_field(cls, path, stream)
            except (InputError, MemoryError):
                raise
            except Exception as exc:  # noqa: BLE001 (zipfile, zlib, numpy or json internals: damaged bytes)
                raise _corrupt(path, f"{type(exc).__name__}: {exc}") from None
        try:
            field.fit_settings()
        except InputError as error:
            raise _corrupt(path, f"stored settings: {error}") from None
        return field

    # --- writing helpers -------------------------------------------------------------------------

    def _header(self, diffuse_layout: dict | None) -> dict:
        return {
            "magic": MAGIC,
            "format_version": self.FORMAT_VERSION,
            "library_version": __version__,
            "light_count": self.light_count,
            "is_dome": bool(self.triangulation.is_dome),
            "face_count": self.triangulation.face_count,
            "directed_edge_count": self.edge_count,
            "capacity": self.capacity,
            "width": self.width,
            "height": self.height,
            "estimated_gaussian_count": int(self.estimated.active.sum()),
            "retargeted_gaussian_count": int(self.retargeted.active.sum()),
            "parameter_columns": list(_PARAMETER_COLUMNS),
            "diffuse": diffuse_layout,
            "light_filenames": self.lights.filenames,
            "settings": self.settings,
            "report": self.report,
        }

    def _write_archive(self, stream, *, lambert_half: bool) -> dict:
        """Write the zip archive to a binary stream; returns the size report."""
        # row-major order: light by light (edge by edge), slots increasing; load scatters the same way
        est_rows, est_slots = np.nonzero(self.estimated.active)
        ret_rows, ret_slots = np.nonzero(self.retargeted.active)
        arrays = [
            (_DIRECTIONS, self.lights.directions.astype("<f8")),
            (_FACES, self.triangulation.faces.astype("<i4")),
            (_ESTIMATED_COUNTS, self.counts.astype("<u2")),
            (_ESTIMATED_SLOTS, est_slots.astype("<u2")),
            (_ESTIMATED, _pack(self.estimated, est_rows, est_slots)),
            (_RETARGETED, _pack(self.retargeted, ret_rows, ret_slots)),
            (_PATH_DELTA, self.path_delta[ret_rows, ret_slots].astype("<f4")),
            (_PATH_CENTRE, self.path_centre[ret_rows, ret_slots].astype("<f4")),
        ]
        diffuse_layout = None
        if self.diffuse is not None:
            lambert = self.diffuse.lambert
            half = lambert_half and float(np.abs(lambert).max()) <= _FLOAT16_MAX
            diffuse_layout = {
                "channels": self.diffuse.channel_count,
                "lambert_dtype": "float16" if half else "float32",
                "images": self.diffuse.images is not None,
            }
            planes = lambert.transpose(2, 3, 0, 1).astype("<f2" if half else "<f4")
            arrays.append((_LAMBERT, planes))
            if self.diffuse.images is not None:
                images = self.diffuse.images.transpose(0, 3, 1, 2).astype("<f2")
                arrays.append((_IMAGES, images))
        header = json.dumps(
            self._header(diffuse_layout), indent=1, allow_nan=False
        ).encode("utf-8")
        with zipfile.ZipFile(stream, "w") as archive:
            with archive.open(_entry_info(_HEADER), "w") as entry:
                entry.write(header)
            for name, array in arrays:
                _write_array(archive, name, array)
            infos = archive.infolist()
        return _size_report(infos, stream.tell())


# --- validation helpers ----------------------------------------------------------------------------


def _positive_int(value, name: str) -> int:
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, (int, np.integer))
        or value < 1
    ):
        raise InputError(f"{name} must be a positive number of pixels, got {value!r}")
    return int(value)


def _finite_array(value, dtype, name: str) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype``; every element finite after the conversion."""
    try:
        array = np.asarray(value)
        if not (
            np.issubdtype(array.dtype, np.number) or array.dtype == bool
        ) or np.iscomplexobj(array):
            raise TypeError(array.dtype)
        with np.errstate(over="ignore", invalid="ignore"):
            array = np.ascontiguousarray(array, dtype=dtype)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real numeric array") from None
    if not np.all(np.isfinite(array)):
        limit = (
            ""
            if dtype == np.float64
            else f" or beyond the {np.dtype(dtype).name} range"
        )
        raise InputError(f"{name} has non-finite values{limit}")
    return array


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
        value = _finite_array(
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


# --- writing helpers -------------------------------------------------------------------------------


def _pack(params: GaussianParams, rows: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """(K, 6) little-endian float32 rows [a, mu_x, mu_y, sigma_x, sigma_y, theta] of the given slots."""
    columns = [
        params.amplitude[rows, slots],
        params.mean[rows, slots, 0],
        params.mean[rows, slots, 1],
        params.sigma[rows, slots, 0],
        params.sigma[rows, slots, 1],
        params.theta[rows, slots],
    ]
    return np.stack(columns, axis=1).astype("<f4")


def _entry_info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def _write_array(archive: zipfile.ZipFile, name: str, array: np.ndarray) -> None:
    """One ``.npy`` entry (deflated; zip64 when it may pass the 2 GiB limit of plain zip)."""
    with archive.open(
        _entry_info(name), "w", force_zip64=array.nbytes > 2**30
    ) as entry:
        np.lib.format.write_array(
            entry, np.ascontiguousarray(array), allow_pickle=False
        )


def _size_report(infos: list[zipfile.ZipInfo], total: int) -> dict:
    sizes = dict.fromkeys(_PARTS, 0)
    for info in infos:
        part = "header" if info.filename == _HEADER else info.filename.split("/")[0]
        if part in sizes:
            sizes[part] += info.compress_size
    sizes["container"] = total - sum(sizes.values())
    sizes["total"] = total
    return sizes


class _CountingSink:
    """A write-only, seekable stream that keeps only its size (to measure a file without writing it)."""

    def __init__(self):
        self._position = 0
        self._size = 0

    def write(self, data) -> int:
        length = memoryview(data).nbytes
        self._position += length
        self._size = max(self._size, self._position)
        return length

    def tell(self) -> int:
        return self._position

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self._position, 2: self._size}[whence]
        self._position = base + offset
        return self._position

    def seekable(self) -> bool:
        return True

    def flush(self) -> None:
        pass


def _fsync_folder(folder: Path) -> None:
    """Make the rename durable where the platform allows (POSIX); best effort."""
    if os.name != "posix":
        return
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def _format_bytes(count: int) -> str:
    if count < 1000:
        return f"{count} B"
    if count < 1000**2:
        return f"{count / 1000:.1f} kB"
    return f"{count / 1000**2:.2f} MB"


# --- reading ---------------------------------------------------------------------------------------


def _corrupt(path: Path, what: str) -> InputError:
    return InputError(
        f"{path}: corrupt field file: {what}; write it again (or restore a copy)"
    )


def _not_a_field(path: Path, what: str) -> InputError:
    return InputError(f"{path}: not a warp-highlights field file ({what})")


def _sniff(head: bytes) -> str:
    """A few words on what a file that is not a zip archive looks like."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "a PNG image"
    if head.startswith(b"\xff\xd8\xff"):
        return "a JPEG image"
    if head.startswith(b"\x76\x2f\x31\x01"):
        return "an OpenEXR image"
    if head.startswith(b"\x93NUMPY"):
        return "a NumPy .npy array"
    if all(byte >= 0x20 or byte in b"\t\r\n" for byte in head):
        return "a text file"
    return "unrecognised binary content"


def _read_field(cls, path: Path, stream) -> HighlightField:
    head = stream.read(64)
    if not head:
        raise InputError(f"{path}: empty file, not a warp-highlights field file")
    if not head.startswith(_ZIP_LOCAL_HEADER):
        raise _not_a_field(path, _sniff(head))
    # our files start with the local header of header.json; a cut may leave part of the name
    ours = _HEADER.encode().startswith(
        head[_ZIP_NAME_OFFSET : _ZIP_NAME_OFFSET + len(_HEADER)]
    )
    stream.seek(0)
    try:
        archive = zipfile.ZipFile(stream)
    except (
        zipfile.BadZipFile,
        EOFError,
        OSError,
        ValueError,
        NotImplementedError,
    ) as exc:
        if ours:
            raise InputError(
                f"{path}: truncated or corrupt field file (its zip directory cannot be read: {exc}); write it again"
            ) from None
        raise _not_a_field(path, f"a damaged zip archive: {exc}") from None
    with archive:
        names = set(archive.namelist())
        if _HEADER not in names:
            raise _not_a_field(path, f"a zip archive without {_HEADER}")
        header = _read_header(path, archive)
        return _build_field(cls, path, archive, names, header, stream)


def _read_header(path: Path, archive: zipfile.ZipFile) -> dict:
    info = archive.getinfo(_HEADER)
    if info.file_size > _MAX_HEADER_BYTES:
        raise _corrupt(path, f"{_HEADER} is {info.file_size} bytes")
    with archive.open(info) as entry:
        raw = entry.read(_MAX_HEADER_BYTES + 1)
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise _corrupt(path, f"{_HEADER} is not valid JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise _not_a_field(path, f"{_HEADER} lacks the magic string {MAGIC!r}")
    version = header.get("format_version")
    if not _is_int(version) or version < 1:
        raise _corrupt(
            path, f"format_version must be a positive integer, got {version!r}"
        )
    if version > HighlightField.FORMAT_VERSION:
        raise InputError(
            f"{path}: written by a newer warp-highlights (library {header.get('library_version')!s}, field format "
            f"{version}; this version {__version__} reads format {HighlightField.FORMAT_VERSION}); upgrade warp-highlights"
        )
    return header


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _header_int(
    path: Path, header: dict, key: str, minimum: int, maximum: int | None = None
) -> int:
    value = header.get(key)
    if (
        not _is_int(value)
        or value < minimum
        or (maximum is not None and value > maximum)
    ):
        upper = "" if maximum is None else f"..{maximum}"
        raise _corrupt(
            path,
            f"header entry {key!r} must be an integer in {minimum}{upper or ' or more'}, got {value!r}",
        )
    return value


def _header_value(path: Path, header: dict, key: str, kinds: tuple, description: str):
    value = header.get(key)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        raise _corrupt(
            path, f"header entry {key!r} must be {description}, got {value!r}"
        )
    return value


def _read_array(
    path: Path,
    archive: zipfile.ZipFile,
    names: set,
    name: str,
    dtype: str,
    shape: tuple,
) -> np.ndarray:
    """Read one ``.npy`` entry, checking its dtype and shape before reading the data."""
    if name not in names:
        raise _corrupt(path, f"entry {name} is missing")
    expected = np.dtype(dtype)
    with archive.open(name) as entry:
        try:
            version = np.lib.format.read_magic(entry)
            if version == (1, 0):
                stored_shape, fortran, stored_dtype = (
                    np.lib.format.read_array_header_1_0(entry)
                )
            elif version == (2, 0):
                stored_shape, fortran, stored_dtype = (
                    np.lib.format.read_array_header_2_0(entry)
                )
            else:
                raise ValueError(f"unsupported .npy version {version}")
        except ValueError as exc:
            raise _corrupt(
                path, f"entry {name} is not a valid .npy array ({exc})"
            ) from None
        if stored_dtype != expected:
            raise _corrupt(
                path,
                f"entry {name} holds {stored_dtype.str} data, expected {expected.str}",
            )
        if fortran:
            raise _corrupt(path, f"entry {name} is stored in Fortran order")
        if tuple(stored_shape) != tuple(shape):
            raise _corrupt(
                path,
                f"entry {name} has shape {tuple(stored_shape)}, expected {tuple(shape)}",
            )
        size = math.prod(shape) * expected.itemsize
        data = entry.read(size)
        if len(data) != size:
            raise _corrupt(path, f"entry {name} is truncated")
        if entry.read(1):  # also completes the zip checksum test
            raise _corrupt(path, f"entry {name} has data after its array")
    array = (
        np.frombuffer(data, dtype=expected)
        .reshape(shape)
        .astype(expected.newbyteorder("="))
    )
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise _corrupt(path, f"entry {name} has non-finite values")
    return array


def _build_field(
    cls, path: Path, archive: zipfile.ZipFile, names: set, header: dict, stream
) -> HighlightField:
    n = _header_int(path, header, "light_count", 3)
    face_count = _header_int(path, header, "face_count", 1)
    edge_count = _header_int(path, header, "directed_edge_count", 2)
    capacity = _header_int(path, header, "capacity", 1, _MAX_SLOTS)
    width = _header_int(path, header, "width", 1)
    height = _header_int(path, header, "height", 1)
    estimated_total = _header_int(
        path, header, "estimated_gaussian_count", 0, n * capacity
    )
    retargeted_total = _header_int(
        path, header, "retargeted_gaussian_count", 0, edge_count * capacity
    )
    is_dome = _header_value(path, header, "is_dome", (bool,), "true or false")
    settings = _header_value(path, header, "settings", (dict,), "a JSON object")
    report = _header_value(path, header, "report", (dict,), "a JSON object")
    filenames = header.get("light_filenames")
    if filenames is not None and (
        not isinstance(filenames, list)
        or len(filenames) != n
        or not all(isinstance(f, str) for f in filenames)
    ):
        raise _corrupt(
            path, f"header entry 'light_filenames' must be null or {n} strings"
        )
    diffuse_layout = header.get("diffuse")
    if diffuse_layout is not None:
        if not isinstance(diffuse_layout, dict):
            raise _corrupt(path, "header entry 'diffuse' must be null or a JSON object")
        channels = _header_int(path, diffuse_layout, "channels", 1)
        lambert_dtype = diffuse_layout.get("lambert_dtype")
        if lambert_dtype not in ("float16", "float32"):
            raise _corrupt(
                path,
                f"diffuse lambert_dtype must be 'float16' or 'float32', got {lambert_dtype!r}",
            )
        with_images = _header_value(
            path, diffuse_layout, "images", (bool,), "true or false"
        )

    def read(name, dtype, shape):
        return _read_array(path, archive, names, name, dtype, shape)

    directions = read(_DIRECTIONS, "<f8", (n, 3))
    if np.any(np.abs(np.linalg.norm(directions, axis=1) - 1.0) > _UNIT_TOLERANCE):
        raise _corrupt(
            path, f"entry {_DIRECTIONS} holds vectors that are not unit length"
        )
    faces = read(_FACES, "<i4", (face_count, 3))
    if faces.min() < 0 or faces.max() >= n:
        raise _corrupt(path, f"entry {_FACES} has vertex indices outside 0..{n - 1}")
    try:
        lights = LightSet(directions, filenames)
        triangulation = SphericalTriangulation.from_faces(directions, faces)
    except InputError as exc:
        raise _corrupt(path, str(exc)) from None
    # keep the stored directions bit for bit (normalising a unit vector again may change its last bit)
    lights.directions = directions
    triangulation.directions = directions
    if triangulation.is_dome != is_dome:
        raise _corrupt(
            path,
            f"the header says is_dome={is_dome} but the faces say {triangulation.is_dome}",
        )
    directed = triangulation.directed_edges()
    if len(directed) != edge_count:
        raise _corrupt(
            path,
            f"the faces give {len(directed)} directed edges but the header says {edge_count}",
        )

    counts = read(_ESTIMATED_COUNTS, "<u2", (n,)).astype(np.int64)
    if counts.max() > capacity or counts.sum() != estimated_total:
        raise _corrupt(
            path,
            f"entry {_ESTIMATED_COUNTS} does not match the capacity and the Gaussian count",
        )
    slots = read(_ESTIMATED_SLOTS, "<u2", (estimated_total,)).astype(np.int64)
    owners = np.repeat(np.arange(n), counts)
    if estimated_total and (
        slots.max() >= capacity
        or np.any((slots[1:] <= slots[:-1]) & (owners[1:] == owners[:-1]))
    ):
        raise _corrupt(
            path,
            f"entry {_ESTIMATED_SLOTS} has slot indices out of range or out of order",
        )
    estimated_active = np.zeros((n, capacity), dtype=bool)
    estimated_active[owners, slots] = True
    retargeted_active = estimated_active[directed[:, 0]]
    if int(retargeted_active.sum()) != retargeted_total:
        raise _corrupt(
            path,
            "the retargeted Gaussian count in the header does not match the estimated slots",
        )

    estimated = _unpack(read(_ESTIMATED, "<f4", (estimated_total, 6)), estimated_active)
    retargeted = _unpack(
        read(_RETARGETED, "<f4", (retargeted_total, 6)), retargeted_active
    )
    rows, cols = np.nonzero(retargeted_active)
    path_delta = np.zeros((edge_count, capacity), dtype=np.float32)
    path_delta[rows, cols] = read(_PATH_DELTA, "<f4", (retargeted_total,))
    path_centre = np.zeros((edge_count, capacity, 2), dtype=np.float32)
    path_centre[rows, cols] = read(_PATH_CENTRE, "<f4", (retargeted_total, 2))

    diffuse = None
    if diffuse_layout is not None:
        lambert_code = "<f2" if lambert_dtype == "float16" else "<f4"
        planes = read(_LAMBERT, lambert_code, (channels, 4, height, width))
        lambert = planes.transpose(2, 3, 0, 1)
        images = None
        if with_images:
            images = read(_IMAGES, "<f2", (n, channels, height, width)).transpose(
                0, 2, 3, 1
            )
        try:
            diffuse = DiffuseModel(lambert, images)
        except InputError as exc:
            raise _corrupt(path, str(exc)) from None

    try:
        field = cls(
            lights=lights,
            triangulation=triangulation,
            width=width,
            height=height,
            estimated=estimated,
            directed_edges=directed,
            retargeted=retargeted,
            path_delta=path_delta,
            path_centre=path_centre,
            settings=settings,
            report=report,
            diffuse=diffuse,
        )
    except InputError as exc:
        raise _corrupt(path, str(exc)) from None
    stream.seek(0, os.SEEK_END)
    field._stored_sizes = _size_report(archive.infolist(), stream.tell())
    field._stored_path = path
    return field


def _unpack(rows: np.ndarray, active: np.ndarray) -> GaussianParams:
    """Inverse of ``_pack``: scatter (K, 6) rows into the active slots (row-major order) of a batch."""
    params = GaussianParams.empty(*active.shape)
    r, s = np.nonzero(active)
    values = rows.astype(np.float64)
    params.amplitude[r, s] = values[:, 0]
    params.mean[r, s] = values[:, 1:3]
    params.sigma[r, s] = values[:, 3:5]
    params.theta[r, s] = values[:, 5]
    params.active = active
    return params
