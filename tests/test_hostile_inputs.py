"""Hostile inputs to the readers: each is refused with exactly one one-line InputError that
names the file and the problem, before anything large is allocated and without a library's traceback."""

from __future__ import annotations

import math
import os
import struct
import warnings
import zlib

import numpy as np
import pytest

from warp_highlights.io import dataset as dataset_module
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.images import (
    DEFAULT_MAX_PIXELS,
    image_shape,
    image_size,
    read_image,
    write_image,
)
from warp_highlights.io.lightfile import read_lp, write_lp
from warp_highlights.model import memory as memory_module
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation

OpenEXR = pytest.importorskip("OpenEXR")
Image = pytest.importorskip("PIL.Image")
ImageFile = pytest.importorskip("PIL.ImageFile")
pytest.importorskip("tqdm")


def _one_line(excinfo, *needles: str) -> str:
    message = str(excinfo.value)
    assert "\n" not in message and "Traceback" not in message and "QH" not in message
    for needle in needles:
        assert needle in message, message
    return message


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _bomb_png(path, width: int = 20000, height: int = 20000) -> None:
    """A complete, valid 1-bit PNG of width x height black pixels: 400 MP in about 50 kB."""
    row = b"\0" * (1 + math.ceil(width / 8))  # filter byte, then the packed pixels
    packer = zlib.compressobj(9)
    data = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", data)
                     + _png_chunk(b"IEND", b""))


def _capture(folder, images, *, names=None, lights=None, suffix=".png"):
    """A dataset folder: the given (H, W[, 3]) linear images as PNG/JPEG/EXR, and dirs.lp listing them."""
    folder.mkdir(parents=True, exist_ok=True)
    lights = lights if lights is not None else LightSet.fibonacci_dome(len(images))
    files = [f"image{i:02d}{suffix}" for i in range(len(images))]
    for file, image in zip(files, images):
        write_image(folder / file, image)
    write_lp(lights, folder / "dirs.lp", names or files)
    return folder


# --- decompression bomb --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    path = tmp_path_factory.mktemp("bomb") / "bomb.png"
    _bomb_png(path)
    assert path.stat().st_size < 100_000
    return path


@pytest.mark.parametrize("reader", [read_image, image_size, image_shape])
def test_a_decompression_bomb_is_refused_from_its_header(bomb, reader):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # Pillow's DecompressionBombWarning would fail the test
        with pytest.raises(InputError) as excinfo:
            reader(bomb)
    _one_line(excinfo, "bomb.png", "20000x20000", "400.0 megapixels", "limit of 160 megapixels", "--max-megapixels 400")


def test_the_pixel_limit_can_be_lifted_or_lowered(bomb, tmp_path):
    assert image_size(bomb, max_pixels=None) == (20000, 20000)
    assert image_shape(bomb, max_pixels=400_000_000) == (20000, 20000)
    path = tmp_path / "small.exr"
    write_image(path, np.ones((10, 20), np.float32))
    assert read_image(path, max_pixels=200).shape == (10, 20)
    with pytest.raises(InputError) as excinfo:
        read_image(path, max_pixels=199)
    _one_line(excinfo, "small.exr", "20x10")


def test_default_limit_admits_a_150_megapixel_back():
    assert 14204 * 10652 <= DEFAULT_MAX_PIXELS < 20000 * 20000  # Phase One IQ4 150MP, and the bomb


def test_pillow_limits_are_ours_during_a_read_and_restored_after(tmp_path, monkeypatch):
    path = tmp_path / "a.png"
    write_image(path, np.full((30, 40), 0.5))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # someone's tight limit: 1200 px is a "bomb" to Pillow
    monkeypatch.setattr(ImageFile, "LOAD_TRUNCATED_IMAGES", True)  # and someone's lax truncation setting
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_image(path).shape == (30, 40)
    assert Image.MAX_IMAGE_PIXELS == 100 and ImageFile.LOAD_TRUNCATED_IMAGES is True


