"""`warp-highlights fit` end to end, its report, the interpolation reference on a fitted field, and bad input."""

from __future__ import annotations

import json
import re
import threading

import numpy as np
import pytest

from conftest import FAST_FIT
from warp_highlights.cli import main
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.relight.interpolation import interpolate_sets
from warp_highlights.residual.decode import light_images


def _overrides() -> list[str]:
    return [arg for item in FAST_FIT for arg in ("--set", item)]


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def fitted(small_donut, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "donut.whf"
    report = out.with_suffix(".json")
    assert main(["fit", str(small_donut), "-o", str(out), "--report", str(report), "--diffuse", "images", "-q",
                 "--device", "cpu",
                 *_overrides()]) == 0  # the CPU's fit on any host (on CUDA the residual is learned by default)
    return out, report


def test_fit_writes_a_field_and_a_report(fitted, capsys):
    out, report_path = fitted
    field = load_field(out)
    assert field.light_count == 32 and len(field.directed_edges) == 6 * 32 - 12
    assert (field.width, field.height) == (96, 54)
    assert field.diffuse is not None and field.diffuse.images.shape == (32, 54, 96, 3)
    report = json.loads(report_path.read_text())
    assert set(report["seconds"]) >= {"loading", "segmentation", "estimation", "retargeting", "paths"}
    assert report["file_bytes"] == out.stat().st_size
    assert list(report["memory"]) == list(report["seconds"])  # every stage's peak memory, loading and saving included
    for peaks in report["memory"].values():
        assert peaks["host_peak_bytes"] > 10_000_000 and peaks["device_peak_bytes"] is None  # a CPU fit: no device pool
    assert report["estimation"]["gaussians_per_light"]["mean"] == pytest.approx(field.counts.mean())
    assert report["retargeting"]["improved_share"] > 0.9
    assert field.fit_settings().estimation.iterations == 300  # the overrides are stored
    residual = report["residual"]
    assert 0.0 <= residual["moving_specular_share"] <= 1.0


def test_info_on_a_field_says_how_much_moves(fitted, capsys):
    out, report_path = fitted
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    report = json.loads(report_path.read_text())["residual"]
    moving = next(line for line in lines if line.startswith("moving Gaussians:"))
    assert moving.startswith(f"moving Gaussians: {report['moving_gaussians']} of ")
    assert f"carrying {100 * report['moving_specular_share']:.0f}% of the specular energy" in moving
    assert 0.6 < report["motion_coherence"] <= 1.0  # a smooth donut: its highlights glide (random hops: about 0)
    assert f"median motion coherence {report['motion_coherence']:.2f}" in moving
    assert main(["info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["residual"] == report


def test_fit_summary_and_working_size(small_donut, tmp_path, capsys):
    out = tmp_path / "half.whf"
    assert main(["fit", str(small_donut), "-o", str(out), "--size", "48x27", "--diffuse", "none", "--workers", "1",
                 "-q", *_overrides()]) == 0
    text = capsys.readouterr().out
    for expected in ("stage times", "segmentation", "estimation", "retargeting", "peak memory: host",
                     "Gaussians per light", "estimation PSNR", "MB"):
        assert expected in text
    field = load_field(out)
    assert (field.width, field.height) == (48, 27) and field.diffuse is None
    residual = field.report["residual"]
    assert (f"{100 * residual['size_budget']:.0f}% of the capture, the captured lights back at "
            f"{residual['captured_psnr_db']:.1f} dB)") in text


def test_fit_holds_back_the_gaussians_whose_motion_does_not_follow_the_light(small_donut, tmp_path, capsys):
    """``residual.move_coherence`` 0.8 holds back the Gaussians whose motion a linear map of the half-vector's change
    explains less well (the small donut's median: about 0.7): the report and the summary count them, and as many
    fewer move as with it off."""
    counts = {}
    for threshold in ("-1", "0.8"):
        out = tmp_path / f"coherence{threshold}.whf"
        assert main(["fit", str(small_donut), "-o", str(out), "--size", "48x27", "--diffuse", "none", "--residual",
                     "lowrank", "-q", *_overrides(), "--set", "residual.check_lights=0", "--set",
                     f"residual.move_coherence={threshold}"]) == 0
        text = capsys.readouterr().out
        counts[threshold] = load_field(out).report["residual"]
    assert counts["-1"]["incoherent_gaussians"] == 0 and counts["-1"]["moving_gaussians"] > 0
    held = counts["0.8"]["incoherent_gaussians"]
    assert 0 < held < counts["-1"]["moving_gaussians"]
    assert counts["0.8"]["moving_gaussians"] == counts["-1"]["moving_gaussians"] - held
    assert f"blend in place ({held} glints whose motion does not follow the light)" in text
    assert "follow the light with a median coherence of" in text


def test_learned_fit_summary_gives_the_learned_check(small_donut, tmp_path, capsys):
    """``fit --residual learned`` says what the learned check measured and what it chose."""
    out = tmp_path / "learned.whf"
    # every measured capture glides at a threshold of -1: the glide's margin decides
    settings = ["residual.learned_epochs=2", "residual.learned_check=3", "residual.learned_glide_coherence=-1"]
    assert main(["fit", str(small_donut), "-o", str(out), "--size", "48x27", "--residual", "learned", "-q",
                 *_overrides(),
                 *[arg for item in settings for arg in ("--set", item)]]) == 0
    text = capsys.readouterr().out
    verdict = load_field(out).report["residual"]["learned_check"]
    assert ("learned check at 3 left-out lights" in text
            and f"images alone {verdict['images_alone_psnr_db']:.2f} dB" in text)
    assert not verdict["sees_gaussians"] and "residual + moved Gaussians" in text
    assert f"({verdict['exact_residual_psnr_db']:.2f} dB with its residual exact)" in text
    assert ("the learned residual keeps them" in text) == verdict["keeps_gaussians"]
    # and by which margin: the glide's where the capture's Gaussians glide with the light
    margin = verdict["tie_margin_db"]
    measured = load_field(out).report["residual"]["motion_coherence"] is not None
    assert verdict["glides"] == measured and margin == (0.5 if measured else -0.5)
    rule = (f"kept unless the images alone lead by more than {margin:.1f} dB" if margin >= 0
            else f"kept where the Gaussians lead by at least {-margin:.1f} dB")
    assert f"({'they glide: ' if verdict['glides'] else ''}{rule})" in text


def test_a_field_with_invalid_stored_settings_is_refused(fitted, tmp_path):
    from warp_highlights.model.errors import InputError

    field = load_field(fitted[0])
    field.settings["retarget"]["iterations"] = "many"
    broken = tmp_path / "broken.whf"
    save_field(field, broken)
    with pytest.raises(InputError, match="settings"):
        load_field(broken)


def test_auto_exposure_scales_the_radiance_and_is_recorded(small_donut, tmp_path):
    from warp_highlights.fit.pipeline import exposure_factor
    from warp_highlights.io.dataset import ReflectanceField

    data = ReflectanceField.load(small_donut, progress=False)
    factor = exposure_factor(data.images, "auto")
    assert np.percentile(data.images * factor, 99.9) == pytest.approx(1.0, rel=0.05)
    out = tmp_path / "auto.whf"
    assert main(["fit", str(small_donut), "-o", str(out), "--exposure", "auto", "--size", "48x27", "-q",
                 *_overrides()]) == 0
    from warp_highlights.io.resample import resize_stack

    working = exposure_factor(resize_stack(data.images, 48, 27), "auto")  # measured at the working size
    assert load_field(out).report["exposure"] == pytest.approx(working, rel=1e-6)


def test_saved_and_loaded_field_is_identical(fitted, tmp_path):
    field = load_field(fitted[0])
    again = tmp_path / "again.whf"
    save_field(field, again)
    loaded = load_field(again)
    for name in ("amplitude", "mean", "sigma", "theta", "active"):
        np.testing.assert_array_equal(getattr(loaded.estimated, name), getattr(field.estimated, name))
        np.testing.assert_array_equal(getattr(loaded.retargeted, name), getattr(field.retargeted, name))
    np.testing.assert_array_equal(loaded.path_delta, field.path_delta)
    np.testing.assert_array_equal(loaded.path_centre, field.path_centre)


@pytest.mark.parametrize("method", ["circular", "straight"])
def test_interpolation_at_a_vertex_is_that_vertex_set(fitted, method):
    field = load_field(fitted[0])
    faces = field.triangulation.faces[:20]
    weights = np.tile([1.0, 0.0, 0.0], (len(faces), 1))
    sets = interpolate_sets(field, faces, weights, method=method)
    capacity = field.capacity
    first = slice(0, capacity)
    source = field.estimated
    np.testing.assert_array_equal(sets.active[:, first], source.active[faces[:, 0]])
    for name in ("amplitude", "mean", "theta"):
        np.testing.assert_allclose(getattr(sets, name)[:, first][sets.active[:, first]],
                                   getattr(source, name)[faces[:, 0]][source.active[faces[:, 0]]], atol=1e-12)
    assert np.all(sets.weight[:, capacity:][sets.active[:, capacity:]] == 0.0)


def test_list_settings(capsys):
    assert main(["fit", "--list-settings"]) == 0
    text = capsys.readouterr().out
    assert "retarget.c_str=0.1" in text and "estimation.iterations=1000" in text


@pytest.mark.parametrize("choice", ["auto", "lowrank", "learned", "images", "none"])
def test_residual_choice_sets_the_residual_kind(choice, capsys):
    """``--residual`` stands for the setting ``residual.kind`` (``--list-settings`` shows it); ``--set`` still overrides
    it."""
    assert main(["fit", "--residual", choice, "--list-settings"]) == 0
    assert f"residual.kind={choice}\n" in capsys.readouterr().out
    assert main(["fit", "--residual", "lowrank", "--set", "residual.kind=images", "--list-settings"]) == 0
    assert "residual.kind=images\n" in capsys.readouterr().out
    assert main(["fit", "--set", "residual.kind=lossy", "--list-settings"]) == 2
    assert "kind must be one of auto, lowrank, learned, images, none" in capsys.readouterr().err


def test_interrupted_fit_leaves_nothing_behind(small_donut, tmp_path, monkeypatch, capsys):
    import warp_highlights.fit.pipeline as fit_module

    out = tmp_path / "field.whf"
    out.write_bytes(b"previous field")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_module, "fit_field", interrupted)
    assert main(["fit", str(small_donut), "-o", str(out), "--overwrite", "-q"]) == 130
    assert "interrupted" in _error_line(capsys)
    assert out.read_bytes() == b"previous field"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.whf"]


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["fit", "{missing}", "-o", "{out}"], "dataset folder not found"),
        (["fit", "{data}"], "the following arguments are required: -o/--output"),
        (["fit", "{data}", "-o", "{out}", "--report", "{out}"], "its own name"),
        (["fit", "{data}", "-o", "{out}", "--set", "paths=3"], "is a group"),
        (["fit", "{data}", "-o", "{out}", "--set", "estimation.iterations=10.5"], "integer"),
        (["fit", "{data}", "-o", "{out}", "--size", "2x1"], "too small"),
        (["fit", "{data}", "-o", "{out}", "--exposure", "bright"], "exposure"),
        (["fit", "{data}", "-o", "{out}", "--set", "retarget.nothing=1"], "no setting"),
        (["fit", "{data}", "-o", "{out}", "--set", "retarget.c_str=-1"], "c_str"),
        (["fit", "{data}", "-o", "{out}", "--size", "50x50"], "aspect"),
        (["fit", "{data}", "-o", "{out}", "--size", "192x108"], "larger"),
        (["fit", "{data}", "-o", "{existing}"], "--overwrite"),
        (["fit", "{data}", "-o", "{nofolder}"], "does not exist"),
        (["fit", "{data}", "-o", "{out}", "--workers", "0"], "workers"),
        (["fit", "{data}", "-o", "{out}", "--device", "cuda:7"], "device"),
        (["fit", "{data}", "-o", "{tmp}"], "folder"),
        (["fit", "{data}", "-o", "{out}", "--report", "{existing}"], "--overwrite"),  # the report obeys it too
        (["fit", "{data}", "-o", "{out}", "--exposure", "1e300"], "1e-12..1e+12"),
        (["fit", "{data}", "-o", "{out}", "--set", "estimation.iterations=100000000"], "[1, 100000]"),
        (["fit", "{data}", "-o", "{out}", "--bogus"], "fit: error: unrecognized arguments: --bogus"),
    ],
)
def test_bad_input_is_one_line(arguments, message, small_donut, tmp_path, capsys):
    existing = tmp_path / "existing.whf"
    existing.write_bytes(b"keep")
    names = {
        "missing": str(tmp_path / "missing"),
        "data": str(small_donut),
        "out": str(tmp_path / "out.whf"),
        "existing": str(existing),
        "nofolder": str(tmp_path / "no" / "such" / "f.whf"),
        "tmp": str(tmp_path),
    }
    args = [a.format(**names) for a in arguments] + ["-q"]
    assert main(args) == 2
    assert message in _error_line(capsys)
    # a loading begun is stopped
    assert not [thread.name for thread in threading.enumerate() if thread.name.startswith("load")]
    assert existing.read_bytes() == b"keep"
    assert not (tmp_path / "out.whf").exists()


@pytest.mark.realdata
@pytest.mark.parametrize(("folder", "size"),
                         [pytest.param("synthrti-object1-material5/Dome", "80x80", marks=pytest.mark.slow),
                          ("realrti-item11", "71x67")])
def test_fit_real_dome_captures(data_root, folder, size, tmp_path):
    """JPEG RTI domes (sRGB decoded, dirs.lp) fit end to end at a small working size."""
    out = tmp_path / "field.whf"
    assert main(["fit", str(data_root / folder), "-o", str(out), "--size", size, "-q", "--device", "cpu",
                 *_overrides()]) == 0
    field = load_field(out)
    assert field.triangulation.is_dome
    assert len(field.directed_edges) == 2 * len(field.triangulation.edges())
    assert f"{field.width}x{field.height}" == size
    report = field.report
    assert report["estimation"]["gaussians_per_light"]["mean"] > 0, "no highlight found on a glossy / metallic object"
    # the field keeps its Gaussians unless the move check found that blending predicts the captured lights better
    assert (field.counts.sum() > 0) == report["residual"]["move_check"]["moves"]
    assert report["retargeting"]["improved_share"] > 0.9
    assert report["estimation"]["psnr_db"]["mean"] > 30.0


def test_fit_messages_go_through_logging(small_donut, tmp_path, capsys, caplog):
    """The fit's stage lines are records of the ``warp_highlights`` logger (INFO): a program sees them
    only if it configures logging; the command line shows them on stderr unless ``-q``, and leaves the
    logger as it found it."""
    import logging

    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings

    quick = FAST_FIT + ["residual.check_lights=0"]
    with caplog.at_level(logging.INFO, logger="warp_highlights"):
        fit_field(ReflectanceField.load(small_donut, progress=False), settings=FitSettings().with_overrides(quick),
                  device="cpu", progress=False)
    stages = [r.getMessage().split(":")[0] for r in caplog.records if r.name == "warp_highlights.fit.pipeline"]
    assert stages[:5] == ["triangulation", "segmentation", "estimation", "retargeting", "paths"]
    logger = logging.getLogger("warp_highlights")
    handlers, level = list(logger.handlers), logger.level
    settings = [part for item in quick for part in ("--set", item)]
    capsys.readouterr()
    for quiet, shown in ((False, True), (True, False)):
        out = tmp_path / f"quiet-{quiet}.whf"
        assert main(["fit", str(small_donut), "-o", str(out), "--device", "cpu", *settings,
                     *(["-q"] if quiet else [])]) == 0
        err = capsys.readouterr().err
        assert bool(re.search(r"  estimation: \d+\.\d s", err)) == shown, err
        assert logger.handlers == handlers and logger.level == level


