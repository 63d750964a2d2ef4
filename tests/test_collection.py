"""``warp-highlights collection``: captures found and named, every good one processed on a 2-process LocalCluster, the
corrupt one reported, reruns that do nothing, Ctrl-C that leaves nothing partial, outputs identical to the commands
run by hand, and an existing scheduler used as it is."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from warp_highlights.cli import main
from warp_highlights.collection.captures import find_captures, fingerprint
from warp_highlights.collection.gallery import write_gallery
from warp_highlights.model.errors import InputError

pytest.importorskip(
    "distributed",
    reason="warp-highlights collection needs Dask distributed (pip install 'warp-highlights[collection]')")

# A fast fit for 16 lights of 48x27: what each capture of the tests gets (the commands' defaults otherwise; a low-rank
# residual, as a CPU too slow to learn one in time keeps, so that a capture fits the same in a worker and by hand)
QUICK = ["--set", "estimation.iterations=150", "--set", "estimation.densify_until=100", "--set",
         "estimation.densify_every=50",
         "--set", "retarget.rigid_iterations=30", "--set", "retarget.iterations=60", "--set", "residual.check_lights=4",
         "--set", "residual.cpu_learned_epochs=0"]
GOOD = ("donut-a", "donut-b", "sphere-c", "teapot-d", "donut-e", "sphere-f")
NO_HELDOUT = ("donut-e",)


def _render(folder: Path, shape: str, *extra: str) -> None:
    folder.parent.mkdir(parents=True, exist_ok=True)
    assert main(["render", shape, str(folder), "--lights", "16", "--size", "48x27", "--samples", "1", "--device", "cpu",
                 "-q", *extra]) == 0


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    """Six tiny rendered captures in nested folders (one without held-out lights) and one whose first image is cut
    short."""
    root = tmp_path_factory.mktemp("collection") / "captures"
    for name in GOOD:
        shape = name.split("-")[0]
        _render(root / ("museum-a" if name < "sphere" else "museum-b") / name, shape,
                *(["--heldout", "none"] if name in NO_HELDOUT else []))
    broken = root / "museum-b" / "broken"
    _render(broken, "donut")
    first = sorted((broken / "images").iterdir())[0]
    first.write_bytes(first.read_bytes()[:200])
    return root


def _collection(*arguments: str, session: bool = False) -> subprocess.Popen:
    command = [sys.executable, "-m", "warp_highlights", "collection", *arguments, "--workers", "2", "--device", "cpu",
               "-q", *QUICK]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=session,
                            env={**os.environ, "PYTHONWARNINGS": "ignore"})


def _communicate(run: subprocess.Popen, timeout: float) -> tuple[str, str]:
    try:
        return run.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL) if _session(run) else run.kill()
        run.communicate()
        raise


def _session(run: subprocess.Popen) -> bool:
    try:
        return os.getpgid(run.pid) == run.pid
    except ProcessLookupError:
        return False


def _alive_in_group(group: int) -> list[str]:
    """Processes of a process group that still run (zombies, which a container's init may never reap, excluded)."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[2]) == group and fields[0] != "Z":
            alive.append(stat.parent.name)
    return alive


def _finished(output: Path) -> dict[str, float]:
    """Finished capture -> the modification time of its record (which a redone capture would change)."""
    return {p.parent.name: p.stat().st_mtime_ns for p in output.glob("*/capture.json")}


def _leftovers(output: Path) -> list[str]:
    return sorted(p.name for p in output.rglob(".*") if ".partial-" in p.name or ".replaced-" in p.name)


@pytest.fixture(scope="module")
def collected(captures, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    output = tmp_path_factory.mktemp("out") / "gallery"
    run = _collection(str(captures), "-o", str(output))
    stdout, stderr = _communicate(run, 600)
    return output, subprocess.CompletedProcess(run.args, run.returncode, stdout, stderr)


def test_captures_are_found_in_nested_folders_and_named_uniquely(tmp_path):
    lp = "1\nimage.png 0 0 1\n"
    for folder in ("a/coin", "b/coin", "c/tablet", "c/tablet/Test", "synth/Dome", "synth/Test", "d/seal",
                   "d/seal/images"):
        (tmp_path / folder).mkdir(parents=True, exist_ok=True)
    for folder in ("a/coin", "b/coin", "c/tablet", "c/tablet/Test", "synth/Dome", "synth/Test", "d/seal"):
        (tmp_path / folder / "dirs.lp").write_text(lp)
    (tmp_path / "d/seal/heldout.lp").write_text(lp)
    found = {c.name: c for c in find_captures([tmp_path])}
    assert sorted(found) == ["a_coin", "b_coin", "seal", "synth", "tablet"]
    assert found["synth"].folder == tmp_path / "synth/Dome" and found["synth"].heldout == tmp_path / "synth/Test"
    assert found["tablet"].heldout == tmp_path / "c/tablet/Test" and found["tablet"].has_heldout
    assert found["seal"].heldout is None and found["seal"].has_heldout  # heldout.lp inside
    assert found["a_coin"].heldout is None and not found["a_coin"].has_heldout
    assert [c.name for c in find_captures([tmp_path / "a/coin", tmp_path / "a/coin"])] == ["coin"]  # given twice: once
    with pytest.raises(InputError, match="no capture found"):
        find_captures([tmp_path / "d/seal/images"])
    with pytest.raises(InputError, match="not a folder"):
        find_captures([tmp_path / "missing"])
    # the held-out folder sorts after or before its capture: the same pairing
    for layout in ("objA/Train", "objB/dome"):
        (tmp_path / "order" / layout).mkdir(parents=True)
        (tmp_path / "order" / layout / "dirs.lp").write_text(lp)
        (tmp_path / "order" / Path(layout).parent / "Test").mkdir()
        (tmp_path / "order" / Path(layout).parent / "Test" / "dirs.lp").write_text(lp)
    paired = {c.name: c for c in find_captures([tmp_path / "order"])}
    assert sorted(paired) == ["objA", "objB"] and all(c.heldout.name == "Test" for c in paired.values())
    assert ([c.name for c in find_captures(str(tmp_path / "a/coin"))] == ["coin"]
            and find_captures([tmp_path / "a/coin"])[0].folder.is_absolute())
    before = fingerprint(found["tablet"])
    (tmp_path / "c/tablet/Test/dirs.lp").write_text(lp + "\n")
    assert fingerprint(found["tablet"]) != before  # a held-out light file changed: the capture is redone


@pytest.mark.slow
def test_every_good_capture_is_processed_and_the_corrupt_one_reported(collected):
    output, run = collected
    assert run.returncode == 1, run.stderr[-2000:]  # some failed
    assert "6 captures done now, 0 finished before, 1 failed (broken)" in run.stdout
    assert "broken: failed at fit:" in run.stderr and "0000.exr" in run.stderr and "Traceback" not in run.stderr
    data = json.loads((output / "collection.json").read_text())
    status = {r["name"]: r["status"] for r in data["captures"]}
    assert status == {**dict.fromkeys(GOOD, "ok"), "broken": "failed"}
    assert data["summary"]["finished"] == 6 and data["summary"]["failed"] == 1
    failure = next(r for r in data["captures"] if r["name"] == "broken")
    assert failure["step"] == "fit" and "damaged or not an image" in failure["error"]
    for name in GOOD:
        record = json.loads((output / name / "capture.json").read_text())
        for relative in ("field.whf", "fit-report.json", "evaluation/report.json", "viewer/index.html",
                         "viewer/manifest.json", "thumbnail.png"):
            assert (output / name / relative).is_file(), (name, relative)
        assert record["lights"] == 16 and record["size"] == [48, 27] and record["gaussians_per_light"] > 0
        methods = record["scores"]["methods"]
        assert {"circular", "alpha", "ptm", "hsh3", "rbf"} <= set(methods)
        assert all(np.isfinite(m["psnr_db"]) and 0 < m["ssim"] <= 1 for m in methods.values())
        assert (record["held_out_lights"]
                == ("lights 0, 5, 10, ... (a second fit)" if name in NO_HELDOUT else "heldout.lp"))
        assert (output / name / "holdout-field.whf").is_file() == (name in NO_HELDOUT)
    assert not _leftovers(output)
    rows = _table_rows((output / "index.html").read_text())
    assert len(rows) == 7 and any("broken" in row and "failed at fit" in " ".join(row) for row in rows)
    assert sum(any(cell.startswith("viewer") for cell in row) for row in rows) == 6


@pytest.mark.slow
def test_a_rerun_does_nothing_other_options_and_force_redo(collected, captures):
    output, _ = collected
    before = _finished(output)
    run = _collection(str(captures), "-o", str(output))
    stdout, stderr = _communicate(run, 300)
    assert run.returncode == 1 and "0 captures done now, 6 finished before, 1 failed (broken)" in stdout, stderr[-2000:]
    assert "not tried again" in stdout and _finished(output) == before
    # another option is other work: only what changed is redone (here every capture, by the option)
    run = _collection(str(captures / "museum-a" / "donut-a"), "-o", str(output), "--no-export")
    stdout, stderr = _communicate(run, 300)
    assert run.returncode == 0 and "1 captures done now" in stdout, stderr[-2000:]
    assert not (output / "donut-a" / "viewer").exists() and not _leftovers(output)
    before = _finished(output)["donut-a"]
    run = _collection(str(captures / "museum-a" / "donut-a"), "-o", str(output), "--no-export", "--force")
    stdout, stderr = _communicate(run, 300)
    assert run.returncode == 0 and "1 captures done now, 0 finished before" in stdout, stderr[-2000:]
    assert _finished(output)["donut-a"] != before and len(_finished(output)) == 6  # the gallery's other captures kept
    assert len(json.loads((output / "collection.json").read_text())["captures"]) == 6


@pytest.mark.slow
def test_outputs_are_those_of_the_commands_run_by_hand(collected, captures, tmp_path):
    from warp_highlights.io.fieldfile import load_field

    output, _ = collected
    for name, museum in (("donut-b", "museum-a"), ("donut-e", "museum-a")):
        capture, here = captures / museum / name, tmp_path / name
        here.mkdir()
        cwd = os.getcwd()
        os.chdir(here)  # as the collection runs them: in the capture's folder, relative names
        try:
            assert main(["fit", str(capture), "-o", "field.whf", "--device", "cpu", "-q", *QUICK]) == 0
            scored = "field.whf"
            if name in NO_HELDOUT:
                scored = "holdout-field.whf"
                assert main(["fit", str(capture), "-o", scored, "--holdout-every", "5", "--device", "cpu", "-q",
                             *QUICK]) == 0
            assert main(["evaluate", scored, str(capture), "-o", "evaluation", "--device", "cpu", "-q"]) == 0
            assert main(["export", "field.whf", "-o", "viewer", "-q"]) == 0
        finally:
            os.chdir(cwd)
        for field_name in ("field.whf", scored):
            mine, theirs = load_field(here / field_name), load_field(output / name / field_name)
            for part in ("amplitude", "mean", "sigma", "theta", "active"):
                np.testing.assert_array_equal(getattr(mine.estimated, part), getattr(theirs.estimated, part))
                np.testing.assert_array_equal(getattr(mine.retargeted, part), getattr(theirs.retargeted, part))
        mine, theirs = (json.loads((root / "evaluation" / "report.json").read_text()) for root in (here, output / name))
        assert mine["per_query"] == theirs["per_query"] and mine["summary"] == theirs["summary"]
        for path in sorted((here / "viewer").iterdir()):
            if path.suffix in (".bin", ".gz"):
                assert path.read_bytes() == (output / name / "viewer" / path.name).read_bytes(), path.name


@pytest.mark.slow
def test_ctrl_c_leaves_nothing_partial_and_a_rerun_completes_exactly_the_rest(captures, tmp_path):
    output = tmp_path / "interrupted"
    run = _collection(str(captures / "museum-a"), str(captures / "museum-b" / "sphere-c"),
                      str(captures / "museum-b" / "sphere-f"),
                      "-o", str(output), "--no-evaluate", session=True)
    started = time.monotonic()
    while not _finished(output) and time.monotonic() - started < 300 and run.poll() is None:
        time.sleep(0.05)
    assert run.poll() is None, "the collection ended before it could be interrupted"
    os.killpg(run.pid, signal.SIGINT)  # as Ctrl-C in a terminal: the whole process group
    stdout, stderr = _communicate(run, 120)
    assert run.returncode == 130, stderr[-2000:]
    assert "interrupted; nothing partial was left behind" in stderr and "Traceback" not in stderr
    ended = time.monotonic() + 15.0
    while _alive_in_group(run.pid) and time.monotonic() < ended:  # no worker, nanny or command left running
        time.sleep(0.1)
    assert not _alive_in_group(run.pid), "processes of the interrupted collection still run 15 s after it ended"
    done = _finished(output)
    assert done, "no capture had finished when the collection was interrupted"
    assert len(done) < 5, "every capture had finished: the interruption came too late to test anything"
    assert not _leftovers(output), _leftovers(output)
    # finished folders only
    assert sorted(p.name for p in output.iterdir() if not p.name.startswith(".")) == sorted(done)
    rerun = _collection(str(captures / "museum-a"), str(captures / "museum-b" / "sphere-c"),
                        str(captures / "museum-b" / "sphere-f"),
                        "-o", str(output), "--no-evaluate")
    stdout, stderr = _communicate(rerun, 300)
    assert rerun.returncode == 0, stderr[-2000:]
    assert f"{5 - len(done)} captures done now, {len(done)} finished before, 0 failed" in stdout
    after = _finished(output)
    assert len(after) == 5 and all(after[name] == stamp for name, stamp in done.items()) and not _leftovers(output)


def test_an_existing_scheduler_is_used_as_it_is(captures, tmp_path):
    from distributed import LocalCluster

    from warp_highlights.collection import JobOptions, run

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with pytest.raises(InputError, match="--workers and --gpus size a local cluster"):
            run([captures / "museum-a" / "donut-a"], tmp_path / "remote", scheduler=cluster.scheduler_address,
                workers=2)
        quick = JobOptions(fit_args=tuple(QUICK), evaluate=False, export=False)
        result = run([captures / "museum-a" / "donut-a"], tmp_path / "remote", scheduler=cluster.scheduler_address,
                     device="cpu", options=quick)
        again = run([captures / "museum-a" / "donut-a"], tmp_path / "remote", scheduler=cluster.scheduler_address,
                    device="cpu", options=quick,
                    # a second run on the same workers (its plugin, its commands: the first run's stop is not its own)
                    force=True)
    assert result.processed == ["donut-a"] and result.ok and again.processed == ["donut-a"] and again.ok
    assert (tmp_path / "remote" / "donut-a" / "field.whf").is_file() and (tmp_path / "remote" / "index.html").is_file()


def test_bad_input_is_one_line_before_any_work(captures, tmp_path, capsys):
    assert main(["collection", str(tmp_path / "nowhere"), "-o", str(tmp_path / "out")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["collection", str(captures), "-o", str(tmp_path / "missing" / "out")]) == 2
    assert "does not exist; create it first" in capsys.readouterr().err
    assert main(["collection", str(captures), "-o", str(tmp_path / "out"), "--set", "estimation.nonsense=1"]) == 2
    assert "nonsense" in capsys.readouterr().err
    assert main(["collection", str(captures), "-o", str(tmp_path / "out"), "--device", "gpu7"]) == 2
    assert "give cpu, cuda or cuda:N" in capsys.readouterr().err
    assert main(["collection", str(captures), "-o", str(tmp_path / "out"), "--gpus", "64"]) == 2
    assert "this machine shows" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_output_folder_overlapping_a_capture_is_refused_and_nothing_is_touched(tmp_path, capsys):
    """OUT as the captures' parent would make OUT/NAME the capture itself (render wrote it, with a manifest:
    replaceable); OUT inside a capture would make the capture change with every run."""
    _render(tmp_path / "shelf" / "coin", "donut")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(["collection", str(tmp_path / "shelf"), "-o", str(tmp_path / "shelf"), "--device", "cpu"]) == 2
    assert "this capture is where its output" in capsys.readouterr().err
    assert main(["collection", str(tmp_path / "shelf" / "coin"), "-o", str(tmp_path / "shelf" / "coin" / "out"),
                 "--device", "cpu"]) == 2
    assert "inside the capture" in capsys.readouterr().err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_an_output_folder_of_other_files_is_refused_and_nothing_is_touched(tmp_path, capsys):
    """The gallery's index.html must never replace a web site's own; a rendered dataset is not a collection."""
    _render(tmp_path / "shelf" / "coin", "donut")
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<p>the museum's home page</p>")
    _render(tmp_path / "renders", "sphere")
    before = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    for output in (site, tmp_path / "renders"):
        assert main(["collection", str(tmp_path / "shelf"), "-o", str(output), "--device", "cpu"]) == 2
        err = capsys.readouterr().err
        assert "not a warp-highlights collection" in err and len(err.splitlines()) == 1, err
    assert {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_the_gallery_lists_scores_and_failures(tmp_path):
    ok = {"name": "coin", "status": "ok", "lights": 40, "size": [480, 270], "gaussians_per_light": 3.25,
          "fit_seconds": 2.5,
          "files": {"viewer": "viewer/index.html", "evaluation": "evaluation/report.json"},
          "scores": {"lights": 8, "methods": {"circular": {"psnr_db": 33.1, "ssim": 0.95},
                                              "alpha": {"psnr_db": 31.0, "ssim": 0.93},
                                              "rbf": {"psnr_db": 30.2, "ssim": 0.9}}}}
    bad = {"name": "seal<1>", "status": "failed", "step": "evaluate", "error": "no held-out lights & no Test/"}
    json_path, html_path = write_gallery(tmp_path, [ok, bad], title="museum")
    data = json.loads(json_path.read_text())
    assert (data["summary"]["finished"] == 1 and data["summary"]["failed"] == 1
            and data["summary"]["circular_beats_alpha"] == "1 of 1")
    rows = _table_rows(html_path.read_text())
    assert (["coin", "40", "480x270", "3.2", "2.5", "33.10", "31.00", "", "", "30.20", "viewer · evaluation"]
            == rows[0][1:])
    # escaped in the page, read back as text
    assert rows[1][1] == "seal<1>" and "no held-out lights & no Test/" in rows[1][2]
    assert "seal&lt;1&gt;" in html_path.read_text() and "&amp; no Test/" in html_path.read_text()


def _table_rows(page: str) -> list[list[str]]:
    """The text of each body row's cells."""

    class Rows(HTMLParser):
        def __init__(self):
            super().__init__()
            self.rows, self.inside, self.cell = [], False, None

        def handle_starttag(self, tag, attrs):
            if tag == "tbody":
                self.inside = True
            elif self.inside and tag == "tr":
                self.rows.append([])
            elif self.inside and tag == "td":
                self.cell = ""

        def handle_endtag(self, tag):
            if tag == "tbody":
                self.inside = False
            elif self.inside and tag == "td" and self.cell is not None:
                self.rows[-1].append(self.cell.strip())
                self.cell = None

        def handle_data(self, data):
            if self.cell is not None:
                self.cell += data

    parser = Rows()
    parser.feed(page)
    return parser.rows


@pytest.mark.slow
def test_the_gallery_opens_in_a_browser_and_its_links_lead_to_the_viewers(collected, tmp_path):
    """As a person would: the served gallery in headless Chromium shows every thumbnail, and a capture's viewer link
    opens a viewer that draws (the exported page's own readiness flag), without console errors."""
    import shutil
    import threading

    from warp_highlights.web.serve import make_server

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("no chromium on the PATH (apt install chromium)")
    playwright = pytest.importorskip("playwright.sync_api",
                                     reason="Playwright for Python is not installed (pip install playwright)")
    output, _ = collected
    server = make_server(output, 0)  # serve takes a collection's folder (index.html + collection.json)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with playwright.sync_playwright() as driver:
            browser = driver.chromium.launch(executable_path=chromium,
                                             args=["--use-gl=angle", "--use-angle=swiftshader",
                                                   "--enable-unsafe-swiftshader"])
            tab = browser.new_page()
            errors = []
            tab.on("pageerror", lambda error: errors.append(str(error)))
            tab.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            tab.wait_for_function("Array.from(document.images).every(i => i.complete)", timeout=30_000)
            widths = tab.eval_on_selector_all("tbody img", "images => images.map(i => i.naturalWidth)")
            # the 48x27 captures' thumbnails (never wider than 320)
            assert len(widths) == 6 and all(w == 48 for w in widths)
            tab.screenshot(path=str(tmp_path / "gallery.png"))
            with tab.expect_navigation():
                tab.click("text=viewer >> nth=1")
            tab.wait_for_function(
                "window.whReady === true || document.getElementById('status').textContent.startsWith('error')",
                timeout=120_000)
            assert tab.evaluate("window.whReady") is True and "/viewer/" in tab.url
            browser.close()
    finally:
        server.shutdown()
        server.server_close()
    assert not errors


@pytest.mark.parametrize("width,height,most", [(567, 534, 200), (534, 567, 200), (160, 160, 200), (3840, 2160, 960),
                                               (7952, 5304, 1000),
                                               (6000, 4000, 1024), (4000, 6000, 1023), (1001, 999, 1000)])
def test_max_side_gives_each_capture_a_size_fit_accepts(width, height, most, monkeypatch):
    """--max-side: the longer side at most PX, never enlarged, the aspect ratio as fit --size checks it (brute force:
    fit's own check)."""
    import warp_highlights.collection.job as job
    from warp_highlights.io.resample import working_size

    monkeypatch.setattr(job, "image_size", lambda capture: (width, height))
    arguments = job._size_arguments(None, most)
    if max(width, height) <= most:
        assert arguments == []
        return
    new_width, new_height = (int(v) for v in arguments[1].split("x"))
    assert working_size(width, height, (new_width, new_height)) == (new_width, new_height)
    assert max(new_width, new_height) <= most and max(new_width, new_height) >= most - 2


def _command_environment(environment: dict) -> tuple[str | None, dict]:
    """On a worker: its own MALLOC_TRIM_THRESHOLD_, and the environment its commands would get."""
    from warp_highlights.collection.job import _Runner, _Steps

    runner = _Runner(device=None, visible_gpu="0", cores=None, steps=_Steps(), linear=False, max_megapixels=None,
                     environment=environment)
    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), runner.env


def test_commands_get_the_launching_environment_back_from_dask(monkeypatch):
    """Dask's nanny gives its workers MALLOC_TRIM_THRESHOLD_=65536 and one BLAS thread (an evaluate took twice as long
    under them); each capture's commands get the variables as the collection's own process had them."""
    from distributed import Client, LocalCluster

    from warp_highlights.collection.runner import launch_environment

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    environment = launch_environment()
    assert environment["MALLOC_TRIM_THRESHOLD_"] is None, environment
    assert environment["OMP_NUM_THREADS"] == "3", environment
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        worker_trim, env = client.submit(_command_environment, environment, pure=False).result()
    assert worker_trim == "65536", "the premise: Dask's workers trim malloc at 64 KiB"
    assert "MALLOC_TRIM_THRESHOLD_" not in env, "the commands must not inherit the worker's trim threshold"
    assert env["OMP_NUM_THREADS"] == "3"
    assert env["CUDA_VISIBLE_DEVICES"] == "0"
