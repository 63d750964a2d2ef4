"""Reliability of the commands that write, as black-box specifications of the CLI.

1. Operating-system failures (a read-only folder, a full file system, a missing parent folder) end
   with exit status 2 and exactly one line ``warp-highlights COMMAND: error: ...`` on stderr, and
   leave nothing behind; what can be checked up front (read-only, missing parent, an existing output
   without --overwrite, an unwritable --report) is refused before any work, in under a second.
2. ``--overwrite`` replaces only a folder this project wrote (it keeps a record of its files there):
   a folder holding a user's file, or a project folder the user added a file to, is refused and
   left byte-identical.

The conditions: a read-only folder is a read-only tmpfs mount (``mount -t tmpfs -o ro``), else, when
not root, a folder with mode 0555, else the test is skipped. A full file system is a small tmpfs
filled up with a filler file, else (no permission to mount) writes into the folder raise
``OSError(ENOSPC)`` through patched ``open``/``os.replace``/``os.rename``. Set
``WARP_HIGHLIGHTS_TEST_NO_MOUNT=1`` to take the fallbacks where mounting works.
"""

from __future__ import annotations

import builtins
import errno
import hashlib
import io
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import TINY_FIT
from warp_highlights.cli import main

SMALL_RENDER = ["--size", "32x18", "--samples", "1", "--heldout", "none", "--device", "cpu"]
CHECK_SECONDS = 1.0
"""An up-front refusal returns within this (imports warmed up first)."""
FULL_TMPFS_BYTES = 64 * 1024
FOLDER_FREE_BYTES = 8 * 1024
"""Left free on the 'full' file system for folder outputs: a file or two fit, the output does not."""
VOLATILE_SUFFIXES = (".json", ".md", ".whf")
"""Files holding timings (reports, indexes, the field file's report): compared by name only."""


@dataclass(frozen=True)
class Cmd:
    argv: tuple[str, ...]  # {out} the output, {report} fit's report; {data} {field} {lp} the inputs
    target: str  # the output's name
    folder: bool  # the output is a folder


COMMANDS = {
    "render": Cmd(("render", "sphere", "{out}", "--lights", "16", *SMALL_RENDER), "dataset", True),
    "demo": Cmd(("demo", "{out}", "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu"), "demo",
                True),
    "relight-exr": Cmd(("relight", "{field}", "--light", "0.3,0.5,1", "-o", "{out}", "--device", "cpu"), "relit.exr",
                       False),
    "relight-png": Cmd(("relight", "{field}", "--light", "0.3,0.5,1", "-o", "{out}", "--device", "cpu"), "relit.png",
                       False),
    "relight-lights": Cmd(("relight", "{field}", "--lights", "{lp}", "-o", "{out}", "--device", "cpu"), "relit", True),
    "animate-gif": Cmd(("animate", "{field}", "--path", "orbit:35", "--frames", "4", "-o", "{out}", "--device", "cpu"),
                       "orbit.gif", False),
    "animate-dir": Cmd(("animate", "{field}", "--path", "orbit:35", "--frames", "4", "-o", "{out}", "--device", "cpu"),
                       "frames", True),
    "evaluate": Cmd(("evaluate", "{field}", "{data}", "--triangle", "none", "-o", "{out}", "--device", "cpu"),
                    "evaluation", True),
    "fit": Cmd(("fit", "{data}", "-o", "{out}", "--report", "{report}", "--device", "cpu", *TINY_FIT), "field.whf",
               False),
    "sheet": Cmd(("sheet", "{data}", "-o", "{out}", "--count", "4", "--thumb-height", "18"), "sheet.png", False),
    "view": Cmd(("view", "{field}", "--screenshot", "{out}", "--window-size", "240x120", "--device", "cpu"), "view.png",
                False),
}