def test_a_dataset_holding_a_bomb_is_refused_before_any_pixel_is_decoded(bomb, tmp_path, monkeypatch):
    folder = _capture(tmp_path / "d", [np.full((4, 5), 0.5)] * 3)
    (folder / "image01.png").write_bytes(bomb.read_bytes())

    def no_decoding(*args, **kwargs):
        raise AssertionError("an image was decoded")

    monkeypatch.setattr(dataset_module, "read_image", no_decoding)
    monkeypatch.setattr(dataset_module, "read_pixels", no_decoding)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _one_line(excinfo, "image01.png", "400.0 megapixels", "--max-megapixels")


def test_info_on_a_bomb_exits_2_with_one_line(bomb, tmp_path, capsys):
    from warp_highlights.cli import main

    folder = _capture(tmp_path / "d", [np.full((4, 5), 0.5)] * 4)
    (folder / "image02.png").write_bytes(bomb.read_bytes())
    capsys.readouterr()
    status = main(["info", str(folder), "--quiet"])
    err = capsys.readouterr().err
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err and "DecompressionBomb" not in err, err
    assert "image02.png" in lines[0] and "megapixels" in lines[0]


# --- truncated and damaged files -----------------------------------------------------------------------


@pytest.mark.parametrize("lax", [False, True])
@pytest.mark.parametrize("cut", [0.5, 0.9, -2])  # mid-scan, near the end, just the end-of-image marker
def test_a_truncated_jpeg_is_refused_not_filled_with_grey(tmp_path, monkeypatch, lax, cut):
    monkeypatch.setattr(ImageFile, "LOAD_TRUNCATED_IMAGES", lax)
    path = tmp_path / "cut.jpg"
    rgb = np.random.default_rng(0).integers(0, 256, (48, 64, 3)).astype(np.uint8)
    Image.fromarray(rgb).save(path, format="JPEG", quality=90)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)] if cut > 0 else data[:cut])
    with pytest.raises(InputError) as excinfo:
        read_image(path)
    _one_line(excinfo, "cut.jpg", "cannot read image")


@pytest.mark.parametrize("suffix", [".png", ".exr"])
def test_a_truncated_png_or_exr_is_refused_quietly(tmp_path, capfd, suffix):
    path = tmp_path / f"cut{suffix}"
    write_image(path, np.random.default_rng(1).uniform(0, 1, (40, 50, 3)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    capfd.readouterr()
    with pytest.raises(InputError) as excinfo:
        read_image(path)
    _one_line(excinfo, path.name, "cannot read image")
    assert capfd.readouterr().err == ""  # OpenEXR's own messages on stderr are held back


def _exr_with_window(path, corners) -> None:
    write_image(path, np.ones((3, 4, 3), np.float32))
    data = bytearray(path.read_bytes())
    key = b"dataWindow\0box2i\0\x10\0\0\0"
    at = data.index(key) + len(key)
    data[at : at + 16] = struct.pack("<4i", *corners)
    path.write_bytes(bytes(data))


def test_an_exr_claiming_a_billion_pixels_is_refused_without_reading_pixels(tmp_path, monkeypatch):
    path = tmp_path / "huge.exr"
    _exr_with_window(path, (0, 0, 31622, 31622))  # 31623^2 = 1.0e9 pixels, 12 GB as float32 RGB
    opened = []
    real_file = OpenEXR.File

    def recording_file(*args, **kwargs):
        opened.append(kwargs.get("header_only", False))
        return real_file(*args, **kwargs)

    monkeypatch.setattr(OpenEXR, "File", recording_file)
    for reader in (read_image, image_size, image_shape):
        with pytest.raises(InputError) as excinfo:
            reader(path)
        _one_line(excinfo, "huge.exr", "31623x31623", "1000.0 megapixels", "--max-megapixels 1001")
    assert opened and all(opened), "the pixels were read"


@pytest.mark.parametrize("corners", [(0, 0, -5, -5), (10, 10, 0, 0), (-(2**31), -(2**31), 2**31 - 1, 2**31 - 1)])
def test_an_exr_with_an_inverted_or_absurd_window_is_refused(tmp_path, corners):
    path = tmp_path / "window.exr"
    _exr_with_window(path, corners)
    for reader in (read_image, image_size):
        with pytest.raises(InputError) as excinfo:
            reader(path)
        _one_line(excinfo, "window.exr")


# --- degenerate captures -------------------------------------------------------------------------------


def test_an_image_listed_twice_is_refused_naming_the_line(tmp_path):
    folder = _capture(tmp_path / "d", [np.full((4, 5), v) for v in (0.2, 0.4, 0.6)],
                      names=["image00.png", "image01.png", "./image00.png"])
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _one_line(excinfo, "dirs.lp:4:", "'./image00.png' is listed again (first on line 2)")
    assert read_lp(folder / "dirs.lp", check_files=False).light_count == 3  # directions alone are fine


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"\xff\xfe3\x00\n", "not valid UTF-16 text"),  # cut inside a UTF-16 character
        (b"9" * 5000 + b"\n", "absurdly large"),  # int() refuses over 4300 digits
        (b"1\n" + b"a" * 300 + b" 0 0 1\n", "not found"),  # a name no file system takes
    ],
)
def test_hostile_light_files_are_refused_in_one_line(tmp_path, content, needle):
    path = tmp_path / "hostile.lp"
    path.write_bytes(content)
    with pytest.raises(InputError) as excinfo:
        read_lp(path)
    _one_line(excinfo, "hostile.lp", needle)


