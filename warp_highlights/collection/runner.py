"""``run``: every capture of a collection fitted, scored and exported on a Dask cluster, resumable.

By default a ``LocalCluster`` of processes: one worker per GPU, each pinned to its device (its commands see only
that GPU), or without GPUs CPU workers with a share of the cores each. ``scheduler`` uses a running cluster
instead (started by dask-jobqueue, Kubernetes, ``dask scheduler``: the user's affair); its workers must see the
captures and the output folder at the same paths (shared storage): only paths travel through the scheduler.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import re
import shutil
import subprocess
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from ..io.atomic import clean_stale_partials, deferred_signals
from ..model.errors import InputError
from ..model.threads import core_count
from .captures import Capture, find_captures, fingerprint
from .gallery import COLLECTION_JSON, INDEX_HTML, write_gallery
from .job import CaptureFailed, JobOptions, process_capture, read_record

__all__ = ["CORES_PER_CPU_WORKER", "CollectionResult", "run", "visible_gpus"]

log = logging.getLogger(__name__)

CORES_PER_CPU_WORKER = 4
"""A CPU worker's default share of the cores: a fit's stages use every core they are given (one thread each),
and four captures' worth of image loading, plotting and Python at once keep a many-core machine busy."""


@dataclass
class CollectionResult:
    """What ``run`` did.

    Attributes:
        output: The output folder (``index.html``, ``collection.json``, one folder per finished capture).
        records: One per capture, in the order found: a finished capture's ``capture.json``, or a failure
            (``status`` "failed", ``step``, ``error``).
        processed: Names fitted in this run. ``skipped``: finished before, with the same options and files.
        failed: Names that failed in this run. ``failed_before``: failed in an earlier run, not tried again (the same
            options and files; ``retry_failed`` or ``force`` tries them).
        dashboard: The Dask dashboard's address (None without a cluster or a dashboard).
    """

    output: Path
    records: list[dict] = field(default_factory=list)
    processed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    failed_before: list[str] = field(default_factory=list)
    dashboard: str | None = None

    @property
    def ok(self) -> bool:
        """Every capture finished."""
        return not self.failed and not self.failed_before


