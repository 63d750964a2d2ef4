"""Robustness harness behind the reliability table (docs/reliability.md): many hundreds of bad inputs
through the ``warp-highlights`` command line, as a new user (or a hostile file) would give them.

    python benchmarks/bad_inputs.py                      # every case (several minutes on a 2-core CPU)
    python benchmarks/bad_inputs.py --quick              # about 60 cases sampled from all categories
    python benchmarks/bad_inputs.py --only images fields --timeout 60 --seed 14 --work /tmp/bad

The command line promises: every bad input or operating-system failure ends with exit status 2 and
exactly one line on stderr starting ``warp-highlights COMMAND: error:`` (no Python traceback),
interrupts end with 130 (SIGINT) or 143 (SIGTERM), and nothing partial is left behind. This script
checks the promise. In a temporary folder it renders a tiny dataset (``render sphere D --lights 16
--size 32x18 --samples 1 --heldout centroids``) and fits a tiny field (``fit D -o F.whf --device
cpu``), derives the bad inputs from them, and runs every case, in these categories:

- ``light files``: malformed ``.lp`` files (counts, columns, NaN/inf/zero vectors, encodings, binary
  garbage, duplicates, 3 lights, lights on one ring, FIFOs and links) through ``info`` and ``fit``;
- ``field files``: truncated, bit-flipped, entries removed or replaced, foreign zips, future versions
  through ``relight``, ``animate``, ``evaluate`` and ``view --screenshot``;
- ``images``: garbage, truncated, decompression bombs, an EXR claiming 10^9 pixels, black and white
  captures, mixed sizes and kinds through ``info``, ``fit`` and ``sheet``;
- ``options``: every numeric option of every command at 0, negative, huge, NaN, inf and not a number;
  ``--set``, ``--path``, ``--light``, ``--methods``, ``--triangle``, ``--device`` and friends;
- ``outputs``: every command that writes, into a read-only folder and a full file system (tmpfs
  mounts), a missing parent, a file where a folder is expected and back, an existing output without
  ``--overwrite``, ``--overwrite`` onto a folder holding a user's file, names over 255 bytes;
- ``interrupts``: SIGINT and SIGTERM sent to running commands (in subprocesses);
- ``targets``, ``races``, ``environment``, ``captures``, ``serve`` (``harm_cases.py``): outputs that are
  devices, FIFOs, sockets, folders of another kind or the command's own inputs; two processes writing
  one name at once; a read-only home or kernel cache, the file size limit and a full standard output;
  a field used with another capture's images; requests that must not block or leak the local server.

Most cases run in-process through ``warp_highlights.cli.main`` (Warp and the kernels load once), in a
worker process, so that a crash (a C library killing the process) or a hang that ignores SIGALRM costs
the case and not the run: the worker is restarted. Every case passes ``-q`` (no progress bars, which
would be lines on stderr too); stdout and stderr are captured at the Python level and at the file
descriptor level (what C code prints). Fits use a shortened schedule (``--set`` overrides, shown in
each command line; ``--full-fits`` drops them). Outcomes of a case:

- ``one-line error``: exit status 2, exactly one line on stderr starting ``warp-highlights COMMAND:
  error:`` (for ``interrupts``: status 130/143, at most one line);
- ``accepted``: exit status 0; fine only where the input is valid (cases whose input is known to be
  bad and were accepted anyway are listed separately, as are valid inputs that were refused);
- ``traceback``: an exception escaped ``main()``, or stderr holds a Python traceback;
- ``hang``: not finished within ``--timeout`` seconds (SIGALRM in the worker);
- ``other``: anything else (another exit status, several lines, a crash of the process);
- ``litter`` (counted besides the outcome): a hidden ``.*.partial-*``/``.*.replaced-*`` entry left
  anywhere in the case's folder or the shared inputs, or an output that a failed command created or
  changed;
- ``data lost`` (counted besides the outcome): a path the case protects (an input, a user's file, a
  device) or the shared inputs changed or removed, whatever the exit status, or two racing writers
  that both said they wrote one name;
- ``failed check``: the case's own check found a wrong message or a missing or mixed output.

Prints the table (and every failing case with a command line that reproduces it; the inputs of
failing cases are kept in the work folder). Writes everything to $OUT/bad_inputs.json when OUT is set.
Needs root for the tmpfs mounts (``mount -t tmpfs``); without them those cases are skipped and the
output says so.

This script holds one thing: the bad-input harness, its cases grouped by category.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import gzip
import hashlib
import importlib.util
import io
import json
import multiprocessing
import os
import platform
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CATEGORIES = ("light files", "field files", "images", "options", "outputs", "interrupts", "targets", "races",
              "environment", "captures", "serve")
COMMANDS = ("render", "info", "sheet", "fit", "relight", "animate", "evaluate", "view", "demo", "export", "maps",
            "serve", "collection")
OUTCOMES = ("error", "accepted", "traceback", "hang", "other")
LITTER_NAME = re.compile(r"^\..+\.(partial|replaced)-")
GRACE_SECONDS = 30.0
"""How long past the limit a worker may take to answer SIGALRM before it is killed."""
FAST_FIT = ["--set", "estimation.iterations=100", "--set", "estimation.densify_until=60", "--set",
            "estimation.densify_every=20",
            "--set", "retarget.rigid_iterations=10", "--set", "retarget.iterations=20"]
"""A short fit schedule (the bad inputs concern loading and checking, not the optimisation)."""
MEMORY_LIMIT_GB = 12.0
"""The worker's address-space limit (RLIMIT_AS): a runaway allocation fails with MemoryError in the
worker instead of waking the machine's OOM killer."""


# --- the worker: runs main() in-process -------------------------------------------------------------


class CaseTimeout(BaseException):
    """Raised by SIGALRM in the worker when a case runs past its limit (a BaseException, so that no
    ``except Exception`` in the package takes it for an error of its own)."""


def _on_alarm(signum, frame):
    raise CaseTimeout()


def _worker_main(conn, memory_limit_gb: float) -> None:
    """The worker process: load the CLI once, then run every request it is sent."""
    import resource

    if memory_limit_gb > 0:
        limit = int(memory_limit_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    import threading

    from tqdm import tqdm

    from warp_highlights.cli import main

    tqdm.set_lock(threading.RLock())  # not a multiprocessing lock: a killed worker leaves no semaphore behind
    signal.signal(signal.SIGALRM, _on_alarm)
    conn.send({"ready": True})
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        conn.send(_run_in_process(main, request["argv"], request["timeout"]))


def _run_in_process(main, argv: list[str], timeout: float) -> dict:
    """``main(argv)`` with stdout/stderr captured (Python and file descriptors) under a SIGALRM limit."""
    out, err = io.StringIO(), io.StringIO()
    result = {"rc": None, "exception": None, "hang": False, "crashed": None}
    started = time.perf_counter()
    try:
        with _native_capture() as native:
            with warnings.catch_warnings(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                # catch_warnings: a warning is shown again in every case, as in a fresh process
                signal.setitimer(signal.ITIMER_REAL, timeout)
                try:
                    result["rc"] = main(list(argv))
                except SystemExit as stop:  # escaped main(): Python would exit with this status
                    result["rc"] = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
                    if isinstance(stop.code, str):
                        print(stop.code, file=sys.stderr)
                except CaseTimeout:
                    raise
                except BaseException:  # noqa: BLE001 (whatever escapes main() is what we are looking for)
                    signal.setitimer(signal.ITIMER_REAL, 0)
                    result["exception"] = traceback.format_exc()
                finally:
                    signal.setitimer(signal.ITIMER_REAL, 0)
    except CaseTimeout:
        result["hang"] = True
    result["seconds"] = time.perf_counter() - started
    result["stdout"] = out.getvalue() + native.get("stdout", "")
    result["stderr"] = err.getvalue() + native.get("stderr", "")
    return result


@contextlib.contextmanager
def _native_capture():
    """Send file descriptors 1 and 2 to temporary files for the block (what C and C++ code print)."""
    import ctypes

    captured: dict[str, str] = {}
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    files = [tempfile.TemporaryFile(), tempfile.TemporaryFile()]
    os.dup2(files[0].fileno(), 1)
    os.dup2(files[1].fileno(), 2)
    try:
        yield captured
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)
        for fd, dup in zip((1, 2), saved):
            os.dup2(dup, fd)
            os.close(dup)
        for key, handle in zip(("stdout", "stderr"), files):
            handle.seek(0)
            captured[key] = handle.read().decode("utf-8", "replace")
            handle.close()


class Worker:
    """The parent's handle on the worker process; restarts it after a crash or a hang."""

    def __init__(self, memory_limit_gb: float):
        self.memory_limit_gb = memory_limit_gb
        self.process = None
        self.conn = None
        self.starts = 0

    def _start(self) -> None:
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(target=_worker_main, args=(child, self.memory_limit_gb),
                                       name="bad-inputs-worker", daemon=True)
        self.process.start()
        child.close()
        if not self.conn.poll(600):
            raise RuntimeError("the worker process did not start")
        self.conn.recv()
        self.starts += 1

    def run(self, argv: list[str], timeout: float) -> dict:
        if self.process is None or not self.process.is_alive():
            self._start()
        try:
            self.conn.send({"argv": [str(a) for a in argv], "timeout": timeout})
        except OSError:  # it died since the last case: once more with a fresh one
            self.stop()
            self._start()
            self.conn.send({"argv": [str(a) for a in argv], "timeout": timeout})
        started = time.perf_counter()
        try:
            if self.conn.poll(timeout + GRACE_SECONDS):
                result = self.conn.recv()
                if result.get("hang"):
                    self.stop()  # threads of the stopped command may still run: start afresh
                return result
        except (EOFError, OSError):
            self.process.join(10)
            code = self.process.exitcode
            self.stop()
            what = (f"killed by {signal.Signals(-code).name}" if code is not None and code < 0
                    else f"exited with status {code}")
            return {"rc": code, "exception": None, "hang": False, "crashed": f"the process died: {what}",
                    "stdout": "", "stderr": "", "seconds": time.perf_counter() - started}
        self.stop()
        return {"rc": None, "exception": None, "hang": True, "crashed": None, "stdout": "", "stderr": "",
                "seconds": time.perf_counter() - started,
                "note": f"ignored SIGALRM for {GRACE_SECONDS:.0f} s more; killed"}

    def stop(self, gently: bool = False) -> None:
        if self.process is not None:
            if gently and self.process.is_alive():
                with contextlib.suppress(OSError):
                    self.conn.send(None)
                self.process.join(20)
            if self.process.is_alive():
                self.process.kill()
            self.process.join(10)
        if self.conn is not None:
            self.conn.close()
        self.process = self.conn = None


# --- cases ------------------------------------------------------------------------------------------


class Skip(Exception):
    """A case that cannot run here (no tmpfs mounts, no off-screen rendering)."""


@dataclass
class Run:
    """What a built case runs, and what to check afterwards."""

    argv: list
    outputs: list = field(default_factory=list)
    """Paths the command may write: after a failure each must be as it was before."""
    check: Callable[[dict], str | None] | None = None
    """Further check after the run: a problem (a failed check: a wrong message, a missing output) or None."""
    protected: list = field(default_factory=list)
    """Paths that must be exactly as they were after the run, whatever its outcome (inputs, a user's files,
    devices): a change is data lost."""
    runner: Callable[[Run, Context], dict] | None = None
    """Runs the case instead of the worker (subprocesses: several at once, another environment, a server)."""
    cleanup: Callable[[], None] | None = None
    note: str = ""
    interrupt: tuple[int, float] | None = None
    """(signal, seconds): run as a subprocess and send the signal that long after main() started."""


@dataclass
class Case:
    category: str
    label: str
    build: Callable[[Path], Run]
    expect: str | None = None
    """'error': the input is bad and must be refused; 'ok': valid, must be accepted; None: either."""


@dataclass
class Result:
    case: Case
    index: int
    argv: list
    outcome: str
    rc: int | None
    seconds: float
    stderr: str
    exception: str | None
    litter: list
    folder: Path
    note: str = ""
    lost: list = field(default_factory=list)
    problems: list = field(default_factory=list)

    @property
    def failing(self) -> bool:
        return self.outcome in ("traceback", "hang", "other") or bool(self.litter or self.lost or self.problems)

    def command(self) -> str:
        line = "warp-highlights " + shlex.join(str(a) for a in self.argv)
        return line


class Context:
    """Paths and services the case builders share."""

    def __init__(self, work: Path, worker: Worker, timeout: float, fast: list[str], rng: random.Random):
        self.work, self.worker, self.timeout, self.fast, self.rng = work, worker, timeout, fast, rng
        self.base = work / "base"
        self.cases = work / "cases"
        self.dataset = self.base / "D"
        self.field = self.base / "F.whf"
        self.mounts: list[Path] = []
        self.mount_ok = False
        self.mount_note = ""
        self.view_ok = False
        self.view_note = ""
        self._cache: dict[str, object] = {}

    # shared inputs, made on first use
    def cached(self, key: str, make: Callable[[], object]):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def cli(self, argv: list) -> dict:
        """Run a command in the worker (for builders that need a real earlier output)."""
        result = self.worker.run([str(a) for a in argv], max(self.timeout, 300.0))
        if result.get("rc") != 0:
            raise RuntimeError(f"set-up command failed: warp-highlights "
                               f"{shlex.join(map(str, argv))}\n{result.get('stderr')}{result.get('exception') or ''}")
        return result

    def mount(self, path: Path, options: str) -> None:
        if not self.mount_ok:
            raise Skip(f"tmpfs mounts are not possible here ({self.mount_note})")
        path.mkdir(parents=True, exist_ok=True)
        subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], check=True, capture_output=True)
        self.mounts.append(path)

    def umount(self, path: Path) -> None:
        if path not in self.mounts:
            return
        done = subprocess.run(["umount", str(path)], capture_output=True)
        if done.returncode != 0:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)
        self.mounts.remove(path)

    def umount_all(self) -> None:
        for path in list(reversed(self.mounts)):
            self.umount(path)


