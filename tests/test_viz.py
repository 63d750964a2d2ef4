"""pyvista views (``warp_highlights.view.viz``), the light designer and ``warp-highlights view``.

Geometry is checked against brute force (rotations, triangle membership, circle centres); what is
drawn is read back from the plotter's actors; screenshots are rendered off screen.
"""

from __future__ import annotations

import dataclasses
import gc

import numpy as np
import pytest

pv = pytest.importorskip("pyvista", reason="the views need pyvista (a dependency; absent on the bare GPU machines)")

from warp_highlights.cli import main
from warp_highlights.io.fieldfile import load_field
from warp_highlights.io.images import display_rgb8, read_image
from warp_highlights.model.arcs import circular_position
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.relight.interpolation import interpolate_sets
from warp_highlights.view import viz
from warp_highlights.view.designer import (
    LightDesigner,
    default_direction,
    describe_direction,
    sphere_camera,
)

SPHERE = SphericalTriangulation(LightSet.fibonacci_sphere(32).directions)
DOME = SphericalTriangulation(LightSet.fibonacci_dome(40, min_elevation_deg=15.0).directions)


@pytest.fixture(scope="module")
def field(small_field):
    return load_field(small_field)


@pytest.fixture
def plotter():
    plotter = viz.new_plotter(off_screen=True, window_size=(320, 240))
    yield plotter
    plotter.close()


