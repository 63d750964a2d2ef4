"""RTIViewer's .ptm and .rti files: written, read back to their quantisation, relit as the baselines, refused in
one line when malformed, and taken by info, relight and export."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import smooth_plate, write_capture
from warp_highlights.cli import main
from warp_highlights.io.images import read_image, srgb_to_linear
from warp_highlights.io.legacy_rti import read_legacy_rti, write_hsh_rti, write_ptm
from warp_highlights.model.errors import InputError
from warp_highlights.quality.metrics import psnr_8bit
from warp_highlights.relight.baselines import fit_baseline
from warp_highlights.relight.legacy import fit_legacy, relight_legacy

QUERIES = np.array([[0.3, 0.5, 0.81], [-0.5, 0.2, 0.84], [0.1, -0.7, 0.7], [0.0, 0.0, 1.0]])


def _rgb8(values) -> np.ndarray:
    return np.round(255.0 * np.clip(values, 0.0, 1.0)).astype(np.uint8)


@pytest.mark.parametrize(("suffix", "method"), [(".ptm", "ptm"), (".rti", "hsh3")])
def test_written_files_read_back_to_their_quantisation_and_relight_as_the_baseline(tmp_path, suffix, method):
    values, lights = smooth_plate()
    coefficients = fit_legacy(suffix[1:], values, lights, device="cpu")
    path = tmp_path / f"a{suffix}"
    (write_ptm if suffix == ".ptm" else write_hsh_rti)(path, coefficients)
    model = read_legacy_rti(path)
    assert model.kind == ("ptm" if suffix == ".ptm" else "hsh") and (model.height, model.width) == (12, 20)
    span = coefficients.max(axis=(0, 1, 3)) - coefficients.min(axis=(0, 1, 3))  # one scale a coefficient
    assert (np.abs(model.coefficients - coefficients).max(axis=(0, 1, 3)) <= span / 255 * 0.5 + 1e-6).all()
    baseline = fit_baseline(method, values, lights, device="cpu").relight(QUERIES)
    relit = relight_legacy(model, QUERIES)
    assert min(psnr_8bit(_rgb8(a), _rgb8(b)) for a, b in zip(relit, baseline)) >= 40.0


def test_ptm_rows_are_stored_bottom_up(tmp_path):
    coefficients = np.zeros((3, 2, 6, 3), np.float32)
    coefficients[0, :, 5] = 1.0  # the top row is white under any light (the constant term)
    write_ptm(tmp_path / "a.ptm", coefficients)
    data = (tmp_path / "a.ptm").read_bytes()
    body = np.frombuffer(data[-3 * 3 * 2 * 6:], np.uint8).reshape(3, 3, 2, 6)  # channel, row, pixel, coefficient
    assert body[0, 2, 0, 5] > body[0, 0, 0, 5]  # the file's last row is the image's top
    assert np.allclose(read_legacy_rti(tmp_path / "a.ptm").coefficients[0, :, 5], 1.0, atol=1 / 255)


def test_lrgb_ptm_is_the_luminance_polynomial_times_the_colour(tmp_path):
    height, width = 2, 3
    rng = np.random.default_rng(1)
    luminance = rng.integers(0, 256, (height, width, 6), dtype=np.uint8)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    scale, bias = [0.5, 0.4, 0.3, 0.8, 0.9, 1.0], [10, 20, 30, 40, 50, 0]
    header = f"PTM_1.2\nPTM_FORMAT_LRGB\n{width}\n{height}\n{' '.join(map(str, scale))}\n{' '.join(map(str, bias))}\n"
    (tmp_path / "l.ptm").write_bytes(header.encode() + luminance.tobytes() + rgb.tobytes())
    model = read_legacy_rti(tmp_path / "l.ptm")
    expected = ((luminance - np.array(bias)) * np.array(scale) / 255.0)[..., :, None] * (rgb / 255.0)[..., None, :]
    np.testing.assert_allclose(model.coefficients, expected[::-1], rtol=1e-5, atol=1e-6)
    assert model.source == "PTM_FORMAT_LRGB"


@pytest.mark.parametrize(("content", "needle"), [
    (b"PTM_1.2\nPTM_FORMAT_JPEG_RGB\n2\n2\n1 1 1 1 1 1\n0 0 0 0 0 0\n", "header ends early"),
    (b"PTM_1.2\nPTM_FORMAT_LUM\n", "is not read here"),
    (b"PTM_1.1\nPTM_FORMAT_RGB\n", "PTM_1.2 files are read"),
    (b"PTM_1.2\nPTM_FORMAT_RGB\n99999999\n2\n1 1 1 1 1 1\n0 0 0 0 0 0\n", "1 to 65536 a side"),
    (b"PTM_1.2\nPTM_FORMAT_RGB\n2\n2\n1 1 1 1 1\n0 0 0 0 0 0\n", "expected 6 scales"),
    (b"PTM_1.2\nPTM_FORMAT_RGB\n2\n2\n1 1 1 1 1 1\n0 0 0 0 0 0\n" + bytes(10), "truncated"),
    (b"#HSH1.2\n1\n2 2 3\n9 2 1\n", "RTI type 1"),
    (b"#HSH1.2\n3\n2 2 1\n9 2 1\n", "RGB (3) files are read"),
    (b"#HSH1.2\n3\n2 2 3\n16 2 1\n", "4 or 9"),
    (b"#HSH1.2\n3\n2 2 3\n9 2 1\n" + struct.pack("<18f", *([float("nan")] * 18)) + bytes(108), "not finite"),
    (b"PTM_1.2\nPTM", "header ends early"),
])
def test_malformed_files_are_refused_in_one_line(tmp_path, content, needle):
    path = tmp_path / ("a.rti" if content.startswith(b"#") else "a.ptm")
    path.write_bytes(content)
    with pytest.raises(InputError) as excinfo:
        read_legacy_rti(path)
    message = str(excinfo.value)
    assert needle in message and "\n" not in message and path.name in message


def test_info_on_a_malformed_file_exits_2_in_one_line(tmp_path, capsys):
    path = tmp_path / "bad.ptm"
    path.write_bytes(b"PTM_1.2\nPTM_FORMAT_RGB\n4\n4\n1 1 1 1 1 1\n0 0 0 0 0 0\n" + bytes(5))
    assert main(["info", str(path)]) == 2
    error = capsys.readouterr().err.strip()
    assert "truncated" in error and "\n" not in error


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(header=st.lists(st.sampled_from(["PTM_1.2", "PTM_FORMAT_RGB", "PTM_FORMAT_LRGB", "#HSH1.2", "3", "9 2 1",
                                        "4 2 1", "2 2 3", "65537", "2", "1 1 1 1 1 1", "0 0 0 0 0 0", "-1", "x",
                                        "1e400 1 1 1 1 1", "", "PTM_FORMAT_JPEG_RGB", "PTM_FORMAT_JPEG_LRGB", "90",
                                        " ".join(["0"] * 9), " ".join(["-1"] * 9), " ".join(map(str, range(9))),
                                        " ".join(["5"] * 9)]), min_size=0, max_size=16),
       tail=st.binary(max_size=200), suffix=st.sampled_from([".ptm", ".rti"]))
def test_reader_raises_only_one_line_input_errors(tmp_path, header, tail, suffix):
    path = tmp_path / f"fuzz{suffix}"
    path.write_bytes("\n".join(header).encode() + b"\n" + tail)
    try:
        model = read_legacy_rti(path)
    except InputError as error:
        assert "\n" not in str(error)
        return
    assert np.isfinite(model.coefficients).all() and model.coefficients.size <= 3 * 9 * len(tail)


def test_export_info_and_relight_commands(tmp_path, capsys):
    capture = write_capture(tmp_path / "capture", *smooth_plate(count=20))
    for file_format in ("ptm", "rti"):
        path = tmp_path / f"c.{file_format}"
        assert main(["export", str(capture), "--format", file_format, "-o", str(path), "-q"]) == 0
        assert "for RTIViewer" in capsys.readouterr().out
        assert main(["info", str(path)]) == 0
        assert "20x12" in capsys.readouterr().out
        assert main(["relight", str(path), "--light", "0.3,0.5,1", "-o", str(tmp_path / f"{file_format}.png")]) == 0
        relit = read_image(tmp_path / f"{file_format}.png")
        expected = relight_legacy(read_legacy_rti(path), np.array([[0.3, 0.5, 1.0]]))[0]
        assert psnr_8bit(_rgb8(np.clip(relit, 0, 1)), _rgb8(srgb_to_linear(expected))) >= 45.0
    assert main(["export", str(capture), "--format", "ptm", "-o", str(tmp_path / "x.rti")]) == 2
    assert "name ending in .ptm" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "c.ptm"), "--format", "rti", "-o", str(tmp_path / "y.rti")]) == 2
    assert "give the capture folder" in capsys.readouterr().err


def test_animate_maps_and_openlime_export_take_legacy_files(tmp_path, capsys):
    from warp_highlights.io.images import read_image as read
    from warp_highlights.web.openlime import relight_openlime

    values, lights = smooth_plate(count=30, height=24, width=32)
    for file_format, model_name in (("ptm", "ptm"), ("rti", "hsh")):
        path = tmp_path / f"c.{file_format}"
        (write_ptm if file_format == "ptm" else write_hsh_rti)(path, fit_legacy(file_format, values, lights,
                                                                                device="cpu"))
        model = read_legacy_rti(path)
        assert main(["animate", str(path), "--path", "orbit:40", "--frames", "6", "-o",
                     str(tmp_path / f"{file_format}-frames"), "-q"]) == 0
        frames = sorted((tmp_path / f"{file_format}-frames").glob("*.png"))
        assert len(frames) == 6 and read(frames[0]).shape == (24, 32, 3)
        assert main(["animate", str(path), "--path", "orbit:40", "--specular-only", "-o", str(tmp_path / "x.gif")]) == 2
        assert "leave out --specular-only" in capsys.readouterr().err
        assert main(["relight", str(path), "--light", "0,0,1", "--method", "alpha", "-o", str(tmp_path / "x.png")]) == 2
        assert "leave out --method" in capsys.readouterr().err
        # maps: the plate's normals lean as its normal field does (x from sin(5u), y from cos(4v))
        assert main(["maps", str(path), "-o", str(tmp_path / f"{file_format}-maps"), "-q"]) == 0
        normals = read(tmp_path / f"{file_format}-maps" / "normals.exr")
        assert normals.shape == (24, 32, 3) and np.all(normals[..., 2] > 0.5)
        u = np.arange(32) / 32
        assert np.corrcoef(normals[12, :, 0], np.sin(5 * u))[0, 1] > 0.9
        # OpenLIME: the file's coefficients as they are (PTM reordered to OpenLIME's basis)
        folder = tmp_path / f"{file_format}-openlime"
        assert main(["export", str(path), "--format", "openlime", "-o", str(folder), "-q"]) == 0
        relit = relight_openlime(folder, QUERIES)
        expected = relight_legacy(model, QUERIES)
        assert min(psnr_8bit(_rgb8(a), _rgb8(b)) for a, b in zip(relit, expected)) >= 40.0, model_name


def _jpeg_ptm(path, raw: np.ndarray, scale, bias, *, layout: str, predicted: dict | None = None,
              side: dict | None = None) -> None:
    """A JPEG PTM of the (planes, H, W) bytes ``raw`` (plane i: coefficient i mod 6 of block i div 6), each plane a
    greyscale JPEG of quality 100; ``predicted``: plane -> (reference, inverted), stored as the difference + 128;
    ``side``: plane -> [(offset, byte)] corrections."""
    import io

    from PIL import Image

    count, height, width = raw.shape
    predicted, side = predicted or {}, side or {}
    streams, sides, references, transforms = [], [], [], []
    for plane in range(count):
        values = raw[plane].astype(np.int64)
        reference, inverted = predicted.get(plane, (-1, False))
        if reference >= 0:
            base = raw[reference].astype(np.int64)
            values = (values - (255 - base if inverted else base) + 128) % 256
        buffer = io.BytesIO()
        Image.fromarray(values.astype(np.uint8), "L").save(buffer, "JPEG", quality=100)
        streams.append(buffer.getvalue())
        sides.append(b"".join(struct.pack(">IB", offset, byte) for offset, byte in side.get(plane, [])))
        references.append(reference)
        transforms.append(1 if inverted else 0)
    ints = lambda values: " ".join(str(int(v)) for v in values)  # noqa: E731
    order = list(range(count))
    header = "\n".join(["PTM_1.2", f"PTM_FORMAT_JPEG_{layout}", str(width), str(height), " ".join(map(str, scale)),
                        ints(bias), "100", ints(transforms), ints([0] * count),
                        ints([0] * count), ints(order), ints(references), ints(map(len, streams)),
                        ints(map(len, sides))]) + "\n"
    path.write_bytes(header.encode() + b"".join(s + t for s, t in zip(streams, sides)))


@pytest.mark.parametrize("layout", ["RGB", "LRGB"])
def test_jpeg_ptm_planes_read_as_the_uncompressed_layout(tmp_path, layout):
    height, width = 16, 24
    v, u = np.mgrid[0:height, 0:width]
    count = 18 if layout == "RGB" else 9
    raw = np.stack([(40 + 7 * k + 3 * u + 2 * v) % 200 + 20 for k in range(count)]).astype(np.uint8)  # smooth
    scale, bias = [0.5, 0.4, 0.3, 0.8, 0.9, 1.0], [10, 20, 30, 40, 50, 0]
    side = {2: [(5, 250), (width * height + 7, 1)]}  # the second record lies outside the plane: ignored
    _jpeg_ptm(tmp_path / "j.ptm", raw, scale, bias, layout=layout, predicted={1: (0, False), 4: (3, True)}, side=side)
    expected = raw.copy()
    expected[2].reshape(-1)[5] = 250
    if layout == "RGB":
        body = expected.reshape(3, 6, height, width).transpose(0, 2, 3, 1).tobytes()
    else:
        body = np.stack(list(expected[:6]), axis=-1).tobytes() + np.stack(list(expected[6:]), axis=-1).tobytes()
    numbers = f"{' '.join(map(str, scale))}\n{' '.join(map(str, bias))}\n"
    header = f"PTM_1.2\nPTM_FORMAT_{layout}\n{width}\n{height}\n{numbers}"
    (tmp_path / "r.ptm").write_bytes(header.encode() + body)
    jpeg, uncompressed = read_legacy_rti(tmp_path / "j.ptm"), read_legacy_rti(tmp_path / "r.ptm")
    assert jpeg.source == f"PTM_FORMAT_JPEG_{layout}" and jpeg.coefficients.shape == uncompressed.coefficients.shape
    # JPEG of quality 100 keeps a smooth plane to a few levels (an LRGB's colour too); the side information exactly
    assert np.abs(jpeg.coefficients - uncompressed.coefficients).max() <= 6 * max(scale) / 255.0
    np.testing.assert_allclose(jpeg.coefficients[height - 1, 5, 2], uncompressed.coefficients[height - 1, 5, 2],
                               atol=1e-6)


def test_jpeg_ptm_with_motion_vectors_is_refused(tmp_path):
    path = tmp_path / "m.ptm"
    ones = " ".join(["1"] * 18)
    zeros = " ".join(["0"] * 18)
    path.write_bytes(f"PTM_1.2\nPTM_FORMAT_JPEG_RGB\n2\n2\n1 1 1 1 1 1\n0 0 0 0 0 0\n90\n{zeros}\n{ones}\n{zeros}\n"
                     f"{' '.join(map(str, range(18)))}\n{' '.join(['-1'] * 18)}\n{zeros}\n{zeros}\n".encode())
    with pytest.raises(InputError, match="motion compensation"):
        read_legacy_rti(path)