FOLDER_VARIANTS = {
    # an earlier output (A) and the one written over it (B): B lacks some of A's files
    "render": (("render", "sphere", "{out}", "--lights", "16", *SMALL_RENDER),
               ("render", "sphere", "{out}", "--lights", "12", *SMALL_RENDER)),
    "relight-lights": (("relight", "{field}", "--lights", "{lp}", "-o", "{out}", "--device", "cpu"),
                       ("relight", "{field}", "--lights", "{lp3}", "-o", "{out}", "--device", "cpu")),
    "animate-dir": (("animate", "{field}", "--path", "orbit:35", "--frames", "5", "-o", "{out}", "--device", "cpu"),
                    ("animate", "{field}", "--path", "orbit:35", "--frames", "3", "-o", "{out}", "--device", "cpu")),
    "evaluate": (("evaluate", "{field}", "{data}", "--triangle", "none", "-o", "{out}", "--device", "cpu"),
                 ("evaluate", "{field}", "{data}", "--triangle", "none", "--methods", "circular,straight", "-o",
                  "{out}", "--device", "cpu")),
    "demo": (("demo", "{out}", "--lights", "9", "--size", "32x18", "--frames", "2", "--device", "cpu"),
             ("demo", "{out}", "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu")),
}  # fmt: skip
SLOW_FOLDERS = {"demo", "evaluate"}
"""Folder commands whose replacement tests run the command three times for real: marked slow."""


# --- helper functions ------------------------------------------------------------------------------


def _argv(template, inputs: dict, **paths) -> list[str]:
    names = {**{k: str(v) for k, v in inputs.items()}, **{k: str(v) for k, v in paths.items()}}
    return [part.format(**names) for part in template] + ["-q"]


def _run(argv: list[str]):
    """main(argv) -> (status, seconds); an exception escaping main fails the test with its message."""
    started = time.perf_counter()
    try:
        status = main(argv)
    except SystemExit as stop:
        status = f"SystemExit({stop.code})"
    except Exception as error:  # noqa: BLE001 - what escaped main is the finding
        pytest.fail(f"main({' '.join(argv[:1])} ...) raised {type(error).__name__}: {error}", pytrace=False)
    return status, time.perf_counter() - started


def _one_error_line(capsys, command: str, status) -> str:
    err = capsys.readouterr().err
    assert status == 2, f"exit status {status}, expected 2; stderr: {err.strip()[-2000:]!r}"
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1, f"expected exactly one line on stderr, got {len(lines)}: {err[-2000:]!r}"
    assert lines[0].startswith(f"warp-highlights {command}: error:"), lines[0]
    return lines[0]


def _tree(folder: Path) -> dict[str, str]:
    """Every entry under ``folder`` (hidden ones included): files by SHA-256, folders as '/'."""
    folder = Path(folder)
    result = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        result[name] = "/" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return result


def _listing(folder: Path) -> list[str]:
    return sorted(os.listdir(folder))


def _temporaries(folder: Path) -> list[str]:
    return [name for name in os.listdir(folder) if ".partial-" in name or ".replaced-" in name]


# --- the conditions --------------------------------------------------------------------------------


def _mount_tmpfs(folder: Path, options: str, request) -> bool:
    """Mount a tmpfs on ``folder`` (unmounted at teardown); False where that is not permitted."""
    if os.environ.get("WARP_HIGHLIGHTS_TEST_NO_MOUNT") or shutil.which("mount") is None:
        return False
    try:
        result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True,
                                timeout=30)
    except (OSError, subprocess.SubprocessError):
        return False
    if result.returncode != 0:
        return False

    def unmount():
        for command in (["umount", str(folder)], ["umount", "-l", str(folder)]):
            if subprocess.run(command, capture_output=True, timeout=30).returncode == 0:
                return

    request.addfinalizer(unmount)
    return True


def _fill(root: Path, free: int) -> None:
    """Fill the file system at ``root`` with ``root/filler.bin`` until ``free`` bytes are left."""
    chunk = b"\0" * 4096
    descriptor = os.open(root / "filler.bin", os.O_CREAT | os.O_WRONLY, 0o644)
    try:
        while True:
            os.write(descriptor, chunk)
    except OSError as error:
        assert error.errno == errno.ENOSPC, error
    finally:
        os.close(descriptor)
    size = (root / "filler.bin").stat().st_size
    os.truncate(root / "filler.bin", max(0, size - free))
    left = os.statvfs(root)
    assert abs(left.f_bavail * left.f_frsize - free) <= 4096, (left.f_bavail * left.f_frsize, free)


