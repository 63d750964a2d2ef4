"""Property-based tests of the readers: whatever bytes they are given, the only exception
that leaves them is the project's one-line ``InputError`` naming the file, and valid input reads back right.

Each reader gets ``EXAMPLES`` generated inputs: random bytes, a valid file truncated, bit-flipped or with
a slice overwritten at random places, and a valid file under a random header. Runs are derandomised
(the same examples every run, in CI too) and bounded: the whole file takes well under a minute on 2 cores.
"""

from __future__ import annotations

import codecs
import io
import json
import math
import re
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
pytest.importorskip("OpenEXR")
pytest.importorskip("PIL")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from warp_highlights.io.fieldfile import load_field  # noqa: E402
from warp_highlights.io.images import image_shape, image_size, read_image, write_image  # noqa: E402
from warp_highlights.io.lightfile import read_lights, read_lp, write_lp  # noqa: E402
from warp_highlights.model.errors import InputError  # noqa: E402
from warp_highlights.model.lights import LightSet  # noqa: E402

EXAMPLES = 500  # per reader
SMALL_BUDGET = 1_000_000  # pixels: a damaged header may claim any size; this bounds what a read allocates


def _settings(examples: int = EXAMPLES):
    return settings(
        max_examples=examples,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
    )


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("properties")


def _one_line(error: InputError, path: Path) -> None:
    message = str(error)
    hypothesis.event("InputError: " + re.sub(r"\d+", "N", message.replace(str(path), ""))[:48])
    assert "\n" not in message and "\r" not in message
    assert path.name in message, message


# --- damage -----------------------------------------------------------------------------------------


@st.composite
def _damaged(draw, valid: bytes, header: int) -> bytes:
    """``valid`` truncated, bit-flipped, overwritten in a slice, or random bytes; ``header`` bytes at the
    start (where parsers decide what to allocate) are hit half the time."""
    kind = draw(st.sampled_from(["random", "truncate", "truncate", "flip", "flip", "flip", "overwrite", "overwrite"]))
    if kind == "random":
        return draw(st.binary(max_size=1024))
    if kind == "truncate":
        return valid[: draw(st.integers(0, len(valid) - 1))]
    end = draw(st.sampled_from([min(header, len(valid)), len(valid)]))
    data = bytearray(valid)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 6))):
            data[draw(st.integers(0, end - 1))] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    start = draw(st.integers(0, end - 1))
    patch = draw(st.binary(min_size=1, max_size=16))
    data[start : start + len(patch)] = patch
    return bytes(data)


def _check_image_readers(path: Path) -> None:
    """read_image, image_size and image_shape raise nothing but a one-line InputError, and agree."""
    results = {}
    for name, call in (("read", read_image), ("size", image_size), ("shape", image_shape)):
        try:
            results[name] = call(path, max_pixels=SMALL_BUDGET)
        except InputError as error:
            _one_line(error, path)
    hypothesis.event(f"succeeded: {', '.join(sorted(results)) or 'none'}")
    if "read" in results:
        image = results["read"]
        assert image.dtype == np.float32 and image.ndim in (2, 3) and image.size <= 3 * SMALL_BUDGET
        assert results.get("shape") == image.shape
        assert results.get("size") == (image.shape[1], image.shape[0])


# --- PNG ----------------------------------------------------------------------------------------------


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


@pytest.fixture(scope="module")
def valid_pngs(workdir) -> list[bytes]:
    """8- and 16-bit, grey and colour (16-bit colour goes through VTK), as ``write_image`` writes them."""
    pngs = []
    rng = np.random.default_rng(5)
    for bits, shape in ((8, (9, 11)), (8, (9, 11, 3)), (16, (9, 11)), (16, (9, 11, 3))):
        path = workdir / f"valid{len(pngs)}.png"
        write_image(path, rng.uniform(0, 1, shape), bits=bits)
        pngs.append(path.read_bytes())
    return pngs


_PNG_DEPTH_COLOUR = [(d, 0) for d in (1, 2, 4, 8, 16)] + [(d, 3) for d in (1, 2, 4, 8)] + [
    (d, c) for d in (8, 16) for c in (2, 4, 6)
]  # every (bit depth, colour type) pair the PNG standard allows


@st.composite
def _png_with_random_header(draw, valid: bytes) -> bytes:
    """A valid PNG whose IHDR (with a correct CRC) claims a random size, depth and colour type."""
    width = draw(st.one_of(st.integers(0, 64), st.integers(0, 2**31 - 1)))
    height = draw(st.one_of(st.integers(0, 64), st.integers(0, 2**31 - 1)))
    depth, colour = draw(st.sampled_from(_PNG_DEPTH_COLOUR + [(0, 0), (3, 0), (16, 3), (8, 1), (8, 7)]))
    tail = draw(st.sampled_from([b"\0\0\0", b"\0\0\1", b"\0\1\0", b"\1\0\0", b"\0\0\2"]))
    ihdr = _png_chunk(b"IHDR", struct.pack(">IIBB", width, height, depth, colour) + tail)
    return valid[:8] + ihdr + valid[33:]


@_settings()
@given(data=st.data())
def test_png_readers_raise_only_input_errors(workdir, valid_pngs, data):
    valid = data.draw(st.sampled_from(valid_pngs))
    content = data.draw(st.one_of(_damaged(valid, header=64), _png_with_random_header(valid)))
    path = workdir / "fuzz.png"
    path.write_bytes(content)
    _check_image_readers(path)


# --- JPEG ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def valid_jpegs() -> list[bytes]:
    from PIL import Image

    jpegs = []
    for mode, progressive in (("RGB", False), ("L", False), ("RGB", True)):
        rgb = np.random.default_rng(len(jpegs)).integers(0, 256, (12, 17, 3)).astype(np.uint8)
        buffer = io.BytesIO()
        Image.fromarray(rgb).convert(mode).save(buffer, format="JPEG", quality=90, progressive=progressive)
        jpegs.append(buffer.getvalue())
    return jpegs


@st.composite
def _jpeg_with_random_size(draw, valid: bytes) -> bytes:
    """A valid JPEG whose frame header (SOF) claims a random height and width."""
    marker = max(valid.find(b"\xff\xc0"), valid.find(b"\xff\xc2"))
    data = bytearray(valid)
    data[marker + 5 : marker + 9] = struct.pack(">HH", draw(st.integers(0, 65535)), draw(st.integers(0, 65535)))
    return bytes(data)


@_settings()
@given(data=st.data())
def test_jpeg_readers_raise_only_input_errors(workdir, valid_jpegs, data):
    valid = data.draw(st.sampled_from(valid_jpegs))
    content = data.draw(st.one_of(_damaged(valid, header=400), _jpeg_with_random_size(valid)))
    path = workdir / "fuzz.jpg"
    path.write_bytes(content)
    _check_image_readers(path)


# --- EXR ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def valid_exrs(workdir) -> list[bytes]:
    exrs = []
    rng = np.random.default_rng(11)
    for shape, half in (((6, 7, 3), False), ((6, 7), True), ((5, 4, 3), True)):
        path = workdir / f"valid{len(exrs)}.exr"
        write_image(path, rng.uniform(-2, 8, shape).astype(np.float32), half=half)
        exrs.append(path.read_bytes())
    return exrs


def _header_end(exr: bytes) -> int:
    """Offset of the byte that ends an EXR's (single-part) header."""
    position = 8
    while exr[position] != 0:
        name_end = exr.index(b"\0", position)
        type_end = exr.index(b"\0", name_end + 1)
        (size,) = struct.unpack("<i", exr[type_end + 1 : type_end + 5])
        position = type_end + 5 + size
    return position


@st.composite
def _exr_with_random_window(draw, valid: bytes) -> bytes:
    """A valid EXR whose dataWindow claims random corners (huge, negative, inverted)."""
    corner = st.one_of(st.integers(-8, 64), st.integers(-(2**31), 2**31 - 1))
    key = b"dataWindow\0box2i\0\x10\0\0\0"
    at = valid.index(key) + len(key)
    data = bytearray(valid)
    data[at : at + 16] = struct.pack("<4i", *(draw(corner) for _ in range(4)))
    return bytes(data)


@_settings()
@given(data=st.data())
def test_exr_readers_raise_only_input_errors(workdir, valid_exrs, data):
    valid = data.draw(st.sampled_from(valid_exrs))
    strategies = [_damaged(valid, header=_header_end(valid) + 1), _exr_with_random_window(valid)]
    content = data.draw(st.one_of(strategies))
    path = workdir / "fuzz.exr"
    path.write_bytes(content)
    _check_image_readers(path)


# --- valid images read back right ---------------------------------------------------------------------


@_settings(100)
@given(
    height=st.integers(1, 12),
    width=st.integers(1, 12),
    colour=st.booleans(),
    form=st.sampled_from(["exr", "exr-half", "png8", "png16"]),
    seed=st.integers(0, 2**32 - 1),
)
def test_valid_images_read_back(workdir, height, width, colour, form, seed):
    shape = (height, width, 3) if colour else (height, width)
    image = np.random.default_rng(seed).uniform(0, 1, shape).astype(np.float32)
    path = workdir / ("valid.exr" if form.startswith("exr") else "valid.png")
    write_image(path, image, half=form == "exr-half", bits=16 if form == "png16" else 8, linear=True)
    assert image_size(path) == (width, height) and image_shape(path) == shape
    back = read_image(path, linear=True)
    assert back.shape == shape and back.dtype == np.float32
    tolerance = {"exr": 0.0, "exr-half": 1e-3, "png8": 0.5 / 255, "png16": 0.5 / 65535}[form]
    np.testing.assert_allclose(back, image, rtol=0, atol=tolerance * 1.0001)
    if height * width > 1:
        with pytest.raises(InputError, match="megapixels"):
            read_image(path, max_pixels=height * width - 1)


# --- .lp light files ----------------------------------------------------------------------------------

_NAME = st.text(st.sampled_from("abcXYZ019_-. /\\"), min_size=1, max_size=12).map(str.strip).filter(bool)
_COMPONENT = st.floats(-1.0, 1.0, allow_nan=False).map(lambda v: round(v, 6))


@st.composite
def _light_set(draw) -> tuple[list[str], np.ndarray]:
    count = draw(st.integers(1, 12))
    names = draw(st.lists(_NAME, min_size=count, max_size=count, unique_by=lambda n: n.replace("\\", "/")))
    vectors = np.array(draw(st.lists(st.tuples(_COMPONENT, _COMPONENT, _COMPONENT), min_size=count, max_size=count)))
    return names, vectors


def _valid_directions(vectors: np.ndarray) -> bool:
    norms = np.linalg.norm(vectors, axis=1)
    if np.any(norms < 1e-3):
        return False
    unit = vectors / norms[:, None]
    gaps = np.linalg.norm(unit[:, None] - unit[None], axis=2) + np.eye(len(unit)) * 9
    return bool(gaps.min() > 1e-3)


@_settings(200)
@given(lights=_light_set())
def test_valid_light_files_read_back(workdir, lights):
    names, vectors = lights
    hypothesis.assume(_valid_directions(vectors))
    path = workdir / "valid.lp"
    write_lp(LightSet(vectors, names), path)
    back = read_lp(path, check_files=False)
    assert back.filenames == [name.replace("\\", "/") for name in names]
    np.testing.assert_allclose(back.directions, vectors / np.linalg.norm(vectors, axis=1)[:, None], atol=1e-12)


_LP_TOKEN = st.one_of(
    st.sampled_from(["nan", "inf", "-0", "1e999", "1e-999", "5e-324", "1e308", "0,5", "1_0", "-3", "0", "9" * 5000]),
    st.sampled_from(["a" * 300, "d/" * 2100, "../" * 3 + "etc", "\\\\server\\share"]),  # names no file system takes
    st.text(st.sampled_from("0123456789.,-+eE"), max_size=8),
    st.floats().map(repr),
    st.integers(-(10**30), 10**30).map(str),
    _NAME,
)


def _encoded(text: str, encoding: str) -> bytes:
    if encoding == "utf-16-be+bom":
        return codecs.BOM_UTF16_BE + text.encode("utf-16-be", "surrogatepass")
    return text.encode(encoding, "surrogatepass" if encoding.startswith("utf") else "replace")


@st.composite
def _damaged_lp(draw) -> bytes:
    """A light file: valid, with lines replaced by random tokens, or random text; in one of the encodings
    the reader takes; then, half the time, damaged byte by byte."""
    names, vectors = draw(_light_set())
    lines = [str(len(names))] + [f"{n} {x!r} {y!r} {z!r}" for n, (x, y, z) in zip(names, vectors.tolist())]
    kind = draw(st.sampled_from(["valid", "names", "lines", "lines", "text"]))
    if kind == "names" and len(lines) > 1:  # entries with other names: repeated, absurd, or none
        for _ in range(draw(st.integers(1, 3))):
            index = draw(st.integers(1, len(lines) - 1))
            name = draw(st.one_of(_LP_TOKEN, st.sampled_from(names), st.just("")))
            lines[index] = " ".join([name, *lines[index].rsplit(None, 3)[1:]])
    if kind == "lines":
        for _ in range(draw(st.integers(1, 3))):
            index = draw(st.integers(0, len(lines) - 1))
            lines[index] = draw(st.sampled_from([" ", "\t"])).join(draw(st.lists(_LP_TOKEN, min_size=1, max_size=5)))
    text = "\n".join(lines) + "\n"
    if kind == "text":  # numbers, signs, exponents, decimal commas, separators, odd characters
        text = draw(st.text(st.sampled_from("0123456789+-.,eE \t\r\nab/\\\x00\u00e9\u2028\ud800"), max_size=200))
    encoding = draw(st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "utf-16-be+bom", "latin-1"]))
    data = _encoded(text, encoding)
    return draw(_damaged(data, header=len(data))) if data and draw(st.booleans()) else data


@_settings()
@given(content=_damaged_lp(), check_files=st.booleans())
def test_light_file_reader_raises_only_input_errors(workdir, content, check_files):
    path = workdir / "fuzz.lp"
    path.write_bytes(content)
    try:
        lights = read_lp(path, check_files=check_files)
    except InputError as error:
        _one_line(error, path)
        return
    # a file of directions without names pairs the folder's images, or (unchecked) gives no names
    assert lights.light_count >= 1 and (lights.filenames is None or len(lights.filenames) == lights.light_count)
    assert np.all(np.isfinite(lights.directions))
    np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0, atol=1e-12)


_JSON_VALUE = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.sampled_from(["x", "y", "z", "directions", "images", "dome", "filename", "skip", "direction", "folder",
                         "lightConfiguration", "positions3d", "positionsSphere"]), inner, max_size=5),
    max_leaves=30)


@_settings()
@given(document=st.one_of(_JSON_VALUE, st.fixed_dictionaries({
    "directions": st.lists(st.fixed_dictionaries({axis: st.floats(-2, 2) for axis in "xyz"}), max_size=6),
    "lightConfiguration": st.sampled_from(["directional", "spherical", "lights3d", 3]),
    "positions3d": st.lists(st.lists(st.floats(), min_size=3, max_size=3), max_size=6)})),
    suffix=st.sampled_from([".dome", ".relight"]), check_files=st.booleans())
def test_relight_json_light_files_raise_only_input_errors(workdir, document, suffix, check_files):
    path = workdir / f"fuzz{suffix}"
    path.write_text(json.dumps(document))
    try:
        lights = read_lights(path, check_files=check_files)
    except InputError as error:
        _one_line(error, path)
        return
    assert lights.light_count >= 1 and np.all(np.isfinite(lights.directions))
    assert lights.positions is None or lights.positions.shape == lights.directions.shape


# --- field files --------------------------------------------------------------------------------------

LEGACY = Path(__file__).parent / "data" / "legacy-v1.whf"
_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=8,
)


@pytest.fixture(scope="module")
def legacy_field():
    with zipfile.ZipFile(LEGACY) as archive:
        entries = [(info.filename, archive.read(info)) for info in archive.infolist()]
    return LEGACY.read_bytes(), entries, load_field(LEGACY)


def _zip(entries: list[tuple[str, bytes]]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, content in entries:
            archive.writestr(name, content)
    return buffer.getvalue()


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=False)
    return buffer.getvalue()


@st.composite
def _replaced_entry(draw, entries: list[tuple[str, bytes]]) -> bytes:
    """The field with one entry's content replaced (or the entry dropped), zipped again."""
    entries = list(entries)
    index = draw(st.integers(0, len(entries) - 1))
    name, content = entries[index]
    kind = draw(st.sampled_from(["json", "npy", "bytes", "drop", "swap"]))
    if name == "header.json" and kind == "json":
        header = json.loads(content)
        path = [draw(st.sampled_from(sorted(header)))]
        if isinstance(header[path[0]], dict) and header[path[0]] and draw(st.booleans()):
            path.append(draw(st.sampled_from(sorted(header[path[0]]))))
        node = header
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = draw(_JSON)
        content = json.dumps(header).encode()
    elif kind in ("npy", "json"):
        dtype = draw(st.sampled_from(["<f8", "<f4", "<f2", "<i4", "<u2", "<i8", ">f8", "|b1"]))
        shape = tuple(draw(st.lists(st.integers(0, 7), max_size=3)))
        values = draw(st.sampled_from([0.0, 1.0, -1.0, 1e30, np.nan, np.inf, 65535.0]))
        with np.errstate(over="ignore", invalid="ignore"):
            content = _npy(np.full(shape, values).astype(dtype))
    elif kind == "bytes":
        content = draw(_damaged(content, header=128))
    elif kind == "drop":
        del entries[index]
        return _zip(entries)
    else:
        content = entries[draw(st.integers(0, len(entries) - 1))][1]
    entries[index] = (name, content)
    return _zip(entries)


@_settings()
@given(data=st.data())
def test_field_loader_raises_only_input_errors(workdir, legacy_field, data):
    valid, entries, original = legacy_field
    content = data.draw(st.one_of(_damaged(valid, header=2048), _replaced_entry(entries)))
    path = workdir / "fuzz.whf"
    path.write_bytes(content)
    try:
        field = load_field(path)
    except InputError as error:
        _one_line(error, path)
        return
    assert field.light_count == original.light_count or content != valid
    assert math.isfinite(float(field.estimated.amplitude.sum()))


def test_field_loader_reads_the_valid_file_exactly(workdir, legacy_field):
    valid, _, original = legacy_field
    path = workdir / "copy.whf"
    path.write_bytes(valid)
    field = load_field(path)
    np.testing.assert_array_equal(field.lights.directions, original.lights.directions)
    np.testing.assert_array_equal(field.triangulation.faces, original.triangulation.faces)
    np.testing.assert_array_equal(field.retargeted.amplitude, original.retargeted.amplitude)
