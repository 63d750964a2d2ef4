"""pyvista views of a highlight field: the light sphere with its triangulation, and the Gaussians'
paths over the image plane. ``warp-highlights view`` composes them into the light designer
(:mod:`warp_highlights.view.designer`); notebooks and scripts compose their own.

Scene coordinates:

- **Light sphere**: camera space (docs/method.md, Units and conventions: x right, y up, z towards the camera), unit
  radius; a light direction is a point on the sphere.
- **Image plane**: the Gaussians' image-height units with y turned up so the picture stands upright:
  image point (x, y) is drawn at (x, -y, 0), and the image covers [0, W/H] x [-1, 0].

The builders (``great_circle_arcs``, ``triangulation_lines``, ``spherical_triangle``, ``image_plane``,
``gaussian_paths``...) return plain pyvista meshes or NumPy arrays; the ``plot_*`` functions add
them to a ``pyvista.Plotter`` (a new one when none is given, off screen when there is no display) and
return it; called again on the same plotter they refill their actors in place (``put_mesh``).
pyvista is imported on first use.

This module holds one thing: the pyvista scene pieces that views of a field are built from.
"""

from __future__ import annotations

import copy
import functools
import os
import sys
import weakref
from dataclasses import dataclass

import numpy as np

from ..io.images import display_rgb8
from ..model.arcs import circular_position
from ..model.errors import InputError
from ..model.triangulation import unit_query_directions
from ..relight.interpolation import INTERPOLATION_METHODS, edge_rows, interpolate_sets

__all__ = [
    "LINE_RADIUS",
    "PATH_METHODS",
    "GaussianPaths",
    "check_path_method",
    "gaussian_colours",
    "gaussian_ellipses",
    "gaussian_paths",
    "great_circle_arcs",
    "has_display",
    "hide",
    "image_plane",
    "light_points",
    "look_at_sphere",
    "new_plotter",
    "plot_image",
    "plot_paths",
    "plot_query",
    "plot_triangulation",
    "put_mesh",
    "put_text",
    "software_opengl",
    "spherical_triangle",
    "to_plane",
    "triangulation_lines",
    "unit_direction",
    "update_image",
]

LINE_RADIUS = 1.004
"""Radius the edges and the current triangle are drawn at: just above the unit sphere, so the sphere's
facets never hide them."""

PATH_METHODS = INTERPOLATION_METHODS
"""The paths drawn: ``interpolation.INTERPOLATION_METHODS``."""

_ARC_SEGMENTS = 24  # segments of each drawn great-circle edge (a 109-degree tetrahedron edge: 4.5 deg each)
_PATH_SAMPLES = 33  # points of each drawn Gaussian path
_ELLIPSE_SAMPLES = 49
_ELLIPSE_SIGMAS = 1.0  # outlines drawn at this Mahalanobis distance
_PATH_LIFT = 2e-3  # height of the paths above the image plane (image heights), so they sit on top
# renderer -> {name: (actor, mesh)}, see put_mesh
_ADDED_MESHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_COLOURS = {
    "sphere": "#d9dde3",
    "lights": "#f28e2b",
    "edges": "#4e5968",
    "boundary": "#c0392b",
    "triangle": "#4c9be8",
    "query": "#f1c40f",
    "clamped": "#e74c3c",
    "camera": "#7f8c8d",
}


# --- plotters ------------------------------------------------------------------------------------


