"""The ``warp-highlights`` application (also ``python -m warp_highlights``): the parser, built from the
command modules' ``COMMANDS``, and ``main``, which runs one command.

User mistakes and operating-system failures (permissions, a full disk, a missing folder) end with one
line on stderr and exit status 2; Ctrl-C with status 130, SIGTERM with 143. Nothing is left
half-written: every output goes to a temporary name first, and whatever a failed or interrupted
command had started is removed (``io.atomic``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import signal
import sys
import threading

from .. import __version__
from ..io.atomic import (
    Terminated,
    describe_os_error,
    end_of_command,
    guard_stopping,
    handle_termination,
    received_signal,
    remove_partials,
)
from ..model.errors import InputError
from . import collection, dataset, demo, distil, fit, maps, relight, view, web
from .cache import prepare_kernel_cache

__all__ = ["COMMAND_MODULES", "EXIT_INPUT_ERROR", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "OneLineParser", "main"]

COMMAND_MODULES = (dataset, fit, distil, relight, maps, web, collection, view, demo)
"""The modules whose ``COMMANDS`` make up the command line, in the order ``--help`` lists them."""

EXIT_INPUT_ERROR = 2
"""Exit status after bad input (one line on stderr says what, where and what to do)."""
EXIT_INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT, as shells report it)."""
EXIT_TERMINATED = 143
"""Exit status after SIGTERM (128 + 15): ``kill``, a job scheduler's time limit."""


def main(argv: list[str] | None = None) -> int:
    """Run the command line (``argv``, default the process's arguments); returns the exit status."""
    console = argv is None
    previous = _install_signal_handlers()
    if console:
        guard_stopping()  # a process that a signal did not stop in time is ended (never a library caller's)
    try:
        parser = _build_parser()
        argv = _attach_negative_values(sys.argv[1:] if argv is None else list(argv), _value_options(parser))
        try:
            args, unknown = parser.parse_known_args(argv)
            if unknown:  # reported by the command's own parser, so the line names the command
                command = getattr(args, "command", None)
                (parser._command_parsers.get(command, parser) if command else parser).error(
                    f"unrecognized arguments: {' '.join(unknown)}")
        except SystemExit as stop:  # --help, --version, or a one-line usage error (OneLineParser)
            return stop.code if isinstance(stop.code, int) else EXIT_INPUT_ERROR
        if not getattr(args, "command", None):
            parser.print_help(sys.stdout)
            print("warp-highlights: error: no command given; choose one of those listed above", file=sys.stderr)
            return EXIT_INPUT_ERROR
        try:
            if getattr(args, "check", None) is not None:
                args.check(args)  # the arguments among themselves, before Warp too
        except InputError as error:
            print(f"warp-highlights {args.command}: error: {error}", file=sys.stderr)
            return EXIT_INPUT_ERROR
        with python_stderr_apart() if console else contextlib.nullcontext():
            _quiet_warp(verbose=args.verbose)  # after parsing: --help and usage errors never import Warp
            started = _start_warp(args)
            if started is not None:
                return started
            with messages_to_stderr(quiet=args.quiet, verbose=args.verbose):
                return _run(args)
    except KeyboardInterrupt as interruption:  # before the command started: nothing was written
        print("warp-highlights: interrupted while starting; nothing was written", file=sys.stderr)
        return EXIT_TERMINATED if isinstance(interruption, Terminated) else EXIT_INTERRUPTED
    finally:
        if console:  # the process is about to exit: a late signal must not turn success into a crash
            _ignore_signals()
        else:
            _restore_signal_handlers(previous)


def _run(args) -> int:
    """Run the parsed command; every failure becomes one line on stderr and an exit status."""
    name = f"warp-highlights {args.command}"
    stdout = sys.stdout = _WatchedStream(sys.stdout)
    try:
        try:
            return args.run(args) or 0
        finally:
            sys.stdout = stdout.stream
            end_of_command()  # a signal held back once the outputs were in place: the command finished
            remove_partials()  # whatever the command had started to write, on any way out
    except InputError as error:
        message, status = f"error: {error}", EXIT_INPUT_ERROR
    except Terminated:
        stopped = getattr(args, "stopped", None)
        message = f"{stopped(args)} (SIGTERM)" if stopped else "terminated (SIGTERM); nothing partial was left behind"
        status = EXIT_TERMINATED
    except KeyboardInterrupt:
        stopped = getattr(args, "stopped", None)
        message = stopped(args) if stopped else "interrupted; nothing partial was left behind"
        status = EXIT_INTERRUPTED
    except OSError as error:
        if error.filename is None and stdout.failed is not None:
            _silence_stdout()
            message = (f"error: could not print the summary on stdout ({error.strerror or error}); the outputs "
                       "finished before it are in place")
        else:
            message = f"error: {describe_os_error(error)}"
        status = EXIT_INPUT_ERROR
    except MemoryError:
        message, status = ("error: not enough memory for this request; use a smaller --size, fewer lights or frames, "
                           "or a machine with more memory"), EXIT_INPUT_ERROR
    except Exception:
        signum = received_signal()
        if signum is None:
            raise  # a bug, not the user's doing: the traceback is what a report needs
        # a signal that broke a library call (e.g. an import) on its way: still an interruption
        terminated = signum == signal.SIGTERM
        message = ("terminated (SIGTERM)" if terminated else "interrupted") + "; nothing partial was left behind"
        status = EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    # every progress bar was closed as the command unwound (each lives in a with block or an exit stack), so the
    # message starts on its own line
    print(f"{name}: {message}", file=sys.stderr)
    return status