def put(path: Path, data) -> Path:
    """Write ``data`` (bytes or str) to ``path``, replacing whatever is there (never writing through a
    hard link into a shared input)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_symlink() or path.exists():
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    path.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return path


def link_tree(source: Path, target: Path) -> Path:
    """Hard-link every file of ``source`` into ``target`` (cheap copies of the shared inputs)."""
    for root, _, names in os.walk(source):
        folder = target / Path(root).relative_to(source)
        folder.mkdir(parents=True, exist_ok=True)
        for name in names:
            try:
                os.link(Path(root, name), folder / name)
            except OSError:
                shutil.copy2(Path(root, name), folder / name)
    return target


def lp_text(names, directions, number=repr) -> str:
    lines = [str(len(names))] + [f"{n} {number(float(x))} {number(float(y))} {number(float(z))}"
                                 for n, (x, y, z) in zip(names, directions)]
    return "\n".join(lines) + "\n"


def ring(count: int, elevation_deg: float) -> np.ndarray:
    """``count`` directions at one elevation (z towards the camera), evenly spread in azimuth."""
    azimuth = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    e = np.radians(elevation_deg)
    return np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.full(count, np.sin(e))], axis=1)


def npy(array, **kwargs) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, **kwargs)
    return buffer.getvalue()


def npy_with_header(header: dict, data: bytes, version=(1, 0)) -> bytes:
    """A .npy file with a header of our own (claims the data need not keep)."""
    text = repr({"descr": header["descr"], "fortran_order": header["fortran_order"],
                 "shape": tuple(header["shape"])}).encode("latin-1")
    size = 4 if version[0] >= 2 else 2
    pad = 64 - (6 + 2 + size + len(text) + 1) % 64
    text += b" " * pad + b"\n"
    return b"\x93NUMPY" + bytes(version) + len(text).to_bytes(size, "little") + text + data


# --- the inputs everything starts from --------------------------------------------------------------


def set_up(ctx: Context) -> None:
    """Render the tiny dataset and fit the tiny field (in the worker), check mounts and off-screen
    rendering, and make the shared inputs derived from them."""
    from warp_highlights.io.images import read_image
    from warp_highlights.io.lightfile import read_lp

    ctx.base.mkdir(parents=True)
    ctx.cases.mkdir(parents=True)
    ctx.cli(["render", "sphere", ctx.dataset, "--lights", "16", "--size", "32x18", "--samples", "1", "--heldout",
             "centroids", "--device", "cpu", "-q"])
    # a Lambertian diffuse part, so that the field file holds every kind of entry the cases damage
    ctx.cli(["fit", ctx.dataset, "-o", ctx.field, "--diffuse", "lambert", "--device", "cpu", "-q"])
    view = ctx.worker.run(["view", str(ctx.field), "--screenshot", str(ctx.base / "view-check.png"), "-q"],
                          max(ctx.timeout, 300.0))
    ctx.view_ok = view.get("rc") == 0
    if ctx.view_ok:
        ctx.view_note = "view --screenshot renders off screen"
    else:
        why = last_lines(view.get("exception") or view.get("stderr") or "", 1)
        ctx.view_note = "view skipped: off-screen rendering failed here" + (f" ({why[0]})" if why else "")
    with contextlib.suppress(FileNotFoundError):
        (ctx.base / "view-check.png").unlink()

    lights = read_lp(ctx.dataset / "lights.lp")
    ctx.names = [Path(n).name for n in lights.filenames]
    ctx.directions = np.asarray(lights.directions, dtype=np.float64)
    ctx.images = [read_image(ctx.dataset / "images" / n) for n in ctx.names]

    # a plain capture: images and lights.lp, no ground truth (what a user brings), as EXR and as PNG
    capture = ctx.base / "capture-exr"
    link_tree(ctx.dataset / "images", capture / "images")
    put(capture / "lights.lp", lp_text([f"images/{n}" for n in ctx.names], ctx.directions))
    ctx.capture_exr = capture
    ctx.lp8 = put(ctx.base / "eight.lp", lp_text([f"l{i}.exr" for i in range(8)], ctx.directions[:8]))
    ctx.other_dataset = ctx.base / "D8"
    ctx.cli(["render", "sphere", ctx.other_dataset, "--lights", "8", "--size", "32x18", "--samples", "1", "--device",
             "cpu", "-q"])

    ctx.mount_ok, ctx.mount_note = _can_mount(ctx.base / "mount-check")


def _can_mount(path: Path) -> tuple[bool, str]:
    if os.name != "posix" or shutil.which("mount") is None:
        return False, "no mount command"
    path.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(path)], capture_output=True,
                              text=True)
        if done.returncode != 0:
            return False, (done.stderr.strip() or f"mount exited with {done.returncode}")
        subprocess.run(["umount", str(path)], check=True, capture_output=True)
        return True, "tmpfs mounts work (read-only and full-disk cases run)"
    finally:
        with contextlib.suppress(OSError):
            path.rmdir()


def rgb8(ctx: Context, index: int) -> np.ndarray:
    from warp_highlights.io.images import display_rgb8

    return display_rgb8(ctx.images[index])


def png_bytes(array: np.ndarray, mode: str | None = None, **save) -> bytes:
    from PIL import Image

    image = Image.fromarray(array) if mode is None else Image.fromarray(array).convert(mode)
    buffer = io.BytesIO()
    image.save(buffer, "PNG", **save)
    return buffer.getvalue()


def jpeg_bytes(array: np.ndarray, mode: str | None = None, **save) -> bytes:
    from PIL import Image

    image = Image.fromarray(array) if mode is None else Image.fromarray(array).convert(mode)
    buffer = io.BytesIO()
    image.save(buffer, "JPEG", quality=95, **save)
    return buffer.getvalue()


def write_exr(path: Path, channels: dict, *, half: bool = False) -> Path:
    import OpenEXR

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() or path.is_symlink():
        path.unlink()
    data = {name: np.ascontiguousarray(plane.astype(np.float16 if half else np.float32))
            for name, plane in channels.items()}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, data).write(str(path))
    return path


def exr_bytes(channels: dict, *, half: bool = False) -> bytes:
    with tempfile.TemporaryDirectory() as scratch:
        return write_exr(Path(scratch, "x.exr"), channels, half=half).read_bytes()


def rgb_channels(image: np.ndarray) -> dict:
    return {c: image[:, :, i] for i, c in enumerate("RGB")}


def png16_bytes(image: np.ndarray) -> bytes:
    """A 16-bit colour PNG (the package reads these through OpenImageIO), written with the package."""
    from warp_highlights.io.images import write_image

    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch, "x.png")
        write_image(path, image, bits=16)
        return path.read_bytes()


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    import struct

    pos, chunks = 8, []
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        chunks.append((kind, data[pos + 8 : pos + 8 + length]))
        pos += 12 + length
    return chunks


def png_from_chunks(chunks) -> bytes:
    import struct
    import zlib

    out = b"\x89PNG\r\n\x1a\n"
    for kind, body in chunks:
        out += struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    return out


def bomb_png(ctx: Context) -> Path:
    """A 20000x20000 one-bit PNG: a few tens of kB on disk, 400 megapixels once decoded."""

    def make():
        from PIL import Image

        path = ctx.base / "bomb.png"
        Image.new("1", (20000, 20000)).save(path, "PNG")
        return path

    return ctx.cached("bomb", make)


def huge_exr(ctx: Context) -> Path:
    """A 32x18 EXR whose header's dataWindow was patched to claim 31623 x 31623 (10^9) pixels."""

    def make():
        import struct

        data = bytearray(exr_bytes(rgb_channels(ctx.images[0])))
        key = b"dataWindow\x00box2i\x00"
        at = data.index(key) + len(key) + 4
        x0, y0, _, _ = struct.unpack("<4i", data[at : at + 16])
        data[at : at + 16] = struct.pack("<4i", x0, y0, x0 + 31622, y0 + 31622)
        return put(ctx.base / "huge.exr", bytes(data))

    return ctx.cached("huge-exr", make)


def huge_jpeg(ctx: Context) -> bytes:
    """A small JPEG whose frame header claims 65000 x 65000 pixels."""
    import struct

    data = bytearray(jpeg_bytes(rgb8(ctx, 0)))
    at = data.index(b"\xff\xc0")
    data[at + 5 : at + 9] = struct.pack(">HH", 65000, 65000)
    return bytes(data)


# --- category 1: light files ------------------------------------------------------------------------


