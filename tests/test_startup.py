"""Start-up and operating-system failures told in one true line: Warp's kernel cache where it cannot be written,
file size limits and quotas, standard output that cannot take the summary, special files given as images, and
link loops in a collection."""

from __future__ import annotations

import errno
import logging
import os
import resource
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import TINY_FIT
from warp_highlights.cli import main
from warp_highlights.io.atomic import describe_os_error
from warp_highlights.io.images import write_image


def _command(arguments, *, env=None, stdout=subprocess.PIPE, limit=None, timeout=300):
    """``python -m warp_highlights ARGUMENTS`` in a child process (with ``RLIMIT_FSIZE`` = ``limit`` bytes)."""
    def limited():
        if limit is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))

    return subprocess.run([sys.executable, "-m", "warp_highlights", *arguments], stdout=stdout, stderr=subprocess.PIPE,
                          text=True, env=env, timeout=timeout, preexec_fn=limited)


def _environment(tmp_path, **changes) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("WARP_CACHE_PATH", "XDG_CACHE_HOME")}
    env["TMPDIR"] = str(tmp_path / "tmp")
    (tmp_path / "tmp").mkdir(exist_ok=True)
    env.update(changes)
    return env


@pytest.mark.parametrize("variable", ["WARP_CACHE_PATH", "XDG_CACHE_HOME", "HOME"])
def test_an_unwritable_kernel_cache_moves_to_the_temporary_folder_with_one_warning(tiny_sphere, tmp_path, variable):
    a_file = tmp_path / "a-file"
    a_file.write_text("not a folder")
    run = _command(["info", str(tiny_sphere[0])], env=_environment(tmp_path, **{variable: str(a_file)}))
    assert run.returncode == 0, run.stderr
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert lines[0].startswith("warp-highlights info: warning: Warp's kernel cache ") and "WARP_CACHE_PATH" in lines[0]
    assert str(a_file) in lines[0] and "lights: 16" in run.stdout
    fallback = tmp_path / "tmp" / f"warp-highlights-kernels-{os.getuid()}"
    assert fallback.is_dir() and (fallback.stat().st_mode & 0o777) == 0o700


def test_no_writable_kernel_cache_anywhere_is_one_error_naming_warp_cache_path(tiny_sphere, tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("not a folder")
    env = _environment(tmp_path, WARP_CACHE_PATH=str(a_file))
    (tmp_path / "tmp" / f"warp-highlights-kernels-{os.getuid()}").write_text("in the way")
    run = _command(["info", str(tiny_sphere[0])], env=env)
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warp-highlights info: error: Warp's kernel cache "), run.stderr
    assert "set WARP_CACHE_PATH to a writable folder" in lines[0]


def test_a_failure_inside_the_kernel_cache_names_the_cache(tmp_path, monkeypatch):
    import warp as wp

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path / "cache"))
    error = OSError(errno.EROFS, os.strerror(errno.EROFS), str(tmp_path / "cache" / "wp_module" / "a.o"))
    line = describe_os_error(error)
    assert f"Warp's kernel cache {tmp_path / 'cache'}" in line and "WARP_CACHE_PATH" in line
    assert "choose an output" not in line


@pytest.mark.parametrize(("code", "words"), [
    (errno.EFBIG, "the file size limit (ulimit -f) was reached; raise the limit"),
    (errno.EDQUOT, "the disk quota is exceeded; free some space within the quota"),
    (errno.ENOSPC, "No space left on device; free some space"),
])
def test_size_limits_and_quotas_are_told_as_they_are(code, words):
    line = describe_os_error(OSError(code, os.strerror(code), "/data/out.exr"))
    assert line == f"cannot write /data/out.exr: {words}" + line.split(words, 1)[1]


@pytest.mark.parametrize("suffix", [".png", ".exr", ".tif"])
def test_an_image_over_the_file_size_limit_is_efbig(tmp_path, suffix):
    script = ("import resource, sys, numpy as np\n"
              "from warp_highlights.io.images import write_image\n"
              "resource.setrlimit(resource.RLIMIT_FSIZE, (2000, resource.RLIM_INFINITY))\n"
              "image = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32)\n"
              "try:\n"
              "    write_image(sys.argv[1], image, bits=16 if sys.argv[1].endswith('.png') else 8)\n"
              "except OSError as error:\n"
              "    print(error.errno)\n")
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path / f"a{suffix}")], capture_output=True, text=True,
                         timeout=120)
    assert run.stdout.split() == [str(errno.EFBIG)], run.stdout + run.stderr


def test_a_render_over_the_file_size_limit_says_so_in_one_line(tmp_path):
    out = tmp_path / "render"
    run = _command(["render", "sphere", str(out), "--lights", "6", "--size", "160x120", "--samples", "1", "--device",
                    "cpu", "-q"], limit=3000)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and "the file size limit (ulimit -f) was reached" in lines[0], run.stderr
    assert not out.exists() and os.listdir(tmp_path) == []


def test_a_summary_that_stdout_cannot_take_says_the_field_was_written(tiny_sphere, tmp_path):
    field = tmp_path / "out.whf"
    with open("/dev/full", "w") as full:
        run = _command(["fit", str(tiny_sphere[0]), "-o", str(field), "--device", "cpu", "-q", *TINY_FIT],
                       stdout=full)
    assert run.returncode == 2
    lines = run.stderr.splitlines()
    assert lines == ["warp-highlights fit: error: could not print the summary on stdout (No space left on device); "
                     "the outputs finished before it are in place"], run.stderr
    assert field.is_file() and field.stat().st_size > 1000


@pytest.fixture()
def copied_capture(tiny_sphere, tmp_path):
    folder = tmp_path / "capture"
    shutil.copytree(tiny_sphere[0], folder)
    return folder


def test_a_nonfinite_image_says_what_the_command_line_can_do(copied_capture, capsys):
    image = np.ones((18, 32, 3), np.float32)
    image[3, 4] = np.nan
    write_image(copied_capture / "images" / "0003.exr", image)
    assert main(["info", str(copied_capture)]) == 2
    line = capsys.readouterr().err.strip()
    assert "non-finite" in line and "the command line does not replace them" in line
    assert "ReflectanceField.load(folder, replace_nonfinite=True)" in line and "pass replace_nonfinite" not in line


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_an_image_that_is_a_special_file_is_not_called_missing(copied_capture, capsys, kind):
    image = copied_capture / "images" / "0002.exr"
    image.unlink()
    if kind == "fifo":
        os.mkfifo(image)
    else:
        image.symlink_to("/dev/zero")
    assert main(["info", str(copied_capture)]) == 2
    line = capsys.readouterr().err.strip()
    assert "not found" not in line and "is not a regular file but a " in line, line
    assert ("FIFO" if kind == "fifo" else "character device") in line


def test_a_link_loop_in_a_collection_is_skipped_with_a_warning(tiny_sphere, tmp_path, caplog):
    from warp_highlights.collection.captures import find_captures

    root = tmp_path / "collection"
    root.mkdir()
    os.symlink(tiny_sphere[0], root / "sphere")
    os.symlink(root / "loop", root / "loop")
    with caplog.at_level(logging.WARNING, logger="warp_highlights"):
        captures = find_captures(root)
    assert [c.name for c in captures] == ["sphere"]
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and warned[0].startswith(f"{root / 'loop'}: skipped"), warned
    assert "points back at itself" in warned[0]
