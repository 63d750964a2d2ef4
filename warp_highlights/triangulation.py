"""Spherical Delaunay triangulation of light directions (method.md section 4).

The spherical Delaunay triangulation of points on the unit sphere is their convex hull. For a full
sphere every hull face is kept. For a dome (all lights on one side, as in RTI captures) the hull also
has faces that close the open side; they are removed, leaving an open mesh with a boundary.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .errors import InputError

__all__ = ["SphericalTriangulation"]

# A face whose plane passes this close to the origin (or beyond it) has an empty circumcap of at least
# a hemisphere: no lights there, so it closes the open side of a dome rather than covering lights.
_PLANE_OFFSET_TOLERANCE = 1e-9


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
        directions = np.asarray(directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3 or len(directions) < 3:
            raise InputError(f"a triangulation needs at least 3 light directions of shape (n, 3), got {directions.shape}")
        self.directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        try:
            hull = ConvexHull(self.directions)
        except QhullError as error:
            first_line = str(error).strip().splitlines()[0] if str(error).strip() else "degenerate input"
            raise InputError(
                f"cannot triangulate the light directions (all on one great circle or too few?): {first_line}"
            ) from None
        faces = _wind_outwards(self.directions, hull.simplices)
        faces, self.is_dome = _drop_closing_faces(self.directions, faces)
        self.faces = faces.astype(np.int32)

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

    def _face_edges(self) -> np.ndarray:
        """(3F, 2) the three edges of every face, smaller index first (shared edges appear twice)."""
        pairs = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        return np.sort(pairs, axis=1)

    def centroid_directions(self) -> np.ndarray:
        """(F, 3) unit directions through the face centroids: normalize(wA + wB + wC) (the thesis' held-out queries)."""
        total = self.directions[self.faces].sum(axis=1)
        return total / np.linalg.norm(total, axis=1, keepdims=True)


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
