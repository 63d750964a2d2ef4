"""Synthetic reflectance fields: ray-trace a mesh under many distant lights, with ground truth.

The camera sits on +z and looks along -z, so the scene frame is the light-direction frame
(x right, y up the image, z towards the camera; docs/method.md, Units and conventions). Meshes are normalised to a unit
bounding sphere and turned to a per-shape viewing orientation; the camera distance is chosen so the
object fills a given fraction of the frame.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from .. import __version__
from ..kernels import raytrace
from ..kernels.segmentation import LUMINANCE_WEIGHTS
from ..model.errors import InputError
from ..model.lights import LightSet
from ..model.triangulation import SphericalTriangulation
from .settings import Material, RenderSettings
from .shapes import SHAPE_NAMES, TriangleMesh, make_shape

__all__ = ["Material", "RenderSettings", "RenderedImages", "Renderer", "default_material", "render_dataset",
           "renderer_from_meta", "view_rotation"]

CHUNK_MEMORY_SHARE = 0.25
"""Share of the free memory one launch's images may take (the images are copied out and written in
threads beside them)."""


def view_rotation(shape: str) -> np.ndarray:
    """3x3 rotation that shows ``shape`` from a pleasant three-quarter view (identity for mesh files)."""
    shape = shape.lower()
    if shape in ("donut", "torus", "bumpy"):
        return _rotation_x(math.radians(40.0))
    if shape == "teapot":
        return _rotation_x(math.radians(20.0)) @ _rotation_y(math.radians(-25.0))
    return np.eye(3)


def default_material(shape: str) -> Material:
    """The built-in material of each synthetic shape."""
    shape = shape.lower()
    if shape == "teapot":
        return Material(albedo=(0.52, 0.58, 0.68), ambient=0.02, specular=0.5, shininess=150.0)
    if shape == "sphere":
        return Material(albedo=(0.6, 0.6, 0.6), ambient=0.02, specular=0.5, shininess=120.0)
    if shape == "coin":  # worn bronze: a dark base under a GGX lobe
        return Material(albedo=(0.3, 0.2, 0.11), ambient=0.02, specular=0.6, roughness=0.15)
    return Material()


@dataclass
class RenderedImages:
    """Images of one light chunk, linear float32, shape (L, H, W, C) or (L, H, W) when single-channel."""

    start: int
    full: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray


@dataclass
class Renderer:
    """Renders one mesh from one camera under any number of distant lights.

    Args:
        mesh: the object; it is normalised to a unit bounding sphere and turned by ``rotation``.
        material: surface parameters.
        settings: image and sampling settings.
        rotation: 3x3 viewing rotation applied to the normalised mesh.
        device: Warp device ("cpu", "cuda:0", ...); None for Warp's preferred device.
    """

    mesh: TriangleMesh
    material: Material = field(default_factory=Material)
    settings: RenderSettings = field(default_factory=RenderSettings)
    rotation: np.ndarray | None = None
    device: str | None = None

    def __post_init__(self):
        wp.init()
        self.device = str(wp.get_device(self.device))
        scene = self.mesh.normalized()
        if self.rotation is not None:
            scene = scene.transformed(rotation=np.asarray(self.rotation, dtype=np.float64))
        self.scene_mesh = scene
        self.camera_position = _frame_camera(scene.points, self.settings)
        self._points = wp.array(scene.points.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._normals = wp.array(scene.normals.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._mesh = wp.Mesh(
            points=self._points,
            indices=wp.array(scene.faces.astype(np.int32).ravel(), dtype=wp.int32, device=self.device),
        )
        self._tile_share = None
        camera = raytrace.make_camera(self.camera_position, self.settings.fov_y_deg, self.settings.width,
                                      self.settings.height)
        self._samples = raytrace.trace_camera(
            self._mesh,
            self._normals,
            camera,
            grid=self.settings.grid,
            seed=self.settings.seed,
            shadow_bias=self.settings.shadow_bias,
            device=self.device,
        )
        self._params = raytrace.make_shading_parameters(
            shininess=self.material.shininess, samples_per_pixel=self.settings.samples_per_pixel,
            roughness=self.material.roughness,
        )

    @property
    def coverage(self) -> np.ndarray:
        """(H, W) float32: fraction of each pixel covered by the object."""
        return self._samples.coverage_image

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels at least half covered by the object."""
        return self.coverage >= 0.5

    def camera_samples_numpy(self) -> dict[str, np.ndarray]:
        """Host copies of the camera pass: hit_mask (H, W, S) and shading_normal, view_direction,
        shadow_origin (H, W, S, 3), in scene coordinates."""
        names = ("hit_mask", "shading_normal", "view_direction", "shadow_origin")
        return {name: getattr(self._samples, name).numpy() for name in names}

    def _colours(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Albedo and specular colour, (C,) or per covered pixel (P, C) for a texture, and the ambient (C,)."""
        material = self.material
        albedo = np.asarray(material.albedo, dtype=np.float64)
        if material.texture == "tiles":
            albedo = np.stack([albedo, np.asarray(material.tile_albedo, dtype=np.float64)])  # (2, 3)
        if not self.settings.colour:
            albedo = (albedo @ np.asarray(LUMINANCE_WEIGHTS))[..., None]
        channels = albedo.shape[-1]
        ambient = np.full(channels, material.ambient)
        if material.texture == "none":
            return albedo, ambient, np.full(channels, material.specular)
        share = self._second_tile_share()[:, None]  # (P, 1): of each pixel's samples on the second tiles
        specular = material.specular * (1.0 - share + share * material.tile_specular)
        return (1.0 - share) * albedo[0] + share * albedo[1], ambient, np.repeat(specular, channels, axis=1)

    def _second_tile_share(self) -> np.ndarray:
        """(P,) share of each covered pixel's hit samples that land on the second material's tiles: cells
        of ``tile_size`` in the scene's frame, alternating like a checkerboard."""
        if self._tile_share is None:
            rows, cols = self._samples.pixel_rows.numpy(), self._samples.pixel_cols.numpy()
            hits = self._samples.hit_mask.numpy()[rows, cols].astype(np.float64)  # (P, S)
            points = self._samples.shadow_origin.numpy()[rows, cols]  # (P, S, 3)
            cells = np.floor(points / self.material.tile_size).astype(np.int64).sum(axis=-1)
            second = (cells % 2 == 1) * hits
            self._tile_share = second.sum(axis=1) / np.maximum(hits.sum(axis=1), 1.0)
        return self._tile_share

    def shade_on_device(self, directions: np.ndarray) -> tuple[wp.array, wp.array, wp.array]:
        """(full, diffuse, specular) device arrays (L, H, W, C) for ``directions``, all in one batch."""
        albedo, ambient, specular_colour = self._colours()
        return raytrace.shade_and_compose(
            self._mesh,
            self._samples,
            _unit_directions(directions),
            self._params,
            albedo=albedo,
            ambient=ambient,
            specular_colour=specular_colour,
            height=self.settings.height,
            width=self.settings.width,
            device=self.device,
        )

    def render_chunks(self, directions: np.ndarray) -> Iterator[RenderedImages]:
        """Yield the images of ``directions`` ((L, 3) unit vectors) chunk by chunk, in order."""
        directions = _unit_directions(directions)
        chunk = self.light_chunk()
        for start in range(0, len(directions), chunk):
            images = [a.numpy() for a in self.shade_on_device(directions[start : start + chunk])]
            if not self.settings.colour:
                images = [a[..., 0] for a in images]
            yield RenderedImages(start, *images)

    def light_chunk(self) -> int:
        """Lights shaded per launch: ``settings.light_chunk``, fewer where their three images would take
        more than ``CHUNK_MEMORY_SHARE`` of the free device memory (the host's available memory on the
        CPU): 64 lights of 3840x2160 RGB are 19 GB."""
        from ..model.memory import device_free_memory

        free = device_free_memory(wp.get_device(self.device))
        per_light = 3 * 4 * self.settings.width * self.settings.height * (3 if self.settings.colour else 1)
        if free is None:
            return self.settings.light_chunk
        return int(max(1, min(self.settings.light_chunk, CHUNK_MEMORY_SHARE * free // per_light)))

    def render(self, directions: np.ndarray) -> RenderedImages:
        """All images of ``directions`` at once (for tests and small sets; use render_chunks for many)."""
        parts = list(self.render_chunks(directions))
        if not parts:
            shape = (0, self.settings.height, self.settings.width) + ((3,) if self.settings.colour else ())
            empty = np.zeros(shape, np.float32)
            return RenderedImages(0, empty, empty.copy(), empty.copy())
        return RenderedImages(0, *(np.concatenate([getattr(p, k) for p in parts])
                                   for k in ("full", "diffuse", "specular")))

    def describe(self) -> dict:
        """What meta.json records about the scene."""
        return {
            "material": asdict(self.material),
            "settings": asdict(self.settings),
            "camera": {
                "position": [float(x) for x in self.camera_position],
                "look_direction": [0.0, 0.0, -1.0],
                "up": [0.0, 1.0, 0.0],
                "fov_y_deg": self.settings.fov_y_deg,
            },
            "view_rotation": (np.eye(3) if self.rotation is None else np.asarray(self.rotation)).tolist(),
            "mesh": {"name": self.mesh.name, "vertices": self.mesh.vertex_count, "faces": self.mesh.face_count},
            "light_model": "distant light of intensity 1; diffuse = albedo * max(n.l, 0) * visibility + ambient; "
            + ("specular = specular * D_GGX(n.h; roughness) * G_Smith(n.l, n.v) / (4 n.v) * visibility"
               if self.material.roughness > 0 else
               "specular = specular * (shininess + 8) / (8 pi) * max(n.h, 0)^shininess * max(n.l, 0) * visibility")
            + ("; albedo and specular alternate with tile_albedo and specular * tile_specular on a checkerboard of "
               "tile_size cells" if self.material.texture == "tiles" else ""),
            "colour_space": "linear Rec.709" if self.settings.colour else "linear luminance (Rec.709 weights)",
        }


def render_dataset(
    shape: str,
    folder: str | Path,
    *,
    lights: LightSet,
    heldout: LightSet | None | str = "centroids",
    material: Material | None = None,
    settings: RenderSettings | None = None,
    device: str | None = None,
    overwrite: bool = False,
    half: bool = False,
    progress: bool = True,
) -> Path:
    """Render a dataset folder (dataset-format.md) with ground-truth specular and diffuse images.

    Args:
        shape: "donut", "teapot", "sphere", or a mesh file pyvista reads.
        folder: the dataset folder to create; written in a temporary sibling and renamed when complete.
        lights: the reflectance field's light directions.
        heldout: "centroids" (every face centroid of the lights' spherical triangulation), a LightSet,
            or None for no held-out ground truth.
        material, settings: defaults per shape when None.
        device: Warp device; None for Warp's preferred device.
        overwrite: replace an existing non-empty folder.
        half: store EXR as half floats instead of float32.
        progress: show a progress bar on stderr.

    Returns:
        The folder written.
    """
    from tqdm import tqdm

    from ..io.dataset import DatasetWriter

    started = time.perf_counter()
    with tqdm(total=len(lights), unit="light", desc=f"render {shape}: preparing", disable=not progress,
              leave=False) as bar:
        mesh = make_shape(shape)
        shape_name = mesh.name if Path(shape).suffix == "" else str(shape)
        material = material or default_material(shape)
        settings = settings or RenderSettings()
        if heldout == "centroids":
            heldout = LightSet(SphericalTriangulation(lights.directions).centroid_directions())
        elif isinstance(heldout, str):
            raise InputError(f"held-out lights must be 'centroids', a LightSet or None, got {heldout!r}")
        renderer = Renderer(mesh, material=material, settings=settings, rotation=view_rotation(shape), device=device)
        groups = [("lights", lights)] + ([("heldout", heldout)] if heldout is not None and len(heldout) else [])
        bar.total = sum(len(group) for _, group in groups)
        bar.set_description_str(f"render {shape_name}")
        with DatasetWriter(folder, overwrite=overwrite, half=half) as writer:
            for group, light_set in groups:
                for images in renderer.render_chunks(light_set.directions):
                    writer.write_images(group, images.start, images.full, specular=images.specular,
                                        diffuse=images.diffuse)
                    bar.update(len(images.full))
            meta = {
                "generator": f"warp-highlights {__version__} render",
                "shape": shape_name,
                "resolution": [settings.width, settings.height],
                "light_count": len(lights),
                "heldout_count": 0 if heldout is None else len(heldout),
                "heldout_protocol": "triangle centroids of the lights' spherical Delaunay triangulation"
                if heldout is not None
                else None,
                "device": renderer.device,
                "render_seconds": round(time.perf_counter() - started, 3),
                **renderer.describe(),
            }
            writer.finish(lights, heldout, mask=renderer.mask, meta=meta)
            return writer.commit()


def _frame_camera(points: np.ndarray, settings: RenderSettings) -> np.ndarray:
    """Camera position on the +z axis through the projected bounding-box centre, filling ``fill``.

    Every vertex p must satisfy |x - cx| / (d - z) <= fill * aspect * t and |y - cy| / (d - z) <= fill * t
    with t = tan(fov/2); the smallest such distance d has a closed form per vertex.
    """
    t = math.tan(math.radians(settings.fov_y_deg) / 2.0) * settings.fill
    aspect = settings.width / settings.height
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    rel = points - np.array([centre[0], centre[1], 0.0])
    distance = np.max(np.maximum(np.abs(rel[:, 0]) / (aspect * t), np.abs(rel[:, 1]) / t) + rel[:, 2])
    # Never put the camera inside the object's bounding sphere.
    distance = max(distance, points[:, 2].max() + 1e-3)
    return np.array([centre[0], centre[1], distance])


def _unit_directions(directions: np.ndarray) -> np.ndarray:
    """(L, 3) unit vectors; LightSet rejects zero or non-finite ones with one clear line."""
    return LightSet(np.asarray(directions, dtype=np.float64).reshape(-1, 3)).directions


def _rotation_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def renderer_from_meta(meta: dict, *, device: str | None = None) -> Renderer | None:
    """The renderer that made a dataset, rebuilt from its ``meta.json``; None when it cannot be.

    Only datasets of the built-in shapes are rebuilt (a mesh file may have moved or changed); the
    material, image settings and view rotation come from the metadata, so new ground truth at other
    light directions matches the dataset's images.
    """
    try:
        shape = str(meta["shape"]).strip().lower()
        if shape not in (*SHAPE_NAMES, "torus"):
            return None
        material = Material(**meta["material"])
        settings = RenderSettings(**meta["settings"])
        rotation = np.asarray(meta["view_rotation"], dtype=np.float64).reshape(3, 3)
    except (KeyError, TypeError, ValueError, InputError):
        return None
    return Renderer(make_shape(shape), material=material, settings=settings, rotation=rotation, device=device)
