"""One capture of a collection: ``fit``, ``evaluate``, ``export`` and a thumbnail, as the command line runs them.

Each step is the ``warp-highlights`` command itself, run as a child process in the capture's output folder
(built under a temporary name and renamed when complete, ``io.atomic``): the outputs are those of the
commands run by hand there, a crash or a leak stays in its child, and each child sees one GPU
(``CUDA_VISIBLE_DEVICES``) or its share of the CPU cores. This module does not need Dask: ``runner`` calls
``process_capture`` on the workers.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..io.atomic import atomic_file, atomic_folder
from ..model.errors import InputError
from .captures import Capture, image_size
from .captures import fingerprint as capture_fingerprint

__all__ = ["CAPTURE_RECORD", "CaptureFailed", "JobOptions", "THUMBNAIL_LIGHT", "THUMBNAIL_WIDTH", "process_capture",
           "read_record", "stop_children"]

CAPTURE_RECORD = "capture.json"
"""Written last in a capture's output folder: what was done, with which options, the scores and times. A capture
whose folder has it, with the same options, is finished (the folder appears whole or not at all)."""

THUMBNAIL_LIGHT = (-0.5, 0.5, 0.707107)
"""The gallery's light: from the upper left at 45 degrees of elevation, the raking light RTI viewers open with
(camera space: x right, y up, z to the camera)."""

THUMBNAIL_WIDTH = 320
"""Thumbnail width in pixels (at most; the aspect ratio kept)."""

_STOP_SECONDS = 20.0  # how long a child has to clean up after SIGTERM before it is killed
_children: dict[str, set[subprocess.Popen]] = {}  # run -> its running commands in this process
_stopped: set[str] = set()  # runs told to stop in this process
_children_lock = threading.Lock()
_PILLOW_LIMIT_LOCK = threading.Lock()  # Pillow's limit is process-wide: one thumbnail at a time lifts it
try:  # resolved here, not in the child between fork and exec (the worker has threads)
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None
except (OSError, AttributeError):
    _PRCTL = None


class CaptureFailed(Exception):
    """A command of one capture failed: ``step`` (fit, evaluate, ...), its one-line message, and whether the capture
    itself is at fault (``bad_input``: the command's exit status 2, which a rerun with the same files would repeat)."""

    def __init__(self, step: str, message: str, *, bad_input: bool = False):
        super().__init__(f"{step}: {message}")
        self.step, self.message, self.bad_input = step, message, bad_input


@dataclass(frozen=True)
class JobOptions:
    """What is done to every capture; a finished capture made with other options is done again.

    Attributes:
        fit_args: Options passed through to ``fit`` (``--set``, ``--size``, ``--residual``, ...).
        holdout_every: For a capture without held-out lights: the scores come from a second fit without
            lights 0, K, 2K, ... (``fit --holdout-every K``), the published field keeps every light.
        evaluate: Score each capture (``evaluate``); off: one fit, no scores.
        export: Write the web viewer (``export``).
        baselines: ``evaluate --baselines``.
        linear: The images' PNG/JPEG values are linear (``--linear`` of fit and evaluate).
        max_megapixels: ``--max-megapixels`` of fit and evaluate (None: their default).
        max_side: Fit each capture at most this many pixels on its longer side (its ``fit --size`` worked out from its
            images, the aspect ratio kept); None: at the images' size (or ``--size`` in ``fit_args``).
        device: Where the commands run, as far as it changes the outputs: ``"cuda"`` (a worker's GPU: ``fit``'s default
            residual is the learned one there), ``"cpu"``, or None (a running cluster's workers decide).
    """

    fit_args: tuple[str, ...] = ()
    holdout_every: int = 5
    evaluate: bool = True
    export: bool = True
    baselines: str = "ptm,hsh2,hsh3,rbf"
    linear: bool = False
    max_megapixels: float | None = None
    max_side: int | None = None
    device: str | None = None

    def key(self) -> dict:
        """The options as stored in ``capture.json`` and compared on a rerun."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass
class _Steps:
    """The commands' wall times (s) as they ran."""

    seconds: dict[str, float] = field(default_factory=dict)


def process_capture(capture: Capture, output, options: JobOptions, *, device: str | None = None,
                    visible_gpu: str | None = None, cores: list[int] | None = None, replace: bool = False,
                    fingerprint: str | None = None,
                    run_id: str = "", environment: dict[str, str | None] | None = None) -> dict:
    """Fit, score, export and thumbnail one capture into ``output/<name>``; returns its record (``capture.json``).

    Args:
        device: ``--device`` for the commands (None: theirs, CUDA when present).
        visible_gpu: ``CUDA_VISIBLE_DEVICES`` for the commands (a worker pinned to one GPU), None to leave it.
        cores: CPU cores the commands may use (a CPU worker's share), None for all.
        replace: Replace an existing output folder (a stale or forced capture).
        fingerprint: The capture's files' digest (``captures.fingerprint``), kept in the record; None computes it.
        run_id: The collection run this is part of: ``stop_children(run_id)`` stops its commands.
        environment: Variables set (None: removed) in the commands' environment over this process's
            (``runner.launch_environment``: what Dask's nanny changed for its workers, as the user had it).

    Raises:
        CaptureFailed: a command failed (its one-line message); nothing is left in ``output``.
        KeyboardInterrupt: the run was interrupted; nothing is left either.
    """
    started = time.perf_counter()
    target = Path(output) / capture.name
    steps = _Steps()
    run = _Runner(device=device, visible_gpu=visible_gpu, cores=cores, steps=steps, linear=options.linear,
                  max_megapixels=options.max_megapixels,
                  run_id=run_id, environment=environment)
    fit_args = list(options.fit_args) + _size_arguments(capture, options.max_side)
    with atomic_folder(target, kind="collection capture", overwrite=replace) as folder:
        run(folder, "fit",
            ["fit", str(capture.folder.resolve()), "-o", "field.whf", "--report", "fit-report.json", *fit_args],
            device_option=True, reads_images=True)
        if options.evaluate:
            scored = "field.whf"
            if not capture.has_heldout:
                scored = "holdout-field.whf"
                run(folder, "holdout fit", ["fit", str(capture.folder.resolve()), "-o", scored, "--report",
                                            "holdout-fit-report.json",
                                            "--holdout-every", str(options.holdout_every), *fit_args],
                    device_option=True, reads_images=True)
            heldout = ["--heldout", str(capture.heldout.resolve())] if capture.heldout is not None else []
            run(folder, "evaluate", ["evaluate", scored, str(capture.folder.resolve()), *heldout, "-o", "evaluation",
                                     "--baselines", options.baselines or "none"], device_option=True, reads_images=True)
        if options.export:
            run(folder, "export", ["export", "field.whf", "-o", "viewer"])
        run(folder, "thumbnail", ["relight", "field.whf", "--light", ",".join(f"{v:g}" for v in THUMBNAIL_LIGHT), "-o",
                                  "thumbnail-full.png",
                                  "--bits", "8"], device_option=True)
        _shrink(folder / "thumbnail-full.png", folder / "thumbnail.png")
        record = _record(capture, folder, options, steps.seconds, time.perf_counter() - started)
        record["fingerprint"] = fingerprint if fingerprint is not None else capture_fingerprint(capture)
        (folder / CAPTURE_RECORD).write_text(json.dumps(record, indent=2, allow_nan=False))
    return record


def _size_arguments(capture: Capture, max_side: int | None) -> list[str]:
    """``["--size", "WxH"]`` bringing the capture's longer side to ``max_side`` (never up; at least 8 pixels a side)."""
    if max_side is None:
        return []
    try:
        width, height = image_size(capture)
    except (InputError, OSError) as error:
        raise CaptureFailed("size", str(error) if isinstance(error, InputError) else f"{error.strerror or error}",
                            bad_input=True) from None
    if max(width, height) <= max_side:
        return []
    long, short = max(width, height), min(width, height)
    new_short = max(8, round(short * max_side / long))
    new_long = round(long * new_short / short)  # within half a pixel of the ratio, as fit --size wants
    while new_long > max_side and new_short > 8:
        new_short -= 1
        new_long = round(long * new_short / short)
    new_width, new_height = (new_long, new_short) if width >= height else (new_short, new_long)
    return ["--size", f"{min(new_width, width)}x{min(new_height, height)}"]


def read_record(folder) -> dict | None:
    """A finished capture's record (``capture.json``), None where there is none or it cannot be read."""
    try:
        record = json.loads((Path(folder) / CAPTURE_RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") == "ok" else None


def stop_children(run_id: str = "") -> None:
    """Stop the running commands of collection run ``run_id`` in this process (SIGTERM: each removes its partial
    outputs), wait for them and kill what is left; that run's next commands are not started. For a worker that closes
    mid-capture (Ctrl-C, the cluster going away) or a run that ends; other runs on the same worker go on."""
    with _children_lock:
        _stopped.add(run_id)
        children = list(_children.get(run_id, ()))
    for child in children:
        with contextlib.suppress(OSError):
            child.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + _STOP_SECONDS
    for child in children:
        try:
            child.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                child.kill()


class _Runner:
    """Runs ``python -m warp_highlights ...`` in a folder, as a child that ends with this process."""

    def __init__(self, *, device, visible_gpu, cores, steps: _Steps, linear: bool, max_megapixels: float | None,
                 run_id: str = "",
                 environment: dict[str, str | None] | None = None):
        self.device, self.cores, self.steps, self.run_id = device, cores, steps, run_id
        self.linear, self.max_megapixels = linear, max_megapixels
        self.env = dict(os.environ)
        for key, value in (environment or {}).items():
            if value is None:
                self.env.pop(key, None)
            else:
                self.env[key] = value
        if visible_gpu is not None:
            self.env["CUDA_VISIBLE_DEVICES"] = str(visible_gpu)

    def __call__(self, folder: Path, step: str, arguments: list[str], *, device_option: bool = False,
                 reads_images: bool = False) -> None:
        if self._stopped():
            raise KeyboardInterrupt
        command = [sys.executable, "-m", "warp_highlights", *arguments, "-q"]
        if device_option and self.device is not None:
            command += ["--device", self.device]
        if reads_images and self.linear:
            command.append("--linear")
        if reads_images and self.max_megapixels is not None:
            command += ["--max-megapixels", f"{self.max_megapixels:g}"]
        started = time.perf_counter()
        child = subprocess.Popen(command, cwd=folder, env=self.env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.PIPE, text=True, errors="replace",
                                 preexec_fn=_child_setup(self.cores))
        with _children_lock:
            _children.setdefault(self.run_id, set()).add(child)
            stopped = self.run_id in _stopped
        if stopped:  # told to stop while it started
            with contextlib.suppress(OSError):
                child.send_signal(signal.SIGTERM)
        try:
            _, stderr = child.communicate()
        except BaseException:  # interrupted here: the child stops too (it removes its partial outputs)
            with contextlib.suppress(OSError):
                child.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.wait(_STOP_SECONDS)
            raise
        finally:
            with _children_lock:
                _children.get(self.run_id, set()).discard(child)
        self.steps.seconds[step] = round(time.perf_counter() - started, 3)
        if child.returncode in (130, 143, -signal.SIGINT, -signal.SIGTERM, -signal.SIGKILL) or self._stopped():
            raise KeyboardInterrupt
        if child.returncode != 0:
            raise CaptureFailed(step, _last_message(stderr, child.returncode), bad_input=child.returncode == 2)

    def _stopped(self) -> bool:
        with _children_lock:
            return self.run_id in _stopped


def _child_setup(cores: list[int] | None):
    """``preexec_fn``: the child gets SIGTERM when the worker that started it dies (Linux), and its CPU share."""

    def setup() -> None:
        if _PRCTL is not None:
            _PRCTL(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG: SIGTERM when the thread that started it ends
        if cores:
            with contextlib.suppress(AttributeError, OSError):
                os.sched_setaffinity(0, cores)

    return setup


def _last_message(stderr: str, status: int) -> str:
    """The command's error line (``warp-highlights fit: error: ...``), else its last line, else the status."""
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    for line in reversed(lines):
        if line.startswith("warp-highlights") and ": error:" in line:
            return line.split(": error:", 1)[1].strip()
    if lines:
        return f"{lines[-1][:300]} (exit status {status})"
    return f"exit status {status}"


def _shrink(source: Path, target: Path) -> None:
    """``target``: ``source`` (an image ``relight`` just wrote, of the capture's size) at most ``THUMBNAIL_WIDTH`` wide.
    Pillow's decompression-bomb limit is lifted for it (a capture of over 179 megapixels is ours, not a bomb)."""
    from PIL import Image

    with _PILLOW_LIMIT_LOCK:
        saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with Image.open(source, formats=["PNG"]) as image:
                image.thumbnail((THUMBNAIL_WIDTH, THUMBNAIL_WIDTH * 4), Image.Resampling.LANCZOS)
                with atomic_file(target) as temporary:
                    image.save(temporary, format="PNG", optimize=True)
        finally:
            Image.MAX_IMAGE_PIXELS = saved
    source.unlink()


def _record(capture: Capture, folder: Path, options: JobOptions, seconds: dict, total: float) -> dict:
    fit_report = _json(folder / "fit-report.json") or {}
    record = {
        "name": capture.name,
        "status": "ok",
        "capture": str(capture.folder.resolve()),
        "heldout": str(capture.heldout.resolve()) if capture.heldout is not None else None,
        "held_out_lights": "folder" if capture.heldout is not None
        else ("heldout.lp" if capture.has_heldout
              else f"lights 0, {options.holdout_every}, {2 * options.holdout_every}, ... (a second fit)"),
        "options": options.key(),
        "lights": fit_report.get("lights"),
        "size": fit_report.get("size"),
        "gaussians_per_light": _gaussians_per_light(fit_report),
        "field_bytes": (folder / "field.whf").stat().st_size,
        "fit_seconds": seconds.get("fit"),
        "seconds": {**seconds, "total": round(total, 3)},
        "scores": None,
        "files": {"field": "field.whf", "thumbnail": "thumbnail.png",
                  "viewer": "viewer/index.html" if options.export else None,
                  "evaluation": "evaluation/report.json" if options.evaluate else None},
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if options.evaluate:
        record["scores"] = _scores(_json(folder / "evaluation" / "report.json") or {})
    return record


def _json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _gaussians_per_light(report: dict) -> float | None:
    """The mean Gaussians per light of ``fit --report`` (its estimation's)."""
    counts = (report.get("estimation") or {}).get("gaussians_per_light") or {}
    mean = counts.get("mean") if isinstance(counts, dict) else None
    return round(float(mean), 2) if isinstance(mean, (int, float)) else None


def _scores(report: dict) -> dict:
    """Per method: mean (and worst) 8-bit sRGB PSNR and mean SSIM of the full images at the held-out lights."""
    per_query = report.get("per_query") or {}
    psnr, ssim = per_query.get("full_srgb_psnr") or {}, per_query.get("full_ssim") or {}
    scores = {}
    for method, values in psnr.items():
        finite = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
        ssim_values = [v for v in (ssim.get(method) or []) if isinstance(v, (int, float)) and math.isfinite(v)]
        scores[method] = {
            "psnr_db": round(sum(finite) / len(finite), 2) if finite else None,
            "worst_psnr_db": round(min(finite), 2) if finite else None,
            "ssim": round(sum(ssim_values) / len(ssim_values), 4) if ssim_values else None,
        }
    return {"lights": len(per_query.get("directions") or []), "methods": scores}
