"""Hyper-parameters of the method, in one place, in resolution-independent units.

Units (method.md section 0): Gaussian positions and sizes are *normalised by image height* (the image
spans y in (0, 1)); user-facing lengths are in *reference pixels* (rpx), 1 rpx = 1/270 of the image
height, so the thesis' values (it worked at 480 x 270) hold at every resolution. Lengths are converted
from rpx to normalised units here and nowhere else.

Where the thesis gives a value it is the default; every other default says how it was chosen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import InputError

__all__ = [
    "REFERENCE_HEIGHT_PX",
    "AdamSettings",
    "RasterSettings",
    "StructureLossSettings",
    "normalized_to_rpx",
    "pixel_area_rpx2",
    "rpx_to_normalized",
]

REFERENCE_HEIGHT_PX = 270
"""Image height, in pixels, that defines one reference pixel (the thesis' working height)."""


def rpx_to_normalized(length_rpx: float) -> float:
    """A length in reference pixels as a length in image heights."""
    return float(length_rpx) / REFERENCE_HEIGHT_PX


def normalized_to_rpx(length: float) -> float:
    """A length in image heights as a length in reference pixels."""
    return float(length) * REFERENCE_HEIGHT_PX


def pixel_area_rpx2(height_px: int) -> float:
    """Area of one pixel of an image ``height_px`` pixels tall, in rpx^2 (1 at the thesis' 270 rows).

    Image sums (the fit loss) are weighted by it so they measure the same thing at every resolution.
    """
    return (REFERENCE_HEIGHT_PX / float(height_px)) ** 2


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


@dataclass(frozen=True)
class RasterSettings:
    """How Gaussians are drawn (method.md section 1).

    Attributes:
        cutoff: truncation radius in Mahalanobis units. Beyond it a Gaussian is exactly zero; inside,
            the cut-off level exp(-cutoff^2 / 2) is subtracted and the rest rescaled so the peak stays
            a^2 and the Gaussian falls to zero continuously (no jump for the optimiser or the
            gradient check). The change from the untruncated Gaussian is at most
            a^2 exp(-cutoff^2 / 2) anywhere (3.4e-4 a^2 at the default 4, method.md's value).
        sigma_eps_rpx2: epsilon added to sigma^2 in the covariance, rpx^2. The thesis leaves it
            unspecified; 0.01 rpx^2 (a floor of 0.1 rpx on the standard deviation) keeps a collapsed
            Gaussian finite without changing any Gaussian wider than half a pixel by more than 2%.
            A Gaussian that collapses between pixel centres draws nothing and gets no gradient; the
            estimation's pruning removes such Gaussians (no energy or loss contribution).
        tile_size: culling tile edge in pixels, a power of two (a performance knob; it never changes
            the image).
            8, 16 and 32 measured within 2% of each other on the CPU and the H200
            (benchmarks/bench_raster.py --tile-sizes 8,16,32); 16 kept.
    """

    cutoff: float = 4.0
    sigma_eps_rpx2: float = 0.01
    tile_size: int = 16

    def __post_init__(self):
        _require(math.isfinite(self.cutoff) and 1.0 <= self.cutoff <= 12.0, f"cutoff must be in [1, 12] Mahalanobis units, got {self.cutoff}")
        _require(math.isfinite(self.sigma_eps_rpx2) and self.sigma_eps_rpx2 > 0, f"sigma_eps_rpx2 must be > 0, got {self.sigma_eps_rpx2}")
        _require(self.tile_size in (4, 8, 16, 32), f"tile_size must be 4, 8, 16 or 32 pixels, got {self.tile_size}")

    @property
    def sigma_eps(self) -> float:
        """The covariance epsilon in normalised units (image heights squared)."""
        return self.sigma_eps_rpx2 / REFERENCE_HEIGHT_PX**2

    @property
    def cutoff_level(self) -> float:
        """exp(-cutoff^2 / 2): the fraction of the peak at which a Gaussian is cut."""
        return math.exp(-0.5 * self.cutoff**2)


@dataclass(frozen=True)
class StructureLossSettings:
    """The structure loss of retargeting (method.md section 5).

    Attributes:
        gamma_per_rpx: steepness of the neighbourhood weight h; thesis value 4 (per rpx).
        threshold_rpx: distance m at which h = 1/2; thesis value 15 rpx.
        scale_eps_rpx: epsilon in the scale factor's denominator, rpx; only guards an all-coincident
            reference set (1e-6 rpx is far below any distance that matters).
    """

    gamma_per_rpx: float = 4.0
    threshold_rpx: float = 15.0
    scale_eps_rpx: float = 1e-6

    def __post_init__(self):
        _require(math.isfinite(self.gamma_per_rpx) and self.gamma_per_rpx > 0, f"gamma_per_rpx must be > 0, got {self.gamma_per_rpx}")
        _require(math.isfinite(self.threshold_rpx) and self.threshold_rpx > 0, f"threshold_rpx must be > 0, got {self.threshold_rpx}")
        _require(math.isfinite(self.scale_eps_rpx) and self.scale_eps_rpx > 0, f"scale_eps_rpx must be > 0, got {self.scale_eps_rpx}")


@dataclass(frozen=True)
class AdamSettings:
    """Adam (Kingma and Ba 2014) with one learning rate per parameter group.

    Learning rates are step sizes: Adam moves a parameter by about one learning rate per iteration
    when its gradient keeps its sign. Lengths are in rpx, so they mean the same at every resolution.
    The thesis gives none. The defaults come from benchmarks/tune_adam.py (results in
    benchmarks/README.md): 36 settings x 64 trials of recovering three Gaussians (sigma 2-20 rpx)
    started 4 rpx, 30% and 0.25 rad off. This setting and the same with lr_amplitude 0.05 were the
    fastest (median 40 iterations) of the four that recovered all 64 within 1000 iterations; the
    smaller amplitude step was kept. Estimation and retargeting may retune them.

    Attributes:
        lr_amplitude: step of a (the square root of the peak intensity).
        lr_mean_rpx: step of the mean, rpx.
        lr_sigma_rpx: step of sigma_x, sigma_y, rpx.
        lr_theta: step of the rotation, radians.
        beta1, beta2, epsilon: Adam's moment decay rates and denominator guard (the usual values).
    """

    lr_amplitude: float = 0.02
    lr_mean_rpx: float = 0.25
    lr_sigma_rpx: float = 0.25
    lr_theta: float = 0.01
    beta1: float = 0.9
    beta2: float = 0.999
    epsilon: float = 1e-8

    def __post_init__(self):
        for name in ("lr_amplitude", "lr_mean_rpx", "lr_sigma_rpx", "lr_theta", "epsilon"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value >= 0, f"{name} must be a finite number >= 0, got {value}")
        for name in ("beta1", "beta2"):
            value = getattr(self, name)
            _require(math.isfinite(value) and 0 <= value < 1, f"{name} must be in [0, 1), got {value}")
