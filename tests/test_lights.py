"""LightSet: Fibonacci generators, the liberal .lp reader/writer and relight's .dome/.relight light files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from warp_highlights.io.dataset import ReflectanceField, find_light_file
from warp_highlights.io.images import write_image
from warp_highlights.io.lightfile import images_in_order, read_lights, read_lp, write_lp
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
        ("1\na.jpg 0 1\n", 2, "expected '<image file> <x> <y> <z>'"),
        ("2\n0 0 1\nb.jpg 0 1 0\n", 2, "expected '<image file> <x> <y> <z>'"),  # names on some lines only
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


# --- light files in the wild: no names, a fifth column, sub-folders, relight's JSON ------------------


def test_lp_without_names_pairs_the_folder_images_in_natural_order(tmp_path):
    images = ["img10.jpg", "IMG2.jpg", "img1.png"]
    path = _write_lp(tmp_path, "3\n0 0 1\n1\t0\t1\n0,0 1,0 1,0\n", images=images + ["notes.txt", ".hidden.jpg"])
    assert images_in_order(tmp_path) == ["img1.png", "IMG2.jpg", "img10.jpg"]
    lights = read_lp(path)
    assert lights.filenames == ["img1.png", "IMG2.jpg", "img10.jpg"]
    s = math.sqrt(0.5)
    np.testing.assert_allclose(lights.directions, [[0, 0, 1], [s, 0, s], [0, s, s]], atol=1e-15)


def test_lp_without_names_needs_as_many_images(tmp_path):
    path = _write_lp(tmp_path, "3\n0 0 1\n1 0 1\n0 1 1\n", images=["a.jpg", "b.jpg"])
    with pytest.raises(InputError) as excinfo:
        read_lp(path)
    assert "3 directions without image names" in _single_line_error(excinfo, path)
    assert "holds 2 images" in str(excinfo.value)
    assert read_lp(path, check_files=False).filenames is None  # directions alone, for --lights and paths


def test_lp_fifth_column_is_ignored(tmp_path):
    path = _write_lp(tmp_path, "2\na.jpg 0 0 1 0.9\nsub/b b.jpg 1 0 0 1,1\n", images=["a.jpg", "sub/b b.jpg"])
    lights = read_lp(path)
    assert lights.filenames == ["a.jpg", "sub/b b.jpg"]
    np.testing.assert_allclose(lights.directions, [[0, 0, 1], [1, 0, 0]])


def test_lp_name_ending_in_a_number_is_not_a_fifth_column(tmp_path):
    path = _write_lp(tmp_path, "2\nscan 1 0 0 1\nscan 2 1 0 0\n", images=["scan 1", "scan 2"])
    assert read_lp(path).filenames == ["scan 1", "scan 2"]


def test_lp_images_in_a_sub_folder_load_as_a_dataset(tmp_path):
    for i, name in enumerate(["jpg/a.png", "jpg/b.png", "jpg/c.png", "jpg/d.png"]):
        (tmp_path / "jpg").mkdir(exist_ok=True)
        write_image(tmp_path / name, np.full((6, 8, 3), 0.1 + 0.2 * i, np.float32))
    _write_lp(tmp_path, "4\njpg/a.png 0 0 1\njpg\\b.png 1 0 1\njpg/c.png 0 1 1\njpg/d.png -1 0 1\n", name="lights.lp")
    field = ReflectanceField.load(tmp_path)
    assert field.light_count == 4 and field.images.shape == (4, 6, 8, 3)
    np.testing.assert_allclose(field.images[3], 0.7, atol=0.01)


def _dome(directions, configuration="directional", positions=None) -> dict:
    vectors = lambda rows: [{"x": x, "y": y, "z": z} for x, y, z in rows]  # noqa: E731
    dome = {"label": "test dome", "domeDiameter": 800.0, "verticalOffset": 0.0, "lightConfiguration": configuration,
            "directions": vectors(directions), "positionsSphere": [], "positions3d": [], "ledAdjust": []}
    if positions is not None:
        dome["positions3d" if configuration == "lights3d" else "positionsSphere"] = vectors(positions)
    return dome


def test_dome_file_pairs_images_and_keeps_positions(tmp_path):
    directions = [[0, 0, 1], [0.6, 0, 0.8], [0, -0.6, 0.8]]
    positions = [[0, 0, 400], [240, 0, 320], [0, -240, 320]]
    (tmp_path / "rig.dome").write_text(json.dumps(_dome(directions, "spherical", positions)))
    for name in ("p01.jpg", "p02.jpg", "p03.jpg"):
        (tmp_path / name).write_bytes(b"")
    lights = read_lights(tmp_path / "rig.dome")
    assert lights.filenames == ["p01.jpg", "p02.jpg", "p03.jpg"]
    np.testing.assert_allclose(lights.directions, directions, atol=1e-15)
    np.testing.assert_allclose(lights.positions, positions)
    assert lights.take([2, 0]).positions.tolist() == [positions[2], positions[0]]
    assert read_lights(tmp_path / "rig.dome").take(np.array([True, False, True])).filenames == ["p01.jpg", "p03.jpg"]


def test_relight_project_reads_its_images_folder_skips_and_dome(tmp_path):
    directions = [[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]]
    positions = [[0, 0, 300], [180, 0, 240], [0, 180, 240], [-180, 0, 240]]
    images = [{"filename": f"im{i}.png", "skip": i == 2, "direction": {"x": 0, "y": 0, "z": 0}} for i in range(4)]
    project = {"application": "RelightLab", "width": 8, "height": 6, "folder": "photos", "images": images,
               "dome": _dome(directions, "lights3d", positions)}
    (tmp_path / "photos").mkdir()
    for i in range(4):
        write_image(tmp_path / "photos" / f"im{i}.png", np.full((6, 8, 3), 0.2 + 0.1 * i, np.float32))
    (tmp_path / "capture.relight").write_text(json.dumps(project))
    lights = read_lights(tmp_path / "capture.relight")
    assert lights.filenames == ["photos/im0.png", "photos/im1.png", "photos/im3.png"]
    np.testing.assert_allclose(lights.directions, [directions[i] for i in (0, 1, 3)], atol=1e-15)
    np.testing.assert_allclose(lights.positions, [positions[i] for i in (0, 1, 3)])
    assert find_light_file(tmp_path) == tmp_path / "capture.relight"
    field = ReflectanceField.load(tmp_path)
    assert field.light_count == 3 and field.lights.positions is not None
    np.testing.assert_allclose(field.images[2], 0.5, atol=0.01)


def test_relight_project_without_dome_directions_uses_each_images_direction(tmp_path):
    images = [{"filename": f"im{i}.jpg", "direction": {"x": x, "y": 0, "z": 1}} for i, x in enumerate((0, 1))]
    (tmp_path / "a.relight").write_text(json.dumps({"folder": ".", "images": images, "dome": {"directions": []}}))
    lights = read_lights(tmp_path / "a.relight", check_files=False)
    assert lights.filenames == ["im0.jpg", "im1.jpg"] and lights.positions is None
    np.testing.assert_allclose(lights.directions[1], [math.sqrt(0.5), 0, math.sqrt(0.5)])


@pytest.mark.parametrize(("name", "content", "needle"), [
    ("a.dome", b"{not json", "not a JSON light file"),
    ("a.dome", b"[1, 2]", "expected a JSON object"),
    ("a.dome", json.dumps({"directions": [{"x": 0, "y": 0}]}).encode(), "'directions' entry 0 is not an {x, y, z}"),
    ("a.dome", json.dumps({"directions": [{"x": 0, "y": 0, "z": 0}]}).encode(), "zero or not finite"),
    ("a.dome", json.dumps({"directions": []}).encode(), "holds no light directions"),
    ("a.dome", json.dumps({"directions": [[0, 0, 1], [0, 0, 2]]}).encode(), "give the same light direction"),
    ("a.dome", json.dumps({"lightConfiguration": "lights3d", "directions": [[0, 0, 1]],
                           "positions3d": [[0, 0, 1], [0, 0, 2]]}).encode(), "2 'positions3d' for 1 light"),
    ("a.relight", json.dumps({"images": "x", "dome": {}}).encode(), "no 'images' list"),
    ("a.relight", json.dumps({"images": []}).encode(), "no 'dome' object"),
    ("a.relight", json.dumps({"images": [{"skip": False}], "dome": {}}).encode(), "image 0 of the project has no"),
    ("a.txt", b"1\na 0 0 1\n", "not a light file"),
])
def test_json_light_files_reject_with_one_line(tmp_path, name, content, needle):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError) as excinfo:
        read_lights(path, check_files=False)
    assert needle in _single_line_error(excinfo, path)


def test_relight_project_names_a_missing_image(tmp_path):
    images = [{"filename": "gone.jpg"}]
    (tmp_path / "a.relight").write_text(json.dumps({"images": images, "dome": {"directions": [[0, 0, 1]]}}))
    with pytest.raises(InputError) as excinfo:
        read_lights(tmp_path / "a.relight")
    assert "'gone.jpg' not found" in _single_line_error(excinfo, tmp_path / "a.relight")
