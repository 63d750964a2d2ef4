"""Triangle meshes of the synthetic objects: donut (torus), sphere, Utah teapot, or a mesh file.

Every builder returns a :class:`TriangleMesh`: float64 points, int32 faces wound counter-clockwise seen
from outside (the right-hand normal points out), and unit smooth-shading vertex normals that point out.
The renderer builds a ``wp.Mesh`` from ``points``/``faces`` and interpolates ``normals`` with the hit
barycentrics. Lengths are in the caller's units (the teapot keeps Newell's original units, about
6.4 x 3.15 x 4). The up axis is +y for every built-in shape.

Only NumPy and SciPy are needed, except :func:`load_mesh`, which imports pyvista when called.

This module holds one thing: the meshes of the built-in shapes (and a mesh file loaded as one).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from .relief import bump_height, coin_height

__all__ = [
    "SHAPE_NAMES",
    "TriangleMesh",
    "bumpy_torus",
    "coin",
    "load_mesh",
    "make_shape",
    "signed_volume",
    "sphere",
    "teapot",
    "torus",
    "vertex_normals",
    "weld_vertices",
]

SHAPE_NAMES = ("donut", "teapot", "sphere", "coin", "bumpy")
"""Names of the built-in shapes accepted by :func:`make_shape` ("torus" is an alias of "donut"): "coin" is a
relief plate facing the camera, "bumpy" a donut with small bumps all over."""

_MESH_SUFFIXES = "PLY/OBJ/STL"
_RELATIVE_WELD_TOLERANCE = 1e-7
"""Vertex welding distance as a fraction of the bounding-box diagonal."""


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """An indexed triangle mesh with outward winding and smooth vertex normals.

    Attributes:
        points: (V, 3) float64 vertex positions [length units].
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        normals: (V, 3) float64 unit vertex normals pointing out.
        name: Short label ("donut", "teapot", a file stem...).
    """

    points: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    name: str = "mesh"

    def __post_init__(self):
        points = np.ascontiguousarray(self.points, dtype=np.float64)
        faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        normals = np.ascontiguousarray(self.normals, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (V, 3), got {points.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
        if normals.shape != points.shape:
            raise ValueError(f"normals must have shape {points.shape}, got {normals.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= len(points)):
            raise ValueError("faces index outside the points array")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "normals", normals)

    @property
    def vertex_count(self) -> int:
        """Number of vertices V."""
        return int(self.points.shape[0])

    @property
    def face_count(self) -> int:
        """Number of triangles F."""
        return int(self.faces.shape[0])

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """An enclosing sphere centred on the bounding-box centre.

        Returns:
            ``(centre, radius)``: centre (3,) float64 and radius [length units].
        """
        lower, upper = self.points.min(axis=0), self.points.max(axis=0)
        centre = 0.5 * (lower + upper)
        radius = float(np.sqrt(((self.points - centre) ** 2).sum(axis=1).max()))
        return centre, radius

    def transformed(self, *, rotation=None, scale: float = 1.0, translation=None) -> TriangleMesh:
        """A copy moved by ``p' = scale * R p + t``.

        Normals are rotated by R. A reflection (det R < 0 or scale < 0) reverses the winding so that
        faces and normals still face out.

        Args:
            rotation: (3, 3) orthogonal matrix R; identity when None.
            scale: Uniform scale factor, non-zero.
            translation: (3,) offset t [length units]; zero when None.

        Returns:
            The transformed mesh, same name.
        """
        matrix = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if matrix.shape != (3, 3) or not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-6):
            raise ValueError("rotation must be an orthogonal 3x3 matrix")
        if not np.isfinite(scale) or scale == 0.0:
            raise ValueError(f"scale must be finite and non-zero, got {scale}")
        offset = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        if offset.shape != (3,):
            raise ValueError(f"translation must have shape (3,), got {offset.shape}")
        points = scale * self.points @ matrix.T + offset
        normals = np.sign(scale) * self.normals @ matrix.T
        mirrored = np.linalg.det(matrix) * np.sign(scale) < 0.0
        faces = self.faces[:, ::-1] if mirrored else self.faces
        return TriangleMesh(points, faces, normals, self.name)

    def normalized(self) -> TriangleMesh:
        """A copy centred on its bounding-sphere centre and scaled to radius 1."""
        centre, radius = self.bounding_sphere()
        if radius <= 0.0:
            raise ValueError(f"mesh {self.name!r} has zero extent and cannot be normalized")
        return self.transformed(scale=1.0 / radius, translation=-centre / radius)


# ---------------------------------------------------------------------------------------------------
# Mesh helper functions


def _doubled_area_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted face normals: (F, 3) cross products, length = 2 * area [length^2]."""
    corners = points[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def signed_volume(points: np.ndarray, faces: np.ndarray, *, origin=None) -> float:
    """Signed volume enclosed by a triangle mesh; positive for outward winding.

    Args:
        points: (V, 3) vertex positions [length units].
        faces: (F, 3) vertex indices.
        origin: (3,) apex of the summed tetrahedra; the bounding-box centre when None. It does not
            change the result for a closed mesh and keeps it meaningful for a nearly closed one.

    Returns:
        Volume [length^3].
    """
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces)
    if origin is None:
        origin = 0.5 * (points.min(axis=0) + points.max(axis=0)) if len(points) else np.zeros(3)
    corners = points[faces] - np.asarray(origin, dtype=np.float64)
    triple = np.einsum("fk,fk->f", corners[:, 0], np.cross(corners[:, 1], corners[:, 2]))
    return float(triple.sum() / 6.0)