def test_extreme_but_valid_light_vectors_are_read(tmp_path):
    path = tmp_path / "extreme.lp"
    path.write_text("2\na.jpg 1e308 1e308 1e308\nb.jpg 5e-324 0 5e-324\n")
    np.testing.assert_allclose(read_lp(path, check_files=False).directions, [[3**-0.5] * 3, [2**-0.5, 0, 2**-0.5]])


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".exr"])
def test_an_all_black_capture_is_refused(tmp_path, suffix):
    folder = _capture(tmp_path / "d", [np.zeros((6, 8, 3))] * 5, suffix=suffix)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _one_line(excinfo, "dirs.lp", "all 5 images are entirely black")


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_an_all_white_capture_is_refused(tmp_path, suffix):
    folder = _capture(tmp_path / "d", [np.ones((6, 8))] * 5, suffix=suffix)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _one_line(excinfo, "dirs.lp", "all 5 images are entirely white", "over-exposed")


def test_a_few_black_images_and_bright_exrs_are_fine(tmp_path):
    images = [np.zeros((6, 8)), np.full((6, 8), 0.3), np.zeros((6, 8)), np.full((6, 8), 0.7)]
    assert ReflectanceField.load(_capture(tmp_path / "a", images), progress=False).light_count == 4
    bright = [np.full((6, 8), 5.0)] * 4  # absolute radiance: above 1 everywhere is no saturation in an EXR
    assert ReflectanceField.load(_capture(tmp_path / "b", bright, suffix=".exr"), progress=False).light_count == 4


def _ring(count: int, elevation_deg: float, decimals: int | None = None) -> np.ndarray:
    azimuth = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    elevation = np.radians(elevation_deg)
    ring = np.stack([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation),
                     np.full(count, np.sin(elevation))], axis=1)
    return ring if decimals is None else np.round(ring, decimals)


@pytest.mark.parametrize(
    ("directions", "needle"),
    [
        (np.eye(3), "3 lights cannot be triangulated"),
        (_ring(16, 30.0), "the 16 lights lie on one circle"),
        (_ring(24, 45.0, decimals=6), "the 24 lights lie on one circle"),  # as a .lp file rounds them
        (_ring(12, 0.0), "the 12 lights lie on one circle"),  # a great circle
        (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0.6, 0.8, 0]]), "lie on one circle"),
    ],
)
def test_degenerate_light_sets_are_refused_in_words(directions, needle):
    with pytest.raises(InputError) as excinfo:
        SphericalTriangulation(directions)
    _one_line(excinfo, needle, "several elevations")


