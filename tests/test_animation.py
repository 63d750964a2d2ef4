"""Light paths (great circle, orbit, through a list, CLI specs) and animation writers (GIF, MP4, frames)."""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import pytest

from warp_highlights.io.images import linear_to_srgb, read_image
from warp_highlights.io.lightfile import write_lp
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.view import animation as animation_module
from warp_highlights.view.animation import animation_kind, check_animation_output, write_animation
from warp_highlights.view.light_paths import great_circle, orbit, parse_light_path, through_directions

Image = pytest.importorskip("PIL.Image")


def _angles(a, b) -> np.ndarray:
    """Angle between unit vectors along the last axis, radians (atan2 form: exact near 0 and pi)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _steps(path: np.ndarray) -> np.ndarray:
    return _angles(path[:-1], path[1:])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _visible(folder) -> list[str]:
    """Sorted names in ``folder`` without hidden ones (the output manifest)."""
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def _one_line(excinfo, *fragments: str) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


# --- great circle ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_great_circle_endpoints_norms_and_equal_steps(seed):
    rng = np.random.default_rng(seed)
    start, end = rng.normal(size=3) * 3.0, rng.normal(size=3) * 0.5
    path = great_circle(start, end, 17)
    assert path.shape == (17, 3) and path.dtype == np.float64
    assert np.array_equal(path[0], _unit(start)) and np.array_equal(path[-1], _unit(end))
    np.testing.assert_allclose(np.linalg.norm(path, axis=1), 1.0, atol=1e-15)
    total = _angles(_unit(start), _unit(end))
    np.testing.assert_allclose(_steps(path), total / 16, atol=1e-12)
    normal = np.cross(_unit(start), _unit(end))  # a great circle lies in a plane through the origin
    np.testing.assert_allclose(path @ normal, 0.0, atol=1e-14)


def test_great_circle_takes_the_shorter_arc():
    path = great_circle([1, 0, 0], [0, 1, 0], 9)
    assert _steps(path).sum() == pytest.approx(math.pi / 2, abs=1e-13)
    assert np.all(path[:, :2] >= -1e-15)  # stays in the first quadrant, not round the other way


def test_great_circle_constant_and_single_frame():
    np.testing.assert_array_equal(great_circle([0, 0, 2], [0, 0, 5], 4), np.tile([0.0, 0.0, 1.0], (4, 1)))
    np.testing.assert_array_equal(great_circle([0, 3, 4], [1, 0, 0], 1), [[0.0, 0.6, 0.8]])


@pytest.mark.parametrize("end", [[-1, 0, 0], [-1, 1e-9, 0]])
def test_great_circle_opposite_endpoints_are_ambiguous(end):
    with pytest.raises(InputError) as excinfo:
        great_circle([1, 0, 0], end, 10)
    _one_line(excinfo, "opposite", "ambiguous", "list path", "middle direction")


@pytest.mark.parametrize(("start", "frames"), [([0, 0, 0], 5), ([np.nan, 0, 1], 5), ([1, 0], 5), ([0, 0, 1], 0)])
def test_great_circle_bad_input(start, frames):
    with pytest.raises(InputError):
        great_circle(start, [0, 1, 0], frames)


# --- orbit ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("elevation", "start_azimuth"), [(30.0, 0.0), (-20.0, 45.0), (75.0, -100.0)])
def test_orbit_constant_elevation_equal_steps_seamless_loop(elevation, start_azimuth):
    frames = 12
    path = orbit(elevation, frames, start_azimuth_deg=start_azimuth)
    assert path.shape == (frames, 3)
    np.testing.assert_allclose(np.linalg.norm(path, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(path[:, 2], math.sin(math.radians(elevation)), atol=1e-15)
    azimuth = np.degrees(np.arctan2(path[:, 1], path[:, 0]))
    assert azimuth[0] == pytest.approx((start_azimuth + 180) % 360 - 180, abs=1e-12)
    np.testing.assert_allclose(np.mod(np.diff(azimuth), 360.0), 360.0 / frames, atol=1e-10)
    # No repeated end frame: the step from the last frame back to the first is one more equal step.
    loop = np.concatenate([path, path[:1]])
    np.testing.assert_allclose(_steps(loop), _steps(loop)[0], atol=1e-13)
    assert _steps(loop)[-1] > 0.1


def test_orbit_direction_convention():
    # Azimuth runs from +x towards +y (image up); positive elevation is on the camera side.
    np.testing.assert_allclose(orbit(0.0, 4), [[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], atol=1e-15)
    np.testing.assert_allclose(orbit(90.0, 3), np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-15)
    clockwise = orbit(0.0, 4, turns=-1.0)
    np.testing.assert_allclose(clockwise[1], [0, -1, 0], atol=1e-15)
    two_turns = orbit(10.0, 8, turns=2.0)
    np.testing.assert_allclose(two_turns[:4], two_turns[4:], atol=1e-15)


@pytest.mark.parametrize("elevation", [90.5, -91.0, math.nan, math.inf])
def test_orbit_elevation_out_of_range(elevation):
    with pytest.raises(InputError) as excinfo:
        orbit(elevation, 10)
    _one_line(excinfo, "elevation")


# --- through directions ---------------------------------------------------------------------------


def test_through_directions_spreads_frames_by_arc_length():
    # Arcs of 30 and 60 degrees, 9 steps: 3 on the first, 6 on the second, all 10 degrees.
    a = [1.0, 0.0, 0.0]
    b = [math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0]
    c = [b[0] * math.cos(math.radians(60)), b[1] * math.cos(math.radians(60)), math.sin(math.radians(60))]
    path = through_directions([a, b, c], 10)
    assert path.shape == (10, 3)
    assert np.array_equal(path[0], _unit(a)) and np.array_equal(path[3], _unit(b))
    assert np.array_equal(path[9], _unit(c))
    np.testing.assert_allclose(np.degrees(_steps(path)), 10.0, atol=1e-10)


@pytest.mark.parametrize("seed", range(4))
def test_through_directions_visits_every_direction_in_order(seed):
    rng = np.random.default_rng(seed)
    given = rng.normal(size=(5, 3))
    path = through_directions(given, 40)
    assert path.shape == (40, 3)
    np.testing.assert_allclose(np.linalg.norm(path, axis=1), 1.0, atol=1e-15)
    hits = [int(np.flatnonzero(np.all(path == _unit(g), axis=1))[0]) for g in given]
    assert hits[0] == 0 and hits[-1] == 39 and hits == sorted(hits) and len(set(hits)) == 5
    arcs = _angles(np.array([_unit(g) for g in given[:-1]]), np.array([_unit(g) for g in given[1:]]))
    steps = _steps(path)
    for k in range(4):  # equal steps within an arc, and as many steps as the arc's share of the length
        within = steps[hits[k] : hits[k + 1]]
        np.testing.assert_allclose(within, arcs[k] / (hits[k + 1] - hits[k]), atol=1e-12)
        assert abs((hits[k + 1] - hits[k]) - 39 * arcs[k] / arcs.sum()) <= 1.0
    # Piecewise great circles: each point of an arc lies in the plane of its two ends.
    for k in range(4):
        normal = np.cross(_unit(given[k]), _unit(given[k + 1]))
        np.testing.assert_allclose(path[hits[k] : hits[k + 1] + 1] @ normal / np.linalg.norm(normal), 0, atol=1e-13)


def test_through_directions_constant_repeats_and_minimum_frames():
    np.testing.assert_array_equal(through_directions([[0, 0, 3]], 4), np.tile([0.0, 0.0, 1.0], (4, 1)))
    np.testing.assert_array_equal(through_directions([[0, 1, 0], [0, 2, 0]], 3), np.tile([0.0, 1.0, 0.0], (3, 1)))
    repeated = through_directions([[1, 0, 0], [1, 0, 0], [0, 1, 0]], 3)  # a repeat adds no frame
    np.testing.assert_allclose(repeated, great_circle([1, 0, 0], [0, 1, 0], 3), atol=1e-15)
    np.testing.assert_array_equal(through_directions([[1, 0, 0], [0, 1, 0], [0, 0, 1]], 3), np.eye(3))
    with pytest.raises(InputError) as excinfo:
        through_directions([[1, 0, 0], [0, 1, 0], [0, 0, 1]], 2)
    _one_line(excinfo, "at least 3 frames", "got 2")


def test_through_directions_opposite_neighbours_are_ambiguous():
    with pytest.raises(InputError) as excinfo:
        through_directions([[0, 0, 1], [1, 0, 0], [-1, 0, 0]], 20)
    _one_line(excinfo, "directions 1 and 2", "opposite", "middle direction")
    # Opposite but not consecutive is fine: the path goes round through the middle one.
    path = through_directions([[1, 0, 0], [0, 0, 1], [-1, 0, 0]], 5)
    np.testing.assert_allclose(path[2], [0, 0, 1], atol=1e-15)


@pytest.mark.parametrize("directions", [np.zeros((0, 3)), np.ones((3, 2)), [[0, 0, 0], [1, 0, 0]]])
def test_through_directions_bad_arrays(directions):
    with pytest.raises(InputError):
        through_directions(directions, 10)


# --- light path specs -----------------------------------------------------------------------------


def test_parse_light_path_great_and_orbit():
    np.testing.assert_array_equal(parse_light_path("great:1,0,1:-1,0,1", 7), great_circle([1, 0, 1], [-1, 0, 1], 7))
    np.testing.assert_array_equal(parse_light_path(" great: 0, 1 ,1 : 0,-1,1 ", 3),
                                  great_circle([0, 1, 1], [0, -1, 1], 3))
    np.testing.assert_array_equal(parse_light_path("orbit:30", 12), orbit(30.0, 12))
    np.testing.assert_array_equal(parse_light_path("ORBIT:-15.5:90", 8), orbit(-15.5, 8, start_azimuth_deg=90.0))


def test_parse_light_path_text_list(tmp_path):
    path_file = tmp_path / "path.txt"
    path_file.write_text("# light path\n1 0 0\n\n0,1,0   # comma form\n  0\t0\t2\n", encoding="utf-8")
    expected = through_directions([[1, 0, 0], [0, 1, 0], [0, 0, 1]], 9)
    np.testing.assert_array_equal(parse_light_path(f"list:{path_file}", 9), expected)


def test_parse_light_path_lp_list(tmp_path):
    directions = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [-1.0, 0.0, 1.0]])
    lp = tmp_path / "path.lp"
    write_lp(LightSet(directions), lp)  # the listed images do not exist: only the directions are read
    np.testing.assert_allclose(parse_light_path(f"list:{lp}", 11), through_directions(directions, 11), atol=1e-15)


@pytest.mark.parametrize(
    ("spec", "fragments"),
    [
        ("orbit:abc", ["elevation", "number", "orbit:30"]),
        ("orbit:", ["orbit:ELEVATION_DEG"]),
        ("orbit:30:east", ["azimuth", "'east'"]),
        ("orbit:120", ["[-90, 90]"]),
        ("orbit:30:0:1", ["orbit:ELEVATION_DEG"]),
        ("great:1,0,0", ["two directions", "great:x,y,z:x,y,z"]),
        ("great:1,0:0,1,0", ["start direction", "three numbers"]),
        ("great:1,0,0:0,nan,0", ["end direction", "'nan'"]),
        ("great:0,0,0:0,1,0", ["zero"]),
        ("great:0,0,1:0,0,-1", ["opposite", "middle direction"]),
        ("spiral:3", ["unknown kind 'spiral'", "great:", "orbit:", "list:"]),
        ("", ["unknown kind"]),
        ("list:", ["list:FILE"]),
        ("list:/no/such/dir/path.txt", ["not found"]),
        ("list:/dev/zero", ["not a regular file but a character device"]),
        ("list:/tmp", ["not a regular file but a folder"]),
    ],
)
def test_parse_light_path_errors_are_one_line_naming_the_spec(spec, fragments):
    with pytest.raises(InputError) as excinfo:
        parse_light_path(spec, 10)
    _one_line(excinfo, f"light path {spec!r}", *fragments)


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        ("1 0 0\n0 1\n", 2, "'0 1'"),
        ("# c\n1 0 0\n\n1 0 zero\n", 4, "'1 0 zero'"),
        ("1 0 0\n0 0 0\n", 2, "non-zero"),
        ("1 0 0 4\n", 1, "'x y z'"),
    ],
)
def test_parse_light_path_file_errors_name_file_and_line(tmp_path, text, line, fragment):
    path_file = tmp_path / "bad.txt"
    path_file.write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as excinfo:
        parse_light_path(f"list:{path_file}", 10)
    _one_line(excinfo, f"list:{path_file}", f"{path_file}:{line}:", fragment)


def test_parse_light_path_file_errors_for_empty_and_lp(tmp_path):
    empty = tmp_path / "empty.txt"
    empty.write_text("# only a comment\n\n", encoding="utf-8")
    with pytest.raises(InputError) as excinfo:
        parse_light_path(f"list:{empty}", 10)
    _one_line(excinfo, str(empty), "no directions")
    lp = tmp_path / "bad.lp"
    lp.write_text("2\na.png 1 0 0\nb.png 0 1\n", encoding="utf-8")
    with pytest.raises(InputError) as excinfo:
        parse_light_path(f"list:{lp}", 10)
    _one_line(excinfo, f"list:{lp}", f"{lp}:3:")


# --- output kinds ---------------------------------------------------------------------------------


def test_animation_kind(tmp_path):
    assert animation_kind(tmp_path / "a.gif") == "gif"
    assert animation_kind(tmp_path / "a.GIF") == "gif"
    assert animation_kind(tmp_path / "a.mp4") == "mp4"
    assert animation_kind(tmp_path / "frames") == "frames"
    (tmp_path / "take.v2").mkdir()
    assert animation_kind(tmp_path / "take.v2") == "frames"
    with pytest.raises(InputError) as excinfo:
        animation_kind(tmp_path / "a.avi")
    _one_line(excinfo, "'.avi'", ".gif", ".mp4", "folder")


# --- writers --------------------------------------------------------------------------------------

H, W = 40, 60


def _background(colour: bool = True) -> np.ndarray:
    rows, cols = np.mgrid[0:H, 0:W]
    if not colour:
        return (0.05 + 0.6 * cols / W).astype(np.float32)
    return np.stack([0.05 + 0.6 * cols / W, 0.1 + 0.4 * rows / H, 0.25 + 0 * cols], axis=-1).astype(np.float32)


def _frames(count: int, *, colour: bool = True, highlight: float = 3.0):
    """A still gradient with a bright highlight moving along rows 20..30 (values above 1 included)."""
    background = _background(colour)
    rows, cols = np.mgrid[20:31, 0:W]
    for k in range(count):
        image = background.copy()
        blob = highlight * np.exp(-((cols - 5 - 2 * k) ** 2 + (rows - 25) ** 2) / 8.0)
        image[20:31] += blob[..., None] * np.array([1.0, 0.9, 0.6]) if colour else blob
        yield image


def _srgb8(image: np.ndarray) -> np.ndarray:
    return np.rint(linear_to_srgb(np.clip(image, 0.0, 1.0)) * 255).astype(np.int64)


def _gif_structure(data: bytes) -> dict:
    """Walk a GIF's blocks: global table flag, loop count, per image its delay and local-table flag."""
    assert data[:6] == b"GIF89a"
    flags = data[10]
    pos = 13 + (3 * 2 ** ((flags & 7) + 1) if flags & 0x80 else 0)
    info = {"global_table": bool(flags & 0x80), "loop": None, "delays": [], "local_tables": []}
    delay = None
    while data[pos] != 0x3B:
        if data[pos] == 0x21:  # extension
            label, pos = data[pos + 1], pos + 2
            if label == 0xF9:
                delay = int.from_bytes(data[pos + 2 : pos + 4], "little")
            if label == 0xFF and data[pos + 1 : pos + 12] == b"NETSCAPE2.0":
                info["loop"] = int.from_bytes(data[pos + 14 : pos + 16], "little")
        elif data[pos] == 0x2C:  # image descriptor
            packed = data[pos + 9]
            info["local_tables"].append(bool(packed & 0x80))
            info["delays"].append(delay)
            pos += 10 + (3 * 2 ** ((packed & 7) + 1) if packed & 0x80 else 0) + 1
        else:
            raise AssertionError(f"unexpected GIF block {data[pos]:#x} at {pos}")
        while data[pos]:  # data sub-blocks
            pos += data[pos] + 1
        pos += 1
    return info


