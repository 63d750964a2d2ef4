"""Outputs that appear complete or not at all, folders replaced only when this project wrote them.

Every file and folder the project writes is first built beside its target under a hidden name,
``.NAME.partial-<host>-<pid>-<tag>``, and renamed into place when complete. A folder being replaced is
swapped with the new one in one ``renameat2(RENAME_EXCHANGE)`` call where the system has it (Linux),
otherwise moved aside as ``.NAME.replaced-<host>-<pid>-<tag>`` first; an interruption therefore
leaves either the old output or the new one, never a mix.

Every folder written here holds a manifest, ``.warp-highlights.json``, listing its files with their
sizes and modification times. With ``overwrite`` an existing folder is replaced only when it is
empty, or when the manifest is of the same kind and lists every file in it, unchanged (a file the
user added or edited since is never deleted), or, for folders written before manifests existed,
when every file is one the writer makes (``legacy``). Only a regular file is ever replaced by a
file: a device, FIFO or socket is refused, with ``overwrite`` or not, at the first check and again
just before the rename.

Without ``overwrite`` the final step creates the target exclusively (``link`` for a file,
``renameat2(RENAME_NOREPLACE)`` for a folder; where neither exists, a ``.NAME.lock`` file created
exclusively is held for the last check and the rename), so of two writers racing for one new name
one fails with one line; with ``overwrite`` the later one wins whole.

Cleanup: the temporary names a process creates are registered until renamed or removed;
``remove_partials`` removes what is left (the CLI calls it as every command ends), and a run that writes NAME
first removes the ``.NAME.partial-*`` left by processes that no longer exist (SIGKILL, power loss),
and puts back a ``.NAME.replaced-*`` whose replacement never arrived.

Signals: ``handle_termination`` makes SIGTERM raise :class:`Terminated` (a ``KeyboardInterrupt``, so
every cleanup written for Ctrl-C runs for it too), and ``deferred_signals`` holds SIGINT/SIGTERM back
during the few statements that rename or remove, so cleanup is never cut half-way. In a command-line
process, ``guard_stopping`` makes sure a signal ends it even where the main thread cannot take the
interruption (blocked in native code or on a lock): ``STOP_GRACE_SECONDS`` after the signal a watching
thread removes the temporary outputs itself, prints one line and ends the process with 128 + the signal.

This module holds one thing: outputs that appear whole, with the signal handling that keeps them so.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import re
import shutil
import signal
import socket
import stat
import sys
import threading
import time
import uuid
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

from ..model.errors import InputError

__all__ = [
    "FolderTransaction",
    "MANIFEST_NAME",
    "Terminated",
    "atomic_file",
    "atomic_folder",
    "check_file_target",
    "check_folder_target",
    "clean_stale_partials",
    "deferred_signals",
    "describe_os_error",
    "enclosing_output",
    "end_of_command",
    "guard_stopping",
    "handle_termination",
    "received_signal",
    "remove_partials",
]

MANIFEST_NAME = ".warp-highlights.json"
"""The manifest every output folder holds: who wrote it, what kind of output, and its files."""

STALE_FOREIGN_HOST_SECONDS = 24 * 3600
"""A partial output from another machine (shared storage) counts as stale after this long: its
process cannot be asked whether it is alive, and no command of this project runs a day."""

STOP_GRACE_SECONDS = 20.0
"""After SIGINT or SIGTERM, how long a command-line process may take to stop by itself before
``guard_stopping`` ends it: the commands' own cleanup takes well under a second (the interrupts of
``benchmarks/bad_inputs.py`` end within 0.4 s), and the bad-input harness calls a process hung after 60 s."""

_TAG_PATTERN = re.compile(
    r"^\.(?P<name>.+)\.(?P<state>partial|replaced)-(?P<host>[0-9a-f]{6})-(?P<pid>\d+)-[0-9a-f]{8}$")
_RENAME_NOREPLACE = 1
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100

_live: dict[Path, Path] = {}  # temporary path -> the output it is for
_live_lock = threading.Lock()
_deferring = 0
_pending_signal: int | None = None
_received_signal: int | None = None
_hold_after_output = False
_output_committed = False
_IMPORT_RETRY_SECONDS = 0.05
_MAX_IMPORT_RETRIES = 40  # 2 s: an import taking longer (or main() run from an import) is interrupted anyway
_import_retries = 0
_retry_timers: list[threading.Timer] = []
_exclusive: set[str] = set()  # absolute outputs checked without overwrite: created exclusively, never replaced
_resent = 0  # signals this process sent itself (``_deliver_again``) that the stop guard has not yet seen
_resent_lock = threading.Lock()
_guard: _StopGuard | None = None

class Terminated(KeyboardInterrupt):
    """SIGTERM arrived (``kill``, a job scheduler's time limit); handled wherever Ctrl-C is."""


# --- signals ---------------------------------------------------------------------------------------


def handle_termination(*, hold_after_output: bool = False) -> None:
    """Make SIGINT raise ``KeyboardInterrupt`` and SIGTERM raise :class:`Terminated`, both held back
    inside :func:`deferred_signals` and while a module is being imported (a signal there would break
    the import, not stop the work). Only from the main thread; a no-op elsewhere.

    Args:
        hold_after_output: Once a final output is in place, hold signals back until
            :func:`end_of_command`: the command is then finishing (its outputs are new), and stopping
            it half-way through the rest would leave some outputs new and some old.
    """
    global _hold_after_output, _output_committed, _pending_signal, _received_signal, _import_retries
    if threading.current_thread() is not threading.main_thread():
        return
    _hold_after_output, _output_committed, _pending_signal, _received_signal = hold_after_output, False, None, None
    _import_retries = 0
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    if sys.unraisablehook is not _unraisable:
        global _previous_unraisable
        _previous_unraisable, sys.unraisablehook = sys.unraisablehook, _unraisable


def end_of_command() -> int | None:
    """Cancel pending re-deliveries; returns a signal that arrived while signals were held after outputs (the
    command finished all the same), or None. Where an output is in place, signals stay held until the handlers
    are replaced (the next :func:`handle_termination`, or the process's end): one arriving while the finished
    command returns would otherwise report an interruption of outputs that are complete."""
    global _hold_after_output, _output_committed, _pending_signal, _import_retries
    held = _pending_signal if _output_committed and not _deferring else None
    if not _output_committed:
        _hold_after_output = False
    if held is not None:
        _pending_signal = None
    while _retry_timers:
        _retry_timers.pop().cancel()
    _import_retries = 0
    _exclusive.clear()
    return held


def received_signal() -> int | None:
    """The last SIGINT/SIGTERM the handlers saw since :func:`handle_termination`, or None."""
    return _received_signal


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Run the block with SIGINT/SIGTERM held back (when :func:`handle_termination` installed the
    handlers); a signal that came meanwhile is raised as the block ends."""
    global _deferring, _pending_signal
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers run in the main thread only: nothing to hold back here
        return
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
        if _deferring == 0 and _pending_signal is not None and not (_hold_after_output and _output_committed):
            signum, _pending_signal = _pending_signal, None
            raise _interruption(signum)


def _on_signal(signum, frame) -> None:
    global _pending_signal, _received_signal, _import_retries
    _received_signal = signum
    if _deferring or (_hold_after_output and _output_committed):
        _pending_signal = signum
        return
    if _import_retries < _MAX_IMPORT_RETRIES and _swallowing(frame):  # again shortly, where it can propagate
        _deliver_again(signum)
        return
    _import_retries = 0
    raise _interruption(signum)


def _deliver_again(signum: int) -> None:
    """Send ``signum`` to this process again in ``_IMPORT_RETRY_SECONDS`` (``end_of_command`` cancels it)."""
    global _import_retries
    _import_retries += 1
    timer = threading.Timer(_IMPORT_RETRY_SECONDS, _send_again, (signum,))
    timer.daemon = True
    _retry_timers.append(timer)
    timer.start()


def _send_again(signum: int) -> None:
    global _resent
    with _resent_lock:
        _resent += 1
    os.kill(os.getpid(), signum)


def _take_resent() -> bool:
    """Whether a signal the stop guard reads is one this process sent itself (counted off)."""
    global _resent
    with _resent_lock:
        if _resent:
            _resent -= 1
            return True
    return False


def guard_stopping() -> None:
    """In a command-line process, after :func:`handle_termination`: end the process if a SIGINT or SIGTERM
    has not stopped it within ``STOP_GRACE_SECONDS`` (unless it was held back because the command's outputs
    are in place and it is finishing). The signal reaches a watching thread through
    ``signal.set_wakeup_fd``, which the interpreter writes as the signal arrives, whatever the main thread is
    doing. Only from the main thread, once a process; never in a library caller's process."""
    global _guard
    if _guard is None and threading.current_thread() is threading.main_thread():
        _guard = _StopGuard()


class _StopGuard:
    """The watching thread of :func:`guard_stopping` and the socket the interpreter writes signals to."""

    def __init__(self):
        self._reader, writer = socket.socketpair()
        writer.setblocking(False)
        self._writer = writer  # kept open for as long as the process runs
        signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        # a forked child's signals are not this process's: it forks without the guard, which the parent takes back
        os.register_at_fork(before=_unguard, after_in_parent=self._take_back, after_in_child=_unguarded_child)
        threading.Thread(target=self._watch, name="stop-guard", daemon=True).start()

    def _take_back(self) -> None:
        if _guard is self:
            with contextlib.suppress(ValueError):  # forked from a thread other than the main one: never let go
                signal.set_wakeup_fd(self._writer.fileno(), warn_on_full_buffer=False)

    def _watch(self) -> None:
        signum, deadline = None, None
        while True:
            self._reader.settimeout(None if deadline is None else max(0.0, deadline - time.monotonic()))
            try:
                data = self._reader.recv(64)
            except TimeoutError:
                if _hold_after_output and _output_committed:  # finishing with its outputs in place: let it
                    deadline = time.monotonic() + STOP_GRACE_SECONDS
                    continue
                _end_process(signum)
            except OSError:
                return
            if not data:
                return
            for byte in data:
                if byte in (signal.SIGINT, signal.SIGTERM) and deadline is None and not _take_resent():
                    signum, deadline = byte, time.monotonic() + STOP_GRACE_SECONDS


def _unguard() -> None:
    with contextlib.suppress(ValueError):  # only the main thread may; a child forked from another lets go itself
        signal.set_wakeup_fd(-1)


def _unguarded_child() -> None:
    """In a forked child: signals no longer written to the parent's guard (the child has no watching thread)."""
    global _guard
    _guard = None
    _unguard()


def _end_process(signum: int) -> None:
    """Remove this process's temporary outputs, say so in one line and end it with 128 + ``signum``, from
    the stop guard's thread; nothing here waits on a lock the blocked main thread may hold."""
    leftovers = {}
    if _live_lock.acquire(timeout=1.0):
        try:
            leftovers = dict(_live)
            _live.clear()
        finally:
            _live_lock.release()
    else:
        for _ in range(10):
            with contextlib.suppress(RuntimeError):  # changed while copied
                leftovers = dict(_live)
                break
    _clean_up(leftovers)
    stopped = "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted"
    line = (f"warp-highlights: {stopped}; the command had not stopped {STOP_GRACE_SECONDS:g} s later and was ended; "
            "nothing partial was left behind\n")
    try:  # the command's own stderr (file descriptor 2 may point at the null device while native decoders run)
        descriptor = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        descriptor = 2
    with contextlib.suppress(OSError):
        os.write(descriptor, line.encode())
    os._exit(128 + signum)


def _unraisable(unraisable) -> None:
    """``sys.unraisablehook`` while the handlers are installed: an interruption the handler raised in
    a callback the interpreter runs with errors printed and ignored (a weakref callback or finaliser
    that ``_swallowing`` cannot tell from its frames, such as a library's lambda) is not printed as a
    traceback but delivered again shortly, where it can stop the work; anything else goes to the
    hook there was before."""
    signum = _received_signal
    if (isinstance(unraisable.exc_value, KeyboardInterrupt) and signum is not None
        and _import_retries < _MAX_IMPORT_RETRIES):
        _deliver_again(signum)
        return
    _previous_unraisable(unraisable)


def _swallowing(frame) -> bool:
    """Whether an exception raised in ``frame`` would be lost or half-done: inside an import, or in a
    weakref callback or ``__del__``, which the interpreter runs with errors printed and ignored."""
    while frame is not None:
        code = frame.f_code
        if (code.co_filename.startswith("<frozen importlib") or code.co_name == "__del__"
            or code.co_filename.endswith(_WEAKREF_FILE)):
            return True
        frame = frame.f_back
    return False


_WEAKREF_FILE = f"{os.sep}weakref.py"
_previous_unraisable = sys.unraisablehook


def _interruption(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _mark_committed(path: Path) -> None:
    """Record that a final output (not a file inside a temporary folder) is now in place."""
    global _output_committed
    if not any(_TAG_PATTERN.match(part) for part in path.parts):
        _output_committed = True


# --- temporary names -------------------------------------------------------------------------------


def _stable_host_tag() -> str:
    """Six hex digits naming this machine, the same in every process (unlike ``hash``)."""
    return format(zlib.crc32(socket.gethostname().encode()) & 0xFFFFFF, "06x")


def _temporary_path(path: Path, state: str = "partial") -> Path:
    """``.NAME.<state>-<host>-<pid>-<tag>`` beside ``path``, registered until :func:`_forget`."""
    name = f".{_short_name(path.name)}.{state}-{_stable_host_tag()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    temporary = path.with_name(name)
    with _live_lock:
        _live[temporary] = path
    return temporary


_NAME_BYTES = 255 - 40
"""Longest output name kept whole in a temporary name (file systems allow 255 bytes; the suffix
``.partial-<host>-<pid>-<tag>`` and the leading dot take up to 40)."""


def _short_name(name: str) -> str:
    """``name``, or for a name too long to carry the temporary suffix, its start and a checksum."""
    encoded = name.encode("utf-8", "surrogateescape")
    if len(encoded) <= _NAME_BYTES:
        return name
    start = encoded[: _NAME_BYTES - 9].decode("utf-8", "ignore")
    return f"{start}~{zlib.crc32(encoded):08x}"


def _forget(temporary: Path) -> None:
    with _live_lock:
        _live.pop(temporary, None)


def _remove(path: Path) -> None:
    """Remove a file or folder tree if it exists; errors are ignored (best effort cleanup)."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass


def remove_partials() -> list[Path]:
    """Remove every temporary output this process still has (after a failure); returns them.

    A ``.replaced-*`` folder is the previous output moved aside: it is put back where its target is
    missing, so a failure never loses what was there.
    """
    with deferred_signals():
        with _live_lock:
            leftovers = dict(_live)
            _live.clear()
        _clean_up(leftovers)
    return sorted(leftovers)


def _clean_up(leftovers: dict[Path, Path]) -> None:
    """Remove the temporary outputs (temporary -> target); put back a ``.replaced-*`` whose target is missing."""
    for temporary, target in sorted(leftovers.items()):
        match = _TAG_PATTERN.match(temporary.name)
        if match and match["state"] == "replaced" and not target.exists() and temporary.exists():
            with contextlib.suppress(OSError):
                os.rename(temporary, target)
                continue
        _remove(temporary)


def clean_stale_partials(path) -> list[Path]:
    """Remove the temporary outputs for ``path`` left by processes that no longer run.

    ``.NAME.partial-*`` entries of dead processes are removed; a dead process's ``.NAME.replaced-*``
    (the old output, moved aside) is put back when ``path`` is missing and removed otherwise. Entries
    of live processes, and recent ones from other machines, are left alone.

    Returns:
        The entries removed or restored.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    try:
        short = _short_name(path.name)
        names = [entry for entry in os.listdir(parent) if entry.startswith(f".{short}.")]
    except OSError:
        return []
    cleaned = []
    for entry in sorted(names):
        match = _TAG_PATTERN.match(entry)
        if not match or match["name"] != short:
            continue
        candidate = parent / entry
        if candidate in _live or not _is_stale(match["host"], int(match["pid"]), candidate):
            continue
        with deferred_signals():
            if match["state"] == "replaced" and not path.exists():
                with contextlib.suppress(OSError):
                    os.rename(candidate, path)
                    cleaned.append(candidate)
                    continue
            _remove(candidate)
        cleaned.append(candidate)
    return cleaned


def _is_stale(host: str, pid: int, candidate: Path) -> bool:
    """Whether ``candidate``, made by process ``pid`` of the machine tagged ``host``, was left by a
    process that no longer runs (on another machine: when it is older than ``STALE_FOREIGN_HOST_SECONDS``)."""
    if host != _stable_host_tag():
        try:
            return time.time() - candidate.lstat().st_mtime > STALE_FOREIGN_HOST_SECONDS
        except OSError:
            return False
    if pid == os.getpid() or os.name != "posix":
        return False  # ours (another thread's, maybe), or no safe liveness test (os.kill ends processes on Windows)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # EPERM: alive, someone else's
        return False
    return False


# --- files -----------------------------------------------------------------------------------------


def check_file_target(path, *, overwrite: bool) -> None:
    """Raise ``InputError`` unless a file may be written at ``path``: it is new, or a regular file and
    ``overwrite`` is set (never a folder, device, FIFO or socket), and its folder exists and takes
    new files (tried, not guessed). Without ``overwrite`` the later :func:`atomic_file` for ``path``
    creates it exclusively even when called with ``overwrite=True``."""
    path = _as_target(path)
    if path.is_dir():
        raise InputError(f"output {path} is a folder; give a file name")
    _refuse_special(path)
    if path.exists() and not overwrite:
        raise InputError(f"output {path} exists; pass --overwrite to replace it")
    _check_parent(path)
    key = os.path.abspath(path)
    if overwrite:
        _exclusive.discard(key)
    else:
        _exclusive.add(key)


def _refuse_special(path: Path) -> None:
    """InputError if ``path`` (followed through links) is a device, FIFO or socket: never replaced."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return  # missing (or a dangling link): nothing but a name would be replaced
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return
    what = ("a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a FIFO" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
    raise InputError(f"output {path} is {what}; it is never replaced, --overwrite or not: give a file name")


@contextlib.contextmanager
def atomic_file(path, *, overwrite: bool = True, durable: bool = False, checked: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends it replaces ``path``.

    On an exception (Ctrl-C, SIGTERM, a full disk) the temporary file is removed and ``path`` is
    left as it was.

    Args:
        path: The file to write.
        overwrite: Replace an existing regular file; without it (or after :func:`check_file_target`
            without it) the file is created exclusively, so a file that appeared meanwhile stays.
        durable: ``fsync`` the file and its folder, so the new content survives a power loss.
        checked: Clean stale temporaries and check the target first. False skips both, for the many
            files written inside a folder that is itself temporary (or already checked).

    Raises:
        InputError: ``path`` is a folder, a device, FIFO or socket, exists (or appeared while
            writing) without ``overwrite``, or its folder is missing.
    """
    path = _as_target(path)
    key = os.path.abspath(path)
    exclusive = not overwrite or key in _exclusive
    if checked:
        clean_stale_partials(path)
        check_file_target(path, overwrite=not exclusive)
    temporary = _temporary_path(path)
    try:
        with _naming_failures(path):
            yield temporary
        if durable:
            _fsync(temporary)
        with deferred_signals():
            if exclusive:
                _create_exclusively(temporary, path)
            else:
                _refuse_special(path)  # it may have changed since the first check
                if path.is_dir():
                    raise InputError(f"output {path} became a folder while it was being written; nothing was replaced")
                os.replace(temporary, path)
            _forget(temporary)
            _exclusive.discard(key)  # the claim is used: a later write of the same path states its own
            _mark_committed(path)
        if durable:
            _fsync(path.parent)
    finally:
        if temporary in _live:
            with deferred_signals():
                _remove(temporary)
                _forget(temporary)


def _create_exclusively(temporary: Path, path: Path) -> None:
    """Put the file ``temporary`` at ``path`` only if nothing is there (``link``, then the temporary
    name removed; ``renameat2(RENAME_NOREPLACE)`` or a last check where links are not supported)."""
    try:
        os.link(temporary, path, follow_symlinks=False)
    except FileExistsError:
        raise InputError(_appeared(path)) from None
    except OSError as error:
        if error.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS):
            raise
        _rename_new(temporary, path)  # a file system without hard links
        return
    with contextlib.suppress(FileNotFoundError):
        os.unlink(temporary)


def _appeared(path: Path) -> str:
    return (f"output {path} appeared while it was being written; nothing was replaced: choose another name or "
            f"pass --overwrite")


def _rename_new(source: Path, path: Path) -> None:
    """Rename ``source`` to ``path``, refusing (InputError) when ``path`` exists: one
    ``renameat2(RENAME_NOREPLACE)`` call where the system has it, else a check just before the rename."""
    if _renameat2(source, path, _RENAME_NOREPLACE):
        return
    with _name_lock(path):
        if os.path.lexists(path):
            raise InputError(_appeared(path))
        os.rename(source, path)


@contextlib.contextmanager
def _name_lock(path: Path) -> Iterator[None]:
    """Hold ``.NAME.lock`` beside ``path`` (created exclusively, holding ``<host> <pid>``) for a check
    and rename on systems without ``renameat2``: of two writers one holds it, the other is refused
    (InputError). A lock left by a process that no longer runs is taken over once."""
    lock = path.with_name(f".{_short_name(path.name)}.lock")
    for attempt in range(2):
        try:
            descriptor = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            break
        except FileExistsError:
            if attempt or not _lock_is_stale(lock):
                raise InputError(_appeared(path)) from None
            with contextlib.suppress(FileNotFoundError):
                os.unlink(lock)
    with _live_lock:
        _live[lock] = path
    try:
        with os.fdopen(descriptor, "w") as file:
            file.write(f"{_stable_host_tag()} {os.getpid()}\n")
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        _forget(lock)


def _lock_is_stale(lock: Path) -> bool:
    """Whether the name lock ``lock`` was left by a process that no longer runs."""
    try:
        host, pid = lock.read_text().split()
        return _is_stale(host, int(pid), lock)
    except (OSError, ValueError):
        return False  # being written right now, or unreadable: not ours to take


# --- folders ---------------------------------------------------------------------------------------


def check_folder_target(path, *, overwrite: bool, legacy: Callable[[str], bool] | None = None,
                        kind: str | None = None) -> None:
    """Raise ``InputError`` unless :func:`atomic_folder` may write ``path``.

    A new or empty folder is fine. An existing one needs ``overwrite`` and must have been written by
    this project: its manifest lists every file in it, unchanged since (size and modification time),
    or, with no manifest (an older output), ``legacy`` accepts the relative path of every file in it.
    A folder whose manifest names another ``kind`` (a dataset where relit images go) is refused,
    ``overwrite`` or not. Anything else is refused, so no user's file is ever deleted.
    """
    path = _as_target(path)
    if path.exists() and not path.is_dir():
        _refuse_special(path)
        raise InputError(f"output {path} is a file, not a folder; give a folder name")
    if kind is not None and path.is_dir():
        found = _manifest_kind(path)
        if found is not None and found != kind:
            raise InputError(f"output folder {path} holds a warp-highlights {found}, not {kind}; it is never "
                             f"replaced, --overwrite or not: choose another folder")
    if not path.exists():
        _check_parent(path)
        return
    try:
        entries = os.listdir(path)
    except OSError as error:
        raise InputError(describe_os_error(error, path=path, action="read the output folder")) from None
    if not entries:
        _check_parent(path)
        return
    if not overwrite:
        raise InputError(f"output folder {path} exists; pass --overwrite to replace it, or choose another folder")
    problem = _foreign_file(path, legacy)
    if problem is not None:
        name, why = problem
        raise InputError(
            f"output folder {path} holds {name}, {why}; it is not replaced: move that file or choose another folder")
    _check_parent(path)


class FolderTransaction:
    """A folder built under a temporary name beside ``path``, then swapped into place by :meth:`commit`.

    :func:`check_folder_target` runs on creation and again just before the swap; the manifest is
    written at commit, listing every file made in :attr:`temporary`. :meth:`abort` (or a failed
    commit) removes the temporary folder and leaves ``path`` as it was.

    Args:
        path: The output folder.
        kind: What the folder holds (``"dataset"``, ``"relit images"``, ...), kept in the manifest.
        overwrite: Replace an existing folder this project wrote.
        legacy: Accepts the relative paths (``images/0001.exr``) of this kind of output written
            before manifests existed.

    Attributes:
        temporary: The folder to write into until :meth:`commit`.
    """

    def __init__(self, path, *, kind: str, overwrite: bool, legacy: Callable[[str], bool] | None = None):
        self.path, self.kind, self.overwrite, self.legacy = _as_target(path), kind, overwrite, legacy
        clean_stale_partials(self.path)
        check_folder_target(self.path, overwrite=overwrite, legacy=legacy, kind=kind)
        with deferred_signals():
            self.temporary = _temporary_path(self.path)
            try:
                self.temporary.mkdir()
            except BaseException:
                _forget(self.temporary)
                raise
        self.state = "open"

    def commit(self) -> Path:
        """Write the manifest and put the folder in place (swapping out the old one); returns it.

        Only the renames hold signals back; the old folder, swapped out under a temporary name, is
        removed afterwards (by :func:`remove_partials` or the next run, if that is interrupted).
        """
        if self.state != "open":
            raise RuntimeError(f"commit of a folder transaction that is {self.state}")
        old = None
        try:
            _write_manifest(self.temporary, self.kind)
            # nothing appeared meanwhile, and the target is still of this kind
            check_folder_target(self.path, overwrite=self.overwrite, legacy=self.legacy, kind=self.kind)
            with deferred_signals():
                if self.overwrite:
                    old = _swap_in(self.temporary, self.path) if self.path.exists() else None
                    if old is None:
                        os.rename(self.temporary, self.path)
                else:
                    self._place_new()
                if old is None:
                    _forget(self.temporary)
                self.state = "committed"
                _mark_committed(self.path)
        finally:
            if self.state != "committed":
                self.abort()
        if old is not None:
            _remove(old)
            _forget(old)
        return self.path

    def _place_new(self) -> None:
        """Without overwrite: rename into place only if nothing is there (of two writers, one fails
        here); an empty folder that was there is removed first."""
        try:
            _rename_new(self.temporary, self.path)
            return
        except InputError:
            if self.path.is_symlink():
                raise
            try:
                os.rmdir(self.path)  # an empty folder only; of two writers one removes it
            except FileNotFoundError:
                pass  # another writer removed it: the one whose rename comes first wins
            except OSError:
                raise InputError(_appeared(self.path)) from None
        _rename_new(self.temporary, self.path)

    def abort(self) -> None:
        """Remove the temporary folder; ``path`` stays as it was. Safe to call twice."""
        if self.state == "committed":
            return
        with deferred_signals():
            _remove(self.temporary)
            _forget(self.temporary)
            self.state = "aborted"


@contextlib.contextmanager
def atomic_folder(path, *, kind: str, overwrite: bool, legacy: Callable[[str], bool] | None = None) -> Iterator[Path]:
    """Yield a new temporary folder beside ``path``; when the block ends it takes ``path``'s place
    (a :class:`FolderTransaction`). On an exception the temporary folder is removed and ``path`` is
    left as it was."""
    transaction = FolderTransaction(path, kind=kind, overwrite=overwrite, legacy=legacy)
    try:
        with _naming_failures(transaction.path):
            yield transaction.temporary
        transaction.commit()
    finally:
        transaction.abort()


@contextlib.contextmanager
def _naming_failures(path: Path) -> Iterator[None]:
    """An ``OSError`` from the block that names no file (Pillow, pipes) names ``path``."""
    try:
        yield
    except OSError as error:
        if error.errno is not None and not error.filename:
            error.filename = str(path)
        raise


def _swap_in(temporary: Path, path: Path) -> Path:
    """Put the folder ``temporary`` at ``path``; returns where the old folder now is (a registered
    temporary name, for the caller to remove)."""
    if _exchange(temporary, path):
        return temporary  # it now holds the old output, under its partial name
    aside = _temporary_path(path, "replaced")
    os.rename(path, aside)
    try:
        os.rename(temporary, path)
    except BaseException:
        os.rename(aside, path)
        _forget(aside)
        raise
    _forget(temporary)
    return aside


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one system call (Linux renameat2); False where that is not available."""
    return _renameat2(a, b, _RENAME_EXCHANGE)


def _renameat2(a: Path, b: Path, flags: int) -> bool:
    """``renameat2(a, b, flags)`` (Linux); False where the call or the flag is not available. EEXIST
    (``RENAME_NOREPLACE`` onto an existing name) is an InputError; other failures an OSError."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError, TypeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    result = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), flags)
    if result == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False  # a file system (or kernel) without this call or flag: the caller falls back
    if code == errno.EEXIST and flags == _RENAME_NOREPLACE:
        raise InputError(_appeared(b))
    raise OSError(code, os.strerror(code), str(b))


def _files(folder: Path) -> Iterator[tuple[str, Path]]:
    """``(relative posix path, path)`` of every file under ``folder`` but the manifest, sorted."""
    for root, folders, names in os.walk(folder):
        folders.sort()
        for name in sorted(names):
            file = Path(root, name)
            relative = file.relative_to(folder).as_posix()
            if relative != MANIFEST_NAME:
                yield relative, file


def _write_manifest(folder: Path, kind: str) -> None:
    """The manifest: who wrote the folder, its kind, and each file's size and modification time."""
    from .. import __version__

    files = {}
    for relative, file in _files(folder):
        status = file.stat()
        files[relative] = {"bytes": status.st_size, "mtime_ns": status.st_mtime_ns}
    manifest = {"written_by": "warp-highlights", "version": __version__, "kind": kind, "files": files}
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")


def _foreign_file(path: Path, legacy: Callable[[str], bool] | None) -> tuple[str, str] | None:
    """The first file in ``path`` that this project did not write, or changed since, with why; or None."""
    listed = _manifest_files(path)
    for relative, file in _files(path):
        if listed is None:
            if legacy is None or not legacy(relative):
                return relative, "which warp-highlights did not write"
            continue
        if relative not in listed:
            return relative, "which warp-highlights did not write"
        try:
            status = file.stat()
        except OSError:
            continue
        if [status.st_size, status.st_mtime_ns] != listed[relative]:
            return relative, "which was changed after warp-highlights wrote it"
    return None


def _manifest(path: Path) -> dict | None:
    """The warp-highlights manifest in the folder ``path``; None if absent, unreadable or not this project's."""
    try:
        manifest = json.loads((path / MANIFEST_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(manifest, dict) or manifest.get("written_by") != "warp-highlights":
        return None
    return manifest


def _manifest_kind(path: Path) -> str | None:
    """The ``kind`` a warp-highlights manifest in ``path`` names; None if none, unreadable or unnamed."""
    kind = (_manifest(path) or {}).get("kind")
    return kind if isinstance(kind, str) else None


def _manifest_files(path: Path) -> dict[str, list[int]] | None:
    """The manifest's files as ``{relative path: [bytes, mtime_ns]}``; None if absent or unreadable."""
    manifest = _manifest(path)
    if manifest is None:
        return None
    files = manifest.get("files")
    if not isinstance(files, dict):
        return None
    try:
        return {str(name): [int(entry["bytes"]), int(entry["mtime_ns"])] for name, entry in files.items()}
    except (TypeError, KeyError, ValueError):
        return None


def enclosing_output(path, *, levels: int = 3) -> tuple[Path, str] | None:
    """The output folder of this project whose manifest lists the file ``path`` (looked for in its
    folder and up to ``levels`` folders in all), with that folder's kind; None where none does."""
    path = Path(os.path.abspath(path))
    for folder in list(path.parents)[:levels]:
        files = _manifest_files(folder)
        if files is not None and path.relative_to(folder).as_posix() in files:
            return folder, _manifest_kind(folder) or "output"
    return None


def _as_target(path) -> Path:
    """``path`` as given, or resolved where it has no name of its own (``.``, ``..``, ``/``)."""
    path = Path(path)
    if path.name in ("", ".", ".."):
        path = path.resolve()
    if not path.name:
        raise InputError(f"output {path} is the root folder; give a file or folder name")
    return path


# --- checks and messages ---------------------------------------------------------------------------


def _check_parent(path: Path) -> None:
    """InputError unless ``path``'s folder exists and a file can be created in it (a probe file is
    made and removed: permissions, read-only mounts and name limits are found before any work)."""
    parent = path.parent
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist; create it first"
        raise InputError(f"folder {parent} for the output {path.name} {what}")
    probe = _temporary_path(path)
    try:
        with deferred_signals():
            fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
            os.close(fd)
            os.unlink(probe)
    except OSError as error:
        raise InputError(describe_os_error(error, path=path)) from None
    finally:
        _forget(probe)


def _fsync(path: Path) -> None:
    """Flush a file or folder to the disk; best effort (some systems cannot open or sync folders)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems (and folders on some systems) cannot be synced
    finally:
        os.close(fd)


_ADVICE = {
    errno.EACCES: "check its permissions or choose another location",
    errno.EPERM: "check its permissions or choose another location",
    errno.EROFS: "choose an output on a writable disk",
    errno.ENOSPC: "free some space or choose an output on another disk",
    errno.EDQUOT: "free some space within the quota or choose an output on another disk",
    errno.EFBIG: "raise the limit (ulimit -f unlimited) or write a smaller output",
    errno.ENOENT: "a folder on the way does not exist; create it first",
    errno.ENOTDIR: "a part of the path is a file, not a folder; fix the path",
    errno.EISDIR: "that is a folder; give a file name",
    errno.ENAMETOOLONG: "the name is too long for the file system; choose a shorter name",
    errno.EEXIST: "something appeared there meanwhile; choose another name or pass --overwrite",
    errno.ELOOP: "a symbolic link on the way points back at itself; fix or remove the link",
    errno.EMLINK: "the folder holds too many entries; choose another location",
    errno.ENXIO: "it is a device or socket with nothing behind it; give a regular file",
    errno.ETXTBSY: "a running program uses that file; choose another name",
    errno.EIO: "check the disk",
    errno.EMFILE: "too many open files; raise the limit (ulimit -n) or process fewer lights at once",
    errno.ENFILE: "the system has too many open files; close some programs or try again later",
}
_REASONS = {
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EFBIG: "the file size limit (ulimit -f) was reached",
}
"""The true reason where the system's own words mislead (``File too large`` for a per-process limit)."""
_WRITING_ERRNOS = (errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_CACHE_ADVICE = "set WARP_CACHE_PATH to a folder on a writable disk"


def describe_os_error(error: OSError, *, path=None, action: str | None = None) -> str:
    """One line for an operating-system failure: what, which file (the output it was for, not a
    temporary name) and what to do. A failure inside Warp's kernel cache names the cache and
    ``WARP_CACHE_PATH``.

    Args:
        error: The failure.
        path: The file it concerns (default: the error's own file name).
        action: The verb, e.g. ``"write"``; default "write" for a temporary output or a full or
            read-only disk, else "access".
    """
    raw = str(path if path is not None else (error.filename or ""))
    where = _public_name(raw) if raw else "the output"
    if action is None:
        action = "write" if (path is not None or ".partial-" in raw or error.errno in _WRITING_ERRNOS) else "access"
    reason = _REASONS.get(error.errno) or error.strerror or str(error) or type(error).__name__
    cache = _kernel_cache_folder()
    if raw and cache is not None and _is_within(raw, cache):
        return f"cannot {action} Warp's kernel cache {cache} ({where}): {reason}; {_CACHE_ADVICE}"
    advice = _ADVICE.get(error.errno, "check the path and the disk")
    return f"cannot {action} {where}: {reason}; {advice}"


def _kernel_cache_folder() -> str | None:
    """The folder Warp compiles kernels into, once Warp has been imported and configured; else None."""
    warp = sys.modules.get("warp")
    folder = getattr(getattr(warp, "config", None), "kernel_cache_dir", None)
    return str(folder) if folder else None


def _is_within(path: str, folder: str) -> bool:
    try:
        return os.path.commonpath([os.path.abspath(path), os.path.abspath(folder)]) == os.path.abspath(folder)
    except ValueError:  # different drives
        return False


def _public_name(text: str) -> str:
    """A temporary name ``.NAME.partial-...`` (anywhere in the path) -> ``NAME``."""
    parts = Path(text).parts
    return str(Path(*[(m["name"] if (m := _TAG_PATTERN.match(p)) else p) for p in parts])) if parts else text
