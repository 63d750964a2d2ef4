"""The web viewer (``warp-highlights export``/``serve``): the page in a real headless Chromium against
``Relighter``, interaction, and bad input. Page tests skip where Chromium or Playwright is absent."""

from __future__ import annotations

import dataclasses
import shutil
import threading

import numpy as np
import pytest

DIRECTIONS = [(0.3, 0.5, 1.0), (-0.5, 0.2, 1.0), (0.1, -0.7, 0.4), (0.9, 0.1, 0.1), (-0.2, -0.3, -1.0)]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SOFTWARE_GL = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


@pytest.fixture(scope="module")
def exported(small_field, tmp_path_factory):
    from warp_highlights.cli import main

    folder = tmp_path_factory.mktemp("web") / "viewer"
    assert main(["export", str(small_field), "-o", str(folder), "-q"]) == 0
    return folder


@pytest.fixture(scope="module")
def page(exported):
    """The exported viewer of the fitted small donut, open in headless Chromium; console errors collected."""
    if CHROMIUM is None:
        pytest.skip("no chromium on the PATH (apt install chromium)")
    playwright = pytest.importorskip("playwright.sync_api", reason="Playwright for Python is not installed (pip install playwright)")
    from warp_highlights.web.serve import make_server

    server = make_server(exported, 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    with playwright.sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=CHROMIUM, args=SOFTWARE_GL)
        tab = browser.new_page()
        tab.errors = []
        tab.on("console", lambda message: tab.errors.append(message.text) if message.type == "error" else None)
        tab.on("pageerror", lambda error: tab.errors.append(str(error)))
        tab.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        tab.wait_for_function("window.whViewer !== undefined || document.getElementById('status').textContent.startsWith('error')", timeout=60_000)
        yield tab
        browser.close()
    server.shutdown()
    server.server_close()


def _canvas(tab, width: int, height: int) -> np.ndarray:
    return np.array(tab.evaluate("Array.from(whViewer.pixels())"), dtype=np.uint8).reshape(height, width, 4)[..., :3]


@pytest.mark.parametrize("method", ["circular", "straight"])
def test_the_page_relights_as_relight_does(page, small_field, method):
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.io.images import display_rgb8
    from warp_highlights.io.metrics import psnr_8bit
    from warp_highlights.relight.relighter import Relighter

    field = load_field(small_field)
    relighter = Relighter(field, device="cpu", scale=1.0 / field.exposure, residual_decode="query")
    assert page.errors == []
    for direction in DIRECTIONS:
        page.evaluate(f"whSetLight({direction[0]}, {direction[1]}, {direction[2]}, '{method}')")
        shown = _canvas(page, field.width, field.height)
        expected = display_rgb8(relighter.relight(np.asarray(direction), method=method).full)
        assert psnr_8bit(shown, expected) >= 40.0
        assert np.mean(shown != expected) < 0.001  # the same image, but for a rare rounding of the last level
    assert page.errors == []


def test_dragging_on_the_light_disc_moves_the_light_and_changes_the_image(page, small_field):
    from warp_highlights.io.fieldfile import load_field

    field = load_field(small_field)
    page.evaluate("whSetLight(0.0, 0.0, 1.0, 'circular')")
    before, text = _canvas(page, field.width, field.height), page.inner_text("#direction")
    box = page.locator("#disc").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + 0.85 * box["width"], box["y"] + 0.3 * box["height"], steps=5)
    page.mouse.up()
    x, y, z = (float(v) for v in page.inner_text("#direction").split(","))
    assert page.inner_text("#direction") != text and x > 0.5 and y > 0.2 and z > 0
    assert np.mean(_canvas(page, field.width, field.height) != before) > 0.01
    page.keyboard.press("ArrowLeft")
    assert float(page.inner_text("#direction").split(",")[0]) < x
    assert page.errors == []


def test_export_writes_the_manifest_and_arrays_it_names(exported):
    import json

    manifest = json.loads((exported / "manifest.json").read_text())
    assert manifest["format"] == "warp-highlights web viewer" and manifest["version"] == 1
    for name, spec in manifest["arrays"].items():
        size = np.dtype(spec["dtype"]).itemsize * int(np.prod(spec["shape"]))
        assert (exported / spec["file"]).stat().st_size == size, name
    assert (exported / "index.html").is_file() and (exported / "viewer.js").is_file()


def test_export_refuses_bad_output_and_fields_it_cannot_show(small_field, tmp_path, capsys):
    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.model.errors import InputError
    from warp_highlights.web.export import export_viewer

    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "mine.txt").write_text("keep")
    assert main(["export", str(small_field), "-o", str(taken), "-q"]) == 2
    assert sorted(p.name for p in taken.iterdir()) == ["mine.txt"]
    assert main(["export", str(small_field), "-o", str(tmp_path / "missing" / "viewer"), "-q"]) == 2
    assert main(["export", str(tmp_path / "nothing.whf"), "-o", str(tmp_path / "viewer"), "-q"]) == 2
    assert not (tmp_path / "viewer").exists()
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith("warp-highlights export: error:") for line in lines)
    field = load_field(small_field)
    with pytest.raises(InputError, match="low-rank residual"):
        export_viewer(dataclasses.replace(field, residual=None), tmp_path)


def test_serve_listens_on_this_computer_only(exported, tmp_path):
    from warp_highlights.model.errors import InputError
    from warp_highlights.web.serve import HOST, make_server

    server = make_server(exported, 0)
    try:
        assert HOST == "127.0.0.1" and server.server_address[0] == "127.0.0.1"
    finally:
        server.server_close()
    with pytest.raises(InputError, match="not an exported viewer"):
        make_server(tmp_path, 0)
