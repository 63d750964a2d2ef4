"""LightSet: Fibonacci generators and the liberal .lp reader/writer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from warp_highlights.io.lightfile import read_lp, write_lp
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet


def _nearest_neighbour_distances(directions: np.ndarray) -> np.ndarray:
    distances, _ = cKDTree(directions).query(directions, k=2)
    return distances[:, 1]


def _write_lp(folder, text: str | bytes, *, images=(), name="dirs.lp"):
    for image in images:
        (folder / image).parent.mkdir(parents=True, exist_ok=True)
        (folder / image).write_bytes(b"")
    path = folder / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


def _single_line_error(excinfo, path, line: int | None = None) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    assert path.name in message
    if line is not None:
        assert f"{path.name}:{line}:" in message
    return message


# --- Fibonacci lattices ---------------------------------------------------------------------------


@pytest.mark.parametrize("count", [1, 2, 7, 49, 250, 1000])
def test_fibonacci_sphere_count_and_unit_length(count):
    lights = LightSet.fibonacci_sphere(count)
    assert lights.directions.shape == (count, 3)
    assert lights.light_count == len(lights) == count
    assert lights.directions.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("count", [250, 1000])
def test_fibonacci_sphere_is_balanced_and_even(count):
    directions = LightSet.fibonacci_sphere(count).directions
    assert np.linalg.norm(directions.mean(axis=0)) < 2.0 / count
    spacing = _nearest_neighbour_distances(directions)
    assert spacing.min() > 0.85 * spacing.mean()
    assert spacing.max() < 1.15 * spacing.mean()
    expected = math.sqrt(4.0 * math.pi / count)  # side of the square each point covers
    assert 0.8 * expected < spacing.mean() < 1.2 * expected


@pytest.mark.parametrize("count", [1, 5, 49, 250])
@pytest.mark.parametrize("elevation", [0.0, 10.0, 35.0])
def test_fibonacci_dome_stays_on_the_cap(count, elevation):
    lights = LightSet.fibonacci_dome(count, min_elevation_deg=elevation)
    z_min = math.sin(math.radians(elevation))
    assert lights.directions.shape == (count, 3)
    np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0, atol=1e-12)
    assert np.all(lights.directions[:, 2] >= z_min)


@pytest.mark.parametrize("elevation", [10.0, 35.0])
def test_fibonacci_dome_is_uniform_in_solid_angle(elevation):
    count = 500
    directions = LightSet.fibonacci_dome(count, min_elevation_deg=elevation).directions
    z_min = math.sin(math.radians(elevation))
    # Uniform in solid angle on a cap means z uniform on [z_min, 1] (Archimedes).
    np.testing.assert_allclose(np.sort(directions[:, 2]), np.linspace(z_min, 1.0, count), atol=2.0 / count)
    spacing = _nearest_neighbour_distances(directions)
    assert spacing.min() > 0.85 * spacing.mean()
    assert spacing.max() < 1.15 * spacing.mean()


@pytest.mark.parametrize("count", [0, -3, 2.5, True])
def test_fibonacci_rejects_bad_counts(count):
    with pytest.raises(InputError, match="positive integer"):
        LightSet.fibonacci_sphere(count)
    with pytest.raises(InputError, match="positive integer"):
        LightSet.fibonacci_dome(count)


def test_fibonacci_dome_rejects_bad_elevation():
    with pytest.raises(InputError, match="min_elevation_deg"):
        LightSet.fibonacci_dome(10, min_elevation_deg=90.0)


def test_constructor_normalises_and_validates():
    lights = LightSet(np.array([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]]), ["a.png", "b.png"])
    np.testing.assert_allclose(lights.directions, [[0, 0, 1], [0.6, 0.8, 0]])
    with pytest.raises(InputError, match="shape"):
        LightSet(np.zeros((3, 2)))
    with pytest.raises(InputError, match="zero"):
        LightSet(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(InputError, match="file names"):
        LightSet(np.eye(3), ["a.png"])


# --- .lp round trip -------------------------------------------------------------------------------


def test_lp_round_trip(tmp_path):
    lights = LightSet.fibonacci_dome(37)
    names = [f"images/{i:04d} copy.png" for i in range(37)]
    path = tmp_path / "lights.lp"
    write_lp(lights, path, names)
    assert [p.name for p in tmp_path.iterdir()] == ["lights.lp"]  # no temporary file left behind
    back = read_lp(path, check_files=False)
    assert back.filenames == names
    np.testing.assert_allclose(back.directions, lights.directions, rtol=0, atol=1e-15)


def test_lp_write_uses_own_or_default_names(tmp_path):
    write_lp(LightSet(np.eye(3), ["x.jpg", "y.jpg", "z.jpg"]), tmp_path / "own.lp")
    assert read_lp(tmp_path / "own.lp", check_files=False).filenames == ["x.jpg", "y.jpg", "z.jpg"]
    write_lp(LightSet(np.eye(3)), tmp_path / "default.lp")
    lines = (tmp_path / "default.lp").read_text().splitlines()
    assert lines[0] == "3" and lines[1].startswith("0000 ") and len(lines) == 4


def test_lp_write_keeps_six_significant_digits(tmp_path):
    lights = LightSet(np.array([[1.234567891e-5, 0.3, 0.9]]), ["a"])
    write_lp(lights, tmp_path / "a.lp")
    x = float((tmp_path / "a.lp").read_text().splitlines()[1].split()[1])
    assert abs(x - lights.directions[0, 0]) <= 1e-6 * abs(lights.directions[0, 0])


def test_lp_write_rejects_unwritable_names(tmp_path):
    with pytest.raises(InputError, match="cannot be written"):
        write_lp(LightSet(np.eye(3)), tmp_path / "a.lp", ["a", "b\nc", "d"])
    with pytest.raises(InputError, match="3 light directions"):
        write_lp(LightSet(np.eye(3)), tmp_path / "a.lp", ["a"])


# --- .lp quirks -----------------------------------------------------------------------------------


def test_lp_reads_real_world_quirks(tmp_path):
    text = (
        "\ufeff3  \r\n"  # BOM, trailing spaces, CRLF
        "\r\n"
        "image one.jpg\t0,5\t0\t0,5\r\n"  # file name with a space, tabs, decimal commas
        "   \t \r\n"
        "sub\\image2.jpg  0.0 2.0 0.0 \t\r\n"  # backslash, unnormalised, trailing tab
        "image,3.jpg 0 0 1e0\r\n"  # comma inside the file name stays
        "\r\n\r\n"
    )
    path = _write_lp(tmp_path, text, images=["image one.jpg", "sub/image2.jpg", "image,3.jpg"])
    lights = read_lp(path)
    assert lights.filenames == ["image one.jpg", "sub/image2.jpg", "image,3.jpg"]
    s = math.sqrt(0.5)
    np.testing.assert_allclose(lights.directions, [[s, 0, s], [0, 1, 0], [0, 0, 1]], atol=1e-15)


def test_lp_reads_utf16_with_bom(tmp_path):
    path = _write_lp(tmp_path, "1\r\na.jpg 0 0 1\r\n".encode("utf-16"), images=["a.jpg"])
    assert read_lp(path).filenames == ["a.jpg"]


def test_lp_reads_comma_line_next_to_dot_line(tmp_path):
    path = _write_lp(tmp_path, "2\na 0,6 -0,8 0\nb 0.6 0.8 0\n")
    np.testing.assert_allclose(read_lp(path, check_files=False).directions, [[0.6, -0.8, 0], [0.6, 0.8, 0]])


def test_lp_count_line_may_carry_more_tokens(tmp_path):
    path = _write_lp(tmp_path, "1 lights\na 0 0 1\n")
    assert read_lp(path, check_files=False).light_count == 1


# --- .lp rejections -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "needle"),
    [
        ("2\na.jpg 0 0 0\nb.jpg 0 0 1\n", 2, "zero"),
        ("3\na.jpg 0 0 1\nb.jpg 0 1 0\n", 1, "count says 3"),
        ("1\na.jpg 0 0 1\nb.jpg 0 1 0\n", 1, "count says 1"),
        ("2\na.jpg 0 0 1\nb.jpg 0 x 1\n", 3, "'x' is not a number"),
        ("2\na.jpg 0 0 1\nb.jpg 0.5 0,5 1\n", 3, "'0,5' is not a number"),  # mixed marks: no guessing
        ("1\na.jpg 0 0 nan\n", 2, "not a number"),
        ("1\na.jpg 0 1_0 1\n", 2, "not a number"),
        ("1\n0 0 1\n", 2, "expected '<image file> <x> <y> <z>'"),
        ("-2\na.jpg 0 0 1\n", 1, "must be positive"),
        ("0\n", 1, "must be positive"),
        ("two\na.jpg 0 0 1\n", 1, "light count"),
        ("2.0\na.jpg 0 0 1\nb.jpg 0 1 0\n", 1, "light count"),
        ("\n\n3\na.jpg 0 0 1\n", 3, "count says 3"),
    ],
)
def test_lp_rejects_with_file_and_line(tmp_path, text, line, needle):
    path = _write_lp(tmp_path, text)
    with pytest.raises(InputError) as excinfo:
        read_lp(path, check_files=False)
    assert needle in _single_line_error(excinfo, path, line)


def test_lp_rejects_duplicate_directions_naming_both_lines(tmp_path):
    path = _write_lp(tmp_path, "3\na.jpg 0 0 1\n\nb.jpg 1 0 0\nc.jpg 0 0 2\n")
    with pytest.raises(InputError) as excinfo:
        read_lp(path, check_files=False)
    assert "lines 2 and 5" in _single_line_error(excinfo, path)


def test_lp_rejects_missing_image(tmp_path):
    path = _write_lp(tmp_path, "2\na.jpg 0 0 1\nb.jpg 0 1 0\n", images=["a.jpg"])
    with pytest.raises(InputError) as excinfo:
        read_lp(path)
    assert "'b.jpg' not found" in _single_line_error(excinfo, path, 3)
    assert read_lp(path, check_files=False).light_count == 2


@pytest.mark.parametrize("text", [b"", b"\xef\xbb\xbf", b"\r\n  \n\t\n"])
def test_lp_rejects_empty_file(tmp_path, text):
    path = _write_lp(tmp_path, text)
    with pytest.raises(InputError) as excinfo:
        read_lp(path)
    assert "empty" in _single_line_error(excinfo, path)


def test_lp_rejects_missing_file(tmp_path):
    path = tmp_path / "nothing.lp"
    with pytest.raises(InputError) as excinfo:
        read_lp(path)
    assert "not found" in _single_line_error(excinfo, path)


@pytest.mark.realdata
def test_real_lp_files(data_root):
    dome = read_lp(data_root / "synthrti-object1-material5" / "Dome" / "dirs.lp")
    test = read_lp(data_root / "synthrti-object1-material5" / "Test" / "dirs.lp")
    item = read_lp(data_root / "realrti-item11" / "dirs.lp")
    assert (dome.light_count, test.light_count, item.light_count) == (49, 20, 54)
    assert dome.filenames[0] == "image01.jpg" and item.filenames[0] == "image00.jpg"
    for lights in (dome, test, item):
        np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0, atol=1e-12)
        assert np.all(lights.directions[:, 2] > 0.0)  # upper hemisphere only
