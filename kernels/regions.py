"""Connected regions where a residual S - R exceeds a threshold, labelled and measured on the device.

The estimation's add rounds (docs/method.md, Fitting step 2) need, for every image of a batch at once, the
8-connected regions of ``target - image > threshold`` and each region's pixel count, residual mass,
peak, and residual-weighted centroid and second moments. Here the labelling is a union-find over one
int32 per pixel (``parent``), so only the regions' figures come to the host:

1. ``mark_above``: parent[i] = i where the residual exceeds the threshold, else -1 (i is the flat
   index (b H + row) W + col).
2. ``unite_neighbours``: each marked pixel unites with its marked west, north-west, north and
   north-east neighbours: roots are linked by ``atomic_min``, so a region's root is always its
   smallest flat index whatever the threads' order (retrying where another thread moved a root).
3. ``flatten_roots``: every marked pixel points straight at its root.
4. The roots are listed, sorted on the host (the regions numbered in raster order of their first
   pixel, as ``scipy.ndimage.label`` numbers them), and each root's parent becomes -(region + 2).
5. ``region_sums`` and ``region_moments``: float64 sums per region (atomics), the second moments
   about the region's weighted centroid, and the peak's pixel (the last in raster order among ties).

Figures are float64 sums of the float32 residual, in the coordinates of the rasterizer (image
heights: pixel (col, row) at ((col + 0.5) / H, (row + 0.5) / H)). On the CPU the sums run in pixel
order, the order ``numpy.bincount`` sums in; on CUDA atomics add in any order (differences of a
float64 rounding).
"""

# ruff: noqa: UP018  (Warp declares a mutable kernel local with float(0.0) / int(0))

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_highlights.model.errors import InputError

__all__ = ["ResidualRegions", "Regions", "flatten_roots", "mark_above", "number_regions", "region_at", "region_moments",
           "region_sums", "unite_neighbours"]


_FIRST_ROOTS = 1024
"""Regions the first listing has room for (a guess: a few a light; more are listed again with room for all)."""


@wp.func
def _root(parent: wp.array(dtype=wp.int32), i: int) -> int:
    """Follow parent links from i to its root (links only point to smaller indices, so this ends)."""
    j = int(i)
    while parent[j] != j:
        j = parent[j]
    return j


@wp.func
def _unite(parent: wp.array(dtype=wp.int32), i: int, k: int):
    """Join the trees of i and k: the larger root is linked to the smaller with atomic_min, retried
    when another thread linked that root first (atomic_min then returns the link it found)."""
    a = _root(parent, i)
    b = _root(parent, k)
    done = int(0)
    while done == 0:
        a = _root(parent, a)
        b = _root(parent, b)
        if a < b:
            old = wp.atomic_min(parent, b, a)
            if old == b:
                done = 1
            else:
                b = old
        elif b < a:
            old = wp.atomic_min(parent, a, b)
            if old == a:
                done = 1
            else:
                a = old
        else:
            done = 1


@wp.kernel(enable_backward=False)
def mark_above(target: wp.array3d(dtype=float), image: wp.array3d(dtype=float), threshold: float,
               parent: wp.array(dtype=wp.int32)):
    """parent[i] = i where target - image > threshold (float32 difference), else -1."""
    b, row, col = wp.tid()
    i = (b * target.shape[1] + row) * target.shape[2] + col
    if target[b, row, col] - image[b, row, col] > threshold:
        parent[i] = i
    else:
        parent[i] = -1


@wp.kernel(enable_backward=False)
def unite_neighbours(parent: wp.array(dtype=wp.int32), height: int, width: int):
    """Unite each marked pixel with its marked W, NW, N and NE neighbours (8-connected within an image)."""
    b, row, col = wp.tid()
    i = (b * height + row) * width + col
    if parent[i] < 0:
        return
    if col > 0 and parent[i - 1] >= 0:
        _unite(parent, i, i - 1)
    if row > 0:
        up = i - width
        if col > 0 and parent[up - 1] >= 0:
            _unite(parent, i, up - 1)
        if parent[up] >= 0:
            _unite(parent, i, up)
        if col + 1 < width and parent[up + 1] >= 0:
            _unite(parent, i, up + 1)


@wp.kernel(enable_backward=False)
def flatten_roots(parent: wp.array(dtype=wp.int32), roots: wp.array(dtype=wp.int32),
                  root_count: wp.array(dtype=wp.int32)):
    """Point every marked pixel at its root; list the roots (in any order) while there is room."""
    i = wp.tid()
    if parent[i] < 0:
        return
    r = _root(parent, i)
    parent[i] = r
    if r == i:
        k = wp.atomic_add(root_count, 0, 1)
        if k < roots.shape[0]:
            roots[k] = i


