"""Interrupts: SIGINT, SIGTERM and SIGKILL at random points never damage an earlier output.

Each command runs as ``python -m warp_highlights`` writing, with --overwrite, over an earlier output
of the same command, and gets SIGINT or SIGTERM after a random delay (a fixed-seed generator, from
0.3 s after the start to the command's typical duration). Afterwards: exit status 130 (SIGINT) or
143 (SIGTERM), or 0 when the command finished first; the earlier output byte-identical when
interrupted, wholly the new one when finished; no ``.partial-``/``.replaced-`` entry beside it; no
traceback. A render killed with SIGKILL leaves a hidden partial folder, which the next render to the
same output cleans up.
"""

from __future__ import annotations

import hashlib
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import TINY_FIT
from warp_highlights.cli import main

pytestmark = pytest.mark.slow

POINTS = 5
"""Random interrupt points per command and signal."""
EARLIEST_S = 0.3
SIGNALS = {"SIGINT": (signal.SIGINT, 130), "SIGTERM": (signal.SIGTERM, 143)}
VOLATILE_SUFFIXES = (".json", ".md", ".whf")
"""Files holding timings (reports, indexes, the field file's report): compared by name only."""
RUN_TIMEOUT_S = 120

@dataclass(frozen=True)
class Workload:
    target: str  # the output's name
    earlier: tuple[str, ...]  # the output written first (in-process)
    new: tuple[str, ...]  # the interrupted command: a second or two of work on the 2-core CPU


WORKLOADS = {
    "render": Workload(
        "dataset",
        ("render", "sphere", "{out}", "--lights", "16", "--size", "32x18", "--samples", "1", "--heldout", "none",
         "--device", "cpu"),
        ("render", "sphere", "{out}", "--lights", "64", "--size", "96x54", "--samples", "4", "--device", "cpu"),
    ),
    "fit": Workload(
        "field.whf",
        ("fit", "{data}", "-o", "{out}", "--size", "16x9", "--device", "cpu", *TINY_FIT),
        ("fit", "{data}", "-o", "{out}", "--set", "estimation.iterations=500", "--device", "cpu"),
    ),
    "relight": Workload(
        "relit",
        ("relight", "{field}", "--lights", "{lp_few}", "-o", "{out}", "--device", "cpu"),
        ("relight", "{field}", "--lights", "{lp_many}", "--size", "320x180", "-o", "{out}", "--device", "cpu"),
    ),
    "animate": Workload(
        "frames",
        ("animate", "{field}", "--path", "orbit:35", "--frames", "3", "-o", "{out}", "--device", "cpu"),
        ("animate", "{field}", "--path", "orbit:35", "--frames", "48", "--size", "320x180", "-o", "{out}", "--device",
         "cpu"),
    ),
    "evaluate": Workload(
        "evaluation",
        ("evaluate", "{field}", "{data}", "--triangle", "none", "--methods", "circular", "-o", "{out}", "--device",
         "cpu"),
        ("evaluate", "{field}", "{data}", "--steps", "3", "-o", "{out}", "--device", "cpu"),
    ),
    "demo": Workload(
        "demo",
        ("demo", "{out}", "--lights", "9", "--size", "32x18", "--frames", "2", "--device", "cpu"),
        ("demo", "{out}", "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu"),
    ),
}


# --- helper functions ------------------------------------------------------------------------------


def _argv(template, inputs: dict, out: Path) -> list[str]:
    names = {**{k: str(v) for k, v in inputs.items()}, "out": str(out)}
    return [part.format(**names) for part in template] + ["-q"]


def _snapshot(path: Path) -> dict[str, str]:
    """A file's or a folder's every entry (hidden ones included): files by SHA-256, folders as '/'."""
    path = Path(path)
    if path.is_file():
        return {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}
    result = {}
    for entry in sorted(path.rglob("*")):
        result[str(entry.relative_to(path))] = "/" if entry.is_dir() else hashlib.sha256(entry.read_bytes()).hexdigest()
    return result


def _temporaries(folder: Path) -> list[str]:
    return [name for name in os.listdir(folder) if ".partial-" in name or ".replaced-" in name]


def _subprocess_env() -> dict[str, str]:
    """This environment, with the Warp kernel cache this test session uses."""
    import warp as wp

    env = dict(os.environ)
    cache = wp.config.kernel_cache_dir
    if "WARP_CACHE_PATH" not in env and cache and Path(cache).name == wp.config.version:
        env["WARP_CACHE_PATH"] = str(Path(cache).parent)  # Warp adds the version folder itself
    return env


