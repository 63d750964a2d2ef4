"""Names that moved out of the model (issue 13) still work, warn once per call, and give what the new
names give. Delete this file with the forwards in 0.3."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import warp_highlights as wh
from warp_highlights.model.field import HighlightField
from warp_highlights.model.lights import LightSet

LEGACY = Path(__file__).resolve().parent / "data" / "legacy-v1.whf"


def _moved(call, new_name: str):
    """Run ``call`` expecting exactly one DeprecationWarning that names ``new_name``; return its result."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = call()
    deprecations = [w for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(deprecations) == 1, [str(w.message) for w in caught]
    message = str(deprecations[0].message)
    assert new_name in message and "0.3" in message, message
    assert deprecations[0].filename == __file__, "the warning should point at the caller's line"
    return result


def test_highlight_field_load_save_and_size_report_forward(tmp_path):
    field = _moved(lambda: HighlightField.load(LEGACY), "warp_highlights.load_field(path)")
    reference = wh.load_field(LEGACY)
    assert field.gaussian_count == reference.gaussian_count
    written = _moved(lambda: field.save(tmp_path / "a.whf", lambert_half=False), "warp_highlights.save_field(field, path)")
    assert written == wh.save_field(reference, tmp_path / "b.whf", lambert_half=False)
    assert (tmp_path / "a.whf").read_bytes() == (tmp_path / "b.whf").read_bytes()
    sizes = _moved(field.size_report, "warp_highlights.field_size_report(field)")
    assert sizes == wh.field_size_report(field)


def test_size_report_of_a_field_never_saved_and_format_version_forward(tmp_path):
    fresh = replace(wh.load_field(LEGACY))  # a new object: it has never been in a file
    assert fresh.file_sizes is None
    sizes = _moved(fresh.size_report, "warp_highlights.field_size_report(field)")
    wh.save_field(replace(fresh), tmp_path / "now.whf")
    assert sizes == wh.load_field(tmp_path / "now.whf").file_sizes  # measured without writing: the bytes save_field writes
    from warp_highlights.io.fieldfile import FORMAT_VERSION

    assert _moved(lambda: HighlightField.FORMAT_VERSION, "warp_highlights.io.fieldfile.FORMAT_VERSION") == FORMAT_VERSION


def test_highlight_field_relight_forwards():
    field = wh.load_field(LEGACY)
    direction = [0.2, 0.3, 1.0]
    old = _moved(lambda: field.relight(direction, method="straight", device="cpu"), "warp_highlights.relight_field(field, directions)")
    new = wh.relight_field(field, direction, method="straight", device="cpu")
    np.testing.assert_array_equal(old.full, new.full)


def test_light_set_read_and_write_lp_forward(tmp_path):
    lights = LightSet.fibonacci_dome(5)
    _moved(lambda: lights.write_lp(tmp_path / "old.lp", ["a", "b", "c", "d", "e"]), "warp_highlights.write_lp(lights, path)")
    wh.write_lp(lights, tmp_path / "new.lp", ["a", "b", "c", "d", "e"])
    assert (tmp_path / "old.lp").read_bytes() == (tmp_path / "new.lp").read_bytes()
    read = _moved(lambda: LightSet.read_lp(tmp_path / "old.lp", check_files=False), "warp_highlights.read_lp(path)")
    np.testing.assert_array_equal(read.directions, wh.read_lp(tmp_path / "new.lp", check_files=False).directions)
    assert read.filenames == ["a", "b", "c", "d", "e"]


def test_deprecation_warnings_are_errors_in_this_suite():
    """pyproject.toml's filterwarnings makes our own deprecation warnings errors, so that any use of a
    moved name left in the package (or in a test without ``_moved``) fails the suite."""
    with pytest.raises(DeprecationWarning, match="will be removed in warp-highlights"):
        HighlightField.load(LEGACY)