def test_gaussian_size_shrinks_by_whole_factors_to_the_row_limit():
    from warp_highlights.model.config import EstimationSettings

    default = EstimationSettings()
    # the renders, the statue
    assert default.gaussian_size(480, 270) == (480, 270) and default.gaussian_size(567, 534) == (567, 534)
    assert default.gaussian_size(1920, 1080) == (960, 540) and default.gaussian_size(3840, 2160) == (960, 540)
    assert default.gaussian_size(4000, 6000) == (333, 500)  # a 24-megapixel portrait: a factor of 12
    assert EstimationSettings(max_pixels_per_rpx=0).gaussian_size(3840, 2160) == (3840, 2160)
    for height in range(1, 3000, 7):
        width, rows = default.gaussian_size(2 * height, height)
        assert rows <= 540 and (rows == height or rows > 270 or height <= 540)


def test_a_large_capture_fits_its_gaussians_at_a_shrunk_size(small_donut, small_field, tmp_path, capsys):
    """With a row limit of 27 (0.1 pixel per rpx) the 96x54 donut's Gaussians are fitted at 48x27 and
    the field keeps 96x54; the moved highlights score at the held-out lights close to a full-size fit's."""
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.relight.evaluation import evaluate_field

    out, report = tmp_path / "shrunk.whf", tmp_path / "shrunk.json"
    assert main(["fit", str(small_donut), "-o", str(out), "--report", str(report), "--diffuse", "images", "-q",
                 "--device", "cpu",
                 *_overrides(), "--set", "estimation.max_pixels_per_rpx=0.1"]) == 0
    assert "working size 96x54 (Gaussians fitted at 48x27)" in capsys.readouterr().out
    values = json.loads(report.read_text())
    assert values["size"] == [96, 54] and values["gaussian_size"] == [48, 27]
    assert values["residual"]["move_check"]["lights"] == 32  # the check ran, at the Gaussians' size
    shrunk, full = load_field(out), load_field(small_field)
    assert ((shrunk.width, shrunk.height) == (96, 54)
            and light_images(shrunk.residual, np.eye(32)[:1]).shape[1:3] == (54, 96))
    dataset = ReflectanceField.load(small_donut, progress=False)
    scores = [evaluate_field(field, dataset, device="cpu", methods=("circular", "alpha"), barycentric_face=None,
                             example_count=0).specular_psnr
              for field in (shrunk, full)]
    assert (np.nanmean(scores[0]["circular"]) > np.nanmean(scores[1]["circular"])
            - 1.5), (np.nanmean(scores[0]["circular"]), np.nanmean(scores[1]["circular"]))
    assert np.nanmean(scores[0]["circular"]) > np.nanmean(scores[0]["alpha"])


def test_a_fit_segmented_in_row_bands_is_the_whole_fit(small_donut, monkeypatch):
    """When the stack does not fit the memory at once (here: the host's available memory made just
    enough for bands of 7 rows beside the parts held whole), the fit segments it in row bands; the
    field is the untiled fit's, bit for bit (the specular part, kept as float16 in host bands, only
    sets the highlight colour, 8 bits over [0, 4])."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.kernels.chunks import DEVICE_SHARE
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT)
    fields = [pipeline.fit_field(dataset, settings=settings, device="cpu", diffuse="images", workers=2)]
    n, height, width, channels = dataset.images.shape
    row_bytes = 4 * n * width * (3 * channels + 1)
    held = n * height * width * (6 * channels + 4)  # the specular part as float16, the diffuse part and the luminance
    monkeypatch.setattr(pipeline, "available_memory", lambda: held + 7.5 * row_bytes / DEVICE_SHARE)
    bands = []
    real = pipeline.segment_in_bands
    monkeypatch.setattr(pipeline, "segment_in_bands",
                        lambda *args, rows, **kwargs: bands.append(rows) or real(*args, rows=rows, **kwargs))
    fields.append(pipeline.fit_field(dataset, settings=settings, device="cpu", diffuse="images", workers=2))
    assert bands == [7]
    assert fields[0].report["estimation"] == fields[1].report["estimation"]
    for name in ("estimated", "retargeted"):
        for part in ("mean", "sigma", "theta", "amplitude", "active"):
            np.testing.assert_array_equal(getattr(getattr(fields[1], name), part),
                                          getattr(getattr(fields[0], name), part), err_msg=f"{name}.{part}")
    np.testing.assert_array_equal(fields[1].diffuse.images, fields[0].diffuse.images)
    np.testing.assert_array_equal(fields[1].residual.luminance.codes, fields[0].residual.luminance.codes)
    np.testing.assert_array_equal(fields[1].residual.highlight_colour, fields[0].residual.highlight_colour)


@pytest.mark.parametrize("large", [True, False])
def test_a_device_that_is_not_there_is_reported_before_a_large_capture_is_decoded(large, small_donut, tmp_path, capsys,
                                                                                  monkeypatch):
    """The images load while the pipeline is imported; a capture of more than ``EARLY_LOAD_BYTES`` only
    once Warp has found the device (a small one may be read first). Either way: one error line."""
    import warp_highlights.cli.fit as fit_cli
    import warp_highlights.io.dataset as dataset_module

    decoded = []
    for reader in ("read_image", "read_pixels"):  # the mask's reader, the images'
        real = getattr(dataset_module, reader)
        monkeypatch.setattr(dataset_module, reader,
                            lambda *args, real=real, **kwargs: decoded.append(1) or real(*args, **kwargs))
    if large:
        monkeypatch.setattr(fit_cli, "EARLY_LOAD_BYTES", 0)
    assert main(["fit", str(small_donut), "-o", str(tmp_path / "f.whf"), "--device", "cuda:7", "-q"]) == 2
    assert "device" in _error_line(capsys)
    assert not (tmp_path / "f.whf").exists()
    if large:
        assert decoded == []


@pytest.mark.slow
@pytest.mark.parametrize("verbose", [False, True])
def test_a_small_capture_decodes_while_warp_starts_unless_verbose(verbose, small_donut, tmp_path, monkeypatch):
    """At most ``EARLY_LOAD_BYTES`` of stacks decode before the warm-up has started Warp (held back here
    until an image is decoded, or 2 s); under -v the loading waits for it (Warp's own messages)."""
    import threading

    import warp_highlights.io.dataset as dataset_module
    import warp_highlights.kernels.warmup as warmup_module

    order, decoded = [], threading.Event()
    real_warm, real_reads = (warmup_module.DeviceWarmup._warm,
                             {name: getattr(dataset_module, name) for name in ("read_image", "read_pixels")})

    def warm(self):
        decoded.wait(2.0)
        order.append("warp")
        real_warm(self)

    def reader(name):  # the mask's reader, the images'
        def read(*args, **kwargs):
            if not decoded.is_set():
                order.append("decode")
                decoded.set()
            return real_reads[name](*args, **kwargs)

        return read

    monkeypatch.setattr(warmup_module.DeviceWarmup, "_warm", warm)
    for name in real_reads:
        monkeypatch.setattr(dataset_module, name, reader(name))
    assert main(["fit", str(small_donut), "-o", str(tmp_path / "f.whf"), "--device", "cpu", "-q",
                 *(["-v"] if verbose else [])]) == 0
    assert order[:2] == (["warp", "decode"] if verbose else ["decode", "warp"])


def test_progress_bars_take_a_thread_lock_alone(small_donut, tmp_path):
    """``fit``'s bars share a thread lock (tqdm's default also makes a multiprocessing lock, importing
    ``multiprocessing`` in the loading thread): by the time the pipeline starts, loading has imported no
    ``multiprocessing`` (the field file's codec imports it later, while saving); a lock set already (by a
    program embedding us) is kept."""
    import subprocess
    import sys

    from conftest import TINY_FIT

    fit = ["fit", str(small_donut), "-o", str(tmp_path / "f.whf"), "--device", "cpu", *TINY_FIT]
    code = ("import sys, threading; import warp_highlights.fit.pipeline as pipeline; "
            "real = pipeline.fit_field; seen = []; "
            "pipeline.fit_field = lambda *a, **k: seen.append('multiprocessing' in sys.modules) or real(*a, **k); "
            f"from warp_highlights.cli.app import main; status = main({fit!r}); "
            "from tqdm import tqdm; from warp_highlights.cli.fit import _thread_lock_for_progress_bars as take; lock = "
            "tqdm.get_lock(); take(); "
            "print(status, seen == [False], type(lock) is type(threading.RLock()), "
            "tqdm.get_lock() is lock)")
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert shown[-4:] == ["0", "True", "True", "True"]


@pytest.mark.skipif(not __import__("warp").is_cuda_available(), reason="images are held on CUDA devices only")
def test_a_small_capture_s_images_are_held_from_the_segmentation_s_upload(small_donut, tmp_path, monkeypatch):
    """On CUDA the move check and the residual's stacks read the images the segmentation sent up and the own
    highlights as rendered there: ``hold_images`` is handed those very arrays (nothing sent up again)."""
    import warp_highlights.fit.pipeline as pipeline
    from conftest import TINY_FIT

    kept, handed = [], []
    real_segment, real_hold = pipeline.segment_in_bands, pipeline.hold_images

    def segment(*args, **kwargs):
        result = real_segment(*args, **kwargs)
        kept.append(result.images)
        return result

    def hold(images, own, device, **kwargs):
        handed.append(kwargs)
        return real_hold(images, own, device, **kwargs)

    monkeypatch.setattr(pipeline, "segment_in_bands", segment)
    monkeypatch.setattr(pipeline, "hold_images", hold)
    assert main(["fit", str(small_donut), "-o", str(tmp_path / "f.whf"), "--residual", "lowrank", "--device", "cuda:0",
                 "-q", *TINY_FIT]) == 0
    assert len(kept) == 1 and kept[0] is not None and len(handed) == 1
    assert handed[0]["images_up"] is kept[0] and handed[0]["own_up"] is not None


def test_evaluate_scores_a_light_path_against_rendered_truth(fitted, small_donut, tmp_path, capsys):
    """``evaluate --path``: every frame scored, with the highlights' motion; on the donut, moving highlights
    leave fewer ghosts and sit nearer the truth than the blend's."""
    out, _ = fitted
    capsys.readouterr()
    assert main(["evaluate", str(out), str(small_donut), "--path", "orbit:35", "--frames", "12", "--baselines",
                 "none", "--triangle", "none", "--methods", "circular,alpha", "-o", str(tmp_path / "ev"), "-q",
                 "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "along orbit:35 (12 frames, ground truth rendered anew):" in printed
    path = json.loads((tmp_path / "ev" / "report.json").read_text())["path"]
    assert path["frames"] == 12 and path["spec"] == "orbit:35"
    for method in ("circular", "alpha"):
        scores = path[method]
        assert len(scores["psnr_db"]["per_frame"]) == 12 and len(scores["flicker_levels"]["per_frame"]) == 11
        assert 15 < scores["psnr_db"]["mean"] < 60 and 0 < scores["ssim"]["mean"] <= 1
    assert path["circular"]["ghost_share"]["mean"] < path["alpha"]["ghost_share"]["mean"]
    for method in ("circular", "alpha"):
        assert 0 <= path[method]["visible_ghost_share"]["mean"] <= path[method]["ghost_share"]["mean"]
    assert path["circular"]["visible_ghost_share"]["mean"] < path["alpha"]["visible_ghost_share"]["mean"]
    assert "| visible ghost share |" in printed
    assert path["circular"]["position_error_rpx"]["mean"] < path["alpha"]["position_error_rpx"]["mean"]


def test_evaluate_refuses_a_path_without_a_renderer(fitted, small_donut, tmp_path, capsys):
    """A dataset whose meta.json names no built-in shape cannot give ground truth along a path: one line, exit 2,
    nothing written."""
    import shutil

    out, _ = fitted
    copy = tmp_path / "copy"
    shutil.copytree(small_donut, copy)
    (copy / "meta.json").unlink()
    capsys.readouterr()
    assert main(["evaluate", str(out), str(copy), "--path", "orbit:35", "-o", str(tmp_path / "ev"), "-q",
                 "--device", "cpu"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "has no ground truth along a path" in error[0]
    assert not (tmp_path / "ev").exists()
