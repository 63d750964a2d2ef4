"""TIFF and 16-bit captures, EXIF orientation and ICC profiles: read through OpenImageIO,
recorded in ``info``, the field's header and the relit output's bit depth."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from PIL import Image, ImageCms, ImageOps

from conftest import FAST_FIT
from warp_highlights.cli import main
from warp_highlights.io import images as images_module
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.images import (
    image_encoding,
    image_shape,
    image_size,
    read_image,
    write_image,
)
from warp_highlights.io.lightfile import write_lp
from warp_highlights.model.lights import LightSet


@pytest.mark.parametrize("suffix", [".tif", ".tiff"])
@pytest.mark.parametrize("channels", [1, 3])
def test_tiff_16bit_keeps_all_65536_levels(tmp_path, suffix, channels):
    levels = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    if channels == 3:
        levels = np.stack([levels, levels[::-1], levels.T], axis=-1)
    path = tmp_path / f"a{suffix}"
    write_image(path, levels / 65535.0, bits=16, linear=True)
    back = read_image(path, linear=True)
    assert back.shape == levels.shape and image_shape(path) == levels.shape
    np.testing.assert_array_equal(np.rint(back * 65535.0).astype(np.uint16), levels)
    assert image_encoding(path) == {"format": "TIFF", "bits": 16, "values": "sRGB", "profile": None}


def test_tiff_8bit_and_float(tmp_path):
    import OpenImageIO as oiio

    rng = np.random.default_rng(1)
    levels = rng.integers(0, 256, (5, 7, 3)).astype(np.uint8)
    write_image(tmp_path / "a.tif", levels / 255.0, linear=True)
    np.testing.assert_array_equal(np.rint(read_image(tmp_path / "a.tif", linear=True) * 255).astype(np.uint8), levels)
    values = rng.uniform(0.0, 40.0, (5, 7, 3)).astype(np.float32)  # radiance beyond display white
    output = oiio.ImageOutput.create("tiff")
    assert (output.open(str(tmp_path / "f.tif"), oiio.ImageSpec(7, 5, 3, "float")) and output.write_image(values)
            and output.close())
    np.testing.assert_array_equal(read_image(tmp_path / "f.tif"), values)  # a float TIFF holds linear values, as EXR
    assert image_encoding(tmp_path / "f.tif")["values"] == "linear" and image_encoding(tmp_path / "f.tif")["bits"] == 32


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_is_applied(tmp_path, orientation):
    """A camera's rotated JPEG comes out as Pillow's ``exif_transpose`` shows it, and its header size agrees."""
    rows, cols = np.mgrid[0:24, 0:40]
    picture = np.stack([rows * 10, cols * 6, np.full_like(rows, 60)], axis=-1).astype(np.uint8)
    picture[:6, :8] = 255  # a white corner: any wrong turn moves it
    stored = Image.fromarray(picture)
    exif = stored.getexif()
    exif[0x0112] = orientation
    path = tmp_path / "rotated.jpg"
    stored.save(path, exif=exif.tobytes(), quality=98)
    upright = np.asarray(ImageOps.exif_transpose(Image.open(path))).astype(np.float64)
    got = read_image(path, linear=True) * 255.0
    assert got.shape == upright.shape == image_shape(path) and image_size(path) == (upright.shape[1], upright.shape[0])
    assert np.abs(got - upright).mean() < 1.0  # two JPEG decoders; a wrong orientation differs by tens of levels


def _profile(name: str) -> bytes:
    """Pillow's sRGB profile under another name (an RGB profile that is not called sRGB)."""
    data = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    old = "sRGB built-in".encode("utf-16-be")
    assert data.count(old) == 1 and len(name) == len("sRGB built-in")
    return data.replace(old, name.encode("utf-16-be"))


