"""Cases of the bad-input harness (``bad_inputs.py``) where the danger is losing data or hiding the truth:

- ``targets``: outputs that are devices, FIFOs, sockets or folders of another kind, and outputs that are the
  command's own inputs (the field, the light file, a capture's images, the dataset, through links too);
- ``races``: two processes writing one new name at once (exactly one may say ``wrote``), or one name with
  ``--overwrite`` (the later wins, whole);
- ``environment``: a read-only home, ``XDG_CACHE_HOME`` or ``WARP_CACHE_PATH`` (Warp's kernel cache), the file
  size limit (``ulimit -f``) and a standard output that cannot take the summary;
- ``captures``: a field used with another capture's images, and files of a capture that are not images
  (non-finite values, a FIFO, a link to ``/dev/zero``, a link loop under a collection);
- ``serve``: the local server under requests for FIFOs, links out of its folder, listings, and a client that
  goes away mid-download.

Every case names the paths that must stay exactly as they were (``Run.protected``: a change is data lost),
and checks the message where its words matter. The subprocess cases run ``python -m warp_highlights``.

This module holds one thing: these case builders; the harness runs and reports them.
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import socket
import stat
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bad_inputs import REPO, Case, Context, Run, Skip, finish, link_tree, put, writers

RACE_REPEATS = 3
"""Times each two-writer race is run (each a case of its own)."""
SERVE_ANSWER_SECONDS = 5.0
"""How long the server may take to answer one request before the case counts it as blocked."""


# --- running subprocesses ---------------------------------------------------------------------------


def _environment(**changes) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
               PYTHONFAULTHANDLER="1")  # a hang's stacks, on the SIGABRT that ``finish`` sends
    for name, value in changes.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = str(value)
    return env


def _command(argv) -> list[str]:
    return [sys.executable, "-m", "warp_highlights", *map(str, argv)]


def subprocess_runner(*, env: dict | None = None, file_size_limit: int | None = None,
                      stdout_path: str | None = None) -> Callable[[Run, Context], dict]:
    """Run the case's command in a child process with ``env``, ``RLIMIT_FSIZE`` = ``file_size_limit`` bytes
    and standard output into ``stdout_path`` (e.g. ``/dev/full``)."""

    def limits():
        if file_size_limit is not None:
            import resource

            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit, resource.RLIM_INFINITY))

    def runner(run: Run, ctx: Context) -> dict:
        started = time.perf_counter()
        with contextlib.ExitStack() as stack:
            out = stack.enter_context(open(stdout_path, "w")) if stdout_path else subprocess.PIPE
            process = subprocess.Popen(_command(run.argv), stdout=out, stderr=subprocess.PIPE, text=True,
                                       env=env or _environment(), cwd=ctx.work, preexec_fn=limits,
                                       start_new_session=True)
            stdout, stderr, hang = finish(process, ctx.timeout)
        return {"rc": process.returncode, "exception": None, "hang": hang, "crashed": None,
                "stdout": stdout or "", "stderr": stderr or "", "seconds": time.perf_counter() - started}

    return runner


def race_runner(argvs: list[list], target: Path, *, overwrite: bool) -> Callable[[Run, Context], dict]:
    """Start every command at once. Without ``overwrite`` exactly one may finish (the others: one line, exit 2)
    and two that say ``wrote`` is data lost (the earlier output was replaced); with it every one finishes."""

    def runner(run: Run, ctx: Context) -> dict:
        started = time.perf_counter()
        processes = [subprocess.Popen(_command(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      env=_environment(), cwd=ctx.work, start_new_session=True) for argv in argvs]
        results, hang = [], False
        for process in processes:
            out, err, hung = finish(process, ctx.timeout)
            hang = hang or hung
            results.append((process.returncode, out, err))
        wrote = [r for r in results if r[0] == 0]
        refused = [r for r in results if r[0] != 0]
        tracebacks = "".join(r[2] for r in results if "Traceback" in r[2])
        lost = []
        if overwrite:
            rc, stderr = (0, "") if not refused else (refused[0][0], refused[0][2])
        elif len(wrote) == 1 and all(r[0] == 2 and len(r[2].splitlines()) == 1 for r in refused):
            rc, stderr = 2, refused[0][2]
        elif len(wrote) > 1:
            rc, stderr = 0, ""
            lost.append(f"{len(wrote)} writers each said 'wrote {target}': all but one output were replaced")
        else:
            rc, stderr = (refused[0][0], "".join(r[2] for r in refused)) if refused else (0, "")
        return {"rc": rc, "exception": None, "hang": hang, "crashed": None, "stderr": tracebacks or stderr,
                "stdout": "".join(r[1] for r in results), "seconds": time.perf_counter() - started, "lost": lost,
                "note": "exit statuses " + ", ".join(str(r[0]) for r in results)}

    return runner


# --- targets ----------------------------------------------------------------------------------------


def _special(folder: Path, leaf: str, kind: str) -> Path:
    """A FIFO, a listening socket's name or a character device (/dev/null's numbers) at ``folder/leaf``."""
    path = folder / leaf
    if kind == "FIFO":
        os.mkfifo(path)
    elif kind == "socket":
        if len(os.fsencode(path)) > 100:
            raise Skip("the case folder's path is too long for a socket name")
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(str(path))
        server.close()  # the name stays, a socket file
    elif kind == "device":
        if os.geteuid() != 0:
            raise Skip("making a device node needs root")
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    return path


def target_cases(ctx: Context) -> list[Case]:
    cases = []
    F = str(ctx.field)
    file_writers = [(name, suffix, argv_of) for name, kind, suffix, argv_of in writers(ctx) if kind == "file"]
    file_writers.append(("export --single-file", ".html",
                         lambda o, d: ["export", F, "--single-file", "-o", o]))
    folder_writers = [(name, argv_of) for name, kind, _, argv_of in writers(ctx) if kind == "folder"]
    folder_writers += [("maps", lambda o, d: ["maps", F, "-o", o]), ("export", lambda o, d: ["export", F, "-o", o])]

    for name, suffix, argv_of in file_writers:
        for kind in ("FIFO", "socket", "device"):
            def build(folder, argv_of=argv_of, kind=kind, suffix=suffix):
                target = _special(folder, "out" + suffix, kind)
                return Run([*argv_of(target, folder), "--overwrite", "-q"], protected=[target])

            cases.append(Case("targets", f"{name}: -o is a {kind}, --overwrite", build, "error"))

        def build_link(folder, argv_of=argv_of, suffix=suffix):
            fifo = _special(folder, "pipe", "FIFO")
            link = folder / ("out" + suffix)
            link.symlink_to(fifo)
            return Run([*argv_of(link, folder), "--overwrite", "-q"], protected=[fifo, link])

        cases.append(Case("targets", f"{name}: -o is a link to a FIFO, --overwrite", build_link, "error"))

    for name, argv_of in folder_writers:
        if name != "render":  # a dataset is render's own kind: replaced with --overwrite
            def onto_dataset(folder, argv_of=argv_of):
                target = link_tree(ctx.dataset, folder / "out")
                return Run([*argv_of(target, folder), "--overwrite", "-q"], protected=[target])

            cases.append(Case("targets", f"{name}: -o is a rendered dataset (another kind), --overwrite",
                              onto_dataset, "error"))

        def onto_fifo(folder, argv_of=argv_of):
            target = _special(folder, "out", "FIFO")
            return Run([*argv_of(target, folder), "--overwrite", "-q"], protected=[target])

        cases.append(Case("targets", f"{name}: -o is a FIFO, --overwrite", onto_fifo, "error"))
    return cases + _own_input_cases(ctx)


def _own_input_cases(ctx: Context) -> list[Case]:
    """Outputs that are the command's inputs, or a capture's images, under every name they go by."""
    F = ctx.field
    first = ctx.names[0]

    def field_copy(folder):
        return Path(shutil.copy(F, folder / "F.whf"))

    def capture(folder):
        return link_tree(ctx.capture_exr, folder / "C")

    def dataset(folder):
        return link_tree(ctx.dataset, folder / "D")

    def hard_link(folder):
        field = field_copy(folder)
        os.link(field, folder / "alias.html")
        return field, folder / "alias.html"

    def symlinked_capture(folder):
        data = capture(folder)
        (folder / "L").symlink_to(data, target_is_directory=True)
        return data, folder / "L"

    items = [
        ("export --single-file -o its own field", lambda d: (lambda f: (
            ["export", f, "--single-file", "-o", f, "--overwrite"], [f]))(field_copy(d))),
        ("export --single-file -o a hard link of its field", lambda d: (lambda pair: (
            ["export", pair[0], "--single-file", "-o", pair[1], "--overwrite"], [pair[0]]))(hard_link(d))),
        ("fit -o the capture's light file", lambda d: (lambda c: (
            ["fit", c, "--size", "16x9", "-o", c / "lights.lp", "--overwrite", "--device", "cpu", *ctx.fast],
            [c]))(capture(d))),
        ("fit --report one of the capture's images", lambda d: (lambda c: (
            ["fit", c, "-o", d / "F.whf", "--report", c / "images" / first, "--overwrite", "--device", "cpu",
             *ctx.fast], [c]))(capture(d))),
        ("fit -o a new file inside the capture", lambda d: (lambda c: (
            ["fit", c, "-o", c / "field.whf", "--device", "cpu", *ctx.fast], [c]))(capture(d))),
        ("fit through a linked capture folder, -o inside it", lambda d: (lambda pair: (
            ["fit", pair[1], "-o", pair[1] / "field.whf", "--device", "cpu", *ctx.fast], [pair[0]]))(
            symlinked_capture(d))),
        ("relight -o one of a capture's images (the capture not read)", lambda d: (lambda c: (
            ["relight", F, "--light", "0.3,0.5,1", "-o", c / "images" / first, "--overwrite"], [c]))(capture(d))),
        ("relight -o a capture's image through a linked folder", lambda d: (lambda pair: (
            ["relight", F, "--light", "0.3,0.5,1", "-o", pair[1] / "images" / first, "--overwrite"], [pair[0]]))(
            symlinked_capture(d))),
        ("relight -o a file of a rendered dataset (mask.png)", lambda d: (lambda data: (
            ["relight", F, "--light", "0.3,0.5,1", "-o", data / "mask.png", "--overwrite"], [data]))(dataset(d))),
        ("relight --lights the capture's light file -o the capture", lambda d: (lambda c: (
            ["relight", F, "--lights", c / "lights.lp", "-o", c, "--overwrite"], [c]))(capture(d))),
        ("relight --dataset D -o D", lambda d: (lambda data: (
            ["relight", F, "--method", "alpha", "--dataset", data, "--lights", ctx.lp8, "-o", data, "--overwrite"],
            [data]))(dataset(d))),
        ("evaluate F D -o D", lambda d: (lambda data: (
            ["evaluate", F, data, "-o", data, "--overwrite", "--triangle", "none"], [data]))(dataset(d))),
        ("maps -o a rendered dataset", lambda d: (lambda data: (
            ["maps", F, "-o", data, "--overwrite"], [data]))(dataset(d))),
        ("animate -o its own field", lambda d: (lambda f: (
            ["animate", f, "--path", "orbit:35", "--frames", "4", "-o", f, "--overwrite"], [f]))(field_copy(d))),
        ("collection -o a web site's folder (its own index.html)", lambda d: (
            ["collection", capture(d), "-o", put(d / "site" / "index.html", "<p>home</p>").parent, "--device", "cpu",
             "--no-evaluate", "--no-export"], [d / "site"])),
        ("collection -o a rendered dataset", lambda d: (lambda data: (
            ["collection", capture(d), "-o", data, "--device", "cpu", "--no-evaluate", "--no-export"], [data]))(
            dataset(d))),
    ]
    cases = []
    for label, make in items:
        def build(folder, make=make):
            argv, protected = make(folder)
            # a collection starts a Dask cluster: not from the harness's daemonic worker
            runner = subprocess_runner() if argv[0] == "collection" else None
            return Run([*argv, "-q"], protected=protected, runner=runner)

        cases.append(Case("targets", label, build, "error"))
    return cases


# --- races ------------------------------------------------------------------------------------------


def race_cases(ctx: Context) -> list[Case]:
    F, D = str(ctx.field), str(ctx.dataset)
    commands = [
        ("fit", ".whf", lambda o, light: ["fit", D, "-o", o, "--device", "cpu", *ctx.fast], _field_whole),
        ("relight", ".png", lambda o, light: ["relight", F, "--light", light, "-o", o], _image_whole),
        ("relight --lights", "", lambda o, light: ["relight", F, "--lights", ctx.lp8, "-o", o], _folder_whole),
        ("render", "", lambda o, light: ["render", "sphere", o, "--lights", "8", "--size", "32x18", "--samples", "1",
                                         "--device", "cpu"], _folder_whole),
        ("animate", ".gif", lambda o, light: ["animate", F, "--path", "orbit:35", "--frames", "4", "-o", o],
         _image_whole),
        ("evaluate", "", lambda o, light: ["evaluate", F, D, "-o", o, "--triangle", "none"], _folder_whole),
        ("export", "", lambda o, light: ["export", F, "-o", o], _folder_whole),
    ]
    cases = []
    for name, suffix, argv_of, whole in commands:
        for overwrite in (False, True):
            if overwrite and name not in ("fit", "relight", "render"):
                continue
            for repeat in range(RACE_REPEATS if not overwrite else 2):
                def build(folder, argv_of=argv_of, suffix=suffix, whole=whole, overwrite=overwrite):
                    target = folder / ("out" + suffix)
                    if overwrite:
                        ctx.cli([*argv_of(target, "0,0,1"), "-q"])
                    flag = ["--overwrite"] if overwrite else []
                    argvs = [[*argv_of(target, light), *flag, "-q"] for light in ("0.3,0.5,1", "-0.3,0.5,1")]
                    return Run(argvs[0], runner=race_runner(argvs, target, overwrite=overwrite),
                               check=lambda result, target=target: whole(target))

                what = "--overwrite, one name" if overwrite else "one new name"
                cases.append(Case("races", f"{name}: two at once, {what} (run {repeat + 1})", build,
                                  "ok" if overwrite else "error"))
    return cases


def _field_whole(path: Path) -> str | None:
    from warp_highlights.io.fieldfile import load_field

    try:
        load_field(path)
    except Exception as error:  # noqa: BLE001 (any failure is the finding)
        return f"{path} does not load: {error}"
    return None


def _image_whole(path: Path) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as image:
            image.load()
    except Exception as error:  # noqa: BLE001
        return f"{path} is not a whole image: {error}"
    return None


def _folder_whole(path: Path) -> str | None:
    import json

    from warp_highlights.io.atomic import MANIFEST_NAME

    try:
        manifest = json.loads((path / MANIFEST_NAME).read_text())
        listed = set(manifest["files"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        return f"{path} has no readable manifest: {error}"
    present = {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file() and p.name != MANIFEST_NAME}
    return None if present == listed else f"{path} holds other files than its manifest lists (a mix of two writers)"


# --- environment ------------------------------------------------------------------------------------


def _read_only_folder(ctx: Context, folder: Path) -> tuple[Path, Callable[[], None] | None]:
    """A folder no file can be created in: a read-only tmpfs as root (root ignores permission bits), else 0555."""
    if os.geteuid() == 0:
        ctx.mount(folder, "ro,size=64k")
        return folder, lambda: ctx.umount(folder)
    folder.mkdir(parents=True)
    folder.chmod(0o555)
    return folder, lambda: folder.chmod(0o755)


def _one_line(prefix: str, *words: str) -> Callable[[dict], str | None]:
    def check(result):
        lines = (result.get("stderr") or "").splitlines()
        if len(lines) != 1 or not lines[0].startswith(prefix) or not all(w in lines[0] for w in words):
            return f"stderr is not one line starting {prefix!r} naming {words}: {lines[:3]}"
        return None

    return check


def environment_cases(ctx: Context) -> list[Case]:
    D, F = str(ctx.dataset), str(ctx.field)
    cases = []
    no_cache = {"WARP_CACHE_PATH": None, "XDG_CACHE_HOME": None}

    for variable in ("HOME", "XDG_CACHE_HOME", "WARP_CACHE_PATH"):
        def build(folder, variable=variable):
            if variable == "WARP_CACHE_PATH":
                place, cleanup = put(folder / "a-file", "not a folder"), None
            else:
                place, cleanup = _read_only_folder(ctx, folder / "read-only")
            env = _environment(**{**no_cache, variable: place, "TMPDIR": ctx.work / "tmp"})
            return Run(["info", D], runner=subprocess_runner(env=env), cleanup=cleanup,
                       check=_one_line("warp-highlights info: warning: Warp's kernel cache", "WARP_CACHE_PATH"))

        what = "a file" if variable == "WARP_CACHE_PATH" else "read-only"
        cases.append(Case("environment", f"info: {variable} {what} (the kernel cache falls back)", build, "ok"))

    def nowhere(folder):
        temporary = folder / "tmp"
        put(temporary / f"warp-highlights-kernels-{os.getuid()}", "in the way")
        env = _environment(**{**no_cache, "WARP_CACHE_PATH": put(folder / "a-file", "x"), "TMPDIR": temporary})
        return Run(["info", D], runner=subprocess_runner(env=env),
                   check=_one_line("warp-highlights info: error: Warp's kernel cache", "WARP_CACHE_PATH"))

    cases.append(Case("environment", "info: no writable kernel cache anywhere", nowhere, "error"))

    limited = [
        ("relight to an EXR", ".exr", 1000, lambda o: ["relight", F, "--light", "0.3,0.5,1", "-o", o]),
        ("relight to a PNG", ".png", 2000,
         lambda o: ["relight", F, "--light", "0.3,0.5,1", "--size", "256x144", "-o", o]),
        ("render", "", 3000, lambda o: ["render", "sphere", o, "--lights", "6", "--size", "160x120", "--samples", "1",
                                        "--device", "cpu"]),
        ("fit", ".whf", 4000, lambda o: ["fit", D, "-o", o, "--device", "cpu", *ctx.fast]),
    ]
    for name, suffix, limit, argv_of in limited:
        def build(folder, suffix=suffix, limit=limit, argv_of=argv_of):
            out = folder / ("out" + suffix)
            return Run([*argv_of(out), "-q"], outputs=[out], runner=subprocess_runner(file_size_limit=limit),
                       check=_one_line("warp-highlights ", "error:", "ulimit -f"))

        cases.append(Case("environment", f"{name}: file size limit {limit} bytes (EFBIG)", build, "error"))

    summaries = [
        ("fit", ".whf", lambda o: ["fit", D, "-o", o, "--device", "cpu", *ctx.fast]),
        ("relight", ".png", lambda o: ["relight", F, "--light", "0.3,0.5,1", "-o", o]),
    ]
    for name, suffix, argv_of in summaries:
        def build(folder, suffix=suffix, argv_of=argv_of):
            out = folder / ("out" + suffix)

            def check(result, out=out):
                problem = _one_line("warp-highlights ", "could not print the summary", "are in place")(result)
                return problem or (None if out.is_file() else f"{out} is missing, though the summary came after it")

            return Run([*argv_of(out), "-q"], runner=subprocess_runner(stdout_path="/dev/full"), check=check)

        cases.append(Case("environment", f"{name}: standard output is /dev/full", build, "error"))
    return cases


# --- captures ---------------------------------------------------------------------------------------


def _other_capture(ctx: Context) -> Path:
    """Another object under the same 16 lights at the same size: only its pixels differ."""
    def make():
        other = ctx.base / "other-object"
        ctx.cli(["render", "donut", other, "--lights", "16", "--size", "32x18", "--samples", "1", "--heldout",
                 "centroids", "--device", "cpu", "-q"])
        return other

    return ctx.cached("other capture", make)


def _says(present: list[str], absent: list[str], what: str) -> Callable[[dict], str | None]:
    """A check that stderr holds every phrase of ``present`` and none of ``absent`` (it says ``what``)."""
    def check(result):
        text = result.get("stderr") or ""
        if any(phrase not in text for phrase in present) or any(phrase in text for phrase in absent):
            return f"the message does not say {what}: {text.strip()[:200]}"
        return None

    return check


def capture_cases(ctx: Context) -> list[Case]:
    F, D = str(ctx.field), str(ctx.dataset)
    cases = []
    refused = [
        ("relight --method alpha --dataset OTHER", lambda o, x: ["relight", F, "--method", "alpha", "--dataset", x,
                                                                 "--light", "0.3,0.5,1", "-o", o / "a.png"]),
        ("evaluate F OTHER", lambda o, x: ["evaluate", F, x, "-o", o / "scores", "--triangle", "none"]),
        ("animate --compare --dataset OTHER", lambda o, x: ["animate", F, "--compare", "--dataset", x, "--path",
                                                            "orbit:35", "--frames", "4", "-o", o / "a.gif"]),
    ]
    for label, argv_of in refused:
        for override in (False, True):
            def build(folder, argv_of=argv_of, override=override):
                other = _other_capture(ctx)
                argv = [*argv_of(folder, other), *(["--other-capture"] if override else []), "-q"]
                check = None if override else _one_line("warp-highlights ", "fitted to another capture",
                                                        "--other-capture")
                return Run(argv, protected=[other], check=check)

            cases.append(Case("captures", f"{label}" + (" --other-capture" if override else ""), build,
                              "ok" if override else "error"))
    cases.append(Case("captures", "evaluate F with its own capture", lambda folder: Run(
        ["evaluate", F, D, "-o", folder / "scores", "--triangle", "none", "-q"]), "ok"))

    first = ctx.names[0]

    def nonfinite(folder):
        from warp_highlights.io.images import write_image

        capture = link_tree(ctx.capture_exr, folder / "C")
        image = np.array(ctx.images[0], dtype=np.float32)
        image[3, 4] = np.nan
        (capture / "images" / first).unlink()
        write_image(capture / "images" / first, image)

        check = _says(["non-finite"], ["pass replace_nonfinite"], "what is wrong and what to do")
        return Run(["fit", capture, "-o", folder / "F.whf", "--device", "cpu", *ctx.fast, "-q"], check=check)

    cases.append(Case("captures", "fit: an EXR holding NaN", nonfinite, "error"))

    for kind in ("FIFO", "link to /dev/zero"):
        def build(folder, kind=kind):
            capture = link_tree(ctx.capture_exr, folder / "C")
            image = capture / "images" / first
            image.unlink()
            if kind == "FIFO":
                os.mkfifo(image)
            else:
                image.symlink_to("/dev/zero")

            check = _says(["not a regular file"], ["not found"], "what the file is")
            return Run(["fit", capture, "-o", folder / "F.whf", "--device", "cpu", *ctx.fast, "-q"], check=check)

        cases.append(Case("captures", f"fit: an image that is a {kind}", build, "error"))

    def loop(folder):
        shelf = folder / "shelf"
        link_tree(ctx.capture_exr, shelf / "coin")
        (shelf / "loop").symlink_to(shelf / "loop")

        def check(result):
            text = result.get("stderr") or ""
            if "loop" not in text or result.get("rc") != 0:
                return f"the loop is not skipped with a warning naming it: {text.strip()[:200]}"
            return None

        return Run(["collection", shelf, "-o", folder / "out", "--device", "cpu", "--workers", "1", "--no-evaluate",
                    "--no-export", *ctx.fast, "-q"], check=check, runner=subprocess_runner())

    cases.append(Case("captures", "collection: a link loop beside a capture", loop, "ok"))
    return cases


# --- serve ------------------------------------------------------------------------------------------


def _site(ctx: Context) -> Path:
    def make():
        site = ctx.base / "site"
        ctx.cli(["export", ctx.field, "-o", site, "-q"])
        return site

    return ctx.cached("site", make)


def serve_runner(request: Callable[[str, Path], str | None]) -> Callable[[Run, Context], dict]:
    """Start ``serve`` on a free port, make ``request(base URL, folder)`` (its problem, or None), then Ctrl-C it."""

    def runner(run: Run, ctx: Context) -> dict:
        started = time.perf_counter()
        process = subprocess.Popen(_command(run.argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env=_environment(), cwd=ctx.work, start_new_session=True)
        problem, hang = None, False
        try:
            ready, _, _ = select.select([process.stdout], [], [], ctx.timeout)
            line = process.stdout.readline() if ready else ""
            if "http://" not in line:
                problem = f"serve printed no address: {line!r}"
            else:
                base = line.split("http://", 1)[1].split("/", 1)[0]
                problem = request(f"http://{base}", Path(run.argv[1]))
            process.send_signal(signal.SIGINT)
            out, err, hang = finish(process, ctx.timeout)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        return {"rc": process.returncode, "exception": None, "hang": hang, "crashed": None, "stdout": out or "",
                "stderr": err or "", "seconds": time.perf_counter() - started, "problem": problem}

    return runner


def _status(url: str) -> tuple[int, float]:
    started = time.perf_counter()
    try:
        with urllib.request.urlopen(url, timeout=SERVE_ANSWER_SECONDS) as response:
            response.read()
            return response.status, time.perf_counter() - started
    except urllib.error.HTTPError as error:
        return error.code, time.perf_counter() - started
    except (OSError, TimeoutError):
        return -1, time.perf_counter() - started


def _expect(path: str, status: int) -> Callable[[str, Path], str | None]:
    def request(base, folder):
        got, seconds = _status(base + path)
        if got != status:
            return f"{path}: status {got} after {seconds:.1f} s, expected {status}"
        alive, _ = _status(base + "/index.html")
        return None if alive == 200 else f"the server no longer answers /index.html (status {alive})"

    return request


def _disconnect(base: str, folder: Path) -> str | None:
    host, port = base.removeprefix("http://").split(":")
    for _ in range(3):
        with socket.create_connection((host, int(port)), timeout=SERVE_ANSWER_SECONDS) as client:
            client.sendall(b"GET /big.bin HTTP/1.1\r\nHost: x\r\n\r\n")
            client.recv(65536)
            client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # reset, not close
    time.sleep(0.5)
    alive, _ = _status(base + "/index.html")
    return None if alive == 200 else f"the server no longer answers /index.html (status {alive})"


def serve_cases(ctx: Context) -> list[Case]:
    def site_copy(folder: Path) -> Path:
        site = link_tree(_site(ctx), folder / "site")
        os.mkfifo(site / "pipe.bin")
        put(folder / "secret.txt", "outside the folder")
        (site / "out.txt").symlink_to(folder / "secret.txt")
        (site / "zero.bin").symlink_to("/dev/zero")
        put(site / "bare" / "a.json", "{}")
        (site / "big.bin").write_bytes(os.urandom(32 << 20))
        return site

    requests = [
        ("a request for a FIFO", _expect("/pipe.bin", 404)),
        ("a request for a link out of the folder", _expect("/out.txt", 404)),
        ("a request for a link to /dev/zero", _expect("/zero.bin", 404)),
        ("a request for a folder without index.html (a listing)", _expect("/bare/", 404)),
        ("a request for ../ outside the folder", _expect("/../secret.txt", 404)),
        ("clients that go away mid-download", _disconnect),
    ]
    cases = []
    for label, request in requests:
        def build(folder, request=request):
            site = site_copy(folder)

            def check(result):
                return result.get("problem")

            return Run(["serve", site, "--port", "0"], runner=serve_runner(request), check=check,
                       interrupt=(signal.SIGINT, 0.0), protected=[folder / "secret.txt"])

        cases.append(Case("serve", label, build, None))
    return cases