def _cli(argv: list[str]) -> list[str]:
    return [sys.executable, "-m", "warp_highlights", *argv]


def _stderr_problem(stderr: str) -> str | None:
    return f"a traceback on stderr:\n{stderr[-3000:]}" if "Traceback" in stderr else None


# --- fixtures --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inputs(tiny_sphere, tmp_path_factory) -> dict:
    """A 16-light 32x18 sphere with held-out centroids, a tiny fit of it, light files of 3 and 80 lights."""
    from warp_highlights.io.lightfile import write_lp
    from warp_highlights.model.lights import LightSet

    root = tmp_path_factory.mktemp("inputs")
    data, field = tiny_sphere
    lp_few, lp_many = root / "few.lp", root / "many.lp"
    few = np.array([[0.0, 0.0, 1.0], [0.5, 0.2, 1.0], [-0.4, 0.3, 1.0]])
    write_lp(LightSet(few / np.linalg.norm(few, axis=1, keepdims=True)), lp_few)
    write_lp(LightSet.fibonacci_dome(80), lp_many)
    return {"data": data, "field": field, "lp_few": lp_few, "lp_many": lp_many, "env": _subprocess_env()}


@dataclass
class Prepared:
    workload: Workload
    out: Path  # the output every run writes over
    earlier: list[str]  # argv writing the earlier output (in-process)
    new: list[str]  # argv of the interrupted runs (with --overwrite)
    expected_new: dict[str, str]  # the new output, written once undisturbed
    seconds: float  # how long that run took as a subprocess
    env: dict[str, str]  # the subprocesses' environment


@pytest.fixture(scope="module")
def prepared(inputs, tmp_path_factory):
    """The command's shared state (made on first use): the earlier output in place, the new output's
    content and typical duration measured by one undisturbed subprocess run."""
    _prepared: dict[str, Prepared] = {}

    def get(name: str) -> Prepared:
        if name not in _prepared:
            workload = WORKLOADS[name]
            root = tmp_path_factory.mktemp(f"interrupt-{name}")
            (root / "work").mkdir()
            (root / "reference").mkdir()
            out = root / "work" / workload.target
            earlier = _argv(workload.earlier, inputs, out)
            assert main(earlier) == 0, f"writing the earlier {name} output failed"
            reference = root / "reference" / workload.target
            started = time.perf_counter()
            result = subprocess.run(_cli(_argv(workload.new, inputs, reference)), env=inputs["env"],
                                    capture_output=True, text=True,
                                    timeout=RUN_TIMEOUT_S)
            seconds = time.perf_counter() - started
            assert result.returncode == 0, f"the undisturbed {name} run failed: {result.stderr[-3000:]}"
            _prepared[name] = Prepared(workload, out, earlier + ["--overwrite"],
                                       _argv(workload.new, inputs, out) + ["--overwrite"],
                                       _snapshot(reference), seconds, inputs["env"])
        return _prepared[name]

    return get


def _reset(state: Prepared, *, rewrite: bool = False) -> None:
    """Put the earlier output back in place alone (after a run that replaced it, or failed)."""
    import shutil

    for name in os.listdir(state.out.parent):
        path = state.out.parent / name
        if name != state.out.name or (rewrite and state.out.is_dir() and not state.out.is_symlink()):
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    if rewrite or not state.out.exists():
        assert main(state.earlier) == 0


def _delays(command: str, signame: str, longest: float) -> list[float]:
    rng = random.Random(f"warp-highlights interrupts {command} {signame}")
    return [EARLIEST_S + rng.random() * max(0.0, longest - EARLIEST_S) for _ in range(POINTS)]


def _check_new_output(prepared: Prepared, after: dict[str, str]) -> None:
    expected = prepared.expected_new
    assert sorted(after) == sorted(expected), "finished, but the output is not exactly the new one"
    different = [name for name, digest in after.items()
                 if not name.endswith(VOLATILE_SUFFIXES) and digest != expected[name]]
    assert not different, f"finished, but these differ from the new output: {different[:5]}"


