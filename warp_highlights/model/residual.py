"""The residual of a fitted field: what each captured image holds beyond its own moving highlights.

Relighting by residual transfer (method.md section 6) composes ``I'(w) = R~(w) + c(x) S'(w)``, where
``R_i = I_i - c(x) R(x; G_i)`` is light i's captured image minus its own fitted highlights,
``R~`` interpolates those residuals over the triangulation with the query's barycentric weights, and
``c(x)`` is the per-pixel highlight colour. A :class:`ResidualModel` stores the residuals in one of
two ways:

- **uncompressed**: the n residual images, float16 (what the alpha blend needs too);
- **low rank** (the default): an opponent colour split, luminance Y = 0.2126 R + 0.7152 G + 0.0722 B
  and chroma (B - Y, R - Y), each a :class:`LowRankStack`: a mean image plus k basis images with
  per-light weights. Blending the weights barycentrically blends the images exactly, so a query costs
  k multiply-adds per pixel and plane. The basis images are kept as 8-bit codes with a per-image
  range, exactly as the field file stores them.

All values are in the field's units (the fit's exposure applied).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["COLOUR_STEP", "LUMINANCE_WEIGHTS", "LowRankStack", "ResidualModel", "from_opponent", "to_opponent"]

LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB primaries, linear: luminance Y of an RGB value."""

_CODE_LEVELS = 255
_FLOAT16_SAFE = 6.0e4
COLOUR_STEP = 4.0 / 255
"""Resolution of the stored highlight colour c(x): 8 bits over [0, 4] per channel (4: a highlight four
times brighter in one channel than its luminance, beyond any metal's tint)."""


