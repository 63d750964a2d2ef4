"""Argument parsers and checks shared by the ``warp-highlights`` commands."""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..model.errors import InputError

__all__ = [
    "Command",
    "add_common_options",
    "add_pixel_limit_option",
    "check_device",
    "check_not_input",
    "check_output_file",
    "check_output_folder",
    "exposure_option",
    "in_range",
    "parse_direction",
    "parse_size",
    "parse_triple",
    "pixel_limit",
    "size_option",
    "triple_option",
]


@dataclass(frozen=True)
class Command:
    """One ``warp-highlights`` subcommand; each command module lists its own in ``COMMANDS``.

    Attributes:
        name: What the user types after ``warp-highlights``.
        arguments: Adds the command's arguments to its parser (``-q``/``-v`` follow them).
        run: Runs the command on the parsed arguments; returns the exit status.
        help: Its line in ``warp-highlights --help``.
        description: The text at the top of its own ``--help``; None for none.
        check: Checks the parsed arguments among themselves (raising ``InputError``) before Warp is
            imported, so that a wrong combination is answered at once; None for none.
        stopped: The line that Ctrl-C (or SIGTERM) ends the command with, for a command that writes nothing
            (``serve``); None: "interrupted; nothing partial was left behind".
    """

    name: str
    arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str
    description: str | None = None
    check: Callable[[argparse.Namespace], None] | None = None
    stopped: Callable[[argparse.Namespace], str] | None = None

    def add_to(self, commands) -> None:
        """Add the command to ``commands``, what ``ArgumentParser.add_subparsers`` returned."""
        parser = commands.add_parser(self.name, help=self.help, description=self.description)
        self.arguments(parser)
        add_common_options(parser)
        parser.set_defaults(run=self.run, check=self.check, stopped=self.stopped)


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """Add -q/--quiet and -v/--verbose, which every command takes."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars; warnings and errors only")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="debug messages too, and Warp's own (its start, kernel compilation)")


def in_range(kind: type, low: float, high: float, *, unit: str = ""):
    """An argparse ``type`` that reads an int or float and refuses values outside [low, high], naming
    the range (so the error says what is allowed, at parse time, before any work)."""
    allowed = f"{low:g}..{high:g}{' ' + unit if unit else ''}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            noun = "a whole number" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"'{text}' is not {noun}; use {allowed}") from None
        if not low <= value <= high:  # also refuses NaN
            raise argparse.ArgumentTypeError(f"{text} is out of range; use {allowed}")
        return value

    parse.__name__ = kind.__name__
    return parse


def size_option(what: str = "image size"):
    """An argparse ``type`` for WIDTHxHEIGHT (see :func:`parse_size`)."""
    return _as_option(parse_size, what, "size")


def triple_option(what: str):
    """An argparse ``type`` for R,G,B values that are finite and not negative (see :func:`parse_triple`)."""
    return _as_option(parse_triple, what, "triple")


MIN_EXPOSURE, MAX_EXPOSURE = 1e-12, 1e12
"""The range ``--exposure`` takes: wide enough for any radiance units, far from float32 overflow."""


def exposure_option(text: str):
    """An argparse ``type`` for ``--exposure`` (fit, collection): 'auto' or a positive finite factor."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"'{text}' is neither 'auto' nor a number; use auto or a factor > 0, e.g. 4") from None
    if not (MIN_EXPOSURE <= value <= MAX_EXPOSURE):
        raise argparse.ArgumentTypeError(
            f"{text} is out of range; use auto or a factor in {MIN_EXPOSURE:g}..{MAX_EXPOSURE:g}, e.g. 4")
    return value


def _as_option(parse: Callable, what: str, name: str):
    """``parse(text, what)`` as an argparse ``type``: its InputError becomes argparse's one-line error."""

    def option(text: str):
        try:
            return parse(text, what)
        except InputError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    option.__name__ = name
    return option


MAX_SIDE_PX = 8000
"""Largest accepted image side in pixels (an 8K frame is 7680 wide); larger requests are refused
before any memory is taken."""


def add_pixel_limit_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--max-megapixels``: the largest image a command decodes (a guard against decompression
    bombs and mistakes; raise it for very large scans)."""
    from ..io.images import DEFAULT_MAX_PIXELS

    parser.add_argument(
        "--max-megapixels", type=in_range(float, 0.001, 100_000.0), default=DEFAULT_MAX_PIXELS / 1e6, metavar="MP",
        help=f"refuse images larger than this many megapixels (default {DEFAULT_MAX_PIXELS / 1e6:g}; raise it "
             f"for larger scans)",
    )


def pixel_limit(args) -> int:
    """The pixel budget of ``--max-megapixels``, in pixels."""
    return int(args.max_megapixels * 1_000_000)


def parse_size(text: str, what: str = "image size") -> tuple[int, int]:
    """'480x270' -> (480, 270); ``what`` names the value in the error message."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise InputError(f"{what} '{text}' is not WIDTHxHEIGHT, e.g. 480x270") from None
    if not (1 <= width <= MAX_SIDE_PX and 1 <= height <= MAX_SIDE_PX):
        raise InputError(f"{what} '{text}' is out of range: use 1..{MAX_SIDE_PX} pixels a side, e.g. 480x270")
    return width, height


