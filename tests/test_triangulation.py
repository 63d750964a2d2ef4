"""Spherical Delaunay triangulation against brute force, on full spheres and domes."""

from __future__ import annotations

import numpy as np
import pytest

from warp_highlights.errors import InputError
from warp_highlights.lights import LightSet
from warp_highlights.triangulation import SphericalTriangulation


def _circumcaps_are_empty(tri: SphericalTriangulation) -> bool:
    """Delaunay on the sphere: no light lies strictly beyond the plane of any face (brute force)."""
    normals = tri.face_normals()
    offsets = np.einsum("ij,ij->i", normals, tri.directions[tri.faces[:, 0]])
    beyond = tri.directions @ normals.T - offsets[None, :]
    return bool(beyond.max() < 1e-9)


@pytest.mark.parametrize("count", [12, 50, 250])
def test_full_sphere_counts_winding_and_delaunay(count):
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(count).directions)
    assert not tri.is_dome
    assert tri.face_count == 2 * count - 4
    assert len(tri.edges()) == 3 * count - 6
    assert len(tri.boundary_edges()) == 0
    centres = tri.directions[tri.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", tri.face_normals(), centres) > 0)  # outward
    assert _circumcaps_are_empty(tri)
    # Every directed edge appears exactly once: consistent winding of a closed surface.
    directed = np.concatenate([tri.faces[:, [0, 1]], tri.faces[:, [1, 2]], tri.faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)


def test_centroid_directions_are_unit_and_inside_their_faces():
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(40).directions)
    centroids = tri.centroid_directions()
    np.testing.assert_allclose(np.linalg.norm(centroids, axis=1), 1.0)
    a, b, c = (tri.directions[tri.faces[:, k]] for k in range(3))
    for u, v in ((a, b), (b, c), (c, a)):
        assert np.all(np.einsum("ij,ij->i", np.cross(u, v), centroids) > 0)


@pytest.mark.parametrize("min_elevation", [0.0, 10.0, 30.0])
def test_dome_has_a_boundary_and_no_closing_faces(min_elevation):
    lights = LightSet.fibonacci_dome(80, min_elevation_deg=min_elevation)
    tri = SphericalTriangulation(lights.directions)
    assert tri.is_dome
    boundary = tri.boundary_edges()
    assert len(boundary) > 0
    # Euler for a disc: V - E + F = 1; and every light is used.
    assert tri.light_count - len(tri.edges()) + tri.face_count == 1
    assert len(np.unique(tri.faces)) == tri.light_count
    assert np.all(tri.face_normals()[:, 2] > -0.2)
    assert _circumcaps_are_empty(tri)


@pytest.mark.realdata
@pytest.mark.parametrize("folder", ["synthrti-object1-material5/Dome", "realrti-item11"])
def test_sample_domes_triangulate_with_a_boundary(data_root, folder):
    lights = LightSet.read_lp(next((data_root / folder).glob("*.lp")))
    tri = SphericalTriangulation(lights.directions)
    assert tri.is_dome and len(tri.boundary_edges()) > 0
    assert tri.light_count - len(tri.edges()) + tri.face_count == 1


def test_degenerate_input_is_an_input_error():
    with pytest.raises(InputError):
        SphericalTriangulation(np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    ring = np.stack([np.cos(np.linspace(0, 6, 10)), np.sin(np.linspace(0, 6, 10)), np.zeros(10)], 1)
    with pytest.raises(InputError):
        SphericalTriangulation(ring)


@pytest.mark.realdata
def test_synthrti_dome_boundary_is_its_lowest_ring(data_root):
    lights = LightSet.read_lp(data_root / "synthrti-object1-material5" / "Dome" / "dirs.lp")
    tri = SphericalTriangulation(lights.directions)
    lowest = np.flatnonzero(np.isclose(lights.directions[:, 2], lights.directions[:, 2].min(), atol=1e-3))
    assert len(lowest) == 18
    np.testing.assert_array_equal(np.unique(tri.boundary_edges()), lowest)