def to_opponent(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) linear RGB -> luminance (...,) and chroma (..., 2) = (B - Y, R - Y), float64."""
    rgb = np.asarray(rgb, dtype=np.float64)
    y = rgb @ np.asarray(LUMINANCE_WEIGHTS)
    return y, np.stack([rgb[..., 2] - y, rgb[..., 0] - y], axis=-1)


def from_opponent(luminance: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """Inverse of ``to_opponent``: (...,) Y and (..., 2) chroma -> (..., 3) RGB, float64."""
    wr, wg, wb = LUMINANCE_WEIGHTS
    y = np.asarray(luminance, dtype=np.float64)
    cb, cr = chroma[..., 0], chroma[..., 1]
    return np.stack([y + cr, y - (wr * cr + wb * cb) / wg, y + cb], axis=-1)


@dataclass(frozen=True, eq=False)
class LowRankStack:
    """n images of P planes as mean + weights @ basis.

    Attributes:
        mean: (H, W, P) float32.
        codes: (k, H, W, P) uint8: basis image j is ``low[j] + codes[j] * (high[j] - low[j]) / 255``.
        ranges: (k, 2) float32 (low, high) per basis image.
        weights: (n, k) float32 per-light weights.
    """

    mean: np.ndarray
    codes: np.ndarray
    ranges: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        mean = _finite(self.mean, np.float32, "residual mean")
        codes = np.ascontiguousarray(self.codes)
        if codes.dtype != np.uint8:
            raise InputError(f"residual basis codes must be uint8, got {codes.dtype}")
        ranges = _finite(self.ranges, np.float32, "residual basis ranges")
        weights = _finite(self.weights, np.float32, "residual weights")
        if mean.ndim != 3 or codes.ndim != 4 or codes.shape[1:] != mean.shape:
            raise InputError(f"residual basis {codes.shape} does not match its mean image {mean.shape}: expected (k, H, W, P)")
        k = len(codes)
        if ranges.shape != (k, 2) or weights.ndim != 2 or weights.shape[1] != k:
            raise InputError(f"residual ranges {ranges.shape} and weights {weights.shape} must be ({k}, 2) and (n, {k})")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "weights", weights)

    @classmethod
    def fit(cls, stack: np.ndarray, rank: int) -> LowRankStack:
        """The best rank-``rank`` approximation (PCA) of an (n, H, W, P) stack, basis quantised to 8 bits.

        The weights are refitted to the quantised basis by least squares, so quantisation only
        costs what the 8-bit basis cannot represent.
        """
        stack = np.asarray(stack, dtype=np.float64)
        n = len(stack)
        flat = stack.reshape(n, -1)
        mean = flat.mean(axis=0)
        centred = flat - mean
        rank = int(max(0, min(rank, n - 1)))
        if rank:
            # eigenvectors of the n x n Gram matrix: cheap for n << pixels
            gram = centred @ centred.T
            values, vectors = np.linalg.eigh(gram)
            order = np.argsort(values)[::-1][:rank]
            keep = values[order] > 1e-12 * max(float(values.max()), 1e-300)
            order = order[keep]
            basis = (vectors[:, order].T @ centred) / np.sqrt(values[order])[:, None]
        else:
            basis = np.zeros((0, flat.shape[1]))
        low = basis.min(axis=1) if len(basis) else np.zeros(0)
        high = basis.max(axis=1) if len(basis) else np.zeros(0)
        span = np.where(high > low, high - low, 1.0)
        codes = np.round((basis - low[:, None]) / span[:, None] * _CODE_LEVELS).clip(0, _CODE_LEVELS).astype(np.uint8)
        ranges = np.stack([low, low + span], axis=1).astype(np.float32)
        # the mean as the file keeps it: float16 unless a value is beyond its range
        mean32 = mean.astype(np.float16).astype(np.float32) if np.abs(mean).max(initial=0.0) < _FLOAT16_SAFE else mean.astype(np.float32)
        model = cls(mean32.reshape(stack.shape[1:]), codes.reshape((len(codes),) + stack.shape[1:]), ranges, np.zeros((n, len(codes)), np.float32))
        dequantised = model.basis.reshape(len(codes), -1).astype(np.float64)
        if len(codes):
            weights, *_ = np.linalg.lstsq(dequantised.T, (flat - mean32.astype(np.float64)).T, rcond=None)
            model = cls(model.mean, model.codes, model.ranges, weights.T.astype(np.float32))
        return model

    @property
    def rank(self) -> int:
        return len(self.codes)

    @property
    def basis(self) -> np.ndarray:
        """(k, H, W, P) float32 dequantised basis images."""
        low = self.ranges[:, 0].reshape(-1, 1, 1, 1)
        step = ((self.ranges[:, 1] - self.ranges[:, 0]) / np.float32(_CODE_LEVELS)).reshape(-1, 1, 1, 1)
        return (low + self.codes.astype(np.float32) * step).astype(np.float32)

    def images(self, weights: np.ndarray) -> np.ndarray:
        """(Q, H, W, P) float64 images for (Q, k) weight rows (e.g. blended per-light weights)."""
        weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        flat = weights @ self.basis.reshape(self.rank, -1).astype(np.float64)
        return flat.reshape((len(weights),) + self.mean.shape) + self.mean.astype(np.float64)


@dataclass(frozen=True, eq=False)
class ResidualModel:
    """The residual images R_i of a field's n lights (see the module docstring).

    Attributes:
        images: (n, H, W, C) float16 uncompressed residuals, or None when low rank.
        luminance: ``LowRankStack`` of Y (P = 1), or None when uncompressed.
        chroma: ``LowRankStack`` of (B - Y, R - Y) (P = 2) for colour fields, else None.
        highlight_colour: (H, W, C) float32 c(x) >= 0 (luminance 1 for a grey highlight), or None (white).
        channels: C, 1 or 3.
    """

    images: np.ndarray | None = None
    luminance: LowRankStack | None = None
    chroma: LowRankStack | None = None
    highlight_colour: np.ndarray | None = None

    def __post_init__(self):
        if (self.images is None) == (self.luminance is None):
            raise InputError("a residual model holds either the residual images or a low-rank luminance stack")
        if self.images is not None:
            images = _finite(self.images, np.float16, "residual images")
            if images.ndim != 4 or images.shape[3] not in (1, 3):
                raise InputError(f"residual images must have shape (n, H, W, C) with C 1 or 3, got {images.shape}")
            object.__setattr__(self, "images", images)
            if self.chroma is not None:
                raise InputError("uncompressed residual images take no chroma stack")
        else:
            lum = self.luminance
            if lum.mean.shape[2] != 1:
                raise InputError(f"the residual luminance stack must have 1 plane, got {lum.mean.shape[2]}")
            if self.chroma is not None:
                if self.chroma.mean.shape != lum.mean.shape[:2] + (2,) or len(self.chroma.weights) != len(lum.weights):
                    raise InputError("the residual chroma stack must have 2 planes of the luminance's size and the same light count")
        if self.highlight_colour is not None:
            colour = _finite(self.highlight_colour, np.float32, "highlight colour")
            if colour.shape != (self.height, self.width, self.channels) or np.any(colour < 0):
                raise InputError(f"highlight colour must be ({self.height}, {self.width}, {self.channels}) values >= 0, got {colour.shape}")
            object.__setattr__(self, "highlight_colour", colour)

    @property
    def compressed(self) -> bool:
        return self.images is None

    @property
    def light_count(self) -> int:
        return len(self.images) if self.images is not None else len(self.luminance.weights)

    @property
    def height(self) -> int:
        return (self.images.shape[1] if self.images is not None else self.luminance.mean.shape[0])

    @property
    def width(self) -> int:
        return (self.images.shape[2] if self.images is not None else self.luminance.mean.shape[1])

    @property
    def channels(self) -> int:
        if self.images is not None:
            return self.images.shape[3]
        return 3 if self.chroma is not None else 1

    def describe(self) -> str:
        if self.images is not None:
            kind = f"{self.light_count} residual images (float16)"
        else:
            chroma = f" + chroma rank {self.chroma.rank}" if self.chroma is not None else ""
            kind = f"low rank: luminance rank {self.luminance.rank}{chroma} (8-bit bases)"
        colour = "per-pixel" if self.highlight_colour is not None else "white"
        return f"residual: {kind}; highlight colour {colour}"

    def light_images(self, weights: np.ndarray) -> np.ndarray:
        """R~ for (Q, n) per-light blend weights: (Q, H, W, C) float64 (the float64 reference)."""
        weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        if self.images is not None:
            return np.einsum("qn,nhwc->qhwc", weights, self.images.astype(np.float64))
        y = self.luminance.images(weights @ self.luminance.weights.astype(np.float64))[..., 0]
        if self.chroma is None:
            return y[..., None]
        chroma = self.chroma.images(weights @ self.chroma.weights.astype(np.float64))
        return from_opponent(y, chroma)


def _finite(value, dtype, name: str) -> np.ndarray:
    try:
        array = np.asarray(value)
        if not np.issubdtype(array.dtype, np.number):
            raise TypeError(array.dtype)
        with np.errstate(over="ignore", invalid="ignore"):
            array = np.ascontiguousarray(array, dtype=dtype)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real numeric array") from None
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name} has non-finite values or values beyond the {np.dtype(dtype).name} range")
    return array
