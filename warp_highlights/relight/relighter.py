"""Relight a fitted highlight field for any light directions (docs/method.md, Relighting), batched on a device.

A :class:`Relighter` uploads a field once (its Gaussians, paths, triangulation tables and residual
or diffuse model) and then turns any number of query directions into images with a fixed number of
kernel launches: locate -> interpolate the Gaussian sets -> rasterize S' -> compose I'. By default
I' is residual transfer, I' = R~ + c(x) S': the captured images minus their own fitted highlights,
blended with the query's barycentric weights, plus the moved highlights in the per-pixel highlight
colour; so a captured light gives back its image, and what the Gaussians do not model blends like the
alpha baseline. A learned residual (``fit --residual learned``) is decoded instead for each query at its
located direction (``kernels.neural.QueryDecoder``). Every output is clamped at 0. Large batches run in chunks that
bound the device memory.

Methods:

- ``circular``: Gaussians move along the stored circular paths (the method);
- ``straight``: the same, with positions blended along straight lines (the thesis' ablation);
- ``alpha``: no Gaussians; the barycentric blend of the three corner lights' images (the baseline).
  It needs those images: ``alpha_specular`` (specular luminance per light) for S' and
  ``alpha_images`` (full images per light) for I'.

Units: images in the field's radiance units (the fit's exposure applied; 1 = display white) times
``scale``; Gaussian coordinates in image heights, so any output size with the field's aspect ratio
works.

This module holds one thing: the batched relighter (``Relighter``) and the tables it uploads.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..io.resample import resample_image
from ..kernels import interpolation as kernels
from ..kernels import upsample
from ..kernels.chunks import map_chunks, problem_chunks
from ..kernels.neural import QueryDecoder, bound_decoded
from ..kernels.raster import Rasterizer
from ..model.config import RasterSettings
from ..model.errors import InputError
from ..model.gaussians import GaussianBatch, GaussianParams
from ..model.threads import core_count
from ..model.triangulation import unit_query_directions
from ..residual.cpu_training import CpuQueryDecoder
from ..residual.decode import decoded_blocks
from ..residual.device import (
    RESIDUAL_DECODES,
    LowRankArrays,
    decode_on_load,
    decode_residual,
    decodes_on_device,
    rbf_rows,
)
from .interpolation import edge_rows

__all__ = [
    "DIFFUSE_MODES",
    "RELIGHT_METHODS",
    "Relighter",
    "RelitImages",
    "alpha_inputs",
    "check_same_lights",
    "default_queries",
    "face_edge_rows",
    "relight_bytes",
    "relight_field",
]

RELIGHT_METHODS = ("circular", "straight", "alpha")
DIFFUSE_MODES = ("auto", "residual", "lambert", "images", "none")
"""What I' adds S' to. ``residual``: residual transfer (the field's residual model); ``lambert``: the
per-pixel Lambertian model; ``images``: the blended diffuse images; ``none``: nothing. ``auto``: the
first of residual, images, lambert that the field stores."""

_DECODE_BLOCK = 16  # lights decoded, resampled and uploaded at a time: the host holds one block

# Bytes of output images (specular + full) one launch may hold; larger batches run in chunks.
_CHUNK_BYTES = 256 * 2**20
_INSIDE_TOLERANCE = 1e-12  # as SphericalTriangulation.locate
_FLOAT16_MAX = float(np.finfo(np.float16).max)
_THREADED_PIXELS = 1 << 18  # output pixels from which a CPU compose is split over the cores (a 512 x 512 image)
_KEPT_BUFFER_SETS = 3  # query counts whose device buffers are kept (a full chunk, the last chunk, one query)


@dataclass(frozen=True, eq=False)
class RelitImages:
    """Images of Q queries, NumPy float32.

    Attributes:
        specular: (Q, H, W) S', the specular luminance in the field's units (the fit's exposure
            applied; ``scale`` is not).
        full: (Q, H, W, C) I' = scale (B + colour S'), B the blended residual (or the diffuse model the
            relighter was asked for), or None when not asked for.
        faces: (Q,) face of the triangulation each query fell in.
        barycentric: (Q, 3) weights of that face's corners (``triangulation.faces`` order).
        clamped: (Q,) bool, True where the query lay outside a dome and was moved onto its rim.
    """

    specular: np.ndarray
    full: np.ndarray | None
    faces: np.ndarray
    barycentric: np.ndarray
    clamped: np.ndarray


class _DeviceQueries:
    """Device buffers of one chunk of queries: directions, location, interpolated sets, images."""

    def __init__(self, count: int, capacity: int, height: int, width: int, channels: int, device):
        self.count = count
        self.directions = wp.empty(count, dtype=wp.vec3d, device=device)
        self.faces = wp.empty(count, dtype=wp.int32, device=device)
        # each face slice's best (deepest_faces)
        self.depths = wp.empty((count, kernels.FACE_SLICES), dtype=wp.float64, device=device)
        self.best_faces = wp.empty((count, kernels.FACE_SLICES), dtype=wp.int32, device=device)
        self.weights = wp.empty(count, dtype=wp.vec3, device=device)
        self.located = wp.empty(count, dtype=wp.vec3, device=device)
        self.unit = wp.empty(count, dtype=wp.vec3, device=device)
        self.clamped = wp.empty(count, dtype=wp.int32, device=device)
        self.sets = GaussianBatch(count, 3 * capacity, device=device, requires_grad=False)
        self.specular = wp.empty((count, height, width), dtype=float, device=device)
        self.full = wp.empty((count, height * width, channels), dtype=float, device=device)
        self.coefficients: dict[str, wp.array] = {}  # per-query blended low-rank weights, by stack
        self.decoded = None  # (count, pixels, 3) float16: a learned residual decoded for these queries (first use)
        # at the field's size, for an output larger than the field (made on first use): each query's residual term
        # (count, pixels, C) and the alpha method's specular blend (count, pixels)
        self.source = self.source_specular = None
        self.staging_specular = self.staging_full = None  # pinned host copies (CUDA), made on first use


class Relighter:
    """Renders a ``HighlightField`` for batches of light directions on one device.

    Args:
        field: the fitted field.
        device: Warp device (default: Warp's default device).
        size: output (width, height) in pixels; default the field's size. Must keep the field's aspect
            ratio (to within a pixel). A smaller output gets the field's arrays resampled to it once
            (area average); a larger one reads them at the field's size, by bilinear interpolation at
            every output pixel (``kernels.upsample``), while the highlights are drawn at the output size.
        diffuse: one of ``DIFFUSE_MODES``.
        specular_colour: colour of the light per channel, multiplying the highlights c(x) S' (white
            by default; c(x) is the field's per-pixel highlight colour, white when it has none).
        scale: factor applied to I' (e.g. 1 / exposure to return to the input's units).
        alpha_specular: (n, H, W) specular luminance per light, for the ``alpha`` method's S'.
        alpha_images: (n, H, W[, C]) full images per light, for the ``alpha`` method's I' (field
            units, like ``alpha_specular``: ``scale`` applies to them too).
        raster: rasterizer settings (default: the field's).
        max_batch: queries per launch (default: as many as fit in about 256 MB of images; never more than
            one rasterizer launch draws, ``Rasterizer.problems_per_launch``).
        residual_decode: how a low-rank residual is decoded (``RESIDUAL_DECODES``): "query" in every
            query's compose pass (k multiply-adds per pixel and plane, nothing more held), "load" once
            here into n float16 residual images that queries blend like the alpha blend (3 per pixel
            and channel; n x pixels x channels x 2 bytes held on the device), "auto" (default): "load"
            when those images take at most ``DECODED_RESIDUAL_BYTES`` and save work, else "query".
        graphs: relight a single direction (``relight(direction)``) as one captured CUDA graph launch,
            with its input and results through page-locked memory (default: on CUDA, for fields
            without a learned residual, whose decoder's buffers grow with the batch).
    """

    def __init__(
        self,
        field,
        *,
        device=None,
        size: tuple[int, int] | None = None,
        diffuse: str = "auto",
        specular_colour=(1.0, 1.0, 1.0),
        scale: float = 1.0,
        alpha_specular: np.ndarray | None = None,
        alpha_images: np.ndarray | None = None,
        raster: RasterSettings | None = None,
        max_batch: int | None = None,
        residual_decode: str = "auto",
        graphs: bool | None = None,
    ):
        if diffuse not in DIFFUSE_MODES:
            raise InputError(f"diffuse must be one of {', '.join(DIFFUSE_MODES)}, got '{diffuse}'")
        if residual_decode not in RESIDUAL_DECODES:
            raise InputError(f"residual_decode must be one of {', '.join(RESIDUAL_DECODES)}, got '{residual_decode}'")
        self.field = field
        self.device = wp.get_device(device)
        self.width, self.height = _output_size(field, size)
        # the size the field's per-pixel arrays are held at: the output's, or the field's for a larger output
        self.source_width, self.source_height = _source_size(field, self.width, self.height)
        self.upsampled = (self.source_width, self.source_height) != (self.width, self.height)
        settings = field.fit_settings()
        # narrower Gaussians, unresolved by the field's pixels, are widened when drawn larger (normalised units)
        self._least_sigma = (raster or settings.raster).upsampled_min_sigma_px / field.height
        self.straight_below = float(settings.paths.straight_below)
        threads = 1 if self.device.is_cuda else core_count()  # a CPU launch runs on one thread: large images split
        self._source_raster = None  # the field's size, for a decoder that sees the Gaussians of a larger output
        self.raster = Rasterizer(self.height, self.width, settings=raster or settings.raster, device=self.device,
                                 threads=threads)
        self.diffuse, self._residual_images = _diffuse_mode(field, diffuse)
        self.channels = _field_channels(field)
        if (self.diffuse == kernels.DIFFUSE_LOWRANK
            # decided by the output's pixels, as when every array was resampled to it: the same images whatever size
            and decode_on_load(field.residual, self.width * self.height, residual_decode, self.device)):
            self.diffuse, self._residual_images = kernels.DIFFUSE_BLEND, True
        colour = np.asarray(specular_colour, dtype=np.float64).reshape(-1)
        if colour.size not in (1, 3) or not np.all(np.isfinite(colour)) or np.any(colour < 0):
            raise InputError(
                f"specular colour must be 1 or 3 finite numbers >= 0, got {np.asarray(specular_colour).tolist()}")
        colour = np.broadcast_to(colour, (3,))
        self.specular_colour = wp.vec3(*colour.astype(np.float32))
        if not (np.isfinite(scale) and scale > 0):
            raise InputError(f"scale must be a positive number, got {scale}")
        self.scale = float(scale)
        self._upload_field()
        self._upload_diffuse()
        self._alpha_specular = self._upload_stack(alpha_specular, "alpha specular", channels=False)
        self._alpha_images = self._upload_stack(alpha_images, "alpha images", channels=True)
        if self._alpha_images is not None and self._alpha_images.shape[2] != self.channels:
            if field.diffuse is not None or field.residual is not None:
                raise InputError(
                    f"alpha images have {self._alpha_images.shape[2]} channels, the field's images {self.channels}")
            self.channels = self._alpha_images.shape[2]
            self._upload_colour()
        default_batch = default_queries(field, self.width, self.height)
        self.max_batch = int(max_batch) if max_batch is not None else default_batch
        if self.max_batch < 1:
            raise InputError(f"max_batch must be >= 1, got {max_batch}")
        self.max_batch = min(self.max_batch, self.raster.problems_per_launch)  # one launch indexes below 2^31 pixels
        self._buffers: dict[int, _DeviceQueries] = {}
        self.graphs = self.device.is_cuda and self._learned is None if graphs is None else bool(graphs)
        if self.graphs and not self.device.is_cuda:
            raise InputError("CUDA graphs need a CUDA device; relight on the CPU with graphs=False")
        if self.graphs and self._learned is not None:
            raise InputError(
                "a learned residual's decoder grows its buffers with the batch: relight it with graphs=False")
        self._graphs: dict[tuple[str, bool], _SingleQuery] = {}

    # --- set-up ------------------------------------------------------------------------------------

    def _upload_field(self) -> None:
        field, device = self.field, self.device
        self.capacity = field.capacity
        self._estimated = GaussianBatch.from_numpy(field.estimated, device=device, requires_grad=False)
        self._moving = wp.array(field.moving_mask.astype(np.int32), dtype=wp.int32, device=device)
        self._retargeted = GaussianBatch.from_numpy(field.retargeted, device=device, requires_grad=False)
        self._path_delta = wp.array(field.path_delta.astype(np.float32), dtype=float, device=device)
        tri = field.triangulation
        self._face_vertices = wp.array(tri.faces.astype(np.int32), dtype=wp.int32, device=device)
        self._face_edges = wp.array(face_edge_rows(tri.faces, field.directed_edges, field.light_count), dtype=wp.int32,
                                    device=device)
        tables = tri._locate_tables
        vec3d = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.vec3d, device=device)
        self._edge_normals = vec3d(tables.edge_normals.transpose(1, 0, 2))
        self._inverses = wp.array(tables.inverses.astype(np.float64), dtype=wp.mat33d, device=device)
        rim = rim_tables(tri)
        self._is_dome = int(rim is not None)
        if rim is not None:
            *rims, faces, opposite = rim
        else:  # a closed sphere: one dummy rim edge keeps the launch's arrays non-empty
            rims = (np.zeros((1, 3)),) * 5
            faces, opposite = np.zeros(1), np.zeros(1)
        self._rims = [vec3d(r) for r in rims] + [
            wp.array(np.asarray(faces, dtype=np.int32), dtype=wp.int32, device=device),
            wp.array(np.asarray(opposite, dtype=np.int32), dtype=wp.int32, device=device),
        ]

    def _upload_diffuse(self) -> None:
        device, model, residual = self.device, self.field.diffuse, self.field.residual
        lambert = np.zeros((1, 1, 4), dtype=np.float32)
        images = np.zeros((1, 1, 1), dtype=np.float16)
        self._stacks = {name: LowRankArrays.empty(device, planes) for name, planes in (("luminance", 1), ("chroma", 2))}
        residual_scale = np.ones(1, np.float32)
        self._learned = self._learned_bounds = None
        self._rbf = None  # a radial basis residual's rows and lights (``rbf_rows``)
        width, height = self.source_width, self.source_height
        if self.diffuse == kernels.DIFFUSE_DECODED:
            learned = residual.learned
            codes = resample_image(learned.codes.astype(np.float32), width, height).reshape(-1, learned.codes.shape[2])
            if learned.bounds is not None:  # resampled as the codes are
                bounds = np.stack([resample_image(plane.astype(np.float32), width, height).reshape(-1, 3)
                                   for plane in learned.bounds])
                self._learned_bounds = wp.array(bounds.astype(np.float16), dtype=wp.float16, device=device)
            if device.is_cuda:  # the fitted decoder's tile kernels, a smaller decoder embedded in its shape
                self._learned = QueryDecoder(codes, learned.standard_weights, learned.unit, device=device)
            else:  # NumPy's threads on the CPU, at the decoder's own size
                self._learned = CpuQueryDecoder(codes, learned.weights, learned.unit, device=device)
        if self.diffuse == kernels.DIFFUSE_LAMBERT:
            planes = resample_image(model.lambert.reshape(model.height, model.width, -1), width, height)
            lambert = planes.reshape(height * width, model.channel_count, 4)
        elif self.diffuse == kernels.DIFFUSE_BLEND:
            images = self._upload_images(residual if self._residual_images else model)
        elif self.diffuse == kernels.DIFFUSE_LOWRANK:
            self._stacks["luminance"] = LowRankArrays.upload(residual.luminance, width, height, device)
            if residual.scale is not None:
                residual_scale = resample_image(residual.scale, width, height).reshape(-1)
            if residual.chroma is not None:
                self._stacks["chroma"] = LowRankArrays.upload(residual.chroma, width, height, device)
            if residual.rbf_sigma is not None:
                self._rbf = rbf_rows(residual, self.field.triangulation.directions, device)
        self._lambert = wp.array(np.ascontiguousarray(lambert), dtype=wp.vec4, device=device)
        self._diffuse_images = (images if isinstance(images, wp.array)
                                else wp.array(images, dtype=wp.float16, device=device))
        self._residual_scale = wp.array(np.ascontiguousarray(residual_scale, dtype=np.float32), dtype=float,
                                        device=device)
        self._unit_scale = wp.ones(1, dtype=float, device=device)
        self._upload_colour()

    def _upload_images(self, source) -> wp.array:
        """The per-light images of ``source`` (a residual, decoded here, or a diffuse model's images) at the
        size the field's arrays are held at (``source_width`` x ``source_height``) on the device, (n, pixels,
        C) float16: a low-rank residual decoded on a CUDA device where it can be (``decode_residual``), else
        made on the host ``_DECODE_BLOCK`` lights at a time."""
        width, height = self.source_width, self.source_height
        if (source is self.field.residual and self.device.is_cuda
            and decodes_on_device(source, width, height, self.device)):
            return decode_residual(source, self.device)
        if source is self.field.residual:
            blocks, count, channels = decoded_blocks(source, block=_DECODE_BLOCK), source.light_count, source.channels
        else:
            images = source.images
            blocks = ((start, images[start : start + _DECODE_BLOCK]) for start in range(0, len(images), _DECODE_BLOCK))
            count, channels = len(images), images.shape[3]
        pixels = height * width
        out = wp.empty((count, pixels, channels), dtype=wp.float16, device=self.device)
        for start, block in blocks:
            shrunk = (np.stack([resample_image(image, width, height) for image in block])
                      if block.shape[1:3] != (height, width) else block)
            out[start : start + len(block)].assign(np.ascontiguousarray(shrunk, dtype=np.float16).reshape(len(block),
                                                                                                          pixels,
                                                                                                          channels))
        return out

    def _upload_colour(self) -> None:
        """c(x) per pixel (at ``source_width`` x ``source_height``) and channel, (pixels, C) float32, or one
        white row."""
        residual = self.field.residual
        colour = np.ones((1, self.channels), dtype=np.float32)
        if residual is not None and residual.highlight_colour is not None and residual.channels == self.channels:
            colour = resample_image(residual.highlight_colour, self.source_width,
                                    self.source_height).reshape(-1, self.channels)
            colour = np.maximum(colour, 0.0)
        self._pixel_colour = wp.array(np.ascontiguousarray(colour, dtype=np.float32), dtype=float, device=self.device)

    def _upload_stack(self, stack, what: str, *, channels: bool):
        if stack is None:
            return None
        stack = np.asarray(stack, dtype=np.float32)
        n = self.field.light_count
        if channels and stack.ndim == 3:
            stack = stack[..., None]
        expected = 4 if channels else 3
        if stack.ndim != expected or len(stack) != n:
            raise InputError(f"{what} must have shape (n={n}, H, W{', C' if channels else ''}), got {stack.shape}")
        if not np.all(np.isfinite(stack)):
            raise InputError(f"{what} contain non-finite values")
        width, height = self.source_width, self.source_height
        if stack.shape[1:3] != (height, width):
            stack = np.stack([resample_image(image, width, height) for image in stack])
        if channels:
            if np.abs(stack).max() > _FLOAT16_MAX:
                raise InputError(
                    f"{what} exceed the float16 range ({_FLOAT16_MAX:g}) they are kept in; scale them down")
            return wp.array(stack.reshape(n, height * width, -1).astype(np.float16), dtype=wp.float16,
                            device=self.device)
        return wp.array(stack.reshape(n, -1), dtype=float, device=self.device)

    def _chunk_buffers(self, count: int) -> _DeviceQueries:
        """Buffers for ``count`` queries, kept per count (a few), so mixing single and batch queries reuses them."""
        buffers = self._buffers.pop(count, None)
        if buffers is None:
            buffers = _DeviceQueries(count, self.capacity, self.height, self.width, self.channels, self.device)
        self._buffers[count] = buffers  # most recently used last
        while len(self._buffers) > _KEPT_BUFFER_SETS:
            self._buffers.pop(next(iter(self._buffers)))
        return buffers

    # --- the pipeline ------------------------------------------------------------------------------

    def launch(self, directions: np.ndarray, *, method: str = "circular", full: bool = True,
               render: bool = True) -> _DeviceQueries:
        """Run the kernels for at most ``max_batch`` directions; the results stay on the device.

        Returns the chunk's buffers: ``specular`` (Q, H, W) unless not ``render``, ``full``
        (Q, H*W, C) when ``full``, ``faces``, ``weights``, ``clamped``, ``sets`` (the interpolated
        Gaussians). They are reused by the next call with the same count.
        """
        method = _checked_method(method)
        directions = unit_query_directions(directions)
        if len(directions) > self.max_batch:
            raise InputError(
                f"launch takes at most max_batch={self.max_batch} queries, got {len(directions)}; use relight()")
        buffers = self._chunk_buffers(len(directions))
        buffers.directions.assign(directions)
        buffers.unit.assign(directions.astype(np.float32))
        return self._run(buffers, self.raster, method=method, full=full, render=render)

    def _run(self, buffers: _DeviceQueries, raster: Rasterizer, *, method: str, full: bool,
             render: bool = True) -> _DeviceQueries:
        """The kernels of ``launch`` on buffers whose directions are set: device work only (capturable)."""
        self._locate(buffers)
        if method == "alpha":
            self._alpha(buffers, full=full)
            return buffers
        wp.launch(
            kernels.interpolate_gaussians,
            dim=(buffers.count, 3, self.capacity),
            inputs=[self._estimated.arrays, self._retargeted.arrays, self._path_delta, self._moving,
                    self._face_vertices, self._face_edges,
                    buffers.faces, buffers.weights, int(method == "circular"), self.straight_below],
            outputs=[buffers.sets.arrays],
            device=self.device,
        )
        if not render:
            return buffers
        if self.upsampled and self._least_sigma > 0:
            wp.launch(upsample.widen_narrow_gaussians, dim=(buffers.count, 3 * self.capacity),
                      inputs=[buffers.sets.arrays, self._least_sigma, raster.settings.sigma_eps], device=self.device)
        raster.render(buffers.sets, out=buffers.specular)
        if full:
            images = self._diffuse_images
            if self._learned is not None:
                if buffers.decoded is None:
                    buffers.decoded = wp.empty((buffers.count, self._learned.pixels, 3), dtype=wp.float16,
                                               device=self.device)
                # at the direction as located: clamped to a dome's rim
                seen = self._seen_highlights(buffers, raster) if self._learned.sees_highlights else None
                self._learned.decode(buffers.located, buffers.decoded, seen)
                if self._learned_bounds is not None:
                    wp.launch(bound_decoded, dim=buffers.decoded.shape[:2], inputs=[self._learned_bounds],
                              outputs=[buffers.decoded], device=self.device)
                images = buffers.decoded
            # a decoder that sees the Gaussians gives the whole image: they are its inputs, not added to it
            sees = self._learned is not None and self._learned.sees_highlights
            self._compose(buffers, buffers.specular, add_specular=not sees, mode=self.diffuse, images=images)
        return buffers

    def _seen_highlights(self, buffers: _DeviceQueries, raster: Rasterizer) -> wp.array:
        """(Q, pixels) the moved Gaussians' luminance (field units) at the field's size, where the learned residual
        is decoded: the output's render, or for a larger output one more render at the field's size."""
        pixels = self.source_width * self.source_height
        if not self.upsampled:
            return buffers.specular.reshape((buffers.count, pixels))
        if buffers.source_specular is None:
            buffers.source_specular = wp.empty((buffers.count, pixels), dtype=float, device=self.device)
        if self._source_raster is None:
            self._source_raster = Rasterizer(self.source_height, self.source_width, settings=raster.settings,
                                             device=self.device, threads=1 if self.device.is_cuda else core_count())
        self._source_raster.render(buffers.sets,
                                   out=buffers.source_specular.reshape((buffers.count, self.source_height,
                                                                        self.source_width)))
        return buffers.source_specular

    def _locate(self, buffers: _DeviceQueries) -> None:
        wp.launch(kernels.deepest_faces, dim=buffers.depths.shape, inputs=[buffers.directions, self._edge_normals],
                  outputs=[buffers.depths, buffers.best_faces], device=self.device)
        wp.launch(
            kernels.locate_directions,
            dim=buffers.count,
            inputs=[buffers.directions, buffers.depths, buffers.best_faces, self._inverses, *self._rims, self._is_dome,
                    _INSIDE_TOLERANCE],
            outputs=[buffers.faces, buffers.weights, buffers.located, buffers.clamped],
            device=self.device,
        )

    def _alpha(self, buffers: _DeviceQueries, *, full: bool) -> None:
        if self._alpha_specular is None:
            raise InputError("the alpha method needs the specular images of the lights (alpha_specular; on the command "
                             "line, --dataset)")
        blended = buffers.specular.reshape((buffers.count, self.height * self.width))
        if self.upsampled:
            if buffers.source_specular is None:
                buffers.source_specular = wp.empty((buffers.count, self.source_width * self.source_height),
                                                   dtype=float, device=self.device)
            blended = buffers.source_specular
        wp.launch(kernels.blend_images, dim=blended.shape,
                  inputs=[self._alpha_specular, self._face_vertices, buffers.faces, buffers.weights], outputs=[blended],
                  device=self.device)
        if self.upsampled:
            per_thread = self._pixels_per_thread()
            pixels = self.height * self.width

            def part(chunk: slice, stop=None) -> None:
                wp.launch(upsample.upsample_images, dim=(buffers.count, chunk.stop - chunk.start),
                          inputs=[blended, self.width, self.source_width, self.source_height, per_thread, chunk.start],
                          outputs=[buffers.specular.reshape((buffers.count, pixels))], device=self.device)

            map_chunks(part, self._parts((pixels + per_thread - 1) // per_thread))
        if full:
            if self._alpha_images is None:
                raise InputError("the alpha method's full images need the images of the lights (alpha_images; on the "
                                 "command line, --dataset)")
            self._compose(buffers, buffers.specular, add_specular=False, mode=kernels.DIFFUSE_BLEND,
                          images=self._alpha_images)

    def _compose(self, buffers: _DeviceQueries, specular: wp.array, *, add_specular: bool, mode: int,
                 images: wp.array) -> None:
        pixels = self.height * self.width
        coefficients = []
        for name in ("luminance", "chroma"):
            stack = self._stacks[name]
            out = buffers.coefficients.get(name)
            if out is None or out.shape != (buffers.count, stack.rank + 1):
                out = buffers.coefficients[name] = wp.zeros((buffers.count, stack.rank + 1), dtype=float,
                                                            device=self.device)
            if mode == kernels.DIFFUSE_LOWRANK and stack.uploaded and self._rbf is not None:
                wp.launch(kernels.blend_rbf, dim=(buffers.count, stack.rank + 1),
                          inputs=[self._rbf.rows[name], self._rbf.lights, self._rbf.inverse_sigma_squared,
                                  buffers.located], outputs=[out], device=self.device)
            elif mode == kernels.DIFFUSE_LOWRANK and stack.uploaded:
                wp.launch(kernels.blend_images, dim=(buffers.count, stack.rank + 1),
                          inputs=[stack.weights, self._face_vertices, buffers.faces, buffers.weights], outputs=[out],
                          device=self.device)
            coefficients.append(out)
        lum, chroma = self._stacks["luminance"], self._stacks["chroma"]
        per_thread = self._pixels_per_thread()
        if self.upsampled:
            self._compose_upsampled(buffers, specular, add_specular=add_specular, mode=mode, images=images,
                                    coefficients=coefficients, per_thread=per_thread)
            return
        wp.launch(
            kernels.compose_images,
            dim=(buffers.count, (pixels + per_thread - 1) // per_thread),
            inputs=[specular.reshape((buffers.count, pixels)), self.specular_colour, self._pixel_colour,
                    int(add_specular), mode, self._lambert, images,
                    lum.mean, lum.basis, coefficients[0], chroma.mean, chroma.basis, coefficients[1],
                    self._residual_scale,
                    self._face_vertices, buffers.faces, buffers.weights, buffers.unit, self.scale, per_thread],
            outputs=[buffers.full],
            device=self.device,
        )

    def _compose_upsampled(self, buffers: _DeviceQueries, specular: wp.array, *, add_specular: bool, mode: int,
                           images: wp.array, coefficients: list, per_thread: int) -> None:
        """``_compose`` for an output larger than the field: each query's residual term at the field's
        size, then read by bilinear interpolation at every output pixel (``kernels.upsample``)."""
        source_pixels = self.source_width * self.source_height
        if buffers.source is None:
            buffers.source = wp.zeros((buffers.count, source_pixels, self.channels), dtype=float, device=self.device)
        lum, chroma = self._stacks["luminance"], self._stacks["chroma"]
        if mode in (kernels.DIFFUSE_BLEND, kernels.DIFFUSE_LOWRANK, kernels.DIFFUSE_DECODED):
            wp.launch(upsample.residual_at_source, dim=(buffers.count, source_pixels),
                      inputs=[mode, images, lum.mean, lum.basis, coefficients[0], chroma.mean, chroma.basis,
                              coefficients[1], self._unit_scale, self._face_vertices, buffers.faces, buffers.weights],
                      outputs=[buffers.source], device=self.device)
        pixels = self.height * self.width

        def part(chunk: slice, stop=None) -> None:
            wp.launch(
                upsample.compose_upsampled,
                dim=(buffers.count, chunk.stop - chunk.start),
                inputs=[specular.reshape((buffers.count, pixels)), self.specular_colour, self._pixel_colour,
                        int(add_specular), mode, self._lambert, buffers.source, self._residual_scale, buffers.unit,
                        self.width, self.source_width, self.source_height, self.scale, per_thread, chunk.start],
                outputs=[buffers.full],
                device=self.device,
            )

        map_chunks(part, self._parts((pixels + per_thread - 1) // per_thread))

    def _parts(self, count: int) -> list[slice]:
        """``range(count)`` of a compose launch's threads in one part on CUDA, else one part per CPU core
        (Warp runs a CPU launch on one thread) where the image is large enough to pay for the threads."""
        threads = 1 if self.device.is_cuda or self.height * self.width < _THREADED_PIXELS else core_count()
        return problem_chunks(count, self.device, threads)

    def _pixels_per_thread(self) -> int:
        """Output pixels a compose thread does: 1 on CUDA; a row on the CPU, where a thread's start costs about
        as much as a pixel."""
        return 1 if self.device.is_cuda else self.width

    # --- host-facing API ---------------------------------------------------------------------------

    def relight(self, directions, *, method: str = "circular", full: bool = True, progress=None) -> RelitImages:
        """Images for (Q, 3) or (3,) light directions (any non-zero length), as new host arrays (one
        direction on CUDA with graphs: arrays on page-locked memory that no later query writes while
        any view of them is alive).

        Args:
            directions: towards the lights, camera space (docs/method.md, Units and conventions).
            method: one of ``RELIGHT_METHODS``.
            full: also compose I' (else ``RelitImages.full`` is None).
            progress: optional callable(count_done) called after each chunk.
        """
        single = np.ndim(directions) == 1
        queries = unit_query_directions(directions)
        count = len(queries)
        if single and self.graphs:
            return self._single_query(queries[0], _checked_method(method), bool(full))
        specular = np.empty((count, self.height, self.width), dtype=np.float32)
        images = np.empty((count, self.height, self.width, self.channels), dtype=np.float32) if full else None
        faces = np.empty(count, dtype=np.int32)
        barycentric = np.empty((count, 3), dtype=np.float64)
        clamped = np.empty(count, dtype=bool)
        for start in range(0, count, self.max_batch):
            stop = min(start + self.max_batch, count)
            chunk = self.launch(queries[start:stop], method=method, full=full)
            _copy_to_host(chunk, specular[start:stop], None if images is None else images[start:stop])
            faces[start:stop] = chunk.faces.numpy()
            barycentric[start:stop] = chunk.weights.numpy()
            clamped[start:stop] = chunk.clamped.numpy() != 0
            if progress is not None:
                progress(stop)
        result = RelitImages(specular, images, faces, barycentric, clamped)
        if single:
            result = RelitImages(specular[0], None if images is None else images[0], faces[0], barycentric[0],
                                 clamped[0])
        return result

    def _single_query(self, direction: np.ndarray, method: str, full: bool) -> RelitImages:
        """One query as one graph launch: the direction in and the images out through page-locked
        memory, everything between on the device. The graphs are captured on the first query of a
        method and kept for one method at a time, so their page-locked buffers stay within
        ``RESULT_SLOT_BYTES`` (results already handed out keep their own buffers)."""
        query = self._graphs.get((method, full))
        if query is None:
            self._graphs.clear()
            query = self._graphs[(method, full)] = _SingleQuery(self, method, full)
        return query.run(direction)

    def iter_relight(self, directions, *, method: str = "circular", full: bool = True):
        """Yield ``RelitImages`` chunk by chunk (at most ``max_batch`` queries each, new arrays), for streaming."""
        queries = unit_query_directions(directions)
        for start in range(0, len(queries), self.max_batch):
            yield self.relight(queries[start : start + self.max_batch], method=method, full=full)

    def interpolated_sets(self, directions, *, method: str = "circular") -> GaussianParams:
        """The interpolated Gaussian sets (Q, 3N) of the queries, float64 host copy (circular or straight)."""
        if _checked_method(method) == "alpha":
            raise InputError("the alpha method has no Gaussian sets; use circular or straight")
        queries = unit_query_directions(directions)
        parts = []
        for start in range(0, len(queries), self.max_batch):
            parts.append(self.launch(queries[start : start + self.max_batch], method=method, full=False,
                                     render=False).sets.numpy())
        return GaussianParams.concatenate(parts, axis=0)


def relight_field(
    field, directions, *, method: str = "circular", device=None, size: tuple[int, int] | None = None,
    diffuse: str = "auto"
) -> RelitImages:
    """Images of a ``HighlightField`` for light direction(s): S' in the field's units, I' (the blended
    residual plus the highlights, or ``diffuse``'s model plus them) in the input's (divided by the fit's
    ``exposure``), NumPy float32.

    A shortcut for ``Relighter(field, device=..., size=..., diffuse=..., scale=1 / field.exposure)
    .relight(directions, method=...)``; the relighter (the field's arrays on the device) is kept with
    the field for the next call with the same options (not thread-safe: use one ``Relighter`` per
    thread). Build a ``Relighter`` yourself for the alpha method or batch control.
    """
    key = (str(wp.get_device(device)), None if size is None else tuple(size), diffuse)
    cache = vars(field).setdefault("_relighters", {})
    if key not in cache:
        cache.clear()
        cache[key] = Relighter(field, device=device, size=size, diffuse=diffuse, scale=1.0 / field.exposure)
    return cache[key].relight(directions, method=method)


def rim_tables(triangulation) -> tuple[np.ndarray, ...] | None:
    """A dome's rim edges as the locate kernel (and the web viewer) take them: (R, 3) float64 start,
    end, great-circle normal, along (normal x start) and back (end x normal), then (R,) face and the
    face's corner opposite the edge; None for a closed sphere."""
    tables = triangulation._locate_tables
    if not (triangulation.is_dome and len(tables.rim_face)):
        return None
    along = np.cross(tables.rim_normal, tables.rim_start)
    back = np.cross(tables.rim_end, tables.rim_normal)
    opposite = 3 - tables.rim_corner.sum(axis=1)
    return tables.rim_start, tables.rim_end, tables.rim_normal, along, back, tables.rim_face, opposite


def alpha_inputs(field, dataset, *, device=None) -> tuple[np.ndarray, np.ndarray]:
    """The alpha method's per-light stacks for ``field`` from the ``dataset`` it was fitted to.

    Returns (specular, images): (n, H, W) specular luminance from the field's own segmentation
    settings and the (n, H, W, C) images, both at the field's size and in the field's units (the
    fit's exposure applied, like every Relighter input). Pass them to
    ``Relighter(alpha_specular=..., alpha_images=...)``.
    """
    from ..io.resample import resize_stack
    from ..kernels.segmentation import segment

    check_same_lights(field, dataset)
    images = resize_stack(dataset.images, field.width, field.height)
    images = images * np.float32(field.exposure)
    seg = segment(images, dataset.lights.directions, settings=field.fit_settings().segmentation, device=device)
    return seg.specular_luminance.numpy().copy(), images


def check_same_lights(field, dataset) -> None:
    """Raise ``InputError`` unless ``dataset`` has the lights ``field`` was fitted to (same order)."""
    if dataset.light_count != field.light_count:
        raise InputError(f"the field was fitted to {field.light_count} lights but the dataset has "
                         f"{dataset.light_count}; pass the dataset it was fitted to")
    gap = float(np.abs(dataset.lights.directions - field.lights.directions).max())
    if gap > 1e-5:
        raise InputError(f"the dataset's light directions differ from the field's (by up to {gap:.2g}); pass the "
                         f"dataset it was fitted to")


def face_edge_rows(faces: np.ndarray, directed_edges: np.ndarray, light_count: int) -> np.ndarray:
    """(F, 3, 2) int32: for corner k of face f, the rows of edges v_k -> v_{k+1} and v_k -> v_{k+2}.

    ``directed_edges`` must be sorted lexicographically (``SphericalTriangulation.directed_edges``).
    """
    faces = np.asarray(faces, dtype=np.int64)
    rows = np.empty(faces.shape + (2,), dtype=np.int64)
    for k in range(3):
        for j, step in enumerate((1, 2)):
            rows[:, k, j] = edge_rows(directed_edges, light_count, faces[:, k], faces[:, (k + step) % 3])
    return rows.astype(np.int32)


class _SingleQuery:
    """One query as one captured CUDA graph: the direction copied in from page-locked memory, the relight
    kernels on buffers and a rasterizer of its own (a batch elsewhere cannot move them), and the results
    copied out to page-locked memory.

    The images are handed out without a host copy: as arrays viewing a ``_ResultSlot``'s page-locked
    buffers, which are written again only once no array of them is alive. Each slot has its own graph
    (a graph's copies have fixed addresses); while ``result_slots`` results are held, a query is copied
    out of one more slot as before.
    """

    def __init__(self, relighter: Relighter, method: str, full: bool):
        device = relighter.device
        self.device = device
        self.full = full
        self.buffers = _DeviceQueries(1, relighter.capacity, relighter.height, relighter.width, relighter.channels,
                                      device)
        self.raster = Rasterizer(relighter.height, relighter.width, settings=relighter.raster.settings, device=device)
        b = self.buffers
        self.inputs = [(b.directions, _pinned_like(b.directions)), (b.unit, _pinned_like(b.unit))]
        self._kernels = lambda: relighter._run(b, self.raster, method=method, full=full)
        self._set(np.array([0.0, 0.0, 1.0]))
        for target, source in self.inputs:
            wp.copy(target, source)
        self._kernels()  # eagerly once: loads the kernels and makes the arrays made on first use
        self.slots: list[_ResultSlot] = []
        self.slot_count = result_slots(relighter.height, relighter.width, relighter.channels)
        self._copying: _ResultSlot | None = None  # the slot results are copied out of when every slot is held

    def _capture(self) -> _ResultSlot:
        b = self.buffers
        outputs = {name: (_pinned_like(array), array) for name, array in
                   (("specular", b.specular), ("faces", b.faces), ("weights", b.weights), ("clamped", b.clamped))
                   + ((("full", b.full),) if self.full else ())}
        with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
            for target, source in self.inputs:
                wp.copy(target, source)
            self._kernels()
            for target, source in outputs.values():
                wp.copy(target, source)
        return _ResultSlot(capture.graph, outputs)

    def _set(self, direction: np.ndarray) -> None:
        self.inputs[0][1].numpy()[0] = direction
        self.inputs[1][1].numpy()[0] = direction.astype(np.float32)

    def _free_slot(self) -> tuple[_ResultSlot, bool]:
        """A slot whose results nobody holds (made when fewer than ``slot_count`` exist), and False;
        else the copying slot and True."""
        for slot in self.slots:
            if not slot.held():
                return slot, False
        if len(self.slots) < self.slot_count:
            self.slots.append(self._capture())
            return self.slots[-1], False
        if self._copying is None:
            self._copying = self._capture()
        return self._copying, True

    def run(self, direction: np.ndarray) -> RelitImages:
        slot, copy = self._free_slot()
        self._set(direction)
        wp.capture_launch(slot.graph)
        wp.synchronize_device(self.device)
        return slot.results(self.buffers.specular.shape[1:], copy=copy)


RESULT_SLOTS = 4
"""Results of single CUDA queries held at once without a host copy (each slot is one query's page-locked
images: 2 MB at 480x270 RGB, 33 MB at 1920x1080); more held results are copied out of one more slot."""
RESULT_SLOT_BYTES = 256 * 2**20
"""Page-locked memory a relighter's single queries take at most, the copying slot included (but at
least one slot besides it): one slot and the copying one at 3840x2160 RGB, where one query's images
are 133 MB. Page-locked memory cannot be paged out, so it is kept small."""


def result_slots(height: int, width: int, channels: int) -> int:
    """How many ``_ResultSlot``s whose results are handed out without a copy a single query of this size
    keeps: ``RESULT_SLOTS``, fewer where they and the copying slot would exceed ``RESULT_SLOT_BYTES``."""
    images = 4 * height * width * (1 + channels)  # S' and I', float32
    return int(max(1, min(RESULT_SLOTS, RESULT_SLOT_BYTES // images - 1)))


def _pinned_like(array: wp.array) -> wp.array:
    return wp.empty_like(array, device="cpu", pinned=True)


class _Lease:
    """The owner of the host arrays handed out from one page-locked buffer. NumPy makes the owner the
    base of every view and slice of them, so the lease stays alive exactly while any of them does."""

    def __init__(self, buffer: np.ndarray):
        self._buffer = buffer  # keeps the page-locked memory alive
        self.__array_interface__ = buffer.__array_interface__


class _ResultSlot:
    """One captured graph of a single query and the page-locked buffers its results land in, with weak
    references to the leases of the images last handed out from them."""

    def __init__(self, graph, outputs: dict[str, tuple[wp.array, wp.array]]):
        self.graph = graph
        self.outputs = outputs
        self.leases: list[weakref.ref] = []

    def held(self) -> bool:
        return any(lease() is not None for lease in self.leases)

    def results(self, image_shape: tuple[int, int], *, copy: bool) -> RelitImages:
        """The last query's results: the images as arrays on the buffers (copies when ``copy``)."""
        host = {name: pinned.numpy() for name, (pinned, _) in self.outputs.items()}
        specular, images = host["specular"][0], host["full"][0].reshape(image_shape + (-1,)) if "full" in host else None
        if copy:
            specular, images = specular.copy(), None if images is None else images.copy()
        else:
            leases = [_Lease(array) for array in (specular, images) if array is not None]
            self.leases = [weakref.ref(lease) for lease in leases]
            specular = np.asarray(leases[0])
            images = None if images is None else np.asarray(leases[1])
        return RelitImages(specular, images, host["faces"][0].copy(), host["weights"][0].astype(np.float64),
                           host["clamped"][0] != 0)


def _copy_to_host(chunk: _DeviceQueries, specular: np.ndarray, images: np.ndarray | None) -> None:
    """Copy the chunk's S' (and I' when ``images`` is given) into host arrays (Q, H, W), (Q, H, W, C)."""
    device_specular, device_full = chunk.specular, chunk.full
    if device_specular.device.is_cuda:
        # a copy into page-locked memory runs at full bus speed (a pageable one is several times slower)
        if chunk.staging_specular is None:
            chunk.staging_specular = wp.empty_like(device_specular, device="cpu", pinned=True)
        wp.copy(chunk.staging_specular, device_specular)
        device_specular = chunk.staging_specular
        if images is not None:
            if chunk.staging_full is None:
                chunk.staging_full = wp.empty_like(chunk.full, device="cpu", pinned=True)
            wp.copy(chunk.staging_full, chunk.full)
            device_full = chunk.staging_full
        wp.synchronize_device(chunk.specular.device)
    # host views of buffers the next chunk overwrites: copy them out now
    specular[...] = device_specular.numpy()
    if images is not None:
        images[...] = device_full.numpy().reshape(images.shape)


def _checked_method(method: str) -> str:
    if method not in RELIGHT_METHODS:
        raise InputError(f"method must be one of {', '.join(RELIGHT_METHODS)}, got '{method}'")
    return method


def _output_size(field, size) -> tuple[int, int]:
    if size is None:
        return field.width, field.height
    width, height = (int(v) for v in size)
    if min(width, height) < 1:
        raise InputError(f"output size must be at least 1x1 pixels, got {width}x{height}")
    if abs(width - field.width * height / field.height) > 1.0:
        raise InputError(
            f"output size {width}x{height} changes the field's aspect ratio ({field.width}x{field.height}); "
            f"use e.g. {round(field.width * height / field.height)}x{height}"
        )
    return width, height


def _query_bytes(field, width: int, height: int) -> int:
    """Device bytes one query's images take in a ``Relighter`` of ``field`` at ``width`` x ``height``: S' and I'
    at the output size, and at the field's size its residual term (a larger output) and a learned decode."""
    channels = _field_channels(field)
    source_width, source_height = _source_size(field, width, height)
    source = source_width * source_height
    upsampled = source != width * height
    learned = field.residual is not None and field.residual.learned is not None
    return (4 * width * height * (1 + channels) + (4 * source * (1 + channels) if upsampled else 0)
            + (2 * 3 * source if learned else 0))


def default_queries(field, width: int, height: int) -> int:
    """Queries a ``Relighter`` of ``field`` at ``width`` x ``height`` launches at a time by default: as many as
    fit in ``_CHUNK_BYTES`` of images, at least one."""
    return max(1, _CHUNK_BYTES // _query_bytes(field, width, height))


def relight_bytes(field, width: int, height: int, *, queries: int = 1, alpha: bool = False) -> int:
    """Bytes of memory relighting ``field`` at ``width`` x ``height`` takes, ``queries`` at a time, up to the
    images written (on the CPU all of it is host memory; on CUDA the part on the device is about as large): the
    field's arrays as a ``Relighter`` holds them (at the output size when it is smaller than the field, else at
    the field's), the rasterizer's tile lists, each query's images on the device and their host copies, the
    alpha method's captured stacks, and what writing one image takes (16-bit codes, the encoder's copy, the file
    read back to check it)."""
    channels = _field_channels(field)
    source_width, source_height = _source_size(field, width, height)
    source = source_width * source_height
    pixels = width * height
    n = field.light_count
    held = 0
    residual = field.residual
    if residual is not None:
        if residual.luminance is not None:  # float32 basis and mean read per query, or n decoded float16 images
            stacks = [stack for stack in (residual.luminance, residual.chroma) if stack is not None]
            basis = sum(4 * source * (stack.rank + 1) * stack.mean.shape[2] for stack in stacks)
            held += max(basis, 2 * n * source * residual.channels)
        elif residual.images is not None:
            held += 2 * n * source * residual.channels
        elif residual.learned is not None:
            held += 4 * source * residual.learned.codes.shape[2]
        held += 4 * source * (1 + residual.channels)  # the per-pixel scale and highlight colour
    if field.diffuse is not None:
        held += 16 * source * field.diffuse.channel_count
        if field.diffuse.images is not None:
            held += 2 * n * source * field.diffuse.channel_count
    if alpha:  # float16 images and float32 specular on the device, their float32 host copies while uploaded
        held += n * source * (4 + 2 * channels) + n * source * 4 * (1 + channels)
    tile = field.fit_settings().raster.tile_size
    tiles = -(-width // tile) * -(-height // tile)
    raster = queries * tiles * (3 * field.capacity + 1) * 4
    images = queries * (_query_bytes(field, width, height) + 4 * pixels * (1 + channels))
    written = 8 * pixels * channels  # 16-bit codes, the encoder's copy, and the file read back and compared
    return held + raster + images + written


def _source_size(field, width: int, height: int) -> tuple[int, int]:
    """The size the field's per-pixel arrays are held at for a ``width`` x ``height`` output: the field's own
    when the output is at least as large along both axes (read by interpolation), else the output's."""
    if width >= field.width and height >= field.height:
        return field.width, field.height
    return width, height


def _diffuse_mode(field, diffuse: str) -> tuple[int, bool]:
    """The compose mode for ``diffuse``, and whether its image stack is the residual's."""
    model, residual = field.diffuse, field.residual
    if diffuse == "auto":
        diffuse = ("residual" if residual is not None else "images" if model is not None and model.images is not None
                   else "lambert" if model is not None else "none")
    if diffuse == "none":
        return kernels.DIFFUSE_NONE, False
    if diffuse == "residual":
        if residual is None:
            raise InputError("diffuse 'residual' needs a field fitted with a residual (fit --residual lowrank or "
                             "images; fields before version 0.2 have none)")
        if residual.learned is not None:
            return kernels.DIFFUSE_DECODED, False
        return (kernels.DIFFUSE_LOWRANK, False) if residual.kind == "lowrank" else (kernels.DIFFUSE_BLEND, True)
    if model is None:
        raise InputError(
            f"diffuse '{diffuse}' needs a field fitted with a diffuse model (fit --diffuse lambert or images)")
    if diffuse == "images" and model.images is None:
        raise InputError(
            "diffuse 'images' needs a field fitted with --diffuse images (this one stores only the Lambertian model)")
    return (kernels.DIFFUSE_LAMBERT if diffuse == "lambert" else kernels.DIFFUSE_BLEND), False


def _field_channels(field) -> int:
    if field.residual is not None:
        return field.residual.channels
    return field.diffuse.channel_count if field.diffuse is not None else 1


