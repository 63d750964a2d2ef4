"""Spherical Delaunay triangulation against brute force, on full spheres and domes."""

from __future__ import annotations

import numpy as np
import pytest

from warp_highlights.io.lightfile import read_lp
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import Location, SphericalTriangulation


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
    lights = read_lp(next((data_root / folder).glob("*.lp")))
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
    lights = read_lp(data_root / "synthrti-object1-material5" / "Dome" / "dirs.lp")
    tri = SphericalTriangulation(lights.directions)
    lowest = np.flatnonzero(np.isclose(lights.directions[:, 2], lights.directions[:, 2].min(), atol=1e-3))
    assert len(lowest) == 18
    np.testing.assert_array_equal(np.unique(tri.boundary_edges()), lowest)


# --- locate, directed_edges, from_faces ----------------------------------------------------------


def _crossings(tri: SphericalTriangulation, directions: np.ndarray) -> np.ndarray:
    """(Q, F) brute force: solve [A B C] mu = omega face by face; the ray crosses where every mu >= 0."""
    crossed = np.zeros((len(directions), tri.face_count), dtype=bool)
    for face, corners in enumerate(tri.directions[tri.faces]):
        mu = np.linalg.solve(corners.T, directions.T).T
        crossed[:, face] = mu.min(axis=1) >= -1e-9
    return crossed


def _check_reconstruction(tri: SphericalTriangulation, location: Location) -> None:
    """The barycentric weights are a convex combination whose point lies on the located ray."""
    assert isinstance(location, Location)
    weights = location.barycentric
    assert weights.dtype == np.float64 and location.faces.dtype == np.int32
    assert np.all(weights >= 0.0)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(location.vertices, tri.faces[location.faces])
    np.testing.assert_allclose(np.linalg.norm(location.directions, axis=1), 1.0, atol=1e-12)
    point = np.einsum("qk,qkj->qj", weights, tri.directions[location.vertices])
    assert np.abs(np.cross(point, location.directions)).max() < 1e-9
    assert np.all(np.einsum("ij,ij->i", point, location.directions) > 0.0)


@pytest.mark.parametrize("count", [12, 50, 250])
def test_locate_matches_brute_force_on_full_spheres(count):
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(count).directions)
    rng = np.random.default_rng(count)
    queries = rng.normal(size=(2000, 3)) * rng.uniform(0.01, 100.0, size=(2000, 1))  # not unit
    location = tri.locate(queries)
    assert location.faces.shape == (2000,) and location.barycentric.shape == (2000, 3)
    assert not location.clamped.any()
    np.testing.assert_allclose(location.directions, queries / np.linalg.norm(queries, axis=1, keepdims=True))
    _check_reconstruction(tri, location)
    crossed = _crossings(tri, location.directions)
    assert crossed.any(axis=1).all()
    assert crossed[np.arange(2000), location.faces].all()
    # Barycentric weights are the planar ones of the crossing point, against an independent solve.
    corners = tri.directions[location.vertices].transpose(0, 2, 1)
    mu = np.linalg.solve(corners, location.directions[:, :, None])[:, :, 0]
    np.testing.assert_allclose(location.barycentric, mu / mu.sum(axis=1, keepdims=True), atol=1e-9)


@pytest.mark.parametrize("lights", [LightSet.fibonacci_sphere(60), LightSet.fibonacci_dome(80)], ids=["sphere", "dome"])
def test_locate_at_vertices_and_centroids(lights):
    tri = SphericalTriangulation(lights.directions)
    at_vertices = tri.locate(tri.directions * 3.0)
    assert not at_vertices.clamped.any()
    hit = at_vertices.vertices == np.arange(tri.light_count)[:, None]
    assert np.all(hit.sum(axis=1) == 1)  # each light is a corner of its face
    np.testing.assert_allclose(at_vertices.barycentric[hit], 1.0, atol=1e-12)
    _check_reconstruction(tri, at_vertices)

    at_centroids = tri.locate(tri.centroid_directions())
    assert not at_centroids.clamped.any()
    np.testing.assert_array_equal(at_centroids.faces, np.arange(tri.face_count))
    np.testing.assert_allclose(at_centroids.barycentric, 1.0 / 3.0, atol=1e-9)

    # On a shared edge: one of its faces, deterministically, with weight 1/2 on each end and 0 opposite.
    edges = tri.edges()
    midpoints = tri.directions[edges].sum(axis=1)
    at_edges = tri.locate(midpoints)
    assert not at_edges.clamped.any()
    np.testing.assert_array_equal(tri.locate(midpoints).faces, at_edges.faces)
    on_edge = (at_edges.vertices == edges[:, :1]) | (at_edges.vertices == edges[:, 1:])
    assert np.all(on_edge.sum(axis=1) == 2)
    np.testing.assert_allclose(at_edges.barycentric[on_edge], 0.5, atol=1e-9)
    np.testing.assert_allclose(at_edges.barycentric[~on_edge], 0.0, atol=1e-12)


