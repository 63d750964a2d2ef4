"""The command line: the main jobs end to end, and one clear line with exit status 2 for bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from warp_highlights.cli import main
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.images import write_image
from warp_highlights.io.lightfile import write_lp
from warp_highlights.model.lights import LightSet


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert "Traceback" not in err
    return err


def test_render_writes_a_loadable_dataset(tmp_path, capsys):
    out = tmp_path / "sphere"
    assert main(["render", "sphere", str(out), "--lights", "8", "--size", "32x24", "--gray", "-q"]) == 0
    assert "wrote" in capsys.readouterr().out
    field = ReflectanceField.load(out, progress=False)
    assert field.images.shape == (8, 24, 32)
    assert field.heldout.light_count == 12
    meta = json.loads((out / "meta.json").read_text())
    assert meta["settings"]["colour"] is False


def test_render_dome_with_lights_file_and_no_heldout(tmp_path):
    lp = tmp_path / "dome.lp"
    write_lp(LightSet.fibonacci_dome(10), lp, [f"x{i}.jpg" for i in range(10)])
    out = tmp_path / "dome"
    assert (main(["render", "donut", str(out), "--lights-file", str(lp), "--heldout", "none", "--size", "32x18", "-q"])
            == 0)
    field = ReflectanceField.load(out, progress=False)
    assert field.light_count == 10 and field.heldout is None


def test_info_summarises_a_dataset(tmp_path, capsys):
    out = tmp_path / "ds"
    main(["render", "sphere", str(out), "--lights", "6", "--size", "24x16", "-q"])
    capsys.readouterr()
    assert main(["info", str(out), "--json", "-q"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["lights"] == 6 and summary["size"] == "24x16" and summary["heldout_lights"] == 8
    assert main(["info", str(out), "-q"]) == 0  # for people: words, short numbers, no Python reprs
    lines = capsys.readouterr().out.splitlines()
    fields = dict(line.strip().split(": ", 1) for line in lines)
    assert fields["lights"] == "6" and fields["held-out lights"] == "8" and fields["mask"].endswith(" pixels")
    low, high = summary["elevation_deg"]
    assert fields["elevation"] == f"{low:.4g} to {high:.4g} deg"
    assert not any(token in line for line in lines for token in ("None", "[", "]"))
    assert (fields["values"] == "{:.4g} to {:.4g}".format(*summary["value_range"])
            and fields["mean value"] == f"{summary['mean_value']:.4g}")


def test_demo_renders_and_draws_a_contact_sheet(tmp_path):
    """The demo's folder holds the dataset and the contact sheet; ``demo.json`` says whether the highlights' animation
    shows moving Gaussians, as the field holds them."""
    from warp_highlights.io.fieldfile import load_field

    out = tmp_path / "demo"
    assert main(["demo", str(out), "--lights", "12", "--size", "64x36", "-q"]) == 0
    assert (out / "donut" / "lights.lp").is_file()
    assert (out / "donut-contact-sheet.png").stat().st_size > 1000
    said = json.loads((out / "demo.json").read_text())["files"]["orbit-highlights.gif"]
    moving = bool(load_field(out / "donut.whf").moving_mask.any())
    assert ("watch them glide" in said) == moving and ("keeps no moving Gaussian" in said) != moving


@pytest.mark.parametrize("choice", ["auto", "lowrank", "learned"])
def test_demo_fits_with_the_residual_it_is_given(choice, tmp_path, monkeypatch):
    """``demo --residual`` reaches the fit as ``fit --residual`` would set it; the stopped demo leaves nothing."""
    import warp_highlights.fit.pipeline as pipeline

    seen = []

    def stop(dataset, *, settings=None, **kwargs):
        seen.append(settings)
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "fit_field", stop)
    out = tmp_path / "demo"
    assert (main(["demo", str(out), "--lights", "8", "--size", "32x18", "--device", "cpu", "--residual", choice, "-q"])
            == 130)
    (settings,) = seen
    assert settings.residual.kind == choice
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["render", "cube", "{out}"], "unknown shape 'cube'"),
        (["render", "sphere", "{out}", "--size", "big"], "WIDTHxHEIGHT"),
        (["render", "sphere", "{out}", "--samples", "5"], "square number"),
        (["render", "sphere", "{out}", "--lights", "2"], "use 4..20000"),
        (["render", "sphere", "{out}", "--size", "-16x9"], "out of range"),
        (["render", "sphere", "{out}", "--lights", "200000"], "use 4..20000"),
        (["sheet", "{tmp}", "-o", "{tmp}/s.png", "--thumb-height", "0"], "use 16..1024 pixels"),
        (["sheet", "{tmp}", "-o", "{tmp}/s.png", "--thumb-height", "100000"], "use 16..1024 pixels"),
        (["fit", "{tmp}", "-o", "{tmp}/f.whf", "--exposure", "-2"], "--exposure"),
        (["collection", "{tmp}", "-o", "{tmp}/out", "--exposure", "x"], "neither 'auto' nor a number"),
        (["collection", "{tmp}", "-o", "{tmp}/out", "--baselines", "ptm,phong"], "--baselines 'ptm,phong'"),
        (["fit", "{tmp}", "-o", "{tmp}/f.whf", "--workers", "0"], "--workers"),
        (["render", "sphere", "{out}", "--albedo", "red"], "albedo"),
        (["render", "sphere", "{out}", "--albedo", "2,0,0"], "albedo"),
        (["render", "sphere", "{out}", "--shininess", "0"], "shininess"),
        (["render", "sphere", "{out}", "--lights-file", "{tmp}/none.lp"], "none.lp"),
        (["render", "sphere", "{out}", "--device", "cuda:7"], "cuda:7"),
        (["render", "{tmp}/missing.ply", "{out}"], "missing.ply"),
        (["info", "{tmp}/nowhere"], "nowhere"),
        (["sheet", "{tmp}", "-o", "{tmp}/sheet.jpg"], ".png"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, arguments, expected):
    argv = [a.format(out=tmp_path / "out", tmp=tmp_path) for a in arguments] + ["-q"]
    assert main(argv) == 2
    line = _error_line(capsys)
    assert line.startswith(f"warp-highlights {argv[0]}: error:")
    assert expected in line


def test_existing_output_is_never_clobbered(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    assert main(["render", "sphere", str(out), "--lights", "6", "--size", "16x16", "-q"]) == 2
    assert "--overwrite" in _error_line(capsys)
    assert (out / "precious.txt").read_text() == "keep me"
    # --overwrite replaces only what this project wrote: a folder holding the user's file is refused
    assert main(["render", "sphere", str(out), "--lights", "6", "--size", "16x16", "-q", "--overwrite"]) == 2
    assert "precious.txt" in _error_line(capsys)
    assert (out / "precious.txt").read_text() == "keep me"
    (out / "precious.txt").unlink()
    assert main(["render", "sphere", str(out), "--lights", "6", "--size", "16x16", "-q"]) == 0
    assert main(["render", "sphere", str(out), "--lights", "5", "--size", "16x16", "-q", "--overwrite"]) == 0
    assert (out / "lights.lp").is_file() and not (out / "images" / "0005.exr").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporaries left


def _broken_dataset(folder, case: str):
    folder.mkdir()
    image = np.full((8, 10), 0.5, np.float32)
    names = [f"img{i}.exr" for i in range(4)]
    directions = LightSet.fibonacci_dome(4).directions
    for name in names:
        write_image(folder / name, image)
    lines = [f"{n} {x:.6f} {y:.6f} {z:.6f}" for n, (x, y, z) in zip(names, directions)]
    if case == "missing image":
        (folder / names[2]).unlink()
    elif case == "zero vector":
        lines[1] = f"{names[1]} 0 0 0"
    elif case == "count":
        lines = lines[:3]
    elif case == "size":
        write_image(folder / names[3], np.zeros((9, 10), np.float32))
    elif case == "nan":
        bad = image.copy()
        bad[2, 3] = np.nan
        write_image(folder / names[1], bad)
    (folder / "dirs.lp").write_text("4\n" + "\n".join(lines) + "\n")


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("missing image", "img2.exr"),
        ("zero vector", "dirs.lp:3"),
        ("count", "4"),
        ("size", "img3.exr"),
        ("nan", "img1.exr"),
    ],
)
def test_info_rejects_bad_datasets_in_one_line(tmp_path, capsys, case, expected):
    _broken_dataset(tmp_path / "ds", case)
    assert main(["info", str(tmp_path / "ds"), "-q"]) == 2
    assert expected in _error_line(capsys)


def test_module_entry_point_reports_errors_without_traceback(tmp_path):
    env = dict(os.environ)
    result = subprocess.run(
        [sys.executable, "-m", "warp_highlights", "render", "cube", str(tmp_path / "x"), "-q"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert result.returncode == 2
    # Warp's CUDA warning too would be a line here (test_cpu_runs_say_nothing_of_warp_or_cuda)
    lines = result.stderr.splitlines()
    assert lines == ["warp-highlights render: error: unknown shape 'cube': use donut, teapot, sphere, coin, bumpy or a "
                     "path to a PLY/OBJ/STL file"]
    version = subprocess.run([sys.executable, "-m", "warp_highlights", "--version"], capture_output=True, text=True,
                             timeout=300)
    assert version.returncode == 0 and version.stdout.startswith("warp-highlights ")


def test_render_accepts_a_mesh_file(tmp_path):
    pv = pytest.importorskip("pyvista")
    mesh_path = tmp_path / "ball.ply"
    pv.Sphere(radius=2.0, theta_resolution=48, phi_resolution=24).save(mesh_path)
    out = tmp_path / "ball"
    assert (main(["render", str(mesh_path), str(out), "--lights", "6", "--size", "32x24", "--heldout", "none", "-q"])
            == 0)
    field = ReflectanceField.load(out, progress=False)
    assert field.mask.mean() > 0.2 and field.specular.max() > 1.0
    assert json.loads((out / "meta.json").read_text())["shape"] == str(mesh_path)


@pytest.mark.parametrize("arguments", [["--help"], ["render", "--help"], ["view", "--help"], ["demo", "--help"],
                                       ["collection", "--help"],
                                       ["fit", "x", "-o", "y.whf", "--size", "big"], ["fit"],
                                       ["relight", "x.whf", "-o", "a.png"],
                                       ["evaluate", "x.whf", "d", "--triangle", "foo"],
                                       ["evaluate", "x.whf", "d", "--heldout", "h", "--holdout-every", "3"],
                                       ["export", "x.whf", "--single-file", "-o", "x.png"]])
def test_help_and_usage_errors_do_not_start_warp(arguments):
    """``--help`` and argument errors are answered before Warp, SciPy or pyvista are imported (they cost
    1 s on the 2-core CPU; benchmarks/bench_startup.py times it); importing the package prints nothing."""
    probe = ("import sys; from warp_highlights.cli import main; status = main(sys.argv[1:]); "
             "print('HEAVY', [m for m in ('warp', 'scipy', 'pyvista', 'distributed') if m in sys.modules], status)")
    run = subprocess.run([sys.executable, "-c", probe, *arguments], capture_output=True, text=True, timeout=120)
    assert run.stdout.splitlines()[-1] == f"HEAVY [] {0 if '--help' in arguments else 2}", run.stdout + run.stderr
    quiet = subprocess.run([sys.executable, "-c", "import warp_highlights"], capture_output=True, text=True,
                           timeout=120)
    assert quiet.stdout == "" and quiet.stderr == ""


@pytest.mark.parametrize("command", ["fit", "relight", "animate", "export", "maps", "sheet", "collection", "evaluate"])
def test_usage_shows_which_commands_require_o(command, capsys):
    """``-o`` is required (shown bare in the usage line) wherever there is no default output; evaluate has one."""
    import re

    assert main([command, "--help"]) == 0
    usage = " ".join(capsys.readouterr().out.split("\n\n")[0].split())
    assert ("[-o OUTPUT]" in usage) == (command == "evaluate") and re.search(r"(^|[ \[])-o OUTPUT", usage), usage


def test_fit_without_o_says_it_is_required_and_list_settings_needs_none(capsys):
    assert main(["fit", "data/donut"]) == 2
    err = capsys.readouterr().err
    assert err == ("warp-highlights fit: error: the following arguments are required: -o/--output (see "
                   "warp-highlights fit --help)\n")
    assert main(["fit", "--list-settings"]) == 0 and main(["fit", "--list-settings", "-o", "x.whf"]) == 0
    assert "estimation.iterations=" in capsys.readouterr().out


@pytest.mark.slow
def test_cpu_runs_say_nothing_of_warp_or_cuda(tmp_path):
    """A run on the CPU prints neither Warp's greeting nor, on a machine without an NVIDIA driver, its
    'CUDA driver not found' warning, which would come before our own lines; ``-v`` brings Warp's lines
    back. Each command is its own process, as a user runs it."""
    from warp_highlights.cli.app import _cuda_driver_present

    capture, field = tmp_path / "sphere", tmp_path / "sphere.whf"
    commands = [["render", "sphere", str(capture), "--lights", "10", "--size", "32x18", "--device", "cpu"],
                ["fit", str(capture), "-o", str(field), "--device", "cpu", "--residual", "lowrank"],
                ["relight", str(field), "--light", "0.3,0.4,0.866", "-o", str(tmp_path / "relit.png"), "--device",
                 "cpu"],
                ["maps", str(field), "-o", str(tmp_path / "maps"), "--device", "cpu"],
                ["info", str(capture)],
                ["relight", str(field), "--light", "0.3,0.4,0.866", "-o", str(tmp_path / "verbose.png"), "--device",
                 "cpu", "-v"]]
    for command in commands:
        run = subprocess.run([sys.executable, "-m", "warp_highlights", *command], capture_output=True, text=True,
                             timeout=600)
        assert run.returncode == 0, run.stderr
        warp_lines = [line for line in (run.stdout + run.stderr).splitlines()
                      if "CUDA" in line or line.startswith("Warp ")]
        if "-v" not in command:
            assert warp_lines == [], f"{command[0]}: {warp_lines}"
        else:  # Warp says it started (and, without a driver, that it found none)
            assert any(line.startswith("Warp ") for line in warp_lines), run.stdout + run.stderr
            assert _cuda_driver_present() or any("CUDA" in line for line in warp_lines), run.stdout + run.stderr


@pytest.mark.parametrize("arguments", [["animate", "x.whf", "--path", "bogus", "-o", "a.gif"],
                                       ["animate", "x.whf", "--path", "orbit:35", "-o", "a.avi"],
                                       ["animate", "x.whf", "--path", "orbit:35", "-o", "a.gif", "--exr"],
                                       ["animate", "x.whf", "--path", "orbit:35", "-o", "a.gif", "--compare"]])
def test_animate_argument_errors_do_not_start_warp(arguments):
    """animate's path and output are checked by its own parsers (which read light files through SciPy) before Warp is
    imported."""
    probe = ("import sys; from warp_highlights.cli import main; status = main(sys.argv[1:]); "
             "print('HEAVY', [m for m in ('warp', 'pyvista', 'distributed') if m in sys.modules], status)")
    run = subprocess.run([sys.executable, "-c", probe, *arguments], capture_output=True, text=True, timeout=120)
    assert run.stdout.splitlines()[-1] == "HEAVY [] 2", run.stdout + run.stderr
    assert run.stderr.count("\n") == 1 and "animate: error:" in run.stderr, run.stderr


def test_python_messages_show_while_the_readers_quiet_descriptor_2(capfd):
    """Under ``python_stderr_apart`` (the console command's stderr), what Python writes to stderr still
    shows while an image reader points fd 2 at the null device; native output there is dropped."""
    import os
    import sys

    from warp_highlights.cli.app import python_stderr_apart
    from warp_highlights.io.images import quiet_native_stderr

    original = sys.stderr
    with python_stderr_apart():
        assert sys.stderr is not original
        with quiet_native_stderr():
            os.write(2, b"native noise\n")
            print("python line", file=sys.stderr)
    assert sys.stderr is original
    os.write(2, b"after\n")
    err = capfd.readouterr().err
    assert "python line" in err and "after" in err and "native noise" not in err


def test_the_console_ends_without_teardown_after_flushing_everything(tmp_path):
    """The process ends at once after ``main`` (``console._end``): what it printed and wrote is all there,
    into a pipe as into files, with ``main``'s status; a closed pipe is not an error of its own."""
    helped = subprocess.run([sys.executable, "-m", "warp_highlights", "render", "--help"], capture_output=True,
                            text=True, timeout=300)
    parser = subprocess.run([sys.executable, "-c",
                             "from warp_highlights.cli.app import main; main(['render', '--help'])"],
                            capture_output=True, text=True, timeout=300)
    assert helped.returncode == 0 and helped.stdout == parser.stdout and len(helped.stdout) > 500
    out = tmp_path / "tiny"
    made = subprocess.run([sys.executable, "-m", "warp_highlights", "render", "sphere", str(out), "--lights", "6",
                           "--size", "16x12",
                           "--heldout", "none", "--device", "cpu"], capture_output=True, text=True, timeout=300)
    assert made.returncode == 0 and "wrote" in made.stdout + made.stderr
    assert ReflectanceField.load(out, progress=False).light_count == 6
    closed = subprocess.run(f"'{sys.executable}' -m warp_highlights render --help | head -c 10", shell=True,
                            capture_output=True, text=True, timeout=300)
    assert closed.stdout == helped.stdout[:10] and "Traceback" not in closed.stderr
    no_stdout = subprocess.run(f"'{sys.executable}' -m warp_highlights --version >&-", shell=True, capture_output=True,
                               text=True, timeout=300)
    assert no_stdout.returncode == 0 and "Traceback" not in no_stdout.stderr
    # buffered output is flushed too
    environment = {key: value for key, value in os.environ.items() if key != "PYTHONUNBUFFERED"}
    buffered = subprocess.run([sys.executable, "-m", "warp_highlights", "render", "--help"], capture_output=True,
                              text=True, timeout=300,
                              env=environment)
    assert buffered.stdout == helped.stdout


def test_a_profiled_command_ends_as_the_profiler_needs(tmp_path):
    """Under cProfile the console exits through the interpreter, which writes the profile."""
    profile = tmp_path / "prof.out"
    run = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), "-m", "warp_highlights", "--version"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and profile.is_file() and profile.stat().st_size > 0