def _field_width(path: Path):
    """The width of the field file at ``path`` (the earlier fit is 16 pixels wide, the new one 32)."""
    from warp_highlights.io.fieldfile import load_field

    try:
        return load_field(path).width
    except Exception as error:  # noqa: BLE001 - reported by the assertion
        return f"unreadable: {error}"


# --- SIGINT / SIGTERM ------------------------------------------------------------------------------


@pytest.mark.parametrize("point", range(POINTS))
@pytest.mark.parametrize("signame", list(SIGNALS))
@pytest.mark.parametrize("command", list(WORKLOADS))
def test_an_interrupt_keeps_the_earlier_output(command, signame, point, prepared):
    state = prepared(command)
    signum, interrupted_status = SIGNALS[signame]
    delay = _delays(command, signame, state.seconds)[point]
    parent = state.out.parent
    _reset(state)
    before = _snapshot(state.out)

    process = subprocess.Popen(_cli(state.new), env=state.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    time.sleep(delay)
    process.send_signal(signum)  # does nothing when it has already exited
    try:
        stdout, stderr = process.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        pytest.fail(f"{command} did not end within {RUN_TIMEOUT_S} s of {signame} at {delay:.2f} s")
    status = process.returncode
    after = _snapshot(state.out) if state.out.exists() else None
    leftovers = _temporaries(parent)
    others = sorted(set(os.listdir(parent)) - {state.out.name})
    new_width = _field_width(state.out) if command == "fit" and status == 0 else None
    if status == 0 or after != before or leftovers or others:  # the next run writes over the earlier output again
        _reset(state, rewrite=True)

    where = f"{command}, {signame} after {delay:.2f} s (typical run {state.seconds:.1f} s)"
    if after is None:
        content = "gone"
    elif after == before:
        content = "the earlier output, intact"
    elif sorted(after) == sorted(state.expected_new):
        content = "the new output's files"
    else:
        content = ("changed: "
                   + ", ".join(sorted(n for n in set(before) | set(after) if before.get(n) != after.get(n))[:5]))
    assert _stderr_problem(stderr) is None, f"{where}: {_stderr_problem(stderr)}"
    assert status in (interrupted_status, 0), (
        f"{where}: exit status {status}, expected {interrupted_status} (or 0); output {content}; "
        f"stdout: {stdout[-300:]!r}; stderr: {stderr[-1200:]!r}"
    )
    assert not leftovers, f"{where}: left beside the output: {leftovers}"
    assert not others, f"{where}: left beside the output: {others}"
    assert after is not None, f"{where}: the earlier output is gone"
    if status == 0:
        _check_new_output(state, after)
        if command == "fit":
            assert new_width == 32, f"{where}: finished, but the field is not the new one (32 pixels wide): {new_width}"
    else:
        assert after == before, (f"{where}: exit status {status} but the earlier output is not intact: {content}; "
                                 f"stdout: {stdout[-300:]!r}")


# --- SIGKILL ---------------------------------------------------------------------------------------


def test_a_killed_render_is_cleaned_up_by_the_next_one(inputs, tmp_path):
    workload = WORKLOADS["render"]
    parent = tmp_path / "work"
    parent.mkdir()
    out = parent / workload.target
    assert main(_argv(workload.earlier, inputs, out)) == 0
    before = _snapshot(out)
    new = _argv(workload.new, inputs, out) + ["--overwrite"]

    process = subprocess.Popen(_cli(new), env=inputs["env"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
    prefix = f".{out.name}.partial-"
    deadline = time.monotonic() + RUN_TIMEOUT_S
    partial = []
    while not partial and process.poll() is None and time.monotonic() < deadline:
        partial = [name for name in os.listdir(parent) if name.startswith(prefix)]
        time.sleep(0.005)
    process.kill()
    _, stderr = process.communicate(timeout=RUN_TIMEOUT_S)
    assert partial, (f"no hidden {prefix}* entry appeared while render ran (exit status {process.returncode}): "
                     f"{stderr[-1500:]!r}")
    assert process.returncode == -signal.SIGKILL, f"render ended before SIGKILL (status {process.returncode})"
    assert _snapshot(out) == before, "SIGKILL mid-way changed the earlier output"

    status = main(new)
    assert status == 0
    assert not _temporaries(parent), f"left after the next render: {_temporaries(parent)}"
    assert sorted(os.listdir(parent)) == [out.name]
    from warp_highlights.io.dataset import ReflectanceField

    assert ReflectanceField.load(out, progress=False).light_count == 64
