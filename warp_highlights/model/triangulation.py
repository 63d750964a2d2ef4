"""Spherical Delaunay triangulation of light directions (docs/method.md, Fitting step 3).

The spherical Delaunay triangulation of points on the unit sphere is their convex hull. For a full
sphere every hull face is kept. For a dome (all lights on one side, as in RTI captures) the hull also
has faces that close the open side; they are removed, leaving an open mesh with a boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .errors import InputError

__all__ = ["Location", "SphericalTriangulation", "unit_query_directions"]

# A face whose plane passes this close to the origin (or beyond it) has an empty circumcap of at least
# a hemisphere: no lights there, so it closes the open side of a dome rather than covering lights.
_PLANE_OFFSET_TOLERANCE = 1e-9
# A direction at most this far outside a face (sine of the angle to the face's edge plane, ~radians)
# still counts as inside: it absorbs rounding on shared edges, vertices and the boundary of a dome.
_INSIDE_TOLERANCE = 1e-12
# locate() works on blocks of queries x faces of about this many entries, to bound its memory.
_BLOCK_ENTRIES = 1 << 20
# Lights whose spread out of their best-fitting plane (RMS) is below this fraction of their spread within
# it (RMS) lie on one circle of the sphere: a .lp file's ~6 decimals put a single ring ~1e-6 off its plane,
# while two rings even one degree of elevation apart are ~1e-2 off it.
_FLATNESS = 1e-3


@dataclass(frozen=True, eq=False)
class Location:
    """Where directions fall on a triangulation: one face and barycentric weights per direction.

    Arrays have a leading query axis (Q,), absent when a single (3,) direction was located.

    Attributes:
        faces: (Q,) int32 face index into ``SphericalTriangulation.faces``.
        vertices: (Q, 3) int32 light indices of those faces, ``triangulation.faces[faces]``.
        barycentric: (Q, 3) float64 planar barycentric weights in the order of ``vertices``:
            non-negative, summing to 1.
        clamped: (Q,) bool, True where the direction lay outside a dome and was projected onto its rim.
        directions: (Q, 3) float64 unit directions actually located (the projected ones where clamped).
    """

    faces: np.ndarray
    vertices: np.ndarray
    barycentric: np.ndarray
    clamped: np.ndarray
    directions: np.ndarray


class _FaceTables(NamedTuple):
    """The per-face constants of ``SphericalTriangulation.locate`` (as in ``_LocateTables``)."""

    edge_normals: np.ndarray
    inverses: np.ndarray


class _LocateTables(NamedTuple):
    """Per-face and per-rim-edge constants of ``SphericalTriangulation.locate``."""

    edge_normals: np.ndarray  # (3, F, 3) unit normals of the planes (origin, edge); inside is positive
    inverses: np.ndarray  # (F, 3, 3) inverse of the matrix whose columns are the face's vertices
    rim_start: np.ndarray  # (K, 3) unit start vertex of each boundary edge
    rim_end: np.ndarray  # (K, 3) unit end vertex
    rim_normal: np.ndarray  # (K, 3) unit normal of the edge's great circle, start x end
    rim_face: np.ndarray  # (K,) the face owning the edge
    rim_corner: np.ndarray  # (K, 2) positions (0..2) of start and end within that face


class SphericalTriangulation:
    """Triangles over the light directions, wound counter-clockwise seen from outside the sphere.

    Args:
        directions: (n, 3) unit light directions.

    Attributes:
        directions: (n, 3) float64 unit vectors.
        faces: (F, 3) int32 vertex indices; the right-hand normal of every face points outwards.
        is_dome: True when the lights cover only part of the sphere and the mesh has a boundary.
    """

    def __init__(self, directions: np.ndarray):
        self.directions = _light_directions(directions)
        _check_spread(self.directions)
        try:
            hull = ConvexHull(self.directions)
        except QhullError:  # its message is pages of Qhull internals: say what it means instead
            raise InputError(
                f"the {self.light_count} lights cannot be triangulated: they lie too close to one circle of the "
                "sphere or to each other; RTI needs lights spread over several elevations"
            ) from None
        faces = _wind_outwards(self.directions, hull.simplices)
        faces, self.is_dome = _drop_closing_faces(self.directions, faces)
        self.faces = faces.astype(np.int32)

    @classmethod
    def from_faces(cls, directions: np.ndarray, faces: np.ndarray) -> SphericalTriangulation:
        """Rebuild a stored triangulation without re-running the hull (the faces are checked, not recomputed).

        Raises ``InputError`` when a face index is out of range, a face is degenerate or wound
        inwards, or a directed edge is used twice (inconsistent winding).
        """
        directions = _light_directions(directions)
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1 or not np.issubdtype(faces.dtype, np.integer):
            raise InputError(f"faces must be a non-empty (F, 3) integer array, got {faces.dtype} {faces.shape}")
        if faces.min() < 0 or faces.max() >= len(directions):
            raise InputError(f"face indices must lie in 0..{len(directions) - 1}")
        tri = cls.__new__(cls)
        tri.directions = directions
        tri.faces = faces.astype(np.int32)
        a, b, c = (tri.directions[tri.faces[:, k]] for k in range(3))
        if np.any(np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) <= 0):
            raise InputError("a face is degenerate or wound inwards")
        directed = tri._directed_face_edges()
        if len(np.unique(directed, axis=0)) != len(directed):
            raise InputError("the faces are not wound consistently (a directed edge is used twice)")
        tri.is_dome = len(tri.boundary_edges()) > 0
        return tri

    @property
    def light_count(self) -> int:
        return len(self.directions)

    @property
    def face_count(self) -> int:
        return len(self.faces)

    def face_normals(self) -> np.ndarray:
        """(F, 3) outward unit normals of the planar faces."""
        a, b, c = (self.directions[self.faces[:, k]] for k in range(3))
        normals = np.cross(b - a, c - a)
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)

    def edges(self) -> np.ndarray:
        """(E, 2) int32 undirected edges, each once, smaller index first, sorted."""
        return np.unique(self._face_edges(), axis=0).astype(np.int32)

    def boundary_edges(self) -> np.ndarray:
        """(K, 2) int32 edges used by only one face (empty on a full sphere), smaller index first."""
        unique, counts = np.unique(self._face_edges(), axis=0, return_counts=True)
        return unique[counts == 1].astype(np.int32)

    def directed_edges(self) -> np.ndarray:
        """(2E, 2) int32 (source, target) pairs: every edge in both directions, sorted.

        These are the retargeting problems: 6n - 12 on a full sphere of n lights.
        """
        edges = self.edges()
        return np.unique(np.concatenate([edges, edges[:, ::-1]]), axis=0).astype(np.int32)

    def _directed_face_edges(self) -> np.ndarray:
        """(3F, 2) the three edges of every face in winding order."""
        return np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])

    def _face_edges(self) -> np.ndarray:
        """(3F, 2) the three edges of every face, smaller index first (shared edges appear twice)."""
        return np.sort(self._directed_face_edges(), axis=1)

    def centroid_directions(self) -> np.ndarray:
        """(F, 3) unit directions through the face centroids: normalize(wA + wB + wC) (the thesis' held-out queries)."""
        total = self.directions[self.faces].sum(axis=1)
        return total / np.linalg.norm(total, axis=1, keepdims=True)

    def locate(self, directions: np.ndarray) -> Location:
        """Find the face each direction falls in, and its planar barycentric weights (docs/method.md, Fitting step 3).

        The face is the one whose planar triangle the ray from the origin along the direction crosses;
        the weights are those of the crossing point. A direction on a shared edge or vertex gets one of
        its faces, chosen deterministically (the one it lies deepest inside). On a dome, a direction
        outside the covered region is first moved to the nearest point (in angle) of the boundary and
        flagged ``clamped``.

        Args:
            directions: (Q, 3) or (3,) directions towards the light, of any non-zero length.

        Returns:
            A ``Location``; its arrays have no query axis when a single (3,) direction was given.

        Raises:
            InputError: The shape is not (3,) or (Q, 3), or a direction is zero or not finite.
        """
        queries = unit_query_directions(directions)
        tables = self._face_tables  # the rim's tables only where a query lies outside a dome
        count = len(queries)
        faces = np.empty(count, dtype=np.intp)
        depth = np.empty(count, dtype=np.float64)  # sine of the angle inside the face's nearest edge
        block = max(1, _BLOCK_ENTRIES // self.face_count)
        for start in range(0, count, block):
            part = queries[start : start + block]
            margin = part @ tables.edge_normals[0].T
            np.minimum(margin, part @ tables.edge_normals[1].T, out=margin)
            np.minimum(margin, part @ tables.edge_normals[2].T, out=margin)
            best = margin.argmax(axis=1)
            faces[start : start + block] = best
            depth[start : start + block] = margin[np.arange(len(part)), best]

        located = queries.copy()
        clamped = np.zeros(count, dtype=bool)
        if self.is_dome:
            clamped = depth < -_INSIDE_TOLERANCE
        weights = np.einsum("qij,qj->qi", tables.inverses[faces], located)
        if clamped.any():
            outside = np.flatnonzero(clamped)
            tables = self._locate_tables
            edges, located[outside] = _nearest_rim_points(queries[outside], tables)
            faces[outside] = tables.rim_face[edges]
            weights[outside] = np.einsum("qij,qj->qi", tables.inverses[faces[outside]], located[outside])
            # The projected direction lies in the plane of the rim edge: its opposite corner weighs 0.
            weights[outside, 3 - tables.rim_corner[edges].sum(axis=1)] = 0.0
        np.maximum(weights, 0.0, out=weights)
        weights /= weights.sum(axis=1, keepdims=True)

        faces = faces.astype(np.int32)
        arrays = (faces, self.faces[faces], weights, clamped, located)
        if np.ndim(directions) == 1:
            arrays = tuple(array[0] for array in arrays)
        return Location(*(np.asarray(array) for array in arrays))

    @cached_property
    def _face_tables(self) -> _FaceTables:
        """``_LocateTables``' ``edge_normals`` and ``inverses``, computed on first use: all that
        ``locate`` needs unless a query lies outside a dome (a leave-one-out check builds dozens of
        triangulations to locate one light in each)."""
        corners = self.directions[self.faces]  # (F, 3 vertices, 3 coordinates)
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        edge_normals = np.stack([np.cross(a, b), np.cross(b, c), np.cross(c, a)])
        edge_normals /= np.linalg.norm(edge_normals, axis=2, keepdims=True)
        inverses = np.linalg.inv(corners.transpose(0, 2, 1))  # columns are the vertices
        return _FaceTables(edge_normals, inverses)

    @cached_property
    def _locate_tables(self) -> _LocateTables:
        """Constants of ``locate`` (the faces' and the rim's), computed on first use."""
        edge_normals, inverses = self._face_tables

        directed = self._directed_face_edges()  # face f's k-th edge is row k * F + f
        owner = np.arange(len(directed)) % self.face_count
        start_corner = np.arange(len(directed)) // self.face_count
        _, inverse, counts = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
        rim = np.flatnonzero(counts[inverse.ravel()] == 1)
        rim_start = self.directions[directed[rim, 0]]
        rim_end = self.directions[directed[rim, 1]]
        rim_normal = np.cross(rim_start, rim_end)
        rim_normal /= np.linalg.norm(rim_normal, axis=1, keepdims=True)
        return _LocateTables(
            edge_normals=edge_normals,
            inverses=inverses,
            rim_start=rim_start,
            rim_end=rim_end,
            rim_normal=rim_normal,
            rim_face=owner[rim],
            rim_corner=np.stack([start_corner[rim], (start_corner[rim] + 1) % 3], axis=1),
        )


def _light_directions(directions: np.ndarray) -> np.ndarray:
    """Check (n >= 3, 3) light directions and return them as float64 unit vectors."""
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3 or len(directions) < 3:
        raise InputError(f"a triangulation needs at least 3 light directions of shape (n, 3), got {directions.shape}")
    norms = np.linalg.norm(directions, axis=1)
    bad = np.flatnonzero(~(np.isfinite(norms) & (norms > 0.0)))
    if bad.size:
        raise InputError(f"light direction {bad[0]} is zero or not finite: {directions[bad[0]].tolist()}")
    return directions / norms[:, None]


def _check_spread(directions: np.ndarray) -> None:
    """Refuse lights whose convex hull has no volume: fewer than 4, or all on one plane (one circle)."""
    count = len(directions)
    if count < 4:
        raise InputError(
            f"{count} lights cannot be triangulated: the light sphere needs at least 4, not all on one circle; "
            "RTI needs lights at several elevations"
        )
    spread = np.linalg.svd(directions - directions.mean(axis=0), compute_uv=False)  # RMS extent per axis, x sqrt(n)
    if spread[2] <= _FLATNESS * spread[0]:
        raise InputError(
            f"the {count} lights lie on one circle of the sphere (one ring at a single elevation, or one great "
            "circle): the light sphere cannot be triangulated; RTI needs lights at several elevations"
        )


def unit_query_directions(directions: np.ndarray) -> np.ndarray:
    """Check (Q, 3) or (3,) query directions of any non-zero length; return them as (Q, 3) unit vectors."""
    try:
        queries = np.array(directions, dtype=np.float64, ndmin=2)
    except (TypeError, ValueError):
        raise InputError("query directions must be numbers of shape (3,) or (Q, 3)") from None
    if queries.ndim != 2 or queries.shape[1] != 3 or np.ndim(directions) not in (1, 2):
        raise InputError(f"query directions must have shape (3,) or (Q, 3), got {np.shape(directions)}")
    # Divide by the largest component first, so that huge or tiny vectors neither overflow nor underflow.
    scale = np.abs(queries).max(axis=1, initial=0.0)
    bad = np.flatnonzero(~(np.isfinite(scale) & (scale > 0.0)))
    if bad.size:
        raise InputError(f"query direction {bad[0]} is zero or not finite: {queries[bad[0]].tolist()}")
    queries /= scale[:, None]
    return queries / np.linalg.norm(queries, axis=1, keepdims=True)


def _nearest_rim_points(queries: np.ndarray, tables: _LocateTables) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point, in angle, of a dome's boundary to each unit direction outside it.

    The boundary is the union of the great-circle arcs of the boundary edges, endpoints included.

    Returns:
        (Q,) index of the boundary edge holding the point, and the (Q, 3) unit points.
    """
    # Unit vectors in the edge's plane, at its start pointing along the arc and at its end pointing back:
    # a direction projects inside the arc exactly when it has a non-negative component along both.
    along = np.cross(tables.rim_normal, tables.rim_start)
    back = np.cross(tables.rim_end, tables.rim_normal)
    edges = np.empty(len(queries), dtype=np.intp)
    points = np.empty_like(queries)
    block = max(1, _BLOCK_ENTRIES // len(tables.rim_face))
    for start in range(0, len(queries), block):
        part = queries[start : start + block]
        rows = np.arange(len(part))
        off_plane = part @ tables.rim_normal.T  # sine of the angle to each edge's great circle
        foot = np.sqrt(np.maximum(1.0 - off_plane**2, 0.0))  # cosine of that angle
        to_start = part @ tables.rim_start.T
        to_end = part @ tables.rim_end.T
        over_arc = (part @ along.T >= 0.0) & (part @ back.T >= 0.0) & (foot > 1e-12)
        closeness = np.where(over_arc, foot, np.maximum(to_start, to_end))  # cosine of the angle to the arc
        best = closeness.argmax(axis=1)
        inner = part - off_plane[rows, best][:, None] * tables.rim_normal[best]
        inner /= np.maximum(np.linalg.norm(inner, axis=1, keepdims=True), 1e-300)
        corner = np.where((to_start >= to_end)[rows, best][:, None], tables.rim_start[best], tables.rim_end[best])
        edges[start : start + block] = best
        points[start : start + block] = np.where(over_arc[rows, best][:, None], inner, corner)
    return edges, points


def _wind_outwards(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Flip the hull triangles whose right-hand normal points towards the hull's interior."""
    faces = np.array(simplices, dtype=np.int64)
    a, b, c = (points[faces[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    interior = points.mean(axis=0)
    inward = np.einsum("ij,ij->i", normals, a - interior) < 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces


def _drop_closing_faces(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, bool]:
    """Remove the faces that close the open side of a dome; report whether there were any.

    A hull face whose plane does not pass strictly between the origin and the face has an empty
    circumcap of a hemisphere or more, so no lights lie on that side: it spans the uncovered region.
    """
    a, b, c = (points[faces[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    plane_offset = np.einsum("ij,ij->i", normals, a)
    closing = plane_offset <= _PLANE_OFFSET_TOLERANCE
    mean_direction = points.mean(axis=0)
    if np.linalg.norm(mean_direction) > 0.25:
        # A dome whose rim dips below its great circle: the closing faces then sit just past the origin
        # but still face away from the lights.
        closing |= normals @ (mean_direction / np.linalg.norm(mean_direction)) < -0.5
    if closing.all():
        raise InputError("the light directions cover no area of the sphere: check the light file")
    return faces[~closing], bool(closing.any())