def _rotate(axis: np.ndarray, angle: float, vector: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation, the brute-force reference for great-circle arcs."""
    axis = axis / np.linalg.norm(axis)
    return (vector * np.cos(angle) + np.cross(axis, vector) * np.sin(angle)
            + axis * (axis @ vector) * (1 - np.cos(angle)))


def _cells(mesh) -> list[np.ndarray]:
    """The points of every line cell of a PolyData, in order."""
    return [np.asarray(mesh.get_cell(k).points) for k in range(mesh.n_cells)]


def _actor_mesh(plotter, name: str):
    return plotter.renderer.actors[name].mapper.dataset


# --- the light sphere ------------------------------------------------------------------------------


def test_great_circle_arcs_match_rotations_about_the_edge_normal():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 3))
    b = rng.normal(size=(6, 3))
    lines = viz.great_circle_arcs(a, b, segments=10, radius=1.0)
    assert lines.n_cells == 6
    for k, points in enumerate(_cells(lines)):
        ua, ub = a[k] / np.linalg.norm(a[k]), b[k] / np.linalg.norm(b[k])
        angle = np.arccos(np.clip(ua @ ub, -1, 1))
        expected = np.array([_rotate(np.cross(ua, ub), angle * t, ua) for t in np.linspace(0, 1, 11)])
        np.testing.assert_allclose(points, expected, atol=1e-6)


def test_coincident_arc_ends_give_a_point_and_opposite_ends_are_refused():
    lines = viz.great_circle_arcs([[0, 0, 1.0]], [[0, 0, 2.0]], segments=4)
    assert np.all(np.isfinite(lines.points))
    np.testing.assert_allclose(lines.points, [[0, 0, viz.LINE_RADIUS]] * 5, atol=1e-6)
    with pytest.raises(InputError, match="opposite"):
        viz.great_circle_arcs([[0, 0, 1.0]], [[0, 0, -1.0]])


@pytest.mark.parametrize("triangulation", [SPHERE, DOME], ids=["sphere", "dome"])
def test_triangulation_lines_are_one_arc_per_edge_with_the_rim_flagged(triangulation):
    lines = viz.triangulation_lines(triangulation)
    edges = triangulation.edges()
    pairs = {tuple(sorted((int(f[k]), int(f[(k + 1) % 3])))) for f in triangulation.faces for k in range(3)}
    assert lines.n_cells == len(pairs)
    if not triangulation.is_dome:
        assert lines.n_cells == 3 * triangulation.light_count - 6  # Euler: a closed triangulated sphere
    np.testing.assert_array_equal(lines.cell_data["edge"], edges)
    rim = {tuple(e) for e in triangulation.boundary_edges()}
    assert [bool(f) for f in lines.cell_data["boundary"]] == [tuple(e) in rim for e in edges]
    assert (len(rim) > 0) == triangulation.is_dome
    for (i, j), points in zip(edges, _cells(lines), strict=True):
        np.testing.assert_allclose(np.linalg.norm(points, axis=1), viz.LINE_RADIUS, atol=1e-9)
        np.testing.assert_allclose(points[0], viz.LINE_RADIUS * triangulation.directions[i], atol=1e-6)
        np.testing.assert_allclose(points[-1], viz.LINE_RADIUS * triangulation.directions[j], atol=1e-6)


@pytest.mark.parametrize("triangulation", [SPHERE, DOME], ids=["sphere", "dome"])
def test_plot_triangulation_draws_every_edge_light_and_the_dome_rim(triangulation, plotter):
    viz.plot_triangulation(triangulation, plotter=plotter, labels=True)
    actors = plotter.renderer.actors
    pairs = {tuple(sorted((int(f[k]), int(f[(k + 1) % 3])))) for f in triangulation.faces for k in range(3)}
    assert _actor_mesh(plotter, "edges").n_cells == len(pairs)
    assert _actor_mesh(plotter, "lights").n_points == triangulation.light_count
    if triangulation.is_dome:
        assert _actor_mesh(plotter, "boundary").n_cells == len(triangulation.boundary_edges())
    else:
        assert "boundary" not in actors
    assert "query" not in actors


def test_spherical_triangle_lies_inside_its_triangle_on_the_sphere():
    corners = SPHERE.directions[SPHERE.faces[5]]
    patch = viz.spherical_triangle(*corners, level=6, radius=1.0)
    assert patch.n_cells == 36
    points = np.asarray(patch.points)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=1e-12)
    for k in range(3):  # inside the great circle through each edge, brute force
        a, b, c = corners[k], corners[(k + 1) % 3], corners[(k + 2) % 3]
        side = np.cross(a, b)
        assert np.all(points @ side * np.sign(c @ side) >= -1e-12)
    # a fine patch approximates the triangle's spherical excess (Girard's theorem)
    fine = viz.spherical_triangle(*corners, level=40, radius=1.0)
    a, b, c = corners
    excess = 2 * np.arctan2(abs(a @ np.cross(b, c)), 1 + a @ b + b @ c + c @ a)
    assert fine.area == pytest.approx(excess, rel=2e-3)


def test_plot_query_marks_the_triangle_it_falls_in_and_a_clamped_rim_point(plotter):
    viz.plot_triangulation(DOME, plotter=plotter)
    location = viz.plot_query(DOME, (0.2, 0.3, 1.0), plotter=plotter)
    corners = DOME.directions[DOME.faces[int(location.faces)]]
    np.testing.assert_allclose(_actor_mesh(plotter, "query corners").points, corners * viz.LINE_RADIUS, atol=1e-6)
    assert _actor_mesh(plotter, "query triangle edges").n_cells == 3
    assert "clamped" not in plotter.renderer.actors
    below = viz.plot_query(DOME, (1.0, 0.0, -0.5), plotter=plotter)
    assert bool(below.clamped)
    clamped = plotter.renderer.actors["clamped"]
    assert clamped.GetVisibility()
    np.testing.assert_allclose(clamped.mapper.dataset.center, below.directions * viz.LINE_RADIUS, atol=1e-6)
    viz.plot_query(DOME, (0.2, 0.3, 1.0), plotter=plotter)
    assert not clamped.GetVisibility()


def test_query_updates_reuse_the_actors_and_draw_the_new_geometry(plotter):
    """A drag must not create actors per move: the second query re-fills the first's meshes, and what
    the mappers draw is the second query's."""
    viz.plot_query(SPHERE, (0.2, 0.3, 1.0), plotter=plotter)
    plotter.screenshot(None, return_img=True)
    before = dict(plotter.renderer.actors)
    second = viz.plot_query(SPHERE, (-0.6, 0.1, 0.4), plotter=plotter)
    after = dict(plotter.renderer.actors)
    assert before.keys() == after.keys()
    assert all(before[name] is after[name] for name in before)
    after["query corners"].mapper.Update()
    corners = after["query corners"].mapper.GetInput()
    drawn = np.array([corners.GetPoint(k) for k in range(corners.GetNumberOfPoints())])
    np.testing.assert_allclose(drawn, SPHERE.directions[second.vertices] * viz.LINE_RADIUS, atol=1e-6)


def test_put_mesh_updates_a_mesh_coloured_by_scalars_after_other_actors_were_added(plotter):
    """pyvista feeds a scalar-coloured mesh through a filter: the update must reach the mapper's input."""
    first = pv.PolyData(np.zeros((3, 3)) + [0.0, 0.0, 0.0])
    first.point_data["colour"] = np.zeros((3, 3), dtype=np.uint8)
    actor = viz.put_mesh(plotter, first, "dots", scalars="colour", rgb=True)
    plotter.add_mesh(pv.Sphere(), name="another")
    del first  # the caller lets go of its mesh: pyvista's mapper then only has a copy of the filtered one
    gc.collect()
    second = pv.PolyData(np.arange(15, dtype=float).reshape(5, 3))
    second.point_data["colour"] = np.full((5, 3), 200, dtype=np.uint8)
    assert viz.put_mesh(plotter, second, "dots", scalars="colour", rgb=True) is actor
    actor.mapper.Update()
    drawn = actor.mapper.GetInput()
    assert drawn.GetNumberOfPoints() == 5
    np.testing.assert_allclose(drawn.GetPoint(4), (12.0, 13.0, 14.0))


# --- the image plane -------------------------------------------------------------------------------


def test_image_plane_covers_the_gaussian_coordinates_and_updates_in_place():
    image = np.zeros((4, 6, 3), dtype=np.float32)
    image[0, 0] = (1.0, 0.0, 0.0)  # top-left red
    image[3, 5] = (0.0, 0.0, 1.0)  # bottom-right blue
    plane, texture = viz.image_plane(image)
    np.testing.assert_allclose(plane.bounds[:4], (0.0, 1.5, -1.0, 0.0))
    np.testing.assert_array_equal(texture.to_array(), display_rgb8(image))
    viz.update_image(texture, np.ones((4, 6), dtype=np.float32))
    assert np.all(texture.to_array() == 255)
    with pytest.raises(InputError, match="pixels"):
        viz.update_image(texture, np.ones((5, 6)))


def test_plot_image_shows_row_zero_at_the_top_left_and_reuses_its_actor(plotter):
    """Rendered: pixel (col, row) of the image lands at Gaussian coordinates ((col + 0.5)/H, (row + 0.5)/H)."""
    image = np.zeros((4, 6, 3), dtype=np.float32)
    image[0, 0] = (1.0, 0.0, 0.0)
    image[3, 5] = (0.0, 0.0, 1.0)
    viz.plot_image(image, plotter=plotter)  # 320 x 240 window: the 6 x 4 image fills its width, 53.3 px a pixel
    picture = plotter.screenshot(None, return_img=True)
    red = np.argwhere((picture[..., 0] > 200) & (picture[..., 1] < 50) & (picture[..., 2] < 50))
    blue = np.argwhere((picture[..., 2] > 200) & (picture[..., 0] < 50) & (picture[..., 1] < 50))
    assert len(red) and len(blue)
    assert red[:, 1].max() < 60 and red[:, 0].max() < blue[:, 0].min()  # red: left column, above blue
    assert blue[:, 1].min() > 260  # blue: right column
    actor = plotter.renderer.actors["image"]
    viz.plot_image(np.ones((4, 6)), plotter=plotter, frame=False)
    assert plotter.renderer.actors["image"] is actor
    assert np.all(actor.texture.to_array() == 255)


def test_display_rgb8_clips_encodes_and_handles_non_finite_values():
    image = np.array([[0.0, 0.5, 1.0, 4.0, np.nan, np.inf, -1.0]], dtype=np.float32)
    shown = display_rgb8(image)
    assert shown.shape == (1, 7, 3) and shown.dtype == np.uint8
    assert shown[0, :, 0].tolist() == [0, 188, 255, 255, 0, 255, 0]
    with pytest.raises(InputError, match="displayed image"):
        display_rgb8(np.zeros((2, 2, 2)))


# --- Gaussian paths --------------------------------------------------------------------------------


def _busy_face(field) -> int:
    """The face whose corners have the most Gaussians (so every path kind appears)."""
    counts = field.estimated.counts[field.triangulation.faces].sum(axis=1)
    return int(np.argmax(counts))


def test_gaussian_paths_start_and_end_at_the_gaussians_positions(field):
    face = _busy_face(field)
    paths = viz.gaussian_paths(field, face, samples=17)
    vertices = field.triangulation.faces[face]
    assert paths.path_count == 2 * field.estimated.counts[vertices].sum()
    rows = {tuple(e): k for k, e in enumerate(field.directed_edges)}
    for p in range(paths.path_count):
        source, target, slot = vertices[paths.corner[p]], vertices[paths.target[p]], paths.slot[p]
        assert paths.corner[p] != paths.target[p]
        assert paths.gaussian[p] == paths.corner[p] * field.capacity + slot
        row = rows[(source, target)]
        np.testing.assert_allclose(paths.circular[p, 0], field.estimated.mean[source, slot], atol=1e-12)
        np.testing.assert_allclose(paths.circular[p, -1], field.retargeted.mean[row, slot], atol=1e-9)
        np.testing.assert_allclose(paths.straight[p, [0, -1]], paths.circular[p, [0, -1]], atol=1e-9)
        assert paths.delta[p] == pytest.approx(field.path_delta[row, slot])
    # the drawn polylines are the same points on the image plane
    for method in viz.PATH_METHODS:
        cells = _cells(paths.polylines(method))
        assert len(cells) == paths.path_count
        for p, points in enumerate(cells):
            np.testing.assert_allclose(points[0], viz.to_plane(paths.start[p], lift=points[0][2]), atol=1e-6)
            np.testing.assert_allclose(points[-1], viz.to_plane(paths.end[p], lift=points[0][2]), atol=1e-6)


def test_circular_paths_are_arcs_about_the_stored_centres(field):
    """Brute force: every sample of a turning path is as far from the fit's stored centre O as its start."""
    paths = viz.gaussian_paths(field, _busy_face(field), samples=9)
    straight_below = field.fit_settings().paths.straight_below
    rows = {tuple(e): k for k, e in enumerate(field.directed_edges)}
    turning = 0
    for p in range(paths.path_count):
        vertices = field.triangulation.faces[paths.face]
        row = rows[(vertices[paths.corner[p]], vertices[paths.target[p]])]
        if abs(paths.delta[p]) < max(straight_below, 0.05):
            continue
        turning += 1
        centre = field.path_centre[row, paths.slot[p]].astype(np.float64)
        radii = np.linalg.norm(paths.circular[p] - centre, axis=1)
        np.testing.assert_allclose(radii, radii[0], rtol=2e-4, atol=2e-6)
        # and the arc turns by delta: R(delta / 2)(start - O) + O is the middle sample
        half = paths.delta[p] / 2
        rotation = np.array([[np.cos(half), -np.sin(half)], [np.sin(half), np.cos(half)]])
        np.testing.assert_allclose(rotation @ (paths.start[p] - centre) + centre, paths.circular[p, 4], atol=2e-5)
    assert turning > 0
    np.testing.assert_allclose(paths.circular, circular_position(paths.start[:, None], paths.end[:, None],
                                                                 paths.delta[:, None],
                                                                 np.linspace(0, 1, 9)[None], straight_below))


def test_gaussian_paths_reject_a_missing_face(field):
    with pytest.raises(InputError, match="does not exist"):
        viz.gaussian_paths(field, field.triangulation.face_count)
    with pytest.raises(InputError, match="samples"):
        viz.gaussian_paths(field, 0, samples=1)


def test_ellipse_outlines_lie_at_two_sigma():
    from warp_highlights.model.gaussians import GaussianParams

    params = GaussianParams.from_sets([{"amplitude": [1.0, 0.5], "mean": [[0.5, 0.4], [0.9, 0.2]],
                                        "sigma": [[0.05, 0.02], [0.01, 0.03]],
                                        "theta": [0.7, -0.3]}])
    outlines = viz.gaussian_ellipses(params, sigmas=2.0, samples=13)
    assert outlines.shape == (2, 13, 2)
    for k in range(2):
        c, s = np.cos(params.theta[0, k]), np.sin(params.theta[0, k])
        rotation = np.array([[c, -s], [s, c]])
        cov = rotation @ np.diag(params.sigma[0, k] ** 2) @ rotation.T
        d = outlines[k] - params.mean[0, k]
        mahalanobis = np.sqrt(np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d))
        np.testing.assert_allclose(mahalanobis, 2.0, rtol=1e-9)


def test_plot_paths_draws_every_path_and_the_interpolated_gaussians(field, plotter):
    face = _busy_face(field)
    direction = field.triangulation.centroid_directions()[face]
    viz.plot_paths(field, direction, plotter=plotter, method="circular")
    paths = viz.gaussian_paths(field, face)
    location = field.triangulation.locate(direction)
    interpolated = interpolate_sets(field, location.vertices[None], location.barycentric[None])
    assert _actor_mesh(plotter, "paths circular").n_cells == paths.path_count
    assert _actor_mesh(plotter, "paths straight").n_cells == paths.path_count
    assert _actor_mesh(plotter, "path starts").n_points == len(np.unique(paths.gaussian))
    now = _actor_mesh(plotter, "gaussians now")
    assert now.n_cells == (interpolated.active & (interpolated.weight > 0)).sum()
    # each outline's centre is the interpolated mean (the first outline: the first active slot)
    first = np.flatnonzero(interpolated.active[0])[0]
    outline = _cells(now)[0][:-1]
    np.testing.assert_allclose(outline.mean(axis=0)[:2], viz.to_plane(interpolated.mean[0, first])[:2], atol=1e-6)
    # one colour per Gaussian: both paths of a Gaussian share it, different Gaussians differ
    colours = np.asarray(_actor_mesh(plotter, "paths circular").cell_data["colour"])
    for g in np.unique(paths.gaussian):
        assert len(np.unique(colours[paths.gaussian == g], axis=0)) == 1
    assert len(np.unique(colours, axis=0)) == len(np.unique(paths.gaussian))
    # the start dots and the outlines wear their Gaussian's colour too
    of_gaussian = {int(g): tuple(colours[k]) for k, g in enumerate(paths.gaussian)}
    dots = np.asarray(_actor_mesh(plotter, "path starts").point_data["colour"])
    assert [tuple(c) for c in dots] == [of_gaussian[int(g)] for g in np.unique(paths.gaussian)]
    outline_colours = np.asarray(now.cell_data["colour"])[:, :3]
    shown = np.flatnonzero(interpolated.active[0] & (interpolated.weight[0] > 0))
    assert [tuple(c) for c in outline_colours] == [of_gaussian[int(g)] for g in shown]
    viz.plot_paths(field, direction, plotter=plotter, methods=("circular",))
    assert not plotter.renderer.actors["paths straight"].GetVisibility()


