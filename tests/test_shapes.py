"""Tests of the synthetic shapes and mesh loading (warp_highlights.synth.shapes); NumPy and pyvista only."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from warp_highlights.model.errors import InputError
from warp_highlights.synth.shapes import (
    SHAPE_NAMES,
    TriangleMesh,
    load_mesh,
    make_shape,
    signed_volume,
    sphere,
    teapot,
    torus,
    vertex_normals,
    weld_vertices,
)


def _edge_counts(faces: np.ndarray) -> np.ndarray:
    """How many faces share each undirected edge."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)[1]


def _has_repeated_directed_edge(faces: np.ndarray) -> bool:
    """True when two faces traverse an edge the same way (inconsistent winding)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return bool((np.unique(directed, axis=0, return_counts=True)[1] > 1).any())


def _face_normals(mesh: TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals and face areas."""
    corners = mesh.points[mesh.faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    doubled = np.linalg.norm(cross, axis=1)
    return cross / doubled[:, None], 0.5 * doubled


def _assert_well_formed(mesh: TriangleMesh) -> None:
    assert mesh.points.dtype == np.float64 and mesh.points.shape[1] == 3
    assert mesh.faces.dtype == np.int32 and mesh.faces.shape[1] == 3
    assert mesh.normals.shape == mesh.points.shape
    assert np.isfinite(mesh.points).all() and np.isfinite(mesh.normals).all()
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-12)
    assert mesh.faces.min() >= 0 and mesh.faces.max() < mesh.vertex_count
    assert mesh.vertex_count == len(mesh.points) and mesh.face_count == len(mesh.faces)


# --- torus -----------------------------------------------------------------------------------------


def test_torus_is_closed_outward_with_the_right_volume():
    major, minor = 1.0, 0.4
    mesh = torus(major_radius=major, minor_radius=minor, major_segments=192, minor_segments=96)
    _assert_well_formed(mesh)
    assert mesh.name == "donut"
    assert (_edge_counts(mesh.faces) == 2).all()
    assert not _has_repeated_directed_edge(mesh.faces)
    volume = signed_volume(mesh.points, mesh.faces)
    assert volume > 0.0
    assert volume == pytest.approx(2.0 * np.pi**2 * major * minor**2, rel=0.01)


def test_torus_lies_in_xz_plane_with_analytic_normals():
    major, minor = 1.5, 0.3
    mesh = torus(major_radius=major, minor_radius=minor, major_segments=64, minor_segments=32)
    np.testing.assert_allclose(mesh.points[:, 1].max(), minor, rtol=1e-12)
    np.testing.assert_allclose(mesh.points[:, [0, 2]].max(), major + minor, rtol=1e-12)
    ring = mesh.points * np.array([1.0, 0.0, 1.0])
    centre = major * ring / np.linalg.norm(ring, axis=1, keepdims=True)
    analytic = (mesh.points - centre) / minor
    np.testing.assert_allclose(np.linalg.norm(mesh.points - centre, axis=1), minor, rtol=1e-12)
    cosine = np.einsum("ij,ij->i", mesh.normals, analytic)
    assert np.degrees(np.arccos(np.clip(cosine.min(), -1.0, 1.0))) < 0.5
    face_normals, _ = _face_normals(mesh)
    assert (np.einsum("fij,fj->fi", mesh.normals[mesh.faces], face_normals) > 0.9).all()


def test_torus_rejects_impossible_radii():
    with pytest.raises(InputError, match="minor_radius < major_radius"):
        torus(major_radius=1.0, minor_radius=1.2)


# --- sphere ----------------------------------------------------------------------------------------


def test_sphere_is_an_outward_icosphere():
    radius = 2.0
    mesh = sphere(radius=radius, subdivisions=5)
    _assert_well_formed(mesh)
    assert mesh.vertex_count == 10 * 4**5 + 2 and mesh.face_count == 20 * 4**5
    np.testing.assert_allclose(np.linalg.norm(mesh.points, axis=1), radius, rtol=1e-12)
    np.testing.assert_allclose(mesh.normals, mesh.points / radius, atol=1e-12)
    assert (_edge_counts(mesh.faces) == 2).all()
    assert not _has_repeated_directed_edge(mesh.faces)
    assert signed_volume(mesh.points, mesh.faces) == pytest.approx(4.0 / 3.0 * np.pi * radius**3, rel=0.005)


