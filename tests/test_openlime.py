"""export --format openlime: relight's web layout written, relit here with OpenLIME's formulas, and opened by
OpenLIME itself (1.2.6, ../shared/tools/openlime, GPL-3.0: served to the browser from a temporary folder,
never part of the project) in headless Chromium."""

from __future__ import annotations

import dataclasses
import functools
import http.server
import json
import math
import os
import shutil
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from conftest import sample_data_root, smooth_plate, write_capture
from warp_highlights.cli import main
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.images import linear_to_srgb
from warp_highlights.quality.metrics import psnr_8bit
from warp_highlights.relight.baselines import fit_baseline
from warp_highlights.web.openlime import (
    OPENLIME_MODELS,
    export_openlime,
    export_openlime_neural,
    openlime_weights,
    relight_openlime,
)

OPENLIME = Path(os.environ.get("WARP_HIGHLIGHTS_OPENLIME", sample_data_root().parent / "tools" / "openlime"))
# the light (x, y) of the page tests; OpenLIME takes z = sqrt(1 - x^2 - y^2)
PAGE_LIGHTS = [(0.3, 0.5), (-0.5, 0.2), (0.1, -0.7), (0.0, 0.0), (-0.6, -0.6)]
# the keys OpenLIME's RTI shader may receive: it copies every info.json key onto itself, so a stray one breaks it
RTI_KEYS = {"width", "height", "format", "type", "colorspace", "nplanes", "lights", "materials", "basis", "quality"}


def _rgb8(values) -> np.ndarray:
    return np.round(255.0 * np.clip(values, 0.0, 1.0)).astype(np.uint8)


def _lit(xy) -> np.ndarray:
    x, y = xy
    return np.array([x, y, math.sqrt(max(0.0, 1.0 - x * x - y * y))])


@pytest.mark.parametrize(("model", "method"), [("ptm", "ptm"), ("hsh", "hsh3")])
def test_ptm_and_hsh_exports_relight_as_the_baselines_do(tmp_path, model, method):
    values, lights = smooth_plate()
    info = export_openlime(values, lights, tmp_path, model=model)
    assert set(info) <= RTI_KEYS and info["nplanes"] == {"ptm": 18, "hsh": 27}[model]
    jpegs = sorted(p.name for p in tmp_path.glob("plane_*.jpg"))
    assert jpegs == [f"plane_{j}.jpg" for j in range(info["nplanes"] // 3)]
    queries = np.array([_lit(xy) for xy in PAGE_LIGHTS])
    baseline = fit_baseline(method, values, lights, device="cpu").relight(queries)
    relit = relight_openlime(tmp_path, queries)
    # the same least-squares model (the same span of the basis), apart from the planes' 8-bit quantisation
    assert min(psnr_8bit(_rgb8(a), _rgb8(b)) for a, b in zip(relit, baseline)) >= 45.0


def test_hsh_weights_use_openlimes_constants():
    weights = openlime_weights("hsh", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    assert weights[0, 0] == pytest.approx(1 / math.sqrt(2 * 3.1415))
    assert weights[0, 2] == pytest.approx(math.sqrt(3 / (2 * 3.1415)))  # theta 0: cos 1
    theta = 3.1415 / 2 - 0.15  # the horizon clamped, as OpenLIME does
    assert weights[1, 2] == pytest.approx(math.sqrt(3 / (2 * 3.1415)) * (2 * math.cos(theta) - 1))
    np.testing.assert_allclose(weights[2, 1:4:2] / weights[2, 1], [1.0, 4 / 3])  # (x, y) beyond 1 scaled to unit length
    np.testing.assert_allclose(openlime_weights("ptm", [[0.6, 0.0, 0.8]])[0], [1, 0.6, 0, 0.36, 0, 0])


def test_rbf_export_with_every_component_is_the_adaptive_blend_of_the_images(tmp_path):
    values, lights = smooth_plate(count=12, height=20, width=14)
    info = export_openlime(values, lights, tmp_path, model="rbf", planes=36)
    assert set(info) <= RTI_KEYS and info["colorspace"] == "mrgb" and info["nplanes"] == 36
    assert len(info["basis"]) == 37 * 12 * 3 and min(info["basis"]) >= 0 and max(info["basis"]) <= 255
    queries = np.array([_lit(xy) for xy in PAGE_LIGHTS])
    weights = openlime_weights("rbf", queries, info=info)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    blend = np.einsum("qn,nhwc->qhwc", weights, values.astype(np.float64))
    relit = relight_openlime(tmp_path, queries)
    assert min(psnr_8bit(_rgb8(a), _rgb8(b)) for a, b in zip(relit, blend)) >= 40.0


def test_export_openlime_command_writes_the_folder_and_refuses_a_field(tmp_path, small_field, capsys):
    capture = write_capture(tmp_path / "capture", *smooth_plate(count=20, height=24, width=16))
    assert main(["export", str(capture), "-o", str(tmp_path / "ptm"), "--format", "openlime", "--model", "ptm"]) == 0
    assert "for OpenLIME" in capsys.readouterr().out
    info = json.loads((tmp_path / "ptm" / "info.json").read_text())
    assert (info["type"], info["width"], info["height"]) == ("ptm", 16, 24)  # size is (H, W)
    assert main(["export", str(capture), "-o", str(tmp_path / "ptm"), "--format", "openlime"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["export", str(small_field), "-o", str(tmp_path / "no"), "--format", "openlime"]) == 2
    error = capsys.readouterr().err.strip()
    assert "give the capture folder" in error and "\n" not in error and not (tmp_path / "no").exists()
    for options, needle in ((["--model", "ptm"], "--model does not apply to --format page"),
                            (["--format", "openlime", "--single-file"], "--single-file does not apply"),
                            (["--format", "openlime", "--model", "ptm", "--seconds", "5"], "--model neural only"),
                            (["--format", "openlime", "--model", "neural", "--seconds", "0"], "positive number")):
        assert main(["export", str(capture), "-o", str(tmp_path / "no"), *options]) == 2
        assert needle in capsys.readouterr().err


# --- a learned residual as OpenLIME's neural layer ------------------------------------------------

NEURAL_KEYS = {"width", "height", "format", "type", "quality", "planes", "samples", "colorspace", "min", "max",
               "weights", "biases"}


@pytest.fixture(scope="module")
def learned_field(small_learned_field):
    """The small donut fitted with a learned residual: (field, path) (``conftest.small_learned_field``)."""
    return small_learned_field


def _with_decoder(field, kind: str):
    """``field`` with a learned decoder of code and direction only ("plain": w0's first 12 columns), or one that sees
    the highlights ("seeing": as fitted where it does, else w0's 12 columns and two non-zero ones for sqrt(g), g)."""
    import dataclasses

    learned = field.residual.learned
    w0 = learned.weights[0][:, :12]
    if kind == "seeing":
        w0 = (learned.weights[0] if learned.sees_highlights else
              np.concatenate([w0, np.random.default_rng(6).normal(0.0, 0.5, (len(w0), 2)).astype(np.float32)], axis=1))
    learned = dataclasses.replace(learned, weights=(w0, *learned.weights[1:]))
    assert learned.sees_highlights == (kind == "seeing")
    return dataclasses.replace(field, residual=dataclasses.replace(field.residual, learned=learned))


@pytest.fixture(scope="module", params=["plain", "seeing"])
def neural_export(learned_field, tmp_path_factory, request):
    """``learned_field`` with a decoder of code and direction only, or one that sees the highlights, exported as
    OpenLIME's neural layer (a 20-18 decoder, 40 epochs): (field, folder, info, figures, log lines)."""
    from warp_highlights.model.config import DistilSettings

    field = _with_decoder(learned_field[0], request.param)
    folder = tmp_path_factory.mktemp("neural")
    lines = []
    info, figures = export_openlime_neural(field, folder, hidden=(20, 18),
                                           settings=DistilSettings(epochs=40, seconds=0), log=lines.append)
    return field, folder, info, figures, lines


def test_neural_export_writes_openlimes_layout_and_relights_as_the_field(neural_export):
    """The folder relit here against the field's learned image as shown; a decoder that sees the highlights is
    distilled from its relit image (g of the Gaussians moved to each light), and the export says in one line that
    OpenLIME's highlights cross-fade."""
    from warp_highlights.relight.relighter import Relighter
    from warp_highlights.residual.cpu_training import CpuDecoder
    from warp_highlights.residual.opponent import decode_display
    from warp_highlights.web.openlime import SEEING_NOTE

    field, folder, info, figures, lines = neural_export
    assert set(info) == NEURAL_KEYS and info["planes"] == 9 and info["samples"] == 20  # 18 padded to 20 too
    assert sorted(p.name for p in folder.glob("plane_*.jpg")) == ["plane_1.jpg", "plane_2.jpg", "plane_3.jpg"]
    assert [len(w) for w in info["weights"]] == [20 * 12, 20 * 20, 3 * 20]
    assert [len(b) for b in info["biases"]] == [20, 20, 3]
    second, third = np.asarray(info["weights"][1]).reshape(20, 20), np.asarray(info["weights"][2]).reshape(3, 20)
    assert not second[18:].any() and not third[:, 18:].any() and not info["biases"][1][18]  # padded units: zero
    # the folder relit here against the field's learned residual as shown (sRGB of the residual over the exposure)
    learned = field.residual.learned
    teacher = CpuDecoder(learned.codes.reshape(-1, 9).astype(np.float32), learned.weights)
    upper = field.lights.directions[field.lights.directions[:, 2] > 0]
    g = None
    if learned.sees_highlights:  # the moved Gaussians' luminance, display units
        relighter = Relighter(dataclasses.replace(field, residual=None), device="cpu", diffuse="none")
        g = relighter.relight(upper, full=False).specular.reshape(len(upper), -1) / np.float32(learned.unit)
    values = decode_display(teacher.decode(upper.astype(np.float32), highlights=g)) * np.float32(learned.unit)
    values = learned.within_bounds(values.reshape(len(upper), field.height, field.width, 3))
    shown = linear_to_srgb(np.clip(values / field.exposure, 0, 1))
    mine = relight_openlime(folder, upper)
    score = np.mean([psnr_8bit(_rgb8(a), _rgb8(b)) for a, b in zip(mine, shown)])
    # a teacher that sees the highlights gives the whole image, its moving highlights cross-fading in OpenLIME's shape
    least = 27.0 if learned.sees_highlights else 30.0
    assert figures["captured_psnr_db"] >= least and figures["between_psnr_db"] >= least, figures
    assert score == pytest.approx(figures["captured_psnr_db"], abs=0.5)  # the folder decodes as the export measured
    if learned.sees_highlights:
        assert figures["note"] == SEEING_NOTE and lines[-1] == SEEING_NOTE and "\n" not in SEEING_NOTE
        assert "cross-fade" in SEEING_NOTE
    else:
        assert "note" not in figures and SEEING_NOTE not in lines


def test_export_neural_command_says_what_it_kept_and_refuses_what_it_cannot_show(learned_field, small_field,
                                                                                tmp_path, capsys):
    _, path = learned_field
    assert main(["export", str(path), "-o", str(tmp_path / "n"), "--format", "openlime", "--model", "neural",
                 "--seconds", "2", "-q"]) == 0
    out = capsys.readouterr().out
    assert "OpenLIME's neural layer" in out and "decoder 48-48" in out and "cannot draw the field's moving" in out
    assert json.loads((tmp_path / "n" / "info.json").read_text())["samples"] == 48
    for source, needle in ((small_field, "a lowrank residual"), (path.parent, "give the field file")):
        assert main(["export", str(source), "-o", str(tmp_path / "no"), "--format", "openlime", "--model",
                     "neural"]) == 2
        error = capsys.readouterr().err.strip()
        assert needle in error and "\n" not in error and not (tmp_path / "no").exists()


# --- OpenLIME itself, in headless Chromium --------------------------------------------------------

PAGE = (Path(__file__).parent / "data" / "openlime-page.html").read_text()
"""A bare page of OpenLIME's viewer over ``data/info.json``: ``window.relightAt(x, y)`` sets the light and gives the
canvas's RGBA bytes (benchmarks/bench_openlime.py --page uses it too)."""


@pytest.fixture(scope="module")
def openlime_js() -> Path:
    """OpenLIME's bundle (skips where it is absent)."""
    if not (OPENLIME / "openlime.min.js").is_file():
        pytest.skip(f"OpenLIME not found at {OPENLIME} (set WARP_HIGHLIGHTS_OPENLIME)")
    return OPENLIME / "openlime.min.js"


@contextmanager
def openlime_page(browser, openlime_js: Path, export: Path, site: Path):
    """OpenLIME's page over ``export`` (copied with OpenLIME into ``site``), served on 127.0.0.1 and loaded; the
    tab's console errors in ``tab.errors``."""
    site.mkdir()
    shutil.copy(openlime_js, site)
    shutil.copytree(export, site / "data")
    (site / "index.html").write_text(PAGE)
    handler = functools.partial(_QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    tab = browser.new_page()
    tab.errors = []
    tab.on("console", lambda message: tab.errors.append(message.text) if message.type == "error" else None)
    tab.on("pageerror", lambda error: tab.errors.append(str(error)))
    try:
        tab.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        tab.wait_for_function("window.olReady === true", timeout=60_000)
        yield tab
    finally:
        tab.close()
        server.shutdown()
        server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # no request lines in the test output
        pass


def page_scores(tab, export: Path) -> list[float]:
    """8-bit PSNR (dB) of OpenLIME's canvas against ``relight_openlime`` at each of ``PAGE_LIGHTS``."""
    info = json.loads((export / "info.json").read_text())
    expected = relight_openlime(export, np.array([_lit(xy) for xy in PAGE_LIGHTS]))
    scores = []
    for (x, y), reference in zip(PAGE_LIGHTS, expected):
        canvas = np.array(tab.evaluate(f"relightAt({x}, {y})"), np.uint8).reshape(info["height"], info["width"], 4)
        scores.append(psnr_8bit(canvas[..., :3], _rgb8(reference)))
    return scores


SAMPLES = {"dome": ("synthrti-object1-material5/Dome", (96, 96)), "statue": ("realrti-item11", (96, 90))}


@pytest.fixture(scope="module")
def sample_values(data_root):
    """Each sample's display values at a small size, with its lights."""
    from warp_highlights.io.resample import resize_stack

    loaded = {}
    for name, (folder, size) in SAMPLES.items():
        field = ReflectanceField.load(data_root / folder)
        loaded[name] = (linear_to_srgb(np.clip(resize_stack(field.images, *size), 0, 1)), field.lights.directions)
    return loaded


@pytest.mark.realdata
@pytest.mark.parametrize("sample", sorted(SAMPLES))
@pytest.mark.parametrize("model", OPENLIME_MODELS)
def test_openlime_shows_the_samples_as_relit_here(browser, openlime_js, sample_values, sample, model, tmp_path):
    values, lights = sample_values[sample]
    export = tmp_path / "export"
    export.mkdir()
    export_openlime(values, lights, export, model=model)
    with openlime_page(browser, openlime_js, export, tmp_path / "site") as tab:
        scores = page_scores(tab, export)
        assert not tab.errors, tab.errors
    # OpenLIME shows its value through pow(v, 2.2), an 8-bit buffer and pow(v, 1 / 2.2): dark levels are coarser
    assert min(scores) >= 35.0, scores


def test_openlime_shows_the_neural_layer_as_relit_here(browser, openlime_js, neural_export, tmp_path):
    _, folder, _, _, _ = neural_export
    with openlime_page(browser, openlime_js, folder, tmp_path / "site") as tab:
        scores = page_scores(tab, folder)
        assert not tab.errors or all(error.startswith("fps slow") for error in tab.errors), tab.errors
    assert min(scores) >= 30.0, scores
