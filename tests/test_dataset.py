"""ReflectanceField.load / save and DatasetWriter: round trips, atomic commits, one-line errors.

This module holds one thing: the tests of ``io.dataset``.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
import warnings

import numpy as np
import pytest

from warp_highlights.io.dataset import DatasetWriter, ReflectanceField
from warp_highlights.io.images import read_image, srgb_to_linear, write_image
from warp_highlights.io.lightfile import read_lp, write_lp
from warp_highlights.model import threads
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet

pytest.importorskip("OpenEXR")
pytest.importorskip("PIL")
pytest.importorskip("tqdm")


def _field(*, channels: int = 3, count: int = 5, heldout_count: int = 3, seed: int = 0) -> ReflectanceField:
    """Small synthetic field with ground truth, held-out lights, mask and metadata."""
    rng = np.random.default_rng(seed)

    def stack(n):
        shape = (n, 6, 7) if channels == 1 else (n, 6, 7, 3)
        return (rng.standard_normal(shape) * 3.0).astype(np.float32)

    def field_of(lights):
        diffuse, specular = stack(len(lights)), stack(len(lights))
        return ReflectanceField(diffuse + specular, lights, specular=specular, diffuse=diffuse)

    heldout = field_of(LightSet.fibonacci_dome(heldout_count, min_elevation_deg=20.0))
    main = field_of(LightSet.fibonacci_sphere(count))
    main.heldout = heldout
    main.mask = rng.uniform(size=(6, 7)) > 0.5
    main.meta = {"generator": "test", "shape": "donut", "resolution": [7, 6]}
    return main


def _assert_same(loaded: ReflectanceField, field: ReflectanceField) -> None:
    np.testing.assert_array_equal(loaded.images, field.images)
    np.testing.assert_array_equal(loaded.specular, field.specular)
    np.testing.assert_array_equal(loaded.diffuse, field.diffuse)
    np.testing.assert_allclose(loaded.lights.directions, field.lights.directions, rtol=0, atol=1e-15)


def _single_line_error(excinfo, *names: str) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    for name in names:
        assert name in message
    return message


def _jpeg_dataset(folder, sizes, *, lp_name="dirs.lp", mode="RGB"):
    """A real-capture-like folder: JPEGs of the given (width, height) and a .lp listing them."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    lights = LightSet.fibonacci_dome(len(sizes))
    names = [f"image{i:02d}.jpg" for i in range(len(sizes))]
    for name, (width, height) in zip(names, sizes):
        Image.new(mode, (width, height), 128).save(folder / name)
    write_lp(lights, folder / lp_name, names)
    return folder


# --- round trips ----------------------------------------------------------------------------------


@pytest.mark.parametrize("channels", [1, 3])
def test_streamed_dataset_loads_back_exactly(tmp_path, channels):
    field = _field(channels=channels)
    folder = tmp_path / "donut"
    with DatasetWriter(folder) as writer:
        for start in range(0, field.light_count, 2):  # chunks, as the renderer produces them
            chunk = slice(start, start + 2)
            writer.write_images("lights", start, field.images[chunk], field.specular[chunk], field.diffuse[chunk])
        held = field.heldout
        writer.write_images("heldout", 0, held.images, held.specular, held.diffuse)
        writer.finish(field.lights, held.lights, mask=field.mask, meta=field.meta)
    for name in ("images/0000.exr", "specular/0004.exr", "diffuse/0004.exr", "heldout/h0002.exr",
                 "specular/h0002.exr", "diffuse/h0000.exr", "lights.lp", "heldout.lp", "mask.png", "meta.json"):
        assert (folder / name).is_file(), name
    assert json.loads((folder / "meta.json").read_text()) == field.meta
    assert [p.name for p in tmp_path.iterdir()] == ["donut"]  # temporary folder renamed away

    loaded = ReflectanceField.load(folder, progress=False)
    _assert_same(loaded, field)
    _assert_same(loaded.heldout, field.heldout)
    np.testing.assert_array_equal(loaded.mask, field.mask)
    assert loaded.meta == field.meta
    assert loaded.root == folder and loaded.channels == channels
    assert (loaded.light_count, loaded.height, loaded.width) == (5, 6, 7)
    assert loaded.lights.filenames[0] == "images/0000.exr"


def test_save_half_is_exact_to_half(tmp_path):
    field = _field()
    field.save(tmp_path / "half", half=True)
    loaded = ReflectanceField.load(tmp_path / "half", progress=False)
    np.testing.assert_array_equal(loaded.images, field.images.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(loaded.heldout.diffuse, field.heldout.diffuse.astype(np.float16).astype(np.float32))


def test_save_without_extras(tmp_path):
    field = ReflectanceField(np.ones((2, 3, 4), np.float32), LightSet(np.eye(3)[:2]))
    field.save(tmp_path / "plain")
    assert sorted(p.name for p in (tmp_path / "plain").iterdir()) == [".warp-highlights.json", "images", "lights.lp"]
    loaded = ReflectanceField.load(tmp_path / "plain", progress=False)
    assert loaded.specular is None and loaded.heldout is None and loaded.mask is None and loaded.meta == {}


def test_empty_heldout_set_writes_no_heldout_file(tmp_path):
    with DatasetWriter(tmp_path / "d") as writer:
        writer.write_images("lights", 0, np.full((2, 3, 4), 0.5, np.float32))  # all black would be refused
        writer.finish(LightSet.fibonacci_sphere(2), LightSet(np.zeros((0, 3))))
    assert not (tmp_path / "d" / "heldout.lp").exists()
    assert ReflectanceField.load(tmp_path / "d", progress=False).heldout is None


def test_many_lights_get_wider_names(tmp_path):
    writer = DatasetWriter(tmp_path / "wide")
    writer.write_images("lights", 10000, np.zeros((1, 2, 2), np.float32))
    writer.write_images("heldout", 7, np.zeros((1, 2, 2), np.float32))
    names = sorted(str(p.relative_to(p.parents[1])) for p in tmp_path.glob(".wide.partial-*/*/*.exr"))
    assert names == ["heldout/h0007.exr", "images/10000.exr"]
    writer.abort()
    assert not any(tmp_path.iterdir())


def test_png_dataset_in_sub_folders_with_linear_flag(tmp_path):
    folder = tmp_path / "capture"
    levels = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4) * 10
    names = [f"shots/a b/{i}.png" for i in range(2)]
    for name, image in zip(names, levels):
        write_image(folder / name, image / 255.0, linear=True)
    write_lp(LightSet(np.array([[0, 0, 1], [0, 1, 1]]), names), folder / "capture.lp")
    loaded = ReflectanceField.load(folder, linear=True, progress=False)
    np.testing.assert_array_equal(loaded.images, (levels / 255.0).astype(np.float32))
    decoded = ReflectanceField.load(folder, progress=False)
    np.testing.assert_array_equal(decoded.images, srgb_to_linear(levels / 255.0).astype(np.float32))
    np.testing.assert_array_equal(decoded.images[1], read_image(folder / names[1]))


def test_lights_lp_wins_over_other_lp_and_heldout_lp_is_not_a_candidate(tmp_path):
    field = _field()
    field.save(tmp_path / "d")
    write_lp(LightSet(np.eye(3), ["x", "y", "z"]), tmp_path / "d" / "other.lp")
    assert ReflectanceField.load(tmp_path / "d", progress=False).light_count == 5
    (tmp_path / "d" / "other.lp").unlink()
    (tmp_path / "d" / "lights.lp").rename(tmp_path / "d" / "capture.lp")
    loaded = ReflectanceField.load(tmp_path / "d", progress=False)
    assert loaded.light_count == 5 and loaded.heldout.light_count == 3


# --- the writer's safety --------------------------------------------------------------------------


def test_writer_refuses_an_existing_folder(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "keep.txt").write_text("precious")
    with pytest.raises(InputError) as excinfo:
        DatasetWriter(tmp_path / "d")
    assert "exists; pass --overwrite" in _single_line_error(excinfo, "d")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        DatasetWriter(tmp_path / "file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d", "file"]


def test_writer_uses_an_existing_empty_folder(tmp_path):
    (tmp_path / "d").mkdir()
    _field().save(tmp_path / "d")
    assert ReflectanceField.load(tmp_path / "d", progress=False).light_count == 5


def test_overwrite_replaces_the_folder(tmp_path):
    _field(seed=1, count=6).save(tmp_path / "d")
    field = _field(seed=2, count=4)
    field.save(tmp_path / "d", overwrite=True)
    assert not (tmp_path / "d" / "images" / "0005.exr").exists()  # the old dataset is gone entirely
    _assert_same(ReflectanceField.load(tmp_path / "d", progress=False), field)
    assert [p.name for p in tmp_path.iterdir()] == ["d"]


def test_overwrite_never_deletes_files_the_project_did_not_write(tmp_path):
    _field(seed=1).save(tmp_path / "d")
    (tmp_path / "d" / "notes.txt").write_text("the user's")
    (tmp_path / "d" / "images" / "extra.jpg").write_bytes(b"a photo")
    before = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(InputError) as excinfo:
        _field(seed=2).save(tmp_path / "d", overwrite=True)
    assert "did not write" in _single_line_error(excinfo, "d")
    assert {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    (tmp_path / "d" / "notes.txt").unlink()
    with pytest.raises(InputError, match="extra.jpg"):  # files inside sub-folders count too
        _field(seed=2).save(tmp_path / "d", overwrite=True)


def test_overwrite_replaces_a_dataset_written_before_manifests(tmp_path):
    _field(seed=1).save(tmp_path / "d")
    (tmp_path / "d" / ".warp-highlights.json").unlink()  # as written by version 0.1
    (tmp_path / "d" / "images" / "photo.jpg").write_bytes(b"the user's")
    with pytest.raises(InputError, match="images/photo.jpg"):  # recognised file by file, sub-folders too
        _field(seed=2).save(tmp_path / "d", overwrite=True)
    (tmp_path / "d" / "images" / "photo.jpg").unlink()
    field = _field(seed=2, count=4)
    field.save(tmp_path / "d", overwrite=True)
    _assert_same(ReflectanceField.load(tmp_path / "d", progress=False), field)


def test_abort_leaves_an_existing_folder_intact(tmp_path):
    folder = tmp_path / "d"
    _field(seed=1).save(folder)
    before = {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    with pytest.raises(RuntimeError, match="renderer crashed"):
        with DatasetWriter(folder, overwrite=True) as writer:
            writer.write_images("lights", 0, np.zeros((2, 6, 7, 3), np.float32))
            raise RuntimeError("renderer crashed")
    after = {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert after == before
    assert [p.name for p in tmp_path.iterdir()] == ["d"]


def test_explicit_abort_and_misuse(tmp_path):
    writer = DatasetWriter(tmp_path / "d")
    with pytest.raises(ValueError, match="finish"):
        writer.commit()
    with pytest.raises(ValueError, match="group"):
        writer.write_images("other", 0, np.zeros((1, 2, 2)))
    with pytest.raises(ValueError, match="1 non-finite"):
        writer.write_images("lights", 0, np.array([[[0.0, np.nan], [0.0, 0.0]]]))
    writer.write_images("lights", 0, np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="shape"):
        writer.write_images("lights", 2, np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match=r"no image written for light\(s\) \[2\]"):
        writer.finish(LightSet.fibonacci_sphere(3), None)
    with pytest.raises(ValueError, match="beyond"):
        writer.finish(LightSet.fibonacci_sphere(1), None)
    writer.abort()
    writer.abort()
    assert not any(tmp_path.iterdir())


def test_finish_rejects_partial_ground_truth(tmp_path):
    with pytest.raises(ValueError, match="specular images written for some lights"):
        with DatasetWriter(tmp_path / "d") as writer:
            writer.write_images("lights", 0, np.zeros((1, 2, 2)), specular=np.zeros((1, 2, 2)))
            writer.write_images("lights", 1, np.zeros((1, 2, 2)))
            writer.finish(LightSet.fibonacci_sphere(2), None)
    assert not any(tmp_path.iterdir())


def test_leaving_the_block_without_finish_aborts(tmp_path):
    with pytest.raises(ValueError, match="finish"):
        with DatasetWriter(tmp_path / "d") as writer:
            writer.write_images("lights", 0, np.zeros((1, 2, 2)))
    assert not any(tmp_path.iterdir())


# --- bad datasets ---------------------------------------------------------------------------------


def test_missing_folder(tmp_path):
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "nowhere", progress=False)
    _single_line_error(excinfo, "nowhere", "not found")


def test_no_light_file(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "d", progress=False)
    _single_line_error(excinfo, "no light file")


def test_several_light_files_are_listed(tmp_path):
    folder = _jpeg_dataset(tmp_path / "d", [(8, 6)] * 2)
    (folder / "b.lp").write_text((folder / "dirs.lp").read_text())
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _single_line_error(excinfo, "several light files", "b.lp, dirs.lp")


def test_missing_image(tmp_path):
    folder = _jpeg_dataset(tmp_path / "d", [(8, 6)] * 3)
    (folder / "image01.jpg").unlink()
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _single_line_error(excinfo, "dirs.lp:3:", "image01.jpg")


def test_mismatched_size_names_the_file_and_both_sizes(tmp_path):
    folder = _jpeg_dataset(tmp_path / "d", [(8, 6), (8, 6), (9, 6)])
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _single_line_error(excinfo, "image02.jpg: image is 9x6", "image00.jpg is 8x6")


def test_mismatched_channels(tmp_path):
    folder = _jpeg_dataset(tmp_path / "d", [(8, 6)] * 2)
    from PIL import Image

    Image.new("L", (8, 6), 100).save(folder / "image01.jpg")
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _single_line_error(excinfo, "image01.jpg: image has 1 channel(s)", "has 3")


def test_heldout_of_another_size(tmp_path):
    folder = _jpeg_dataset(tmp_path / "d", [(8, 6)] * 2)
    _jpeg_dataset(tmp_path / "t", [(8, 7)])
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, heldout=tmp_path / "t", progress=False)
    _single_line_error(excinfo, "image00.jpg: image is 8x7")
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, heldout=tmp_path / "missing", progress=False)
    _single_line_error(excinfo, "missing", "not found")


def _nan_dataset(tmp_path):
    """A dataset with non-finite pixels, as a foreign tool might write it (our writer refuses them)."""
    field = _field(count=3)
    field.save(tmp_path / "d")
    field.images[1, 0, 0, 0] = np.nan
    field.images[2, 1, :2, 1] = np.inf
    field.heldout.specular[0, 0, 0, 0] = -np.inf
    write_image(tmp_path / "d" / "images" / "0001.exr", field.images[1])
    write_image(tmp_path / "d" / "images" / "0002.exr", field.images[2])
    write_image(tmp_path / "d" / "specular" / "h0000.exr", field.heldout.specular[0])
    return tmp_path / "d"


def test_nonfinite_pixels_are_counted(tmp_path):
    folder = _nan_dataset(tmp_path)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False)
    _single_line_error(excinfo, "4 non-finite pixel values", "0001.exr", "replace_nonfinite=True")


def test_nonfinite_pixels_replaced_on_request(tmp_path):
    folder = _nan_dataset(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = ReflectanceField.load(folder, replace_nonfinite=True, progress=False)
    assert any("4 non-finite" in str(w.message) for w in caught)
    assert loaded.images[1, 0, 0, 0] == 0.0 and np.all(loaded.images[2, 1, :2, 1] == 0.0)
    assert loaded.heldout.specular[0, 0, 0, 0] == 0.0
    assert np.isfinite(loaded.images).all()


def test_partial_specular_set_names_the_first_missing(tmp_path):
    _field().save(tmp_path / "d")
    (tmp_path / "d" / "specular" / "0002.exr").unlink()
    (tmp_path / "d" / "specular" / "0003.exr").unlink()
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "d", progress=False)
    _single_line_error(excinfo, "specular/0002.exr: missing specular image for 0002.exr", "all 5 lights or none")


def test_ground_truth_of_another_size(tmp_path):
    _field().save(tmp_path / "d")
    write_image(tmp_path / "d" / "diffuse" / "h0001.exr", np.zeros((6, 8, 3), np.float32))
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "d", progress=False)
    _single_line_error(excinfo, "h0001.exr: image is 8x6")


def test_bad_mask_and_meta(tmp_path):
    _field().save(tmp_path / "d")
    write_image(tmp_path / "d" / "mask.png", np.ones((5, 7)))
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "d", progress=False)
    _single_line_error(excinfo, "mask.png: mask is 7x5")
    (tmp_path / "d" / "mask.png").unlink()
    (tmp_path / "d" / "meta.json").write_text('{\n  "shape": donut\n}\n')
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(tmp_path / "d", progress=False)
    _single_line_error(excinfo, "meta.json:2: invalid JSON")
    (tmp_path / "d" / "meta.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="JSON object"):
        ReflectanceField.load(tmp_path / "d", progress=False)


def test_constructor_checks_shapes():
    lights = LightSet.fibonacci_sphere(2)
    with pytest.raises(InputError, match="3 images for 2 light"):
        ReflectanceField(np.zeros((3, 4, 4)), lights)
    with pytest.raises(InputError, match="specular"):
        ReflectanceField(np.zeros((2, 4, 4)), lights, specular=np.zeros((2, 4, 5)))
    with pytest.raises(InputError, match="mask"):
        ReflectanceField(np.zeros((2, 4, 4)), lights, mask=np.zeros((4, 5)))
    with pytest.raises(InputError, match="shape"):
        ReflectanceField(np.zeros((2, 4, 4, 2)), lights)


# --- the real samples -----------------------------------------------------------------------------


@pytest.mark.realdata
def test_synthrti_sample_loads_with_sibling_heldout(data_root):
    sample = data_root / "synthrti-object1-material5"
    field = ReflectanceField.load(sample / "Dome", heldout=sample / "Test", progress=False)
    assert field.images.shape == (49, 320, 320, 3) and field.images.dtype == np.float32
    assert field.heldout.images.shape == (20, 320, 320, 3)
    assert field.heldout.lights.light_count == 20
    assert 0.0 <= field.images.min() and field.images.max() <= 1.0
    assert field.specular is None and field.mask is None


@pytest.mark.realdata
def test_realrti_sample_loads(data_root):
    field = ReflectanceField.load(data_root / "realrti-item11", progress=False)
    assert field.light_count == 54 and field.channels == 3
    assert (field.width, field.height) == (567, 534)
    assert field.heldout is None


# --- loading in threads, at the working size, only what fit uses ----------------------------------


def test_threads_load_the_same_stack_in_file_order(small_donut):
    one = ReflectanceField.load(small_donut, progress=False, workers=1)
    four = ReflectanceField.load(small_donut, progress=False, workers=4)
    np.testing.assert_array_equal(four.images, one.images)
    np.testing.assert_array_equal(four.heldout.images, one.heldout.images)
    np.testing.assert_array_equal(four.specular, one.specular)
    assert four.lights.filenames == one.lights.filenames
    with pytest.raises(InputError, match="workers"):
        ReflectanceField.load(small_donut, progress=False, workers=0)


def test_loading_at_a_working_size_is_the_area_average_of_each_image(small_donut):
    from warp_highlights.io.resample import resample_image, resize_stack

    full = ReflectanceField.load(small_donut, progress=False)
    small = ReflectanceField.load(small_donut, progress=False, size=(48, 27))
    assert (small.width, small.height) == (48, 27) and small.source["size"] == [96, 54] == full.source["size"]
    np.testing.assert_array_equal(small.images, resize_stack(full.images, 48, 27))
    np.testing.assert_array_equal(small.heldout.images, resize_stack(full.heldout.images, 48, 27))
    if full.mask is not None:
        np.testing.assert_array_equal(small.mask, resample_image(full.mask.astype(np.float32), 48, 27) >= 0.5)
    with pytest.raises(InputError, match="aspect ratio"):
        ReflectanceField.load(small_donut, progress=False, size=(48, 48))


def test_fit_loads_only_what_it_uses_at_its_working_size(small_donut, tmp_path, monkeypatch):
    """``fit`` skips the held-out ground truth and shrinks each image as it is decoded; the report
    keeps the files' size."""
    from conftest import TINY_FIT
    from warp_highlights.cli import main
    from warp_highlights.io import dataset as dataset_module
    from warp_highlights.io.fieldfile import load_field

    decoded = []
    for reader in ("read_image", "read_pixels"):  # the mask's reader, the images'
        real = getattr(dataset_module, reader)
        monkeypatch.setattr(dataset_module, reader,
                            lambda path, real=real, **k: decoded.append(path.name) or real(path, **k))
    out = tmp_path / "field.whf"
    assert main(["fit", str(small_donut), "-o", str(out), "--size", "48x27", "--device", "cpu", "-q", *TINY_FIT]) == 0
    lights = read_lp(small_donut / "lights.lp")
    names = [name.split("/")[-1] for name in lights.filenames]
    # no held-out image, no ground truth; the capture's fingerprint reads its first, middle and last image again
    fingerprinted = [names[0], names[len(names) // 2], names[-1]]
    assert sorted(decoded) == sorted(names + ["mask.png"] + fingerprinted)
    field = load_field(out)
    assert (field.width, field.height) == (48, 27) and field.report["source_size"] == [96, 54]


def test_a_bad_image_among_many_stops_the_threaded_load_with_one_line(small_donut, tmp_path):
    import shutil

    folder = tmp_path / "donut"
    shutil.copytree(small_donut, folder)
    victim = folder / read_lp(folder / "lights.lp").filenames[17]
    victim.write_bytes(victim.read_bytes()[:200])  # truncated
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False, workers=4)
    assert victim.name in str(excinfo.value) and "\n" not in str(excinfo.value)


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_a_signal_while_a_writer_thread_starts_leaves_no_thread_writing(tmp_path, monkeypatch):
    """SIGINT handled between a worker thread's start and the pool's record of it (CI saw this once):
    that thread must not go on writing images into the dataset's temporary folder once it is removed."""
    import warp_highlights.io.dataset as dataset_module
    from warp_highlights.io import atomic

    real_start, real_write = threading.Thread.start, dataset_module.write_image
    signalled = []

    def start(thread):
        real_start(thread)
        if thread.name.startswith(dataset_module.WRITER_THREAD_PREFIX) and not signalled:
            signalled.append(thread)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs here: inside Thread.start, as a signal during its wait would

    def slow_write(*args, **kwargs):
        time.sleep(0.2)  # still writing after the folder is removed, if it was left running
        real_write(*args, **kwargs)

    monkeypatch.setattr(threading.Thread, "start", start)
    monkeypatch.setattr(dataset_module, "write_image", slow_write)
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    atomic.handle_termination()
    try:
        with pytest.raises(KeyboardInterrupt):
            with DatasetWriter(tmp_path / "out") as writer:
                writer.write_images("lights", 0, np.full((6, 4, 8), 0.5, np.float32))
        for thread in signalled:
            thread.join(timeout=10)
    finally:
        atomic.end_of_command()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    assert signalled, "no writer thread was started"
    assert os.listdir(tmp_path) == [], "the interrupted dataset left something behind"


# --- threaded decoding -------------------------------------------------------------------------------


def test_images_decoded_out_of_order_land_in_their_places(tmp_path, monkeypatch):
    """Each decoding thread copies its image into the stack: the first images finish last here."""
    from warp_highlights.io import dataset as dataset_module

    field = _field(count=9)
    folder = field.save(tmp_path / "capture")
    real = dataset_module.read_pixels

    def slow_first(path, **kwargs):
        index = int(path.stem) if path.stem.isdigit() else 0
        time.sleep(0.02 * max(0, 4 - index))  # images 0..3 decode last
        return real(path, **kwargs)

    monkeypatch.setattr(dataset_module, "read_pixels", slow_first)
    # the stack's pages written from threads, as a large capture's are
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 0)
    loaded = ReflectanceField.load(folder, progress=False, heldout=False, components=False, workers=4)
    np.testing.assert_array_equal(loaded.images, field.images)


def test_loads_run_from_the_shared_threads_do_not_wait_for_ever(tmp_path, monkeypatch):
    """A load inside a parallel map: its decoding threads' own maps (the stack's page fill) run in
    place instead of queueing behind the workers that wait for them."""
    field = _field(count=4)
    folder = field.save(tmp_path / "capture")
    monkeypatch.setattr(threads, "PREFAULT_BYTES", 0)
    monkeypatch.setattr(threads, "NUMPY_THREADS", max(2, threads.NUMPY_THREADS))
    outcome = []

    def many_loads():
        count = 2 * threads.shared_pool()._max_workers
        outcome.extend(threads.parallel_map(
            lambda _: ReflectanceField.load(folder, progress=False, heldout=False, components=False, workers=2).images,
            range(count)))

    runner = threading.Thread(target=many_loads, daemon=True)
    runner.start()
    runner.join(120)
    assert not runner.is_alive(), "the loads waited for each other"
    assert outcome and all(np.array_equal(images, field.images) for images in outcome)


def test_an_image_decoded_to_another_shape_than_the_first_is_named(tmp_path, monkeypatch):
    from warp_highlights.io import dataset as dataset_module

    field = _field(count=6)
    folder = field.save(tmp_path / "capture")
    real = dataset_module.read_pixels

    def odd_one(path, **kwargs):
        image = real(path, **kwargs)
        return image[..., :1] if path.stem == "0003" else image  # passed the header check, decoded otherwise

    monkeypatch.setattr(dataset_module, "read_pixels", odd_one)
    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False, heldout=False, components=False, workers=3)
    message = _single_line_error(excinfo, "0003", "0000")
    assert "first image" in message


def test_a_set_stop_ends_the_loading_early(tmp_path):
    """``stop`` (a caller loading in a thread whose own work failed): the loading raises LoadStopped at
    the first image it would decode or check, and no decoding thread is left running."""
    import threading

    from warp_highlights.io.dataset import LoadStopped

    field = _field(channels=3)
    folder = tmp_path / "donut"
    with DatasetWriter(folder) as writer:
        writer.write_images("lights", 0, field.images, field.specular, field.diffuse)
        writer.finish(field.lights, None, mask=field.mask, meta=field.meta)
    stop = threading.Event()
    stop.set()
    with pytest.raises(LoadStopped, match="loading stopped"):
        ReflectanceField.load(folder, progress=False, stop=stop)
    assert not [thread for thread in threading.enumerate() if thread.name.startswith("load")]
    assert ReflectanceField.load(folder, progress=False, stop=threading.Event()).light_count == field.light_count


@pytest.mark.parametrize("replacement", ["larger", "grey", "other size"])
def test_an_image_replaced_after_its_header_was_read_is_checked_again(tmp_path, replacement):
    """The decoders take each header the loader read first, unless the file changed since (its size or time):
    then it is read and checked again, so the pixel budget and the shape checks name it as before."""
    field = _field(count=6)
    folder = field.save(tmp_path / "capture")
    target = folder / "images" / "0003.exr"
    image = {"larger": np.ones((60, 70, 3)), "grey": np.ones((6, 7)), "other size": np.ones((6, 8, 3))}[replacement]

    def swap(_stack_bytes):  # once every header is read, before any image is decoded
        write_image(target, image.astype(np.float32))

    with pytest.raises(InputError) as excinfo:
        ReflectanceField.load(folder, progress=False, heldout=False, components=False, max_pixels=1000,
                              before_decoding=swap)
    expected = {"larger": "over the limit", "grey": "channel(s) but the first image",
                "other size": "all images must share one size"}
    _single_line_error(excinfo, "0003.exr", expected[replacement])


def test_images_whose_infinities_are_replaced_are_measured_after(tmp_path):
    """An all-black capture but for an infinite pixel, replaced by 0: still all black (the range is taken
    again once the pixel is replaced)."""
    images = np.zeros((4, 6, 7, 3), np.float32)
    ReflectanceField(images, LightSet.fibonacci_sphere(4)).save(tmp_path / "d")
    images[2, 3, 4, 1] = np.inf
    write_image(tmp_path / "d" / "images" / "0002.exr", images[2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(InputError) as excinfo:
            ReflectanceField.load(tmp_path / "d", replace_nonfinite=True, progress=False)
    _single_line_error(excinfo, "entirely black")


def test_each_exr_header_is_read_once_while_loading(tmp_path, monkeypatch):
    """The loader's plan reads every image's header; the decoders take it from there (each decoding thread's
    call back into Python can wait a whole GIL switch interval beside the pipeline's imports)."""
    import OpenEXR

    field = _field(count=5, heldout_count=3)
    folder = field.save(tmp_path / "capture")
    headers, real = [], OpenEXR.File

    def counting(*args, **kwargs):
        if kwargs.get("header_only"):
            headers.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(OpenEXR, "File", counting)
    loaded = ReflectanceField.load(folder, progress=False)
    _assert_same(loaded, field)
    # images, specular and diffuse parts, main and held-out lights
    counts = {name: headers.count(name) for name in headers}
    assert len(counts) == 3 * (5 + 3) and sum(counts.values()) == len(counts) + 1
    assert counts[str(folder / "images" / "0000.exr")] == 2  # the first image's once more: its encoding, for the report
