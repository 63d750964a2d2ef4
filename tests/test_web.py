"""The web viewer (``warp-highlights export``/``serve``): the page in a real headless Chromium against
``Relighter`` (every residual kind, both decode paths, the three methods, exposure), the statue sample,
``view``, interaction, the single-file page, and bad input. Page tests skip where Chromium or
Playwright is absent."""

from __future__ import annotations

import dataclasses
import gzip
import json
import threading
from contextlib import contextmanager

import numpy as np
import pytest

DIRECTIONS = [(0.3, 0.5, 1.0), (-0.5, 0.2, 1.0), (0.1, -0.7, 0.4), (0.9, 0.1, 0.1), (-0.2, -0.3, -1.0)]
READY = "window.whReady === true || document.getElementById('status').textContent.startsWith('error')"


@contextmanager
def opened(browser, url: str):
    """A tab at ``url``, ready (every light decoded), with its console errors in ``tab.errors``."""
    tab = browser.new_page()
    tab.errors = []
    tab.on("console", lambda message: tab.errors.append(message.text) if message.type == "error" else None)
    tab.on("pageerror", lambda error: tab.errors.append(str(error)))
    try:
        tab.goto(url)
        tab.wait_for_function(READY, timeout=120_000)
        yield tab
    finally:
        tab.close()


