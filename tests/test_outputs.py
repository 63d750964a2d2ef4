"""Outputs never replace the wrong thing: devices, FIFOs, sockets and folders of another kind are refused
with ``--overwrite`` or not, no command writes over one of its own inputs, and of two writers racing for
one new name exactly one succeeds."""

from __future__ import annotations

import hashlib
import os
import socket
import stat
import tempfile
import threading
from pathlib import Path

import pytest

from warp_highlights.cli import main
from warp_highlights.cli.args import check_output_file, check_output_folder
from warp_highlights.io.atomic import (
    MANIFEST_NAME,
    FolderTransaction,
    atomic_file,
    atomic_folder,
    check_file_target,
    end_of_command,
)
from warp_highlights.model.errors import InputError

RACE_REPETITIONS = 20


def _digest(path: Path) -> dict[str, str]:
    """Every file under ``path`` (or ``path`` itself) by SHA-256, hidden ones included."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path) if p != path else p.name): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in files}


def _one_line_error(capsys, status, command: str) -> str:
    err = capsys.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"warp-highlights {command}: error:"), lines[0]
    return lines[0]


@pytest.fixture(autouse=True)
def _forget_claims():
    yield
    end_of_command()  # what a command does as it ends: forgets the outputs claimed for exclusive creation


def _dataset_like(folder: Path, kind: str = "dataset") -> None:
    folder.mkdir()
    (folder / "image.png").write_bytes(b"not replaced")
    size, mtime = (folder / "image.png").stat().st_size, (folder / "image.png").stat().st_mtime_ns
    manifest = {"written_by": "warp-highlights", "version": "0", "kind": kind,
                "files": {"image.png": {"bytes": size, "mtime_ns": mtime}}}
    import json

    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))


# --- the atomic writer -----------------------------------------------------------------------------


def test_dev_null_is_refused_by_the_check(tmp_path):
    with pytest.raises(InputError, match=r"/dev/null is a device; it is never replaced"):
        check_file_target("/dev/null", overwrite=True)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("overwrite", [False, True])
def test_fifo_is_never_replaced(tmp_path, overwrite):
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="is a FIFO; it is never replaced"):
        with atomic_file(fifo, overwrite=overwrite) as temporary:
            temporary.write_bytes(b"x")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert os.listdir(tmp_path) == ["pipe.png"]


def test_socket_is_never_replaced():
    with tempfile.TemporaryDirectory(dir="/tmp") as folder:  # a short path: socket names are limited
        path = Path(folder, "s.whf")
        server = socket.socket(socket.AF_UNIX)
        try:
            server.bind(str(path))
            with pytest.raises(InputError, match="is a socket"):
                check_file_target(path, overwrite=True)
        finally:
            server.close()
        assert stat.S_ISSOCK(os.lstat(path).st_mode)


def test_a_fifo_that_appears_during_the_write_is_not_replaced(tmp_path):
    target = tmp_path / "out.png"
    with pytest.raises(InputError, match="is a FIFO"):
        with atomic_file(target, overwrite=True) as temporary:
            temporary.write_bytes(b"new")
            os.mkfifo(target)
    assert stat.S_ISFIFO(os.lstat(target).st_mode)
    assert os.listdir(tmp_path) == ["out.png"]


@pytest.mark.parametrize("overwrite", [False, True])
def test_folder_of_another_kind_is_never_replaced(tmp_path, overwrite):
    target = tmp_path / "capture"
    _dataset_like(target)
    before = _digest(target)
    with pytest.raises(InputError, match="holds a warp-highlights dataset, not relit images"):
        with atomic_folder(target, kind="relit images", overwrite=overwrite) as temporary:
            (temporary / "0001.exr").write_bytes(b"x")
    assert _digest(target) == before
    assert sorted(os.listdir(tmp_path)) == ["capture"]


def test_folder_of_the_same_kind_is_replaced_with_overwrite(tmp_path):
    target = tmp_path / "relit"
    _dataset_like(target, kind="relit images")
    with atomic_folder(target, kind="relit images", overwrite=True) as temporary:
        (temporary / "0001.exr").write_bytes(b"x")
    assert sorted(os.listdir(target)) == [MANIFEST_NAME, "0001.exr"]


def test_a_folder_of_another_kind_that_appears_before_the_swap_stays(tmp_path):
    target = tmp_path / "out"
    transaction = FolderTransaction(target, kind="surface maps", overwrite=True)
    (transaction.temporary / "normals.png").write_bytes(b"x")
    _dataset_like(target)
    before = _digest(target)
    with pytest.raises(InputError, match="holds a warp-highlights dataset"):
        transaction.commit()
    assert _digest(target) == before
    assert sorted(os.listdir(tmp_path)) == ["out"]


def test_claimed_output_is_created_exclusively_by_later_writers(tmp_path):
    target = tmp_path / "field.whf"
    check_output_file(target, overwrite=False)
    target.write_bytes(b"someone else's")
    with pytest.raises(InputError, match="appeared while it was being written"):
        with atomic_file(target, checked=False) as temporary:  # as save_field writes: overwrite by default
            temporary.write_bytes(b"ours")
    assert target.read_bytes() == b"someone else's"
    assert os.listdir(tmp_path) == ["field.whf"]


def _race(target: Path, write, *, overwrite: bool) -> tuple[list[str], list[str]]:
    """Two threads write ``target`` at once, both past the early check; returns (payloads that
    succeeded, error messages)."""
    ready = threading.Barrier(2)
    done, errors = [], []

    def writer(payload: str) -> None:
        try:
            write(target, payload, ready, overwrite)
            done.append(payload)
        except InputError as error:
            errors.append(str(error))

    threads = [threading.Thread(target=writer, args=(name,)) for name in ("first", "second")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    return done, errors


def _write_file(target, payload, ready, overwrite):
    with atomic_file(target, overwrite=overwrite) as temporary:
        temporary.write_text(payload * 1000)
        ready.wait(10)


def _write_folder(target, payload, ready, overwrite):
    with atomic_folder(target, kind="relit images", overwrite=overwrite) as temporary:
        (temporary / f"{payload}.exr").write_text(payload)
        ready.wait(10)


@pytest.mark.parametrize("write", [_write_file, _write_folder], ids=["file", "folder"])
def test_two_writers_without_overwrite_exactly_one_wins(tmp_path, write):
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"out{repetition}"
        done, errors = _race(target, write, overwrite=False)
        assert len(done) == 1 and len(errors) == 1, (done, errors)
        assert "\n" not in errors[0] and "--overwrite" in errors[0]
        assert "appeared while it was being written" in errors[0] or "exists; pass --overwrite" in errors[0]
        if target.is_file():
            assert target.read_text() == done[0] * 1000
        else:
            assert sorted(os.listdir(target)) == [MANIFEST_NAME, f"{done[0]}.exr"]
    assert sorted(os.listdir(tmp_path)) == sorted(f"out{i}" for i in range(RACE_REPETITIONS))  # no temporaries


def test_two_writers_onto_an_empty_folder_exactly_one_wins(tmp_path):
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"out{repetition}"
        target.mkdir()  # made by the user beforehand: new, as far as the rules go
        done, errors = _race(target, _write_folder, overwrite=False)
        assert len(done) == 1 and len(errors) == 1, (done, errors)
        assert sorted(os.listdir(target)) == [MANIFEST_NAME, f"{done[0]}.exr"]
    assert sorted(os.listdir(tmp_path)) == sorted(f"out{i}" for i in range(RACE_REPETITIONS))


def _without_renameat2_or_links(monkeypatch) -> None:
    """The system of a file system without hard links, on a kernel without renameat2."""
    import errno

    from warp_highlights.io import atomic

    def no_link(*args, **kwargs):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(atomic, "_renameat2", lambda *args: False)
    monkeypatch.setattr(atomic.os, "link", no_link)


@pytest.mark.parametrize("write", [_write_file, _write_folder], ids=["file", "folder"])
def test_without_renameat2_a_lock_file_keeps_two_writers_apart(tmp_path, monkeypatch, write):
    _without_renameat2_or_links(monkeypatch)
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"out{repetition}"
        done, errors = _race(target, write, overwrite=False)
        assert len(done) == 1 and len(errors) == 1, (done, errors)
        assert "\n" not in errors[0] and "--overwrite" in errors[0]
        if target.is_file():
            assert target.read_text() == done[0] * 1000
        else:
            assert sorted(os.listdir(target)) == [MANIFEST_NAME, f"{done[0]}.exr"]
    assert sorted(os.listdir(tmp_path)) == sorted(f"out{i}" for i in range(RACE_REPETITIONS))  # no lock left


def test_a_lock_of_a_process_that_ended_is_taken_over_and_a_live_one_is_not(tmp_path, monkeypatch):
    import subprocess
    import sys

    from warp_highlights.io.atomic import _stable_host_tag

    _without_renameat2_or_links(monkeypatch)
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock = tmp_path / ".a.png.lock"
    lock.write_text(f"{_stable_host_tag()} {ended.stdout.strip()}\n")
    with atomic_file(tmp_path / "a.png", overwrite=False) as temporary:
        temporary.write_bytes(b"new")
    assert (tmp_path / "a.png").read_bytes() == b"new" and not lock.exists()

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        (tmp_path / ".b.png.lock").write_text(f"{_stable_host_tag()} {live.pid}\n")
        with pytest.raises(InputError, match="appeared while it was being written"):
            with atomic_file(tmp_path / "b.png", overwrite=False) as temporary:
                temporary.write_bytes(b"new")
    finally:
        live.kill()
        live.wait()
    assert not (tmp_path / "b.png").exists()
    assert sorted(os.listdir(tmp_path)) == [".b.png.lock", "a.png"]  # the live writer's lock stays


def test_two_writers_with_overwrite_the_later_wins_whole(tmp_path):
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"out{repetition}"
        done, errors = _race(target, _write_file, overwrite=True)
        assert sorted(done) == ["first", "second"] and not errors
        assert target.read_text() in ("first" * 1000, "second" * 1000)
    assert len(os.listdir(tmp_path)) == RACE_REPETITIONS


# --- a command's own inputs ------------------------------------------------------------------------


def test_output_that_is_an_input_or_inside_one_is_refused(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "lights.lp").write_text("1\nimage.png 0 0 1\n")
    link = tmp_path / "link"
    link.symlink_to(data)
    field = tmp_path / "f.whf"
    field.write_bytes(b"field")
    alias = tmp_path / "alias.whf"
    os.link(field, alias)
    with pytest.raises(InputError, match="is the command's input"):
        check_output_file(alias, overwrite=True, inputs=[field])
    with pytest.raises(InputError, match="lies inside the input folder"):
        check_output_file(link / "new.png", overwrite=False, inputs=[data])
    with pytest.raises(InputError, match="lies inside the input folder"):
        check_output_file(data / "lights.lp", overwrite=True, inputs=[data])
    with pytest.raises(InputError, match="holds the command's input"):
        check_output_folder(data, overwrite=True, inputs=[data / "lights.lp"])
    check_output_file(tmp_path / "other.whf", overwrite=False, inputs=[data, field, None])


def test_a_capture_image_is_never_replaced_one_by_one(tmp_path):
    photos = tmp_path / "coin"
    (photos / "jpg").mkdir(parents=True)
    for name in ("a.jpg", "b.jpg", "notes.txt"):
        (photos / "jpg" / name).write_bytes(b"photo " + name.encode())
    (photos / "dirs.lp").write_text("2\njpg/a.jpg 0 0 1\njpg\\b.jpg 0 1 1\n")  # a backslash, as Windows tools write
    (photos / "broken.lp").write_text("not a light file")
    (tmp_path / "shelf").symlink_to(photos)
    for output in (photos / "jpg" / "a.jpg", photos / "jpg" / "b.jpg", tmp_path / "shelf" / "jpg" / "a.jpg"):
        with pytest.raises(InputError, match="is an image of the capture .*dirs.lp; .* never replaced"):
            check_output_file(output, overwrite=True)
    check_output_file(photos / "jpg" / "notes.txt", overwrite=True)  # not an image of the capture
    check_output_file(photos / "jpg" / "new.png", overwrite=True)  # a new file beside them
    assert (photos / "jpg" / "a.jpg").read_bytes() == b"photo a.jpg"


def test_a_file_of_an_output_folder_is_replaced_only_with_its_folder(tmp_path):
    folder = tmp_path / "renders"
    _dataset_like(folder)
    with pytest.raises(InputError, match="is a file of the dataset folder .*renders"):
        check_output_file(folder / "image.png", overwrite=True)
    check_output_file(folder / "other.png", overwrite=True)


@pytest.fixture(scope="module")
def capture(tiny_sphere):
    data, field = tiny_sphere
    return data, field, sorted(data.glob("*.lp"))[0]


def test_export_over_its_field_is_refused(capture, capsys, tmp_path):
    _, field, _ = capture
    before = _digest(field)
    status = main(["export", str(field), "--single-file", "-o", str(field), "--overwrite"])
    assert "give a name ending in .html" in _one_line_error(capsys, status, "export")
    alias = tmp_path / "page.html"  # the field under a page's name: a hard link
    os.link(field, alias)
    status = main(["export", str(field), "--single-file", "-o", str(alias), "--overwrite"])
    assert "is the command's input" in _one_line_error(capsys, status, "export")
    assert _digest(field) == before and _digest(alias)[alias.name] == before[field.name]


@pytest.mark.parametrize("option", ["-o", "--report"])
def test_fit_into_its_dataset_is_refused(capture, capsys, tmp_path, option):
    data, _, lights = capture
    before = _digest(data)
    outputs = {"-o": str(tmp_path / "f.whf"), "--report": str(tmp_path / "r.json")}
    outputs[option] = str(lights)
    status = main(["fit", str(data), "-o", outputs["-o"], "--report", outputs["--report"], "--overwrite", "--device",
                   "cpu"])
    assert "lies inside the input folder" in _one_line_error(capsys, status, "fit")
    assert _digest(data) == before


def test_fit_through_a_linked_folder_is_refused(capture, capsys, tmp_path):
    data, _, lights = capture
    link = tmp_path / "link"
    link.symlink_to(data)
    before = _digest(data)
    status = main(["fit", str(data), "-o", str(link / lights.name), "--overwrite", "--device", "cpu"])
    assert "lies inside the input folder" in _one_line_error(capsys, status, "fit")
    assert _digest(data) == before


def test_relight_into_the_dataset_is_refused(capture, capsys):
    data, field, lights = capture
    before = _digest(data)
    image = sorted(data.glob("*.exr"))[0] if list(data.glob("*.exr")) else sorted(data.rglob("*.exr"))[0]
    status = main(["relight", str(field), "--light", "0.3,0.5,1", "--dataset", str(data), "-o", str(image),
                   "--overwrite", "--device", "cpu"])
    assert "lies inside the input folder" in _one_line_error(capsys, status, "relight")
    status = main(["relight", str(field), "--lights", str(lights), "-o", str(data), "--overwrite", "--device", "cpu"])
    assert "holds the command's input" in _one_line_error(capsys, status, "relight")
    assert _digest(data) == before


@pytest.mark.parametrize("command", ["maps", "evaluate"])
def test_dataset_folder_is_not_replaced_by_another_kind(capture, capsys, command, tmp_path):
    data, field, _ = capture
    copy = tmp_path / "copy"
    import shutil

    shutil.copytree(data, copy, copy_function=shutil.copy2)  # keeps sizes and times: the manifest still matches
    before = _digest(copy)
    argv = {"maps": ["maps", str(field)], "evaluate": ["evaluate", str(field), str(data)]}[command]
    status = main([*argv, "-o", str(copy), "--overwrite", "--device", "cpu"])
    assert "holds a warp-highlights dataset" in _one_line_error(capsys, status, command)
    assert _digest(copy) == before


def test_relight_over_a_fifo_is_refused(capture, capsys, tmp_path):
    _, field, _ = capture
    fifo = tmp_path / "out.png"
    os.mkfifo(fifo)
    status = main(["relight", str(field), "--light", "0.3,0.5,1", "-o", str(fifo), "--overwrite", "--device", "cpu"])
    assert "is a FIFO" in _one_line_error(capsys, status, "relight")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_a_claim_is_used_once(tmp_path):
    target = tmp_path / "sheet.png"
    with atomic_file(target, overwrite=False) as temporary:
        temporary.write_bytes(b"first")
    with atomic_file(target, checked=False) as temporary:  # a later write that asks to replace
        temporary.write_bytes(b"second")
    assert target.read_bytes() == b"second"


# --- two commands at once --------------------------------------------------------------------------


def _together(commands: list[list[str]]) -> list[tuple[int, str, str]]:
    """Start ``python -m warp_highlights`` for each argument list at once; (status, stdout, stderr) of each."""
    import subprocess
    import sys

    processes = [subprocess.Popen([sys.executable, "-m", "warp_highlights", *map(str, arguments)],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for arguments in commands]
    results = []
    for process in processes:
        out, err = process.communicate(timeout=300)
        results.append((process.returncode, out, err))
    return results


def _one_wrote(results, command: str, target: Path) -> None:
    wrote = [r for r in results if r[0] == 0]
    refused = [r for r in results if r[0] != 0]
    assert len(wrote) == 1 and len(refused) == 1, results
    assert f"wrote {target}" in wrote[0][1]
    status, _, err = refused[0]
    assert status == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"warp-highlights {command}: error: output {target}"), err


@pytest.mark.slow
def test_two_relights_to_one_new_name_exactly_one_writes(tiny_sphere, tmp_path):
    _, field = tiny_sphere
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"relit{repetition}.png"
        results = _together([["relight", field, "--light", light, "-o", target, "-q"]
                             for light in ("0.3,0.5,1", "-0.3,0.5,1")])
        _one_wrote(results, "relight", target)
    assert sorted(os.listdir(tmp_path)) == sorted(f"relit{i}.png" for i in range(RACE_REPETITIONS))


@pytest.mark.slow
def test_two_fits_to_one_new_name_exactly_one_writes(tiny_sphere, tmp_path):
    from conftest import TINY_FIT
    from warp_highlights.io.fieldfile import load_field

    data, _ = tiny_sphere
    for repetition in range(RACE_REPETITIONS):
        target = tmp_path / f"field{repetition}.whf"
        results = _together([["fit", data, "-o", target, "--device", "cpu", "-q", *TINY_FIT]] * 2)
        _one_wrote(results, "fit", target)
        assert len(load_field(target).lights.directions) == 16
    assert sorted(os.listdir(tmp_path)) == sorted(f"field{i}.whf" for i in range(RACE_REPETITIONS))


def test_two_relights_with_overwrite_leave_one_whole_image(tiny_sphere, tmp_path):
    from warp_highlights.io.images import read_image

    _, field = tiny_sphere
    target = tmp_path / "relit.png"
    for _ in range(5):
        results = _together([["relight", field, "--light", light, "-o", target, "--overwrite", "-q"]
                             for light in ("0.3,0.5,1", "-0.3,0.5,1")])
        assert [r[0] for r in results] == [0, 0], results
        assert read_image(target).shape == (18, 32, 3)
    assert os.listdir(tmp_path) == ["relit.png"]
