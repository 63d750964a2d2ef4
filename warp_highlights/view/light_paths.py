"""Light paths for animations: directions along a great circle, an orbit at one elevation, or through a list
of directions, and the ``--path`` forms that name them.

Light directions are float64 unit vectors from the object towards the light, in camera space: x to
the right of the image, y towards the top, z towards the camera (docs/method.md, Units and conventions). Angles
taken as arguments are in degrees; elevation is measured from the image plane (xy) towards +z (the camera
side), azimuth from +x towards +y.
"""

from __future__ import annotations

import math
import operator
import re
from pathlib import Path

import numpy as np

from ..io.lightfile import LIGHT_FILE_SUFFIXES, read_lights
from ..model.errors import InputError

__all__ = ["LIGHT_PATH_FORMS", "checked_frame_count", "finite_number", "great_circle", "orbit", "parse_light_path",
           "through_directions"]

LIGHT_PATH_FORMS = "great:x,y,z:x,y,z, orbit:ELEVATION_DEG[:START_AZIMUTH_DEG] or list:FILE"
"""The light path specs :func:`parse_light_path` reads, for messages and help texts."""
_ANTIPODAL_RAD = 1e-6  # directions closer than this to opposite have no unique great circle between them
_SAME_RAD = 1e-12  # directions closer than this are one direction (no arc to follow)


def great_circle(start, end, frames: int) -> np.ndarray:
    """Directions along the shorter great-circle arc from ``start`` to ``end`` (spherical interpolation).

    Args:
        start: First direction, 3 numbers (normalised here).
        end: Last direction, 3 numbers (normalised here).
        frames: Number of directions, at least 1; both endpoints are included (1 gives ``start``).

    Returns:
        ``(frames, 3)`` float64 unit vectors at equal angular steps; the first is ``start`` and the last
        is ``end`` exactly (after normalisation). Equal endpoints give a constant path.

    Raises:
        InputError: A zero or non-finite direction, a bad frame count, or opposite endpoints (every
            great circle through them is as short as any other, so the path is ambiguous).
    """
    frames = checked_frame_count(frames)
    a, b = _unit(start, "start direction"), _unit(end, "end direction")
    if frames == 1:
        return a[None].copy()
    _check_not_opposite(a, b, f"great circle from {_fmt(a)} to {_fmt(b)}")
    return np.concatenate([_arc(a, b, frames - 1), b[None]])


def orbit(elevation_deg: float, frames: int, *, start_azimuth_deg: float = 0.0, turns: float = 1.0) -> np.ndarray:
    """Directions on a circle of constant elevation around the view axis, for a looping animation.

    Args:
        elevation_deg: Elevation above the image plane towards the camera, degrees in [-90, 90];
            every direction has ``z = sin(elevation)``.
        frames: Number of directions, at least 1.
        start_azimuth_deg: Azimuth of the first direction, degrees from +x towards +y.
        turns: Number of full turns (negative: clockwise as seen from the camera). With whole turns
            the first direction is not repeated at the end, so the animation loops seamlessly.

    Returns:
        ``(frames, 3)`` float64 unit vectors; frame k is at azimuth
        ``start_azimuth_deg + 360 * turns * k / frames``.

    Raises:
        InputError: Elevation outside [-90, 90], a non-finite angle or turn count, a bad frame count.
    """
    frames = checked_frame_count(frames)
    elevation = finite_number(elevation_deg, "elevation_deg")
    if not -90.0 <= elevation <= 90.0:
        raise InputError(f"orbit elevation must be in [-90, 90] degrees, got {elevation:g}")
    start = finite_number(start_azimuth_deg, "start_azimuth_deg")
    turns = finite_number(turns, "turns")
    azimuth = np.radians(start + 360.0 * turns * np.arange(frames) / frames)
    e = math.radians(elevation)
    ring = math.cos(e)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), np.full(frames, math.sin(e))], axis=1)