def test_two_rings_triangulate():
    tri = SphericalTriangulation(np.concatenate([_ring(12, 20.0), _ring(12, 21.0)]))
    assert tri.is_dome and tri.face_count > 0


@pytest.mark.parametrize(("count", "elevations", "needle"), [(3, None, "3 lights"), (12, 35.0, "one circle")])
def test_info_on_a_degenerate_capture_exits_2_naming_the_folder(tmp_path, capsys, count, elevations, needle):
    from warp_highlights.cli import main

    lights = LightSet.fibonacci_dome(count) if elevations is None else LightSet(_ring(count, elevations))
    folder = _capture(tmp_path / "d", [np.full((4, 5), 0.1 * (i + 1)) for i in range(count)], lights=lights)
    capsys.readouterr()
    status = main(["info", str(folder), "--quiet"])
    err = capsys.readouterr().err
    assert status == 2 and len(err.strip().splitlines()) == 1, err
    assert str(folder) in err and needle in err and "Qhull" not in err


# --- memory ------------------------------------------------------------------------------------------


def test_a_capture_too_big_for_memory_is_refused_before_decoding(tmp_path, monkeypatch):
    folder = _capture(tmp_path / "d", [np.full((30, 40, 3), 0.5)] * 5)
    # needed: (5 + 2) x 30 x 40 x 3 x 4 bytes (one decoding thread)
    monkeypatch.setattr(memory_module, "available_memory", lambda: 50_000)
    for reader in ("read_image", "read_pixels"):
        monkeypatch.setattr(dataset_module, reader, lambda *a, **k: pytest.fail("an image was decoded"))
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False, workers=1)
    message = _one_line(excinfo, "loading needs about 100.8 kB",
                        "(5 images of 40x30x3 as float32) but 50.0 kB is available")
    assert str(folder) in message


def test_unknown_memory_refuses_nothing(tmp_path, monkeypatch):
    folder = _capture(tmp_path / "d", [np.full((30, 40, 3), 0.5)] * 5)
    monkeypatch.setattr(memory_module, "available_memory", lambda: None)
    assert ReflectanceField.load(folder, progress=False).light_count == 5
    monkeypatch.undo()
    available = memory_module.available_memory()
    assert available is None or available > 0


def test_a_pipe_given_as_the_field_file_is_refused_without_blocking(tmp_path):
    from warp_highlights.io.fieldfile import load_field

    pipe = tmp_path / "field.whf"
    os.mkfifo(pipe)
    with pytest.raises(InputError) as excinfo:
        load_field(pipe)  # opening a FIFO for reading would wait for a writer forever
    _one_line(excinfo, "not a regular file")


def test_meta_json_nested_absurdly_deep_is_one_line(tmp_path):
    folder = _capture(tmp_path / "d", [np.full((30, 40, 3), 0.5)] * 5)
    (folder / "meta.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _one_line(excinfo, "meta.json", "nested too deeply")


def test_peak_memory_sees_an_array_held_for_a_moment():
    """``PeakMemory`` reports the resident peak of its block: an array of 300 MB touched and freed
    inside it shows; device None off CUDA."""
    import numpy as np
    import warp as wp

    from warp_highlights.model.memory import PeakMemory, resident_memory

    before = resident_memory()
    if before is None:
        pytest.skip("this system does not report the process's resident memory")
    with PeakMemory("cpu") as peak:
        block = np.ones(300_000_000 // 8)
        del block
    assert peak.host >= before + 250_000_000 and peak.device is None
    with PeakMemory("cpu") as quiet:
        pass
    assert quiet.host < peak.host
    if wp.is_cuda_available():
        with PeakMemory("cuda:0") as gpu:
            array = wp.zeros(50_000_000, dtype=float, device="cuda:0")
            wp.synchronize_device("cuda:0")
            del array
        assert gpu.device >= 200_000_000
