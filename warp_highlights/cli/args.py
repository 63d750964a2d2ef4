"""Argument parsers and checks shared by the ``warp-highlights`` commands."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..model.errors import InputError

__all__ = ["Command", "add_common_options", "check_device", "check_output_file", "parse_direction", "parse_size", "parse_triple"]


@dataclass(frozen=True)
class Command:
    """One ``warp-highlights`` subcommand; each command module lists its own in ``COMMANDS``.

    Attributes:
        name: What the user types after ``warp-highlights``.
        arguments: Adds the command's arguments to its parser (``-q``/``-v`` follow them).
        run: Runs the command on the parsed arguments; returns the exit status.
        help: Its line in ``warp-highlights --help``.
        description: The text at the top of its own ``--help``; None for none.
    """

    name: str
    arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str
    description: str | None = None

    def add_to(self, commands) -> None:
        """Add the command to ``commands``, what ``ArgumentParser.add_subparsers`` returned."""
        parser = commands.add_parser(self.name, help=self.help, description=self.description)
        self.arguments(parser)
        add_common_options(parser)
        parser.set_defaults(run=self.run)


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """Add -q/--quiet and -v/--verbose, which every command takes."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("-v", "--verbose", action="store_true", help="let Warp report kernel compilation")


def parse_size(text: str, what: str = "image size") -> tuple[int, int]:
    """'480x270' -> (480, 270); ``what`` names the value in the error message."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise InputError(f"{what} '{text}' is not WIDTHxHEIGHT, e.g. 480x270") from None
    if not (1 <= width <= 8000 and 1 <= height <= 8000):
        raise InputError(f"{what} '{text}' is out of range: use 1..8000 pixels a side, e.g. 480x270")
    return width, height


def parse_triple(text: str, what: str) -> tuple[float, float, float]:
    """'0.7,0.4,0.2' -> (0.7, 0.4, 0.2); one number is repeated."""
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        raise InputError(f"{what} '{text}' is not R,G,B numbers, e.g. 0.7,0.42,0.24") from None
    if len(values) == 1:
        values *= 3
    if len(values) != 3:
        raise InputError(f"{what} '{text}' needs 1 or 3 numbers, e.g. 0.7,0.42,0.24")
    return tuple(values)


def check_device(device: str | None) -> str | None:
    import warp as wp

    wp.init()
    if device is None:
        return None
    try:
        return str(wp.get_device(device))
    except (RuntimeError, ValueError):
        names = ", ".join(str(d) for d in wp.get_devices())
        raise InputError(f"device '{device}' is not available here; use one of: {names}") from None


def parse_direction(text: str) -> tuple[float, float, float]:
    """'0.3,0.5,1' -> (0.3, 0.5, 1.0): a light direction (towards the light), any non-zero length."""
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        raise InputError(f"light direction '{text}' is not X,Y,Z numbers, e.g. 0.3,0.5,1") from None
    if len(values) != 3:
        raise InputError(f"light direction '{text}' needs 3 numbers X,Y,Z, e.g. 0.3,0.5,1")
    if not all(abs(v) < float("inf") for v in values) or not any(values):
        raise InputError(f"light direction '{text}' must be finite and non-zero, e.g. 0.3,0.5,1")
    return tuple(values)


def check_output_file(path: Path, *, overwrite: bool) -> None:
    """Raise ``InputError`` unless ``path`` may be written: a new file in an existing folder, or ``overwrite``."""
    if path.exists() and (path.is_dir() or not overwrite):
        what = "is a folder" if path.is_dir() else "exists; pass --overwrite to replace it"
        raise InputError(f"output {path} {what}")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"folder {parent} for the output {path.name} does not exist; create it first")