def _decoded_gif(path, mode: str) -> list[np.ndarray]:
    with Image.open(path) as im:
        frames = []
        for i in range(im.n_frames):
            im.seek(i)
            frames.append(np.asarray(im.convert(mode)).astype(np.int64))
        return frames


def test_gif_colour_one_palette_no_flicker_loops(tmp_path):
    count = 24
    target = tmp_path / "anim.gif"
    done = []
    assert write_animation(_frames(count), target, fps=24.0, progress=done.append) == target
    assert done == list(range(1, count + 1))
    with Image.open(target) as im:
        assert im.n_frames == count and im.size == (W, H) and im.info["loop"] == 0
    structure = _gif_structure(target.read_bytes())
    assert structure["global_table"] and not any(structure["local_tables"]) and structure["loop"] == 0
    assert len(structure["delays"]) == count and sum(structure["delays"]) == 100  # 24 frames at 24 fps: 1 s
    assert set(structure["delays"]) == {4, 5}
    decoded = _decoded_gif(target, "RGB")
    errors = [np.abs(d - _srgb8(f)) for d, f in zip(decoded, _frames(count))]
    assert max(e.mean() for e in errors) < 2.5  # 256 colours for ~2400 in a smooth colour ramp
    sampled = animation_module._GIF_PALETTE_FRAMES  # the palette is built from these frames
    assert max(e.max() for e in errors[:sampled]) <= 20
    assert max(e.max() for e in errors) <= 48  # later highlight halos are over colours never sampled
    # The still rows (far from the highlight) decode identically in every frame: one palette, no dither.
    for frame in decoded[1:]:
        np.testing.assert_array_equal(frame[:15], decoded[0][:15])
        np.testing.assert_array_equal(frame[36:], decoded[0][36:])


def test_gif_grayscale_is_exact(tmp_path):
    target = tmp_path / "gray.gif"
    write_animation(list(_frames(6, colour=False)), target, fps=10.0)
    decoded = _decoded_gif(target, "L")
    assert len(decoded) == 6
    for d, f in zip(decoded, _frames(6, colour=False)):
        np.testing.assert_array_equal(d, _srgb8(f))
    assert _gif_structure(target.read_bytes())["delays"] == [10] * 6


def test_gif_keeps_identical_frames(tmp_path):
    still = np.full((H, W, 3), 0.3, np.float32)
    target = tmp_path / "still.gif"
    write_animation(np.stack([still] * 5), target, fps=5.0)
    with Image.open(target) as im:
        assert im.n_frames == 5  # not merged: the frame count and timing stay as asked


@pytest.mark.parametrize("name", ["anim.webp", "anim.apng"])
@pytest.mark.parametrize("colour", [True, False])
def test_webp_and_apng_keep_every_colour_and_the_timing(tmp_path, name, colour):
    """Lossless WebP and APNG (Pillow) give every 8-bit sRGB frame back exactly, loop forever, and last
    1 s at 24 frames per second; identical neighbours become one frame of their summed duration."""
    frames = list(_frames(24, colour=colour))
    frames[10] = frames[9]
    target = tmp_path / name
    done = []
    assert write_animation(frames, target, fps=24.0, progress=done.append) == target and done == list(range(1, 25))
    with Image.open(target) as im:
        assert im.format == ("WEBP" if name.endswith(".webp") else "PNG") and im.n_frames == 23 and im.info["loop"] == 0
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            got = np.asarray(im.convert("RGB" if colour else "L"))  # (decoding the frame sets its duration)
            durations.append(im.info["duration"])
            want = _srgb8(frames[k if k < 10 else k + 1])
            np.testing.assert_array_equal(got, want if colour or got.ndim == 2 else want[..., None])
    assert sum(durations) == 1000 and durations[9] in (83, 84)
    assert animation_module.animation_kind(target) == name.split(".")[1]


@pytest.mark.parametrize("fps", [60.0, 0.0, -1.0, math.nan])
def test_gif_fps_limits(tmp_path, fps):
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(3), tmp_path / "a.gif", fps=fps)
    _one_line(excinfo, "fps")
    assert list(tmp_path.iterdir()) == []


def test_frames_folder_png(tmp_path):
    target = tmp_path / "out" / "frames"
    done = []
    write_animation(_frames(5), target, progress=done.append)
    assert done == [1, 2, 3, 4, 5]
    names = _visible(target)
    assert names == [f"frame_{i:04d}.png" for i in range(5)]
    for name, frame in zip(names, _frames(5)):
        with Image.open(target / name) as im:
            assert im.size == (W, H) and im.mode == "RGB"
            np.testing.assert_array_equal(np.asarray(im).astype(np.int64), _srgb8(frame))
    assert sorted(p.name for p in target.parent.iterdir()) == ["frames"]  # no temporaries left


def test_frames_folder_exr_keeps_linear_values(tmp_path):
    pytest.importorskip("OpenEXR")
    target = tmp_path / "linear"
    write_animation(_frames(3), target, frames_format="exr")
    names = _visible(target)
    assert names == ["frame_0000.exr", "frame_0001.exr", "frame_0002.exr"]
    for name, frame in zip(names, _frames(3)):
        image = read_image(target / name)
        np.testing.assert_array_equal(image, frame)
    assert read_image(target / names[0]).max() > 1.5  # highlights above display white survive


def test_frames_format_only_for_folders(tmp_path):
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(2), tmp_path / "a.gif", frames_format="exr")
    _one_line(excinfo, "frames_format")
    with pytest.raises(InputError):
        write_animation(_frames(2), tmp_path / "f", frames_format="tiff")
    assert list(tmp_path.iterdir()) == []


def test_frames_folder_names_widen_when_there_are_more_frames(tmp_path, monkeypatch):
    monkeypatch.setattr(animation_module, "_FRAME_DIGITS", 1)  # as with 4 digits and 10000+ frames
    tiny = np.zeros((2, 2), np.float32)
    write_animation((tiny for _ in range(11)), tmp_path / "many")  # count unknown until the end
    names = _visible(tmp_path / "many")
    assert names == [f"frame_{i:02d}.png" for i in range(11)]
    write_animation([tiny] * 3, tmp_path / "few")
    assert _visible(tmp_path / "few") == ["frame_0.png", "frame_1.png", "frame_2.png"]
    write_animation((tiny for _ in range(12)), tmp_path / "known", frame_count=12)
    assert min(_visible(tmp_path / "known")) == "frame_00.png"


def _ffmpeg_or_skip() -> None:
    try:
        animation_module._imageio_ffmpeg()
    except InputError:
        pytest.skip("no imageio-ffmpeg (the video extra)")