def test_icc_profiles_are_converted_or_named_once(tmp_path, caplog, monkeypatch):
    picture = np.random.default_rng(2).integers(0, 256, (8, 8, 3)).astype(np.uint8)
    srgb = tmp_path / "srgb.jpg"
    Image.fromarray(picture).save(srgb, quality=100,
                                  icc_profile=ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    wide = tmp_path / "wide.jpg"
    Image.fromarray(picture).save(wide, quality=100, icc_profile=_profile("Test RGB wide"))
    lab = tmp_path / "lab.jpg"
    Image.fromarray(picture).save(lab, quality=100,
                                  icc_profile=ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes())
    monkeypatch.setattr(images_module, "_REPORTED_PROFILES", set())
    conversions = []
    convert = ImageCms.profileToProfile
    monkeypatch.setattr(ImageCms, "profileToProfile", lambda *a, **k: conversions.append(1) or convert(*a, **k))
    with caplog.at_level(logging.WARNING, logger="warp_highlights"):
        plain = read_image(srgb, linear=True)
        assert not caplog.records and not conversions  # sRGB: nothing to say or do
        for _ in range(2):
            # the same colours, converted
            np.testing.assert_allclose(read_image(wide, linear=True), plain, atol=1.5 / 255)
        read_image(lab, linear=True)  # a profile ImageCms cannot apply to RGB: read as sRGB, said so
    messages = [r.getMessage() for r in caplog.records]
    # two conversions and one refused attempt; each profile named once
    assert len(conversions) == 3 and len(messages) == 2
    assert "'Test RGB wide'" in messages[0] and "converted to sRGB" in messages[0]
    assert "'Lab identity built-in'" in messages[1] and "read as sRGB" in messages[1]
    assert image_encoding(wide)["profile"] == "Test RGB wide" and image_encoding(srgb)["profile"] == "sRGB built-in"


def test_float_tiff_profile_is_named_and_its_values_kept(tmp_path, caplog, monkeypatch):
    """ImageCms converts 8-bit codes only: a float TIFF's profile is named, its values stay as stored."""
    import OpenImageIO as oiio

    values = np.random.default_rng(5).random((5, 7, 3)).astype(np.float32) * 2.0
    spec = oiio.ImageSpec(7, 5, 3, "float")
    spec.attribute("ICCProfile", oiio.TypeDesc("uint8[%d]" % len(_profile("Test RGB wide"))),
                   np.frombuffer(_profile("Test RGB wide"), np.uint8))
    output = oiio.ImageOutput.create(str(tmp_path / "f.tif"))
    assert output.open(str(tmp_path / "f.tif"), spec) and output.write_image(values) and output.close()
    monkeypatch.setattr(images_module, "_REPORTED_PROFILES", set())
    with caplog.at_level(logging.WARNING, logger="warp_highlights"):
        np.testing.assert_array_equal(read_image(tmp_path / "f.tif"), values)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1, messages
    assert "'Test RGB wide'" in messages[0], messages[0]
    assert "read as linear sRGB" in messages[0], messages[0]


@pytest.mark.parametrize("suffix", [".tif", ".png"])
def test_16bit_capture_fits_and_relights_keeping_its_16_bits(tmp_path, suffix, capsys):
    """Values only a 16-bit file holds come back exactly from the dataset; the field records the
    capture's encoding in its header; relight writes 16 bits by default after it (8 on request)."""
    rng = np.random.default_rng(3)
    lights = LightSet.fibonacci_dome(12, min_elevation_deg=25.0)
    y, x = np.mgrid[0:24, 0:32] / np.array([24.0, 32.0])[:, None, None]
    codes = []
    folder = tmp_path / "capture"
    folder.mkdir()
    names = [f"img{i:02d}{suffix}" for i in range(len(lights))]
    for i, (name, (lx, ly, lz)) in enumerate(zip(names, lights.directions)):
        shade = np.clip(0.15 + 0.6 * lz + 0.2 * (lx * x + ly * y), 0.0, 1.0)
        highlight = 0.8 * np.exp(-((x - 0.5 - 0.3 * lx) ** 2 + (y - 0.5 - 0.3 * ly) ** 2) / 0.004)
        level = (np.rint(np.clip(shade + highlight, 0.0, 1.0) * 65535.0)[..., None] * np.array([1.0, 0.9, 0.8])
                 + rng.integers(0, 7, (24, 32, 3)))
        level = np.clip(level, 0, 65535).astype(np.uint16)
        codes.append(level)
        write_image(folder / name, level / 65535.0, bits=16, linear=True)
    write_lp(lights, folder / "lights.lp", names)
    dataset = ReflectanceField.load(folder, linear=True, progress=False)
    back = np.rint(dataset.images * 65535.0).astype(np.uint16)
    np.testing.assert_array_equal(back, np.stack(codes))
    assert np.any(np.stack(codes) % 257 != 0)  # not an 8-bit image in disguise
    assert dataset.source == {"format": "TIFF" if suffix == ".tif" else "PNG", "bits": 16, "values": "linear",
                              "profile": None, "size": [32, 24]}
    field_path = tmp_path / "capture.whf"
    settings = [part for item in FAST_FIT + ["residual.check_lights=0"] for part in ("--set", item)]
    assert main(["fit", str(folder), "-o", str(field_path), "--linear", "--device", "cpu", "-q", *settings]) == 0
    from warp_highlights.io.fieldfile import load_field

    assert load_field(field_path).report["input"]["bits"] == 16
    for bits, want in (("auto", 16), ("8", 8)):
        out = tmp_path / f"relit-{bits}{suffix}"
        assert main(["relight", str(field_path), "--light", "0.2,0.3,0.9", "-o", str(out), "--bits", bits, "-q"]) == 0
        assert image_encoding(out)["bits"] == want
        relit = read_image(out)
        assert np.all(np.isfinite(relit)) and relit.min() >= 0 and relit.max() > 0.05
    capsys.readouterr()
    assert main(["relight", str(field_path), "--light", "0.2,0.3,0.9", "-o", str(tmp_path / "relit.exr"), "--bits",
                 "16", "-q"]) == 2
    assert "--bits 16 is for PNG and TIFF" in capsys.readouterr().err
    assert main(["relight", str(field_path), "--light", "0.2,0.3,0.9", "--light", "0.1,0,1", "-o",
                 str(tmp_path / "many"), "--bits", "8", "-q"]) == 2
    assert "folder of EXR images" in capsys.readouterr().err and not (tmp_path / "many").exists()


def test_png_exif_orientation_is_applied_too(tmp_path):
    """A PNG's eXIf orientation turns it as Pillow's ``exif_transpose`` does, and its header size agrees."""
    picture = np.random.default_rng(5).integers(0, 256, (6, 10, 3)).astype(np.uint8)
    stored = Image.fromarray(picture)
    exif = stored.getexif()
    exif[0x0112] = 6
    path = tmp_path / "tagged.png"
    stored.save(path, exif=exif.tobytes())
    got = np.rint(read_image(path, linear=True) * 255).astype(np.uint8)
    np.testing.assert_array_equal(got, np.asarray(ImageOps.exif_transpose(Image.open(path))))
    assert got.shape == (10, 6, 3) and image_shape(path) == got.shape and image_size(path) == (6, 10)