class _WatchedStream:
    """A text stream passed through, remembering the first error its writes or flushes raised (``failed``)."""

    def __init__(self, stream):
        self.stream, self.failed = stream, None

    def write(self, text):
        try:
            return self.stream.write(text)
        except OSError as error:
            self.failed = self.failed or error
            raise

    def flush(self):
        try:
            return self.stream.flush()
        except OSError as error:
            self.failed = self.failed or error
            raise

    def __getattr__(self, name):
        return getattr(self.stream, name)


def _silence_stdout() -> None:
    """Point standard output at the null device, so that what it could not take fails no more (Python's
    last flush at exit included)."""
    with contextlib.suppress(AttributeError, OSError, ValueError, io.UnsupportedOperation):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)


def _install_signal_handlers():
    """SIGINT and SIGTERM interrupt the command (cleanup runs); returns what was installed before."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    handle_termination(hold_after_output=True)
    return previous


def _ignore_signals() -> None:
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)


def _restore_signal_handlers(previous) -> None:
    for signum, handler in (previous or {}).items():
        signal.signal(signum, handler)


def _value_options(parser: argparse.ArgumentParser) -> set[str]:
    """Every option string (of any command) that takes a value."""
    options = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                options |= _value_options(sub)
        elif action.option_strings and action.nargs != 0:
            options.update(action.option_strings)
    return options


def _attach_negative_values(argv: list[str], value_options: set[str]) -> list[str]:
    """'--light -0.5,0.2,1' -> '--light=-0.5,0.2,1': argparse would take a value starting with '-'
    for an option of its own and answer with a usage error instead of our range check."""
    result = []
    values = iter(argv)
    for token in values:
        if token in value_options:
            value = next(values, None)
            if value is not None and len(value) > 1 and value[0] == "-" and (value[1].isdigit() or value[1] == "."):
                result.append(f"{token}={value}")
                continue
            result.append(token)
            if value is not None:
                result.append(value)
            continue
        result.append(token)
    return result


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (what is wrong, where to look), exit 2."""

    def error(self, message: str):
        self.exit(EXIT_INPUT_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="warp-highlights",
        description="Relight reflectance fields with moving specular highlights (NVIDIA Warp).",
    )
    parser.add_argument("--version", action="version", version=f"warp-highlights {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    for module in COMMAND_MODULES:
        for command in module.COMMANDS:
            command.add_to(commands)
    parser._command_parsers = dict(commands.choices)
    return parser


def _start_warp(args) -> int | None:
    """Warp's kernel cache checked (or moved under the temporary folder, with one warning line) and Warp
    started; None when it did, else the exit status after one line on stderr."""
    name = f"warp-highlights {args.command}"
    try:
        warning = prepare_kernel_cache()
        if warning is not None:
            print(f"{name}: {warning}", file=sys.stderr)
        _init_warp(verbose=args.verbose)
    except InputError as error:
        print(f"{name}: error: {error}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except OSError as error:
        print(f"{name}: error: Warp could not start: {describe_os_error(error, action='create')}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    return None


def _init_warp(*, verbose: bool) -> None:
    """Start Warp now; on a machine without an NVIDIA driver, without its 'CUDA driver not found'
    warning (expected there, and it would come before our own one-line messages) unless ``-v``."""
    import warp as wp

    if verbose or _cuda_driver_present():
        return  # Warp starts on first use, saying what it has to say
    from ..io.images import quiet_native_stderr

    with quiet_native_stderr():
        wp.init()


def _cuda_driver_present() -> bool:
    """Whether the NVIDIA driver library can be loaded here (what Warp looks for)."""
    import ctypes

    for name in ("libcuda.so", "libcuda.so.1", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextlib.contextmanager
def python_stderr_apart():
    """Python's ``sys.stderr`` (progress bars, messages, warnings, the last error line) written through a
    copy of file descriptor 2 while a command runs: the image readers point fd 2 itself at the null
    device while native decoders run in threads (``io.images.quiet_native_stderr``), which would hide them."""
    original = sys.stderr
    try:
        original.flush()
        copy = os.dup(original.fileno())
    # no descriptor behind it (captured, embedded)
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        yield
        return
    stream = io.TextIOWrapper(io.FileIO(copy, "w"), encoding=original.encoding or "utf-8", errors="backslashreplace",
                              line_buffering=True,
                              write_through=True)
    sys.stderr = stream
    try:
        yield
    finally:
        sys.stderr = original
        with contextlib.suppress(OSError, ValueError):
            stream.close()


@contextlib.contextmanager
def messages_to_stderr(*, quiet: bool, verbose: bool):
    """Show the library's messages (the ``warp_highlights`` logger) on stderr while a command runs,
    indented under its progress bars: INFO by default, only warnings with ``-q``, DEBUG with ``-v``."""
    logger = logging.getLogger("warp_highlights")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("  %(message)s"))
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    previous = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(previous)


def _quiet_warp(*, verbose: bool) -> None:
    """Hide Warp's greeting and per-module compile lines unless asked for; keep its warnings."""
    import warp as wp

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING
