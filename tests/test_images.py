"""Image IO: sRGB transfer function, EXR / PNG 8+16-bit / JPEG round trips, clean errors."""

from __future__ import annotations

import numpy as np
import pytest

from warp_highlights.io import images as images_module
from warp_highlights.io.images import (
    encode_levels,
    image_size,
    linear_to_srgb,
    read_image,
    srgb_to_linear,
    write_image,
)
from warp_highlights.model.errors import InputError

pytest.importorskip("OpenEXR")
Image = pytest.importorskip("PIL.Image")


def _png_header(path) -> tuple[int, int]:
    """(bit depth, colour type) from a PNG's IHDR chunk."""
    head = path.read_bytes()[:26]
    return head[24], head[25]


def _single_line_error(excinfo, path) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    assert path.name in message
    return message


# --- sRGB -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("encoded", "linear"),
    [
        (0.0, 0.0),
        (1.0, 1.0),
        (0.04045, 0.04045 / 12.92),
        (0.5, 0.21404114),
        (128 / 255, 0.21586050),
        (0.02, 0.02 / 12.92),
    ],
)
def test_srgb_known_values(encoded, linear):
    # The standard's rounded thresholds (0.04045, 0.0031308) leave a step of ~3e-8 at the boundary.
    assert srgb_to_linear(encoded) == pytest.approx(linear, abs=1e-8)
    assert linear_to_srgb(linear) == pytest.approx(encoded, abs=1e-7)


def test_srgb_boundary_uses_the_linear_segment():
    assert srgb_to_linear(0.04045) == 0.04045 / 12.92
    assert linear_to_srgb(0.0031308) == 0.0031308 * 12.92
    below, above = srgb_to_linear(np.array([0.04045, np.nextafter(0.04045, 1.0)]))
    assert 0.0 < above - below < 1e-8


def test_srgb_round_trip_and_dtypes():
    x = np.linspace(0.0, 1.0, 10001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert srgb_to_linear(x.astype(np.float32)).dtype == np.float32
    assert linear_to_srgb(np.arange(3)).dtype == np.float64


def test_8_bit_srgb_codes_are_those_of_the_float64_curve():
    """The table lookup gives exactly the rounded float64 sRGB code, at every code's start and around it."""
    rng = np.random.default_rng(3)
    starts = srgb_to_linear((np.arange(1, 256) - 0.5) / 255)
    # a code's start itself is a tie (rounds half up here, half to even in np.rint), and within a few float64
    # steps of it the reference's power function rounds either way: probed a billionth on each side
    probes = np.concatenate([rng.random(200_000), rng.random(50_000) ** 8, starts * (1 - 1e-9), starts * (1 + 1e-9),
                             [0.0, 1.0, -1.0, 2.0, np.nan, np.inf, -np.inf]])
    probes = probes[: len(probes) // 7 * 7]
    for dtype in (np.float64, np.float32):
        values = probes.astype(dtype)
        reference = np.rint(linear_to_srgb(np.clip(np.nan_to_num(values.astype(np.float64), nan=0.0), 0, 1)) * 255)
        codes = encode_levels(values.reshape(-1, 7, 1), 255, linear=False)
        assert codes.dtype == np.uint8 and codes.shape == (len(values) // 7, 7, 1)
        np.testing.assert_array_equal(codes.reshape(-1), reference)


def test_16_bit_and_linear_codes_round_the_clipped_value():
    values = np.array([-0.5, 0.0, 0.25, 0.5, 1.0, 3.0, np.nan], np.float32)
    assert encode_levels(values, 255, linear=True).tolist() == [0, 0, 64, 128, 255, 255, 0]
    expected = np.rint(linear_to_srgb(np.clip(np.nan_to_num(values.astype(np.float64)), 0, 1)) * 65535)
    assert np.abs(encode_levels(values, 65535, linear=False).astype(np.int64) - expected).max() <= 1


# --- EXR ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3)])
def test_exr_round_trip_float32_is_exact(tmp_path, shape):
    image = (np.random.default_rng(1).standard_normal(shape) * 100.0).astype(np.float32)
    path = tmp_path / "a.exr"
    write_image(path, image)
    back = read_image(path)
    assert back.dtype == np.float32 and back.shape == shape
    np.testing.assert_array_equal(back, image)
    assert image_size(path) == (7, 5)


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3)])
def test_exr_round_trip_half_is_exact_to_half(tmp_path, shape):
    image = np.random.default_rng(2).uniform(-4, 40, shape).astype(np.float32)
    path = tmp_path / "a.exr"
    write_image(path, image, half=True)
    np.testing.assert_array_equal(read_image(path), image.astype(np.float16).astype(np.float32))


def test_exr_keeps_nonfinite_values(tmp_path):
    image = np.array([[np.nan, np.inf], [-np.inf, 1.0]], dtype=np.float32)
    write_image(tmp_path / "a.exr", image)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), image)


def _foreign_exr(path, planes: dict) -> None:
    """An EXR of ``planes`` (name -> (H, W) array, its dtype the stored type), as another tool writes it."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {name: np.ascontiguousarray(plane) for name, plane in planes.items()}).write(str(path))


@pytest.mark.parametrize("layout", ["RGB half", "RGB float", "RGBA half", "RGB mixed types", "RGB and Z", "Y",
                                    "one channel", "Y and A"])
def test_exr_channel_layouts_read_as_each_channel_alone(tmp_path, layout):
    """R, G and B as OpenEXR groups them (one interleaved "RGB" or "RGBA" channel), or alone where it does
    not (mixed types): the values of each kept channel read alone, widened to float32; ``read_pixels`` the
    same values as stored (what the loader copies into its stack), with or without the header read first."""
    import OpenEXR

    from warp_highlights.io.images import image_header, read_pixels

    rng = np.random.default_rng(7)

    def plane(dtype):
        return rng.uniform(-2.0, 60.0, size=(9, 13)).astype(dtype)

    planes = {
        "RGB half": {"R": plane(np.float16), "G": plane(np.float16), "B": plane(np.float16)},
        "RGB float": {"R": plane(np.float32), "G": plane(np.float32), "B": plane(np.float32)},
        "RGBA half": {"R": plane(np.float16), "G": plane(np.float16), "B": plane(np.float16), "A": plane(np.float16)},
        "RGB mixed types": {"R": plane(np.float16), "G": plane(np.float32), "B": plane(np.float16)},
        "RGB and Z": {"R": plane(np.float16), "G": plane(np.float16), "B": plane(np.float16), "Z": plane(np.float32)},
        "Y": {"Y": plane(np.float16)},
        "one channel": {"depth": plane(np.float32)},
        "Y and A": {"Y": plane(np.float32), "A": plane(np.float32)},
    }[layout]
    path = tmp_path / "a.exr"
    _foreign_exr(path, planes)
    alone = {name: channel.pixels
             for name, channel in OpenEXR.File(str(path), separate_channels=True).channels().items()}
    keep = ("R", "G", "B") if "R" in planes else ("Y",) if "Y" in planes else tuple(planes)
    expected = (np.stack([alone[name].astype(np.float32) for name in keep], axis=-1) if len(keep) == 3
                else alone[keep[0]].astype(np.float32))
    image = read_image(path)
    assert image.dtype == np.float32 and image.flags.writeable and image.flags.owndata
    np.testing.assert_array_equal(image, expected)
    header = image_header(path)
    assert header.shape == expected.shape and header.exr_channels == keep
    for given in (None, header):
        stored = read_pixels(path, header=given)
        widened = np.empty(stored.shape, np.float32)
        np.copyto(widened, stored, casting="unsafe")
        np.testing.assert_array_equal(widened, expected)


def test_an_exr_with_a_subsampled_alpha_is_read_quietly_as_before(tmp_path, capfd):
    """R, G and B at every pixel beside an alpha at every other: the header says OpenEXR will not group them,
    so they are read apart at once (an attempt to group them prints a warning on stdout)."""
    import OpenEXR

    rng = np.random.default_rng(8)
    planes = {name: rng.uniform(0.0, 4.0, size=(8, 10)).astype(np.float16) for name in "RGB"}
    channels = {name: OpenEXR.Channel(name, plane) for name, plane in planes.items()}
    # stored at every other pixel
    channels["A"] = OpenEXR.Channel("A", rng.uniform(size=(8, 10)).astype(np.float16), 2, 2)
    path = tmp_path / "a.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))
    capfd.readouterr()
    image = read_image(path)
    np.testing.assert_array_equal(image, np.stack([planes[name].astype(np.float32) for name in "RGB"], axis=-1))
    shown = capfd.readouterr()
    assert shown.out == "" and shown.err == ""


# --- PNG ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("channels", [1, 3])
def test_png_8bit_round_trip(tmp_path, channels):
    rng = np.random.default_rng(3)
    levels = rng.permutation(np.tile(np.arange(256, dtype=np.uint8), 3 * channels)).reshape(12, 64, channels)
    levels = levels[:, :, 0] if channels == 1 else levels
    path = tmp_path / "a.png"
    write_image(path, srgb_to_linear(levels / 255.0))
    assert _png_header(path) == (8, 0 if channels == 1 else 2)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), levels)
    np.testing.assert_array_equal(read_image(path), srgb_to_linear(levels / 255.0).astype(np.float32))
    np.testing.assert_array_equal(read_image(path, linear=True), (levels / 255.0).astype(np.float32))


@pytest.mark.parametrize("channels", [1, 3])
def test_png_16bit_keeps_all_65536_levels(tmp_path, channels):
    levels = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    if channels == 3:
        levels = np.stack([levels, levels[::-1], levels.T], axis=-1)
    path = tmp_path / "a.png"
    write_image(path, levels / 65535.0, bits=16, linear=True)
    assert _png_header(path) == (16, 0 if channels == 1 else 2)
    back = read_image(path, linear=True)
    assert back.shape == levels.shape
    np.testing.assert_array_equal(np.rint(back * 65535.0).astype(np.uint16), levels)
    assert np.unique(back).size == 65536


@pytest.mark.parametrize("shape", [(9, 11), (9, 11, 3)])
def test_png_16bit_srgb_round_trip(tmp_path, shape):
    image = np.random.default_rng(4).uniform(0.0, 1.0, shape).astype(np.float32)
    write_image(tmp_path / "a.png", image, bits=16)
    np.testing.assert_allclose(read_image(tmp_path / "a.png"), image, atol=2e-5)


def test_png_16bit_rgba_drops_alpha(tmp_path):
    levels = np.random.default_rng(5).integers(0, 65536, (6, 8, 4)).astype(np.uint16)
    path = tmp_path / "rgba.png"
    images_module._write_with_oiio(path, "png", levels)
    assert _png_header(path) == (16, 6)
    back = read_image(path, linear=True)
    np.testing.assert_array_equal(np.rint(back * 65535.0).astype(np.uint16), levels[:, :, :3])


@pytest.mark.parametrize(
    ("mode", "shape"),
    [("L", (4, 6)), ("LA", (4, 6)), ("RGB", (4, 6, 3)), ("RGBA", (4, 6, 3)), ("P", (4, 6, 3)), ("1", (4, 6))],
)
def test_png_modes_convert(tmp_path, mode, shape):
    rgb = np.random.default_rng(6).integers(0, 256, (4, 6, 3)).astype(np.uint8)
    Image.fromarray(rgb).convert(mode).save(tmp_path / "a.png")
    back = read_image(tmp_path / "a.png")
    assert back.shape == shape and back.dtype == np.float32
    if mode in ("RGB", "RGBA"):
        np.testing.assert_array_equal(back, srgb_to_linear(rgb / 255.0).astype(np.float32))


def test_png_clips_and_zeroes_nan_on_write(tmp_path):
    write_image(tmp_path / "a.png", np.array([[-1.0, 2.0, np.nan]]))
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), [[0.0, 1.0, 0.0]])


# --- JPEG -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".jpg", ".jpeg", ".JPG"])
def test_jpeg_reads_with_correct_size(tmp_path, suffix):
    rgb = np.full((23, 37, 3), (200, 120, 40), dtype=np.uint8)
    path = tmp_path / f"a{suffix}"
    Image.fromarray(rgb).save(path, format="JPEG", quality=95)
    image = read_image(path)
    assert image.shape == (23, 37, 3) and image.dtype == np.float32
    assert image_size(path) == (37, 23)
    np.testing.assert_allclose(image, srgb_to_linear(rgb / 255.0), atol=0.02)


def test_jpeg_write_round_trip(tmp_path):
    image = np.full((16, 16), 0.25, dtype=np.float32)
    write_image(tmp_path / "a.jpg", image)
    back = read_image(tmp_path / "a.jpg")
    assert back.shape == (16, 16)
    np.testing.assert_allclose(back, image, atol=0.01)


@pytest.mark.realdata
def test_real_samples(data_root):
    folder = data_root / "synthrti-object1-material5" / "Dome"
    image = read_image(folder / "image01.jpg")
    assert image.shape == (320, 320, 3) and 0.0 <= image.min() and image.max() <= 1.0
    assert image_size(folder / "image01.jpg") == (320, 320)
    normals = read_image(folder / "normals.png", linear=True)  # 16-bit RGB PNG
    assert normals.shape == (320, 320, 3)
    assert np.unique(normals).size > 256  # Pillow alone would have cut it to 8 bits


# --- errors and atomic writes ---------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "none.png"
    with pytest.raises(InputError) as excinfo:
        read_image(path)
    assert "not found" in _single_line_error(excinfo, path)
    with pytest.raises(InputError):
        image_size(path)


def test_unsupported_extension_lists_supported(tmp_path):
    path = tmp_path / "a.bmp"
    path.write_bytes(b"BM\x00\x00")
    for call in (read_image, image_size, lambda p: write_image(p, np.zeros((2, 2)))):
        with pytest.raises(InputError) as excinfo:
            call(path)
        assert ".exr, .png, .jpg, .jpeg, .tif, .tiff" in _single_line_error(excinfo, path)


@pytest.mark.parametrize("suffix", [".exr", ".png", ".jpg"])
def test_corrupt_file_is_named(tmp_path, suffix):
    path = tmp_path / f"broken{suffix}"
    path.write_bytes(b"this is not an image" * 20)
    with pytest.raises(InputError) as excinfo:
        read_image(path)
    assert "cannot read image" in _single_line_error(excinfo, path)


@pytest.mark.parametrize(
    ("damage", "channels"),
    [("truncate", 1), ("truncate", 3), ("flip_byte", 1), ("flip_byte", 3)],
)
def test_damaged_16bit_png_is_reported_not_fatal(tmp_path, damage, channels):
    # libpng (inside OpenImageIO) reports each of these; a file whose image data is whole but whose
    # end chunk is missing is read (test_png_without_its_end_chunk_reads_its_whole_data).
    shape = (64, 64) if channels == 1 else (64, 64, 3)
    path = tmp_path / "a.png"
    write_image(path, np.random.default_rng(7).uniform(0, 1, shape), bits=16)
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "drop_end":
        data = data[:-12]
    else:
        data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as excinfo:
        read_image(path)
    assert "cannot read image" in _single_line_error(excinfo, path)


@pytest.mark.parametrize("channels", [1, 3])
def test_png_without_its_end_chunk_reads_its_whole_data(tmp_path, channels):
    shape = (64, 64) if channels == 1 else (64, 64, 3)
    path = tmp_path / "a.png"
    write_image(path, np.random.default_rng(7).uniform(0, 1, shape), bits=16)
    whole = read_image(path)
    path.write_bytes(path.read_bytes()[:-12])
    np.testing.assert_array_equal(read_image(path), whole)


@pytest.mark.parametrize(
    ("name", "image", "kwargs", "needle"),
    [
        ("a.png", np.zeros((2, 2, 4)), {}, "shape"),
        ("a.png", np.zeros(5), {}, "shape"),
        ("a.png", np.zeros((2, 2)), {"half": True}, "EXR option"),
        ("a.jpg", np.zeros((2, 2)), {"bits": 16}, "bits=16"),
        ("a.png", np.zeros((2, 2)), {"bits": 12}, "bits=12"),
    ],
)
def test_write_rejects_bad_requests(tmp_path, name, image, kwargs, needle):
    with pytest.raises(InputError) as excinfo:
        write_image(tmp_path / name, image, **kwargs)
    assert needle in _single_line_error(excinfo, tmp_path / name)


def test_write_makes_parent_folders(tmp_path):
    write_image(tmp_path / "a" / "b" / "c.exr", np.ones((2, 3), dtype=np.float32))
    assert image_size(tmp_path / "a" / "b" / "c.exr") == (3, 2)


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    write_image(path, np.ones((2, 2), dtype=np.float32))
    before = path.read_bytes()

    def fail_halfway(tmp, image, *, half):
        tmp.write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(images_module, "_write_exr", fail_halfway)
    with pytest.raises(OSError, match="disk full"):
        write_image(path, np.zeros((2, 2), dtype=np.float32))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]


def test_quiet_native_stderr_is_shared_by_threads_and_restored_after_the_last():
    """fd 2 points at the null device while any thread is inside; the first one out leaves it so for
    the others, the last one out restores it (the reads decode in threads at once)."""
    import os
    import threading

    from warp_highlights.io.images import quiet_native_stderr

    real = os.fstat(2)
    null = os.stat(os.devnull)
    inside, release = threading.Barrier(3), threading.Event()
    seen = []

    def reader():
        with quiet_native_stderr():
            inside.wait()
            seen.append(os.fstat(2).st_rdev == null.st_rdev)
            release.wait()

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for thread in threads:
        thread.start()
    inside.wait()
    assert os.fstat(2).st_rdev == null.st_rdev
    with quiet_native_stderr():  # a third, nested in time, leaves first
        pass
    assert os.fstat(2).st_rdev == null.st_rdev
    release.set()
    for thread in threads:
        thread.join()
    assert seen == [True, True]
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (real.st_dev, real.st_ino)


def test_exr_images_decode_in_threads_to_the_same_values(tmp_path):
    """EXR reads hold no lock while they decode; read in threads they give what serial reads give."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(4)
    paths = []
    for index in range(6):
        path = tmp_path / f"{index}.exr"
        write_image(path, rng.uniform(0.0, 2.0, size=(40, 56, 3)).astype(np.float32))
        paths.append(path)
    serial = [read_image(path) for path in paths]
    with ThreadPoolExecutor(4) as pool:
        threaded = list(pool.map(read_image, paths * 3))
    for index, image in enumerate(threaded):
        np.testing.assert_array_equal(image, serial[index % len(paths)])