@pytest.mark.parametrize(("height", "width", "colour"), [(H, W, True), (21, 33, False)])
def test_mp4_written(tmp_path, height, width, colour, capfd):
    _ffmpeg_or_skip()
    import imageio_ffmpeg

    target = tmp_path / "anim.mp4"
    frames = (f[:height, :width] for f in _frames(12, colour=colour))
    done = []
    write_animation(frames, target, fps=12.0, progress=done.append)
    data = target.read_bytes()
    assert data[4:8] == b"ftyp", "not an MP4 file"
    assert done == list(range(1, 13))
    assert [p.name for p in tmp_path.iterdir()] == ["anim.mp4"]
    assert imageio_ffmpeg.count_frames_and_secs(str(target))[0] == 12
    reader = imageio_ffmpeg.read_frames(str(target))
    meta = next(reader)
    assert tuple(meta["size"]) == (width + width % 2, height + height % 2), "odd sizes padded to even"
    assert "FFREPORT" not in os.environ, "ffmpeg's report variable left set"
    assert capfd.readouterr().err == "", "ffmpeg wrote onto stderr"


def test_mp4_colours_close_to_the_frames(tmp_path):
    _ffmpeg_or_skip()
    import imageio_ffmpeg

    frames = list(_frames(6, colour=True))
    write_animation(frames, tmp_path / "a.mp4", fps=6.0)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "a.mp4"))
    meta = next(reader)
    width, height = meta["size"]
    decoded = [np.frombuffer(raw, np.uint8).reshape(height, width, 3)[: H, : W] for raw in reader]
    assert len(decoded) == 6
    expected = _srgb8(frames[3]).astype(float)
    error = np.abs(decoded[3].astype(float) - expected)
    assert np.median(error) <= 3.0, f"BT.709 round trip off by {np.median(error)} levels (median)"


def test_mp4_ffmpeg_failure_is_an_input_error(tmp_path, monkeypatch, capfd):
    _ffmpeg_or_skip()
    import imageio_ffmpeg

    write_frames = imageio_ffmpeg.write_frames
    monkeypatch.setattr(imageio_ffmpeg, "write_frames",
                        lambda *a, **k: write_frames(*a, **{**k, "codec": "no_such_encoder"}))
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(30), tmp_path / "a.mp4")
    _one_line(excinfo, "ffmpeg could not write", "no_such_encoder")
    assert list(tmp_path.iterdir()) == []
    assert capfd.readouterr().err == "", "ffmpeg's own messages reached stderr"


def test_mp4_short_video_is_an_input_error(tmp_path, monkeypatch):
    """A video that reads back with fewer frames than were sent (ffmpeg exited early, a full disk) is refused."""
    _ffmpeg_or_skip()
    import imageio_ffmpeg

    count = imageio_ffmpeg.count_frames_and_secs
    monkeypatch.setattr(imageio_ffmpeg, "count_frames_and_secs", lambda path: (count(path)[0] - 1, 0.0))
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(8), tmp_path / "a.mp4")
    _one_line(excinfo, "ffmpeg could not write", "holds 7 of 8 frames")
    assert list(tmp_path.iterdir()) == []


def test_ffmpeg_report_path_with_colon_and_backslash(tmp_path):
    """The FFREPORT value escapes ':' and '\\' (Windows drive letters), so the log lands where asked."""
    _ffmpeg_or_skip()
    import subprocess

    import imageio_ffmpeg

    folder = tmp_path / "C:odd\\name"
    folder.mkdir()
    log = folder / "ffmpeg.log"
    with animation_module._ffmpeg_report(log):
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "quiet", "-f", "lavfi", "-i", "nullsrc=s=16x16:d=0.1",
                        "-c:v", "no_such_encoder", "-f", "null", "-"], capture_output=True, check=False)
    assert "FFREPORT" not in os.environ
    assert "Unknown encoder 'no_such_encoder'" in animation_module._ffmpeg_errors(log)


def test_mp4_without_imageio_ffmpeg_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(3), tmp_path / "a.mp4")
    _one_line(excinfo, "needs the imageio-ffmpeg package", "pip install imageio-ffmpeg", ".gif")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError):
        check_animation_output(tmp_path / "a.mp4")


# --- atomicity and errors ---------------------------------------------------------------------------

KINDS = ["anim.gif", "anim.webp", "anim.apng", "frames", "anim.mp4"]


def _target(tmp_path, name):
    if name.endswith(".mp4"):
        _ffmpeg_or_skip()
    return tmp_path / name


def _failing(count: int, error: BaseException):
    for k, frame in enumerate(_frames(count + 5)):
        if k == count:
            raise error
        yield frame


def _snapshot(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()} | {
        p.relative_to(folder).as_posix() + "/": b"" for p in folder.rglob("*") if p.is_dir()
    }


@pytest.mark.parametrize("name", KINDS)
@pytest.mark.parametrize("error", [RuntimeError("renderer failed"), KeyboardInterrupt()])
def test_failure_midway_leaves_nothing(tmp_path, name, error):
    target = _target(tmp_path, name)
    with pytest.raises(type(error)):
        write_animation(_failing(10, error), target)  # past the GIF's palette frames
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", KINDS)
def test_failure_midway_keeps_existing_output(tmp_path, name):
    target = _target(tmp_path, name)
    write_animation(_frames(3), target)
    before = _snapshot(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        write_animation(_failing(4, KeyboardInterrupt()), target, overwrite=True)
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("name", KINDS)
def test_non_finite_frame_is_rejected_and_nothing_written(tmp_path, name):
    target = _target(tmp_path, name)

    def frames():
        for k, frame in enumerate(_frames(12)):
            if k == 9:
                frame[3, 4, 1] = np.inf if k % 2 else np.nan
            yield frame

    with pytest.raises(InputError) as excinfo:
        write_animation(frames(), target)
    _one_line(excinfo, "frame 9", "NaN or infinite")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", KINDS)
def test_shape_mismatch_names_the_frame(tmp_path, name):
    target = _target(tmp_path, name)
    frames = list(_frames(4))
    frames[2] = frames[2][:, :-2]
    with pytest.raises(InputError) as excinfo:
        write_animation(frames, target)
    _one_line(excinfo, "frame 2", str((H, W - 2, 3)), str((H, W, 3)))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("frame", [np.zeros((H, W, 4)), np.zeros((3, H, W, 3)), np.zeros((0, W))])
def test_bad_frame_shape(tmp_path, frame):
    with pytest.raises(InputError) as excinfo:
        write_animation([frame], tmp_path / "a.gif")
    _one_line(excinfo, "frame 0", "(H, W) or (H, W, 3)")


def test_no_frames_and_wrong_frame_count(tmp_path):
    for empty in (iter([]), [], np.zeros((0, H, W))):
        with pytest.raises(InputError) as excinfo:
            write_animation(empty, tmp_path / "a.gif")
        _one_line(excinfo, "no frames")
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(3), tmp_path / "frames", frame_count=4)
    _one_line(excinfo, "3 frames", "frame_count", "4")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", KINDS)
def test_existing_output_needs_overwrite(tmp_path, name):
    target = _target(tmp_path, name)
    write_animation(_frames(2), target)
    before = _snapshot(tmp_path)
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(3), target)
    _one_line(excinfo, str(target), "--overwrite")
    assert _snapshot(tmp_path) == before
    write_animation(_frames(3), target, overwrite=True)
    assert _snapshot(tmp_path) != before
    if name == "frames":
        assert len(_visible(target)) == 3
    if name.endswith(".gif"):
        with Image.open(target) as im:
            assert im.n_frames == 3


def test_frames_folder_with_other_files_is_never_replaced(tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me", encoding="utf-8")
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(2), folder, overwrite=True)
    _one_line(excinfo, "notes.txt", "did not write")
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]
    empty = tmp_path / "empty.d"
    empty.mkdir()  # an existing empty folder (any name) is a fine target without overwrite
    write_animation(_frames(2), empty)
    assert len(_visible(empty)) == 2
    (empty / "later.txt").write_text("added by the user", encoding="utf-8")  # not in the manifest
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(2), empty, overwrite=True)
    _one_line(excinfo, "later.txt", "did not write")
    assert (empty / "later.txt").read_text(encoding="utf-8") == "added by the user"


def test_file_target_that_is_a_folder(tmp_path):
    (tmp_path / "a.gif").mkdir()
    with pytest.raises(InputError) as excinfo:
        write_animation(_frames(2), tmp_path / "a.gif", overwrite=True)
    _one_line(excinfo, "is a folder")


@pytest.mark.parametrize("name", ["anim.gif", "frames"])
def test_writers_stream(tmp_path, name):
    """Frames are written while the source still yields: at most the GIF's palette sample is held."""
    written = []
    lag = []

    def frames():
        for k, frame in enumerate(_frames(30)):
            lag.append(k - (written[-1] if written else 0))
            yield frame

    write_animation(frames(), tmp_path / name, progress=written.append)
    assert written[-1] == 30
    assert max(lag) <= (animation_module._GIF_PALETTE_FRAMES if name.endswith(".gif") else 1)


