"""`warp-highlights relight`, `animate`, `evaluate` and `demo` end to end, and their bad input."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from warp_highlights.cli import main
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.io.images import read_image
from warp_highlights.io.lightfile import read_lp, write_lp
from warp_highlights.model.lights import LightSet

LIGHT = "0.3,0.5,1"


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err, "no error message"
    assert err.count("\n") == 0, err
    assert "Traceback" not in err
    return err


def _tree(folder: Path) -> list[str]:
    """Everything under ``folder``, hidden temporary files included."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture(scope="module")
def field(small_field):
    return load_field(small_field)


def _relighter(field, **options):
    from warp_highlights.relight.relighter import Relighter

    return Relighter(field, device="cpu", scale=1.0 / float(field.report.get("exposure") or 1.0), **options)


# --- relight ---------------------------------------------------------------------------------------


def test_relight_one_light_to_exr_equals_the_relighter(small_field, field, tmp_path, capsys):
    out = tmp_path / "relit.exr"
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--device", "cpu", "-q"]) == 0
    assert "wrote" in capsys.readouterr().out
    image = read_image(out)
    assert image.shape == (field.height, field.width, 3)
    expected = _relighter(field).relight(np.array([0.3, 0.5, 1.0])).full
    np.testing.assert_allclose(image, expected, rtol=1e-6, atol=1e-7)
    assert image.max() > 0.05  # something is lit


def test_relight_to_png_is_the_same_image_in_srgb(small_field, field, tmp_path):
    out = tmp_path / "relit.png"
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--device", "cpu", "-q"]) == 0
    image = read_image(out)
    assert image.shape == (field.height, field.width, 3)
    expected = np.clip(_relighter(field).relight(np.array([0.3, 0.5, 1.0])).full, 0.0, 1.0)
    np.testing.assert_allclose(image, expected, atol=0.01)


def test_relight_at_double_size(small_field, field, tmp_path):
    out = tmp_path / "big.exr"
    size = f"{2 * field.width}x{2 * field.height}"
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--size", size, "--device", "cpu",
                 "-q"]) == 0
    image = read_image(out)
    assert image.shape == (2 * field.height, 2 * field.width, 3)
    expected = _relighter(field, size=(2 * field.width, 2 * field.height)).relight(np.array([0.3, 0.5, 1.0])).full
    np.testing.assert_allclose(image, expected, rtol=1e-6, atol=1e-7)


def test_a_large_relight_counts_its_memory_and_says_its_time(small_field, field, tmp_path):
    """Relit at 20 times the field's width: the peak memory of the command grows, from one at the field's size,
    by no more than its up-front estimate (``relight_bytes``); the line gives the command's time."""
    import subprocess
    import sys

    from warp_highlights.relight.relighter import relight_bytes

    width, height = 20 * field.width, 20 * field.height
    script = ("import resource, sys\n"
              "from warp_highlights.cli import main\n"
              "field, out, size = sys.argv[1:4]\n"
              "arguments = ['relight', field, '--light', '0.3,0.5,1', '--size', size, '-o', out, '--device', 'cpu']\n"
              "assert main(arguments) == 0\n"
              "print('peak', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n")

    def run(size: str, name: str) -> tuple[int, str]:
        done = subprocess.run([sys.executable, "-c", script, str(small_field), str(tmp_path / name), size],
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        return 1024 * int(done.stdout.split("peak")[1]), done.stdout

    run(f"{field.width}x{field.height}", "warm.png")  # compiles any kernel not in the cache yet
    small, _ = run(f"{field.width}x{field.height}", "small.png")
    big, out = run(f"{width}x{height}", "big.png")
    estimate = relight_bytes(field, width, height)
    assert big - small <= 1.1 * estimate, (big - small, estimate)
    line = [text for text in out.splitlines() if text.startswith("wrote")][-1]
    assert re.search(rf"\({width}x{height}, circular, [0-9.]+ s: relit in [0-9.]+ ms, written in [0-9.]+ ms\)", line)
    assert read_image(tmp_path / "big.png").shape == (height, width, 3)


def test_a_large_relight_shows_its_stages(small_field, field, tmp_path, capsys, monkeypatch):
    import warp_highlights.cli.relight as relight_cli

    size = f"{2 * field.width}x{2 * field.height}"
    monkeypatch.setattr(relight_cli, "STAGE_BAR_PIXELS", 4 * field.width * field.height)
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(tmp_path / "a.png"), "--size", size,
                 "--device", "cpu"]) == 0
    err = capsys.readouterr().err
    assert all(stage in err for stage in ("relight: preparing", "relight: relighting", "relight: writing")), err
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(tmp_path / "b.png"), "--size", size,
                 "--device", "cpu", "-q"]) == 0
    assert "relight:" not in capsys.readouterr().err


def test_relight_specular_only(small_field, field, tmp_path):
    out = tmp_path / "spec.exr"
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--specular-only", "--device", "cpu",
                 "-q"]) == 0
    image = read_image(out)
    assert image.shape == (field.height, field.width)
    relit = _relighter(field).relight(np.array([0.3, 0.5, 1.0]), full=False)
    np.testing.assert_allclose(image, relit.specular / float(field.report.get("exposure") or 1.0), rtol=1e-6, atol=1e-7)
    assert image.max() > 0.05 and np.mean(image > 1e-3) < 0.5  # a highlight, not a diffuse shading


def _check_folder(out: Path, field, directions: np.ndarray, *, method: str = "circular") -> None:
    names = [f"relit_{i:04d}.exr" for i in range(len(directions))]
    assert sorted(p.name for p in out.iterdir()) == sorted(names + ["lights.lp", ".warp-highlights.json"])
    lights = read_lp(out / "lights.lp")  # checks the named images exist
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    np.testing.assert_allclose(lights.directions, unit, atol=1e-5)
    assert [Path(n).name for n in lights.filenames] == names
    expected = _relighter(field).relight(directions, method=method).full
    for i, name in enumerate(names):
        np.testing.assert_allclose(read_image(out / name), expected[i], rtol=1e-6, atol=1e-7)


def test_relight_two_lights_into_a_folder(small_field, field, tmp_path, capsys):
    out = tmp_path / "two"
    assert main(["relight", str(small_field), "--light", LIGHT, "--light=-2,0,1", "-o", str(out), "--device", "cpu",
                 "-q"]) == 0
    assert "2 images" in capsys.readouterr().out
    _check_folder(out, field, np.array([[0.3, 0.5, 1.0], [-2.0, 0.0, 1.0]]))
    assert (_tree(tmp_path)
            == ["two", *(f"two/{n}"
                         for n in (".warp-highlights.json", "lights.lp", "relit_0000.exr", "relit_0001.exr"))])


def test_relight_a_light_with_a_negative_first_coordinate(small_field, tmp_path):
    # a light on the left, written the way the help shows (--light X,Y,Z): argparse must not take it for an option
    out = tmp_path / "left.exr"
    try:
        status = main(["relight", str(small_field), "--light", "-0.5,0.2,1", "-o", str(out), "--device", "cpu", "-q"])
    except SystemExit as stop:  # argparse: "argument --light: expected one argument"
        status = f"argparse exit {stop.code}"
    assert status == 0
    assert out.is_file()


def test_relight_a_light_file_and_a_light(small_field, field, tmp_path):
    lp = tmp_path / "query.lp"
    directions = np.array([[0.0, 0.0, 2.0], [1.0, 1.0, 0.5], [0.0, -1.0, 0.2]])
    write_lp(LightSet(directions / np.linalg.norm(directions, axis=1, keepdims=True)), lp)
    out = tmp_path / "many"
    assert main(["relight", str(small_field), "--light", LIGHT, "--lights", str(lp), "-o", str(out), "--device", "cpu",
                 "-q"]) == 0
    _check_folder(out, field, np.concatenate([[[0.3, 0.5, 1.0]], directions]))
    # and again with --overwrite, fewer lights: the old images go
    assert main(["relight", str(small_field), "--lights", str(lp), "-o", str(out), "--overwrite", "--device", "cpu",
                 "-q"]) == 0
    _check_folder(out, field, directions)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_relight_alpha_needs_the_dataset(small_field, tmp_path, capsys):
    out = tmp_path / "alpha.exr"
    assert main(["relight", str(small_field), "--light", LIGHT, "--method", "alpha", "-o", str(out), "--device", "cpu",
                 "-q"]) == 2
    assert "--dataset" in _error_line(capsys)
    assert _tree(tmp_path) == []


def test_relight_alpha_with_the_dataset(small_field, small_donut, field, tmp_path):
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.relight.relighter import alpha_inputs

    out = tmp_path / "alpha.exr"
    assert main(["relight", str(small_field), "--light", LIGHT, "--method", "alpha", "--dataset", str(small_donut),
                 "-o", str(out),
                 "--device", "cpu", "-q"]) == 0
    specular, images = alpha_inputs(field, ReflectanceField.load(small_donut, progress=False), device="cpu")
    expected = _relighter(field, alpha_specular=specular, alpha_images=images).relight(np.array([0.3, 0.5, 1.0]),
                                                                                       method="alpha").full
    image = read_image(out)
    np.testing.assert_allclose(image, expected, rtol=1e-3, atol=1e-3)  # the images are blended as float16
    circular = _relighter(field).relight(np.array([0.3, 0.5, 1.0])).full
    assert np.abs(image - circular).max() > 1e-3  # a different method


def test_relight_alpha_at_a_light_gives_its_captured_image(small_donut, tmp_path):
    """With a field fitted with an exposure, --method alpha still writes the dataset's units."""
    from conftest import FAST_FIT
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.resample import resize_stack
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    field = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT), device="cpu", diffuse="images",
                      exposure=2.0,
                      size=(48, 27), progress=False)
    path = tmp_path / "exposed.whf"
    save_field(field, path)
    light = 5
    direction = ",".join(f"{v:.17g}" for v in dataset.lights.directions[light])
    captured = resize_stack(dataset.images, 48, 27)[light]
    for method in ("circular", "alpha"):
        out = tmp_path / f"{method}.exr"
        assert main(["relight", str(path), f"--light={direction}", "--method", method, "--dataset", str(small_donut),
                     "-o", str(out),
                     "--device", "cpu", "-q"]) == 0
        image = read_image(out)
        ratio = image.sum() / captured.sum()
        assert ratio == pytest.approx(1.0, abs=0.05), (method, ratio)
    np.testing.assert_allclose(image, captured, rtol=2e-3, atol=1e-4)  # alpha at a light: that light's image


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["--light", "0.3,up,1", "-o", "x.png"], "is not X,Y,Z numbers"),
        (["--light", "0.3,1", "-o", "x.png"], "needs 3 numbers"),
        (["--light", "0,0,0", "-o", "x.png"], "non-zero"),
        (["--light", "nan,0,1", "-o", "x.png"], "finite"),
        (["--light", LIGHT, "--light", "0,0,1", "-o", "x.png"], "give -o a folder name"),
        (["--light", LIGHT, "-o", "x"], "image suffix"),
        (["-o", "x.png"], "at least one light"),
        (["--light", LIGHT, "-o", "x.png", "--size", "100x100"], "aspect ratio"),
        (["--light", LIGHT, "-o", "x.png", "--size", "big"], "WIDTHxHEIGHT"),
        (["--light", LIGHT, "-o", "x.png", "--specular-colour", "1,2"], "1 or 3 numbers"),
        (["--light", LIGHT, "-o", "no/such/folder/x.png"], "does not exist"),
    ],
)
def test_relight_bad_input_is_one_line_and_writes_nothing(small_field, tmp_path, monkeypatch, capsys, arguments,
                                                          expected):
    monkeypatch.chdir(tmp_path)
    assert main(["relight", str(small_field), *arguments, "--device", "cpu", "-q"]) == 2
    assert expected in _error_line(capsys)
    assert _tree(tmp_path) == []


def test_relight_keeps_an_existing_output(small_field, tmp_path, capsys):
    out = tmp_path / "relit.png"
    out.write_bytes(b"precious")
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--device", "cpu", "-q"]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert out.read_bytes() == b"precious" and _tree(tmp_path) == ["relit.png"]
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "keep.txt").write_text("x")
    assert main(["relight", str(small_field), "--light", LIGHT, "--light", "0,0,1", "-o", str(folder), "--device",
                 "cpu", "-q"]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert _tree(folder) == ["keep.txt"]


def test_relight_on_a_device_that_is_not_there(small_field, tmp_path, capsys):
    out = tmp_path / "relit.png"
    assert main(["relight", str(small_field), "--light", LIGHT, "-o", str(out), "--device", "cuda:97", "-q"]) == 2
    assert "cuda:97" in _error_line(capsys)
    assert _tree(tmp_path) == []


def test_relight_a_missing_field(tmp_path, capsys):
    out = tmp_path / "relit.png"
    assert main(["relight", str(tmp_path / "nope.whf"), "--light", LIGHT, "-o", str(out), "--device", "cpu", "-q"]) == 2
    assert "nope.whf" in _error_line(capsys)
    assert _tree(tmp_path) == []


# --- animate ---------------------------------------------------------------------------------------


def test_animate_an_orbit_to_a_gif(small_field, field, tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "orbit.gif"
    assert main(["animate", str(small_field), "--path", "orbit:30", "--frames", "6", "-o", str(out), "--device", "cpu",
                 "-q"]) == 0
    assert "6 frames" in capsys.readouterr().out
    with Image.open(out) as gif:
        assert gif.n_frames == 6 and gif.size == (field.width, field.height)
        frames = []
        for i in range(6):
            gif.seek(i)
            frames.append(np.asarray(gif.convert("RGB"), dtype=np.float64))
    assert np.abs(frames[0] - frames[3]).max() > 10  # the light moves: the frames differ


def test_animate_to_a_folder_of_frames(small_field, field, tmp_path):
    out = tmp_path / "frames"
    assert main(["animate", str(small_field), "--path", "orbit:30", "--frames", "6", "-o", str(out), "--device", "cpu",
                 "-q"]) == 0
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert len(names) == 6 and all(n.endswith(".png") for n in names)
    from warp_highlights.view.light_paths import orbit

    expected = np.clip(_relighter(field).relight(orbit(30, 6)).full, 0, 1)
    for i, name in enumerate(names):
        image = read_image(out / name)
        assert image.shape == (field.height, field.width, 3)
        np.testing.assert_allclose(image, expected[i], atol=0.01)


def test_animate_compare_puts_the_methods_side_by_side(small_field, field, tmp_path):
    from PIL import Image

    out = tmp_path / "compare.gif"
    assert main(["animate", str(small_field), "--path", "great:1,0,1:-1,0,1", "--frames", "4", "--compare", "--methods",
                 "circular,straight",
                 "-o", str(out), "--device", "cpu", "-q"]) == 0
    with Image.open(out) as gif:
        assert gif.n_frames == 4 and gif.size == (2 * field.width, field.height)


def test_animate_a_great_circle_to_exr_frames(small_field, field, tmp_path):
    from warp_highlights.view.light_paths import great_circle

    out = tmp_path / "arc"
    assert main(["animate", str(small_field), "--path", "great:1,0,1:-1,0,1", "--frames", "3", "--exr",
                 "--specular-only", "-o", str(out),
                 "--device", "cpu", "-q"]) == 0
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert len(names) == 3 and all(n.endswith(".exr") for n in names)
    expected = _relighter(field).relight(great_circle([1, 0, 1], [-1, 0, 1], 3), full=False).specular
    for i, name in enumerate(names):
        np.testing.assert_allclose(read_image(out / name), expected[i], rtol=1e-6, atol=1e-7)


def test_animate_compare_with_the_alpha_blend(small_field, small_donut, field, tmp_path):
    out = tmp_path / "compare"
    assert main(["animate", str(small_field), "--path", "orbit:30", "--frames", "2", "--compare", "--dataset",
                 str(small_donut), "--exr",
                 "--specular-only", "-o", str(out), "--device", "cpu", "-q"]) == 0
    frames = [read_image(p) for p in sorted(out.glob("frame_*"))]
    assert len(frames) == 2 and frames[0].shape == (field.height, 2 * field.width)
    from warp_highlights.view.light_paths import orbit

    circular = _relighter(field).relight(orbit(30, 2), full=False).specular
    np.testing.assert_allclose(frames[1][:, : field.width], circular[1], rtol=1e-6, atol=1e-7)  # left: circular
    assert np.abs(frames[1][:, field.width :] - circular[1]).max() > 1e-3  # right: the alpha blend


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["--path", "spiral:3", "-o", "x.gif"], "unknown kind"),
        (["--path", "orbit:120", "-o", "x.gif"], "[-90, 90]"),
        (["--path", "great:1,0,0:-1,0,0", "-o", "x.gif"], "great"),
        (["--path", "orbit:30", "-o", "x.avi"], ".avi"),
        (["--path", "orbit:30", "-o", "x.gif", "--frames", "0"], "--frames"),
        (["--path", "orbit:30", "-o", "x.gif", "--compare"], "--dataset"),  # default methods circular,alpha
        (["--path", "orbit:30", "-o", "x.gif", "--compare", "--methods", "circular,cubic"], "methods"),
        (["--path", "orbit:30", "-o", "x.gif", "--method", "alpha"], "--dataset"),
    ],
)
def test_animate_bad_input_is_one_line_and_writes_nothing(small_field, tmp_path, monkeypatch, capsys, arguments,
                                                          expected):
    monkeypatch.chdir(tmp_path)
    assert main(["animate", str(small_field), "--frames", "3", *arguments, "--device", "cpu", "-q"]) == 2
    assert expected in _error_line(capsys)
    assert _tree(tmp_path) == []


def test_animate_compare_without_the_dataset_speaks_of_what_was_given(small_field, tmp_path, capsys):
    for methods, shown in (([], "circular,alpha"), (["--methods", "alpha,straight"], "alpha,straight")):
        assert main(["animate", str(small_field), "--path", "orbit:30", "--frames", "2", "--compare", *methods, "-o",
                     str(tmp_path / "x.gif"), "--device", "cpu", "-q"]) == 2
        line = _error_line(capsys)
        assert f"--compare shows each method of --methods ({shown}), and alpha blends the captured images" in line
        assert "--dataset DATASET" in line and "--methods without alpha" in line and "--method alpha" not in line
    assert _tree(tmp_path) == []


# --- lights outside the dome -----------------------------------------------------------------------


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if "warning:" in line]


def test_relight_outside_the_dome_says_so_on_stderr_even_with_q(tmp_path, capsys):
    field = load_field(LEGACY_FIELD)
    assert field.triangulation.is_dome
    out = tmp_path / "behind.exr"
    assert main(["relight", str(LEGACY_FIELD), "--light", "0,0,-1", "-o", str(out), "--device", "cpu", "-q"]) == 0
    captured = capsys.readouterr()
    assert "(outside the dome: moved onto its rim)" in captured.out
    [line] = _warnings(captured.err)
    assert captured.err.count("\n") == 1
    rim = field.triangulation.locate(np.array([0.0, 0.0, -1.0])).directions
    text = ",".join(f"{v + 0.0:.3f}" for v in np.round(rim, 3))
    assert line == (f"  warning: the light 0.000,0.000,-1.000 lies outside the captured lights: moved onto the "
                     f"dome's rim, to {text} (x,y,z); the image is that of the nearest captured direction on the rim")
    # the image is the one at that rim direction
    moved = tmp_path / "rim.exr"
    assert main(["relight", str(LEGACY_FIELD), "--light", ",".join(f"{v:.17g}" for v in rim), "-o", str(moved),
                 "--device", "cpu", "-q"]) == 0
    assert _warnings(capsys.readouterr().err) == []
    np.testing.assert_allclose(read_image(out), read_image(moved), atol=1e-5)
    # a light inside: no warning, no note
    assert main(["relight", str(LEGACY_FIELD), "--light", "0.1,0.2,1", "-o", str(tmp_path / "in.exr"), "--device",
                 "cpu", "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and "outside the dome" not in captured.out


def test_relight_lights_and_animate_outside_the_dome_count_them_in_one_line(tmp_path, capsys):
    lp = tmp_path / "query.lp"
    directions = np.array([[0.0, 0.0, -1.0], [0.1, 0.2, 1.0], [1.0, 0.0, -0.2]])
    write_lp(LightSet(directions / np.linalg.norm(directions, axis=1, keepdims=True)), lp)
    assert main(["relight", str(LEGACY_FIELD), "--lights", str(lp), "-o", str(tmp_path / "many"), "--device", "cpu",
                 "-q"]) == 0
    assert _warnings(capsys.readouterr().err) == [
        "  warning: 2 of 3 lights lie outside the captured lights: moved onto the dome's rim, relit as the nearest "
        "captured directions on the rim"]
    # an orbit below the horizon: every frame
    assert main(["animate", str(LEGACY_FIELD), "--path", "orbit:-30", "--frames", "4", "-o", str(tmp_path / "below"),
                 "--device", "cpu", "-q"]) == 0
    assert _warnings(capsys.readouterr().err) == [
        "  warning: the light of 4 of 4 frames lies outside the captured lights: moved onto the dome's rim, relit as "
        "the nearest captured directions on the rim"]
    # a path inside the dome: nothing
    assert main(["animate", str(LEGACY_FIELD), "--path", "great:0.3,0.1,1:-0.3,0.1,1", "--frames", "3", "-o",
                 str(tmp_path / "inside"), "--device", "cpu", "-q"]) == 0
    assert capsys.readouterr().err == ""


# --- evaluate --------------------------------------------------------------------------------------

PLOTS = ["barycentric-psnr.png", "examples.png", "gaussian-counts.png", "psnr-circular-vs-alpha.png", "psnr-full.png",
         "psnr-specular.png"]


@pytest.fixture(scope="module")
def evaluated(small_field, small_donut, tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate") / "report"
    import contextlib
    import io

    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        status = main(["evaluate", str(small_field), str(small_donut), "--steps", "2", "-o", str(out), "--device",
                       "cpu", "-q"])
    return status, out, text.getvalue()


def test_evaluate_writes_a_report_and_plots(evaluated, small_field, field):
    status, out, text = evaluated
    assert status == 0
    assert (sorted(p.name for p in out.iterdir())
            == sorted(PLOTS + ["worst-lights.png", "report.json", ".warp-highlights.json"]))
    report = json.loads((out / "report.json").read_text())
    specular = report["summary"]["specular"]
    for method in ("circular", "straight", "alpha"):
        assert specular[method]["count"] == 2 * field.light_count - 4
        assert 10.0 < specular[method]["p5"] <= specular[method]["mean"] <= specular[method]["p95"] <= 100.0
    assert 0.0 <= specular["circular_beats_alpha"] <= 1.0
    assert report["field"] == str(small_field) and report["methods"] == ["circular", "straight", "alpha"]
    assert len(report["barycentric_sweep"]["weights"]) == 6
    from PIL import Image

    for name in PLOTS:
        with Image.open(out / name) as image:
            assert image.format == "PNG" and min(image.size) > 100
    # the table on stdout
    assert "| circular |" in text and "| alpha |" in text
    assert f"{specular['circular']['mean']:.2f}" in text
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]


def test_evaluate_keeps_an_existing_report(evaluated, small_field, small_donut, capsys):
    _, out, _ = evaluated
    before = (out / "report.json").read_bytes()
    assert main(["evaluate", str(small_field), str(small_donut), "--steps", "2", "-o", str(out), "--device", "cpu",
                 "-q"]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert (out / "report.json").read_bytes() == before


def test_evaluate_without_the_triangle_plot(small_field, small_donut, tmp_path, capsys):
    import shutil

    field_path = tmp_path / "mine.whf"
    shutil.copy(small_field, field_path)
    assert main(["evaluate", str(field_path), str(small_donut), "--triangle", "none", "--methods", "circular,alpha",
                 "--device", "cpu", "-q"]) == 0
    out = tmp_path / "mine-evaluation"  # the default: beside the field
    names = sorted(p.name for p in out.iterdir())
    assert "barycentric-psnr.png" not in names and "psnr-circular-vs-alpha.png" in names
    report = json.loads((out / "report.json").read_text())
    assert (report["barycentric_sweep"] is None
            and set(report["summary"]["specular"]) == {"circular", "alpha", "circular_beats_alpha"})
    assert "| straight |" not in capsys.readouterr().out


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["--triangle", "99999", "--steps", "2"], "triangle 99999 does not exist"),
        (["--triangle", "middle"], "--triangle"),
        (["--methods", "circular,cubic"], "methods"),
        (["--methods", ""], "methods"),
    ],
)
def test_evaluate_bad_input_is_one_line_and_writes_nothing(small_field, small_donut, tmp_path, capsys, arguments,
                                                           expected):
    out = tmp_path / "report"
    assert (main(["evaluate", str(small_field), str(small_donut), *arguments, "-o", str(out), "--device", "cpu", "-q"])
            == 2)
    assert expected in _error_line(capsys)
    assert _tree(tmp_path) == []


def test_evaluate_needs_heldout_lights(small_field, small_donut, tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(small_donut, copy)
    (copy / "heldout.lp").unlink()
    assert main(["evaluate", str(small_field), str(copy), "-o", str(tmp_path / "report"), "--device", "cpu", "-q"]) == 2
    line = _error_line(capsys)
    assert f"{copy} has no held-out lights (no heldout.lp, no Test/ folder inside or beside it)" in line
    # both ways out, the field's refit included
    assert "--heldout FOLDER" in line and "--holdout-every K" in line and f"fit {copy} --holdout-every K" in line
    assert "render" not in line
    assert not (tmp_path / "report").exists()


def _test_folder_layout(data: Path, root: Path, where: str) -> tuple[Path, Path]:
    """``data`` (a rendered capture with ``heldout.lp``) as a SynthRTI-style capture: its lights in ``Dome/``, its
    held-out lights and images in a ``Test/`` folder ``where`` ("beside" or "inside") it; returns (Dome, Test)."""
    import shutil

    dome = root / "object" / "Dome"
    shutil.copytree(data, dome, ignore=shutil.ignore_patterns("heldout*", "h*.exr"))
    test = (dome if where == "inside" else dome.parent) / "Test"
    shutil.copytree(data / "heldout", test / "heldout")
    shutil.copytree(data / "specular", test / "specular", ignore=shutil.ignore_patterns("0*.exr"))
    shutil.copy(data / "heldout.lp", test / "lights.lp")
    return dome, test


@pytest.mark.parametrize("where", ["beside", "inside"])
def test_evaluate_finds_a_test_folder_as_the_collection_does(tiny_sphere, tmp_path, capsys, where):
    """A ``Test/`` folder beside the capture (``OBJECT/Dome`` and ``OBJECT/Test``) or inside it is found, said in one
    line, and scored exactly as the same lights in ``heldout.lp``."""
    import shutil

    from warp_highlights.collection.captures import find_captures

    data, field = tiny_sphere
    dome, test = _test_folder_layout(data, tmp_path / "layout", where)
    assert [c.heldout for c in find_captures(tmp_path / "layout")] == [test]  # the runner's choice
    options = ["--triangle", "none", "--baselines", "none", "--methods", "circular", "--device", "cpu"]
    assert main(["evaluate", str(field), str(dome) + "/", "-o", str(tmp_path / "found"), *options]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "held-out lights from" in line]
    assert said == [f"  held-out lights from {test} (the Test/ folder {where} {dome}; --heldout FOLDER takes another)"]
    assert main(["evaluate", str(field), str(data), "-o", str(tmp_path / "heldout-lp"), *options]) == 0
    assert "held-out lights from" not in capsys.readouterr().err  # heldout.lp: nothing to say
    found, inside = (json.loads((tmp_path / name / "report.json").read_text()) for name in ("found", "heldout-lp"))
    assert found["heldout"] == 28 and found["summary"] == inside["summary"]
    # an explicit --heldout wins over the found folder, and --holdout-every does not look for one
    other = tmp_path / "other"
    shutil.copytree(test, other)
    assert main(["evaluate", str(field), str(dome), "--heldout", str(other), "-o", str(tmp_path / "given"), *options,
                 "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_evaluate_holdout_every_on_a_field_fitted_to_every_light(tiny_sphere, tmp_path, capsys):
    data, field = tiny_sphere
    assert main(["evaluate", str(field), str(data), "--holdout-every", "4", "-o", str(tmp_path / "e"), "--device",
                 "cpu", "-q"]) == 2
    line = _error_line(capsys)
    assert line.startswith(f"warp-highlights evaluate: error: {field} was fitted to every light of {data} (16)")
    assert f"refit with 'fit {data} --holdout-every 4 -o FIELD'" in line and "Test/ folder" in line
    assert "pass the dataset it was fitted to" not in line
    assert _tree(tmp_path) == []


def test_evaluate_a_dataset_without_a_renderer_skips_the_triangle_plot(small_field, small_donut, tmp_path):
    import shutil

    copy = tmp_path / "photos"
    shutil.copytree(small_donut, copy)
    (copy / "meta.json").unlink()
    out = tmp_path / "report"
    assert main(["evaluate", str(small_field), str(copy), "--steps", "2", "-o", str(out), "--device", "cpu", "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert "meta.json" in report["barycentric_sweep"]["skipped"]
    assert not (out / "barycentric-psnr.png").exists() and (out / "psnr-specular.png").is_file()


# --- demo ------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_demo_writes_an_index_of_what_it_made(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", str(out), "--lights", "16", "--size", "64x36", "--frames", "4", "--device", "cpu", "-q"]) == 0
    assert "index.md" in capsys.readouterr().out
    index = (out / "index.md").read_text()
    listed = re.findall(r"^\| `([^`]+)` \|", index, flags=re.MULTILINE)
    assert {"donut/", "donut.whf", "evaluation/", "orbit.gif", "relit.png"} <= set(listed)
    for name in listed:
        path = out / name.rstrip("/")
        assert path.is_dir() if name.endswith("/") else path.is_file(), name
    # every file of the folder is in the index
    assert (sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir())
            == sorted(listed + ["demo.json", "index.md", ".warp-highlights.json"]))
    # the evaluation row names the plots it holds
    row = next(line for line in index.splitlines() if line.startswith("| `evaluation/`"))
    plots = re.findall(r"[\w-]+\.(?:png|json)", row)
    assert sorted(set(plots)) == sorted(p.name for p in (out / "evaluation").iterdir() if not p.name.startswith("."))
    demo = json.loads((out / "demo.json").read_text())
    assert set(demo["files"]) == set(listed)
    assert set(demo["seconds"]) == {"render", "fit", "evaluate", "animate"} and demo["total_seconds"] > 0
    report = json.loads((out / "evaluation" / "report.json").read_text())
    for method in ("circular", "straight", "alpha"):
        assert f"| {method} | {report['summary']['specular'][method]['mean']:.2f} |" in index
    from PIL import Image

    with Image.open(out / "orbit.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (64, 36)
    with Image.open(out / "orbit-highlights.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (3 * 64, 36)
    assert read_image(out / "relit.png").shape == (36, 64, 3)
    field = load_field(out / "donut.whf")
    assert (field.width, field.height, field.light_count) == (64, 36, 16)

    before = _tree(out)
    assert main(["demo", str(out), "--lights", "16", "--size", "64x36", "--frames", "4", "--device", "cpu", "-q"]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert _tree(out) == before


def test_demo_refuses_a_file_as_its_folder(tmp_path, capsys):
    target = tmp_path / "notes.txt"
    target.write_text("keep me")
    for extra in ([], ["--overwrite"]):
        assert main(["demo", str(target), "--lights", "8", "--size", "32x18", "--frames", "2", "--device", "cpu", "-q",
                     *extra]) == 2
        assert "notes.txt" in _error_line(capsys)
        assert target.read_text() == "keep me" and _tree(tmp_path) == ["notes.txt"]


def test_demo_bad_options(tmp_path, capsys):
    for extra, expected in ((["--lights", "3"], "use 4..2000"), (["--frames", "1"], "--frames"),
                            (["--size", "64"], "WIDTHxHEIGHT")):
        assert main(["demo", str(tmp_path / "demo"), "--device", "cpu", "-q", *extra]) == 2
        assert expected in _error_line(capsys)
    assert _tree(tmp_path) == []


@pytest.mark.slow
def test_overwrite_never_deletes_other_files(small_field, small_donut, tmp_path, capsys):
    """--overwrite replaces only folders holding what the command itself writes."""
    for argv in (
        ["relight", str(small_field), "--light", "0,0,1", "--light", "1,0,1", "-q"],
        ["evaluate", str(small_field), str(small_donut), "--triangle", "none", "-q"],
    ):
        out = tmp_path / argv[0]
        out.mkdir()
        (out / "thesis.tex").write_text("keep me")
        assert main([*argv, "-o", str(out), "--overwrite"]) == 2
        assert "thesis.tex, which warp-highlights did not write" in _error_line(capsys)
        assert _tree(out) == ["thesis.tex"]
        # a folder the command wrote itself is replaced, and the old contents go
        (out / "thesis.tex").unlink()
        assert main([*argv, "-o", str(out)]) == 0
        first = _tree(out)
        victim = next(name for name in first if not name.startswith("."))
        manifest = (out / ".warp-highlights.json").read_bytes()
        assert main([*argv, "-o", str(out), "--overwrite"]) == 0
        assert _tree(out) == first and (out / ".warp-highlights.json").read_bytes() != manifest  # a new folder
        # a file of ours that the user edited since is not deleted either
        (out / victim).write_bytes(b"edited by the user")
        assert main([*argv, "-o", str(out), "--overwrite"]) == 2
        assert f"holds {victim}, which was changed after warp-highlights wrote it" in _error_line(capsys)
        assert (out / victim).read_bytes() == b"edited by the user"
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# --- residual transfer and the capture protocols ----------------------------------------------------

LEGACY_FIELD = Path(__file__).resolve().parent / "data" / "legacy-v1.whf"


def test_relight_residual_of_a_field_from_before_residuals_is_one_line(tmp_path, capsys):
    out = tmp_path / "x.exr"
    assert main(["relight", str(LEGACY_FIELD), "--light", LIGHT, "--diffuse", "residual", "-o", str(out), "--device",
                 "cpu", "-q"]) == 2
    line = _error_line(capsys)
    assert "residual" in line and "fit" in line
    assert _tree(tmp_path) == []
    # the same field still relights with what it has (auto: its diffuse images)
    assert main(["relight", str(LEGACY_FIELD), "--light", LIGHT, "-o", str(out), "--device", "cpu", "-q"]) == 0


def test_fit_and_evaluate_with_every_kth_light_held_out(tiny_sphere, tmp_path, capsys):
    from conftest import TINY_FIT

    data, _ = tiny_sphere
    field_path = tmp_path / "fold.whf"
    assert (main(["fit", str(data), "-o", str(field_path), "--holdout-every", "4", "--device", "cpu", "-q", *TINY_FIT])
            == 0)
    field = load_field(field_path)
    assert field.light_count == 12 and field.report["holdout_every"] == 4
    assert field.residual is not None and field.diffuse is None
    capsys.readouterr()
    out = tmp_path / "evaluation"
    assert main(["evaluate", str(field_path), str(data), "-o", str(out), "--triangle", "none", "--baselines", "ptm,rbf",
                 "--device", "cpu", "-q"]) == 0
    table = capsys.readouterr().out
    assert "8-bit sRGB PSNR" in table and "| ptm |" in table and "| rbf |" in table
    report = json.loads((out / "report.json").read_text())
    assert report["heldout"] == 4 and report["baselines"] == ["ptm", "rbf"]
    assert report["heldout_protocol"].startswith("every 4th light")
    srgb = report["per_query"]["full_srgb_psnr"]
    assert set(srgb) == {"circular", "straight", "alpha", "ptm", "rbf"} and all(len(v) == 4 for v in srgb.values())
    assert all(0 <= s <= 1 for values in report["per_query"]["full_ssim"].values() for s in values)
    assert (out / "worst-lights.png").is_file()
    # another K than the field's names the field's
    assert main(["evaluate", str(field_path), str(data), "-o", str(tmp_path / "other"), "--holdout-every", "3",
                 "--device", "cpu", "-q"]) == 2
    line = _error_line(capsys)
    assert "fitted with --holdout-every 4: evaluate it with --holdout-every 4" in line
    assert not (tmp_path / "other").exists()


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["--holdout-every", "1"], "--holdout-every"),
        (["--baselines", "ptm,lol"], "--baselines"),
    ],
)
def test_evaluate_protocol_options_are_checked(tiny_sphere, tmp_path, capsys, arguments, expected):
    data, field = tiny_sphere
    assert (main(["evaluate", str(field), str(data), "-o", str(tmp_path / "e"), *arguments, "--device", "cpu", "-q"])
            == 2)
    assert expected in _error_line(capsys)
    assert not (tmp_path / "e").exists()
