"""The light designer behind ``warp-highlights view``: drag the light on the sphere, see the object relit.

One pyvista window of up to three panels, side by side:

- ``sphere``: the light sphere (:func:`viz.plot_triangulation`) with the current light, its triangle,
  and a handle (a sphere widget) that drags the light over the sphere;
- ``image``: the relit image for the current light, re-rendered by a :class:`Relighter` on every move;
- ``paths``: the Gaussian paths of the current triangle over the image plane (:func:`viz.plot_paths`).

Keys: ``m`` switches circular and straight interpolation, ``h`` the full image and the highlights alone.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_file
from . import viz
from .panels import PANELS, check_panels

__all__ = ["PANELS", "LightDesigner", "check_panels", "default_direction", "describe_direction", "sphere_camera"]

_PANEL_SIZE = (560, 520)  # default pixels per panel (width, height)
_BACKGROUND = "#1f2329"
_TEXT = "#e8eaed"
_HANDLE_RADIUS = 0.06
_TEXT_HEADROOM = 0.1  # image heights left free above the relit image for its three lines of text


def default_direction(triangulation) -> np.ndarray:
    """The first light a view shows: the centroid of the triangle that (0.3, 0.4, 1) falls in, where
    every corner weighs the same, so all three corners' Gaussians are visible."""
    location = triangulation.locate(np.array([0.3, 0.4, 1.0]) / math.sqrt(1.25))
    return triangulation.centroid_directions()[int(location.faces)]


def sphere_camera(direction) -> list[tuple[float, float, float]]:
    """A camera position for the light sphere that shows ``direction`` from its own side, tilted
    towards the default oblique view (so its triangle is seen at an angle, not edge-on)."""
    oblique = np.array([0.45, 0.35, 0.82])
    oblique /= np.linalg.norm(oblique)
    toward = 0.6 * np.asarray(direction, dtype=np.float64) + 0.4 * oblique
    if np.linalg.norm(toward) < 1e-3:
        toward = np.asarray(direction, dtype=np.float64)
    toward /= np.linalg.norm(toward)
    up = (0.0, 1.0, 0.0) if abs(toward[1]) < 0.95 else (0.0, 0.0, -1.0)
    return [tuple(4.7 * toward), (0.0, 0.0, 0.0), up]


def describe_direction(direction) -> str:
    """'(+0.30, +0.40, +0.87)  elevation 60 deg, azimuth 53 deg' for a unit direction."""
    x, y, z = (float(v) for v in direction)
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, z))))
    azimuth = math.degrees(math.atan2(y, x)) % 360.0
    return f"({x:+.2f}, {y:+.2f}, {z:+.2f})  elevation {elevation:.0f} deg, azimuth {azimuth:.0f} deg"