def test_gaussian_colours_are_distinct():
    colours = viz.gaussian_colours(60)
    assert colours.shape == (60, 3) and np.all((colours >= 0) & (colours <= 1))
    assert len(np.unique(np.round(colours * 255), axis=0)) == 60


# --- the designer ----------------------------------------------------------------------------------


def test_designer_screenshot_is_the_window_and_not_empty(field, device, tmp_path):
    designer = LightDesigner(field, device=device, off_screen=True, window_size=(660, 240))
    try:
        picture = designer.screenshot(tmp_path / "view.png")
    finally:
        designer.close()
    assert picture.shape == (240, 660, 3)
    written = read_image(tmp_path / "view.png")
    assert written.shape == (240, 660, 3)
    background = np.array([0x1F, 0x23, 0x29])
    for k in range(3):  # every panel drew something besides the background
        panel = picture[:, 220 * k : 220 * (k + 1)].reshape(-1, 3).astype(int)
        drawn = np.any(np.abs(panel - background) > 8, axis=1).mean()
        assert drawn > 0.05, f"panel {k} is empty"


def test_designer_shows_the_relighters_image_and_follows_the_handle(field, device):
    designer = LightDesigner(field, device=device, off_screen=True, window_size=(600, 200), panels=("image", "sphere"))
    try:
        designer._on_handle_moved((0.0, 0.0, 0.0))  # ignored: no direction
        designer._on_handle_moved((2.0, -1.0, 2.0))
        np.testing.assert_allclose(designer.direction, np.array([2.0, -1.0, 2.0]) / 3.0)
        relit = designer.relighter.relight(designer.direction)
        designer.plotter.subplot(0, 0)
        shown = designer.plotter.renderer.actors["image"].texture.to_array()
        np.testing.assert_array_equal(shown, display_rgb8(relit.full))
        designer.plotter.subplot(0, 1)
        location = field.triangulation.locate(designer.direction)
        np.testing.assert_allclose(_actor_mesh(designer.plotter, "query corners").points,
                                   field.triangulation.directions[location.vertices] * viz.LINE_RADIUS, atol=1e-6)
        assert set(designer.timings) == {"relight", "scene"}
        designer._toggle_highlights()
        designer.plotter.subplot(0, 0)
        shown = designer.plotter.renderer.actors["image"].texture.to_array()
        np.testing.assert_array_equal(shown, display_rgb8(relit.specular / field.exposure))
        designer._toggle_method()
        assert designer.method == "straight"
    finally:
        designer.close()