def test_sphere_subdivision_zero_is_the_icosahedron():
    mesh = sphere(subdivisions=0)
    assert (mesh.vertex_count, mesh.face_count) == (12, 20)
    assert signed_volume(mesh.points, mesh.faces) > 0.0


# --- teapot ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pot() -> TriangleMesh:
    return teapot(subdivisions=12)


def test_teapot_is_finite_without_degenerate_faces(pot):
    _assert_well_formed(pot)
    assert pot.name == "teapot"
    faces = pot.faces
    assert ((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])).all()
    _, areas = _face_normals(pot)
    assert areas.min() > 1e-8
    assert pot.face_count > 0.95 * 32 * 2 * 12**2


def test_teapot_is_welded_and_consistently_wound(pot):
    assert len(cKDTree(pot.points).query_pairs(r=1e-4)) == 0
    counts = _edge_counts(pot.faces)
    assert counts.max() == 2
    # open edges only where Newell's surface is open: rim/lid gap, spout ends, handle ends
    assert (counts == 1).sum() < 0.03 * len(counts)
    assert not _has_repeated_directed_edge(pot.faces)


def test_teapot_is_outward_and_normals_agree_with_faces(pot):
    assert signed_volume(pot.points, pot.faces) > 0.0
    face_normals, _ = _face_normals(pot)
    agreement = np.einsum("fij,fj->fi", pot.normals[pot.faces], face_normals)
    assert (agreement > 0.0).mean() > 0.999
    np.testing.assert_allclose(vertex_normals(pot.points, pot.faces), pot.normals, atol=1e-12)


def test_teapot_is_y_up_with_the_spout_along_plus_x(pot):
    lower, upper = pot.points.min(axis=0), pot.points.max(axis=0)
    np.testing.assert_allclose(upper - lower, [6.434, 3.15, 4.0], atol=0.01)
    np.testing.assert_allclose([lower[1], upper[1]], [0.0, 3.15], atol=1e-9)
    np.testing.assert_allclose([lower[0], lower[2], upper[2]], [-3.0, -2.0, 2.0], atol=1e-9)
    assert upper[0] > 3.4  # spout tip
    top = np.argmax(pot.points[:, 1])
    bottom = np.argmin(np.linalg.norm(pot.points, axis=1))
    np.testing.assert_allclose(pot.normals[top], [0.0, 1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(pot.normals[bottom], [0.0, -1.0, 0.0], atol=1e-9)
    # left-right symmetric about the x-y plane
    mirrored = pot.points * np.array([1.0, 1.0, -1.0])
    distance, _ = cKDTree(pot.points).query(mirrored)
    assert distance.max() < 1e-9


def test_teapot_subdivisions_scale_the_tessellation():
    coarse = teapot(subdivisions=4)
    assert coarse.face_count < teapot(subdivisions=8).face_count
    assert signed_volume(coarse.points, coarse.faces) > 0.0
    with pytest.raises(InputError):
        teapot(subdivisions=0)


# --- helper functions ------------------------------------------------------------------------------


def test_weld_vertices_merges_duplicates_and_drops_collapsed_faces():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1e-9], [5, 5, 5]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5], [1, 3, 4]])
    welded_points, welded_faces = weld_vertices(points, faces, 1e-6)
    assert welded_faces.dtype == np.int32
    assert len(welded_points) == 4  # duplicates merged, the unreferenced point dropped
    assert len(welded_faces) == 2  # [1, 3, 4] collapsed to an edge
    assert len(np.unique(welded_faces)) == 4
    np.testing.assert_allclose(welded_points[welded_faces[0]], points[[0, 1, 2]], atol=1e-9)


