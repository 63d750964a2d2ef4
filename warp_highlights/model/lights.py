"""Light directions: the ``LightSet`` and its Fibonacci-lattice generators.

A direction points from the object towards the light: x to the right of the image, y up the image,
z towards the camera. Directions are stored as float64 unit vectors. The RTI ``.lp`` light file that
lists them is ``warp_highlights.io.lightfile``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["LightSet"]

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # radians between consecutive lattice points


@dataclass(eq=False)
class LightSet:
    """A set of light directions, optionally with the image file recorded for each.

    Attributes:
        directions: ``(n, 3)`` float64 unit vectors towards the lights (normalised on construction).
        filenames: Image paths relative to the dataset folder, one per light, as in the ``.lp`` file.
        positions: ``(n, 3)`` float64 the lights' positions in millimetres where the light file gives them
            (relight's ``.dome``/``.relight`` files: LED positions), in the directions' frame; None elsewhere.
            Kept for a near-light model; the fit uses the directions.
    """

    directions: np.ndarray
    filenames: list[str] | None = None
    positions: np.ndarray | None = None

    def __post_init__(self) -> None:
        directions = np.asarray(self.directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3:
            raise InputError(f"light directions must have shape (n, 3), got {directions.shape}")
        norms = np.linalg.norm(directions, axis=1)
        bad = np.flatnonzero(~(np.isfinite(norms) & (norms > 0.0)))
        if bad.size:
            raise InputError(f"light direction {bad[0]} is zero or not finite: {directions[bad[0]].tolist()}")
        self.directions = directions / norms[:, None]
        if self.filenames is not None:
            self.filenames = [str(name) for name in self.filenames]
            if len(self.filenames) != len(directions):
                raise InputError(f"{len(self.filenames)} file names for {len(directions)} light directions")
        if self.positions is not None:
            positions = np.asarray(self.positions, dtype=np.float64)
            if positions.shape != directions.shape or not np.isfinite(positions).all():
                raise InputError(f"light positions must be {len(directions)} finite (x, y, z) rows, got shape "
                                 f"{positions.shape}")
            self.positions = positions

    def take(self, rows) -> LightSet:
        """The lights ``rows`` (indices or a boolean mask) with their file names and positions."""
        rows = np.flatnonzero(rows) if np.asarray(rows).dtype == bool else np.asarray(rows, dtype=np.int64)
        names = None if self.filenames is None else [self.filenames[i] for i in rows]
        return LightSet(self.directions[rows], names, None if self.positions is None else self.positions[rows])

    @property
    def light_count(self) -> int:
        """Number of lights."""
        return len(self.directions)

    def __len__(self) -> int:
        return self.light_count

    @classmethod
    def fibonacci_sphere(cls, count: int) -> LightSet:
        """Fibonacci lattice over the full sphere: ``count`` nearly evenly spaced directions.

        Args:
            count: Number of directions, at least 1.
        """
        return cls(_fibonacci_cap(_checked_count(count), z_min=-1.0))

    @classmethod
    def fibonacci_dome(cls, count: int, *, min_elevation_deg: float = 10.0) -> LightSet:
        """Fibonacci lattice over the cap above an elevation, uniform in solid angle, like an RTI dome.

        Args:
            count: Number of directions, at least 1.
            min_elevation_deg: Lowest elevation above the image plane, degrees in [-90, 90); every
                direction has ``z >= sin(min_elevation_deg)``.
        """
        if not -90.0 <= min_elevation_deg < 90.0:
            raise InputError(f"min_elevation_deg must be in [-90, 90), got {min_elevation_deg}")
        return cls(_fibonacci_cap(_checked_count(count), z_min=math.sin(math.radians(min_elevation_deg))))


def _checked_count(count: int) -> int:
    if isinstance(count, bool) or int(count) != count or count < 1:
        raise InputError(f"light count must be a positive integer, got {count!r}")
    return int(count)


def _fibonacci_cap(count: int, *, z_min: float) -> np.ndarray:
    """``count`` lattice points on the spherical cap ``z >= z_min``, equal solid angle each."""
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (1.0 - z_min) * (i + 0.5) / count
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