def test_dragging_the_handle_moves_the_light_on_the_sphere_and_the_image_follows(field, monkeypatch):
    """A real window and interactor (drawn through EGL, so no display is needed): press on the handle,
    move the mouse, release. The light follows on the unit sphere, the image is re-rendered, and each
    move draws the window once."""
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    designer = LightDesigner(field, device="cpu", off_screen=False, window_size=(600, 300), panels=("sphere", "image"),
                             multi_samples=0)
    try:
        plotter = designer.plotter
        plotter.show(auto_close=False, interactive=False)
        interactor = plotter.iren.interactor
        draws = []
        plotter.ren_win.AddObserver("StartEvent", lambda *_: draws.append(1))
        plotter.subplot(0, 1)
        before = plotter.renderer.actors["image"].texture.to_array().copy()
        plotter.subplot(0, 0)
        start = designer.direction.copy()
        plotter.renderer.SetWorldPoint(*start, 1.0)
        plotter.renderer.WorldToDisplay()
        x, y, _ = plotter.renderer.GetDisplayPoint()
        interactor.SetEventInformation(int(x), int(y))
        interactor.InvokeEvent("LeftButtonPressEvent")
        draws.clear()
        for k in range(1, 6):
            interactor.SetEventInformation(int(x) + 12 * k, int(y) + 4 * k)
            interactor.InvokeEvent("MouseMoveEvent")
        assert len(draws) == 5  # one draw per move: the callback leaves it to the widget
        interactor.InvokeEvent("LeftButtonReleaseEvent")
        assert np.degrees(np.arccos(np.clip(start @ designer.direction, -1, 1))) > 5
        assert np.linalg.norm(designer.direction) == pytest.approx(1.0)
        # the handle stays on the sphere
        np.testing.assert_allclose(designer._widget.GetCenter(), designer.direction, atol=1e-9)
        plotter.subplot(0, 1)
        after = plotter.renderer.actors["image"].texture.to_array()
        expected = display_rgb8(designer.relighter.relight(designer.direction).full)
        np.testing.assert_array_equal(after, expected)
        assert np.abs(after.astype(int) - before).max() > 20
    finally:
        designer.close()