def test_locate_single_direction_and_extreme_lengths():
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(20).directions)
    single = tri.locate(np.array([0.3, -0.2, 0.9]))
    assert single.faces.shape == () and single.barycentric.shape == (3,) and single.vertices.shape == (3,)
    assert single.clamped.shape == () and single.directions.shape == (3,)
    batch = tri.locate([[0.3, -0.2, 0.9]])
    assert int(single.faces) == int(batch.faces[0])
    np.testing.assert_array_equal(single.barycentric, batch.barycentric[0])
    for scale in (1e-300, 1e300):
        scaled = tri.locate(np.array([0.3, -0.2, 0.9]) * scale)
        assert int(scaled.faces) == int(single.faces)
        np.testing.assert_allclose(scaled.barycentric, single.barycentric, atol=1e-12)
    assert tri.locate(np.zeros((0, 3))).faces.shape == (0,)


def _check_dome(tri: SphericalTriangulation, rng: np.random.Generator) -> None:
    assert tri.is_dome
    boundary = {tuple(edge) for edge in tri.boundary_edges().tolist()}
    lowest = np.arcsin(tri.directions[:, 2].min())

    # Inside: random points of random faces, pushed to the sphere.
    faces = rng.integers(tri.face_count, size=500)
    weights = rng.dirichlet(np.ones(3), size=500)
    inside = np.einsum("qk,qkj->qj", weights, tri.directions[tri.faces[faces]])
    location = tri.locate(inside)
    assert not location.clamped.any()
    np.testing.assert_array_equal(location.faces, faces)
    np.testing.assert_allclose(location.barycentric, weights, atol=1e-9)

    # Outside: straight down, a ring below the rim, and random directions.
    azimuth = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    elevation = max(lowest - np.radians(5.0), -np.pi / 2)
    ring = np.stack([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.zeros(72)], 1)
    ring[:, 2] = np.sin(elevation)
    outside = np.concatenate([[[0.0, 0.0, -1.0]], ring])
    queries = np.concatenate([outside, rng.normal(size=(300, 3))])
    location = tri.locate(queries)
    assert location.clamped[: len(outside)].all()
    # Clamped exactly where no face is crossed (brute force), away from the rim itself.
    unit = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    crossed = _crossings(tri, unit).any(axis=1)
    depth = np.einsum("ij,ij->i", location.directions, unit)
    clear = ~crossed | (depth > 0.999999999)
    np.testing.assert_array_equal(location.clamped[clear], ~crossed[clear])
    np.testing.assert_allclose(location.directions[~location.clamped], unit[~location.clamped], atol=1e-15)
    _check_reconstruction(tri, location)

    # A clamped direction lands on a boundary face, with the weight of the corner off the rim edge 0.
    clamped = np.flatnonzero(location.clamped)
    for corners, weights in zip(location.vertices[clamped].tolist(), location.barycentric[clamped]):
        rim_edges = [tuple(sorted(corners[:k] + corners[k + 1 :])) for k in np.flatnonzero(weights == 0.0)]
        assert any(edge in boundary for edge in rim_edges)

    # The projected direction is the nearest boundary point: dense sampling of every boundary arc.
    t = np.linspace(0.0, 1.0, 2000)[:, None]
    samples = []
    for start, end in tri.boundary_edges():
        a, b = tri.directions[start], tri.directions[end]
        angle = np.arccos(np.clip(a @ b, -1.0, 1.0))
        samples.append((np.sin((1.0 - t) * angle) * a + np.sin(t * angle) * b) / np.sin(angle))
    samples = np.concatenate(samples)
    nearest = np.arccos(np.clip(unit[clamped] @ samples.T, -1.0, 1.0)).min(axis=1)
    found = np.arccos(np.clip(np.einsum("ij,ij->i", unit[clamped], location.directions[clamped]), -1.0, 1.0))
    assert np.all(found <= nearest + 1e-9)  # never farther than a sampled boundary point
    np.testing.assert_allclose(found, nearest, atol=1e-3)
    on_rim = np.arccos(np.clip(location.directions[clamped] @ samples.T, -1.0, 1.0)).min(axis=1)
    assert on_rim.max() < 1e-3  # and it lies on the boundary


@pytest.mark.parametrize("min_elevation", [0.0, 10.0, 30.0])
def test_locate_on_fibonacci_domes_clamps_to_the_nearest_boundary_point(min_elevation):
    tri = SphericalTriangulation(LightSet.fibonacci_dome(80, min_elevation_deg=min_elevation).directions)
    _check_dome(tri, np.random.default_rng(int(min_elevation)))