def run(captures, output, *, options: JobOptions | None = None, force: bool = False, retry_failed: bool = False,
        scheduler: str | None = None,
        workers: int | None = None, gpus: int | None = None, device: str | None = None,
        progress: bool = False) -> CollectionResult:
    """Fit, score and export every capture into ``output/<name>``, skipping those finished with the same options.

    Args:
        captures: Capture folders or folders to search (``find_captures``), or ``Capture`` objects.
        output: The collection's output folder (made if missing; its parent must exist).
        options: What each capture gets (``JobOptions``: fit options, hold-out, evaluation, export).
        force: Redo finished captures too (and failed ones).
        retry_failed: Try again the captures that failed before although their files and the options are the same.
        scheduler: Address of a running Dask scheduler (``tcp://host:8786``); None starts a ``LocalCluster``.
        workers: Local workers (default: one per GPU, else one per ``CORES_PER_CPU_WORKER`` cores).
        gpus: GPUs to use on this machine (default: every visible one; 0: the CPU). Not with ``scheduler``.
        device: ``--device`` for every command (default: the worker's GPU, else the CPU when ``gpus`` is 0).
        progress: A progress bar over the captures (tqdm, stderr).

    Returns:
        A ``CollectionResult``; ``index.html`` and ``collection.json`` are written before it returns.

    Raises:
        InputError: no capture found, an unusable output folder, Dask distributed missing, a bad option.
        KeyboardInterrupt: Ctrl-C or SIGTERM: the workers stop their commands, no partial output is left, and a
            rerun goes on with the captures not finished.
    """
    options = options or JobOptions()
    if isinstance(captures, (str, os.PathLike)):
        captures = [captures]
    found = list(captures) if captures and all(isinstance(c, Capture) for c in captures) else find_captures(captures)
    target = Path(output).absolute()
    if device is not None and not re.fullmatch(r"cpu|cuda(:\d+)?", device):
        raise InputError(f"--device {device}: give cpu, cuda or cuda:N")
    if scheduler is not None and (workers is not None or gpus is not None):
        raise InputError(
            "--workers and --gpus size a local cluster; with --scheduler the cluster is sized where it was started")
    plan = None if scheduler is not None else _plan_workers(len(found), workers=workers, gpus=gpus, device=device)
    options = dataclasses.replace(options, device=_device_kind(plan, device))
    found = _keep_earlier_names(found, target)
    _check_apart(found, target)
    output = _output_folder(target)
    for capture in found:
        clean_stale_partials(output / capture.name)
    for name in (COLLECTION_JSON, INDEX_HTML):
        clean_stale_partials(output / name)
    result = CollectionResult(output=output)
    records: dict[str, dict] = {}
    earlier = _earlier_failures(output)
    todo: list[tuple[Capture, bool, str]] = []
    for capture in found:
        stamp = fingerprint(capture)
        record = read_record(output / capture.name)
        failure = earlier.get(capture.name)
        if record is not None and not force and _same_work(record, capture, options, stamp):
            records[capture.name] = record
            result.skipped.append(capture.name)
        elif failure is not None and not (force or retry_failed) and _same_work(failure, capture, options, stamp):
            records[capture.name] = failure
            result.failed_before.append(capture.name)
        else:
            todo.append((capture, (output / capture.name).exists(), stamp))
    if todo:
        if plan is not None:
            # no idle workers: the cores shared by those that run
            plan = _plan_workers(len(todo), workers=workers, gpus=gpus, device=device)
        _run_on_cluster(todo, output, options, records, result, scheduler=scheduler, plan=plan, device=device,
                        progress=progress)
    result.records = [records[c.name] for c in found if c.name in records]
    write_gallery(output, result.records + _other_finished(output, found))
    return result


def visible_gpus() -> list[str]:
    """The GPUs this process may use, as ``CUDA_VISIBLE_DEVICES`` names them (``nvidia-smi``; none without it)."""
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        return [part.strip() for part in listed.split(",") if part.strip() and part.strip() != "-1"]
    nvidia_smi = shutil.which("nvidia-smi")
    if nvidia_smi is None:
        return []
    try:
        listing = subprocess.run([nvidia_smi, "--list-gpus"], capture_output=True, text=True, timeout=30,
                                 check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(k) for k, line in enumerate(line for line in listing.splitlines() if line.startswith("GPU "))]


def _device_kind(plan: list[dict] | None, device: str | None) -> str | None:
    """What the commands run on, as the skip key compares it: "cuda", "cpu", or None (a running cluster's default)."""
    if plan is None:
        return None if device is None else ("cpu" if device == "cpu" else "cuda")
    return "cuda" if "visible_gpu" in plan[0] else "cpu"


def _keep_earlier_names(found: list[Capture], output: Path) -> list[Capture]:
    """A capture finished before under another name (the set of captures given then made other names unique) keeps
    that name, so that adding captures to a collection does not fit the old ones again under new names."""
    if not output.is_dir():
        return found
    earlier = {}
    for folder in output.iterdir():
        record = read_record(folder) if folder.is_dir() and not folder.name.startswith(".") else None
        if record is not None and record.get("name") == folder.name and isinstance(record.get("capture"), str):
            earlier[record["capture"]] = folder.name
    taken = {c.name for c in found}
    renamed = []
    for capture in found:
        name = earlier.get(str(capture.folder.resolve()))
        if name is not None and name != capture.name and name not in taken:
            taken.discard(capture.name)
            taken.add(name)
            capture = dataclasses.replace(capture, name=name)
        renamed.append(capture)
    return renamed