def test_vertex_normals_are_area_weighted_and_never_nan():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [9, 9, 9]], float)
    faces = np.array([[0, 1, 2], [0, 3, 1]])  # normals +z and +y; vertex 4 unreferenced
    normals = vertex_normals(points, faces)
    assert np.isfinite(normals).all()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    np.testing.assert_allclose(normals[2], [0, 0, 1])
    np.testing.assert_allclose(normals[0], np.array([0, 1, 1]) / np.sqrt(2.0))
    cancelled = vertex_normals(points[:3], np.array([[0, 1, 2], [0, 2, 1]]))  # two-sided sheet
    assert np.isfinite(cancelled).all()
    np.testing.assert_allclose(np.linalg.norm(cancelled, axis=1), 1.0)


def test_shapes_module_does_not_import_pyvista():
    import subprocess
    import sys

    code = "import sys, warp_highlights.synth.shapes as s; s.teapot(subdivisions=2); print('pyvista' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_transformed_and_normalized():
    mesh = sphere(subdivisions=2)
    angle = 0.7
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = mesh.transformed(rotation=rotation, scale=3.0, translation=[1.0, 2.0, 3.0])
    np.testing.assert_allclose(moved.points, 3.0 * mesh.points @ rotation.T + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(moved.normals, mesh.normals @ rotation.T)
    centre, radius = moved.bounding_sphere()
    np.testing.assert_allclose(centre, [1.0, 2.0, 3.0], atol=1e-9)
    assert radius == pytest.approx(3.0, abs=1e-9)
    unit = moved.normalized()
    centre, radius = unit.bounding_sphere()
    np.testing.assert_allclose(centre, 0.0, atol=1e-12)
    assert radius == pytest.approx(1.0)
    mirrored = mesh.transformed(rotation=np.diag([1.0, 1.0, -1.0]))
    assert signed_volume(mirrored.points, mirrored.faces) > 0.0
    with pytest.raises(ValueError):
        mesh.transformed(rotation=np.ones((3, 3)))


def test_triangle_mesh_checks_shapes():
    with pytest.raises(ValueError):
        TriangleMesh(np.zeros((3, 3)), np.array([[0, 1, 3]]), np.zeros((3, 3)), "bad")
    with pytest.raises(ValueError):
        TriangleMesh(np.zeros((3, 2)), np.array([[0, 1, 2]]), np.zeros((3, 2)), "bad")


# --- files and names -------------------------------------------------------------------------------


def _save(mesh: TriangleMesh, path, *, inverted: bool = False) -> None:
    import pyvista as pv

    faces = mesh.faces[:, ::-1] if inverted else mesh.faces
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    pv.PolyData(mesh.points, cells).save(str(path))


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
@pytest.mark.parametrize("inverted", [False, True])
def test_load_mesh_round_trip_comes_back_outward(tmp_path, suffix, inverted):
    original = sphere(radius=1.5, subdivisions=3)
    path = tmp_path / f"ball{suffix}"
    _save(original, path, inverted=inverted)
    loaded = load_mesh(path)
    _assert_well_formed(loaded)
    assert loaded.name == "ball"
    assert (loaded.vertex_count, loaded.face_count) == (original.vertex_count, original.face_count)
    distance, _ = cKDTree(original.points).query(loaded.points)
    assert distance.max() < 1e-5  # STL stores float32
    assert (_edge_counts(loaded.faces) == 2).all()
    assert not _has_repeated_directed_edge(loaded.faces)
    assert signed_volume(loaded.points, loaded.faces) == pytest.approx(
        signed_volume(original.points, original.faces), rel=1e-5
    )
    radial = loaded.points / np.linalg.norm(loaded.points, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", loaded.normals, radial).min() > 0.99


def test_make_shape_by_name_and_path(tmp_path):
    assert SHAPE_NAMES == ("donut", "teapot", "sphere", "coin", "bumpy")
    assert make_shape("donut", major_segments=16, minor_segments=8).vertex_count == 128
    plate = make_shape("coin", resolution=33)
    assert plate.vertex_count == 33 * 33 and plate.normals[:, 2].min() > 0.5  # a plate facing the camera (+z)
    assert np.all(np.abs(plate.points[:, :2]) <= 1.0) and plate.points[:, 2].max() > 0.03  # raised relief on it
    bumpy = make_shape("bumpy", major_segments=48, minor_segments=24)
    smooth = make_shape("donut", major_segments=48, minor_segments=24)
    offsets = np.einsum("ij,ij->i", bumpy.points - smooth.points, smooth.normals)
    np.testing.assert_allclose(bumpy.points - smooth.points, offsets[:, None] * smooth.normals, atol=1e-12)
    assert 0.003 < offsets.std() < 0.01 and bumpy.name == "bumpy"  # bumps along the normals, ~1.5% of the tube
    with pytest.raises(InputError, match="coin resolution"):
        make_shape("coin", resolution=4)
    assert make_shape(" Torus ", major_segments=16, minor_segments=8).name == "donut"
    assert make_shape("sphere", subdivisions=1).face_count == 80
    assert make_shape("teapot", subdivisions=2).name == "teapot"
    path = tmp_path / "ball.ply"
    _save(sphere(subdivisions=1), path)
    assert make_shape(str(path)).face_count == 80


def _single_line_error(call) -> str:
    with pytest.raises(InputError) as caught:
        call()
    message = str(caught.value)
    assert "\n" not in message and "Traceback" not in message
    return message


def test_input_errors_are_single_lines(tmp_path):
    missing = tmp_path / "nothing.ply"
    assert str(missing) in _single_line_error(lambda: load_mesh(missing))
    assert str(missing) in _single_line_error(lambda: make_shape(str(missing)))
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(np.random.default_rng(0).bytes(300))
    message = _single_line_error(lambda: load_mesh(garbage))
    assert str(garbage) in message and "cannot read" in message
    text = tmp_path / "notes.obj"
    text.write_text("this is not a mesh\n")
    assert "no triangles" in _single_line_error(lambda: load_mesh(text))
    unknown = tmp_path / "cloud.xyz"
    unknown.write_text("1 2 3\n")
    assert str(unknown) in _single_line_error(lambda: load_mesh(unknown))
    assert "folder" in _single_line_error(lambda: load_mesh(tmp_path))
    message = _single_line_error(lambda: make_shape("cube"))
    assert message == "unknown shape 'cube': use donut, teapot, sphere, coin, bumpy or a path to a PLY/OBJ/STL file"


def test_point_cloud_has_no_triangles(tmp_path):
    import pyvista as pv

    path = tmp_path / "cloud.ply"
    pv.PolyData(np.random.default_rng(1).random((20, 3))).save(str(path))
    assert "no triangles" in _single_line_error(lambda: load_mesh(path))


def test_load_mesh_repairs_mixed_winding_per_part(tmp_path):
    ball = sphere(subdivisions=2)
    other = ball.transformed(scale=0.5, translation=[4.0, 0.0, 0.0])
    flipped = np.random.default_rng(2).random(ball.face_count) < 0.4
    faces = np.where(flipped[:, None], ball.faces[:, ::-1], ball.faces)
    points = np.concatenate([ball.points, other.points])
    faces = np.concatenate([faces, other.faces[:, ::-1] + ball.vertex_count])  # second part inside out
    path = tmp_path / "two.ply"
    _save(TriangleMesh(points, faces, np.concatenate([ball.normals, other.normals]), "two"), path)
    loaded = load_mesh(path)
    assert not _has_repeated_directed_edge(loaded.faces)
    right = loaded.points[:, 0] > 2.0
    part_faces = right[loaded.faces[:, 0]]
    for part in (part_faces, ~part_faces):
        assert signed_volume(loaded.points, loaded.faces[part]) > 0.0
    centres = np.where(right[:, None], [4.0, 0.0, 0.0], 0.0)
    radial = loaded.points - centres
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", loaded.normals, radial).min() > 0.95