def _patch_no_space(monkeypatch, root: Path) -> None:
    """Writes under ``root`` fail with ENOSPC: opening a file to write, and renaming into place."""
    prefix = os.path.abspath(root)

    def inside(path) -> bool:
        try:
            text = os.path.abspath(os.fsdecode(os.fspath(path)))
        except TypeError:  # a file descriptor
            return False
        return text == prefix or text.startswith(prefix + os.sep)

    def no_space(path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.fspath(path))

    real_open, real_replace, real_rename = builtins.open, os.replace, os.rename

    def patched_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, bytes, os.PathLike)) and any(c in mode for c in "wax+") and inside(file):
            no_space(file)
        return real_open(file, mode, *args, **kwargs)

    def patched_replace(src, dst, *args, **kwargs):
        if inside(dst):
            no_space(dst)
        return real_replace(src, dst, *args, **kwargs)

    def patched_rename(src, dst, *args, **kwargs):
        if inside(dst):
            no_space(dst)
        return real_rename(src, dst, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", patched_open)
    monkeypatch.setattr(io, "open", patched_open)
    monkeypatch.setattr(os, "replace", patched_replace)
    monkeypatch.setattr(os, "rename", patched_rename)


@dataclass
class Place:
    """Where an output goes under a condition, and what must be there afterwards."""

    condition: str
    parent: Path  # the output's folder
    how: str  # how the condition was made
    expected: dict[Path, list[str]]  # folder -> its listing afterwards

    def check_nothing_left(self) -> None:
        for folder, listing in self.expected.items():
            if listing is None:
                assert not folder.exists(), f"{folder} was created"
            else:
                assert _listing(folder) == listing, f"left behind in {folder} ({self.how})"


def _place(condition: str, tmp_path: Path, request, monkeypatch, *, free: int) -> Place:
    if condition == "read-only":
        folder = tmp_path / "ro"
        folder.mkdir()
        if _mount_tmpfs(folder, "ro,size=1m", request):
            return Place(condition, folder, "tmpfs mounted read-only", {folder: [], tmp_path: ["ro"]})
        folder.chmod(0o555)
        request.addfinalizer(lambda: folder.chmod(0o755))
        try:
            (folder / "probe").touch()
        except OSError:
            return Place(condition, folder, "chmod 0555", {folder: [], tmp_path: ["ro"]})
        (folder / "probe").unlink()
        pytest.skip("no read-only folder can be made here: mounting a tmpfs is not permitted and chmod does not stop "
                    "this user (root)")
    if condition == "full":
        root = tmp_path / "full"
        root.mkdir()
        work = root / "work"
        if _mount_tmpfs(root, f"size={FULL_TMPFS_BYTES}", request):
            work.mkdir()
            _fill(root, free)
            return Place(condition, work, f"tmpfs of {FULL_TMPFS_BYTES // 1024} KiB, {free // 1024} KiB free",
                         {work: [], root: ["filler.bin", "work"]})
        work.mkdir()
        _patch_no_space(monkeypatch, root)
        return Place(condition, work, "monkeypatched ENOSPC", {work: [], root: ["work"]})
    assert condition == "missing parent"
    return Place(condition, tmp_path / "missing", "missing parent folder", {tmp_path / "missing": None, tmp_path: []})


# --- fixtures --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inputs(tiny_sphere, tmp_path_factory) -> dict:
    """A 16-light 32x18 sphere with held-out centroids, a tiny fit of it, and two light files."""
    from warp_highlights.io.lightfile import write_lp
    from warp_highlights.model.lights import LightSet

    root = tmp_path_factory.mktemp("inputs")
    data, field = tiny_sphere
    directions = np.array([[0.0, 0.0, 1.0], [0.5, 0.2, 1.0], [-0.4, 0.3, 1.0], [0.1, -0.6, 1.0], [0.7, 0.7, 0.4]])
    lights = LightSet(directions / np.linalg.norm(directions, axis=1, keepdims=True))
    lp, lp3 = root / "five.lp", root / "three.lp"
    write_lp(lights, lp)
    write_lp(LightSet(lights.directions[:3]), lp3)
    return {"data": data, "field": field, "lp": lp, "lp3": lp3}


@pytest.fixture(scope="module")
def view_unavailable() -> str | None:
    """Why ``view --screenshot`` cannot render here (no pyvista, no off-screen OpenGL), or None."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")  # as warp_highlights.view.viz does
    try:
        import pyvista as pv

        plotter = pv.Plotter(off_screen=True, window_size=(64, 48))
        plotter.add_mesh(pv.Sphere())
        plotter.screenshot(return_img=True)
        plotter.close()
    except Exception as error:  # noqa: BLE001 - any failure means: cannot render here
        return f"pyvista cannot render off screen here: {type(error).__name__}: {error}"
    return None


@pytest.fixture(scope="module")
def warm(inputs, view_unavailable, tmp_path_factory) -> None:
    """Every command once, so that the timed calls pay for no first import."""
    root = tmp_path_factory.mktemp("warm")
    for name, cmd in COMMANDS.items():
        if name == "view" and view_unavailable:
            continue
        try:
            main(_argv(cmd.argv, inputs, out=root / f"{name}-{cmd.target}", report=root / f"{name}-report.json"))
        except Exception:  # noqa: BLE001 - a failure shows up in the tests themselves
            pass


def _need(command: str, view_unavailable) -> None:
    if command == "view" and view_unavailable:
        pytest.skip(view_unavailable)


# --- 1. operating-system failures ------------------------------------------------------------------


@pytest.mark.parametrize("condition", ["read-only", "full", "missing parent"])
@pytest.mark.parametrize("command", list(COMMANDS))
def test_os_failure_is_one_line_exit_2_and_leaves_nothing(command, condition, inputs, warm, view_unavailable, tmp_path,
                                                          request,
                                                          monkeypatch, capsys):
    _need(command, view_unavailable)
    cmd = COMMANDS[command]
    place = _place(condition, tmp_path, request, monkeypatch, free=FOLDER_FREE_BYTES if cmd.folder else 0)
    argv = _argv(cmd.argv, inputs, out=place.parent / cmd.target, report=place.parent / "report.json")
    capsys.readouterr()
    status, seconds = _run(argv)
    monkeypatch.undo()  # the ENOSPC patches off before looking
    line = _one_error_line(capsys, argv[0], status)
    place.check_nothing_left()
    if condition != "full":
        assert seconds < CHECK_SECONDS, (f"{condition} found after {seconds:.2f} s ({place.how}): check it before "
                                         f"the work; {line}")


@pytest.mark.parametrize("command", list(COMMANDS))
def test_an_existing_output_without_overwrite_is_refused_before_the_work(command, inputs, warm, view_unavailable,
                                                                         tmp_path, capsys):
    _need(command, view_unavailable)
    cmd = COMMANDS[command]
    target = tmp_path / cmd.target
    if cmd.folder:
        target.mkdir()
        (target / "notes.txt").write_text("my notes\n")
    else:
        target.write_bytes(b"precious")
    before = _tree(tmp_path)
    capsys.readouterr()
    status, seconds = _run(_argv(cmd.argv, inputs, out=target, report=tmp_path / "report.json"))
    line = _one_error_line(capsys, command.split("-")[0], status)
    if not cmd.folder:  # a folder holding the user's notes is refused whatever the options: no advice to check
        assert "--overwrite" in line
    assert _tree(tmp_path) == before
    assert seconds < CHECK_SECONDS, f"refused after {seconds:.2f} s: check before the work"


@pytest.mark.parametrize("condition", ["read-only", "missing parent"])
def test_an_unwritable_report_is_refused_before_the_fit(condition, inputs, warm, tmp_path, request, monkeypatch,
                                                        capsys):
    place = _place(condition, tmp_path, request, monkeypatch, free=0)
    fields = tmp_path / "fields"
    fields.mkdir()
    place.expected[tmp_path] = sorted([*(place.expected[tmp_path] or []), "fields"])
    argv = _argv(COMMANDS["fit"].argv, inputs, out=fields / "field.whf", report=place.parent / "report.json")
    capsys.readouterr()
    status, seconds = _run(argv)
    line = _one_error_line(capsys, "fit", status)
    assert "report.json" in line
    assert _listing(fields) == []
    place.check_nothing_left()
    assert seconds < CHECK_SECONDS, f"refused after {seconds:.2f} s: check --report before the work"


# --- 2. which folders --overwrite replaces ---------------------------------------------------------


def _folder_params(slow: bool):
    return [pytest.param(name, marks=pytest.mark.slow) if slow and name in SLOW_FOLDERS else name
            for name in FOLDER_VARIANTS]


@pytest.mark.parametrize("command", _folder_params(slow=False))
def test_a_folder_holding_a_users_file_is_never_replaced(command, inputs, warm, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_bytes(b"my notes\n")
    _, second = FOLDER_VARIANTS[command]
    for extra in ([], ["--overwrite"]):
        capsys.readouterr()
        status, _ = _run(_argv(second, inputs, out=out) + extra)
        line = _one_error_line(capsys, command.split("-")[0], status)
        assert _tree(out) == {"notes.txt": hashlib.sha256(b"my notes\n").hexdigest()}, line
        assert _listing(tmp_path) == ["out"]


@pytest.mark.parametrize("command", _folder_params(slow=True))
def test_a_folder_this_project_wrote_is_replaced_whole(command, inputs, warm, tmp_path, capsys):
    first, second = FOLDER_VARIANTS[command]
    reference = tmp_path / "reference" / "out"
    reference.parent.mkdir()
    assert _run(_argv(second, inputs, out=reference))[0] == 0
    expected = _tree(reference)
    work = tmp_path / "work"
    work.mkdir()
    out = work / "out"
    assert _run(_argv(first, inputs, out=out))[0] == 0
    old = _tree(out)
    gone = set(old) - set(expected)
    assert gone, "the test's two outputs should differ in their files"

    capsys.readouterr()
    status, _ = _run(_argv(second, inputs, out=out))  # without --overwrite: refused
    line = _one_error_line(capsys, command.split("-")[0], status)
    assert "--overwrite" in line
    assert _tree(out) == old

    status, _ = _run(_argv(second, inputs, out=out) + ["--overwrite"])
    assert status == 0, capsys.readouterr().err[-2000:]
    new = _tree(out)
    assert sorted(new) == sorted(expected), "the replaced folder should hold exactly the new output"
    different = [name for name, digest in new.items()
                 if not name.endswith(VOLATILE_SUFFIXES) and digest != expected[name]]
    assert not different, f"not the new output: {different[:5]}"
    assert _listing(work) == ["out"], "left beside the output"
    assert not _temporaries(work)


@pytest.mark.parametrize("extra", ["notes.txt", "lookalike"])
@pytest.mark.parametrize("command", _folder_params(slow=True))
def test_a_project_folder_with_a_file_the_user_added_is_not_replaced(command, extra, inputs, warm, tmp_path, capsys):
    first, second = FOLDER_VARIANTS[command]
    out = tmp_path / "out"
    assert _run(_argv(first, inputs, out=out))[0] == 0
    if extra == "notes.txt":
        (out / "notes.txt").write_text("my notes\n")
    else:  # a copy of one of its images under a name like the project's own: only the record tells them apart
        image = next(p for p in sorted(out.rglob("*")) if p.suffix in (".exr", ".png") and not p.name.startswith("."))
        shutil.copyfile(image, image.with_name(f"{image.stem}-copy{image.suffix}"))
    before = _tree(out)
    capsys.readouterr()
    status, _ = _run(_argv(second, inputs, out=out) + ["--overwrite"])
    _one_error_line(capsys, command.split("-")[0], status)
    assert _tree(out) == before
    assert _listing(tmp_path) == ["out"]