def _check_apart(found: list[Capture], output: Path) -> None:
    """Refuse an output folder inside a capture, or a capture inside (or as) a capture's output folder: replacing
    ``OUT/NAME`` must never touch a capture's own files."""
    out = output.resolve()
    for capture in found:
        for source in (capture.folder, capture.heldout):
            if source is None:
                continue
            source = source.resolve()
            if out == source or source in out.parents:
                raise InputError(
                    f"{output}: the output folder is inside the capture {source}; write the collection somewhere else")
            slot = out / capture.name
            if source == slot or slot in source.parents:
                raise InputError(
                    f"{source}: this capture is where its output {slot} would go; give another output folder (-o)")


def _output_folder(output) -> Path:
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise InputError(f"{output}: exists and is not a folder; give a folder for the collection's outputs")
    if not output.parent.is_dir():
        raise InputError(f"{output}: its folder {output.parent} does not exist; create it first")
    if output.is_dir() and not _is_collection(output):
        raise InputError(f"{output}: holds files that are not a warp-highlights collection (no {COLLECTION_JSON}, "
                         f"no finished capture), which its gallery could replace; give a new or empty folder")
    try:
        output.mkdir(exist_ok=True)
    except OSError as error:
        raise InputError(
            f"{output}: cannot create the output folder ({error.strerror}); check the permissions") from None
    return output


def _is_collection(folder: Path) -> bool:
    """Whether ``folder`` is empty (hidden entries aside), or a collection written before: it holds
    ``collection.json`` or a finished capture's folder."""
    try:
        entries = [entry for entry in os.scandir(folder) if not entry.name.startswith(".")]
    except OSError as error:
        raise InputError(f"{folder}: cannot list the output folder ({error.strerror}); check its permissions") from None
    if not entries or (folder / COLLECTION_JSON).is_file():
        return True
    return any(entry.is_dir(follow_symlinks=False) and read_record(entry.path) is not None for entry in entries)


def _same_work(record: dict, capture: Capture, options: JobOptions, stamp: str) -> bool:
    return (record.get("options") == options.key() and record.get("capture") == str(capture.folder.resolve())
            and record.get("fingerprint") == stamp)


def _other_finished(output: Path, found: list[Capture]) -> list[dict]:
    """Finished captures in ``output`` that this run was not given (an earlier run's): the gallery lists them too."""
    names, folders = {c.name for c in found}, {str(c.folder.resolve()) for c in found}
    others = []
    for folder in sorted(output.iterdir()):
        if folder.is_dir() and not folder.name.startswith(".") and folder.name not in names:
            record = read_record(folder)
            if record is not None and record.get("name") == folder.name and record.get("capture") not in folders:
                others.append(record)
    return others


def _earlier_failures(output: Path) -> dict[str, dict]:
    """The failed captures of the last run, from its ``collection.json``."""
    try:
        captures = json.loads((output / COLLECTION_JSON).read_text()).get("captures") or []
    except (OSError, ValueError, AttributeError):
        return {}
    return {r["name"]: r for r in captures
            if isinstance(r, dict) and r.get("status") == "failed" and isinstance(r.get("name"), str)
            # only failures the capture's own files cause (bad input); a full disk or a lost worker is retried
            and r.get("repeatable")}


