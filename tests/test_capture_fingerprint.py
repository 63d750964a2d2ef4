"""A field records the capture it was fitted to; relight/animate --dataset and evaluate refuse another one."""

from __future__ import annotations

from pathlib import Path

import pytest

from warp_highlights.cli import main
from warp_highlights.io.dataset import ReflectanceField, capture_differences, capture_fingerprint
from warp_highlights.io.fieldfile import load_field, save_field

LIGHT = "0.3,0.5,1"


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict:
    """A 16-light 32x18 sphere and donut (same light directions, names and size; other pixels), the sphere's
    field, one fitted with --holdout-every 4, and one whose report records no capture."""
    from conftest import TINY_FIT

    root = tmp_path_factory.mktemp("captures")
    paths = {"sphere": root / "sphere", "donut": root / "donut", "field": root / "sphere.whf",
             "holdout": root / "holdout.whf", "legacy": root / "legacy.whf"}
    for shape in ("sphere", "donut"):
        assert main(["render", shape, str(paths[shape]), "--lights", "16", "--size", "32x18", "--samples", "1",
                     "--device", "cpu", "-q"]) == 0
    assert main(["fit", str(paths["sphere"]), "-o", str(paths["field"]), "--diffuse", "images", "--device", "cpu",
                 "-q", *TINY_FIT]) == 0
    assert main(["fit", str(paths["sphere"]), "-o", str(paths["holdout"]), "--holdout-every", "4", "--diffuse",
                 "images", "--device", "cpu", "-q", *TINY_FIT]) == 0
    field = load_field(paths["field"])
    del field.report["capture"]
    save_field(field, paths["legacy"])
    return paths


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _refusal(capsys, field: Path, dataset: Path) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(field) in err and str(dataset) in err and "--other-capture" in err and "other pixels" in err
    return err


def test_the_fit_records_the_whole_capture_also_when_holding_lights_out(captures):
    recorded = load_field(captures["field"]).report["capture"]
    assert recorded["lights"] == 16 and recorded["size"] == [32, 18] and recorded["digest"]["images"] == [0, 8, 15]
    assert load_field(captures["holdout"]).report["capture"] == recorded
    dataset = ReflectanceField.load(captures["sphere"], progress=False)
    assert capture_fingerprint(dataset) == recorded
    assert capture_fingerprint(ReflectanceField.load(captures["sphere"], progress=False, size=(16, 9))) == recorded


def test_the_differences_are_named(captures):
    sphere = capture_fingerprint(ReflectanceField.load(captures["sphere"], progress=False))
    donut = capture_fingerprint(ReflectanceField.load(captures["donut"], progress=False))
    assert capture_differences(sphere, sphere) == []
    assert [d.split(" (")[0] for d in capture_differences(sphere, donut)] == ["other pixels"]
    other = {**sphere, "directions": "0" * 16, "names": "1" * 16, "size": [64, 36]}
    assert capture_differences(other, sphere)[:2] == ["other light directions", "other image names"]
    assert capture_differences(other, sphere)[2] == "32x18 images of 3 channels, not 64x36 of 3"
    assert capture_differences({**sphere, "lights": 20}, sphere)[0] == "16 lights, not 20"


def test_evaluate_accepts_its_capture_and_refuses_another(captures, tmp_path, capsys):
    common = ["--triangle", "none", "--methods", "circular,alpha", "--baselines", "none", "--device", "cpu", "-q"]
    for field in ("field", "holdout"):
        out = tmp_path / f"{field}-evaluation"
        assert main(["evaluate", str(captures[field]), str(captures["sphere"]), "-o", str(out), *common]) == 0
        assert (out / "report.json").is_file()
    before = _tree(tmp_path)
    out = tmp_path / "donut-evaluation"
    assert main(["evaluate", str(captures["field"]), str(captures["donut"]), "-o", str(out), *common]) == 2
    _refusal(capsys, captures["field"], captures["donut"])
    assert _tree(tmp_path) == before
    assert main(["evaluate", str(captures["field"]), str(captures["donut"]), "-o", str(out), "--other-capture",
                 *common]) == 0
    assert (out / "report.json").is_file()


@pytest.mark.parametrize("command", ["relight", "animate"])
def test_relight_and_animate_refuse_another_capture_unless_told(captures, command, tmp_path, capsys):
    def run(field: str, dataset: str, out: Path, *extra: str) -> int:
        if command == "relight":
            args = ["relight", str(captures[field]), "--light", LIGHT, "--method", "alpha"]
        else:
            args = ["animate", str(captures[field]), "--path", "orbit:30", "--frames", "2", "--compare"]
        return main([*args, "--dataset", str(captures[dataset]), "-o", str(out), "--device", "cpu", "-q", *extra])

    suffix = ".png" if command == "relight" else ".gif"
    assert run("field", "sphere", tmp_path / f"same{suffix}") == 0
    before = _tree(tmp_path)
    assert run("field", "donut", tmp_path / f"other{suffix}") == 2
    _refusal(capsys, captures["field"], captures["donut"])
    assert _tree(tmp_path) == before
    assert run("field", "donut", tmp_path / f"other{suffix}", "--other-capture") == 0
    assert run("legacy", "donut", tmp_path / f"legacy{suffix}") == 0  # a field that records no capture: as before