def through_directions(directions, frames: int) -> np.ndarray:
    """Directions along great-circle arcs through a list of directions, in order.

    The ``frames - 1`` steps are shared among the arcs in proportion to their lengths (each arc gets
    at least one step, the largest step is kept as small as possible), so the light moves at a nearly
    constant angular speed and every given direction is exactly one of the frames.

    Args:
        directions: ``(K, 3)`` directions to pass through (normalised here). Repeating a direction
            right after itself adds no frames.
        frames: Number of directions, at least 1 for K == 1 (a constant path), else at least one more
            than the number of arcs of non-zero length.

    Returns:
        ``(frames, 3)`` float64 unit vectors; the first is ``directions[0]``, the last ``directions[-1]``.

    Raises:
        InputError: A bad array shape, a zero or non-finite direction, two consecutive opposite
            directions (ambiguous arc), or too few frames to visit every direction.
    """
    frames = checked_frame_count(frames)
    points = _unit_rows(directions)
    angles = _angle(points[:-1], points[1:])
    for i in np.flatnonzero(angles > math.pi - _ANTIPODAL_RAD):
        _check_not_opposite(points[i], points[i + 1], f"directions {i} and {i + 1} of the list")
    moving = angles >= _SAME_RAD
    if not moving.any():
        return np.repeat(points[:1], frames, axis=0)
    if frames - 1 < moving.sum():
        raise InputError(
            f"a path through {len(points)} directions needs at least {moving.sum() + 1} frames, got {frames}; "
            "use more frames or fewer directions"
        )
    steps = _share_steps(angles, moving, frames - 1)
    arcs = [_arc(points[i], points[i + 1], int(steps[i])) for i in np.flatnonzero(moving)]
    return np.concatenate([*arcs, points[-1:]])


def parse_light_path(spec: str, frames: int) -> np.ndarray:
    """Light path from a command-line spec.

    Forms: ``great:x,y,z:x,y,z`` (great-circle arc, :func:`great_circle`), ``orbit:ELEVATION_DEG`` or
    ``orbit:ELEVATION_DEG:START_AZIMUTH_DEG`` (one turn, :func:`orbit`), ``list:FILE``
    (:func:`through_directions` through the directions of FILE: an RTI ``.lp`` light file, or a text
    file with one direction per line as ``x y z`` or ``x,y,z``; blank lines and ``#`` comments allowed).

    Args:
        spec: The path spec.
        frames: Number of directions.

    Returns:
        ``(frames, 3)`` float64 unit vectors.

    Raises:
        InputError: One line naming the spec, the problem (file and line for files) and the expected form.
    """
    spec = str(spec)
    kind, _, rest = spec.strip().partition(":")
    parsers = {"great": _parse_great, "orbit": _parse_orbit, "list": _parse_list}
    parser = parsers.get(kind.strip().lower())
    if parser is None:
        raise InputError(f"light path {spec!r}: unknown kind {kind.strip()!r}; expected {LIGHT_PATH_FORMS}")
    try:
        return parser(rest.strip(), frames)
    except InputError as exc:
        raise InputError(f"light path {spec!r}: {exc}") from None


def checked_frame_count(frames) -> int:
    """``frames`` as a positive int, or an InputError."""
    try:
        count = operator.index(frames)
    except TypeError:
        count = None
    if count is None or isinstance(frames, bool) or count < 1:
        raise InputError(f"the frame count must be a positive integer, got {frames!r}")
    return count


