"""The shared atomic outputs (``io.atomic``): files and folders appear whole, folders are replaced only when this
project wrote them, stale temporaries of dead processes are cleaned, signals wait for cleanup."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
import weakref

import pytest

from warp_highlights.io import atomic
from warp_highlights.io.atomic import (
    MANIFEST_NAME,
    FolderTransaction,
    Terminated,
    atomic_file,
    atomic_folder,
    check_folder_target,
    clean_stale_partials,
    deferred_signals,
    describe_os_error,
    end_of_command,
    handle_termination,
    remove_partials,
)
from warp_highlights.model.errors import InputError


def _tree(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _write(folder, files: dict[str, str]) -> None:
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


# --- files -----------------------------------------------------------------------------------------


def test_atomic_file_replaces_only_when_complete(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_file(path) as temporary:
            temporary.write_text("half")
            raise RuntimeError("crash")
    assert path.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["a.txt"]
    with atomic_file(path, durable=True) as temporary:
        assert temporary.parent == tmp_path and temporary.name.startswith(".a.txt.partial-")
        temporary.write_text("new")
    assert path.read_text() == "new" and sorted(os.listdir(tmp_path)) == ["a.txt"]


def test_atomic_file_refuses_before_writing(tmp_path):
    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(InputError, match="--overwrite"):
        with atomic_file(tmp_path / "a.txt", overwrite=False):
            pytest.fail("the block must not run")
    with pytest.raises(InputError, match="does not exist"):
        with atomic_file(tmp_path / "missing" / "a.txt"):
            pytest.fail("the block must not run")
    with pytest.raises(InputError, match="is a folder"):
        with atomic_file(tmp_path):
            pytest.fail("the block must not run")


def test_an_os_error_without_a_file_name_names_the_output(tmp_path):
    with pytest.raises(OSError) as excinfo:
        with atomic_file(tmp_path / "x.gif"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert excinfo.value.filename == str(tmp_path / "x.gif")
    assert os.listdir(tmp_path) == []


# --- folders ---------------------------------------------------------------------------------------


def test_folder_gets_a_manifest_of_its_files(tmp_path):
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"a.txt": "a", "sub/b.txt": "b"})
    manifest = json.loads((tmp_path / "out" / MANIFEST_NAME).read_text())
    assert manifest["written_by"] == "warp-highlights" and manifest["kind"] == "test"
    assert sorted(manifest["files"]) == ["a.txt", "sub/b.txt"]
    assert manifest["files"]["sub/b.txt"]["bytes"] == 1
    assert sorted(os.listdir(tmp_path)) == ["out"]


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_overwrite_swaps_a_folder_this_project_wrote(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"old.txt": "old", "sub/old.txt": "old"})
    with atomic_folder(tmp_path / "out", kind="test", overwrite=True) as temporary:
        _write(temporary, {"new.txt": "new"})
    assert set(_tree(tmp_path / "out")) == {"new.txt", MANIFEST_NAME}
    assert sorted(os.listdir(tmp_path)) == ["out"]


def test_a_failure_leaves_the_old_folder(tmp_path):
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"old.txt": "old"})
    before = _tree(tmp_path / "out")
    with pytest.raises(KeyboardInterrupt):
        with atomic_folder(tmp_path / "out", kind="test", overwrite=True) as temporary:
            _write(temporary, {"new.txt": "new"})
            raise KeyboardInterrupt
    assert _tree(tmp_path / "out") == before and sorted(os.listdir(tmp_path)) == ["out"]


def test_a_failed_swap_puts_the_old_folder_back(tmp_path, monkeypatch):
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"old.txt": "old"})
    before = _tree(tmp_path / "out")
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    real_rename = os.rename

    def rename(source, target):
        if str(target) == str(tmp_path / "out") and ".partial-" in str(source):  # the new folder cannot move in
            raise OSError(errno.EIO, "Input/output error", str(target))
        return real_rename(source, target)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError, match="Input/output"):
        with atomic_folder(tmp_path / "out", kind="test", overwrite=True) as temporary:
            _write(temporary, {"new.txt": "new"})
    monkeypatch.undo()
    assert _tree(tmp_path / "out") == before and sorted(os.listdir(tmp_path)) == ["out"]


@pytest.mark.parametrize(
    ("added", "foreign"),
    [({"notes.txt": "mine"}, "notes.txt"), ({"sub/photo.jpg": "mine"}, "sub/photo.jpg")],
)
def test_a_file_the_project_did_not_write_is_never_deleted(tmp_path, added, foreign):
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"a.txt": "a", "sub/b.txt": "b"})
    _write(tmp_path / "out", added)
    before = _tree(tmp_path / "out")
    with pytest.raises(InputError, match=f"holds {foreign}, which warp-highlights did not write"):
        with atomic_folder(tmp_path / "out", kind="test", overwrite=True):
            pytest.fail("the block must not run")
    assert _tree(tmp_path / "out") == before and sorted(os.listdir(tmp_path)) == ["out"]


def test_a_file_changed_since_it_was_written_is_never_deleted(tmp_path):
    with atomic_folder(tmp_path / "out", kind="test", overwrite=False) as temporary:
        _write(temporary, {"index.md": "generated", "b.txt": "b"})
    (tmp_path / "out" / "index.md").write_text("generated, with the user's notes")
    with pytest.raises(InputError, match="holds index.md, which was changed after warp-highlights wrote it"):
        check_folder_target(tmp_path / "out", overwrite=True)


def test_the_current_folder_as_an_output_is_checked_like_any_other(tmp_path, monkeypatch):
    (tmp_path / "work").mkdir()
    (tmp_path / "work" / "notes.txt").write_text("mine")
    monkeypatch.chdir(tmp_path / "work")
    with pytest.raises(InputError, match="notes.txt"):
        check_folder_target(".", overwrite=True)
    with pytest.raises(InputError, match="root folder"):
        check_folder_target("/", overwrite=True)


def test_folders_without_a_manifest(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    check_folder_target(out, overwrite=False)  # empty: fine without --overwrite
    _write(out, {"frame_0.png": "x"})
    with pytest.raises(InputError, match="--overwrite"):
        check_folder_target(out, overwrite=False)
    with pytest.raises(InputError, match="frame_0.png"):  # nobody vouches for it
        check_folder_target(out, overwrite=True)
    check_folder_target(out, overwrite=True, legacy=lambda name: name.startswith("frame_"))  # an old output
    _write(out, {"sub/frame_1.png": "in a sub-folder"})  # every file counts, not only the top level
    with pytest.raises(InputError, match="sub/frame_1.png"):
        check_folder_target(out, overwrite=True, legacy=lambda name: name.startswith("frame_"))
    (out / "sub" / "frame_1.png").unlink()
    (out / "sub").rmdir()
    _write(out, {"notes.txt": "mine"})
    with pytest.raises(InputError, match="notes.txt"):
        check_folder_target(out, overwrite=True, legacy=lambda name: name.startswith("frame_"))
    (out / MANIFEST_NAME).write_text("{not json")  # a damaged manifest vouches for nothing
    (out / "notes.txt").unlink()
    check_folder_target(out, overwrite=True, legacy=lambda name: name.startswith("frame_"))


def test_transaction_abort_and_commit_once(tmp_path):
    transaction = FolderTransaction(tmp_path / "out", kind="test", overwrite=False)
    (transaction.temporary / "a.txt").write_text("a")
    transaction.abort()
    transaction.abort()
    assert os.listdir(tmp_path) == []
    with pytest.raises(RuntimeError, match="aborted"):
        transaction.commit()


# --- stale temporaries -----------------------------------------------------------------------------


def test_stale_partials_of_dead_processes_are_cleaned(tmp_path):
    host = atomic._stable_host_tag()
    dead, alive = _dead_pid(), os.getppid()
    stale = tmp_path / f".out.partial-{host}-{dead}-0123abcd"
    live = tmp_path / f".out.partial-{host}-{alive}-0123abcd"
    foreign = tmp_path / f".out.partial-{'0' * 6 if host != '000000' else '111111'}-{dead}-0123abcd"
    other = tmp_path / f".other.partial-{host}-{dead}-0123abcd"
    for folder in (stale, live, foreign, other):
        folder.mkdir()
        (folder / "x").write_text("x")
    assert clean_stale_partials(tmp_path / "out") == [stale]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in (live, foreign, other))


def test_a_stale_replaced_folder_is_put_back_when_its_target_is_missing(tmp_path):
    host = atomic._stable_host_tag()
    aside = tmp_path / f".out.replaced-{host}-{_dead_pid()}-0123abcd"  # killed between the two renames
    aside.mkdir()
    (aside / "old.txt").write_text("old")
    clean_stale_partials(tmp_path / "out")
    assert (tmp_path / "out" / "old.txt").read_text() == "old" and sorted(os.listdir(tmp_path)) == ["out"]


def test_remove_partials_removes_what_this_process_left(tmp_path):
    transaction = FolderTransaction(tmp_path / "out", kind="test", overwrite=False)
    (transaction.temporary / "a.txt").write_text("a")
    assert transaction.temporary in remove_partials()
    assert os.listdir(tmp_path) == []


# --- signals and messages --------------------------------------------------------------------------


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_signals_wait_for_the_end_of_a_deferred_block():
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    handle_termination()
    try:
        finished = []
        with pytest.raises(Terminated):
            with deferred_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                finished.append("cleanup")
        assert finished == ["cleanup"]
        with pytest.raises(KeyboardInterrupt) as excinfo:
            os.kill(os.getpid(), signal.SIGINT)
        assert not isinstance(excinfo.value, Terminated)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_a_signal_after_the_end_of_a_command_whose_output_is_in_place_is_held(tmp_path):
    """The finished command is returning: an interruption now would report outputs that are whole as cut."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    handle_termination(hold_after_output=True)
    try:
        with atomic_file(tmp_path / "out.txt", overwrite=False) as temporary:
            temporary.write_text("whole")
        assert end_of_command() is None
        os.kill(os.getpid(), signal.SIGINT)  # held: no KeyboardInterrupt
        time.sleep(0.05)
        handle_termination()  # a new command: signals interrupt again
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
    finally:
        end_of_command()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    assert (tmp_path / "out.txt").read_text() == "whole"


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_an_interrupt_raised_inside_a_library_s_weakref_callback_is_delivered_again_without_a_traceback(capfd):
    """A signal that lands in a weakref callback defined as a lambda (matplotlib's transforms have
    them, and frames cannot tell it for a callback): the interpreter would print the interruption and
    drop it. It is delivered again a moment later and stops the work, and nothing is printed."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    hook = sys.unraisablehook
    handle_termination()
    try:
        class Thing:
            pass

        thing = Thing()
        # the handler runs inside the callback
        reference = weakref.ref(thing, lambda _: signal.raise_signal(signal.SIGINT))
        started = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            del thing
            while time.monotonic() - started < 5.0:
                time.sleep(0.005)
        assert reference() is None and time.monotonic() - started < 1.0
    finally:
        end_of_command()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        sys.unraisablehook = hook
    assert "Traceback" not in capfd.readouterr().err


@pytest.mark.parametrize(
    ("code", "advice"),
    [(errno.EACCES, "check its permissions"), (errno.EROFS, "writable disk"), (errno.ENOSPC, "free some space"),
     (errno.ENAMETOOLONG, "shorter name"), (errno.ENOTDIR, "not a folder")],
)
def test_os_errors_read_as_one_line_naming_the_output(tmp_path, code, advice):
    partial = tmp_path / f".out.partial-{atomic._stable_host_tag()}-{os.getpid()}-0123abcd" / "images" / "0001.exr"
    message = describe_os_error(OSError(code, os.strerror(code), str(partial)))
    assert "\n" not in message and advice in message and os.strerror(code) in message
    assert str(tmp_path / "out" / "images" / "0001.exr") in message and ".partial-" not in message


def test_probe_finds_an_unwritable_folder_before_any_work(tmp_path, monkeypatch):
    def refuse(path, flags, mode=0o777):
        raise OSError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(atomic.os, "open", refuse)
    with pytest.raises(InputError, match="cannot write .*out: Permission denied; check its permissions"):
        check_folder_target(tmp_path / "out", overwrite=False)


def test_names_too_long_for_a_temporary_suffix_still_work(tmp_path):
    name = "n" * 240 + ".png"  # legal (244 bytes), but not with ".partial-<host>-<pid>-<tag>" added
    with atomic_file(tmp_path / name) as temporary:
        assert len(temporary.name.encode()) <= 255
        temporary.write_text("x")
    with atomic_folder(tmp_path / name[:-4], kind="test", overwrite=False) as temporary:
        (temporary / "a.txt").write_text("a")
    with atomic_folder(tmp_path / name[:-4], kind="test", overwrite=True) as temporary:
        (temporary / "b.txt").write_text("b")
    assert sorted(os.listdir(tmp_path)) == sorted([name, name[:-4]])
    stale = atomic._temporary_path(tmp_path / name)  # as a killed process would leave it
    stale.mkdir()
    atomic._forget(stale)
    renamed = stale.with_name(stale.name.replace(f"-{os.getpid()}-", f"-{_dead_pid()}-"))
    stale.rename(renamed)
    assert clean_stale_partials(tmp_path / name) == [renamed]