def parse_triple(text: str, what: str) -> tuple[float, float, float]:
    """'0.7,0.4,0.2' -> (0.7, 0.4, 0.2); one number is repeated; each must be finite and >= 0."""
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        raise InputError(f"{what} '{text}' is not R,G,B numbers, e.g. 0.7,0.42,0.24") from None
    if len(values) == 1:
        values *= 3
    if len(values) != 3:
        raise InputError(f"{what} '{text}' needs 1 or 3 numbers, e.g. 0.7,0.42,0.24")
    if not all(0.0 <= v < float("inf") for v in values):
        raise InputError(f"{what} '{text}' must be finite and not negative, e.g. 0.7,0.42,0.24")
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


def check_output_file(path: Path, *, overwrite: bool, inputs=()) -> None:
    """Raise ``InputError`` unless a file may be written at ``path`` (new, or a regular file with
    ``overwrite``; its folder exists and takes files; not one of the command's ``inputs`` nor inside
    an input folder); removes what killed runs left for it. Before any work starts."""
    from ..io.atomic import check_file_target, clean_stale_partials

    check_not_input(path, inputs)
    if overwrite:
        check_not_capture_image(path)
    clean_stale_partials(path)  # first: a killed run's replaced output may come back and count
    check_file_target(path, overwrite=overwrite)


def check_output_folder(path: Path, *, overwrite: bool, legacy=None, kind: str | None = None, inputs=()) -> None:
    """Raise ``InputError`` unless an output folder may be written at ``path`` (new or empty, or with
    ``overwrite`` one this project wrote, of this ``kind``; its parent exists and takes files; neither
    holding nor inside one of the command's ``inputs``). Before any work starts."""
    from ..io.atomic import check_folder_target, clean_stale_partials

    check_not_input(path, inputs)
    clean_stale_partials(path)  # first: a killed run's replaced output may come back and count
    check_folder_target(path, overwrite=overwrite, legacy=legacy, kind=kind)


CAPTURE_LIGHT_FILES_READ = 20
"""Light files (``*.lp``) read per folder when looking for the capture an existing output belongs to."""


def check_not_capture_image(output) -> None:
    """Raise ``InputError`` if the existing file ``output`` is an image listed by a light file
    (``*.lp``) in its folder or the folder above, or a file of an output folder this project wrote
    (listed by its manifest): a capture's images, and the files of a dataset, are never replaced one
    by one, by any command, ``--overwrite`` or not. Light files that cannot be read are passed over."""
    from ..io.atomic import enclosing_output
    from ..io.lightfile import read_lp

    output = Path(output)
    try:
        if not output.is_file():
            return
    except (OSError, ValueError):
        return
    owner = enclosing_output(output)
    if owner is not None:
        raise InputError(f"output {output} is a file of the {owner[1]} folder {owner[0]} (warp-highlights wrote it); "
                         f"it is replaced only with its whole folder: write elsewhere")
    for folder in dict.fromkeys((output.parent, output.parent.parent)):
        try:
            light_files = sorted(folder.glob("*.lp"))[:CAPTURE_LIGHT_FILES_READ]
        except OSError:
            continue
        for light_file in light_files:
            try:
                names = read_lp(light_file, check_files=False).filenames or []
            except (InputError, OSError, ValueError, UnicodeError):
                continue
            if any(_same_file(folder / name, output) for name in names):
                raise InputError(f"output {output} is an image of the capture {light_file}; a capture's images are "
                                 f"never replaced, --overwrite or not: write elsewhere")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # missing, or a name no file can have
        return False


def check_not_input(output, inputs) -> None:
    """Raise ``InputError`` if ``output`` is one of ``inputs`` (files or folders the command reads),
    lies inside an input folder, or is a folder holding an input; compared by real path and by
    (device, inode), so links and other names of the same file are caught. None inputs are skipped."""
    output = Path(output)
    own = _identities(output)
    for given in inputs:
        if given is None:
            continue
        given = Path(given)
        try:
            status = given.stat()
        except OSError:
            continue  # a missing input is reported by the command's reading
        identity = (status.st_dev, status.st_ino)
        real = Path(os.path.realpath(given))
        if identity == own[0] or real == own[1]:
            raise InputError(f"output {output} is the command's input {given}; give the output another name")
        if given.is_dir() and (identity in own[2] or real in own[3]):
            raise InputError(f"output {output} lies inside the input folder {given}; write it elsewhere")
        if output.is_dir() and _inside(given, output):
            raise InputError(f"output folder {output} holds the command's input {given}; choose another folder")


def _identities(path: Path) -> tuple:
    """``path``'s (device, inode) or None, its real path, and the same for each of its parent folders."""
    try:
        status = path.stat()
        identity = (status.st_dev, status.st_ino)
    except OSError:
        identity = None
    real = Path(os.path.realpath(path))
    parents, reals = set(), set(real.parents)
    for parent in Path(os.path.abspath(path)).parents:
        with contextlib.suppress(OSError):
            status = parent.stat()
            parents.add((status.st_dev, status.st_ino))
    for parent in real.parents:
        with contextlib.suppress(OSError):
            status = parent.stat()
            parents.add((status.st_dev, status.st_ino))
    return identity, real, parents, reals


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` lies inside ``folder`` (by real path or by the folders' device and inode)."""
    _, real, parents, _ = _identities(path)
    try:
        status = folder.stat()
    except OSError:
        return False
    return (status.st_dev, status.st_ino) in parents or Path(os.path.realpath(folder)) in real.parents