@contextmanager
def served(folder):
    """``folder`` served on 127.0.0.1; yields the page's URL."""
    from warp_highlights.web.serve import make_server

    server = make_server(folder, 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/index.html"
    finally:
        server.shutdown()
        server.server_close()


def _export(field_path, folder) -> None:
    from warp_highlights.cli import main

    assert main(["export", str(field_path), "-o", str(folder), "-q"]) == 0


@pytest.fixture(scope="module")
def fields(small_field, tmp_path_factory):
    """The fitted small donut (low-rank residual, weighed by the triangle's weights and by radial basis weights)
    and three variants of it, saved: its residual uncompressed, and a learned residual of random weights (the
    page's decoder against the reference), with
    the fitted decoder's shape and with a smaller one (two hidden layers of 20 and 13 units)."""
    from warp_highlights.io.fieldfile import load_field, save_field
    from warp_highlights.model.residual import NEURAL_LAYER_SHAPES, NeuralResidual, decoder_layer_shapes
    from warp_highlights.residual.decode import decoded_images
    from warp_highlights.residual.interpolation import residual_sigma

    field = load_field(small_field)
    residual = field.residual
    assert residual.kind == "lowrank" and residual.learned is None
    rng = np.random.default_rng(7)
    weights = tuple((rng.normal(size=shape) / np.sqrt(shape[1])).astype(np.float32) for shape in NEURAL_LAYER_SHAPES)
    student = tuple((rng.normal(size=shape) / np.sqrt(shape[1])).astype(np.float32)
                    for shape in decoder_layer_shapes((20, 13)))
    codes = rng.normal(size=(field.height, field.width, 9)).astype(np.float16)
    sigma = residual_sigma(residual, field.lights.directions)
    variants = {
        "lowrank": dataclasses.replace(residual, rbf_sigma=None),
        "rbf": dataclasses.replace(residual, rbf_sigma=sigma),
        "images": dataclasses.replace(residual, images=decoded_images(residual), luminance=None, chroma=None,
                                      scale=None),
        "learned": dataclasses.replace(residual, learned=NeuralResidual(codes, weights, 0.3, field.light_count),
                                       luminance=None, chroma=None, scale=None),
        "student": dataclasses.replace(residual, learned=NeuralResidual(codes, student, 0.3, field.light_count),
                                       luminance=None, chroma=None, scale=None),
    }
    root = tmp_path_factory.mktemp("web-fields")
    paths = {}
    for name, variant in variants.items():
        paths[name] = root / f"{name}.whf"
        save_field(dataclasses.replace(field, residual=variant), paths[name])
    return paths


@pytest.fixture(scope="module")
def exported(fields, tmp_path_factory):
    """name -> exported viewer folder of each of ``fields``."""
    root = tmp_path_factory.mktemp("web")
    folders = {}
    for name, path in fields.items():
        folders[name] = root / name
        _export(path, folders[name])
    return folders


def _canvas(tab, width: int, height: int) -> np.ndarray:
    return np.array(tab.evaluate("Array.from(whViewer.pixels())"), dtype=np.uint8).reshape(height, width, 4)[..., :3]


def _rgb8(image) -> np.ndarray:
    from warp_highlights.io.images import display_rgb8

    shown = display_rgb8(np.asarray(image, dtype=np.float32))
    return np.repeat(shown[..., None], 3, axis=2) if shown.ndim == 2 else np.broadcast_to(shown, shown.shape[:2] + (3,))


def _expected(field, relighter, direction, method: str) -> np.ndarray:
    """What the page must show: relight's image, or for alpha the blend of the field's own images of the
    corner lights (relight at those lights gives them back)."""
    if method != "alpha":
        return _rgb8(relighter.relight(np.asarray(direction, dtype=np.float64), method=method).full)
    location = field.triangulation.locate(np.asarray(direction, dtype=np.float64))
    corners = relighter.relight(field.lights.directions[np.asarray(location.vertices).reshape(3)],
                                method="circular").full
    return _rgb8(np.tensordot(np.asarray(location.barycentric, dtype=np.float64).reshape(3), corners.astype(np.float64),
                              axes=1))


def _check_page(tab, field_path, methods, directions=DIRECTIONS, *, stops: float = 0.0) -> list[float]:
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.quality.metrics import psnr_8bit
    from warp_highlights.relight.relighter import Relighter

    field = load_field(field_path)
    relighter = Relighter(field, device="cpu", scale=2.0**stops / field.exposure)
    scores = []
    for method in methods:
        for direction in directions:
            tab.evaluate(f"whSetLight({direction[0]}, {direction[1]}, {direction[2]}, '{method}', {stops})")
            shown = _canvas(tab, field.width, field.height).astype(int)
            expected = _expected(field, relighter, direction, method).astype(int)
            scores.append(psnr_8bit(shown.astype(np.uint8), expected.astype(np.uint8)))
            assert scores[-1] >= 40.0, (method, direction)
            # the same image but for rounding; alpha's reference clamps each corner's image at 0 before blending, the
            # page after
            assert np.mean(np.abs(shown - expected) > 1) < (0.002 if method != "alpha" else 0.05), (method, direction)
    assert tab.errors == []
    return scores


@pytest.mark.parametrize(("kind", "decode", "methods"), [
    ("lowrank", "auto", ["circular", "straight", "alpha"]),
    pytest.param("lowrank", "query", ["circular", "straight", "alpha"], marks=pytest.mark.slow),
    pytest.param("images", "auto", ["circular", "straight", "alpha"], marks=pytest.mark.slow),
    pytest.param("rbf", "auto", ["circular", "straight", "alpha"], marks=pytest.mark.slow),
    pytest.param("learned", "auto", ["circular", "straight"], marks=pytest.mark.slow),
    pytest.param("student", "auto", ["circular", "straight"], marks=pytest.mark.slow),
])  # fmt: skip
def test_the_page_relights_as_relight_does(browser, exported, fields, kind, decode, methods):
    with served(exported[kind]) as url, opened(browser, f"{url}?decode={decode}") as tab:
        mode = tab.evaluate("whViewer.mode")
        assert mode == {"lowrank": "decoded" if decode == "auto" else "stack", "images": "images", "rbf": "stack",
                        "learned": "learned", "student": "learned"}[kind]
        if mode == "decoded":
            assert tab.evaluate("whViewer.decodedCount()") == tab.evaluate("whViewer.manifest.lights")
        _check_page(tab, fields[kind], methods)
        assert tab.evaluate("whViewer.drawnWith") == {"decoded": "layers"}.get(mode, mode)


def test_frames_before_the_lights_are_decoded_decode_the_stack(browser, exported, fields):
    """A fresh viewer draws from the low-rank stack until a triangle's corners are decoded, then from the layers."""
    with served(exported["lowrank"]) as url, opened(browser, url) as tab:
        tab.evaluate("""async () => { const { Viewer } = await import('./viewer.js');
          window.fresh = await Viewer.load(document.createElement('canvas'),
                                           new URL('manifest.json', location.href)); }""")
        assert tab.evaluate("fresh.decodedCount()") == 0
        tab.evaluate("fresh.setLight([0.3, 0.5, 1.0])")
        assert tab.evaluate("fresh.drawnWith") == "stack"
        stacked = tab.evaluate("Array.from(fresh.pixels())")
        tab.evaluate("fresh.decodeRest()")
        assert tab.evaluate("fresh.decodedCount()") == tab.evaluate("fresh.manifest.lights")
        tab.evaluate("fresh.setLight([0.3, 0.5, 1.0])")
        assert tab.evaluate("fresh.drawnWith") == "layers"
        layered = np.array(tab.evaluate("Array.from(fresh.pixels())"))
        assert np.mean(np.abs(layered - np.array(stacked)) > 1) < 0.002
        # a browser that cannot make the layers (out of memory, no float16 targets) keeps drawing per pixel
        tab.evaluate("""async () => { const { Viewer } = await import('./viewer.js');
          window.failing = await Viewer.load(document.createElement('canvas'), new URL('manifest.json', location.href));
          failing.prepareLayers = () => { throw new Error('no room'); };
          failing.setLight([0.3, 0.5, 1.0]); await failing.decodeRest(); }""")
        assert tab.evaluate("[failing.decodeError, failing.mode, failing.decodedCount()]") == ["no room", "stack", 0]
        tab.evaluate("failing.setLight([0.3, 0.5, 1.0])")
        assert tab.evaluate("failing.drawnWith") == "stack"
        assert np.array_equal(np.array(tab.evaluate("Array.from(failing.pixels())")), np.array(stacked))
        assert tab.errors == []


def test_a_field_with_an_empty_chroma_stack_relights_as_relight_does(browser, tiny_sphere, tmp_path):
    """Rank 0 (the tiny sphere's chroma): empty arrays, a stack of no basis images."""
    from warp_highlights.io.fieldfile import load_field

    _, field_path = tiny_sphere
    assert load_field(field_path).residual.chroma.rank == 0
    folder = tmp_path / "sphere"
    _export(field_path, folder)
    assert json.loads((folder / "manifest.json").read_text())["arrays"]["chroma_ranges"]["shape"] == [0, 2]
    with served(folder) as url, opened(browser, url) as tab:
        _check_page(tab, field_path, ["circular", "alpha"], DIRECTIONS[:3])


def test_the_exposure_slider_scales_the_linear_image(browser, exported, fields):
    with served(exported["lowrank"]) as url, opened(browser, url) as tab:
        _check_page(tab, fields["lowrank"], ["circular"], DIRECTIONS[:2], stops=1.0)
        brighter = tab.evaluate("Array.from(whViewer.pixels()).reduce((a, b) => a + b, 0)")
        tab.evaluate("() => { const e = document.getElementById('exposure'); e.value = '-1.5'; e.dispatchEvent(new "
                     "Event('input')); }")
        tab.wait_for_function(
            "whViewer.exposureStops === -1.5 && document.getElementById('stops').textContent === '-1.5 EV'")
        assert tab.evaluate("Array.from(whViewer.pixels()).reduce((a, b) => a + b, 0)") < 0.8 * brighter


def test_the_page_says_how_much_of_the_image_moves(browser, exported, fields):
    """The status line gives the moving Gaussians and the share of the specular energy they carry, as the
    fit report has them."""
    from warp_highlights.io.fieldfile import load_field

    field = load_field(fields["lowrank"])
    share = field.report["residual"]["moving_specular_share"]
    moving, total = int(field.moving_mask.sum()), int(field.estimated.active.sum())
    manifest = json.loads((exported["lowrank"] / "manifest.json").read_text())
    assert manifest["motion"] == {"moving": moving, "gaussians": total, "specular_share": share}
    with served(exported["lowrank"]) as url, opened(browser, url) as tab:
        status = tab.text_content("#status")
    percent = int(np.floor(100 * share + 0.5))  # as Math.round
    expected = (f"{moving} of {total} Gaussians move ({percent}% of the specular energy)" if moving
                else "no Gaussian moves: the highlights blend")
    assert expected in status, status


def test_a_learned_field_offers_no_alpha_blend(browser, exported):
    with served(exported["learned"]) as url, opened(browser, url) as tab:
        assert tab.eval_on_selector("#method option[value=alpha]", "o => o.disabled")
        with pytest.raises(Exception, match="learned residual has none"):
            tab.evaluate("whViewer.setLight([0, 0, 1], 'alpha')")


@pytest.fixture(scope="module")
def seeing(fields, tmp_path_factory):
    """The learned variant with a decoder that sees the highlights (w0's 12 columns and two non-zero ones, for sqrt(g)
    and g), and bounds; exported from memory: (field, folder)."""
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.model.residual import learned_bounds
    from warp_highlights.web.export import export_viewer

    field = load_field(fields["learned"])
    learned = field.residual.learned
    rng = np.random.default_rng(11)
    w0 = np.concatenate([learned.weights[0], rng.normal(0.0, 0.6, (len(learned.weights[0]), 2))], axis=1)
    low = np.full((field.height, field.width, 3), -0.05)
    bounds = learned_bounds(low, low + rng.uniform(0.3, 3.0, low.shape), np.zeros_like(low))
    seeing_learned = dataclasses.replace(learned, weights=(w0.astype(np.float32), *learned.weights[1:]), bounds=bounds)
    assert seeing_learned.sees_highlights
    field = dataclasses.replace(field, residual=dataclasses.replace(field.residual, learned=seeing_learned))
    folder = tmp_path_factory.mktemp("web-seeing") / "seeing"
    folder.mkdir()
    export_viewer(field, folder)
    return field, folder


def _gaussian_luminance(field, direction, method: str) -> np.ndarray:
    """(H, W) float32 S' of the relighter's moved Gaussians (field units) at ``direction`` by ``method``."""
    from warp_highlights.relight.relighter import Relighter

    relighter = Relighter(dataclasses.replace(field, residual=None), device="cpu", diffuse="none")
    relit = relighter.relight(np.asarray(direction, np.float64), method=method, full=False)
    assert not relit.clamped  # a full sphere: the decoder takes the query's own unit direction
    return relit.specular


def _seeing_reference(field, direction, specular: np.ndarray, *, scale: float = 1.0,
                      highlights: bool = True) -> np.ndarray:
    """(H, W, 3) float64 relit image of a field whose decoder sees the highlights: the decoder at the unit direction
    with sqrt(g), g (g = max(S', 0) / unit; 0 where not ``highlights``), unit * decode_display of it clipped to
    +-6e4 and rounded to float16 as the relighter keeps it, within the bounds, no Gaussians added, times ``scale``,
    clamped at 0."""
    from warp_highlights.residual.opponent import decode_display

    learned = field.residual.learned
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    codes = learned.codes.reshape(-1, 9).astype(np.float64)
    g = np.maximum(specular.astype(np.float64).reshape(-1), 0.0) / learned.unit * highlights
    h = np.concatenate([codes, np.broadcast_to(d, (len(codes), 3)), np.sqrt(g)[:, None], g[:, None]], axis=1).T
    weights = [w.astype(np.float64) for w in learned.weights]
    for w, b in zip(weights[0:-2:2], weights[1:-2:2]):
        z = w @ h + b
        h = np.where(z > 0, z, np.expm1(np.minimum(z, 0.0)))
    y = (weights[-2] @ h + weights[-1]).T
    values = np.clip(learned.unit * decode_display(y), -6e4, 6e4).astype(np.float16).astype(np.float64)
    values = learned.within_bounds(values.reshape(field.height, field.width, 3))
    return scale * np.maximum(values, 0.0)


def _relighter_sees(field) -> bool:
    """Whether ``Relighter`` relights a field whose decoder sees the highlights (else it refuses in one error)."""
    from warp_highlights.model.errors import InputError
    from warp_highlights.relight.relighter import Relighter

    try:
        Relighter(field, device="cpu").relight(np.array([0.0, 0.0, 1.0]))
    except (InputError, ValueError):
        return False
    return True


@pytest.mark.parametrize("stops", [0.0, pytest.param(1.0, marks=pytest.mark.slow)])
def test_a_decoder_that_sees_the_highlights_relights_in_the_page_as_in_the_library(browser, seeing, stops):
    """The page's decoder takes sqrt(g), g of the Gaussians it draws and gives the whole image; it matches the float64
    reference (and ``Relighter``, where it relights such a decoder) as the learned page does."""
    from warp_highlights.quality.metrics import psnr_8bit
    from warp_highlights.relight.relighter import Relighter

    field, folder = seeing
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["version"] == 4 and manifest["residual"]["sees_highlights"] is True
    assert manifest["arrays"]["learned_w0"]["shape"] == [48, 14]
    scale = 2.0**stops / field.exposure
    relighter = Relighter(field, device="cpu", scale=scale) if _relighter_sees(field) else None
    moved = []
    with served(folder) as url, opened(browser, url) as tab:
        assert tab.evaluate("whViewer.mode") == "learned" and "sees the highlights" in tab.text_content("#status")
        for method in ("circular", "straight"):
            for direction in DIRECTIONS:
                tab.evaluate(f"whSetLight({direction[0]}, {direction[1]}, {direction[2]}, '{method}', {stops})")
                shown = _canvas(tab, field.width, field.height)
                specular = _gaussian_luminance(field, direction, method)
                reference = _seeing_reference(field, direction, specular, scale=scale)
                expected = [_rgb8(reference)]
                if relighter is not None:
                    expected.append(_rgb8(relighter.relight(np.asarray(direction), method=method).full))
                for image in expected:
                    assert psnr_8bit(shown, image) >= 40.0, (method, direction)
                    assert np.mean(np.abs(shown.astype(int) - image) > 1) < 0.002, (method, direction)
                # the highlights are the decoder's inputs, not added on top, and they change its image
                blind = _rgb8(_seeing_reference(field, direction, specular, scale=scale, highlights=False))
                added = _rgb8(reference + scale * specular[..., None])
                moved.append((psnr_8bit(shown, blind), psnr_8bit(shown, added)))
        assert tab.errors == []
    assert min(blind for blind, _ in moved) < 35.0 and min(added for _, added in moved) < 35.0, moved


def test_a_twelve_column_learned_field_exports_as_it_did(exported, fields, seeing):
    """Only a decoder that sees the highlights gets the layout's version 4 and the flag."""
    plain = json.loads((exported["learned"] / "manifest.json").read_text())
    assert plain["version"] == 3 and "sees_highlights" not in plain["residual"]
    assert plain["arrays"]["learned_w0"]["shape"] == [48, 12]
    _, folder = seeing
    w0 = _read_array(folder, json.loads((folder / "manifest.json").read_text())["arrays"]["learned_w0"])
    np.testing.assert_array_equal(w0, seeing[0].residual.learned.weights[0])


@pytest.fixture(scope="module")
def statue_field(data_root, tmp_path_factory):
    """The real statue sample, fitted small and fast through the command line (71 x 67), low rank (none of its
    Gaussians moves, so "auto" would learn its residual on the CPU: a page without the alpha blend)."""
    from conftest import TINY_FIT
    from warp_highlights.cli import main

    folder = data_root / "realrti-item11"
    if not folder.is_dir():
        pytest.skip(f"sample realrti-item11 not found under {data_root} (set WARP_HIGHLIGHTS_DATA)")
    path = tmp_path_factory.mktemp("statue") / "statue.whf"
    assert main(["fit", str(folder), "-o", str(path), "--size", "71x67", "--device", "cpu", "--residual", "lowrank",
                 "-q", *TINY_FIT]) == 0
    return path


@pytest.mark.realdata
def test_the_statue_page_relights_as_relight_does(browser, statue_field, tmp_path):
    """The real capture (a dome: directions below its rim clamp to it, as relight does)."""
    folder = tmp_path / "statue"
    _export(statue_field, folder)
    with served(folder) as url, opened(browser, url) as tab:
        assert tab.evaluate("whViewer.manifest.is_dome")
        _check_page(tab, statue_field, ["circular", "alpha"])
        tab.evaluate("whSetLight(0.2, 0.3, -1.0, 'circular')")
        assert tab.evaluate("whViewer.location.clamped")


def test_view_and_the_page_show_the_same_direction_and_image(browser, exported, fields):
    """``view``'s designer (off screen) and the page, moved to the same directions: the same unit
    direction text, the same triangle and the same 8-bit image."""
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.quality.metrics import psnr_8bit
    from warp_highlights.view.designer import LightDesigner

    field = load_field(fields["lowrank"])
    designer = LightDesigner(field, device="cpu", panels=("image",), off_screen=True, window_size=(200, 150))
    try:
        with served(exported["lowrank"]) as url, opened(browser, url) as tab:
            for direction in [None] + DIRECTIONS[:3]:  # None: the first light both show
                if direction is not None:
                    designer.set_direction(direction)
                    tab.evaluate(f"whSetLight({direction[0]}, {direction[1]}, {direction[2]}, 'circular')")
                shown = [float(v) for v in tab.inner_text("#direction").split(",")]
                np.testing.assert_allclose(shown, designer.direction, atol=5e-4)
                location = field.triangulation.locate(designer.direction)
                face = tab.evaluate("whViewer.location.face")
                assert (sorted(field.triangulation.faces[face])
                        == sorted(np.asarray(location.vertices).reshape(3).tolist()))
                assert psnr_8bit(_canvas(tab, field.width, field.height), _rgb8(designer.image)) >= 40.0
            assert tab.errors == []
    finally:
        designer.plotter.close()


def test_dragging_moves_the_light_and_changes_the_image(browser, exported, fields):
    from warp_highlights.io.fieldfile import load_field

    field = load_field(fields["lowrank"])
    with served(exported["lowrank"]) as url, opened(browser, url) as tab:
        tab.evaluate("whSetLight(0.0, 0.0, 1.0, 'circular')")
        before, text = _canvas(tab, field.width, field.height), tab.inner_text("#direction")
        box = tab.locator("#disc").bounding_box()
        tab.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        tab.mouse.down()
        tab.mouse.move(box["x"] + 0.85 * box["width"], box["y"] + 0.3 * box["height"], steps=5)
        tab.mouse.up()
        x, y, z = (float(v) for v in tab.inner_text("#direction").split(","))
        assert tab.inner_text("#direction") != text and x > 0.5 and y > 0.2 and z > 0
        assert np.mean(_canvas(tab, field.width, field.height) != before) > 0.01
        tab.keyboard.press("ArrowLeft")
        assert float(tab.inner_text("#direction").split(",")[0]) < x
        # a finger drags on the image itself (no shift key); a mouse there needs shift
        image = tab.locator("#image").bounding_box()
        text = tab.inner_text("#direction")
        tab.mouse.move(image["x"] + 0.2 * image["width"], image["y"] + 0.5 * image["height"])
        tab.mouse.down()
        tab.mouse.up()
        assert tab.inner_text("#direction") == text
        tab.evaluate("""([x, y]) => {
          const image = document.getElementById('image');
          const at = (type, u, v) => image.dispatchEvent(new PointerEvent(type, {
            pointerId: 7, pointerType: 'touch', isPrimary: true, bubbles: true, clientX: u, clientY: v}));
          at('pointerdown', x, y); at('pointermove', x + 5, y - 5); at('pointerup', x + 5, y - 5);
        }""", [image["x"] + 0.1 * image["width"], image["y"] + 0.5 * image["height"]])
        assert float(tab.inner_text("#direction").split(",")[0]) < -0.5
        assert tab.errors == []


def test_the_triangulation_overlay_shows_the_current_triangle(browser, exported):
    centroid_pixel = """(face) => {  // the disc's pixel at the face's centroid direction, RGB
      const a = whViewer.arrays, d = [0, 0, 0], disc = document.getElementById('disc');
      const r = disc.width / 2 - 4, c = disc.width / 2;
      for (let k = 0; k < 3; k++) for (let i = 0; i < 3; i++) d[i] += a.directions[3 * a.faces[3 * face + k] + i];
      const l = Math.hypot(...d);
      const x = Math.round(c + d[0] / l * r), y = Math.round(c - d[1] / l * r);
      return Array.from(disc.getContext('2d', { willReadFrequently: true }).getImageData(x, y, 1, 1).data.slice(0, 3));
    }"""
    yellowish = lambda rgb: rgb[0] > rgb[2] + 30  # the current triangle's fill over the dark disc
    with served(exported["lowrank"]) as url, opened(browser, url) as tab:
        tab.evaluate("whSetLight(0.3, 0.5, 1.0, 'circular')")
        first = tab.evaluate("whViewer.location.face")
        assert not yellowish(tab.evaluate(centroid_pixel, first))  # no overlay yet
        tab.check("#mesh")
        assert yellowish(tab.evaluate(centroid_pixel, first))
        tab.evaluate("whSetLight(-0.5, -0.2, 1.0, 'circular')")
        second = tab.evaluate("whViewer.location.face")
        assert (second != first and yellowish(tab.evaluate(centroid_pixel, second))
                and not yellowish(tab.evaluate(centroid_pixel, first)))
        assert tab.errors == []


def test_the_single_file_page_opens_from_disk(browser, fields, tmp_path):
    from warp_highlights.cli import main

    page_file = tmp_path / "donut.html"
    assert main(["export", str(fields["lowrank"]), "-o", str(page_file), "--single-file", "-q"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["donut.html"]
    with opened(browser, page_file.as_uri()) as tab:
        _check_page(tab, fields["lowrank"], ["circular"], DIRECTIONS[:2])


def test_the_single_file_page_inlines_the_module_without_clashes(fields):
    """Without a browser: viewer.js is pasted into the page's module, so the two may not declare the
    same top-level name, and the page ends its scripts only where it means to."""
    import re

    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.web.export import _STATIC, single_file_page

    page = single_file_page(load_field(fields["lowrank"])).decode("utf-8")
    assert ('from "./viewer.js"' not in page and page.lower().count("</script") == 2
            and "<!--" not in page.split("<main>")[1])
    declared = lambda text: set(re.findall(r"^(?:export )?(?:async )?(?:const|let|function|class) (\w+)", text,
                                           re.MULTILINE))
    module = (_STATIC / "index.html").read_text().split('<script type="module">')[1]
    shared = declared((_STATIC / "viewer.js").read_text()) & declared(module)
    assert shared == set(), shared


def test_the_arrays_are_gzipped_only_where_that_saves():
    from warp_highlights.web.export import encoded_arrays

    arrays = {"empty": np.zeros((0, 2), "<f4"), "small": np.zeros(100, "<f4"), "zeros": np.zeros(10_000, "<f4"),
              "noise": np.random.default_rng(0).integers(0, 256, 10_000, dtype=np.uint8)}
    manifest = {"arrays": {name: {"file": f"{name}.bin"} for name in arrays}}
    encoded = encoded_arrays(manifest, arrays)
    assert [name for name, spec in manifest["arrays"].items() if spec.get("encoding") == "gzip"] == ["zeros"]
    assert (manifest["arrays"]["zeros"]["file"] == "zeros.bin.gz"
            and gzip.decompress(encoded["zeros"]) == arrays["zeros"].tobytes())
    assert all(encoded[name] == arrays[name].tobytes() for name in ("empty", "small", "noise"))


def test_the_single_file_page_has_a_size_limit(fields, tmp_path, capsys, monkeypatch):
    from warp_highlights.cli import main
    from warp_highlights.web import export

    monkeypatch.setattr(export, "SINGLE_FILE_LIMIT", 1000)
    assert main(["export", str(fields["lowrank"]), "-o", str(tmp_path / "big.html"), "--single-file", "-q"]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "MiB" in line and "without --single-file" in line
    assert list(tmp_path.iterdir()) == []


def test_the_single_file_page_gets_html_added_or_its_suffix_refused(small_field, tmp_path, capsys):
    from warp_highlights.cli import main

    bare = tmp_path / "statue-single"
    assert main(["export", str(small_field), "--single-file", "-o", str(bare), "-q"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote the viewer of {small_field} to {bare}.html (") and f".html added to {bare})" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["statue-single.html"]
    assert (tmp_path / "statue-single.html").read_bytes().lstrip().lower().startswith(b"<!doctype html")
    # a name with .html is kept as it is, and says nothing of it
    assert main(["export", str(small_field), "--single-file", "-o", str(tmp_path / "page.HTML"), "-q"]) == 0
    assert "added" not in capsys.readouterr().out and (tmp_path / "page.HTML").is_file()
    for name in ("statue.png", "statue.v2"):
        assert main(["export", str(small_field), "--single-file", "-o", str(tmp_path / name), "-q"]) == 2
        err = capsys.readouterr().err
        assert err == (f"warp-highlights export: error: -o {tmp_path / name}: --single-file writes an HTML page; give "
                       "a name ending in .html (or no suffix: .html is added)\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page.HTML", "statue-single.html"]


@pytest.mark.parametrize(("signame", "status"), [("SIGINT", 130), ("SIGTERM", 143)])
def test_serve_stopped_says_it_stopped_serving(tmp_path, signame, status):
    """Ctrl-C (or SIGTERM) ends ``serve`` with one line saying what stopped, not that partial output was removed: it
    writes nothing."""
    import os
    import select
    import signal
    import subprocess
    import sys

    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<!doctype html>")
    (site / "manifest.json").write_text("{}")
    process = subprocess.Popen([sys.executable, "-m", "warp_highlights", "serve", str(site), "--port", "0"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        ready, _, _ = select.select([process.stdout], [], [], 120)
        assert ready and "http://127.0.0.1:" in process.stdout.readline()
        process.send_signal(getattr(signal, signame))
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    stopped = f"warp-highlights serve: stopped serving {site}" + (" (SIGTERM)" if signame == "SIGTERM" else "")
    assert (process.returncode, err) == (status, stopped + "\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["site"]


def _read_array(folder, spec) -> np.ndarray:
    data = (folder / spec["file"]).read_bytes()
    data = gzip.decompress(data) if spec.get("encoding") == "gzip" else data
    return np.frombuffer(data, dtype=spec["dtype"]).reshape(spec["shape"])


def test_export_writes_the_manifest_and_arrays_it_names(exported, fields):
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.model.rbf import rbf_kernel, rbf_weights
    from warp_highlights.web.export import WEB_FORMAT

    for kind, folder in exported.items():
        manifest = json.loads((folder / "manifest.json").read_text())
        assert manifest["format"] == "warp-highlights web viewer" and manifest["version"] == WEB_FORMAT
        assert manifest["residual"]["kind"] == {"student": "learned", "rbf": "lowrank"}.get(kind, kind)
        for name, spec in manifest["arrays"].items():
            size = np.dtype(spec["dtype"]).itemsize * int(np.prod(spec["shape"]))
            assert _read_array(folder, spec).nbytes == size, name
        assert (folder / "index.html").is_file() and (folder / "viewer.js").is_file()
    # float16 where the field keeps float16; the colour as its uint8 codes
    manifest = json.loads((exported["images"] / "manifest.json").read_text())
    assert manifest["arrays"]["images"]["dtype"] == "<f2" and manifest["arrays"]["colour"]["dtype"] == "|u1"
    assert json.loads((exported["learned"] / "manifest.json").read_text())["arrays"]["learned_codes"]["dtype"] == "<f2"
    # a smaller decoder's hidden layers padded with zero units to whole vec4s: the same values
    student = json.loads((exported["student"] / "manifest.json").read_text())
    assert student["residual"]["hidden"] == [20, 16]
    assert [student["arrays"][f"learned_{k}"]["shape"] for k in ("w0", "w1", "w2")] == [[20, 12], [16, 20], [3, 16]]
    padded = _read_array(exported["student"], student["arrays"]["learned_w1"])
    kept = load_field(fields["student"]).residual.learned.weights[2]
    np.testing.assert_array_equal(padded[:13], kept)
    assert not padded[13:].any() and not _read_array(exported["student"], student["arrays"]["learned_w2"])[:, 13:].any()
    # a radial basis residual: its width, and (K + lambda I)^-1 over the lights in float64 (model.rbf)
    rbf = json.loads((exported["rbf"] / "manifest.json").read_text())
    sigma = load_field(fields["rbf"]).residual.rbf_sigma
    triangle = json.loads((exported["lowrank"] / "manifest.json").read_text())
    assert rbf["residual"]["rbf_sigma"] == sigma and "rbf_sigma" not in triangle["residual"]
    assert "rbf_inverse" in rbf["arrays"] and "rbf_inverse" not in triangle["arrays"]
    lights = load_field(fields["rbf"]).lights.directions
    inverse = _read_array(exported["rbf"], rbf["arrays"]["rbf_inverse"])  # (n, n): phi(w) times it
    assert inverse.dtype == np.float64 and inverse.shape == (len(lights), len(lights))
    queries = np.array([[0.3, 0.2, 0.93], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(rbf_kernel(queries, lights, sigma) @ inverse, rbf_weights(queries, lights, sigma),
                               atol=1e-8)
    # the packed low-rank codes give back the field's codes
    field, manifest = load_field(fields["lowrank"]), json.loads((exported["lowrank"] / "manifest.json").read_text())
    stack, spec = field.residual.chroma, manifest["arrays"]["chroma_codes"]
    packed = _read_array(exported["lowrank"], spec)  # (G, H, W, 4)
    items = packed.transpose(1, 2, 0, 3).reshape(field.height, field.width, -1)[..., : stack.rank * 2]
    np.testing.assert_array_equal(items.reshape(field.height, field.width, stack.rank, 2),
                                  stack.codes.transpose(1, 2, 0, 3))


def test_export_refuses_bad_output_and_fields_it_cannot_show(small_field, tmp_path, capsys):
    import zipfile

    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import FORMAT_VERSION, load_field
    from warp_highlights.model.errors import InputError
    from warp_highlights.web.export import export_viewer

    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "mine.txt").write_text("keep")
    assert main(["export", str(small_field), "-o", str(taken), "-q"]) == 2
    assert sorted(p.name for p in taken.iterdir()) == ["mine.txt"]
    assert main(["export", str(small_field), "-o", str(tmp_path / "missing" / "viewer"), "-q"]) == 2
    assert main(["export", str(tmp_path / "nothing.whf"), "-o", str(tmp_path / "viewer"), "-q"]) == 2
    newer = tmp_path / "newer.whf"  # a field from a later version of warp-highlights
    with zipfile.ZipFile(small_field) as source, zipfile.ZipFile(newer, "w") as target:
        for info in source.infolist():
            data = source.read(info)
            if info.filename == "header.json":
                data = json.dumps({**json.loads(data), "format_version": FORMAT_VERSION + 1}).encode()
            target.writestr(info, data)
    assert main(["export", str(newer), "-o", str(tmp_path / "viewer"), "-q"]) == 2
    assert main(["export", str(newer), "-o", str(tmp_path / "viewer.html"), "--single-file", "-q"]) == 2
    assert not (tmp_path / "viewer").exists() and not (tmp_path / "viewer.html").exists()
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 5 and all(line.startswith("warp-highlights export: error:") for line in lines)
    assert "newer" in lines[3]
    field = load_field(small_field)
    with pytest.raises(InputError, match="needs a field with a residual"):
        export_viewer(dataclasses.replace(field, residual=None), tmp_path)


def test_serve_listens_on_this_computer_only(exported, tmp_path):
    from warp_highlights.model.errors import InputError
    from warp_highlights.web.serve import HOST, make_server

    server = make_server(exported["lowrank"], 0)
    try:
        assert HOST == "127.0.0.1" and server.server_address[0] == "127.0.0.1"
    finally:
        server.server_close()
    with pytest.raises(InputError, match="not an exported viewer"):
        make_server(tmp_path, 0)