def finite_number(value, name: str) -> float:
    """``value`` as a finite float, or an InputError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(f"{name} must be finite, got {value!r}")
    return number


def _unit(vector, name: str) -> np.ndarray:
    """One direction -> float64 unit vector, or an InputError naming it."""
    try:
        v = np.asarray(vector, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers x,y,z, got {vector!r}") from None
    if v.shape != (3,):
        raise InputError(f"{name} must be 3 numbers x,y,z, got shape {v.shape}")
    norm = float(np.linalg.norm(v))
    if not (math.isfinite(norm) and norm > 0.0):
        raise InputError(f"{name} {v.tolist()} is zero or not finite; give the direction towards the light")
    return v / norm


def _unit_rows(directions) -> np.ndarray:
    try:
        points = np.asarray(directions, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("directions must be a (K, 3) array of numbers") from None
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise InputError(f"directions must have shape (K, 3) with K >= 1, got {points.shape}")
    return np.stack([_unit(p, f"direction {i}") for i, p in enumerate(points)])


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in radians between unit vectors (last axis), accurate near 0 and pi."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _check_not_opposite(a: np.ndarray, b: np.ndarray, what: str) -> None:
    if _angle(a, b) > math.pi - _ANTIPODAL_RAD:
        raise InputError(
            f"{what}: the directions are opposite, so the great circle between them is ambiguous; "
            "use a list path through a middle direction"
        )


def _arc(a: np.ndarray, b: np.ndarray, count: int) -> np.ndarray:
    """``count`` directions at equal angular steps from ``a`` towards ``b``: a included, b excluded."""
    theta = float(_angle(a, b))
    if theta < _SAME_RAD:
        return np.repeat(a[None], count, axis=0)
    w = b - np.dot(a, b) * a  # component of b orthogonal to a; length sin(theta)
    w /= np.linalg.norm(w)
    t = theta * np.arange(count)[:, None] / count
    points = np.cos(t) * a + np.sin(t) * w
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[0] = a
    return points


def _share_steps(angles: np.ndarray, moving: np.ndarray, total: int) -> np.ndarray:
    """``total`` steps over the arcs: one per moving arc, the rest in proportion to arc length.

    The proportional share is rounded down, and each step left over goes to the arc whose step is
    currently the longest (at most one per arc).
    """
    spare = total - int(moving.sum())
    shares = np.floor(spare * np.where(moving, angles, 0.0) / angles[moving].sum())
    steps = moving.astype(np.int64) + shares.astype(np.int64)
    for _ in range(total - int(steps.sum())):
        step_length = np.where(moving, angles / np.maximum(steps, 1), -1.0)
        steps[np.argmax(step_length)] += 1
    return steps


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _parse_number(text: str, what: str, example: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"{what} must be a number, got {text.strip()!r}, e.g. {example}")
    return value


def _parse_vector(text: str, what: str) -> np.ndarray:
    example = "great:1,0,1:-1,0,1"
    parts = text.split(",")
    if len(parts) != 3:
        raise InputError(f"the {what} direction must be three numbers x,y,z, got {text.strip()!r}, e.g. {example}")
    return np.array([_parse_number(p, f"each coordinate of the {what} direction", example) for p in parts])


def _parse_great(rest: str, frames: int) -> np.ndarray:
    parts = rest.split(":")
    if len(parts) != 2:
        raise InputError("expected two directions, great:x,y,z:x,y,z, e.g. great:1,0,1:-1,0,1")
    return great_circle(_parse_vector(parts[0], "start"), _parse_vector(parts[1], "end"), frames)


def _parse_orbit(rest: str, frames: int) -> np.ndarray:
    parts = rest.split(":")
    if len(parts) > 2 or not rest:
        raise InputError("expected orbit:ELEVATION_DEG or orbit:ELEVATION_DEG:START_AZIMUTH_DEG, e.g. orbit:30")
    elevation = _parse_number(parts[0], "elevation (degrees)", "orbit:30")
    azimuth = _parse_number(parts[1], "start azimuth (degrees)", "orbit:30:90") if len(parts) == 2 else 0.0
    return orbit(elevation, frames, start_azimuth_deg=azimuth)


def _parse_list(rest: str, frames: int) -> np.ndarray:
    if not rest:
        raise InputError("expected list:FILE with a light file (.lp, .dome, .relight) or a text file of 'x y z' lines")
    path = Path(rest)
    if path.suffix.lower() in LIGHT_FILE_SUFFIXES:
        directions = read_lights(path, check_files=False).directions
    else:
        directions = _read_direction_file(path)
    return through_directions(directions, frames)


DIRECTION_FILE_MAX_BYTES = 64 << 20
"""Largest direction file read, in bytes (some million lines: more than any light path needs)."""


def _read_direction_file(path: Path) -> np.ndarray:
    """Text file of one direction a line (``x y z`` or ``x,y,z``; blank lines, ``#`` comments) -> (K, 3)."""
    import stat

    from ..io.images import file_kind

    try:
        status = path.stat()
        if not stat.S_ISREG(status.st_mode):
            raise InputError(f"{path}: the direction file is not a regular file but {file_kind(status.st_mode)}; "
                             f"give a text file of 'x y z' lines")
        if status.st_size > DIRECTION_FILE_MAX_BYTES:
            raise InputError(f"{path}: the direction file has {status.st_size} bytes, more than a light path "
                             f"needs ({DIRECTION_FILE_MAX_BYTES >> 20} MB at most); give a text file of 'x y z' lines")
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{path}: direction file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read direction file ({exc}); expected a text file of 'x y z' lines") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if body:
            rows.append(_parse_direction_line(path, number, body))
    if not rows:
        raise InputError(f"{path}: no directions in the file; write one direction a line as 'x y z' or 'x,y,z'")
    return np.array(rows)


def _parse_direction_line(path: Path, number: int, body: str) -> list[float]:
    tokens = [t for t in re.split(r"[,\s]+", body) if t]
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        values = []
    if len(values) != 3 or not all(map(math.isfinite, values)) or not any(values):
        raise InputError(
            f"{path}:{number}: expected a non-zero direction as 'x y z' or 'x,y,z', got {body[:60]!r}"
        )
    return values