class LightDesigner:
    """An interactive (or off-screen) view of a ``HighlightField``.

    Args:
        field: the fitted field.
        direction: the first light direction (default :func:`default_direction`).
        method: "circular" or "straight".
        device: Warp device the relighting runs on.
        size: relit image (width, height); default the field's size.
        diffuse: the relighter's diffuse mode (``relight.DIFFUSE_MODES``).
        specular_only: show the highlights S' alone instead of the full image.
        panels: which of ``PANELS`` to show, in order.
        window_size: (width, height) of the whole window; default 560 x 520 per panel.
        off_screen: render without a window (for screenshots); no widget then.
        multi_samples: MSAA samples; default 8, but 0 for a window on a software OpenGL, where
            smoothing edges costs several times the drawing (``viz.software_opengl``).

    Attributes:
        plotter: the ``pyvista.Plotter``.
        direction: the current unit light direction (3,).
        image: the image shown for it, linear, (H, W[, C]) float32 (the full image times 1/exposure, or
            the highlights alone; what ``relight`` writes, and the web viewer draws, for that direction).
        timings: milliseconds of the last update: ``relight`` (relit image to the host) and ``scene``
            (meshes refilled and texts set, plus the draw when :meth:`set_direction` draws).
    """

    def __init__(self, field, *, direction=None, method: str = "circular", device=None, size=None,
                 diffuse: str = "auto",
                 specular_only: bool = False, panels=PANELS, window_size=None, off_screen: bool = False,
                 multi_samples: int | None = None):
        from ..relight.relighter import Relighter

        panels = check_panels(panels)
        self.field = field
        self.method = viz.check_path_method(method)
        self.specular_only = bool(specular_only)
        self.panels = panels
        self.relighter = Relighter(field, device=device, size=size, diffuse=diffuse, scale=1.0 / field.exposure)
        if window_size is None:
            window_size = (_PANEL_SIZE[0] * len(panels), _PANEL_SIZE[1])
        if multi_samples is None:
            multi_samples = 0 if not off_screen and viz.software_opengl() else 8
        self.plotter = viz.new_plotter(off_screen=off_screen, window_size=window_size, shape=(1, len(panels)),
                                       multi_samples=multi_samples)
        self.plotter.set_background(_BACKGROUND)
        self.interactive = not off_screen
        self.timings: dict[str, float] = {}
        self._face = None
        self._paths = None
        self._framed_face = None
        self._widget = None
        self.direction = viz.unit_direction(default_direction(field.triangulation) if direction is None else direction)
        self._build()
        self.set_direction(self.direction, render=False)
        if self._panel("sphere"):
            position, _, up = sphere_camera(self.direction)
            viz.look_at_sphere(self.plotter, position, up=up)

    # --- set-up ------------------------------------------------------------------------------------

    def _panel(self, name: str) -> bool:
        """Make panel ``name`` the plotter's active subplot; False when it is not shown."""
        if name not in self.panels:
            return False
        self.plotter.subplot(0, self.panels.index(name))
        return True

    def _build(self) -> None:
        plotter = self.plotter
        if self._panel("sphere"):
            viz.plot_triangulation(self.field, plotter=plotter)
            if self.interactive:
                self._widget = plotter.add_sphere_widget(self._on_handle_moved, center=tuple(self.direction),
                                                         radius=_HANDLE_RADIUS,
                                                         color="#f1c40f", interaction_event="always", pass_widget=False)
        if self._panel("image"):
            viz.plot_image(np.zeros((self.relighter.height, self.relighter.width), dtype=np.float32), plotter=plotter,
                           headroom=_TEXT_HEADROOM)
        if self.interactive:
            plotter.add_key_event("m", self._toggle_method)
            plotter.add_key_event("h", self._toggle_highlights)

    # --- updates -----------------------------------------------------------------------------------

    def set_direction(self, direction, *, render: bool = True) -> dict[str, float]:
        """Move the light to ``direction`` (any non-zero length) and redraw; returns :attr:`timings`."""
        self.direction = viz.unit_direction(direction)
        started = time.perf_counter()
        relit = self.relighter.relight(self.direction, method=self.method, full=not self.specular_only)
        relight_ms = 1e3 * (time.perf_counter() - started)
        self.image = relit.specular / self.field.exposure if self.specular_only or relit.full is None else relit.full
        started = time.perf_counter()
        # One location for the sphere and the paths (float64, on the host). On a shared edge the
        # device's float32 locate may name the neighbouring triangle; the image is the same there.
        location = self.field.triangulation.locate(self.direction)
        self._face = int(location.faces)
        self._draw_sphere(location)
        self._draw_image(relit, relight_ms)
        self._draw_paths(relit, location)
        if render:
            self.plotter.render()
        self.timings = {"relight": relight_ms, "scene": 1e3 * (time.perf_counter() - started)}
        return self.timings

    def _draw_sphere(self, location) -> None:
        if not self._panel("sphere"):
            return
        viz.plot_query(self.field.triangulation, self.direction, plotter=self.plotter, handle=not self.interactive,
                       location=location)
        corners = ", ".join(str(int(v)) for v in location.vertices)
        weights = ", ".join(f"{w:.2f}" for w in location.barycentric)
        lines = [f"light {describe_direction(self.direction)}   (grey arrow: towards the camera)",
                 f"triangle {int(location.faces)}: lights {corners}, weights {weights}"]
        if bool(location.clamped):
            lines.append("outside the dome: relit at the nearest rim point (red)")
        viz.put_text(self.plotter, "\n".join(lines), "sphere text", color=_TEXT)
        if self.interactive:
            viz.put_text(self.plotter, "drag the yellow handle to move the light", "sphere help", position="lower_left",
                         color=_TEXT)

    def _draw_image(self, relit, relight_ms: float) -> None:
        if not self._panel("image"):
            return
        viz.plot_image(self.image, plotter=self.plotter, frame=False)
        what = "highlights S'" if self.specular_only else "full image"
        viz.put_text(self.plotter, f"{self.method} paths, {what}, {self.relighter.width}x{self.relighter.height}\n"
                     f"relit in {relight_ms:.1f} ms on {self.relighter.device}\n{self.field.motion_line()}",
                     "image text", color=_TEXT)
        if self.interactive:
            viz.put_text(self.plotter, "m: circular / straight    h: highlights / full image", "image help",
                         position="lower_left", color=_TEXT)

    def _draw_paths(self, relit, location) -> None:
        if not self._panel("paths"):
            return
        if self._paths is None or self._paths.face != self._face:
            self._paths = viz.gaussian_paths(self.field, self._face)
        # reframe on a new triangle only: keep the user's zoom
        frame = "paths" if self._framed_face != self._face else None
        self._framed_face = self._face
        viz.plot_paths(self.field, self.direction, plotter=self.plotter, method=self.method, background=relit.specular,
                       paths=self._paths, frame=frame, location=location)
        count = len(np.unique(self._paths.gaussian))
        viz.put_text(self.plotter, f"paths of the {count} Gaussians of triangle {self._face}\nthick: circular, thin: "
                                   f"straight, dot: start, "
                     f"outline: now ({self.method}, 1 sigma)", "paths text", color=_TEXT)

    def _on_handle_moved(self, centre) -> None:
        centre = np.asarray(centre, dtype=np.float64)
        norm = float(np.linalg.norm(centre))
        if not (np.isfinite(norm) and norm > 1e-6):
            return
        unit = centre / norm
        if self._widget is not None:
            self._widget.SetCenter(*unit)  # keep the handle on the sphere
        self.set_direction(unit, render=False)  # the widget redraws the window after this callback

    def _toggle_method(self) -> None:
        self.method = "straight" if self.method == "circular" else "circular"
        self.set_direction(self.direction)

    def _toggle_highlights(self) -> None:
        self.specular_only = not self.specular_only
        self.set_direction(self.direction)

    # --- output ------------------------------------------------------------------------------------

    def screenshot(self, path=None) -> np.ndarray:
        """Render and return the window as (H, W, 3) uint8; also write it to the PNG ``path`` (atomically)."""
        self.plotter.render()  # after the first frame pyvista's screenshot returns the last drawn one
        picture = self.plotter.screenshot(None, return_img=True)
        if path is not None:
            from PIL import Image

            path = Path(path)
            with atomic_file(path) as temporary:
                Image.fromarray(picture).save(temporary, format="PNG")
        return picture

    def show(self) -> None:
        """Open the window and hand control to the user until it closes."""
        self.plotter.show(title="warp-highlights view")

    def close(self) -> None:
        self.plotter.close()
