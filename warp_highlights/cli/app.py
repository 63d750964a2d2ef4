"""The ``warp-highlights`` application (also ``python -m warp_highlights``): the parser, built from the
command modules' ``COMMANDS``, and ``main``, which runs one command.

User mistakes end with one line on stderr and exit status 2; Ctrl-C with status 130. Nothing is left
half-written: every output goes to a temporary name first.
"""

from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..model.errors import InputError
from . import dataset, demo, fit, relight, view

__all__ = ["COMMAND_MODULES", "EXIT_INPUT_ERROR", "EXIT_INTERRUPTED", "main"]

COMMAND_MODULES = (dataset, fit, relight, view, demo)
"""The modules whose ``COMMANDS`` make up the command line, in the order ``--help`` lists them."""

EXIT_INPUT_ERROR = 2
"""Exit status after bad input (one line on stderr says what, where and what to do)."""
EXIT_INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT, as shells report it)."""


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    argv = _attach_negative_values(sys.argv[1:] if argv is None else list(argv))
    _quiet_warp(verbose="-v" in argv or "--verbose" in argv)
    parser = _build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help(sys.stderr)
        return EXIT_INPUT_ERROR
    try:
        return args.run(args) or 0
    except InputError as error:
        print(f"warp-highlights {args.command}: error: {error}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except KeyboardInterrupt:
        print(f"warp-highlights {args.command}: interrupted; nothing partial was left behind", file=sys.stderr)
        return EXIT_INTERRUPTED


def _attach_negative_values(argv: list[str]) -> list[str]:
    """'--light -0.5,0.2,1' -> '--light=-0.5,0.2,1': argparse takes a value starting with '-' for an option."""
    result = []
    values = iter(argv)
    for token in values:
        if token == "--light":
            value = next(values, None)
            if value is not None and len(value) > 1 and value[0] == "-" and (value[1].isdigit() or value[1] == "."):
                result.append(f"--light={value}")
                continue
            result.append(token)
            if value is not None:
                result.append(value)
            continue
        result.append(token)
    return result


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="warp-highlights",
        description="Relight reflectance fields with moving specular highlights (NVIDIA Warp).",
    )
    parser.add_argument("--version", action="version", version=f"warp-highlights {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    for module in COMMAND_MODULES:
        for command in module.COMMANDS:
            command.add_to(commands)
    return parser


def _quiet_warp(*, verbose: bool) -> None:
    """Hide Warp's greeting and per-module compile lines unless asked for; keep its warnings."""
    import warp as wp

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING
