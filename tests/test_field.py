"""HighlightField: construction checks, the versioned single-file format, atomic saving, load errors.

This module holds one thing: the tests of the highlight field and its file.
"""

from __future__ import annotations

import io
import json
import os
import re
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from warp_highlights.io import fieldfile
from warp_highlights.io.fieldfile import FORMAT_VERSION, MAGIC, field_size_report, load_field, save_field
from warp_highlights.model.config import RESIDUAL_BOOLEANS
from warp_highlights.model.errors import InputError
from warp_highlights.model.field import DiffuseModel, HighlightField
from warp_highlights.model.gaussians import GaussianParams
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation

SETTINGS = {
    "estimation": {"iterations": 1000, "densify_every": 100, "densify_until": 600, "capacity": 8},
    "retarget": {"c_fit": 1.0, "c_str": 0.01, "c_ene": 1e-3, "rigid_iterations": 200, "iterations": 500},
    "raster": {"cutoff": 4.0, "sigma_eps_rpx2": 0.01, "tile_size": 16},
}  # a partial FitSettings dict: load() checks the stored settings


# --- building test fields --------------------------------------------------------------------------


def random_params(rng, active: np.ndarray) -> GaussianParams:
    """Random float64 Gaussians in every slot (free slots too: the field must clear them)."""
    shape = active.shape
    return GaussianParams(
        amplitude=rng.uniform(0.3, 1.5, shape),
        mean=rng.uniform(0.0, 1.0, shape + (2,)) * [16 / 9, 1.0],
        sigma=rng.uniform(0.003, 0.05, shape + (2,)),
        theta=rng.uniform(0.0, np.pi, shape),
        weight=np.ones(shape),
        active=active,
    )


def field_parts(
    lights: LightSet, *, capacity=8, per_set=(0, 6), size=(32, 18), seed=0
) -> dict:
    """Constructor arguments of a random field; slots are scattered (not a prefix), some sets empty."""
    rng = np.random.default_rng(seed)
    tri = SphericalTriangulation(lights.directions)
    n = lights.light_count
    active = np.zeros((n, capacity), dtype=bool)
    for i in range(n):
        count = rng.integers(per_set[0], per_set[1] + 1)
        active[i, rng.choice(capacity, count, replace=False)] = True
    estimated = random_params(rng, active)
    edges = tri.directed_edges()
    retargeted = random_params(rng, active[edges[:, 0]])
    # retargeted = the source's Gaussians, moved a little
    source = edges[:, 0]
    retargeted.mean = estimated.mean[source] + rng.normal(
        0.0, 0.01, retargeted.mean.shape
    )
    retargeted.theta = estimated.theta[source] + rng.normal(
        0.0, 0.1, retargeted.theta.shape
    )
    count = len(edges)
    return {
        "lights": lights,
        "triangulation": tri,
        "width": size[0],
        "height": size[1],
        "estimated": estimated,
        "directed_edges": edges,
        "retargeted": retargeted,
        "path_delta": rng.uniform(-np.pi, np.pi, (count, capacity)),
        "path_centre": rng.uniform(-1.0, 2.0, (count, capacity, 2)),
        "settings": SETTINGS,
        "report": {
            "times_s": {"estimate": 1.5, "retarget": 12.25},
            "counts": [1, 2, 3],
            "psnr": None,
        },
    }


def random_diffuse(
    rng, lights: LightSet, size=(32, 18), *, channels=3, images=False
) -> DiffuseModel:
    width, height = size
    lambert = rng.uniform(-1.0, 1.0, (height, width, channels, 4))
    stack = (
        rng.uniform(0.0, 1.5, (lights.light_count, height, width, channels))
        if images
        else None
    )
    return DiffuseModel(lambert, stack)


def make_field(lights=None, *, diffuse=None, seed=0, **kwargs) -> HighlightField:
    lights = LightSet.fibonacci_sphere(14) if lights is None else lights
    parts = field_parts(lights, seed=seed, **kwargs)
    if diffuse is not None:
        rng = np.random.default_rng(seed + 100)
        parts["diffuse"] = random_diffuse(
            rng, lights, parts_size(parts), images=diffuse == "images"
        )
    return HighlightField(**parts)


def parts_size(parts: dict) -> tuple[int, int]:
    return parts["width"], parts["height"]


def assert_params_equal(a: GaussianParams, b: GaussianParams) -> None:
    for name in ("amplitude", "mean", "sigma", "theta", "weight", "active"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y), name


def assert_fields_equal(
    a: HighlightField, b: HighlightField, *, lambert_exact=True
) -> None:
    assert np.array_equal(a.lights.directions, b.lights.directions)
    assert a.lights.filenames == b.lights.filenames
    assert np.array_equal(a.triangulation.faces, b.triangulation.faces)
    assert a.triangulation.is_dome == b.triangulation.is_dome
    np.testing.assert_allclose(
        a.triangulation.directions, b.triangulation.directions, rtol=0, atol=1e-15
    )
    assert (a.width, a.height) == (b.width, b.height)
    assert np.array_equal(a.directed_edges, b.directed_edges)
    assert a.directed_edges.dtype == b.directed_edges.dtype == np.int32
    assert_params_equal(a.estimated, b.estimated)
    assert_params_equal(a.retargeted, b.retargeted)
    for name in ("path_delta", "path_centre"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32
        assert np.array_equal(x, y), name
    assert a.settings == b.settings
    assert a.report == b.report
    assert (a.diffuse is None) == (b.diffuse is None)
    if a.diffuse is not None:
        expected = (
            a.diffuse.lambert
            if lambert_exact
            else a.diffuse.lambert.astype(np.float16).astype(np.float32)
        )
        assert b.diffuse.lambert.dtype == np.float32
        assert np.array_equal(expected, b.diffuse.lambert)
        assert (a.diffuse.images is None) == (b.diffuse.images is None)
        if a.diffuse.images is not None:
            assert b.diffuse.images.dtype == np.float16
            assert np.array_equal(a.diffuse.images, b.diffuse.images)


def is_float32(x: np.ndarray) -> bool:
    return np.array_equal(x, x.astype(np.float32).astype(x.dtype))


# --- round trip ------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["sphere", "dome"])
@pytest.mark.parametrize("diffuse", [None, "lambert", "images"])
def test_save_load_round_trip_is_exact(tmp_path, kind, diffuse):
    lights = (
        LightSet.fibonacci_sphere(20)
        if kind == "sphere"
        else LightSet.fibonacci_dome(20)
    )
    original = make_field(lights, diffuse=diffuse, seed=7)
    assert original.triangulation.is_dome == (kind == "dome")
    path = tmp_path / "field.whf"
    written = save_field(original, path)
    assert written == path.stat().st_size
    loaded = load_field(path)
    assert_fields_equal(original, loaded, lambert_exact=False)
    assert loaded.triangulation.is_dome == (kind == "dome")
    assert field_size_report(loaded) == field_size_report(original)
    # the exact variant of the Lambertian model
    if diffuse is not None:
        save_field(original, path, lambert_half=False)
        assert_fields_equal(original, load_field(path), lambert_exact=True)


def test_round_trip_keeps_light_filenames_and_single_channel_diffuse(tmp_path):
    lights = LightSet(
        LightSet.fibonacci_dome(9).directions, [f"img {i}.png" for i in range(9)]
    )
    parts = field_parts(lights, size=(5, 7))
    rng = np.random.default_rng(1)
    parts["diffuse"] = random_diffuse(rng, lights, (5, 7), channels=1, images=True)
    original = HighlightField(**parts)
    save_field(original, tmp_path / "f")  # any file name
    loaded = load_field(tmp_path / "f")
    assert loaded.lights.filenames == lights.filenames
    assert_fields_equal(original, loaded, lambert_exact=False)


def test_constructor_rounds_to_float32_and_clears_free_slots():
    parts = field_parts(LightSet.fibonacci_sphere(12))
    before = {
        name: getattr(parts["estimated"], name).copy() for name in ("amplitude", "mean")
    }
    field = HighlightField(**parts)
    for params in (field.estimated, field.retargeted):
        assert params.amplitude.dtype == np.float64
        for name in ("amplitude", "mean", "sigma", "theta"):
            values = getattr(params, name)
            assert is_float32(values)
            assert np.all(values[~params.active] == 0.0)
        assert np.all(params.weight == 1.0)
    free = ~field.retargeted.active
    assert np.all(field.path_delta[free] == 0) and np.all(field.path_centre[free] == 0)
    assert field.path_delta.dtype == field.path_centre.dtype == np.float32
    # active values are the float32 rounding of the inputs; the inputs are untouched
    active = field.estimated.active
    assert np.array_equal(
        field.estimated.amplitude[active],
        before["amplitude"][active].astype(np.float32).astype(np.float64),
    )
    assert not is_float32(parts["estimated"].amplitude)
    for name, value in before.items():
        assert np.array_equal(getattr(parts["estimated"], name), value)
    assert field.estimated is not parts["estimated"]


def test_settings_become_plain_json():
    parts = field_parts(LightSet.fibonacci_sphere(12))
    parts["settings"] = {"range": (1, 2), "scale": np.float32(0.5), "n": np.int64(3)}
    parts["report"] = {
        "counts": np.arange(3),
        "psnr": [np.inf, 30.5, np.float64(np.nan)],
        "best": np.float32(-np.inf),
    }
    field = HighlightField(**parts)
    assert field.settings == {"range": [1, 2], "scale": 0.5, "n": 3}
    assert field.report == {
        "counts": [0, 1, 2],
        "psnr": [None, 30.5, None],
        "best": None,
    }


def test_path_values_of_free_slots_may_be_anything():
    parts = field_parts(LightSet.fibonacci_sphere(12))
    free = ~parts["estimated"].active[parts["directed_edges"][:, 0]]
    assert free.any()
    parts["path_delta"] = np.where(free, np.nan, parts["path_delta"])
    parts["path_centre"] = np.where(free[..., None], np.inf, parts["path_centre"])
    field = HighlightField(**parts)
    assert np.all(field.path_delta[free] == 0) and np.all(field.path_centre[free] == 0)


def test_fit_settings_dict_round_trips(tmp_path):
    from warp_highlights.model.config import FitSettings

    parts = field_parts(LightSet.fibonacci_sphere(12))
    parts["settings"] = FitSettings().to_dict()
    original = HighlightField(**parts)
    save_field(original, tmp_path / "f.whf")
    loaded = load_field(tmp_path / "f.whf")
    assert loaded.settings == original.settings
    assert loaded.fit_settings() == FitSettings.from_dict(original.settings)


def test_saving_is_deterministic_and_readable_by_numpy(tmp_path):
    field = make_field(diffuse="images")
    save_field(field, tmp_path / "a.whf")
    save_field(field, tmp_path / "b.whf")
    assert (tmp_path / "a.whf").read_bytes() == (tmp_path / "b.whf").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.whf") as archive:
        assert archive.namelist()[0] == "header.json"
        header = json.loads(archive.read("header.json"))
    assert header["magic"] == MAGIC
    assert header["format_version"] == FORMAT_VERSION
    with np.load(tmp_path / "a.whf") as npz:
        packed = npz["gaussians/estimated"]
        assert packed.dtype == np.float32 and packed.shape == (
            field.estimated.active.sum(),
            6,
        )
        assert npz["gaussians/estimated_slots"].dtype == np.uint16
        np.testing.assert_array_equal(npz["gaussians/estimated_counts"], field.counts)
        rows, slots = np.nonzero(field.estimated.active)
        np.testing.assert_array_equal(
            packed[:, 0], field.estimated.amplitude[rows, slots]
        )
        np.testing.assert_array_equal(packed[:, 5], field.estimated.theta[rows, slots])


# --- size ------------------------------------------------------------------------------------------


def test_256_lights_with_25_gaussians_per_set_is_smaller_than_the_thesis(tmp_path):
    lights = LightSet.fibonacci_sphere(256)
    parts = field_parts(lights, capacity=64, per_set=(25, 25), size=(480, 270))
    field = HighlightField(**parts)
    assert field.light_count + field.edge_count == 7 * 256 - 12
    assert field.gaussian_count == 25 * (7 * 256 - 12)
    predicted = field_size_report(field)
    written = save_field(field, tmp_path / "big.whf")
    assert written == (tmp_path / "big.whf").stat().st_size
    assert written < 2.2e6 * 0.8, f"{written} bytes"
    sizes = field_size_report(field)
    assert sizes == predicted  # measuring in memory gives the same bytes as writing
    assert sizes["total"] == written
    assert sum(v for k, v in sizes.items() if k != "total") == written
    # random float32 mantissas barely compress: the Gaussians take about their raw size
    assert sizes["gaussians"] <= 25 * (7 * 256 - 12) * (6 * 4 + 2) * 1.01
    assert sizes["paths"] <= 25 * (6 * 256 - 12) * 3 * 4 * 1.01
    assert "file: " in field.describe()
    assert_fields_equal(field, load_field(tmp_path / "big.whf"))


# --- summary ---------------------------------------------------------------------------------------


def test_properties_and_describe(tmp_path):
    field = make_field(LightSet.fibonacci_dome(16), diffuse="lambert", size=(48, 27))
    assert field.light_count == 16
    assert field.edge_count == len(field.triangulation.directed_edges())
    assert field.capacity == 8
    np.testing.assert_array_equal(field.counts, field.estimated.active.sum(axis=1))
    assert (
        field.gaussian_count
        == field.estimated.active.sum() + field.retargeted.active.sum()
    )
    assert (
        field.gaussian_count
        == field.counts[field.directed_edges[:, 0]].sum() + field.counts.sum()
    )
    assert field.aspect == pytest.approx(48 / 27)
    text = field.describe()
    assert "16 lights (dome)" in text and f"{field.edge_count} directed edges" in text
    assert f"min {field.counts.min()}, max {field.counts.max()}" in text
    assert "Lambertian, 3 channel(s)" in text and "file:" not in text
    save_field(field, tmp_path / "f.whf")
    assert str(tmp_path / "f.whf") in field.describe()
    assert "HighlightField(16 lights" in repr(field)


def test_lambertian_diffuse_image():
    lambert = np.zeros((2, 3, 1, 4), dtype=np.float32)
    lambert[..., 0, :3] = [0.0, 0.0, 0.5]
    lambert[..., 0, 3] = 0.1
    lambert[1, 2, 0, :3] = [0.0, 0.0, -0.5]  # faces away: only the ambient term
    image = DiffuseModel(lambert).lambertian([0.0, 0.0, 2.0])
    assert image.shape == (2, 3, 1)
    np.testing.assert_allclose(image[0, 0, 0], 0.6)
    np.testing.assert_allclose(image[1, 2, 0], 0.1)


# --- atomic saving ---------------------------------------------------------------------------------


@pytest.mark.parametrize("error", [RuntimeError("disk gone"), KeyboardInterrupt()])
def test_failed_save_keeps_the_old_file_and_leaves_no_temp_file(
    tmp_path, monkeypatch, error
):
    path = tmp_path / "field.whf"
    save_field(make_field(seed=1), path)
    old = path.read_bytes()
    calls = []
    real = fieldfile._write_array

    def failing(archive, name, array, **kwargs):
        calls.append(name)
        if len(calls) == 4:
            raise error
        real(archive, name, array, **kwargs)

    monkeypatch.setattr(fieldfile, "_write_array", failing)
    with pytest.raises(type(error)):
        save_field(make_field(seed=2), path)
    assert len(calls) == 4
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.whf"]
    monkeypatch.undo()
    assert_fields_equal(make_field(seed=1), load_field(path))


def test_failed_rename_is_an_input_error_and_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "field.whf"
    save_field(make_field(seed=1), path)
    old = path.read_bytes()

    def refuse(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(InputError, match="cannot write .*field.whf: Permission denied"):
        save_field(make_field(seed=2), path)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.whf"]


def test_save_creates_folders_and_refuses_a_folder(tmp_path):
    field = make_field()
    target = tmp_path / "new" / "sub" / "f.whf"
    assert save_field(field, target) == target.stat().st_size
    with pytest.raises(InputError, match="is a folder"):
        save_field(field, tmp_path / "new")


# --- load errors -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> tuple:
    """A saved field with diffuse images (every entry present) and its bytes."""
    path = tmp_path_factory.mktemp("saved") / "field.whf"
    field = make_field(
        LightSet.fibonacci_sphere(12), diffuse="images", size=(6, 4), seed=3
    )
    save_field(field, path, lambert_half=False)
    return field, path, path.read_bytes()


def load_error(path) -> str:
    """The message of the InputError that loading ``path`` must raise (one line naming the file)."""
    with pytest.raises(InputError) as info:
        load_field(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    assert info.value.__cause__ is None or isinstance(info.value.__cause__, InputError)
    return message


def entries(data: bytes) -> dict:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def npy(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array))
    return buffer.getvalue()


def rewrite(data: bytes, path, *, header=None, drop=(), **arrays) -> None:
    """Write ``path`` as a copy of the field file ``data`` with a changed header or entries.

    ``arrays`` maps entry names with '/' written as '__' (and no '.npy') to new arrays.
    """
    contents = entries(data)
    if header is not None:
        contents["header.json"] = json.dumps(
            header(json.loads(contents["header.json"]))
        ).encode()
    for key, value in arrays.items():
        contents[key.replace("__", "/") + ".npy"] = npy(value)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, blob in contents.items():
            if name not in drop:
                archive.writestr(name, blob)


def read_entry(data: bytes, name: str) -> np.ndarray:
    return np.load(io.BytesIO(entries(data)[name]))


def npy_entries(data: bytes) -> dict:
    """The ``.npy`` file of every array of a field file, by array name (``X.npy``): a deflated entry's
    bytes, or a chunked entry's Blosc chunks (``X.npy.blosc``, lengths in ``X.lengths.npy``) decoded."""
    from numcodecs import Blosc

    contents = entries(data)
    arrays = {}
    for name, blob in contents.items():
        if name.endswith(".npy.blosc"):
            lengths = np.load(io.BytesIO(contents[name.removesuffix(".npy.blosc") + ".lengths.npy"]))
            ends = np.cumsum(lengths)
            arrays[name.removesuffix(".blosc")] = b"".join(bytes(Blosc().decode(blob[end - length : end]))
                                                           for end, length in zip(ends, lengths))
        elif (name.endswith(".npy")
              and not (name.endswith(".lengths.npy") and name.replace(".lengths.npy", ".npy.blosc") in contents)):
            arrays[name] = blob
    return arrays


def test_rewrite_helper_round_trips(saved, tmp_path):
    field, _, data = saved
    rewrite(data, tmp_path / "copy.whf")
    assert_fields_equal(field, load_field(tmp_path / "copy.whf"))


def test_missing_file_and_folder(tmp_path):
    assert "not found" in load_error(tmp_path / "nothing.whf")
    assert "is a folder" in load_error(tmp_path)


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"", "empty file"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(40), "a PNG image"),
        (b"4\nimg0.png 0 0 1\nimg1.png 0 1 0\n", "a text file"),
        (b"\x93NUMPY\x01\x00" + bytes(60), "a NumPy .npy array"),
        (bytes(range(256)), "unrecognised binary content"),
    ],
)
def test_foreign_files_are_not_field_files(tmp_path, content, expected):
    path = tmp_path / "foreign.whf"
    path.write_bytes(content)
    message = load_error(path)
    assert expected in message
    if content:
        assert "not a warp-highlights field file" in message


def test_zip_without_header_is_not_a_field_file(tmp_path):
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("notes.txt", "hello")
    assert "without header.json" in load_error(tmp_path / "other.zip")
    np.savez_compressed(tmp_path / "arrays.npz", a=np.arange(3))
    assert "without header.json" in load_error(tmp_path / "arrays.npz")


def test_truncated_copies(saved, tmp_path):
    _, _, data = saved
    path = tmp_path / "cut.whf"
    cuts = sorted(
        {
            1,
            4,
            29,
            35,
            41,
            100,
            len(data) // 3,
            len(data) // 2,
            len(data) - 23,
            len(data) - 1,
        }
    )
    for cut in cuts:
        path.write_bytes(data[:cut])
        message = load_error(path)
        if cut >= 35:
            assert "truncated or corrupt" in message, (cut, message)


def test_flipped_bytes_raise_input_error_or_load_equal_data(saved, tmp_path):
    field, _, data = saved
    path = tmp_path / "flipped.whf"
    rng = np.random.default_rng(0)
    positions = np.unique(
        np.concatenate(
            [
                np.linspace(0, len(data) - 1, 80).astype(int),
                rng.integers(0, len(data), 40),
                np.arange(len(data) - 100, len(data)),  # the zip directory
            ]
        )
    )
    directory_start = len(data) - 100
    errors = {"entries": 0, "directory": 0}
    for position in positions:
        for mask in (0x01, 0xFF):
            damaged = bytearray(data)
            damaged[position] ^= mask
            path.write_bytes(bytes(damaged))
            try:
                loaded = load_field(path)
            except InputError as exc:
                assert str(path) in str(exc) and "\n" not in str(exc)
                errors["directory" if position >= directory_start else "entries"] += 1
            else:  # the flip hit bytes that do not matter (a date, an attribute)
                assert_fields_equal(field, loaded)
    # nearly every flip in the entries is caught (checksums); the directory has more unused bytes
    assert errors["entries"] > 0.85 * 2 * np.count_nonzero(positions < directory_start)
    assert errors["directory"] > 0.3 * 2 * 100
    # a flip in the middle of the data is always caught
    middle = bytearray(data)
    middle[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(middle))
    assert "corrupt" in load_error(path)


def test_newer_format_version(saved, tmp_path):
    _, _, data = saved
    path = tmp_path / "future.whf"
    rewrite(
        data,
        path,
        header=lambda h: {**h, "format_version": FORMAT_VERSION + 1, "library_version": "9.0"},
    )
    message = load_error(path)
    assert (
        "newer warp-highlights" in message and "upgrade" in message and "9.0" in message
    )


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (
            lambda h: {**h, "magic": "something else"},
            "not a warp-highlights field file",
        ),
        (lambda h: [1, 2, 3], "not a warp-highlights field file"),
        (
            lambda h: {k: v for k, v in h.items() if k != "format_version"},
            "format_version",
        ),
        (lambda h: {**h, "format_version": "1"}, "format_version"),
        (lambda h: {**h, "light_count": -3}, "light_count"),
        (lambda h: {**h, "capacity": 7.5}, "capacity"),
        (lambda h: {**h, "capacity": 70000}, "capacity"),
        (lambda h: {**h, "is_dome": True}, "is_dome"),
        (lambda h: {**h, "settings": [1]}, "settings"),
        (lambda h: {**h, "light_filenames": ["a"]}, "light_filenames"),
        (
            lambda h: {**h, "diffuse": {**h["diffuse"], "lambert_dtype": "int8"}},
            "lambert_dtype",
        ),
        (
            lambda h: {
                **h,
                "estimated_gaussian_count": h["estimated_gaussian_count"] + 1,
            },
            "estimated",
        ),
        (
            lambda h: {
                **h,
                "retargeted_gaussian_count": h["retargeted_gaussian_count"] - 1,
            },
            "retargeted",
        ),
        (
            lambda h: {**h, "directed_edge_count": h["directed_edge_count"] + 2},
            "directed edges",
        ),
        (lambda h: {**h, "width": h["width"] + 1}, "diffuse/lambert.npy has shape"),
    ],
)
def test_bad_headers(saved, tmp_path, change, expected):
    _, _, data = saved
    path = tmp_path / "bad-header.whf"
    rewrite(data, path, header=change)
    assert expected in load_error(path)


def test_header_that_is_not_json(saved, tmp_path):
    _, _, data = saved
    contents = entries(data)
    contents["header.json"] = b'{"magic": "warp-highlights field", '
    with zipfile.ZipFile(tmp_path / "f.whf", "w") as archive:
        for name, blob in contents.items():
            archive.writestr(name, blob)
    assert "not valid JSON" in load_error(tmp_path / "f.whf")


@pytest.mark.parametrize(
    "name",
    [
        "lights/directions.npy",
        "triangulation/faces.npy",
        "gaussians/estimated_counts.npy",
        "gaussians/estimated_slots.npy",
        "gaussians/estimated.npy",
        "gaussians/retargeted.npy",
        "paths/delta.npy",
        "paths/centre.npy",
        "diffuse/lambert.npy",
        "diffuse/images.npy",
    ],
)
def test_missing_entries(saved, tmp_path, name):
    _, _, data = saved
    path = tmp_path / "missing.whf"
    rewrite(data, path, drop=(name,))
    assert f"entry {name} is missing" in load_error(path)


def _with_nan(array: np.ndarray, index=0) -> np.ndarray:
    array = array.copy()
    array.reshape(-1)[index] = np.nan
    return array


def _shorter(array: np.ndarray) -> np.ndarray:
    return array[:-1]


@pytest.mark.parametrize(
    ("entry", "change", "expected"),
    [
        ("gaussians/estimated", _shorter, "gaussians/estimated.npy has shape"),
        (
            "gaussians/estimated",
            lambda a: a.astype(np.float64),
            "holds <f8 data, expected <f4",
        ),
        ("gaussians/estimated", lambda a: a.astype(">f4"), "holds >f4 data"),
        ("gaussians/estimated", lambda a: np.asfortranarray(a), "Fortran order"),
        (
            "gaussians/estimated",
            _with_nan,
            "gaussians/estimated.npy has non-finite values",
        ),
        (
            "gaussians/retargeted",
            lambda a: _with_nan(a, 7),
            "retargeted.npy has non-finite values",
        ),
        (
            "gaussians/retargeted",
            lambda a: np.concatenate([a, a[:1]]),
            "retargeted.npy has shape",
        ),
        (
            "paths/delta",
            lambda a: np.full_like(a, np.inf),
            "paths/delta.npy has non-finite values",
        ),
        ("paths/centre", lambda a: a[:, :1], "paths/centre.npy has shape"),
        (
            "lights/directions",
            lambda a: _with_nan(a, 4),
            "directions.npy has non-finite values",
        ),
        ("lights/directions", lambda a: a * 2.0, "not unit length"),
        (
            "lights/directions",
            lambda a: a.astype(np.float32),
            "holds <f4 data, expected <f8",
        ),
        (
            "triangulation/faces",
            lambda a: np.where(a == 0, 12, a),
            "vertex indices outside 0..11",
        ),
        (
            "triangulation/faces",
            lambda a: np.where(a == 0, -1, a),
            "vertex indices outside 0..11",
        ),
        ("triangulation/faces", lambda a: a[:, ::-1], "wound inwards"),
        ("triangulation/faces", lambda a: a.astype(np.int64), "expected <i4"),
        (
            "gaussians/estimated_slots",
            lambda a: np.full_like(a, 8),
            "slot indices out of range",
        ),
        ("gaussians/estimated_slots", lambda a: np.zeros_like(a), "out of order"),
        (
            "gaussians/estimated_counts",
            lambda a: a + (np.arange(len(a)) == 0),
            "estimated_counts.npy does not match",
        ),
        ("gaussians/estimated_counts", lambda a: a.astype(np.int32), "expected <u2"),
        (
            "diffuse/lambert",
            lambda a: _with_nan(a, 5),
            "lambert.npy has non-finite values",
        ),
        ("diffuse/images", lambda a: a[:, :, :, :2], "images.npy has shape"),
        ("diffuse/images", lambda a: _with_nan(a), "images.npy has non-finite values"),
    ],
)
def test_bad_arrays(saved, tmp_path, entry, change, expected):
    _, _, data = saved
    original = read_entry(data, entry + ".npy")
    changed = change(original)
    path = tmp_path / "bad-array.whf"
    rewrite(data, path, **{entry.replace("/", "__"): changed})
    message = load_error(path)
    assert "corrupt field file" in message
    assert expected in message


def test_entry_with_extra_data(saved, tmp_path):
    _, _, data = saved
    contents = entries(data)
    contents["paths/delta.npy"] += b"\x00\x00\x00\x00"
    with zipfile.ZipFile(tmp_path / "f.whf", "w") as archive:
        for name, blob in contents.items():
            archive.writestr(name, blob)
    assert "data after its array" in load_error(tmp_path / "f.whf")


# --- constructor validation ------------------------------------------------------------------------


def _parts() -> dict:
    return field_parts(LightSet.fibonacci_sphere(12), seed=5)


def _drop_row(params: GaussianParams) -> GaussianParams:
    return GaussianParams(
        params.amplitude[:-1],
        params.mean[:-1],
        params.sigma[:-1],
        params.theta[:-1],
        params.weight[:-1],
        params.active[:-1],
    )


def _widen(params: GaussianParams) -> GaussianParams:
    def pad(x):
        return np.concatenate([x, np.zeros_like(x[:, :1])], axis=1)

    return GaussianParams(
        *(
            pad(getattr(params, k))
            for k in ("amplitude", "mean", "sigma", "theta", "weight", "active")
        )
    )


def _toggle_slot(params: GaussianParams) -> GaussianParams:
    params = params.copy()
    params.active[3, 0] = not params.active[3, 0]
    return params


def _set(name, index, value):
    def change(params: GaussianParams) -> GaussianParams:
        params = params.copy()
        getattr(params, name)[index] = value
        return params

    return change


@pytest.mark.parametrize(
    ("key", "change", "expected"),
    [
        ("estimated", _drop_row, "estimated has 11 sets but there are 12 lights"),
        ("retargeted", _drop_row, "retargeted has"),
        (
            "retargeted",
            _widen,
            "retargeted sets have 9 slots but estimated sets have 8",
        ),
        ("retargeted", _toggle_slot, "uses other slots than estimated set"),
        ("estimated", _toggle_slot, "uses other slots than estimated set"),
        ("estimated", lambda p: "not params", "estimated must be GaussianParams"),
        ("retargeted", _set("amplitude", (0, 0), np.nan), "non-finite"),
        ("estimated", _set("mean", (1, 2, 0), np.inf), "non-finite"),
        ("estimated", _set("sigma", (1, 2, 0), 1e39), "beyond the float32 range"),
        (
            "estimated",
            lambda p: replace(p, weight=np.full(p.weight.shape, 0.5)),
            "weight 1",
        ),
        ("directed_edges", lambda e: e[:-1], "directed_edges"),
        ("directed_edges", lambda e: e[::-1], "directed_edges"),
        ("path_delta", lambda d: d[:, :-1], "path_delta must have shape"),
        (
            "path_delta",
            lambda d: np.where(d > 0, np.nan, d),
            "path_delta has non-finite values",
        ),
        (
            "path_delta",
            lambda d: d.astype(str),
            "path_delta must be a real numeric array",
        ),
        ("path_centre", lambda c: c[..., 0], "path_centre must have shape"),
        (
            "path_centre",
            lambda c: c * 1e39,
            "path_centre has non-finite values or beyond the float32 range",
        ),
        ("width", lambda w: 0, "width must be a positive number"),
        ("height", lambda h: -4, "height must be a positive number"),
        ("width", lambda w: 32.0, "width must be a positive number"),
        ("width", lambda w: True, "width must be a positive number"),
        ("settings", lambda s: {"f": object()}, "settings is not JSON-able"),
        ("report", lambda r: {"psnr": {1, 2}}, "report is not JSON-able"),
        ("report", lambda r: [1], "report must be a dict"),
        (
            "lights",
            lambda lights: LightSet.fibonacci_sphere(13),
            "not the 13 light directions",
        ),
        (
            "lights",
            lambda lights: LightSet(lights.directions[::-1]),
            "triangulate these lights",
        ),
        (
            "triangulation",
            lambda t: "faces",
            "triangulation must be a SphericalTriangulation",
        ),
        ("diffuse", lambda d: "lambert", "diffuse must be a DiffuseModel"),
        (
            "diffuse",
            lambda d: DiffuseModel(np.zeros((32, 18, 3, 4))),
            "the diffuse model is 18 x 32 pixels",
        ),
        (
            "diffuse",
            lambda d: DiffuseModel(np.zeros((18, 32, 3, 4)), np.zeros((11, 18, 32, 3))),
            "11 images for 12",
        ),
    ],
)
def test_constructor_rejects(key, change, expected):
    parts = _parts()
    parts[key] = change(parts.get(key))
    with pytest.raises(InputError, match=re.escape(expected)):
        HighlightField(**parts)


@pytest.mark.parametrize(
    ("lambert", "images", "expected"),
    [
        (np.zeros((4, 5, 3)), None, "shape (H, W, C, 4)"),
        (np.zeros((4, 5, 3, 3)), None, "shape (H, W, C, 4)"),
        (np.full((4, 5, 3, 4), np.nan), None, "lambert has non-finite values"),
        (np.zeros((4, 5, 3, 4)), np.zeros((2, 5, 4, 3)), "shape (n, 4, 5, 3)"),
        (
            np.zeros((4, 5, 3, 4)),
            np.full((2, 4, 5, 3), 1e5),
            "beyond the float16 range",
        ),
        ("abc", None, "real numeric array"),
    ],
)
def test_diffuse_model_rejects(lambert, images, expected):
    with pytest.raises(InputError, match=re.escape(expected)):
        DiffuseModel(lambert, images)


def test_diffuse_model_dtypes():
    model = DiffuseModel(np.zeros((4, 5, 3, 4)), np.ones((2, 4, 5, 3)))
    assert model.lambert.dtype == np.float32 and model.images.dtype == np.float16
    assert (model.height, model.width, model.channel_count) == (4, 5, 3)
    with pytest.raises(AttributeError):
        model.lambert = None  # frozen