@pytest.mark.realdata
@pytest.mark.parametrize("folder", ["synthrti-object1-material5/Dome", "realrti-item11"])
def test_locate_on_sample_domes_clamps_to_the_nearest_boundary_point(data_root, folder):
    lights = read_lp(next((data_root / folder).glob("*.lp")))
    _check_dome(SphericalTriangulation(lights.directions), np.random.default_rng(7))


@pytest.mark.parametrize("count", [12, 50])
def test_directed_edges_on_a_full_sphere(count):
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(count).directions)
    directed = tri.directed_edges()
    assert directed.dtype == np.int32 and len(directed) == 6 * count - 12
    assert len(np.unique(directed, axis=0)) == len(directed)
    pairs = {tuple(edge) for edge in directed.tolist()}
    assert all((b, a) in pairs for a, b in pairs)
    np.testing.assert_array_equal(np.unique(np.sort(directed, axis=1), axis=0), tri.edges())


def test_directed_edges_on_a_dome():
    tri = SphericalTriangulation(LightSet.fibonacci_dome(80).directions)
    directed = tri.directed_edges()
    assert len(directed) == 2 * len(tri.edges())
    pairs = {tuple(edge) for edge in directed.tolist()}
    assert all((b, a) in pairs for a, b in pairs)


@pytest.mark.parametrize("lights", [LightSet.fibonacci_sphere(40), LightSet.fibonacci_dome(60)], ids=["sphere", "dome"])
def test_from_faces_round_trip_and_corruption(lights):
    tri = SphericalTriangulation(lights.directions)
    again = SphericalTriangulation.from_faces(tri.directions, tri.faces)
    np.testing.assert_array_equal(again.faces, tri.faces)
    assert again.faces.dtype == np.int32 and again.is_dome == tri.is_dome
    queries = np.random.default_rng(3).normal(size=(200, 3))
    first, second = tri.locate(queries), again.locate(queries)
    np.testing.assert_array_equal(second.faces, first.faces)
    np.testing.assert_array_equal(second.clamped, first.clamped)
    np.testing.assert_allclose(second.barycentric, first.barycentric, atol=1e-12)

    out_of_range = tri.faces.copy()
    out_of_range[3, 1] = tri.light_count
    flipped = tri.faces.copy()
    flipped[5] = flipped[5, ::-1]
    duplicated = np.concatenate([tri.faces, tri.faces[:1]])
    for faces in (out_of_range, flipped, duplicated):
        with pytest.raises(InputError):
            SphericalTriangulation.from_faces(tri.directions, faces)
    zero_light = tri.directions.copy()
    zero_light[0] = 0.0
    with pytest.raises(InputError):
        SphericalTriangulation.from_faces(zero_light, tri.faces)


@pytest.mark.parametrize(
    "bad",
    [
        [0.0, 0.0, 0.0],
        [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]],
        [[np.nan, 0.0, 1.0]],
        [[np.inf, 0.0, 1.0]],
        [1.0, 0.0],
        [[1.0, 0.0, 0.0, 0.0]],
        np.ones((2, 3, 1)),
        [["a", "b", "c"]],
    ],
)
def test_locate_bad_input_is_an_input_error(bad):
    tri = SphericalTriangulation(LightSet.fibonacci_sphere(12).directions)
    with pytest.raises(InputError) as error:
        tri.locate(bad)
    assert "\n" not in str(error.value)


def test_zero_light_direction_is_an_input_error():
    directions = LightSet.fibonacci_sphere(12).directions.copy()
    directions[4] = np.nan
    with pytest.raises(InputError):
        SphericalTriangulation(directions)


def test_locating_inside_the_faces_builds_no_rim_tables_and_a_dome_s_outside_query_does():
    """``locate`` needs the rim's tables (a sort of every edge) only for a query outside a dome; the
    weights are the same whichever tables were built first."""
    sphere = SphericalTriangulation(LightSet.fibonacci_sphere(40).directions)
    inside = sphere.locate(np.array([0.3, -0.2, 0.9]))
    assert "_locate_tables" not in sphere.__dict__ and "_face_tables" in sphere.__dict__
    again = SphericalTriangulation(LightSet.fibonacci_sphere(40).directions)
    again._locate_tables  # noqa: B018 (both tables first)
    np.testing.assert_array_equal(again.locate(np.array([0.3, -0.2, 0.9])).barycentric, inside.barycentric)
    dome = SphericalTriangulation(LightSet.fibonacci_dome(30, min_elevation_deg=20.0).directions)
    dome.locate(np.array([0.1, 0.2, 0.95]))
    assert "_locate_tables" not in dome.__dict__
    below = dome.locate(np.array([1.0, 0.0, -0.5]))
    assert bool(below.clamped) and "_locate_tables" in dome.__dict__