def test_designer_says_how_much_of_the_image_moves(field):
    """The image panel's text carries the field's moving Gaussians and the share of the specular energy they carry,
    as the fit report has them."""
    designer = LightDesigner(field, off_screen=True, window_size=(400, 200), panels=("image",))
    try:
        designer.plotter.subplot(0, 0)
        text = designer.plotter.renderer.actors["image text"].GetText(2)
    finally:
        designer.close()
    share = field.report["residual"]["moving_specular_share"]
    line = field.motion_line()
    assert line in text.splitlines()
    assert line == (f"{int(field.moving_mask.sum())} of {int(field.estimated.active.sum())} Gaussians move "
                    f"({100 * share:.0f}% of the specular energy)")
    legacy = dataclasses.replace(field, report={})  # a field written before the report had the share
    counts = f"{int(field.moving_mask.sum())} of {int(field.estimated.active.sum())}"
    assert legacy.motion_line() == f"{counts} Gaussians move"


def test_designer_redraws_paths_only_for_a_new_triangle(field):
    designer = LightDesigner(field, device="cpu", off_screen=True, window_size=(300, 200), panels=("paths",))
    try:
        faces = field.triangulation.faces
        first = designer._paths
        centroid = field.triangulation.centroid_directions()[designer._face]
        designer.set_direction(centroid + 1e-3 * np.cross(centroid, [0.0, 1.0, 0.0]))
        assert designer._paths is first
        other = (designer._face + 7) % len(faces)
        designer.set_direction(field.triangulation.centroid_directions()[other])
        assert designer._face == other and designer._paths.face == other
    finally:
        designer.close()