@wp.kernel(enable_backward=False)
def number_regions(roots: wp.array(dtype=wp.int32), parent: wp.array(dtype=wp.int32)):
    """parent[roots[k]] = -(k + 2): region k's number kept at its root (-1 means unmarked)."""
    k = wp.tid()
    parent[roots[k]] = -(k + 2)


@wp.func
def _centre_of(col: int, row: int, height: int) -> wp.vec2d:
    """Pixel (col, row)'s centre in image heights, float64."""
    h = wp.float64(height)
    return wp.vec2d((wp.float64(col) + wp.float64(0.5)) / h, (wp.float64(row) + wp.float64(0.5)) / h)


@wp.func
def _region(parent: wp.array(dtype=wp.int32), i: int) -> int:
    """Region number of pixel i after ``number_regions``; -1 when unmarked."""
    p = parent[i]
    if p == -1:
        return -1
    if p < -1:
        return -p - 2
    return -parent[p] - 2


@wp.kernel(enable_backward=False)
def region_sums(
    target: wp.array3d(dtype=float),
    image: wp.array3d(dtype=float),
    parent: wp.array(dtype=wp.int32),
    area: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=wp.float64),
    first: wp.array(dtype=wp.vec2d),
    peak: wp.array(dtype=float),
):
    """Per region: pixel count, sum of w, sum of w (x, y) and max w, with w = target - image."""
    b, row, col = wp.tid()
    r = _region(parent, (b * target.shape[1] + row) * target.shape[2] + col)
    if r < 0:
        return
    w32 = target[b, row, col] - image[b, row, col]
    wp.atomic_add(area, r, 1)
    wp.atomic_add(mass, r, wp.float64(w32))
    wp.atomic_add(first, r, wp.float64(w32) * _centre_of(col, row, target.shape[1]))
    wp.atomic_max(peak, r, w32)


@wp.kernel(enable_backward=False)
def region_moments(
    target: wp.array3d(dtype=float),
    image: wp.array3d(dtype=float),
    parent: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=wp.float64),
    first: wp.array(dtype=wp.vec2d),
    peak: wp.array(dtype=float),
    second: wp.array(dtype=wp.vec3d),
    peak_pixel: wp.array(dtype=wp.int32),
):
    """Per region: sum of w (dx^2, dx dy, dy^2) about the weighted centroid, and the last pixel holding the peak."""
    b, row, col = wp.tid()
    i = (b * target.shape[1] + row) * target.shape[2] + col
    r = _region(parent, i)
    if r < 0:
        return
    w32 = target[b, row, col] - image[b, row, col]
    if w32 == peak[r]:
        wp.atomic_max(peak_pixel, r, i)
    w = wp.float64(w32)
    d = _centre_of(col, row, target.shape[1]) - first[r] / mass[r]
    wp.atomic_add(second, r, wp.vec3d(w * d[0] * d[0], w * d[0] * d[1], w * d[1] * d[1]))