def weld_vertices(points: np.ndarray, faces: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than ``tolerance`` and drop the faces that collapse.

    Clusters are the connected components of the "closer than tolerance" graph; each cluster becomes
    one vertex at the cluster mean. Vertices no face references are removed.

    Args:
        points: (V, 3) vertex positions [length units].
        faces: (F, 3) vertex indices.
        tolerance: Merge distance [length units], >= 0.

    Returns:
        ``(points, faces)``: welded (V', 3) float64 points and (F', 3) int32 faces without repeated
        indices.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pairs = cKDTree(points).query_pairs(r=float(tolerance), output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points))
    )
    cluster_count, labels = connected_components(graph, directed=False)
    sums = np.zeros((cluster_count, 3))
    np.add.at(sums, labels, points)
    counts = np.bincount(labels, minlength=cluster_count)[:, None]
    welded_faces = labels[faces]
    return _compact(sums / counts, _drop_repeated_indices(welded_faces))


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Smooth vertex normals: area-weighted face normals summed per vertex, then normalized.

    A vertex whose sum vanishes (unreferenced, or opposite faces cancelling) gets the direction from the
    bounding-box centre, or +y, so the result is never NaN.

    Args:
        points: (V, 3) vertex positions [length units].
        faces: (F, 3) vertex indices, outward winding.

    Returns:
        (V, 3) float64 unit normals.
    """
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    weighted = _doubled_area_normals(points, faces)
    sums = np.zeros_like(points)
    np.add.at(sums, faces.ravel(), np.repeat(weighted, 3, axis=0))
    magnitudes = np.zeros(len(points))
    np.add.at(magnitudes, faces.ravel(), np.repeat(np.linalg.norm(weighted, axis=1), 3))
    return _unit_or_fallback(sums, points, magnitudes)


def _unit_or_fallback(vectors: np.ndarray, points: np.ndarray, magnitudes: np.ndarray) -> np.ndarray:
    """Normalize rows of ``vectors``, sums of contributions whose lengths sum to ``magnitudes``.

    Rows that (nearly) cancel take the outward direction from the bounding-box centre, or +y.
    """
    lengths = np.linalg.norm(vectors, axis=1)
    bad = ~((lengths > 1e-9 * magnitudes) & (magnitudes > 0.0))
    result = np.zeros_like(vectors)
    result[~bad] = vectors[~bad] / lengths[~bad, None]
    if np.any(bad):
        centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
        radial = points[bad] - centre
        radial_lengths = np.linalg.norm(radial, axis=1)
        fallback = np.tile([0.0, 1.0, 0.0], (len(radial), 1))
        ok = radial_lengths > 0.0
        fallback[ok] = radial[ok] / radial_lengths[ok, None]
        result[bad] = fallback
    return result


def _drop_repeated_indices(faces: np.ndarray) -> np.ndarray:
    """Faces whose three indices differ."""
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    return faces[keep]


def _drop_degenerate_faces(
    points: np.ndarray, faces: np.ndarray, *, relative_area: float = 1e-12
) -> np.ndarray:
    """Faces with repeated indices or (near) zero area removed, and exact duplicate faces kept once."""
    faces = _drop_repeated_indices(faces)
    if len(faces) == 0:
        return faces
    doubled_area = np.linalg.norm(_doubled_area_normals(points, faces), axis=1)
    extent = np.ptp(points, axis=0).max() if len(points) else 0.0
    faces = faces[doubled_area > relative_area * extent**2]
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    return faces[np.sort(first)]


def _compact(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove unreferenced vertices and renumber the faces (int32)."""
    used = np.zeros(len(points), dtype=bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    return np.ascontiguousarray(points[used]), new_index[faces].astype(np.int32)


def _clean(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weld at a tolerance relative to the mesh size, then drop degenerate and duplicate faces."""
    points = np.asarray(points, dtype=np.float64)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0
    points, faces = weld_vertices(points, faces, _RELATIVE_WELD_TOLERANCE * diagonal)
    return _compact(points, _drop_degenerate_faces(points, faces))


def _grid_faces(rows: int, cols: int, *, wrap_rows: bool = False, wrap_cols: bool = False) -> np.ndarray:
    """Two triangles per cell of a (rows, cols) vertex grid indexed ``i * cols + j``.

    Winding: with the row index i along u and the column index j along v, each triangle's right-hand
    normal is along dv x du. Wrapping joins the last row (column) to the first one.
    """
    cell_rows = rows if wrap_rows else rows - 1
    cell_cols = cols if wrap_cols else cols - 1
    i, j = np.meshgrid(np.arange(cell_rows), np.arange(cell_cols), indexing="ij")
    i_next, j_next = (i + 1) % rows, (j + 1) % cols
    a, b = i * cols + j, i_next * cols + j
    c, d = i_next * cols + j_next, i * cols + j_next
    lower = np.stack([a, d, c], axis=-1).reshape(-1, 3)
    upper = np.stack([a, c, b], axis=-1).reshape(-1, 3)
    return np.concatenate([lower, upper]).astype(np.int32)


# ---------------------------------------------------------------------------------------------------
# Built-in shapes


def torus(
    *,
    major_radius: float = 1.0,
    minor_radius: float = 0.4,
    major_segments: int = 192,
    minor_segments: int = 96,
) -> TriangleMesh:
    """A closed torus ("donut") around the +y axis, lying in the x-z plane, with analytic normals.

    Args:
        major_radius: Distance from the centre to the tube centre [length units].
        minor_radius: Tube radius [length units], smaller than ``major_radius``.
        major_segments: Vertices around the y axis (>= 3).
        minor_segments: Vertices around the tube (>= 3).

    Returns:
        The torus, ``major_segments * minor_segments`` vertices.
    """
    if not 0.0 < minor_radius < major_radius:
        raise InputError(
            f"torus radii major={major_radius}, minor={minor_radius} are impossible: "
            "use 0 < minor_radius < major_radius"
        )
    if major_segments < 3 or minor_segments < 3:
        raise InputError(f"torus segments {major_segments}x{minor_segments} are too few: use at least 3 each")
    u = 2.0 * np.pi * np.arange(major_segments) / major_segments
    v = 2.0 * np.pi * np.arange(minor_segments) / minor_segments
    uu, vv = np.meshgrid(u, v, indexing="ij")
    normals = np.stack([np.cos(vv) * np.cos(uu), np.sin(vv), np.cos(vv) * np.sin(uu)], axis=-1).reshape(-1, 3)
    centres = major_radius * np.stack([np.cos(uu), np.zeros_like(uu), np.sin(uu)], axis=-1).reshape(-1, 3)
    points = centres + minor_radius * normals
    faces = _grid_faces(major_segments, minor_segments, wrap_rows=True, wrap_cols=True)
    return TriangleMesh(points, faces, normals, "donut")


def bumpy_torus(*, major_segments: int = 384, minor_segments: int = 192) -> TriangleMesh:
    """The donut of :func:`torus` with small random bumps (``relief.bump_height``) pushed along its
    normals; finer than the smooth donut so that each bump is a few dozen triangles."""
    smooth = torus(major_segments=major_segments, minor_segments=minor_segments)
    points = smooth.points + bump_height(smooth.points)[:, None] * smooth.normals
    return TriangleMesh(points, smooth.faces, vertex_normals(points, smooth.faces), "bumpy")


def coin(*, resolution: int = 384) -> TriangleMesh:
    """A square plate over [-1, 1]^2 facing +z with a coin's relief (``relief.coin_height``) on it, the
    way an RTI dome sees a coin: from above. ``resolution`` vertices along each side (>= 8)."""
    if resolution < 8:
        raise InputError(f"coin resolution {resolution} is too coarse: use at least 8")
    axis = np.linspace(-1.0, 1.0, resolution)
    y, x = np.meshgrid(axis[::-1], axis, indexing="ij")  # rows from the top (+y), columns to the right
    points = np.stack([x, y, coin_height(x, y)], axis=-1).reshape(-1, 3)
    faces = _grid_faces(resolution, resolution)
    if _doubled_area_normals(points, faces)[:, 2].sum() < 0:
        faces = faces[:, ::-1].copy()
    return TriangleMesh(points, faces, vertex_normals(points, faces), "coin")


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron: (12, 3) points and (20, 3) outward faces (from the convex hull)."""
    from scipy.spatial import ConvexHull

    golden = 0.5 * (1.0 + np.sqrt(5.0))
    base = np.array([[s1, s2 * golden, 0.0] for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])
    points = np.concatenate([np.roll(base, shift, axis=1) for shift in range(3)])
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    faces = ConvexHull(points).simplices.astype(np.int64)
    return points, _orient_away_from(points, faces, np.zeros(3))


def _orient_away_from(points: np.ndarray, faces: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Reverse the faces whose normal points towards ``centre`` (for star-shaped meshes)."""
    corners = points[faces]
    outward = np.einsum("fk,fk->f", _doubled_area_normals(points, faces), corners.mean(axis=1) - centre) > 0.0
    return np.where(outward[:, None], faces, faces[:, ::-1])


def _subdivide_on_sphere(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle in four at its edge midpoints, projected onto the unit sphere."""
    edges = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1), axis=-1)
    unique_edges, inverse = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    midpoints = points[unique_edges].sum(axis=1)
    midpoints /= np.linalg.norm(midpoints, axis=1, keepdims=True)
    mid = (inverse.reshape(-1, 3) + len(points)).astype(np.int64)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    new_faces = np.concatenate(
        [np.stack(tri, axis=1) for tri in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    )
    return np.concatenate([points, midpoints]), new_faces


def sphere(*, radius: float = 1.0, subdivisions: int = 5) -> TriangleMesh:
    """An icosphere centred at the origin; vertices lie exactly on the sphere, normals are p / |p|.

    Args:
        radius: Sphere radius [length units], > 0.
        subdivisions: Times each icosahedron face is split in four (0..8); 5 gives 20480 faces.

    Returns:
        The sphere, ``10 * 4**subdivisions + 2`` vertices.
    """
    if not radius > 0.0:
        raise InputError(f"sphere radius {radius} is impossible: use a positive radius")
    if not 0 <= subdivisions <= 8:
        raise InputError(f"sphere subdivisions {subdivisions} out of range: use 0 to 8")
    points, faces = _icosahedron()
    for _ in range(subdivisions):
        points, faces = _subdivide_on_sphere(points, faces)
    return TriangleMesh(radius * points, faces, points.copy(), "sphere")


# ---------------------------------------------------------------------------------------------------
# Utah teapot

_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation (x, y, z) -> (x, z, -y): Newell's z-up data to y-up, spout stays along +x."""


@functools.lru_cache(maxsize=1)
def _teapot_control_net() -> np.ndarray:
    """Newell's 32 bicubic patches as (32, 4, 4, 3) control points, z up, original units."""
    text = resources.files("warp_highlights.synth").joinpath("data", "teapot.txt").read_text(encoding="utf-8")
    sections: dict[str, list[list[str]]] = {}
    current = None
    for line in text.splitlines():
        words = line.split("#", 1)[0].split()
        if len(words) == 2 and words[0] in ("patches", "points"):
            current = sections.setdefault(words[0], [])
        elif words:
            current.append(words)
    patches = np.array(sections["patches"], dtype=np.int64) - 1
    control_points = np.array(sections["points"], dtype=np.float64)
    net = control_points[patches].reshape(-1, 4, 4, 3)
    net.setflags(write=False)
    return net


def _bernstein_cubic(t: np.ndarray) -> np.ndarray:
    """Cubic Bernstein basis: (len(t), 4) weights at parameters t in [0, 1]."""
    s = 1.0 - t
    return np.stack([s**3, 3.0 * s * s * t, 3.0 * s * t * t, t**3], axis=1)


def _tessellate_patches(net: np.ndarray, subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate bicubic patches on a (s+1) x (s+1) grid each: points (P*(s+1)^2, 3), faces (P*2s^2, 3)."""
    basis = _bernstein_cubic(np.linspace(0.0, 1.0, subdivisions + 1))
    grid = np.einsum("ia,pabk,jb->pijk", basis, net, basis)
    per_patch = (subdivisions + 1) ** 2
    local = _grid_faces(subdivisions + 1, subdivisions + 1)
    offsets = per_patch * np.arange(len(net))[:, None, None]
    return grid.reshape(-1, 3), (local[None] + offsets).reshape(-1, 3)


def teapot(*, subdivisions: int = 12) -> TriangleMesh:
    """The Utah teapot, tessellated from Newell's 32 bicubic Bezier patches (bottom included).

    The mesh is y-up with the spout towards +x and the bottom at y = 0, in the original units (bbox about
    6.4 x 3.15 x 4). Patch seams are welded, the collapsed poles (lid top, bottom centre) leave no
    degenerate triangles, and normals are area-weighted vertex normals. Like the original, the surface
    is not watertight: the spout and handle ends are open and run into the body, and a thin ring
    between the lid (radius 1.3) and the rim (radius 1.4) is open.

    Args:
        subdivisions: Grid cells along each side of every patch (1..128).

    Returns:
        The teapot, about ``32 * 2 * subdivisions**2`` triangles.
    """
    if not 1 <= subdivisions <= 128:
        raise InputError(f"teapot subdivisions {subdivisions} out of range: use 1 to 128")
    points, faces = _tessellate_patches(_teapot_control_net(), int(subdivisions))
    points, faces = _clean(points @ _Z_UP_TO_Y_UP.T, faces)
    return TriangleMesh(points, faces, vertex_normals(points, faces), "teapot")


# ---------------------------------------------------------------------------------------------------
# Mesh files


def load_mesh(path) -> TriangleMesh:
    """Read a mesh file (anything ``pyvista.read`` reads: PLY, OBJ, STL, VTK, VTP...).

    The surface is triangulated, welded, cleaned of degenerate faces, wound consistently and outward
    (per connected part, by the sign of its enclosed volume), and given area-weighted vertex normals.
    Coordinates are kept as they are in the file.

    Args:
        path: Mesh file.

    Returns:
        The mesh, named after the file stem.

    Raises:
        InputError: The file is missing, unreadable, or holds no triangles.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        what = "is a folder, not a file" if path.is_dir() else "not found"
        raise InputError(f"mesh file {path} {what}: give the path of a {_MESH_SUFFIXES} file")
    surface = _read_surface(path)
    points, faces = _triangles_of(surface)
    if len(faces):
        points, faces = _clean(points, faces)
    if len(faces) == 0:
        raise InputError(
            f"mesh file {path} holds no triangles with area: give a surface mesh ({_MESH_SUFFIXES})"
        )
    if not np.isfinite(points).all():
        raise InputError(f"mesh file {path} has non-finite coordinates: fix or re-export the mesh")
    faces = _orient_outward(points, _orient_consistently(points, faces))
    return TriangleMesh(points, faces, vertex_normals(points, faces), path.stem)


def _read_surface(path: Path):
    """pyvista PolyData of the outer surface of whatever ``pyvista.read`` finds in ``path``."""
    import pyvista as pv

    try:
        data = _read_quietly(pv, path)
    except Exception as error:  # readers raise many types; all mean "cannot read this file"
        reason = " ".join(str(error).split()) or type(error).__name__
        raise InputError(
            f"cannot read mesh file {path} ({reason[:120]}): give a valid {_MESH_SUFFIXES} file"
        ) from None
    if isinstance(data, pv.MultiBlock):
        data = data.combine()
    if data is None or not hasattr(data, "extract_surface"):
        raise InputError(f"mesh file {path} holds no surface: give a {_MESH_SUFFIXES} mesh file")
    return data if isinstance(data, pv.PolyData) else data.extract_surface()


def _read_quietly(pv, path: Path):
    """``pyvista.read`` without VTK's console noise; a VTK reader error raises ``OSError``."""
    import warnings

    try:
        reader = pv.get_reader(str(path))
    except ValueError:  # no VTK reader for this suffix: let pyvista try its other readers (meshio)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return pv.read(path)
        except Exception:
            raise OSError(f"no reader for {path.suffix or 'suffix-less'} files") from None
    observer = pv.Observer(log=False)
    observer.observe(reader.reader)
    with pv.vtk_verbosity("off"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = reader.read()
    if observer.has_event_occurred():
        raise OSError(f"{reader.reader.GetClassName()} failed, damaged or not a {path.suffix} file")
    return data


def _triangles_of(surface) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) points and (F, 3) triangles of a pyvista PolyData's polygons (lines and points ignored)."""
    if surface.n_points == 0 or surface.n_cells == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    triangles = surface.triangulate()
    cells = np.asarray(triangles.faces, dtype=np.int64)
    if cells.size == 0:
        return np.asarray(triangles.points, dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    return np.asarray(triangles.points, dtype=np.float64), cells.reshape(-1, 4)[:, 1:]


def _orient_consistently(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces re-wound so that neighbours agree (VTK's consistency pass over each connected part)."""
    import pyvista as pv

    cells = np.hstack([np.full((len(faces), 1), 3, dtype=np.int64), faces]).ravel()
    polydata = pv.PolyData(points, cells)
    with pv.vtk_verbosity("off"):
        oriented = polydata.compute_normals(
            cell_normals=False,
            point_normals=True,
            split_vertices=False,
            consistent_normals=True,
            auto_orient_normals=False,
            non_manifold_traversal=True,
        )
    if oriented.n_points != len(points):
        return faces  # VTK changed the points; keep the file's winding
    result = np.asarray(oriented.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]
    return result if result.shape == faces.shape else faces


def _orient_outward(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Reverse every connected part whose signed volume is negative (it was wound inward).

    Each part's volume is summed about the mean of its vertices, which is exact for a closed part and
    a sensible apex for a part with small holes.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].ravel()
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(len(points), len(points)))
    part_count, labels = connected_components(graph, directed=False)
    face_part = labels[faces[:, 0]]
    counts = np.maximum(np.bincount(labels, minlength=part_count), 1)[:, None]
    part_centres = np.stack(
        [np.bincount(labels, weights=points[:, axis], minlength=part_count) for axis in range(3)], axis=1
    ) / counts
    corners = points[faces] - part_centres[face_part][:, None, :]
    triple = np.einsum("fk,fk->f", corners[:, 0], np.cross(corners[:, 1], corners[:, 2]))
    volume = np.bincount(face_part, weights=triple, minlength=part_count)
    flip = (volume < 0.0)[face_part]
    return np.where(flip[:, None], faces[:, ::-1], faces).astype(np.int32)


def make_shape(name_or_path: str, **kwargs) -> TriangleMesh:
    """A built-in shape by name (``SHAPE_NAMES``; "torus" is "donut"), or a mesh file by path.

    Args:
        name_or_path: Shape name (case-insensitive) or mesh file path.
        **kwargs: Keyword arguments of the shape's builder (:func:`torus`, :func:`teapot`, :func:`sphere`,
            :func:`coin`, :func:`bumpy_torus`); none for files.

    Returns:
        The mesh.

    Raises:
        InputError: Unknown name, or a mesh file that cannot be used.
    """
    builders = {"donut": torus, "torus": torus, "teapot": teapot, "sphere": sphere, "coin": coin,
                "bumpy": bumpy_torus}
    key = str(name_or_path).strip().lower()
    if key in builders:
        return builders[key](**kwargs)
    path = Path(str(name_or_path)).expanduser()
    if path.suffix or path.exists() or len(path.parts) > 1:
        if kwargs:
            raise InputError(
                f"options {sorted(kwargs)} do not apply to mesh file {path}: "
                "drop them or use a built-in shape"
            )
        return load_mesh(path)
    raise InputError(
        f"unknown shape {str(name_or_path)!r}: use {', '.join(SHAPE_NAMES)} or a path to a {_MESH_SUFFIXES} file"
    )