def test_designer_after_moves_draws_what_a_fresh_designer_draws(field, tmp_path):
    """Every panel follows the light: after moving through other triangles (and toggling the method
    twice), the window is pixel for pixel the window of a new designer opened at that light."""
    centroids = field.triangulation.centroid_directions()
    target = centroids[_busy_face(field)]
    options = {"device": "cpu", "off_screen": True, "window_size": (600, 200)}
    moved = LightDesigner(field, direction=centroids[(_busy_face(field) + 9) % len(centroids)], **options)
    fresh = None
    try:
        moved.screenshot()
        moved.set_direction(centroids[(_busy_face(field) + 3) % len(centroids)])
        fresh = LightDesigner(field, direction=target, **options)  # other plotters' actors come and go meanwhile
        gc.collect()
        moved._toggle_method()
        moved.set_direction(target, render=False)
        moved._toggle_method()
        assert moved._face == fresh._face == _busy_face(field)
        for name in ("sphere", "image", "paths"):  # cameras are placed on arrival in a triangle: align them
            moved.plotter.subplot(0, moved.panels.index(name))
            fresh.plotter.subplot(0, fresh.panels.index(name))
            moved.plotter.camera_position = fresh.plotter.camera_position
            moved.plotter.camera.parallel_scale = fresh.plotter.camera.parallel_scale
        difference = np.abs(moved.screenshot().astype(int) - fresh.screenshot().astype(int)).max(axis=2)
        difference[:30] = 0  # the texts: "relit in ... ms" differs from run to run
        assert difference.max() == 0, f"{(difference > 0).sum()} pixels differ"
    finally:
        moved.close()
        if fresh is not None:
            fresh.close()