@wp.kernel(enable_backward=False)
def region_at(parent: wp.array(dtype=wp.int32), pixels: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """out[k] = region number of flat pixel pixels[k] (-1 when unmarked)."""
    k = wp.tid()
    out[k] = _region(parent, pixels[k])


@dataclass
class Regions:
    """The regions of one labelling, numbered in raster order of their first pixel (float64 on the host).

    Attributes:
        problem: (R,) image each region lies in.
        area: (R,) pixels.
        mass: (R,) sum of the residual w over the region.
        peak: (R,) largest w; ``peak_pixel`` (R,) its flat pixel index (the last in raster order among ties).
        centroid: (R, 2) w-weighted mean (x, y) in image heights.
        covariance: (R, 3) w-weighted (xx, xy, yy) second moments about the centroid, image heights^2.
    """

    problem: np.ndarray
    area: np.ndarray
    mass: np.ndarray
    peak: np.ndarray
    peak_pixel: np.ndarray
    centroid: np.ndarray
    covariance: np.ndarray

    def __len__(self) -> int:
        return len(self.area)


class ResidualRegions:
    """Labels and measures the regions of ``target - image > threshold`` for a (B, H, W) batch on one device.

    Keeps one int32 per pixel between calls (the union-find forest); the regions' figures are
    copied to the host, the pixels never are.
    """

    def __init__(self, shape: tuple[int, int, int], device):
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise InputError(f"regions need a (images, height, width) shape, got {shape}")
        pixels = self.shape[0] * self.shape[1] * self.shape[2]
        if pixels >= 2**31:
            raise InputError(f"{pixels} pixels exceed one labelling (2^31); label the batch in parts")
        self.device = wp.get_device(device)
        self.parent = wp.empty(pixels, dtype=wp.int32, device=self.device)
        self._count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._roots = wp.empty(_FIRST_ROOTS, dtype=wp.int32, device=self.device)

    def label(self, target: wp.array, image: wp.array, threshold: float) -> Regions:
        """Label the regions where target - image > ``threshold`` (both (B, H, W) float32 here) and measure them."""
        for name, array in (("target", target), ("image", image)):
            if array.shape != self.shape or array.dtype != wp.float32 or array.device != self.device:
                raise InputError(f"{name} must be a float32 {self.shape} array on {self.device}, got "
                                 f"{array.dtype.__name__} {array.shape} on {array.device}")
        count = self._labelled(target, image, float(threshold))
        if count == 0:
            empty = np.zeros(0)
            return Regions(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), empty, empty,
                           np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 3)))
        device = self.device
        area = wp.zeros(count, dtype=wp.int32, device=device)
        mass = wp.zeros(count, dtype=wp.float64, device=device)
        first = wp.zeros(count, dtype=wp.vec2d, device=device)
        peak = wp.full(count, -np.inf, dtype=float, device=device)
        second = wp.zeros(count, dtype=wp.vec3d, device=device)
        peak_pixel = wp.full(count, -1, dtype=wp.int32, device=device)
        wp.launch(region_sums, dim=self.shape, inputs=[target, image, self.parent], outputs=[area, mass, first, peak],
                  device=device)
        wp.launch(region_moments, dim=self.shape, inputs=[target, image, self.parent, mass, first, peak],
                  outputs=[second, peak_pixel], device=device)
        mass_host = mass.numpy()
        return Regions(
            problem=self._ordered // (self.shape[1] * self.shape[2]),
            area=area.numpy().astype(np.int64),
            mass=mass_host,
            peak=peak.numpy().astype(np.float64),
            peak_pixel=peak_pixel.numpy().astype(np.int64),
            centroid=first.numpy() / mass_host[:, None],
            covariance=second.numpy() / mass_host[:, None],
        )

    def regions_at(self, pixels: np.ndarray) -> np.ndarray:
        """(k,) region number of each flat pixel index of the last labelling (-1 where none)."""
        pixels = np.asarray(pixels, dtype=np.int64).reshape(-1)
        if pixels.size == 0:
            return np.zeros(0, dtype=np.int64)
        if pixels.min() < 0 or pixels.max() >= self.parent.size:
            raise InputError(f"pixel index out of range 0..{self.parent.size - 1}")
        device_pixels = wp.array(pixels.astype(np.int32), dtype=wp.int32, device=self.device)
        out = wp.empty(pixels.size, dtype=wp.int32, device=self.device)
        wp.launch(region_at, dim=pixels.size, inputs=[self.parent, device_pixels], outputs=[out], device=self.device)
        return out.numpy().astype(np.int64)

    def _labelled(self, target: wp.array, image: wp.array, threshold: float) -> int:
        """Steps 1-4 of the module docstring; the number of regions."""
        device, (_, height, width) = self.device, self.shape
        wp.launch(mark_above, dim=self.shape, inputs=[target, image, threshold], outputs=[self.parent], device=device)
        wp.launch(unite_neighbours, dim=self.shape, inputs=[self.parent, height, width], device=device)
        self._count.zero_()
        wp.launch(flatten_roots, dim=self.parent.size, inputs=[self.parent], outputs=[self._roots, self._count],
                  device=device)
        count = int(self._count.numpy()[0])
        if count > self._roots.size:  # more regions than room: list them again with room for all
            self._roots = wp.empty(count, dtype=wp.int32, device=device)
            self._count.zero_()
            wp.launch(flatten_roots, dim=self.parent.size, inputs=[self.parent], outputs=[self._roots, self._count],
                      device=device)
        if count == 0:
            self._ordered = np.zeros(0, dtype=np.int64)
            return 0
        self._ordered = np.sort(self._roots.numpy()[:count]).astype(np.int64)
        ordered = wp.array(self._ordered.astype(np.int32), dtype=wp.int32, device=device)
        wp.launch(number_regions, dim=count, inputs=[ordered], outputs=[self.parent], device=device)
        return count