def _plan_workers(todo: int, *, workers: int | None, gpus: int | None, device: str | None) -> list[dict]:
    """One entry per local worker: the GPU its commands see (as their cuda:0), or its CPU cores."""
    if device not in (None, "cpu", "cuda", "cuda:0"):
        raise InputError(f"--device {device}: a local cluster gives each worker one GPU, which its commands see as "
                         f"cuda:0; choose the GPUs "
                         "with --gpus or CUDA_VISIBLE_DEVICES, or give --device cpu or cuda")
    available = visible_gpus()
    if gpus is not None and gpus > len(available):
        raise InputError(f"--gpus {gpus}: this machine shows {len(available)} GPU(s)"
                         + (f" ({', '.join(available)})" if available else ""))
    if gpus == 0 and device in ("cuda", "cuda:0"):
        raise InputError("--gpus 0 runs CPU workers; leave out --device cuda, or give --gpus N")
    if device in ("cuda", "cuda:0") and not available:
        raise InputError(
            "--device cuda: this machine shows no GPU (nvidia-smi); leave out --device, or give --device cpu")
    chosen = available[: gpus if gpus is not None else len(available)]
    if chosen and device != "cpu":
        count = max(1, min(workers or len(chosen), len(chosen), todo))
        return [{"visible_gpu": chosen[k], "device": "cuda:0"} for k in range(count)]
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(core_count()))
    count = max(1, min(workers or max(1, len(cores) // CORES_PER_CPU_WORKER), len(cores), todo))
    shares = [cores[round(k * len(cores) / count): round((k + 1) * len(cores) / count)] for k in range(count)]
    return [{"cores": share, "device": "cpu"} for share in shares]


def launch_environment() -> dict[str, str | None]:
    """The variables Dask's nanny sets for its workers (``distributed.nanny.pre-spawn-environ`` and
    ``environ``: ``MALLOC_TRIM_THRESHOLD_=65536``, one OpenMP/MKL/OpenBLAS thread) as this process has
    them, None where unset: each capture's commands get them back. Dask's trim threshold makes an
    ``evaluate`` far slower: every large array freed goes back to the system and the next one faults
    its pages in again."""
    import dask

    keys = set()
    for name in ("distributed.nanny.pre-spawn-environ", "distributed.nanny.environ"):
        keys |= set(dask.config.get(name, None) or {})
    return {key: os.environ.get(key) for key in sorted(keys)}


def _on_worker(capture: Capture, output: str, options: JobOptions, replace: bool, stamp: str, pins: dict, default: dict,
               run_id: str,
               environment: dict | None = None) -> dict:
    """The task: one capture on the worker that runs it (pinned as ``pins`` says for that worker's name, else
    ``default``; its commands with ``environment`` over the worker's). Returns its record, or a failure record: nothing
    a capture does ends the others."""
    from distributed import get_worker

    pin = pins.get(str(get_worker().name), default)
    try:
        return process_capture(capture, output, options, device=pin.get("device"), visible_gpu=pin.get("visible_gpu"),
                               cores=pin.get("cores"), replace=replace, fingerprint=stamp, run_id=run_id,
                               environment=environment)
    except CaptureFailed as failure:
        return _failure(capture, options, stamp, failure.step, failure.message, repeatable=failure.bad_input)
    except (InputError, OSError) as error:  # the output folder refused (a file edited by the user), a full disk
        message = (str(error) if isinstance(error, InputError)
                   else f"{error.strerror or error} ({error.filename or output})")
        return _failure(capture, options, stamp, "output", message)
    except KeyboardInterrupt:  # its commands were stopped (Ctrl-C, the cluster closing): nothing was left
        return _failure(capture, options, stamp, "interrupted",
                        "stopped before it finished (its worker was closing); run the collection again")
    except Exception as error:  # a bug, or a library's surprise: this capture's failure, with what it was
        return _failure(capture, options, stamp, "internal", f"{type(error).__name__}: {error}")


def _failure(capture: Capture, options: JobOptions, stamp: str, step: str, message: str, *,
             repeatable: bool = False) -> dict:
    """A failed capture's record. ``repeatable``: its own files caused it (a rerun with the same files and options skips
    it)."""
    return {"name": capture.name, "status": "failed", "capture": str(capture.folder.resolve()),
            "options": options.key(),
            "fingerprint": stamp, "step": step, "error": message, "repeatable": repeatable}


def _run_on_cluster(todo, output: Path, options: JobOptions, records: dict, result: CollectionResult, *, scheduler,
                    plan, device,
                    progress: bool) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
        from distributed.client import FutureCancelledError

        from .plugin import StopChildren
    except ImportError:
        raise InputError(
            "warp-highlights collection needs Dask distributed: pip install 'warp-highlights[collection]'") from None
    run_id = uuid.uuid4().hex[:12]
    stack = contextlib.ExitStack()
    try:
        stack.callback(_sweep, output, [c.name for c, _, _ in todo])  # last: once the workers are gone
        if scheduler is None:
            # Dask's own log lines off but its critical ones: a worker whose heartbeat meets the scheduler already
            # closed at the end logs an error with its traceback; what a capture did, a lost worker included, the
            # command says itself
            cluster = stack.enter_context(LocalCluster(n_workers=len(plan), threads_per_worker=1, processes=True,
                                                       dashboard_address="127.0.0.1:0",
                                                       silence_logs=logging.CRITICAL, memory_limit=0))
            pins = {str(k): pin for k, pin in enumerate(plan)}  # LocalCluster names its workers 0, 1, ...
            client = stack.enter_context(Client(cluster))
            where = ", ".join(f"GPU {p['visible_gpu']}" if "visible_gpu" in p else f"{len(p['cores'])} cores"
                              for p in plan)
            log.info("local cluster: %d workers (%s)", len(plan), where)
        else:
            try:
                client = stack.enter_context(Client(scheduler, timeout="30s"))
            except (OSError, TimeoutError, ValueError) as error:
                raise InputError(f"cannot reach the Dask scheduler at {scheduler} ({error}); check the address and "
                                 f"that it runs") from None
            pins = {}
        with contextlib.suppress(Exception):
            result.dashboard = client.dashboard_link
        if result.dashboard:
            log.info("Dask dashboard: %s", result.dashboard)
        plugin = StopChildren(run_id, ignore_interrupts=scheduler is None)  # a remote worker's signals are its own
        client.register_plugin(plugin)
        # removing it stops this run's commands on every worker: at the end (none left), or on Ctrl-C (a running
        # cluster's too)
        stack.callback(_quietly, client.unregister_worker_plugin, plugin.name)
        default = {"device": device} if device is not None else {}  # a running cluster's workers: --device alone
        environment = launch_environment()
        futures = {client.submit(_on_worker, capture, str(output), options, replace, stamp, pins, default, run_id,
                                 environment,
                                 key=f"capture-{capture.name}-{run_id}", pure=False): capture
                   for capture, replace, stamp in todo}
        stack.callback(_quietly, client.cancel, list(futures))  # on any way out: nothing queued starts
        bar = _bar(progress, len(todo), len(result.skipped))
        if bar is not None:
            stack.callback(bar.close)
        for future in as_completed(futures):
            capture = futures[future]
            try:
                record = future.result()
            except FutureCancelledError:
                continue
            except Exception as error:  # the worker died under it (KilledWorker), a lost connection
                record = _failure(capture, options, fingerprint(capture), "worker",
                                  f"{type(error).__name__}: {error}; the worker running it was lost (out of memory?), "
                                  f"see the Dask workers' logs")
            records[capture.name] = record
            (result.processed if record["status"] == "ok" else result.failed).append(capture.name)
            if record["status"] != "ok":
                log.warning("%s: failed at %s: %s", capture.name, record.get("step"), record.get("error"))
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"{len(result.failed)} failed" if result.failed else "", refresh=False)
    finally:
        # a second Ctrl-C waits for the workers to stop and the sweep: nothing is left half-removed
        with deferred_signals():
            stack.close()


def _quietly(function, *args) -> None:
    with contextlib.suppress(Exception):
        function(*args)


def _sweep(output: Path, names: list[str]) -> None:
    """After the cluster: the temporary folders of workers that were stopped mid-capture (their processes are gone)."""
    for name in names:
        clean_stale_partials(output / name)


def _bar(enabled: bool, total: int, skipped: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=f"captures ({skipped} finished before)" if skipped else "captures", unit="capture",
                leave=True)