def test_designer_panels_agree_on_the_triangle_at_a_light(field):
    """A light direction sits on several triangles; the sphere and the paths must name the same one."""
    designer = LightDesigner(field, device="cpu", off_screen=True, window_size=(400, 200), panels=("sphere", "paths"))
    try:
        for light in range(0, field.light_count, 5):
            designer.set_direction(field.lights.directions[light], render=False)
            designer.plotter.subplot(0, 0)
            corners = np.asarray(_actor_mesh(designer.plotter, "query corners").points)
            np.testing.assert_allclose(corners,
                                       field.triangulation.directions[designer._paths.vertices] * viz.LINE_RADIUS,
                                       atol=1e-6)
            assert designer._paths.face == designer._face
    finally:
        designer.close()


def test_designer_rejects_unknown_panels(field):
    with pytest.raises(InputError, match="panels"):
        LightDesigner(field, off_screen=True, panels=("sphere", "sky"))
    with pytest.raises(InputError, match="panels"):
        LightDesigner(field, off_screen=True, panels=("paths", "paths"))


def test_default_direction_is_a_triangle_centroid_and_text_and_camera_helpers():
    direction = default_direction(SPHERE)
    assert np.isclose(np.linalg.norm(direction), 1.0)
    np.testing.assert_allclose(SPHERE.locate(direction).barycentric, 1 / 3, atol=1e-9)
    assert describe_direction((0.0, 0.0, 1.0)) == "(+0.00, +0.00, +1.00)  elevation 90 deg, azimuth 0 deg"
    assert describe_direction((0.0, -1.0, 0.0)).endswith("elevation 0 deg, azimuth 270 deg")
    for light in ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.6, -0.2, 0.7]):
        position, focus, up = sphere_camera(np.array(light) / np.linalg.norm(light))
        assert np.linalg.norm(position) == pytest.approx(4.7) and focus == (0.0, 0.0, 0.0)
        assert np.dot(position, light) > 0  # seen from its own side
        assert abs(np.dot(position, up)) < 0.96 * 4.7  # the up vector is not along the view


# --- the command -----------------------------------------------------------------------------------


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    return err


def test_view_screenshot_has_the_window_size(small_field, tmp_path, capsys):
    out = tmp_path / "view.png"
    assert main(["view", str(small_field), "--screenshot", str(out), "--window-size", "500x180", "--device", "cpu",
                 "--light", "-0.4,0.3,0.8", "--panels", "paths,sphere"]) == 0
    assert "wrote" in capsys.readouterr().out
    picture = read_image(out)
    assert picture.shape == (180, 500, 3)
    assert picture.std() > 0.02
    assert not list(tmp_path.glob(".*")), "a temporary file was left behind"


def test_view_bad_input_is_one_line(small_field, tmp_path, capsys, monkeypatch):
    out = tmp_path / "view.png"
    out.write_bytes(b"keep")
    assert main(["view", str(small_field), "--screenshot", str(out)]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert out.read_bytes() == b"keep"
    assert main(["view", str(small_field), "--screenshot", str(tmp_path / "view.jpg")]) == 2
    assert ".png" in _error_line(capsys)
    assert main(["view", str(small_field), "--screenshot", str(tmp_path / "a.png"), "--panels", "sphere,sky"]) == 2
    assert "panels" in _error_line(capsys)
    assert main(["view", str(small_field), "--screenshot", str(tmp_path / "a.png"), "--light", "0,0,0"]) == 2
    assert "non-zero" in _error_line(capsys)
    assert main(["view", str(tmp_path / "missing.whf"), "--screenshot", str(tmp_path / "a.png")]) == 2
    assert "missing.whf" in _error_line(capsys)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert main(["view", str(small_field)]) == 2
    assert "--screenshot" in _error_line(capsys)
    assert not (tmp_path / "a.png").exists()