def light_file_cases(ctx: Context) -> list[Case]:
    names = [f"images/{n}" for n in ctx.names]
    dirs = ctx.directions
    body = lp_text(names, dirs)
    rows = body.splitlines()

    def lines_with(index: int, text: str) -> str:
        changed = list(rows)
        changed[1 + index] = text
        return "\n".join(changed) + "\n"

    def vector(x, y, z) -> str:
        return lines_with(5, f"{names[5]} {x} {y} {z}")

    def geometry(directions, count=None) -> str:
        count = len(directions) if count is None else count
        return lp_text(names[:count], directions[:count])

    rng = random.Random(ctx.rng.random())
    garbage = bytes(rng.randrange(256) for _ in range(4096))

    def fifo(folder):
        os.mkfifo(folder / "lights.lp")

    def symlink(target):
        return lambda folder: os.symlink(target, folder / "lights.lp")

    def loop(folder):
        os.symlink(folder / "loop-b.lp", folder / "lights.lp")
        os.symlink(folder / "lights.lp", folder / "loop-b.lp")

    def folder_named(folder):
        (folder / "lights.lp").mkdir()

    def two_files(folder):
        put(folder / "dirs.lp", body)
        put(folder / "other.lp", body)

    def latin1(folder):
        # a non-UTF-8 name on disk too
        os.link(folder / "images" / ctx.names[5], os.fsencode(folder / "images") + b"/imag\xe9.exr")
        (folder / "images" / ctx.names[5]).unlink()
        put(folder / "lights.lp",
            lines_with(5, f"images/imag\xe9.exr {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}").encode("latin-1"))

    def bad_heldout(text):
        return lambda folder: put(folder / "heldout.lp", text)

    many = 300_000
    big = "\n".join([str(many)] + [f"images/missing_{i:06d}.exr 0.1 0.2 {1 + i * 1e-6!r}" for i in range(many)]) + "\n"
    cluster = dirs[0] + 0.001 * np.random.default_rng(1).normal(size=(16, 3))

    E, OK = "error", "ok"
    variants = [
        # label, content (str/bytes) or a function(folder) that makes lights.lp, expect (info, fit)
        ("empty file", b"", (E, E)),
        ("blank lines only", "\n\n  \n\t\n", (E, E)),
        ("the count alone", "16\n", (E, E)),
        ("the count is a word", "sixteen\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("negative count", "-16\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count 0 and no lines", "0\n", (E, E)),
        ("count 0 and 16 lines", "0\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count written 16.0", "16.0\n" + "\n".join(rows[1:]) + "\n", (None, None)),
        ("count written 1e3", "1e3\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count 10^30", "1" + "0" * 30 + "\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count 15 for 16 lines", "15\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count 17 for 16 lines", "17\n" + "\n".join(rows[1:]) + "\n", (E, E)),
        ("count followed by a word", "16 lights\n" + "\n".join(rows[1:]) + "\n", (None, None)),
        ("a line without z", lines_with(5, f"{names[5]} 0.1 0.2"), (E, E)),
        ("a line with a fifth column", lines_with(5, f"{names[5]} 0.1 0.2 0.9 1.0"), (E, E)),
        ("every line with a fifth column", "\n".join([rows[0]] + [r + " 1.0" for r in rows[1:]]) + "\n", (E, E)),
        ("names only", "\n".join([rows[0]] + names) + "\n", (E, E)),
        ("numbers only, no names", "\n".join([rows[0]] + [" ".join(r.split()[1:]) for r in rows[1:]]) + "\n", (E, E)),
        ("NaN direction", vector("nan", "0", "1"), (E, E)),
        ("inf direction", vector("inf", "0", "1"), (E, E)),
        ("-inf direction", vector("0", "-inf", "1"), (E, E)),
        ("zero vector", vector("0", "0", "0"), (E, E)),
        ("negative zero vector", vector("-0", "-0.0", "-0e0"), (E, E)),
        ("denormal vector 1e-320,0,0", vector("1e-320", "0", "0"), (None, None)),
        ("tiny vector 1e-200 (its square underflows)", vector("1e-200", "1e-200", "1e-200"), (None, None)),
        ("huge vector 1e200 (its square overflows)", vector("1e200", "1e200", "1e200"), (None, None)),
        ("1e308 in all three", vector("1e308", "1e308", "1e308"), (None, None)),
        ("1e999 (overflows to inf)", vector("1e999", "0", "1"), (E, E)),
        ("hexadecimal float", vector("0x1p-2", "0", "1"), (E, E)),
        ("numbers with underscores", vector("1_0", "0", "1"), (E, E)),
        ("non-UTF-8 (latin-1) file name", latin1, (None, None)),
        ("invalid UTF-8 bytes in a number",
         lines_with(5, f"{names[5]} 0.1 0.2 0.9").encode().replace(b"0.2", b"0.\xff2"), (E, E)),
        ("4 kB of binary garbage", garbage, (E, E)),
        ("garbage after a valid file", body.encode() + garbage, (E, E)),
        ("NUL bytes inside a line", lines_with(5, f"{names[5]}\x00 0.1 0.2 0.9"), (E, E)),
        ("UTF-16 with a BOM (valid)", body.encode("utf-16"), (OK, OK)),
        ("UTF-16 without a BOM", body.encode("utf-16-le"), (E, E)),
        ("UTF-32", body.encode("utf-32"), (E, E)),
        ("BOM, CRLF, tabs and decimal commas (valid)", ("\ufeff" + lp_text(names, dirs,
                                                                           number=lambda v: repr(v).replace(".", ","))
                                                        .replace(" ", "\t").replace("\n", "\r\n")).encode(), (OK, OK)),
        ("a '#' comment line", "# my dome\n" + body, (None, None)),
        ("a trailing 'end' line", body + "end\n", (E, E)),
        ("x,y,z with commas and no spaces",
         "\n".join([rows[0]] + [f"{n} {x!r},{y!r},{z!r}" for n, (x, y, z) in zip(names, dirs)]) + "\n", (E, E)),
        ("an image listed twice", lines_with(5, f"{names[4]} {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"), (E, E)),
        ("a direction listed twice", lines_with(5, f"{names[5]} {dirs[4][0]!r} {dirs[4][1]!r} {dirs[4][2]!r}"), (E, E)),
        ("two directions 1e-9 apart", lines_with(5, f"{names[5]} {dirs[4][0] + 1e-9!r} {dirs[4][1]!r} {dirs[4][2]!r}"),
         (E, E)),
        ("3 lights", geometry(dirs, 3), (None, E)),
        ("4 lights on the equator (coplanar)", geometry(ring(4, 0.0)), (None, E)),
        ("8 lights on one ring at 30 degrees", geometry(ring(8, 30.0)), (None, E)),
        ("all 16 lights on one ring at 45 degrees", geometry(ring(16, 45.0)), (None, E)),
        ("all 16 lights on the equator", geometry(ring(16, 0.0)), (None, E)),
        ("16 lights within 0.1 degrees", geometry(cluster), (None, None)),
        ("all lights behind the object (z < 0)", geometry(dirs * np.array([1.0, 1.0, -1.0])), (None, None)),
        ("a listed image is missing", lines_with(5, f"images/nothere.exr {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"),
         (E, E)),
        ("an image named by absolute path /etc/passwd",
         lines_with(5, f"/etc/passwd {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"), (E, E)),
        ("an image path escaping the folder (../../../etc/hostname)",
         lines_with(5, f"../../../../../../etc/hostname {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"), (E, E)),
        ("an image name that is a folder", lines_with(5, f"images {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"),
         (E, E)),
        ("a 5000-character image name",
         lines_with(5, f"images/{'n' * 5000}.exr {dirs[5][0]!r} {dirs[5][1]!r} {dirs[5][2]!r}"), (E, E)),
        ("a 1 MB line", lines_with(5, "x" * 1_000_000), (E, E)),
        (f"{many} lines naming missing images (9 MB)", big, (E, E)),
        ("lights.lp is a folder", folder_named, (E, E)),
        ("lights.lp is a FIFO", fifo, (E, E)),
        ("lights.lp is a link to /dev/zero", symlink("/dev/zero"), (E, E)),
        ("lights.lp is a link to /dev/urandom", symlink("/dev/urandom"), (E, E)),
        ("lights.lp is a link loop", loop, (E, E)),
        ("lights.lp is a dangling link", symlink("/nonexistent/lights.lp"), (E, E)),
        ("two .lp files and no lights.lp", two_files, (E, E)),
        ("no .lp file at all", lambda folder: None, (E, E)),
        # fit reads no held-out lights: only info refuses these
        ("heldout.lp malformed", ("heldout", bad_heldout("3\nfoo 1 2\n")), (E, None)),
        ("heldout.lp lists missing images",
         ("heldout", bad_heldout(lp_text(["heldout/h0000.exr", "heldout/h0001.exr"], dirs[:2] + 0.1))), (E, None)),
    ]
    cases = []
    for label, content, (expect_info, expect_fit) in variants:
        def build(folder, content=content, command="info"):
            dataset = folder / "capture"
            link_tree(ctx.capture_exr / "images", dataset / "images")
            if isinstance(content, tuple):  # a good lights.lp plus an extra file
                put(dataset / "lights.lp", body)
                content[1](dataset)
            elif callable(content):
                content(dataset)
            else:
                put(dataset / "lights.lp", content)
            if command == "info":
                return Run(["info", dataset, "-q"])
            out = folder / "F.whf"
            return Run(["fit", dataset, "-o", out, "--device", "cpu", *ctx.fast, "-q"], outputs=[out])

        cases.append(Case("light files", f"info: {label}", build, expect_info))
        cases.append(Case("light files", f"fit: {label}", lambda folder, build=build: build(folder, command="fit"),
                          expect_fit))
    return cases


# --- category 2: field files ------------------------------------------------------------------------


_DELETE = object()


def field_cases(ctx: Context) -> list[Case]:
    from warp_highlights.io.fieldfile import FORMAT_VERSION

    raw = ctx.field.read_bytes()
    with zipfile.ZipFile(io.BytesIO(raw)) as archive:
        entries = {info.filename: archive.read(info.filename) for info in archive.infolist()}
    header = json.loads(entries["header.json"])

    def zipped(changes=None, *, compression=zipfile.ZIP_DEFLATED, zip64=False, extra=()) -> bytes:
        items = dict(entries)
        for name, data in (changes or {}).items():
            if data is _DELETE:
                items.pop(name, None)
            else:
                items[name] = data
        buffer = io.BytesIO()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # duplicate names on purpose
            with zipfile.ZipFile(buffer, "w", compression) as archive:
                for name, data in list(items.items()) + list(extra):
                    with archive.open(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), "w",
                                      force_zip64=zip64) as handle:
                        handle.write(data)
        return buffer.getvalue()

    def with_header(**changes) -> bytes:
        changed = copy.deepcopy(header)
        for key, value in changes.items():
            if value is _DELETE:
                changed.pop(key, None)
            else:
                changed[key] = value
        return zipped({"header.json": json.dumps(changed).encode()})

    def array(name) -> np.ndarray:
        return np.load(io.BytesIO(entries[name]))

    def with_array(name, value) -> bytes:
        return zipped({name: npy(value)})

    def patched(offsets: Callable[[bytearray, zipfile.ZipInfo, int, int], None]) -> bytes:
        """Apply ``offsets(data, info, local_header_offset, central_header_offset)`` to every entry."""
        data = bytearray(raw)
        end = data.rindex(b"PK\x05\x06")
        central = int.from_bytes(data[end + 16 : end + 20], "little")
        with zipfile.ZipFile(io.BytesIO(raw)) as archive:
            infos = archive.infolist()
        pos = central
        for info in infos:
            assert data[pos : pos + 4] == b"PK\x01\x02"
            offsets(data, info, info.header_offset, pos)
            name_len, extra_len, comment_len = (int.from_bytes(data[pos + k : pos + k + 2], "little")
                                                for k in (28, 30, 32))
            pos += 46 + name_len + extra_len + comment_len
        return bytes(data)

    def set_flag(data, info, local, central):
        data[local + 6] |= 1
        data[central + 8] |= 1

    def set_method(data, info, local, central):
        data[local + 8 : local + 10] = (9).to_bytes(2, "little")
        data[central + 10 : central + 12] = (9).to_bytes(2, "little")

    def bad_crc(data, info, local, central):
        if info.filename == "lights/directions.npy":
            for at in (local + 14, central + 16):
                data[at] ^= 0xFF

    directions = array("lights/directions.npy")
    faces = array("triangulation/faces.npy")
    estimated = array("gaussians/estimated.npy")
    counts = array("gaussians/estimated_counts.npy")
    slots = array("gaussians/estimated_slots.npy")
    delta = array("paths/delta.npy")
    centre = array("paths/centre.npy")
    lambert = array("diffuse/lambert.npy")
    scale = array("residual/scale.npy")
    mask_png = (ctx.dataset / "mask.png").read_bytes()

    def big_header() -> bytes:
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            with archive.open(zipfile.ZipInfo("header.json", date_time=(1980, 1, 1, 0, 0, 0)), "w",
                              force_zip64=True) as handle:
                handle.write(b"{")
                chunk = b" " * (1 << 20)
                for _ in range(256):
                    handle.write(chunk)
                handle.write(b"}")
            for name, data in entries.items():
                if name != "header.json":
                    archive.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
        return buffer.getvalue()

    def special(kind):
        def make(folder):
            path = folder / "F.whf"
            if kind == "folder":
                path.mkdir()
            elif kind == "fifo":
                os.mkfifo(path)
            elif kind == "zero":
                os.symlink("/dev/zero", path)
            elif kind == "loop":
                os.symlink(folder / "G.whf", path)
                os.symlink(path, folder / "G.whf")
            elif kind == "dangling":
                os.symlink(folder / "nowhere" / "F.whf", path)
            elif kind == "legacy":
                shutil.copy(REPO / "tests" / "data" / "legacy-v1.whf", path)
            return path

        return make

    E, OK = "error", "ok"
    structured: list[tuple[str, object, str | None]] = [
        ("unchanged copy (control)", raw, OK),
        ("the legacy format-1 file from tests/data", special("legacy"), OK),
        ("missing file", special("missing"), E),
        ("a folder named F.whf", special("folder"), E),
        ("a FIFO", special("fifo"), E),
        ("a link to /dev/zero", special("zero"), E),
        ("a link loop", special("loop"), E),
        ("a dangling link", special("dangling"), E),
        ("empty file", b"", E),
        ("1 byte", raw[:1], E),
        ("the first 30 bytes", raw[:30], E),
        ("half the file", raw[: len(raw) // 2], E),
        ("the last byte cut", raw[:-1], E),
        ("no end-of-directory record (last 22 bytes cut)", raw[:-22], E),
        ("100 bytes of junk in front", b"\x00" * 100 + raw, None),
        ("a PNG image named .whf", mask_png, E),
        ("a text file", b"hello, world\n", E),
        ("a gzip of the field", gzip.compress(raw), E),
        ("a .npy array named .whf", npy(directions), E),
        ("a foreign zip (readme.txt)", zipped({name: _DELETE for name in entries}, extra=[("readme.txt", b"hi\n")]), E),
        ("header.json not JSON", zipped({"header.json": b"{not json"}), E),
        ("header.json not UTF-8", zipped({"header.json": b'{"magic": "\xff\xfe"}'}), E),
        ("header.json a JSON list", zipped({"header.json": b"[]"}), E),
        ("header.json nested 100000 deep", zipped({"header.json": b"[" * 100_000 + b"]" * 100_000}), E),
        ("header.json of 256 MB (a zip bomb)", big_header(), E),
        ("header.json with trailing NUL bytes", zipped({"header.json": entries["header.json"] + b"\x00" * 64}), E),
        (f"future format version {FORMAT_VERSION + 1}", with_header(format_version=FORMAT_VERSION + 1), E),
        ("format version 10^30", with_header(format_version=10**30), E),
        ("format version '1' (a string)", with_header(format_version="1"), E),
        ("format version true", with_header(format_version=True), E),
        ("format version 0", with_header(format_version=0), E),
        ("format version 1.5", with_header(format_version=1.5), E),
        ("no format_version", with_header(format_version=_DELETE), E),
        ("wrong magic", with_header(magic="warp-highlights fieId"), E),
        ("light_count 10^12", with_header(light_count=10**12), E),
        ("light_count -1", with_header(light_count=-1), E),
        ("light_count 15 (the arrays hold 16)", with_header(light_count=15), E),
        ("width 0", with_header(width=0), E),
        ("height 10^9", with_header(height=10**9), E),
        ("width and height doubled", with_header(width=64, height=36), E),
        ("capacity 0", with_header(capacity=0), E),
        ("face_count 10^9", with_header(face_count=10**9), E),
        ("diffuse: 7 channels", with_header(diffuse={**header["diffuse"], "channels": 7}), E),
        ("diffuse: images true without the entry", with_header(diffuse={**header["diffuse"], "images": True}), E),
        ("diffuse: a string", with_header(diffuse="lambert"), E),
        ("light_filenames a number", with_header(light_filenames=3), E),
        ("settings: an unknown setting",
         with_header(settings={**header["settings"], "estimation": {**header["settings"]["estimation"], "bogus": 1}}),
         E),
        ("settings: iterations -5",
         with_header(settings={**header["settings"],
                               "estimation": {**header["settings"]["estimation"], "iterations": -5}}), E),
        ("settings missing", with_header(settings=_DELETE), None),
        ("report missing", with_header(report=_DELETE), None),
    ]
    for name in entries:
        structured.append((f"entry {name} removed", zipped({name: _DELETE}),
                           E if name != "diffuse/lambert.npy" else None))
        structured.append((f"entry {name} replaced by garbage", zipped({name: b"garbage" * 10}), E))
    structured += [
        ("directions as float32", with_array("lights/directions.npy", directions.astype(np.float32)), E),
        ("directions of shape (16, 2)", with_array("lights/directions.npy", directions[:, :2]), E),
        ("directions with a NaN",
         with_array("lights/directions.npy",
                    np.where(np.arange(directions.size).reshape(directions.shape) == 7, np.nan, directions)), E),
        ("directions all zero", with_array("lights/directions.npy", np.zeros_like(directions)), E),
        ("directions scaled by 1000", with_array("lights/directions.npy", directions * 1000), None),
        ("directions all the same",
         with_array("lights/directions.npy", np.repeat(directions[:1], len(directions), axis=0)), E),
        ("directions shuffled", with_array("lights/directions.npy", directions[::-1].copy()), None),
        ("faces with index 999",
         with_array("triangulation/faces.npy", np.where(faces == faces.max(), 999, faces).astype(faces.dtype)), E),
        ("faces with index -1",
         with_array("triangulation/faces.npy", np.where(faces == 0, -1, faces).astype(faces.dtype)), E),
        ("degenerate faces (0, 0, 0)", with_array("triangulation/faces.npy", np.zeros_like(faces)), E),
        ("faces wound the other way", with_array("triangulation/faces.npy", faces[:, ::-1].copy()), None),
        ("estimated Gaussians with NaN", with_array("gaussians/estimated.npy", np.full_like(estimated, np.nan)), E),
        ("estimated Gaussians of sigma 0",
         with_array("gaussians/estimated.npy", np.concatenate([estimated[:, :3], np.zeros_like(estimated[:, 3:5]),
                                                               estimated[:, 5:]], axis=1)), None),
        ("estimated amplitudes 1e30",
         with_array("gaussians/estimated.npy",
                    np.concatenate([np.full_like(estimated[:, :1], 1e30), estimated[:, 1:]], axis=1)), None),
        ("estimated counts over the capacity", with_array("gaussians/estimated_counts.npy", counts + 1000), E),
        ("estimated slots out of range", with_array("gaussians/estimated_slots.npy", slots + 1000), E),
        ("path rotations inf", with_array("paths/delta.npy", np.full_like(delta, np.inf)), E),
        ("path centres 1e30", with_array("paths/centre.npy", np.full_like(centre, 1e30)), None),
        ("Lambertian diffuse all inf", with_array("diffuse/lambert.npy", np.full_like(lambert, np.inf)), E),
        ("residual scale all inf", with_array("residual/scale.npy", np.full_like(scale, np.inf)), E),
        ("residual scale negative", with_array("residual/scale.npy", -np.abs(scale) - 1), E),
        ("a .npy header claiming 10^12 x 3 values", zipped({"lights/directions.npy": npy_with_header(
            {"descr": "<f8", "fortran_order": False, "shape": (10**12, 3)}, directions.tobytes())}), E),
        ("an object (pickle) .npy",
         zipped({"lights/directions.npy": npy(np.array([{"a": 1}] * 16, dtype=object), allow_pickle=True)}), E),
        ("a Fortran-order .npy", zipped({"lights/directions.npy": npy(np.asfortranarray(directions))}), E),
        ("a .npy of format version 3.0", zipped({"lights/directions.npy": npy_with_header(
            {"descr": "<f8", "fortran_order": False, "shape": directions.shape}, directions.tobytes(),
            version=(3, 0))}), E),
        ("header.json twice in the zip", zipped(extra=[("header.json", with_header_bytes(header, format_version=2))]),
         None),
        ("an unknown extra entry", zipped(extra=[("notes.txt", b"hello\n")]), None),
        ("encrypted flag on every entry", patched(set_flag), E),
        ("compression method 9 (deflate64)", patched(set_method), E),
        ("a CRC mismatch in lights/directions.npy", patched(bad_crc), E),
        ("stored (uncompressed) entries", zipped(compression=zipfile.ZIP_STORED), OK),
        ("zip64 entries", zipped(zip64=True), OK),
    ]

    commands = ["relight", "animate", "evaluate"] + (["view"] if ctx.view_ok else [])

    def argv_for(command: str, path: Path, folder: Path) -> Run:
        if command == "relight":
            out = folder / "relit.png"
            return Run(["relight", path, "--light", "0.3,0.5,1", "-o", out, "-q"], outputs=[out])
        if command == "animate":
            out = folder / "orbit.gif"
            return Run(["animate", path, "--path", "orbit:35", "--frames", "3", "-o", out, "-q"], outputs=[out])
        if command == "evaluate":
            out = folder / "evaluation"
            return Run(["evaluate", path, ctx.dataset, "-o", out, "--triangle", "none", "-q"], outputs=[out])
        out = folder / "view.png"
        return Run(["view", path, "--screenshot", out, "-q"], outputs=[out])

    def builder(content, command):
        def build(folder):
            path = folder / "F.whf"
            if callable(content):
                path = content(folder)
            else:
                put(path, content)
            return argv_for(command, path, folder)

        return build

    cases = []
    for label, content, expect in structured:
        for command in commands:
            if command == "evaluate" and "legacy" in label:
                expect = None  # a field of another dataset: evaluate against D may refuse it
            cases.append(Case("field files", f"{command}: {label}", builder(content, command), expect))
    if not ctx.view_ok:
        cases.append(Case("field files", "view: skipped", _skipped(ctx.view_note)))
    rng = random.Random(ctx.rng.random())
    for k in range(20):
        cut = rng.randrange(1, len(raw))
        command = commands[k % len(commands)]
        cases.append(Case("field files", f"{command}: truncated at byte {cut} of {len(raw)}",
                          builder(raw[:cut], command), E))
    for k in range(30):
        at, bit = rng.randrange(len(raw)), rng.randrange(8)
        flipped = bytearray(raw)
        flipped[at] ^= 1 << bit
        command = commands[k % len(commands)]
        cases.append(Case("field files", f"{command}: bit {bit} of byte {at} flipped", builder(bytes(flipped), command),
                          None))
    return cases


def with_header_bytes(header: dict, **changes) -> bytes:
    return json.dumps({**header, **changes}).encode()


def _skipped(note: str):
    def build(folder):
        raise Skip(note)

    return build


# --- category 3: images -----------------------------------------------------------------------------


def image_cases(ctx: Context) -> list[Case]:
    count = len(ctx.names)
    rng = random.Random(ctx.rng.random())
    noise = bytes(rng.randrange(256) for _ in range(2000))

    def capture(folder: Path, kind: str, make=None, replace=None, extra=None) -> Path:
        """A capture folder: ``make(i, path)`` writes image i (default: the tiny dataset's image as
        ``kind``, 'png' or 'exr'); ``replace`` maps an index to (file name, maker) for one odd image."""
        dataset = folder / "capture"
        names = []
        for i in range(count):
            name = f"{i:04d}.{kind}"
            maker = make
            if replace and i in replace:
                name, maker = replace[i]
            path = dataset / "images" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            if maker is not None:
                maker(i, path)
            elif kind == "png":
                put(path, png_bytes(rgb8(ctx, i)))
            else:
                os.link(ctx.capture_exr / "images" / ctx.names[i], path)
            names.append(f"images/{name}")
        put(dataset / "lights.lp", lp_text(names, ctx.directions))
        if extra is not None:
            extra(dataset)
        return dataset

    def data(content: bytes):
        return lambda i, path: put(path, content)

    def png_of(i, path):
        put(path, png_bytes(rgb8(ctx, i)))

    def jpeg_of(i, path):
        put(path, jpeg_bytes(rgb8(ctx, i)))

    def exr_of(i, path):
        put(path, exr_bytes(rgb_channels(ctx.images[i])))

    png5 = png_bytes(rgb8(ctx, 5))
    jpeg5 = jpeg_bytes(rgb8(ctx, 5))
    exr5 = exr_bytes(rgb_channels(ctx.images[5]))
    png16 = png16_bytes(ctx.images[5])

    def bad_idat_crc(data: bytes) -> bytes:
        out = bytearray(data)
        at = data.index(b"IDAT") + 4 + 2
        out[at] ^= 0xFF  # inside the compressed data; the chunk's CRC no longer matches
        return bytes(out)

    def corrupt_idat_valid_crc(data: bytes) -> bytes:
        chunks = [(kind, body if kind != b"IDAT" else body[:2] + bytes(b ^ 0x5A for b in body[2:]))
                  for kind, body in png_chunks(data)]
        return png_from_chunks(chunks)

    def ztxt_bomb(data: bytes) -> bytes:
        import zlib

        chunks = png_chunks(data)
        text = (b"Comment\x00\x00" + zlib.compress(b"A" * (50 << 20), 9))
        return png_from_chunks(chunks[:1] + [(b"zTXt", text)] + chunks[1:])

    def link(target):
        return lambda i, path: os.symlink(target, path)

    def fifo(i, path):
        os.mkfifo(path)

    def folder_at(i, path):
        path.mkdir()

    def tiff(i, path):
        from PIL import Image

        Image.fromarray(rgb8(ctx, i)).save(path, "TIFF")

    def black_png(i, path):
        put(path, png_bytes(np.zeros((18, 32, 3), np.uint8)))

    def white_png(i, path):
        put(path, png_bytes(np.full((18, 32, 3), 255, np.uint8)))

    def black_exr(i, path):
        put(path, exr_bytes(rgb_channels(np.zeros((18, 32, 3), np.float32))))

    def scaled_exr(size):
        def make(i, path):
            from PIL import Image

            planes = [np.asarray(Image.fromarray(ctx.images[i][:, :, c]).resize(size, Image.BILINEAR))
                      for c in range(3)]
            put(path, exr_bytes(rgb_channels(np.stack(planes, axis=-1))))

        return make

    def exr_with(channels_of):
        return lambda i, path: put(path, exr_bytes(channels_of(ctx.images[i])))

    def modified(update):
        def make(i, path):
            image = ctx.images[i].copy()
            update(image)
            put(path, exr_bytes(rgb_channels(image)))

        return make

    def set_nan(image):
        image[5, 5, 0] = np.nan

    def set_inf(image):
        image[5, 5, 1] = np.inf

    def set_negative(image):
        image[:, :, :] -= 0.5

    def png16_of(i, path):
        put(path, png16_bytes(ctx.images[i]))

    def gray16_of(i, path):
        put(path, png_bytes((ctx.images[i].mean(axis=2).clip(0, 1) * 65535).astype(np.uint16)))

    def jpeg_mode(mode, **save):
        return lambda i, path: put(path, jpeg_bytes(rgb8(ctx, i), mode, **save))

    def bomb_link(i, path):
        os.link(bomb_png(ctx), path)

    def huge_exr_link(i, path):
        os.link(huge_exr(ctx), path)

    def meta(content: bytes):
        return lambda dataset: put(dataset / "meta.json", content)

    def mask(maker):
        return lambda dataset: maker(dataset / "mask.png")

    def partial_specular(dataset):
        (dataset / "specular").mkdir()
        for i in range(count - 1):  # the last one is missing
            os.link(ctx.dataset / "specular" / ctx.names[i], dataset / "specular" / f"{i:04d}.exr")

    def with_heldout_damaged(dataset):
        link_tree(ctx.dataset / "heldout", dataset / "heldout")
        shutil.copy(ctx.dataset / "heldout.lp", dataset / "heldout.lp")
        first = sorted((dataset / "heldout").iterdir())[0]
        put(first, first.read_bytes()[:100])

    E, OK = "error", "ok"
    inputs = [
        ("random bytes named .png", lambda f: capture(f, "png", replace={5: ("0005.png", data(noise))}), E),
        ("random bytes named .jpg", lambda f: capture(f, "png", replace={5: ("0005.jpg", data(noise))}), E),
        ("random bytes named .exr", lambda f: capture(f, "exr", replace={5: ("0005.exr", data(noise))}), E),
        ("a zero-byte .png", lambda f: capture(f, "png", replace={5: ("0005.png", data(b""))}), E),
        ("a PNG cut in half", lambda f: capture(f, "png", replace={5: ("0005.png", data(png5[: len(png5) // 2]))}), E),
        ("a PNG cut after its header (33 bytes)",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(png5[:33]))}), E),
        ("a PNG with a bad CRC in its image data",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(bad_idat_crc(png5)))}), E),
        ("a PNG with damaged image data (valid CRC)",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(corrupt_idat_valid_crc(png5)))}), E),
        ("a PNG with junk after IEND", lambda f: capture(f, "png", replace={5: ("0005.png", data(png5 + noise))}),
         None),
        ("a PNG with a 50 MB zTXt chunk (text bomb)",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(ztxt_bomb(png5)))}), None),
        ("a JPEG cut in half", lambda f: capture(f, "png", replace={5: ("0005.jpg", data(jpeg5[: len(jpeg5) // 2]))}),
         E),
        ("a JPEG without its end marker", lambda f: capture(f, "png", replace={5: ("0005.jpg", data(jpeg5[:-2]))}),
         None),
        ("an EXR cut in half", lambda f: capture(f, "exr", replace={5: ("0005.exr", data(exr5[: len(exr5) // 2]))}), E),
        ("an EXR cut after 300 bytes", lambda f: capture(f, "exr", replace={5: ("0005.exr", data(exr5[:300]))}), E),
        ("a 20000x20000 PNG bomb", lambda f: capture(f, "png", replace={5: ("0005.png", bomb_link)}), E),
        ("every image a 20000x20000 PNG bomb, --max-megapixels 100000", lambda f: capture(f, "png", make=bomb_link), E),
        ("mask.png a 20000x20000 PNG bomb",
         lambda f: capture(f, "exr", extra=mask(lambda p: os.link(bomb_png(ctx), p))), E),
        ("an EXR whose header claims 10^9 pixels",
         lambda f: capture(f, "exr", replace={5: ("0005.exr", huge_exr_link)}), E),
        ("every EXR claiming 10^9 pixels, --max-megapixels 100000", lambda f: capture(f, "exr", make=huge_exr_link), E),
        ("a JPEG whose header claims 65000x65000",
         lambda f: capture(f, "png", replace={5: ("0005.jpg", data(huge_jpeg(ctx)))}), E),
        ("an all-black PNG capture", lambda f: capture(f, "png", make=black_png), E),
        ("an all-white PNG capture", lambda f: capture(f, "png", make=white_png), E),
        ("an all-black EXR capture", lambda f: capture(f, "exr", make=black_exr), E),
        ("one image 64x36 among 32x18", lambda f: capture(f, "exr", replace={5: ("0005.exr", scaled_exr((64, 36)))}),
         E),
        ("one image 16x9 among 32x18", lambda f: capture(f, "exr", replace={5: ("0005.exr", scaled_exr((16, 9)))}), E),
        ("one grayscale PNG among RGB",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(png_bytes(rgb8(ctx, 5), "L")))}), E),
        ("one RGBA PNG among RGB",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(png_bytes(rgb8(ctx, 5), "RGBA")))}), None),
        ("one palette PNG among RGB",
         lambda f: capture(f, "png", replace={5: ("0005.png", data(png_bytes(rgb8(ctx, 5), "P")))}), None),
        ("one CMYK JPEG among PNG", lambda f: capture(f, "png", replace={5: ("0005.jpg", jpeg_mode("CMYK"))}), None),
        ("a PNG named .jpg", lambda f: capture(f, "png", replace={5: ("0005.jpg", data(png5))}), None),
        ("a JPEG named .png", lambda f: capture(f, "png", replace={5: ("0005.png", data(jpeg5))}), None),
        ("an EXR named .png", lambda f: capture(f, "png", replace={5: ("0005.png", data(exr5))}), E),
        ("a TIFF named .png", lambda f: capture(f, "png", replace={5: ("0005.png", tiff)}), E),
        ("a folder named 0005.png", lambda f: capture(f, "png", replace={5: ("0005.png", folder_at)}), E),
        ("a FIFO named 0005.png", lambda f: capture(f, "png", replace={5: ("0005.png", fifo)}), E),
        ("a dangling link named 0005.png",
         lambda f: capture(f, "png", replace={5: ("0005.png", link("/nonexistent.png"))}), E),
        ("0005.exr a link to /dev/zero", lambda f: capture(f, "exr", replace={5: ("0005.exr", link("/dev/zero"))}), E),
        ("0005.png a link to /dev/urandom",
         lambda f: capture(f, "png", replace={5: ("0005.png", link("/dev/urandom"))}), E),
        ("NaN pixels in one EXR", lambda f: capture(f, "exr", replace={5: ("0005.exr", modified(set_nan))}), E),
        ("+inf pixels in one EXR", lambda f: capture(f, "exr", replace={5: ("0005.exr", modified(set_inf))}), E),
        ("negative pixels in every EXR", lambda f: capture(f, "exr", make=modified(set_negative)), None),
        ("EXR with a Z channel only", lambda f: capture(f, "exr", make=exr_with(lambda im: {"Z": im.mean(axis=2)})),
         None),
        ("EXR with channels A and Z",
         lambda f: capture(f, "exr", make=exr_with(lambda im: {"A": im[:, :, 0], "Z": im[:, :, 1]})), E),
        ("EXR with RGBA channels",
         lambda f: capture(f, "exr", make=exr_with(lambda im: {**rgb_channels(im), "A": np.ones(im.shape[:2])})), OK),
        ("half-float EXR capture",
         lambda f: capture(f, "exr", make=lambda i, p: put(p, exr_bytes(rgb_channels(ctx.images[i]), half=True))), OK),
        ("16-bit colour PNG capture", lambda f: capture(f, "png", make=png16_of), OK),
        ("a 16-bit colour PNG cut in half",
         lambda f: capture(f, "png", make=png16_of, replace={5: ("0005.png", data(png16[: len(png16) // 2]))}), E),
        ("a 16-bit colour PNG with a bad CRC",
         lambda f: capture(f, "png", make=png16_of, replace={5: ("0005.png", data(bad_idat_crc(png16)))}), E),
        ("a 16-bit colour PNG with damaged data (valid CRC)",
         lambda f: capture(f, "png", make=png16_of, replace={5: ("0005.png", data(corrupt_idat_valid_crc(png16)))}), E),
        ("16-bit grayscale PNG capture", lambda f: capture(f, "png", make=gray16_of), OK),
        ("grayscale JPEG capture", lambda f: capture(f, "jpg", make=jpeg_mode("L")), OK),
        ("progressive JPEG capture", lambda f: capture(f, "jpg", make=jpeg_mode(None, progressive=True)), OK),
        ("PNG and EXR mixed", lambda f: capture(f, "exr", replace={5: ("0005.png", png_of), 6: ("0006.jpg", jpeg_of)}),
         None),
        ("1x1 EXR capture", lambda f: capture(f, "exr", make=scaled_exr((1, 1))), None),
        ("2000x1 EXR capture", lambda f: capture(f, "exr", make=scaled_exr((2000, 1))), None),
        ("mask.png damaged", lambda f: capture(f, "exr", extra=mask(lambda p: put(p, png5[:40]))), E),
        ("mask.png of another size",
         lambda f: capture(f, "exr", extra=mask(lambda p: put(p, png_bytes(np.zeros((9, 16), np.uint8))))), E),
        ("meta.json nested 100000 deep", lambda f: capture(f, "exr", extra=meta(b"[" * 100_000 + b"]" * 100_000)), E),
        ("meta.json not UTF-8", lambda f: capture(f, "exr", extra=meta(b'{"shape": "\xff"}')), E),
        ("meta.json a list", lambda f: capture(f, "exr", extra=meta(b"[1, 2]")), E),
        ("specular/ with one image missing", lambda f: capture(f, "exr", extra=partial_specular), E),
        ("a held-out image damaged", lambda f: capture(f, "exr", extra=with_heldout_damaged), E),
        ("an EXR read through a PNG capture (exr_of)", lambda f: capture(f, "png", replace={5: ("0005.exr", exr_of)}),
         None),
    ]
    cases = []
    for label, make_dataset, expect in inputs:
        lifted = "--max-megapixels 100000" in label
        limit = ["--max-megapixels", "100000"] if lifted else []
        for command in ("info", "fit", "sheet"):
            def build(folder, make_dataset=make_dataset, command=command, limit=limit):
                dataset = make_dataset(folder)
                if command == "info":
                    return Run(["info", dataset, *limit, "-q"])
                if command == "fit":
                    out = folder / "F.whf"
                    return Run(["fit", dataset, "-o", out, "--device", "cpu", *ctx.fast, *limit, "-q"], outputs=[out])
                out = folder / "sheet.png"
                return Run(["sheet", dataset, "-o", out, *limit, "-q"], outputs=[out])

            held_out_only = "held-out" in label and command == "fit"  # fit reads no held-out lights
            cases.append(Case("images", f"{command}: {label}", build, None if held_out_only else expect))
    return cases


# --- category 4: options ----------------------------------------------------------------------------


_MISSING = object()


class InCase:
    """An option value naming a path in the case's folder: ``content`` None makes a folder there,
    bytes or str a file, nothing leaves it missing; ``form`` wraps the path (e.g. ``'list:{}'``)."""

    def __init__(self, name: str, content=_MISSING, form: str = "{}"):
        self.name, self.content, self.form = name, content, form

    def __call__(self, folder: Path) -> str:
        path = folder / self.name
        if self.content is None:
            path.mkdir(parents=True, exist_ok=True)
        elif self.content is not _MISSING:
            put(path, self.content)
        return self.form.format(path)

    def __repr__(self) -> str:
        what = ("" if self.content is _MISSING
                else (" (a folder)" if self.content is None else f" (a file of {len(self.content)} bytes)"))
        return repr(self.form.format(f"CASE/{self.name}")) + what


def option_cases(ctx: Context) -> list[Case]:
    F, D = str(ctx.field), str(ctx.dataset)
    bases: dict[str, Callable[[Path], tuple[list, list]]] = {
        "render": lambda d: (["render", "sphere", d / "out", "--lights", "8", "--size", "32x18", "--samples", "1",
                              "--heldout", "none",
                              "--device", "cpu"], [d / "out"]),
        "info": lambda d: (["info", D], []),
        "sheet": lambda d: (["sheet", D, "-o", d / "sheet.png"], [d / "sheet.png"]),
        "fit": lambda d: (["fit", D, "-o", d / "F.whf", "--device", "cpu", *ctx.fast], [d / "F.whf"]),
        "relight": lambda d: (["relight", F, "--light", "0.3,0.5,1", "-o", d / "relit.png"], [d / "relit.png"]),
        "animate": lambda d: (["animate", F, "--path", "orbit:35", "--frames", "3", "-o", d / "orbit.gif"],
                              [d / "orbit.gif"]),
        "evaluate": lambda d: (["evaluate", F, D, "-o", d / "evaluation", "--triangle", "none"], [d / "evaluation"]),
        "demo": lambda d: (["demo", d / "demo", "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu"],
                           [d / "demo"]),
        "view": lambda d: (["view", F, "--screenshot", d / "view.png"], [d / "view.png"]),
    }
    E, OK = "error", "ok"
    cases = []

    def add(command: str, changes: list, expect, label: str | None = None, files: Callable[[Path], list] | None = None,
            raw=None):
        """A case: the command's valid base with ``changes`` (pairs (option, value): value None drops the
        option, True adds a flag; ('@', i, value) replaces positional argument i)."""
        if command == "view" and not ctx.view_ok:
            return

        def build(folder):
            if raw is not None:
                return Run([*raw(folder), "-q"] if raw(folder) else [])
            argv, outputs = bases[command](folder)
            argv = list(argv)
            for change in changes:
                if change[0] == "@":
                    argv[change[1]] = change[2](folder) if callable(change[2]) else change[2]
                    continue
                option, value = change
                value = value(folder) if callable(value) else value
                if option in argv:
                    at = argv.index(option)
                    if value is None:
                        del argv[at : at + 2]
                    else:
                        argv[at + 1] = value
                elif value is True:
                    argv.append(option)
                elif value is not None:
                    argv += [option, value]
            outputs = list(outputs)
            for option in ("-o", "--report", "--screenshot"):
                if option in argv and argv.index(option) + 1 < len(argv):
                    value = str(argv[argv.index(option) + 1])
                    if value.startswith(str(folder)) and Path(value) not in outputs:
                        outputs.append(Path(value))
            return Run([*argv, "-q"], outputs=outputs)

        text = (label
                or " ".join(f"{c[0]} {c[1] if c[0] != '@' else c[2]!s}" if c[1] is not True else c[0] for c in changes))
        cases.append(Case("options", f"{command}: {text}", build, expect))

    def each(command, option, values):
        for value, expect in values:
            add(command, [(option, value)], expect, label=f"{option} {value!r}")

    # render
    each("render", "--lights", [("0", E), ("-16", E), ("3", E), ("4", OK), ("20001", E), ("200000", E), ("nan", E),
                                ("inf", E), ("x", E),
                                ("4.5", E), ("", E), ("1e3", E), ("99999999999999999999999", E)])
    for value, expect in [("-1", E), ("81", E), ("nan", E), ("inf", E), ("x", E), ("80", OK), ("0", OK)]:
        add("render", [("--dome", True), ("--min-elevation", value)], expect, label=f"--dome --min-elevation {value!r}")
    each("render", "--size", [("0x0", E), ("-16x9", E), ("16x-9", E), ("100000x100000", E), ("8001x4500", E), ("32", E),
                              ("x18", E),
                              ("32x18x1", E), ("nanxnan", E), ("infxinf", E), ("1x1", None), ("32X18", OK),
                              ("32*18", None), (" 32x18", None), ("", E)])
    each("render", "--samples", [("0", E), ("-4", E), ("2", E), ("1025", E), ("nan", E), ("x", E), ("16", OK)])
    each("render", "--fov",
         [("0", E), ("0.5", E), ("170", E), ("-30", E), ("nan", E), ("inf", E), ("x", E), ("1", OK), ("169", OK)])
    each("render", "--seed", [("-1", E), ("4294967296", E), ("1.5", E), ("x", E), ("0", OK), ("4294967295", OK)])
    each("render", "--albedo", [("-1,0,0", E), ("nan,0,0", E), ("inf,1,1", E), ("1,2", E), ("a,b,c", E), ("", E),
                                ("2,2,2", E),
                                ("0.5", OK), ("1,1,1,1", E), ("1e400,0,0", E)])
    each("render", "--ambient", [("-1", E), ("101", E), ("nan", E), ("inf", E), ("x", E), ("0", OK)])
    each("render", "--specular", [("-0.5", E), ("1e9", E), ("nan", E), ("0", OK)])
    each("render", "--shininess", [("0", E), ("0.5", E), ("1e7", E), ("nan", E), ("inf", E), ("1", OK), ("1e6", OK)])
    each("render", "--device", [("cuda:7", E), ("gpu", E), ("cpu:1", E), ("", E), ("cuda:-1", E)])
    each("render", "--lights-file", [(InCase("missing.lp"), E), (InCase("dir.lp", None), E),
                                     (InCase("empty.lp", b""), E),
                                     ("/dev/null", E), (F, E), (str(ctx.lp8), OK)])
    each("render", "--heldout", [("bogus", E), (InCase("missing.lp"), E), ("NONE", OK), ("Centroids", OK), (D, E),
                                 (F, E),
                                 (str(ctx.lp8), OK)])
    for shape, expect in [("cube", E), ("", E), (InCase("missing.ply"), E), (InCase("text.ply", "hello\n"), E),
                          (InCase("empty.obj", b""), E),
                          (InCase("solid.stl", b"\x00" * 84), E), (D, E), ("/dev/null", E), ("donut", OK),
                          ("teapot", OK)]:
        add("render", [("@", 1, shape)], expect, label=f"shape {shape!r}")
    add("render", [("--gray", True), ("--half", True), ("--dome", True)], OK)
    add("render", [("--bogus", True)], E)

    # info
    each("info", "--max-megapixels", [("0", E), ("-1", E), ("nan", E), ("inf", E), ("x", E), ("1e-9", E), ("0.0001", E),
                                      ("100001", E),
                                       ("0.001", OK), ("100000", OK)])
    each("info", "--heldout", [(InCase("missing"), E), (F, E), (D, None), (str(ctx.capture_exr), None)])
    for dataset, expect in [(InCase("missing"), E), ("", E), ("/", E), ("/proc", E), (str(ctx.base), E)]:
        add("info", [("@", 1, dataset)], expect, label=f"dataset {dataset!r}")
    add("info", [("@", 1, F)], OK, label="a field file (described)")
    add("info", [("--json", True)], OK)

    # sheet
    each("sheet", "--count", [("0", E), ("-1", E), ("101", E), ("nan", E), ("x", E), ("100", None), ("1", OK)])
    each("sheet", "--thumb-height",
         [("0", E), ("15", E), ("1025", E), ("100000", E), ("-135", E), ("nan", E), ("16", OK), ("1024", OK)])
    each("sheet", "-o", [(InCase("sheet.jpg"), E), (InCase("sheet"), E), (InCase("sheet.PNG"), OK)])
    each("sheet", "--max-megapixels", [("0", E), ("0.0001", E)])

    # fit
    each("fit", "--size", [("0x0", E), ("-32x18", E), ("64x36", E), ("31x18", None), ("16x9", OK), ("1x1", E),
                           ("8000x4500", E), ("x", E)])
    each("fit", "--exposure", [("0", E), ("-1", E), ("nan", E), ("inf", E), ("x", E), ("auto", OK), ("AUTO", OK),
                               ("1e-300", None),
                               ("1e300", None), ("", E)])
    each("fit", "--workers", [("0", E), ("-1", E), ("4097", E), ("4096", OK), ("1", OK), ("x", E), ("1.5", E)])
    each("fit", "--diffuse", [("bogus", E), ("images", OK), ("none", OK)])
    each("fit", "--max-megapixels", [("0", E), ("0.0001", E), ("nan", E)])
    each("fit", "--device", [("cuda:7", E), ("", E), ("cpu", OK)])
    each("fit", "--report", [(InCase("F.whf"), E), (InCase("missing/r.json"), E), (InCase("r.json"), OK)])
    add("fit", [("-o", None)], E, label="no -o")
    add("fit", [("@", 1, InCase("missing"))], E, label="dataset missing")
    add("fit", [("@", 1, F)], E, label="dataset is the field file")
    add("fit", [], OK, label="--list-settings", raw=lambda d: ["fit", "--list-settings"])
    add("fit", [], E, label="no arguments", raw=lambda d: ["fit"])
    for override, expect in [
        ("bogus", E), ("=1", E), ("estimation=1", E), ("estimation.adam=1", E), ("nosuch.x=1", E),
        ("estimation.nosuch=1", E),
        ("estimation.iterations=x", E), ("estimation.iterations=1.5", E), ("estimation.iterations=-1", E),
        ("estimation.iterations=0", E),
        ("estimation.iterations=1", OK), ("estimation.iterations=1e3", E), ("estimation.iterations= 5", OK),
        ("estimation.iterations=5=6", E),
        # legal, but hours of work: a hang here
        ("ESTIMATION.ITERATIONS=5", E), ("estimation.iterations=100000000", None),
        ("estimation.capacity=0", E), ("estimation.capacity=100000", E), ("estimation.capacity=1024", None),
        ("estimation.capacity=1", OK),
        ("raster.tile_size=3", E), ("raster.tile_size=32", OK), ("raster.cutoff=nan", E), ("raster.cutoff=inf", E),
        ("raster.cutoff=0", E),
        ("raster.sigma_eps_rpx2=0", E), ("raster.sigma_eps_rpx2=-1", E),
        ("segmentation.outlier_factor=0.5", E), ("segmentation.max_iterations=0", E),
        ("segmentation.min_valid_lights=3", E),
        ("segmentation.min_valid_lights=1000", None), ("segmentation.valid_threshold=1e9", None),
        ("segmentation.valid_threshold=-1", E),
        ("estimation.adam.beta1=1", E), ("estimation.adam.beta1=nan", E), ("estimation.adam.epsilon=0", None),
        ("estimation.adam.lr_amplitude=1e30", None), ("estimation.adam.lr_amplitude=-1", E),
        ("estimation.adam.lr_mean_rpx=inf", E),
        ("retarget.c_str=1e308", None), ("retarget.iterations=0", OK), ("retarget.rigid_iterations=0", OK),
        ("retarget.c_fit=0", None),
        ("retarget.structure.gamma_per_rpx=0", E), ("retarget.components.level=0", E), ("retarget.lr_rotation=nan", E),
        ("paths.compare_rotations=maybe", E), ("paths.compare_rotations=0", OK), ("paths.length_scale_rpx=0", E),
        ("paths.straight_below=1e9", None),
        ("estimation.densify_every=0", E), ("estimation.densify_until=0", E), ("estimation.residual_threshold=0", E),
        ("estimation.residual_threshold=1e-12", None), ("estimation.prune_energy=-1", E),
        ("estimation.min_region_area_rpx2=1e308", None),
    ]:
        def build(folder, override=override):
            out = folder / "F.whf"
            return Run(["fit", D, "-o", out, "--device", "cpu", *ctx.fast, "--set", override, "-q"], outputs=[out])

        cases.append(Case("options", f"fit: --set {override!r}", build, expect))

    # relight
    each("relight", "--light", [("0,0,0", E), ("nan,0,1", E), ("inf,0,0", E), ("1,2", E), ("1,2,3,4", E), ("a,b,c", E),
                                ("", E),
                                ("1e308,1e308,1e308", None), ("1e-320,0,0", None), ("1e400,0,1", E), ("0,0,-1", OK),
                                ("-0.5,0.2,1", OK),
                                ("0.3;0.5;1", None), (" 0.3, 0.5, 1", None), ("-nan,0,1", E)])
    for value, expect in [(InCase("missing.lp"), E), (InCase("dir.lp", None), E), (InCase("empty.lp", b""), E), (F, E),
                          ("/dev/null", E),
                          (InCase("zero.lp", "2\na 0 0 0\nb 0 0 1\n"), E), ("/dev/zero", E)]:
        add("relight", [("--light", None), ("--lights", value), ("-o", InCase("relit"))], expect,
            label=f"--lights {value!r}")
    many = 5000

    def many_lights(folder):
        rng = np.random.default_rng(5)
        vectors = rng.normal(size=(many, 3))
        return str(put(folder / "many.lp", lp_text([f"m{i}.exr" for i in range(many)], vectors)))

    add("relight", [("--light", None), ("--lights", many_lights), ("-o", InCase("relit"))], None,
        label=f"--lights with {many} lights")
    add("relight", [("--lights", str(ctx.lp8))], E, label="--lights (8) with -o a .png")
    add("relight", [("--light", None)], E, label="no light")
    each("relight", "--size", [("0x0", E), ("8001x4500", E), ("31x18", None), ("64x36", OK), ("8000x4500", None),
                               ("16x9", OK), ("2x1", None),
                               ("-32x18", E)])
    each("relight", "--specular-colour",
         [("-1,0,0", E), ("nan", E), ("inf,1,1", E), ("1,1", E), ("x", E), ("0", OK), ("1e30", None)])
    each("relight", "--method", [("alpha", E), ("bogus", E), ("straight", OK)])
    add("relight", [("--method", "alpha"), ("--dataset", D)], OK)
    add("relight", [("--method", "alpha"), ("--dataset", str(ctx.capture_exr))], None)
    add("relight", [("--method", "alpha"), ("--dataset", str(ctx.other_dataset))], E,
        label="--method alpha --dataset (another dataset, 8 lights)")
    add("relight", [("--method", "alpha"), ("--dataset", InCase("missing"))], E,
        label="--method alpha --dataset missing")
    each("relight", "--diffuse", [("images", E), ("none", OK), ("bogus", E)])
    each("relight", "--device", [("cuda:7", E), ("", E), ("cpu", OK)])
    each("relight", "--max-megapixels", [("0", E), ("nan", E)])
    each("relight", "-o", [(InCase("relit.tif"), OK), (InCase("relit"), E), (InCase("relit.PNG"), OK),
                           (InCase("relit.jpg"), None),
                           (InCase("relit.exr"), OK), ("", E)])

    # animate
    each("animate", "--path", [("", E), ("orbit", E), ("orbit:", E), ("orbit:x", E), ("orbit:91", E), ("orbit:-91", E),
                               ("orbit:nan", E),
                               ("orbit:inf", E), ("orbit:35:nan", E), ("orbit:35:1e308", None), ("orbit:90", None),
                               ("orbit:-90", None),
                               ("orbit:35:0:5", E), ("great:0,0,1:0,0,1", None), ("great:0,0,1:0,0,-1", None),
                               ("great:1,0,0", E),
                               ("great:a:b", E), ("great:0,0,0:0,0,1", E), ("great:nan,0,1:0,0,1", E), ("list:", E),
                               (InCase("missing.lp", form="list:{}"), E), (InCase("dir", None, form="list:{}"), E),
                               (InCase("empty.txt", b"", form="list:{}"), E), (f"list:{F}", E), ("list:/dev/zero", E),
                               (InCase("one.txt", "0 0 1\n", form="list:{}"), None), (f"list:{ctx.lp8}", None),
                               ("spiral:3", E),
                               ("ORBIT:35", None)])
    each("animate", "--frames", [("0", E), ("-1", E), ("100001", E), ("1000000000", E), ("nan", E), ("x", E), ("1", OK),
                                 ("2", OK),
                                 ("100000", None)])
    each("animate", "--fps", [("0", E), ("-24", E), ("1001", E), ("nan", E), ("inf", E), ("0.001", E), ("1000", None),
                              ("0.01", OK), ("50", OK)])
    for methods, expect in [("", E), ("foo", E), ("circular,,straight", None), ("alpha", E),
                            ("circular,circular", None), ("circular,straight", OK)]:
        add("animate", [("--compare", True), ("--methods", methods)], expect, label=f"--compare --methods {methods!r}")
    add("animate", [("--compare", True)], E, label="--compare (alpha without --dataset)")
    add("animate", [("--compare", True), ("--dataset", D)], OK, label="--compare --dataset D")
    each("animate", "-o", [(InCase("orbit.avi"), E),
                           (InCase("orbit.mp4"), None if importlib.util.find_spec("imageio_ffmpeg") else E),
                           (InCase("orbit.GIF"), OK),
                           (InCase("frames"), OK)])
    add("animate", [("--exr", True)], E, label="--exr with a .gif")
    each("animate", "--size", [("0x0", E), ("31x18", None), ("64x36", OK)])
    each("animate", "--specular-colour", [("-1,0,0", E), ("nan,1,1", E)])

    # evaluate
    each("evaluate", "--methods", [("", E), ("foo", E), ("circular", OK), ("alpha", OK), ("circular,circular", None)])
    each("evaluate", "--triangle", [("-1", E), ("1000000000", E), ("x", E), ("1.5", E), ("nan", E), ("", E), ("0", OK),
                                    ("auto", OK), ("NONE", OK)])
    for steps, expect in [("0", E), ("-1", E), ("101", E), ("nan", E), ("x", E), ("1", OK)]:
        add("evaluate", [("--triangle", "auto"), ("--steps", steps)], expect,
            label=f"--triangle auto --steps {steps!r}")
    each("evaluate", "--heldout", [(InCase("missing"), E), (F, E), (str(ctx.capture_exr), None)])
    add("evaluate", [("@", 2, str(ctx.capture_exr))], E, label="dataset without held-out lights")
    add("evaluate", [("@", 2, str(ctx.other_dataset))], E, label="another dataset (8 lights)")
    add("evaluate", [("@", 2, InCase("missing"))], E, label="dataset missing")
    each("evaluate", "--max-megapixels", [("0", E)])
    each("evaluate", "--device", [("cuda:7", E)])

    # demo
    each("demo", "--lights", [("0", E), ("3", E), ("2001", E), ("-64", E), ("nan", E), ("4", None)])
    each("demo", "--size", [("0x0", E), ("-16x9", E), ("100000x1", E), ("1x1", None)])
    each("demo", "--frames", [("0", E), ("1", E), ("10001", E), ("1000000000", E), ("nan", E), ("x", E)])
    each("demo", "--device", [("cuda:7", E)])

    # view
    each("view", "--light", [("0,0,0", E), ("nan,0,1", E), ("x", E), ("0,0,-1", OK)])
    each("view", "--panels", [("", E), ("foo", E), ("sphere,sphere", None), ("image", OK), (" , ", E)])
    each("view", "--window-size", [("0x0", E), ("-1x1", E), ("100000x100000", E), ("10x10", None)])
    each("view", "--size", [("0x0", E), ("31x18", None)])
    each("view", "--method", [("alpha", E)])
    each("view", "--diffuse", [("images", E)])
    each("view", "--screenshot", [(InCase("view.jpg"), E), (InCase("view"), E)])
    add("view", [("--screenshot", None)], E, label="no --screenshot and no display")
    each("view", "--device", [("cuda:7", E)])

    # the program itself
    for argv, expect in [([], E), (["bogus"], E), (["--bogus"], E), (["fit", "--bogus"], E), (["relight"], E),
                         (["render", "sphere"], E),
                         (["--version"], OK), (["-q"], E)]:
        def build(folder, argv=argv):
            return Run(list(argv))

        cases.append(Case("options", f"warp-highlights {' '.join(argv) or '(no arguments)'}", build, expect))
    return cases


# --- category 5: outputs and the operating system ---------------------------------------------------


def writers(ctx: Context) -> list[tuple[str, str, str, Callable[[Path, Path], list]]]:
    """(name, 'file' or 'folder', suffix, argv(output, case folder)) for every command that writes."""
    F, D = str(ctx.field), str(ctx.dataset)
    items = [
        ("render", "folder", "",
         lambda o, d: ["render", "sphere", o, "--lights", "8", "--size", "32x18", "--samples", "1", "--device", "cpu"]),
        ("fit -o", "file", ".whf", lambda o, d: ["fit", D, "-o", o, "--device", "cpu", *ctx.fast]),
        ("fit --report", "file", ".json",
         lambda o, d: ["fit", D, "-o", d / "F.whf", "--report", o, "--device", "cpu", *ctx.fast]),
        ("relight to a PNG", "file", ".png", lambda o, d: ["relight", F, "--light", "0.3,0.5,1", "-o", o]),
        ("relight to an EXR", "file", ".exr", lambda o, d: ["relight", F, "--light", "0.3,0.5,1", "-o", o]),
        ("relight --lights to a folder", "folder", "", lambda o, d: ["relight", F, "--lights", ctx.lp8, "-o", o]),
        ("animate to a GIF", "file", ".gif",
         lambda o, d: ["animate", F, "--path", "orbit:35", "--frames", "4", "-o", o]),
        ("animate to a frames folder", "folder", "",
         lambda o, d: ["animate", F, "--path", "orbit:35", "--frames", "4", "-o", o]),
        ("animate --exr frames", "folder", "",
         lambda o, d: ["animate", F, "--path", "orbit:35", "--frames", "4", "--exr", "-o", o]),
        ("evaluate", "folder", "", lambda o, d: ["evaluate", F, D, "-o", o, "--triangle", "none"]),
        ("sheet", "file", ".png", lambda o, d: ["sheet", D, "-o", o]),
        ("demo", "folder", "",
         lambda o, d: ["demo", o, "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu"]),
    ]
    if ctx.view_ok:
        items.append(("view --screenshot", "file", ".png", lambda o, d: ["view", F, "--screenshot", o]))
    return items


def output_cases(ctx: Context) -> list[Case]:
    cases = []
    E, OK = "error", "ok"
    user_file = b"the user's own notes: do not delete\n"

    def case(name, label, make, expect, argv_of, overwrite=False):
        def build(folder):
            out, extra = make(folder)
            argv = [*argv_of(out, folder), *(["--overwrite"] if overwrite else []), "-q"]
            run = Run(argv, outputs=[out] + extra.get("outputs", []), cleanup=extra.get("cleanup"),
                      note=extra.get("note", ""), protected=extra.get("protected", []))
            return run

        cases.append(Case("outputs", f"{name}: {label}", build, expect))

    for name, kind, suffix, argv_of in writers(ctx):
        leaf = "out" + suffix

        def read_only(folder, leaf=leaf):
            mount_point = folder / "readonly"
            ctx.mount(mount_point, "ro,size=1m")
            return mount_point / leaf, {"cleanup": lambda: ctx.umount(mount_point),
                                        "note": f"{mount_point} was a read-only tmpfs: mount -t tmpfs -o ro,size=1m "
                                                f"tmpfs {mount_point}"}

        case(name, "read-only folder (tmpfs mounted ro)", read_only, E, argv_of)

        for free in (0, 16 << 10, 64 << 10, 256 << 10):
            def full(folder, leaf=leaf, free=free):
                mount_point = folder / "disk"
                ctx.mount(mount_point, f"size={max(free, 8 << 10)}")
                if free == 0:
                    fd = os.open(mount_point / "filler", os.O_WRONLY | os.O_CREAT, 0o644)
                    try:
                        while True:
                            os.write(fd, b"\0" * 4096)
                    except OSError:  # ENOSPC: the disk is full
                        pass
                    finally:
                        os.close(fd)
                return mount_point / leaf, {"cleanup": lambda: ctx.umount(mount_point),
                                            "note": f"{mount_point} was a tmpfs of {max(free, 8 << 10) >> 10} kB"
                                                    + (" filled to the last byte" if free == 0 else "")
                                                    + f": mount -t tmpfs -o size={max(free, 8 << 10) >> 10}k "
                                                      f"tmpfs {mount_point}"}

            label = "full disk (0 bytes free)" if free == 0 else f"disk with {free >> 10} kB free"
            case(name, label, full, E if free == 0 else None, argv_of)

        case(name, "missing parent folder",
             lambda folder, leaf=leaf: (folder / "missing" / "sub" / leaf, {"outputs": [folder / "missing"]}),
             None, argv_of)
        case(name, "parent is a file",
             lambda folder, leaf=leaf: (put(folder / "afile", b"x").parent / "afile" / leaf, {}), E, argv_of)

        if kind == "file":
            def folder_there(folder, leaf=leaf):
                out = folder / leaf
                put(out / "mine.txt", user_file)
                return out, {"protected": [out / "mine.txt"]}

            case(name, "output is an existing folder", folder_there, E, argv_of)
            case(name, "output exists, no --overwrite",
                 lambda folder, leaf=leaf: (put(folder / leaf, b"previous output\n"), {}),
                 None if name == "sheet" else E, argv_of)
            case(name, "output is a dangling link",
                 lambda folder, leaf=leaf: (_symlink(folder / leaf, folder / "nowhere" / leaf), {}), None, argv_of)
        else:
            case(name, "output is an existing file", lambda folder: (put(folder / "out", user_file), {}), E, argv_of)
            case(name, "output folder exists, no --overwrite",
                 lambda folder: (put(folder / "out" / "previous.txt", b"x").parent, {}), E, argv_of)

            def users_folder(folder):
                out = folder / "out"
                put(out / "thesis.txt", user_file)
                return out, {"protected": [out / "thesis.txt"]}

            case(name, "--overwrite onto a folder holding a user's file", users_folder, E, argv_of, overwrite=True)
            if name in ("render", "relight --lights to a folder", "animate to a frames folder"):
                def earlier_plus_user(folder, argv_of=argv_of):
                    out = folder / "out"
                    ctx.cli([*argv_of(out, folder), "-q"])
                    put(out / "notes.txt", user_file)
                    return out, {"protected": [out / "notes.txt"]}

                case(name, "--overwrite onto its own earlier output plus a user's file", earlier_plus_user, E, argv_of,
                     overwrite=True)

                def earlier(folder, argv_of=argv_of):
                    out = folder / "out"
                    ctx.cli([*argv_of(out, folder), "-q"])
                    return out, {}

                case(name, "--overwrite onto its own earlier output", earlier, OK, argv_of, overwrite=True)

        case(name, "a 300-byte name", lambda folder, suffix=suffix: (folder / ("n" * (300 - len(suffix)) + suffix), {}),
             E, argv_of)
        case(name, "a 240-byte name (legal; its temporary name is longer)",
             lambda folder, suffix=suffix: (folder / ("n" * (240 - len(suffix)) + suffix), {}),
             OK, argv_of)

    # outputs onto inputs
    D = str(ctx.dataset)
    cases.append(Case("outputs", "fit: -o the dataset folder itself --overwrite", lambda folder: Run(
        ["fit", link_tree(ctx.dataset, folder / "D"), "-o", folder / "D", "--overwrite", "--device", "cpu", *ctx.fast,
         "-q"],
        outputs=[folder / "D"]), "error"))
    cases.append(Case("outputs", "render: over the input dataset holding a user's file, --overwrite",
                      lambda folder: _render_over_dataset(ctx, folder, user_file), "error"))
    cases.append(Case("outputs", "fit: --report is the dataset's lights.lp", lambda folder: Run(
        ["fit", link_tree(ctx.dataset, folder / "D"), "-o", folder / "F.whf", "--report", folder / "D" / "lights.lp",
         "--device", "cpu", *ctx.fast, "-q"],
        outputs=[folder / "F.whf"]), "error"))  # it replaces an input without --overwrite
    cases.append(Case("outputs", "relight: -o is the field file (.whf)", lambda folder: Run(
        ["relight", shutil.copy(ctx.field, folder / "F.whf"), "--light", "0.3,0.5,1", "-o", folder / "F.whf",
         "--overwrite", "-q"],
        outputs=[folder / "F.whf"]), "error"))
    cases.append(Case("outputs", "evaluate: default output folder beside the field", lambda folder: Run(
        ["evaluate", shutil.copy(ctx.field, folder / "F.whf"), D, "--triangle", "none", "-q"],
        outputs=[folder / "F-evaluation"]), "ok"))
    return cases


def _symlink(link: Path, target: Path) -> Path:
    os.symlink(target, link)
    return link


def _render_over_dataset(ctx: Context, folder: Path, user_file: bytes) -> Run:
    dataset = link_tree(ctx.dataset, folder / "D")
    put(dataset / "my-notes.txt", user_file)
    return Run(["render", "sphere", dataset, "--lights", "8", "--size", "32x18", "--samples", "1", "--device", "cpu",
                "--overwrite", "-q"],
               outputs=[dataset], protected=[dataset])


# --- category 6: interrupts (subprocesses) ----------------------------------------------------------


def interrupt_cases(ctx: Context) -> list[Case]:
    F, D = str(ctx.field), str(ctx.dataset)
    rng = random.Random(ctx.rng.random())

    def many_lp(folder):
        vectors = np.random.default_rng(3).normal(size=(3000, 3))
        return put(folder / "many.lp", lp_text([f"m{i}.exr" for i in range(3000)], vectors))

    commands = [
        ("fit", lambda o, d: ["fit", D, "-o", o, "--device", "cpu"], ".whf"),
        ("render", lambda o, d: ["render", "donut", o, "--lights", "128", "--size", "96x54", "--device", "cpu"], ""),
        ("evaluate", lambda o, d: ["evaluate", F, D, "-o", o], ""),
        ("animate", lambda o, d: ["animate", F, "--path", "orbit:35", "--frames", "400", "-o", o], ".gif"),
        ("animate frames", lambda o, d: ["animate", F, "--path", "orbit:35", "--frames", "400", "-o", o], ""),
        ("relight --lights", lambda o, d: ["relight", F, "--lights", many_lp(d), "-o", o], ""),
        ("demo", lambda o, d: ["demo", o, "--lights", "16", "--size", "64x36", "--frames", "8", "--device", "cpu"], ""),
    ]
    if ctx.view_ok:
        commands.append(("view", lambda o, d: ["view", F, "--screenshot", o], ".png"))
    cases = []
    for name, argv_of, suffix in commands:
        for sig in (signal.SIGINT, signal.SIGTERM):
            delay = round(rng.uniform(0.0, 2.0), 2)

            def build(folder, argv_of=argv_of, suffix=suffix, sig=sig, delay=delay):
                out = folder / ("out" + suffix)
                return Run([*argv_of(out, folder), "-q"], outputs=[out], interrupt=(sig, delay))

            cases.append(Case("interrupts", f"{name}: {signal.Signals(sig).name} {delay} s after start", build, None))
    for name, argv_of, suffix in commands:
        if name not in ("fit", "render", "relight --lights"):
            continue
        delay = round(rng.uniform(0.0, 2.0), 2)

        def build(folder, argv_of=argv_of, suffix=suffix, delay=delay):
            out = folder / ("out" + suffix)
            earlier = [*argv_of(out, folder), "-q"]
            if "--lights" in earlier and earlier[0] == "render":
                earlier[earlier.index("--lights") + 1] = "8"
            ctx.cli(earlier)
            return Run([*argv_of(out, folder), "--overwrite", "-q"], outputs=[out], interrupt=(signal.SIGTERM, delay))

        cases.append(Case("interrupts", f"{name} --overwrite onto an earlier output: SIGTERM {delay} s after start",
                          build, None))
    return cases


def run_interrupted(run: Run, ctx: Context) -> dict:
    """Run the command in a subprocess; once main() has installed its handlers (SIGTERM is caught),
    wait the delay and send the signal."""
    sig, delay = run.interrupt
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
               PYTHONFAULTHANDLER="1")  # a hang's stacks, on the SIGABRT that ``finish`` sends
    started = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-m", "warp_highlights", *map(str, run.argv)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE,
                               env=env, cwd=ctx.work, start_new_session=True)
    try:
        running = _wait_for_handler(process, started + ctx.timeout)
        time.sleep(delay)
        sent = False
        if process.poll() is None:
            process.send_signal(sig)
            sent = True
        out, err, hang = finish(process, ctx.timeout)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return {"rc": process.returncode, "exception": None, "hang": hang, "crashed": None,
            "stdout": out.decode("utf-8", "replace"),
            "stderr": err.decode("utf-8", "replace"), "seconds": time.perf_counter() - started,
            "note": ("signal sent" if sent else "finished before the signal") + ("" if running
                                                                                 else "; its handlers never appeared")}


def finish(process: subprocess.Popen, timeout: float) -> tuple:
    """(stdout, stderr, hung) of ``process`` once it ends; past ``timeout`` s it is sent SIGABRT (with
    PYTHONFAULTHANDLER set, Python prints every thread's stack on stderr), then killed: hung True."""
    try:
        out, err = process.communicate(timeout=timeout)
        return out, err, False
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)
        try:
            out, err = process.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            out, err = process.communicate()
        return out, err, True


def _wait_for_handler(process: subprocess.Popen, deadline: float) -> bool:
    """Wait until the process catches SIGTERM (main() installed its handlers); False if it never did."""
    bit = 1 << (signal.SIGTERM - 1)
    while time.perf_counter() < deadline and process.poll() is None:
        try:
            for line in Path(f"/proc/{process.pid}/status").read_text().splitlines():
                if line.startswith("SigCgt:") and int(line.split()[1], 16) & bit:
                    return True
        except OSError:
            return False
        time.sleep(0.02)
    return False


# --- running and judging ----------------------------------------------------------------------------


def fingerprint(path: Path):
    """What is at ``path``: None, a link target, a file's size and hash, or a folder's whole tree."""
    try:
        if path.is_symlink():
            return ("link", os.readlink(path))
        if path.is_file():
            return ("file", path.stat().st_size, hashlib.sha1(path.read_bytes()).hexdigest())
        if path.is_dir():
            tree = []
            for root, folders, names in os.walk(path):
                rel = Path(root).relative_to(path)
                tree += [("d", str(rel / n)) for n in sorted(folders)]
                for n in sorted(names):
                    p = Path(root, n)
                    tree.append(("f", str(rel / n), p.stat().st_size if p.is_file() else -1,
                                 hashlib.sha1(p.read_bytes()).hexdigest() if p.is_file() and not p.is_symlink()
                                 else ""))
            return ("dir", tuple(tree))
        if path.exists():
            return ("other", path.stat().st_mode)
    except OSError as error:
        return ("unreadable", str(error))
    return None


def litter_in(root: Path) -> set[str]:
    found = set()
    for folder, dirs, names in os.walk(root):
        for name in dirs + names:
            if LITTER_NAME.match(name):
                found.add(str(Path(folder, name)))
    return found


def classify(result: dict, argv: list, interrupt: tuple | None) -> str:
    command = str(argv[0]) if argv and str(argv[0]) in COMMANDS else None
    if result.get("hang"):
        return "hang"
    if result.get("exception") or "Traceback (most recent call last)" in (result.get("stderr") or ""):
        return "traceback"
    if result.get("crashed"):
        return "other"
    rc = result.get("rc")
    stderr = (result.get("stderr") or "").strip("\n")
    lines = stderr.split("\n") if stderr.strip() else []
    if rc == 0:
        return "accepted"
    if interrupt is not None:
        expected = 130 if interrupt[0] == signal.SIGINT else 143
        good_line = not lines or (len(lines) == 1 and lines[0].startswith("warp-highlights"))
        return "error" if rc == expected and good_line else "other"
    prefix = f"warp-highlights {command}: error:" if command else "warp-highlights: error:"
    if rc == 2 and len(lines) == 1 and lines[0].startswith(prefix):
        return "error"
    return "other"


def execute(case: Case, index: int, ctx: Context) -> Result:
    folder = ctx.cases / f"{index:04d}"
    folder.mkdir(parents=True)
    started = time.perf_counter()
    run = None
    try:
        try:
            run = case.build(folder)
        except Skip as skip:
            return Result(case, index, [], "skipped", None, 0.0, "", None, [], folder, note=str(skip))
        except Exception as error:  # noqa: BLE001 (a fault of this harness: say so and go on)
            return Result(case, index, [], "skipped", None, 0.0, "", None, [], folder,
                          note=f"the harness could not build this case: {type(error).__name__}: {error}")
        before = {path: fingerprint(path) for path in run.outputs}
        kept = {path: fingerprint(path) for path in [*run.protected, ctx.base]}
        seen = litter_in(folder) | litter_in(ctx.base)
        if run.runner is not None:
            result = run.runner(run, ctx)
        elif run.interrupt is None:
            result = ctx.worker.run([str(a) for a in run.argv], ctx.timeout)
        else:
            result = run_interrupted(run, ctx)
        outcome = classify(result, run.argv, run.interrupt)
        lost = list(result.get("lost") or [])
        for path, was in kept.items():
            now = fingerprint(path)
            if now != was:
                lost.append(f"{path} was {'removed' if now is None else 'changed'}"
                            + (" (a shared input of every case)" if path == ctx.base else ""))
        litter = sorted((litter_in(folder) | litter_in(ctx.base)) - seen)
        if outcome != "accepted":
            for path, was in before.items():
                now = fingerprint(path)
                if now != was:
                    what = "created" if was is None else ("removed" if now is None else "changed")
                    litter.append(f"{path} was {what} by the failed command")
        problems = []
        if run.check is not None:
            problem = run.check(result)
            if problem:
                problems.append(problem)
        note = "; ".join(filter(None, [run.note, result.get("note"), result.get("crashed")]))
        return Result(case, index, run.argv, outcome, result.get("rc"), time.perf_counter() - started,
                      result.get("stderr") or "",
                      result.get("exception"), litter, folder, note=note, lost=lost, problems=problems)
    finally:
        if run is not None and run.cleanup is not None:
            with contextlib.suppress(Exception):
                run.cleanup()


def select(cases: list[Case], quick: bool, rng: random.Random, target: int = 60) -> list[Case]:
    if not quick:
        return cases
    chosen = []
    for category in CATEGORIES:
        members = [c for c in cases if c.category == category]
        if not members:
            continue
        k = max(4, round(target * len(members) / len(cases)))
        picked = set(rng.sample(range(len(members)), min(k, len(members))))
        chosen += [c for i, c in enumerate(members) if i in picked]
    return chosen


def machine() -> str:
    from importlib import metadata

    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    versions = []
    for package in ("warp-lang", "numpy", "Pillow", "OpenEXR", "OpenImageIO", "vtk", "pyvista"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions.append(f"{'warp' if package == 'warp-lang' else package} {metadata.version(package)}")
    return (f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}, Python "
            f"{platform.python_version()}, " + ", ".join(versions))


def short(text: str, limit: int = 240) -> str:
    """``text`` with its middle elided when longer than ``limit`` (for listings that need no reproduction)."""
    return text if len(text) <= limit else text[: limit // 2 - 2] + " ... " + text[-(limit // 2 - 3) :]


def git_state() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--short", "--untracked-files=no"], cwd=REPO, capture_output=True,
                               text=True).stdout.splitlines()
    except (OSError, subprocess.CalledProcessError):
        return "not a git checkout"
    return f"commit {head}" + (f" with {len(dirty)} files modified" if dirty else "")


def last_lines(text: str, count: int) -> list[str]:
    lines = [line for line in (text or "").rstrip().splitlines() if line.strip()]
    return lines[-count:]


def report(results: list[Result], seconds: dict, ctx: Context, args, total_seconds: float) -> dict:
    ran = [r for r in results if r.outcome != "skipped"]
    skipped = [r for r in results if r.outcome == "skipped"]
    print()
    print(f"# bad_inputs: {len(ran)} cases in {total_seconds:.0f} s (seed {args.seed}, limit "
          f"{args.timeout:g} s per case"
          f"{', --quick' if args.quick else ''}{', full fits' if args.full_fits else ', short fits'}); {machine()}")
    print(f"# package: {git_state()}; {ctx.mount_note}; {ctx.view_note}; worker started {ctx.worker.starts} times")
    print()
    print("| category | tried | one-line errors | accepted | tracebacks | hangs | other | litter | data lost | "
          "failed checks | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    totals = dict.fromkeys(("tried", *OUTCOMES, "litter", "lost", "problems"), 0)
    rows = {}
    for category in CATEGORIES:
        members = [r for r in ran if r.case.category == category]
        if not members and category not in seconds:
            continue
        row = {"tried": len(members), **{o: sum(r.outcome == o for r in members) for o in OUTCOMES},
               "litter": sum(bool(r.litter) for r in members), "lost": sum(bool(r.lost) for r in members),
               "problems": sum(bool(r.problems) for r in members)}
        rows[category] = {**row, "seconds": round(seconds.get(category, 0.0), 1)}
        for key in totals:
            totals[key] += row[key]
        print(f"| {category} | {row['tried']} | {row['error']} | {row['accepted']} | {row['traceback']} | "
              f"{row['hang']} | {row['other']} | "
              f"{row['litter']} | {row['lost']} | {row['problems']} | {seconds.get(category, 0.0):.0f} |")
    print(f"| **total** | **{totals['tried']}** | **{totals['error']}** | **{totals['accepted']}** | "
          f"**{totals['traceback']}** | **{totals['hang']}** | **{totals['other']}** | **{totals['litter']}** | "
          f"**{totals['lost']}** | **{totals['problems']}** | **{sum(seconds.values()):.0f}** |")
    if skipped:
        reasons = sorted({r.note for r in skipped if not r.note.startswith("the harness")})
        print(f"\nSkipped {len(skipped)} cases: " + "; ".join(reasons))
        for r in skipped:
            if r.note.startswith("the harness"):
                print(f"- [{r.case.category}] {r.case.label}: {r.note}")

    failing = [r for r in ran if r.failing]
    print(f"\n## Failing cases ({len(failing)}): traceback, hang, other, litter, data lost, failed check")
    for r in failing:
        tags = ([r.outcome] if r.outcome in ("traceback", "hang", "other") else []) + (["litter"] if r.litter else [])
        tags += (["data lost"] if r.lost else []) + (["failed check"] if r.problems else [])
        print(f"\n- **{' + '.join(tags)}** [{r.case.category}] {r.case.label} (exit {r.rc}, {r.seconds:.1f} s)")
        print(f"  $ {r.command()}")
        print(f"  inputs kept in {r.folder}" + (f"; {r.note}" if r.note else ""))
        for item in r.litter:
            print(f"  litter: {item}")
        for item in r.lost:
            print(f"  data lost: {item}")
        for item in r.problems:
            print(f"  failed check: {item}")
        detail = r.exception or r.stderr
        for line in last_lines(detail, 8 if r.exception or "Traceback" in (r.stderr or "") else 3):
            print(f"    | {line[:300]}")

    accepted_bad = [r for r in ran if r.outcome == "accepted" and r.case.expect == "error"]
    print(f"\n## Accepted although the input is bad ({len(accepted_bad)})")
    for r in accepted_bad:
        print(f"- [{r.case.category}] {r.case.label}: `{short(r.command())}`"
              + (f" (stderr: {short(last_lines(r.stderr, 1)[0])})" if r.stderr.strip() else ""))
    refused_good = [r for r in ran if r.outcome == "error" and r.case.expect == "ok"]
    print(f"\n## Refused although the input is valid ({len(refused_good)})")
    for r in refused_good:
        print(f"- [{r.case.category}] {r.case.label}: `{short(r.command())}`\n    | "
              f"{short(last_lines(r.stderr, 1)[0]) if r.stderr.strip() else ''}")
    accepted_other = [r for r in ran if r.outcome == "accepted" and r.case.expect != "error"]
    print(f"\n## Other accepted cases ({len(accepted_other)}; valid or debatable input)")
    print("; ".join(f"[{r.case.category}] {r.case.label}" for r in accepted_other))
    return {
        "machine": machine(), "package": git_state(), "seed": args.seed, "timeout": args.timeout, "quick": args.quick,
        "mounts": ctx.mount_note, "view": ctx.view_note,
        "table": rows, "totals": totals,
        "cases": [{"category": r.case.category, "label": r.case.label, "expect": r.case.expect, "outcome": r.outcome,
                   "rc": r.rc,
                   "seconds": round(r.seconds, 3), "argv": [str(a) for a in r.argv], "litter": r.litter, "lost": r.lost,
                   "problems": r.problems, "note": r.note,
                   "stderr": r.stderr[-2000:], "exception": r.exception} for r in results],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="about 60 cases sampled over the categories (a smoke run)")
    parser.add_argument("--seed", type=int, default=14,
                        help="seed of the sampled offsets, bits and delays (default 14)")
    parser.add_argument("--timeout", type=float, default=60.0,
                        help="seconds a case may take before it counts as a hang (default 60)")
    parser.add_argument("--only", nargs="+", choices=[c.split()[0] for c in CATEGORIES],
                        help="run these categories only (first word of each)")
    parser.add_argument("--work", type=Path,
                        help="work folder (default: a new temporary folder, kept when a case fails)")
    parser.add_argument("--keep", action="store_true", help="keep every case's inputs, not only the failing ones'")
    parser.add_argument("--full-fits", action="store_true",
                        help="fit with the default schedule instead of the short one")
    parser.add_argument("--memory-limit", type=float, default=MEMORY_LIMIT_GB,
                        help=f"worker address-space limit in GB, 0 for none (default {MEMORY_LIMIT_GB:g})")
    args = parser.parse_args()

    work = args.work or Path(tempfile.mkdtemp(prefix="warp-highlights-bad-inputs-"))
    work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    ctx = Context(work.resolve(), Worker(args.memory_limit), args.timeout, [] if args.full_fits else FAST_FIT, rng)
    results: list[Result] = []
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    print(f"# bad_inputs: work folder {ctx.work}", flush=True)
    try:
        set_up(ctx)
        print(f"# set-up (render, fit, shared inputs) {time.perf_counter() - started:.1f} s; {ctx.mount_note}; "
              f"{ctx.view_note}", flush=True)
        # harm_cases imports its Case, Run and tools from here
        sys.modules.setdefault("bad_inputs", sys.modules[__name__])
        from harm_cases import capture_cases, environment_cases, race_cases, serve_cases, target_cases

        makers = {"light files": light_file_cases, "field files": field_cases, "images": image_cases,
                  "options": option_cases, "outputs": output_cases, "interrupts": interrupt_cases,
                  "targets": target_cases, "races": race_cases, "environment": environment_cases,
                  "captures": capture_cases, "serve": serve_cases}
        wanted = [c for c in CATEGORIES if not args.only or c.split()[0] in args.only]
        all_cases: list[Case] = []
        for category in wanted:
            all_cases += makers[category](ctx)
        cases = select(all_cases, args.quick, random.Random(args.seed))
        print(f"# {len(cases)} cases" + (f" (sampled from {len(all_cases)})" if args.quick else ""), flush=True)
        for index, case in enumerate(cases):
            t0 = time.perf_counter()
            result = execute(case, index, ctx)
            seconds[case.category] = seconds.get(case.category, 0.0) + time.perf_counter() - t0
            results.append(result)
            mark = {"error": ".", "accepted": "a", "traceback": "T", "hang": "H", "other": "O",
                    "skipped": "s"}[result.outcome]
            if result.litter:
                mark += "L"
            if result.lost:
                mark += "D"
            if result.problems:
                mark += "C"
            print(f"{index:4d} {mark:3s} {result.seconds:6.2f} s  [{case.category}] {case.label}", flush=True)
            if not (args.keep or result.failing):
                shutil.rmtree(result.folder, ignore_errors=True)
    finally:
        ctx.umount_all()
        ctx.worker.stop(gently=True)
    data = report(results, seconds, ctx, args, time.perf_counter() - started)
    failing = any(r.failing for r in results)
    if not (failing or args.keep or args.work):
        shutil.rmtree(ctx.work, ignore_errors=True)
        print(f"\n(work folder {ctx.work} removed: no failing case)")
    else:
        print(f"\nwork folder kept: {ctx.work}")
    out = os.environ.get("OUT")
    if out:
        Path(out, "bad_inputs.json").write_text(json.dumps(data, indent=1, default=str))


if __name__ == "__main__":
    main()