def test_empty_sets_are_allowed(tmp_path):
    lights = LightSet.fibonacci_sphere(12)
    parts = field_parts(lights, per_set=(0, 0))
    field = HighlightField(**parts)
    assert field.gaussian_count == 0
    save_field(field, tmp_path / "empty.whf")
    assert_fields_equal(field, load_field(tmp_path / "empty.whf"))


def test_error_files_do_not_leak_open_handles(saved, tmp_path):
    """Loading a damaged file many times must not leave files open (the handle is closed on error)."""
    _, _, data = saved
    path = tmp_path / "cut.whf"
    path.write_bytes(data[: len(data) // 2])
    before = (
        len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else None
    )
    for _ in range(20):
        load_error(path)
    if before is not None:
        assert len(os.listdir("/proc/self/fd")) <= before


def test_lambert_beyond_float16_is_stored_as_float32(tmp_path):
    lights = LightSet.fibonacci_sphere(12)
    parts = field_parts(lights, size=(3, 2))
    lambert = np.random.default_rng(2).uniform(-1.0, 1.0, (2, 3, 3, 4))
    lambert[0, 0, 0, 3] = 1e5
    parts["diffuse"] = DiffuseModel(lambert)
    original = HighlightField(**parts)
    save_field(original, tmp_path / "f.whf")  # lambert_half=True, but the values do not fit
    with zipfile.ZipFile(tmp_path / "f.whf") as archive:
        header = json.loads(archive.read("header.json"))
    assert header["diffuse"]["lambert_dtype"] == "float32"
    assert_fields_equal(original, load_field(tmp_path / "f.whf"))


# --- files written by earlier versions -------------------------------------------------------------

LEGACY = Path(__file__).resolve().parent / "data"


def test_a_field_written_before_the_layout_change_loads_relights_and_saves_the_same(tmp_path):
    """tests/data/legacy-v1.whf was written by the flat-package version (commit 6f21722)."""

    path = LEGACY / "legacy-v1.whf"
    field = load_field(path)
    assert (field.light_count, field.edge_count, field.capacity, field.width, field.height) == (20, 98, 64, 40, 24)
    assert field.gaussian_count == 374 and field.triangulation.is_dome
    assert field.diffuse is not None and field.diffuse.images is not None
    assert field_size_report(field)["total"] == path.stat().st_size == 60165

    _assert_relights_as_recorded(field, "legacy-v1-relit.npz")
    again = tmp_path / "again.whf"
    save_field(field, again)
    old_header, new_header = _headers(path, again)
    old, new = npy_entries(path.read_bytes()), npy_entries(again.read_bytes())
    assert list(new) == list(old)
    assert old_header.pop("library_version") == "0.1.0"
    new_header.pop("library_version")
    # version 2 adds the residual layout and the moving flag; a version-1 field has neither
    assert new_header == {**old_header, "format_version": FORMAT_VERSION, "residual": None, "moving": False}
    assert new == old  # every array's .npy file byte for byte


# --- large arrays in Blosc chunks ------------------------------------------------------------------


def test_large_arrays_are_chunked_npy_entries_that_load_the_same(small_field, tmp_path, monkeypatch):
    """Arrays of ``_CHUNKED_BYTES`` or more (made small here: the diffuse images, the residual's means)
    are stored as ``.npy.blosc`` entries (the ``.npy`` file in Blosc chunks, stored as they are, their
    lengths in ``.lengths.npy``), the others deflated by the zip; the field loads the same, the file is
    the same whatever the threads, and every entry's CRC holds."""
    from numcodecs import Blosc

    field = load_field(small_field)
    monkeypatch.setattr(fieldfile, "_CHUNKED_BYTES", 4096)
    monkeypatch.setattr(fieldfile, "_CHUNK_BYTES", 5000)  # several chunks an array
    path = tmp_path / "chunked.whf"
    save_field(field, path)
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None
        infos = {info.filename: info for info in archive.infolist()}
        assert "diffuse/images.npy.blosc" in infos and "diffuse/images.npy" not in infos
        assert infos["diffuse/images.npy.blosc"].compress_type == zipfile.ZIP_STORED
        assert infos["gaussians/estimated_counts.npy"].compress_type == zipfile.ZIP_DEFLATED
        raw = archive.read("diffuse/images.npy.blosc")
        lengths = np.load(io.BytesIO(archive.read("diffuse/images.lengths.npy")))
    assert len(lengths) > 3 and lengths.sum() == len(raw)
    ends = np.cumsum(lengths)
    npy = b"".join(bytes(Blosc().decode(raw[end - length : end])) for end, length in zip(ends, lengths))
    np.testing.assert_array_equal(np.load(io.BytesIO(npy)), field.diffuse.images.transpose(0, 3, 1, 2).astype("<f2"))
    again = load_field(path)
    assert_fields_equal(field, again, lambert_exact=False)
    np.testing.assert_array_equal(again.diffuse.images, field.diffuse.images)
    np.testing.assert_array_equal(again.residual.luminance.codes, field.residual.luminance.codes)
    assert save_field(field, tmp_path / "again.whf") and (tmp_path / "again.whf").read_bytes() == path.read_bytes()
    monkeypatch.setattr(fieldfile, "NUMPY_THREADS", 1)
    save_field(field, tmp_path / "one.whf")
    assert (tmp_path / "one.whf").read_bytes() == path.read_bytes()


def test_a_cut_or_damaged_chunked_entry_is_a_corrupt_file(small_field, tmp_path, monkeypatch):
    field = load_field(small_field)
    monkeypatch.setattr(fieldfile, "_CHUNKED_BYTES", 4096)
    path = tmp_path / "chunked.whf"
    save_field(field, path)
    data = path.read_bytes()
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("diffuse/images.npy.blosc")
    start = info.header_offset + 30 + len(info.filename)
    for position in (start + 20, start + info.compress_size // 2, start + info.compress_size - 3):
        damaged = bytearray(data)
        damaged[position] ^= 0x21
        path.write_bytes(bytes(damaged))
        assert "corrupt field file" in load_error(path)
    path.write_bytes(data[: start + info.compress_size // 2])
    assert "truncated or corrupt" in load_error(path)
    rewrite(data, path, drop=("diffuse/images.lengths.npy",))
    assert "diffuse/images.lengths.npy is missing" in load_error(path)


# --- a version-4 file --------------------------------------------------------------------------------


def test_a_version_4_field_loads_relights_and_saves_the_same(tmp_path):
    """tests/data/legacy-v4.whf (format 4: the basis codes' row differences deflated run-length only)
    loads the codes it was written with (their SHA-256 taken by that version), relights to the images
    that version relit, and is written back in the current format with every array the same."""
    import hashlib


    path = LEGACY / "legacy-v4.whf"
    with zipfile.ZipFile(path) as archive:
        assert json.loads(archive.read("header.json"))["format_version"] == 4
        assert "residual/Y_codes.npy" in archive.namelist()
    field = load_field(path)
    luminance, chroma = field.residual.luminance, field.residual.chroma
    assert luminance.codes.shape == (8, 24, 40, 1) and luminance.codes.dtype == np.uint16 and chroma.rank == 0
    assert (hashlib.sha256(luminance.codes.tobytes()).hexdigest()
            == "598d2c92922649fa91e1ce7d604a3a4185161f6d0a32045ccc5b4c4cbc718cd9")
    assert field_size_report(field)["total"] == path.stat().st_size == 26937
    # its settings' residual booleans (the defaults: compressed, learned on CUDA) read as the kind it holds
    assert "kind" not in json.loads(entries(path.read_bytes())["header.json"])["settings"]["residual"]
    assert field.fit_settings().residual.kind == "lowrank"

    _assert_relights_as_recorded(field, "legacy-v4-relit.npz")
    again = tmp_path / "again.whf"
    save_field(field, again)
    old_header, new_header = _headers(path, again)
    assert new_header["format_version"] == FORMAT_VERSION == 9
    for header in (old_header, new_header):
        header.pop("format_version"), header.pop("library_version")
    assert new_header["residual"].pop("rbf_sigma") is None  # version 8: the triangle's weights, as version 4 blends
    # the settings' residual booleans saved as the kind they resolved to; the rest of the header as it was
    old_residual, new_residual = old_header["settings"].pop("residual"), new_header["settings"].pop("residual")
    assert new_residual == {"kind": "lowrank", **{k: v for k, v in old_residual.items() if k not in RESIDUAL_BOOLEANS}}
    assert new_header == old_header
    old, new = npy_entries(path.read_bytes()), npy_entries(again.read_bytes())
    assert list(new) == list(old)
    for name in ("residual/Y_codes.npy", "residual/C_codes.npy"):  # the same codes, stored anew
        assert np.load(io.BytesIO(new.pop(name))).shape == np.load(io.BytesIO(old.pop(name))).shape
    assert new == old  # every other array's .npy file byte for byte
    reloaded = load_field(again)
    np.testing.assert_array_equal(reloaded.residual.luminance.codes, luminance.codes)


def _assert_relights_as_recorded(field, recorded: str) -> None:
    """``field`` relit at the directions ``tests/data/RECORDED`` holds gives the images recorded there (circular and
    straight paths, specular and full)."""
    from warp_highlights.relight.relighter import Relighter

    expected = np.load(LEGACY / recorded)
    for method in ("circular", "straight"):
        relit = Relighter(field, device="cpu", diffuse="auto",
                          scale=1.0 / field.exposure).relight(expected["directions"], method=method)
        np.testing.assert_allclose(relit.specular, expected[f"{method}_specular"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(relit.full, expected[f"{method}_full"], rtol=1e-5, atol=1e-6)


def _headers(*paths: Path) -> tuple[dict, ...]:
    """The ``header.json`` of each field file."""
    return tuple(json.loads(entries(path.read_bytes())["header.json"]) for path in paths)


def test_describe_gives_the_checks_figures_from_the_fit_report():
    """``info``'s summary: the move check's and the learned check's scores, the latter's with its residual exact
    where the report has it (left out where it has not)."""
    field = make_field(LightSet.fibonacci_dome(16), size=(48, 27))
    field.moving = field.estimated.active.copy()  # the figures follow the moving Gaussians' line
    check = {"lights": 6, "with_gaussians_psnr_db": 28.605, "images_alone_psnr_db": 41.331,
             "exact_residual_psnr_db": 28.971, "keeps_gaussians": False, "sees_gaussians": False}
    field.report = {"residual": {"moving_specular_share": 0.4, "learned_check": check,
                                 "move_check": {"lights": 48, "moving_psnr_db": 38.331, "blend_psnr_db": 35.708}}}
    text = field.describe()
    assert "move check at 48 left-out lights: moving 38.33 dB, blending 35.71 dB" in text
    assert ("learned check: with the Gaussians 28.61 dB (28.97 with its residual exact), the images alone 41.33 dB"
            in text)
    field.report["residual"]["learned_check"] = {k: v for k, v in check.items() if k != "exact_residual_psnr_db"}
    assert "learned check: with the Gaussians 28.61 dB, the images alone 41.33 dB" in field.describe()
    assert "(the Gaussians glide)" not in field.describe()
    field.report["residual"]["learned_check"]["glides"] = True
    assert "the images alone 41.33 dB (the Gaussians glide)" in field.describe()