def test_gif_of_an_orbit_stays_compact(small_field, tmp_path):
    """Bytes per pixel and frame of a 96-frame orbit GIF, a guard on the palette and encoder: 0.27 for
    this field at 240x135 (the demo field's orbit 0.20, the 250-light 480x270 donut's 0.12, at 1920x1080
    0.068), bounded at 0.35."""
    from warp_highlights.cli import main

    out = tmp_path / "orbit.gif"
    assert main(["animate", str(small_field), "--path", "orbit:35", "--frames", "96", "--size", "240x135", "-o",
                 str(out),
                 "--device", "cpu", "-q"]) == 0
    with Image.open(out) as im:
        assert im.n_frames == 96 and im.size == (240, 135)
    per_pixel = out.stat().st_size / (96 * 240 * 135)
    assert per_pixel <= 0.35, per_pixel


def test_default_size_gif_is_at_most_a_quarter_at_equal_frames(small_field, tmp_path, monkeypatch):
    """A field four times the default longer side (as a 1920x1080 field is to 480): its 96-frame orbit
    GIF without --size is at most a quarter of the one at the field's size (13.5 MB -> 1.5 MB for the
    1920x1080 / 480x270 donut)."""
    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import load_field

    field = load_field(small_field)
    monkeypatch.setitem(animation_module.DEFAULT_LONGER_SIDE, "gif", max(field.width, field.height) // 4)
    common = ["--path", "orbit:35", "--frames", "96", "--device", "cpu", "-q"]
    assert main(["animate", str(small_field), *common, "--size", f"{field.width}x{field.height}", "-o",
                 str(tmp_path / "full.gif")]) == 0
    assert main(["animate", str(small_field), *common, "-o", str(tmp_path / "default.gif")]) == 0
    with Image.open(tmp_path / "default.gif") as im:
        assert im.n_frames == 96, "equal frames"
        assert im.size == animation_module.default_animation_size("gif", field.width, field.height)
        assert max(im.size) <= max(field.width, field.height) // 4
    ratio = (tmp_path / "default.gif").stat().st_size / (tmp_path / "full.gif").stat().st_size
    assert ratio <= 0.25, ratio


@pytest.mark.parametrize(("kind", "size", "expected"), [
    ("gif", (1920, 1080), (480, 270)), ("webp", (1080, 1920), (270, 480)), ("apng", (567, 534), (480, 452)),
    ("gif", (240, 135), (240, 135)), ("gif", (480, 3), (480, 3)), ("gif", (4000, 3), (1333, 1)),
    ("mp4", (3840, 2160), (1920, 1080)), ("mp4", (1920, 1080), (1920, 1080)), ("frames", (3840, 2160), (3840, 2160)),
])
def test_default_animation_size(kind, size, expected):
    width, height = animation_module.default_animation_size(kind, *size)
    assert (width, height) == expected
    longest = animation_module.DEFAULT_LONGER_SIDE[kind]
    if longest is not None and min(size) * longest >= max(size):  # not thinner than 1 : longest
        assert max(width, height) <= longest
    assert abs(width - size[0] * height / size[1]) <= 1.0, "the relighter's aspect-ratio rule"


def test_animate_default_size_shrinks_web_animations_only(small_field, tmp_path, monkeypatch, capsys):
    """Without --size, a GIF is shrunk to the default longer side; a frames folder keeps the field's size."""
    from PIL import Image

    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import load_field

    field = load_field(small_field)
    longest = max(field.width, field.height) // 2
    monkeypatch.setitem(animation_module.DEFAULT_LONGER_SIDE, "gif", longest)
    assert main(["animate", str(small_field), "--path", "orbit:35", "--frames", "3", "-o", str(tmp_path / "a.gif"),
                 "--device", "cpu"]) == 0
    expected = animation_module.default_animation_size("gif", field.width, field.height)
    assert max(expected) == longest
    with Image.open(tmp_path / "a.gif") as im:
        assert im.size == expected
    assert f"animating at {expected[0]}x{expected[1]}" in capsys.readouterr().err, "the shrink is said"
    assert main(["animate", str(small_field), "--path", "orbit:35", "--frames", "3", "-o", str(tmp_path / "frames"),
                 "--device", "cpu", "-q"]) == 0
    assert read_image(tmp_path / "frames" / "frame_0000.png").shape[:2] == (field.height, field.width)
    assert main(["animate", str(small_field), "--path", "orbit:35", "--frames", "3", "--size",
                 f"{field.width}x{field.height}",
                 "-o", str(tmp_path / "b.gif"), "--device", "cpu", "-q"]) == 0
    with Image.open(tmp_path / "b.gif") as im:
        assert im.size == (field.width, field.height), "--size wins over the default"
