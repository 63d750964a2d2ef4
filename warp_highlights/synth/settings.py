"""What a render looks like: the material and the image settings (no Warp, so the command line can
show their defaults without starting it)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.errors import InputError

__all__ = ["TEXTURES", "Material", "RenderSettings"]

TEXTURES = ("none", "tiles")
"""Albedo patterns of :class:`Material`: uniform, or tiles of two materials."""


@dataclass(frozen=True)
class Material:
    """Lambertian base plus a specular lobe (normalised Blinn-Phong, or GGX microfacet), under a distant
    light of intensity 1.

    Attributes:
        albedo: linear RGB diffuse reflectance in [0, 1]; radiance = albedo * max(n.l, 0).
        ambient: constant radiance added on the object (also in shadow), linear, per channel or scalar.
        specular: scale of the lobe (white); peak radiance ~ specular * (shininess + 8) / (8 pi) for
            Blinn-Phong, specular / (4 pi roughness^2) for GGX (``peak_specular``).
        shininess: Blinn-Phong exponent of (n . h); larger is a smaller, brighter highlight.
        roughness: GGX alpha in (0, 1]: when > 0 the lobe is the GGX (Trowbridge-Reitz) microfacet lobe
            D G / (4 n.v) with Smith's shadowing, the shape of metal and glaze highlights (a sharp
            core and long tails); 0 keeps Blinn-Phong.
        texture: "none", or "tiles": a checkerboard of cells ``tile_size`` wide (in units of the
            object's bounding radius, in the camera's frame) alternating this material with a second
            one of albedo ``tile_albedo`` and lobe ``tile_specular`` times this one's: texture and
            several materials, as painted or inlaid objects have.
    """

    albedo: tuple[float, float, float] = (0.7, 0.42, 0.24)
    ambient: float = 0.02
    specular: float = 0.5
    shininess: float = 120.0
    roughness: float = 0.0
    texture: str = "none"
    tile_albedo: tuple[float, float, float] = (0.86, 0.82, 0.72)
    tile_specular: float = 0.1
    tile_size: float = 0.3

    def __post_init__(self):
        for name in ("albedo", "tile_albedo"):
            albedo = np.asarray(getattr(self, name), dtype=np.float64)
            if albedo.shape != (3,) or not np.all(np.isfinite(albedo)) or albedo.min() < 0 or albedo.max() > 1:
                raise InputError(f"{name} must be three numbers in [0, 1], got {getattr(self, name)}")
        if not (math.isfinite(self.roughness) and 0.0 <= self.roughness <= 1.0):
            raise InputError(f"roughness must be in [0, 1] (0: Blinn-Phong), got {self.roughness}")
        if self.texture not in TEXTURES:
            raise InputError(f"texture must be one of {', '.join(TEXTURES)}, got {self.texture!r}")
        if not (math.isfinite(self.tile_size) and self.tile_size > 0):
            raise InputError(f"tile_size must be a number > 0, got {self.tile_size}")
        for name in ("ambient", "specular", "tile_specular"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise InputError(f"{name} must be a finite number >= 0, got {value}")
        if not math.isfinite(self.shininess) or self.shininess < 1:
            raise InputError(f"shininess must be a number >= 1, got {self.shininess}")

    @property
    def peak_specular(self) -> float:
        """Radiance at the centre of a highlight on a surface facing the light and the camera."""
        if self.roughness > 0:
            return self.specular / (4.0 * math.pi * self.roughness**2)
        return self.specular * (self.shininess + 8.0) / (8.0 * math.pi)


@dataclass(frozen=True)
class RenderSettings:
    """Image and sampling settings.

    Attributes:
        width, height: image size in pixels.
        samples_per_pixel: a square number (4, 9, 16, ...): stratified jittered samples per pixel.
        fov_y_deg: vertical field of view of the pinhole camera, degrees.
        fill: fraction of the frame (height or width, whichever binds) the object's projection fills.
        colour: True for RGB images, False for single-channel luminance.
        light_chunk: lights shaded per launch; bounds device memory (3 images x chunk x H x W x C floats).
        seed: seed of the sample jitter.
        shadow_bias: shadow-ray offset in units of the object's bounding radius.
    """

    width: int = 480
    height: int = 270
    samples_per_pixel: int = 4
    fov_y_deg: float = 30.0
    fill: float = 0.9
    colour: bool = True
    light_chunk: int = 64
    seed: int = 0
    shadow_bias: float = 1e-4

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")
        root = math.isqrt(max(self.samples_per_pixel, 0))
        if self.samples_per_pixel < 1 or root * root != self.samples_per_pixel:
            raise InputError(
                f"samples per pixel must be a square number (1, 4, 9, 16, ...), got {self.samples_per_pixel}")
        if not 0 < self.fov_y_deg < 170:
            raise InputError(f"field of view must be between 0 and 170 degrees, got {self.fov_y_deg}")
        if not 0 < self.fill <= 1:
            raise InputError(f"fill must be in (0, 1], got {self.fill}")
        if self.light_chunk < 1:
            raise InputError(f"light chunk must be >= 1, got {self.light_chunk}")

    @property
    def grid(self) -> int:
        """Samples per pixel along each axis."""
        return math.isqrt(self.samples_per_pixel)