def has_display() -> bool:
    """True where an on-screen window can open (always on Windows and macOS; Linux needs DISPLAY or WAYLAND_DISPLAY)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def new_plotter(*, off_screen: bool | None = None, window_size: tuple[int, int] = (900, 700),
                shape: tuple[int, int] = (1, 1),
                multi_samples: int | None = None):
    """A ``pyvista.Plotter``; off screen when asked or when there is no display (then VTK renders
    through EGL instead of probing for an X server). ``multi_samples``: MSAA samples (default
    pyvista's theme, 8); 0 draws several times faster on a software OpenGL (see :func:`software_opengl`)."""
    if off_screen is None:
        off_screen = not has_display()
    if off_screen and not has_display():
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import pyvista as pv
    except ImportError as error:
        raise InputError(f"drawing needs pyvista, which does not import here ({error}): pip install pyvista") from None

    theme = None
    if multi_samples is not None:
        theme = copy.deepcopy(pv.global_theme)
        theme.multi_samples = int(multi_samples)
    return pv.Plotter(off_screen=off_screen, window_size=tuple(int(v) for v in window_size), shape=shape, border=False,
                      theme=theme)


def software_opengl() -> bool:
    """True when VTK draws with a CPU OpenGL (Mesa's llvmpipe or softpipe, SwiftShader): no GPU helps."""
    import pyvista as pv

    try:
        renderer = pv.GPUInfo().renderer.lower()
    except Exception:  # noqa: BLE001 - no OpenGL context at all: treat as software
        return True
    return any(name in renderer for name in ("llvmpipe", "softpipe", "swiftshader", "software"))


# --- the light sphere ----------------------------------------------------------------------------


def great_circle_arcs(starts, ends, *, segments: int = _ARC_SEGMENTS, radius: float = LINE_RADIUS):
    """One polyline cell per pair: the shorter great-circle arc from ``starts[k]`` to ``ends[k]``.

    Args:
        starts, ends: (K, 3) directions (any non-zero length; normalised here).
        segments: straight segments per arc.
        radius: sphere radius the arcs are drawn on.

    Returns:
        ``pyvista.PolyData`` with K line cells of ``segments + 1`` points each, the arcs in input order.
    """
    import pyvista as pv

    a = _unit_rows(starts, "arc starts")
    b = _unit_rows(ends, "arc ends")
    if a.shape != b.shape:
        raise InputError(f"arc starts and ends differ in shape: {a.shape} vs {b.shape}")
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0))
    if np.any(angle > np.pi - 1e-9):
        raise InputError("an arc between opposite directions has no single great circle")
    t = np.linspace(0.0, 1.0, segments + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_angle = np.sin(angle)
        short = sin_angle < 1e-9
        wa = np.where(short[:, None], 1.0 - t[None],
                      np.sin((1.0 - t[None]) * angle[:, None]) / np.where(short, 1.0, sin_angle)[:, None])
        wb = np.where(short[:, None], t[None],
                      np.sin(t[None] * angle[:, None]) / np.where(short, 1.0, sin_angle)[:, None])
    points = wa[..., None] * a[:, None] + wb[..., None] * b[:, None]
    points = radius * points / np.linalg.norm(points, axis=-1, keepdims=True)
    return pv.PolyData(points.reshape(-1, 3), lines=_polyline_cells(len(a), segments + 1))


def triangulation_lines(triangulation, *, segments: int = _ARC_SEGMENTS, radius: float = LINE_RADIUS):
    """Every edge of a ``SphericalTriangulation`` as a great-circle arc (one line cell per edge, in the
    order of ``triangulation.edges()``), with cell arrays ``edge`` (the two light indices) and
    ``boundary`` (1 on the rim of a dome)."""
    edges = triangulation.edges()
    directions = triangulation.directions
    lines = great_circle_arcs(directions[edges[:, 0]], directions[edges[:, 1]], segments=segments, radius=radius)
    lines.cell_data["edge"] = edges
    rim = triangulation.boundary_edges()
    boundary = np.zeros(len(edges), dtype=np.uint8)
    boundary[edge_rows(edges, triangulation.light_count, rim[:, 0], rim[:, 1])] = 1
    lines.cell_data["boundary"] = boundary
    return lines


def light_points(triangulation, *, radius: float = 1.0):
    """The light directions as points on the sphere, with point array ``light`` (index)."""
    import pyvista as pv

    points = pv.PolyData(radius * np.asarray(triangulation.directions, dtype=np.float64))
    points.point_data["light"] = np.arange(triangulation.light_count)
    return points


def spherical_triangle(a, b, c, *, level: int = 12, radius: float = LINE_RADIUS):
    """A filled spherical triangle with corners at directions ``a``, ``b``, ``c`` (a surface patch of
    ``level**2`` planar triangles projected onto the sphere)."""
    import pyvista as pv

    corners = _unit_rows(np.stack([a, b, c]), "triangle corners")
    weights, faces = _triangle_grid(int(level))
    points = weights @ corners
    points = radius * points / np.linalg.norm(points, axis=1, keepdims=True)
    return pv.PolyData(points, faces=faces)


@functools.lru_cache(maxsize=4)
def _triangle_grid(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights (P, 3) of a triangle's grid points at subdivision ``level`` and its
    ``level**2`` faces as VTK connectivity (made once per level: the query's triangle is rebuilt on
    every move)."""
    rows = [(i, j) for i in range(level + 1) for j in range(level + 1 - i)]
    index = {ij: k for k, ij in enumerate(rows)}
    weights = np.array([(level - i - j, i, j) for i, j in rows], dtype=np.float64) / level
    faces = []
    for i in range(level):
        for j in range(level - i):
            faces.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j + 1 < level:
                faces.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    faces = np.asarray(faces, dtype=np.int64)
    connectivity = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    weights.flags.writeable = connectivity.flags.writeable = False
    return weights, connectivity


def plot_triangulation(field_or_triangulation, *, plotter=None, direction=None, labels: bool = False,
                       sphere: bool = True, camera: bool = True):
    """Draw the light sphere: the unit sphere, the lights, the triangulation's edges and (for a dome) its
    boundary; with ``direction``, also the query and its triangle (:func:`plot_query`).

    Args:
        field_or_triangulation: a ``HighlightField`` or a ``SphericalTriangulation``.
        plotter: draw into this ``pyvista.Plotter`` (its active subplot); default a new one.
        direction: a light direction (3,) to mark, or None.
        labels: write each light's index beside it.
        sphere: draw the unit sphere itself.
        camera: draw the direction towards the camera (+z) as a grey arrow.

    Returns:
        The plotter. Its actors are named ``sphere``, ``lights``, ``edges``, ``boundary`` (only for a
        dome), ``camera`` and the names :func:`plot_query` uses.
    """
    import pyvista as pv

    triangulation = getattr(field_or_triangulation, "triangulation", field_or_triangulation)
    plotter = plotter if plotter is not None else new_plotter()
    if sphere:
        plotter.add_mesh(pv.Sphere(radius=1.0, theta_resolution=96, phi_resolution=48), color=_COLOURS["sphere"],
                         smooth_shading=True,
                         ambient=0.35, diffuse=0.65, specular=0.1, name="sphere", pickable=False)
    lines = triangulation_lines(triangulation)
    plotter.add_mesh(lines, color=_COLOURS["edges"], line_width=1.5, name="edges", pickable=False)
    rim = lines.extract_cells(np.flatnonzero(lines.cell_data["boundary"]))
    if rim.n_cells:
        plotter.add_mesh(rim, color=_COLOURS["boundary"], line_width=4, name="boundary", pickable=False)
    points = light_points(triangulation, radius=LINE_RADIUS)
    plotter.add_mesh(points, color=_COLOURS["lights"], point_size=9, render_points_as_spheres=True, name="lights",
                     pickable=False)
    if labels:
        plotter.add_point_labels(points.points * 1.04, [str(k) for k in range(triangulation.light_count)], font_size=9,
                                 point_size=1,
                                 shape=None, name="light labels")
    if camera:
        plotter.add_mesh(pv.Arrow(start=(0, 0, 1.05), direction=(0, 0, 1), scale=0.45, tip_length=0.3,
                                  shaft_radius=0.02),
                         color=_COLOURS["camera"], name="camera", pickable=False)
    if direction is not None:
        plot_query(triangulation, direction, plotter=plotter)
    look_at_sphere(plotter, (2.3, 1.7, 3.6))
    return plotter


def look_at_sphere(plotter, toward, *, up=(0.0, 1.0, 0.0), radius: float = 1.2) -> None:
    """Point the active subplot's camera at the centre from direction ``toward``, just far enough
    that a sphere of ``radius`` (the unit sphere and its marks) fills the panel's shorter side."""
    toward = unit_direction(toward)
    left, bottom, right, top = plotter.renderer.GetViewport()
    aspect = (right - left) * plotter.window_size[0] / max((top - bottom) * plotter.window_size[1], 1)
    half_height = np.radians(plotter.camera.view_angle) / 2
    half = min(half_height, np.arctan(np.tan(half_height) * aspect))
    plotter.camera_position = [tuple(radius / np.sin(half) * toward), (0.0, 0.0, 0.0), tuple(up)]


def plot_query(triangulation, direction, *, plotter, handle: bool = True, location=None):
    """Mark a query direction on the light sphere: a line from the centre to it, a handle sphere at
    it (``handle``), its triangle filled and outlined, and where a dome clamped it onto its rim.

    Re-calling with the same plotter replaces the marks (actors ``query``, ``query handle``, ``query
    triangle``, ``query triangle edges``, ``query corners``, ``clamped``). ``location``: the direction's
    ``triangulation.locate`` result when already known (so every panel shows the same triangle on a
    shared edge). Returns the ``Location``.
    """
    import pyvista as pv

    direction = unit_direction(direction)
    location = triangulation.locate(direction) if location is None else location
    corners = triangulation.directions[location.vertices]
    put_mesh(plotter, spherical_triangle(*corners), "query triangle", color=_COLOURS["triangle"], opacity=0.55)
    put_mesh(plotter, great_circle_arcs(corners, np.roll(corners, -1, axis=0)), "query triangle edges",
             color=_COLOURS["triangle"], line_width=4)
    put_mesh(plotter, pv.PolyData(corners * LINE_RADIUS), "query corners", color=_COLOURS["triangle"], point_size=14,
             render_points_as_spheres=True)
    put_mesh(plotter, pv.Line((0.0, 0.0, 0.0), tuple(1.25 * direction)), "query", color=_COLOURS["query"], line_width=4)
    if handle:
        put_mesh(plotter, pv.Sphere(radius=0.05, center=tuple(direction)), "query handle", color=_COLOURS["query"])
    if bool(location.clamped):
        put_mesh(plotter, pv.Sphere(radius=0.035, center=tuple(location.directions * LINE_RADIUS)), "clamped",
                 color=_COLOURS["clamped"])
    else:
        hide(plotter, "clamped")
    return location


# --- the image plane -----------------------------------------------------------------------------


def to_plane(points, *, lift: float = 0.0) -> np.ndarray:
    """Image points (..., 2) in image heights (x right, y down) -> scene points (..., 3): (x, -y, lift)."""
    points = np.asarray(points, dtype=np.float64)
    return np.stack([points[..., 0], -points[..., 1], np.full(points.shape[:-1], float(lift))], axis=-1)


def image_plane(image):
    """A linear image (H, W[, C]) as a textured rectangle covering [0, W/H] x [-1, 0] of the image plane.

    Returns:
        ``(plane, texture)``: a one-quad ``pyvista.PolyData`` and a ``pyvista.Texture`` holding the sRGB
        pixels (``texture.to_array()`` gives them back, row 0 at the top), drawn without filtering so
        every pixel stays a sharp square.
    """
    import pyvista as pv

    colours = display_rgb8(image)
    height, width = colours.shape[:2]
    aspect = width / height
    plane = pv.Plane(center=(0.5 * aspect, -0.5, 0.0), direction=(0.0, 0.0, 1.0), i_size=aspect, j_size=1.0,
                     i_resolution=1,
                     j_resolution=1)
    texture = pv.Texture(colours)
    texture.interpolate = False
    return plane, texture


def update_image(texture, image) -> None:
    """Write a new image of the same size into a texture made by :func:`image_plane` (in place)."""
    colours = display_rgb8(image)
    pv_image = texture.to_image()
    width, height = pv_image.dimensions[:2]
    if colours.shape[:2] != (height, width):
        raise InputError(
            f"the image is {colours.shape[1]} x {colours.shape[0]} pixels but the texture {width} x {height}")
    pixels = pv_image.point_data.active_scalars
    pixels[:] = colours[::-1].reshape(-1, 3)  # VTK stores the bottom row first
    pv_image.Modified()
    texture.Modified()


def plot_image(image, *, plotter=None, name: str = "image", dim: float = 1.0, frame: bool = True,
               headroom: float = 0.0):
    """Draw a linear image on the image plane (``dim`` scales it, e.g. 0.55 under paths); returns the plotter.

    An image actor of the same ``name`` and size is updated in place (cheap enough for every frame of
    a drag); ``frame`` points the camera straight at the image, filling the view but for ``headroom``
    (a share of the image height) left free above it for text.
    """
    plotter = plotter if plotter is not None else new_plotter()
    image = np.asarray(image, dtype=np.float32) * np.float32(dim)
    actor = plotter.renderer.actors.get(name)
    texture = getattr(actor, "texture", None)
    if texture is not None and tuple(texture.to_image().dimensions[:2]) == (image.shape[1], image.shape[0]):
        update_image(texture, image)
        actor.SetVisibility(True)
    else:
        plane, texture = image_plane(image)
        plotter.add_mesh(plane, texture=texture, name=name, pickable=False, lighting=False)
    if frame:
        aspect = image.shape[1] / image.shape[0]
        _look_at(plotter, (0.0, aspect, -1.0, float(headroom)))
    return plotter


# --- Gaussian paths ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GaussianPaths:
    """The paths of every Gaussian of one triangle's three corners towards the other two corners.

    P paths: each active Gaussian of corner A contributes two, A -> B and A -> C (likewise for B and
    C). Positions are image heights (x right, y down).

    Attributes:
        face: the triangle (index into ``triangulation.faces``).
        vertices: (3,) its light indices, in ``triangulation.faces`` order (corners 0, 1, 2).
        gaussian: (P,) which Gaussian of the triangle the path belongs to: ``corner * N + slot``.
        corner: (P,) the corner (0..2) the Gaussian is estimated at.
        target: (P,) the corner (0..2) the path leads to.
        slot: (P,) its slot in that corner's estimated set.
        delta: (P,) the signed rotation along the path, radians (the fit's path decision).
        start: (P, 2) the Gaussian's mean in its corner's estimated set (mu_A).
        end: (P, 2) its mean in the set retargeted to the target (mu_{A->B}).
        circular: (P, S, 2) points along the circular path (the arc the relighting follows).
        straight: (P, S, 2) points along the straight segment.
    """

    face: int
    vertices: np.ndarray
    gaussian: np.ndarray
    corner: np.ndarray
    target: np.ndarray
    slot: np.ndarray
    delta: np.ndarray
    start: np.ndarray
    end: np.ndarray
    circular: np.ndarray
    straight: np.ndarray

    @property
    def path_count(self) -> int:
        return len(self.gaussian)

    def polylines(self, method: str = "circular", *, lift: float = _PATH_LIFT):
        """The paths of ``method`` as a ``pyvista.PolyData`` on the image plane, one line cell per path
        (in this object's order), with cell array ``gaussian``."""
        import pyvista as pv

        points = {"circular": self.circular, "straight": self.straight}[check_path_method(method)]
        mesh = pv.PolyData(to_plane(points, lift=lift).reshape(-1, 3),
                           lines=_polyline_cells(len(points), points.shape[1]))
        mesh.cell_data["gaussian"] = self.gaussian
        return mesh


def gaussian_paths(field, face: int, *, samples: int = _PATH_SAMPLES) -> GaussianPaths:
    """The circular and straight paths of the Gaussians of triangle ``face`` of a ``HighlightField``."""
    faces = field.triangulation.faces
    if not (0 <= int(face) < len(faces)):
        raise InputError(f"face {face} does not exist: the triangulation has {len(faces)} faces")
    if samples < 2:
        raise InputError(f"a path needs at least 2 samples, got {samples}")
    vertices = faces[int(face)].astype(np.int64)
    capacity = field.capacity
    corner, target, slot = [], [], []
    for k in range(3):
        slots = np.flatnonzero(field.estimated.active[vertices[k]])
        for step in (1, 2):
            corner.append(np.full(len(slots), k))
            target.append(np.full(len(slots), (k + step) % 3))
            slot.append(slots)
    corner, target, slot = (np.concatenate(parts).astype(np.int64) for parts in (corner, target, slot))
    rows = edge_rows(field.directed_edges, field.light_count, vertices[corner], vertices[target])
    start = field.estimated.mean[vertices[corner], slot]
    end = field.retargeted.mean[rows, slot]
    delta = field.path_delta[rows, slot].astype(np.float64)
    fraction = np.linspace(0.0, 1.0, samples)
    straight_below = field.fit_settings().paths.straight_below
    circular = circular_position(start[:, None], end[:, None], delta[:, None], fraction[None], straight_below)
    straight = start[:, None] + fraction[None, :, None] * (end - start)[:, None]
    return GaussianPaths(
        face=int(face), vertices=vertices, gaussian=corner * capacity + slot, corner=corner, target=target, slot=slot,
        delta=delta, start=start, end=end, circular=circular, straight=straight,
    )


def gaussian_colours(count: int) -> np.ndarray:
    """(count, 3) float RGB in [0, 1]: well-separated hues (golden-ratio steps), one per Gaussian."""
    from matplotlib.colors import hsv_to_rgb

    hues = (np.arange(count) * 0.6180339887498949 + 0.08) % 1.0
    return hsv_to_rgb(np.stack([hues, np.full(count, 0.75), np.ones(count)], axis=-1)).reshape(count, 3)


def gaussian_ellipses(params, rows=None, *, sigmas: float = _ELLIPSE_SIGMAS,
                      samples: int = _ELLIPSE_SAMPLES) -> np.ndarray:
    """Outlines (G, S, 2) of active Gaussians at ``sigmas`` Mahalanobis units, image heights.

    Args:
        params: a ``GaussianParams`` of one set (1, N) or several.
        rows: which set, when there are several (default 0).
    """
    row = 0 if rows is None else int(rows)
    active = params.active[row]
    mean, sigma, theta = params.mean[row][active], np.abs(params.sigma[row][active]), params.theta[row][active]
    t = np.linspace(0.0, 2.0 * np.pi, samples)
    local = sigmas * np.stack([np.cos(t)[None] * sigma[:, :1], np.sin(t)[None] * sigma[:, 1:]], axis=-1)
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    rotated = np.stack([cos * local[..., 0] - sin * local[..., 1], sin * local[..., 0] + cos * local[..., 1]], axis=-1)
    return mean[:, None] + rotated


def plot_paths(field, direction, *, plotter=None, method: str = "circular", background=None,
               paths: GaussianPaths | None = None,
               interpolated=None, methods=PATH_METHODS, frame: str | None = "paths", location=None):
    """Draw the Gaussian paths of the triangle a light direction falls in, over the image plane.

    Each Gaussian of the triangle's corners has one colour: its two paths (thick: circular, thin:
    straight), a dot where it starts (its mean in the corner's estimated set), and the outline (1
    sigma) of where it is at ``direction`` under ``method``, more opaque the more it weighs there.

    Args:
        field: a ``HighlightField``.
        direction: the light direction (3,).
        plotter: draw into this ``pyvista.Plotter`` (its active subplot); default a new one.
        method: "circular" or "straight": how the outlines at ``direction`` are interpolated.
        background: an image (H, W[, C]) drawn dimmed under the paths, or None for the relit
            highlights S' at ``direction`` (``relight_field``, Warp's default device).
        paths: the triangle's :class:`GaussianPaths` when already computed.
        interpolated: the (1, 3N) interpolated set at ``direction`` when already computed.
        methods: which paths to draw.
        frame: point the camera at the ``"paths"`` (with a margin), the whole ``"image"``, or leave it
            (None).
        location: ``field.triangulation.locate(direction)`` when already known.

    Returns:
        The plotter; actors ``image``, ``paths circular``, ``paths straight``, ``path starts``,
        ``gaussians now``.
    """
    import pyvista as pv

    method = check_path_method(method)
    direction = unit_direction(direction)
    location = field.triangulation.locate(direction) if location is None else location
    if paths is None or paths.face != int(location.faces):
        paths = gaussian_paths(field, int(location.faces))
    if interpolated is None:
        interpolated = interpolate_sets(field, location.vertices[None], location.barycentric[None], method=method)
    plotter = plotter if plotter is not None else new_plotter()
    if background is None:
        from ..relight.relighter import (
            relight_field,  # loads Warp: only when the image is needed
        )

        background = relight_field(field, direction, method=method).specular
    if frame not in ("paths", "image", None):
        raise InputError(f"frame must be 'paths', 'image' or None, got {frame!r}")
    plot_image(background, plotter=plotter, dim=0.55, frame=frame == "image")
    colours = gaussian_colours(3 * field.capacity)
    for name in PATH_METHODS:
        lines = paths.polylines(name)
        if name not in methods or lines.n_cells == 0:
            hide(plotter, f"paths {name}")
            continue
        lines.cell_data["colour"] = _to_rgb8(colours[paths.gaussian])
        wide = name == "circular"
        put_mesh(plotter, lines, f"paths {name}", scalars="colour", rgb=True, line_width=4.5 if wide else 2.0,
                 opacity=1.0 if wide else 0.75,
                 lighting=False, show_scalar_bar=False)
    starts, first = np.unique(paths.gaussian, return_index=True)
    if len(starts):
        dots = pv.PolyData(to_plane(paths.start[first], lift=2 * _PATH_LIFT))
        dots.point_data["colour"] = _to_rgb8(colours[starts])
        put_mesh(plotter, dots, "path starts", scalars="colour", rgb=True, point_size=10, render_points_as_spheres=True,
                 show_scalar_bar=False)
    else:
        hide(plotter, "path starts")
    outlines = _plot_current_gaussians(plotter, interpolated, colours)
    if frame == "paths":
        _frame_paths(plotter, paths, outlines, field.aspect)
    return plotter


def _plot_current_gaussians(plotter, interpolated, colours: np.ndarray) -> np.ndarray:
    """Outlines of the interpolated set, coloured by Gaussian, opacity following their weights; returns them (G, S,
    2)."""
    import pyvista as pv

    shown = interpolated.active[0] & (interpolated.weight[0] > 0)  # a corner of weight 0 contributes nothing
    active = np.flatnonzero(shown)
    outlines = gaussian_ellipses(interpolated)[shown[interpolated.active[0]]]
    if not len(active):
        hide(plotter, "gaussians now")
        return outlines
    mesh = pv.PolyData(to_plane(outlines, lift=3 * _PATH_LIFT).reshape(-1, 3),
                       lines=_polyline_cells(len(outlines), outlines.shape[1]))
    alpha = np.clip(interpolated.weight[0][active], 0.15, 1.0)
    rgba = np.concatenate([colours[active], alpha[:, None]], axis=1)
    mesh.cell_data["colour"] = np.round(255 * rgba).astype(np.uint8)
    put_mesh(plotter, mesh, "gaussians now", scalars="colour", rgba=True, line_width=2.5, lighting=False,
             show_scalar_bar=False)
    return outlines


# --- helper functions ----------------------------------------------------------------------------


def put_mesh(plotter, mesh, name: str, **options):
    """``plotter.add_mesh(mesh, name=name, **options)``, except that an actor ``name`` this function
    made in the active subplot gets the new geometry in place (no new actor, so no new buffers and
    shaders: what keeps a drag smooth). ``options`` only take effect when the actor is made.

    The mesh that was added is kept here, not read back from the actor: a mesh coloured by
    ``scalars`` reaches its mapper through a filter, and the actor's ``mapper.dataset`` is then a copy.
    """
    renderer = plotter.renderer
    actor = renderer.actors.get(name)
    made = _ADDED_MESHES.get(renderer, {}).get(name)
    if actor is not None and made is not None and made[0] is actor and type(made[1]) is type(mesh):
        made[1].copy_from(mesh, deep=False)
        actor.SetVisibility(True)
        return actor
    actor = plotter.add_mesh(mesh, name=name, pickable=False, **options)
    _ADDED_MESHES.setdefault(renderer, {})[name] = (actor, mesh)
    return actor


def put_text(plotter, text: str, name: str, *, position: str = "upper_left", font_size: int = 9, color=None):
    """Corner text ``name`` of the active subplot, updated in place when it exists."""
    actor = plotter.renderer.actors.get(name)
    corners = {"lower_left": 0, "lower_right": 1, "upper_left": 2, "upper_right": 3}
    if actor is not None and hasattr(actor, "set_text") and position in corners:
        actor.set_text(position, text)
        return actor
    return plotter.add_text(text, position=position, font_size=font_size, color=color, name=name)


def hide(plotter, name: str) -> None:
    """Hide actor ``name`` of the active subplot, if it exists."""
    actor = plotter.renderer.actors.get(name)
    if actor is not None:
        actor.SetVisibility(False)



def _look_at(plotter, bounds) -> None:
    """Parallel projection straight onto the image plane, the region (x0, x1, y0, y1) (scene units)
    filling the view."""
    x0, x1, y0, y1 = (float(v) for v in bounds)
    centre = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0)
    plotter.camera_position = [(centre[0], centre[1], 5.0), centre, (0.0, 1.0, 0.0)]
    plotter.enable_parallel_projection()
    left, bottom, right, top = plotter.renderer.GetViewport()
    width, height = (right - left) * plotter.window_size[0], (top - bottom) * plotter.window_size[1]
    plotter.camera.parallel_scale = 0.52 * max(y1 - y0, (x1 - x0) * height / max(width, 1))


def _frame_paths(plotter, paths: GaussianPaths, outlines: np.ndarray, aspect: float) -> None:
    """Frame the paths and outlines with a margin; at least a quarter of the image height; the whole
    image when there are none."""
    points = np.concatenate([paths.circular.reshape(-1, 2), paths.straight.reshape(-1, 2), outlines.reshape(-1, 2)])
    if not len(points):
        _look_at(plotter, (0.0, aspect, -1.0, 0.0))
        return
    low, high = points.min(axis=0), points.max(axis=0)
    centre, half = 0.5 * (low + high), np.maximum(0.65 * (high - low) + 0.02, 0.125)
    _look_at(plotter, (centre[0] - half[0], centre[0] + half[0], -centre[1] - half[1], -centre[1] + half[1]))


def _polyline_cells(count: int, points_each: int) -> np.ndarray:
    """VTK connectivity of ``count`` polylines of ``points_each`` consecutive points."""
    ids = np.arange(count * points_each, dtype=np.int64).reshape(count, points_each)
    return np.hstack([np.full((count, 1), points_each, dtype=np.int64), ids]).ravel()


def unit_direction(direction) -> np.ndarray:
    """One query direction (3,) as a unit vector; ``InputError`` for anything else."""
    if np.shape(direction) != (3,):
        raise InputError(f"a light direction must be 3 numbers (x, y, z), got shape {np.shape(direction)}")
    return unit_query_directions(direction)[0]


def _unit_rows(values, what: str) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64).reshape(-1, 3)
    norms = np.linalg.norm(values, axis=1, keepdims=True)
    if not np.all(np.isfinite(values)) or np.any(norms == 0):
        raise InputError(f"{what} must be finite, non-zero directions")
    return values / norms


def _to_rgb8(colours: np.ndarray) -> np.ndarray:
    return np.round(255 * np.clip(colours, 0.0, 1.0)).astype(np.uint8)


def check_path_method(method: str) -> str:
    """``method`` if it is one of ``PATH_METHODS``; ``InputError`` otherwise."""
    if method not in PATH_METHODS:
        raise InputError(f"path method must be one of {', '.join(PATH_METHODS)}, got '{method}'")
    return method
