"""How the field file stores basis codes (``io.codes``): row differences in byte planes, run-length
deflate; the rate search counts the bytes the file holds."""

from __future__ import annotations

import dataclasses
import io
import zipfile
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from warp_highlights.io.codes import (
    STREAM_END,
    DeflatedCodes,
    codes_from_stored,
    deflated_piece,
    deflated_size,
    stored_bytes,
    stored_codes,
    stored_shape,
)
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.model.residual import ResidualModel, code_levels
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import quantised_stack
from warp_highlights.residual.rate import RateSample, component_bytes

RNG = np.random.default_rng(14)


def _reference_stored(codes: np.ndarray) -> np.ndarray:
    """The stored form in plain integer arithmetic: (P, R, W) codes -> row differences mod 2^bits, byte planes."""
    bits = 8 * codes.dtype.itemsize
    values = codes.astype(np.int64)
    above = np.concatenate([np.zeros_like(values[..., :1, :]), values[..., :-1, :]], axis=-2)
    difference = (values - above) % (1 << bits)
    if bits == 8:
        return difference.astype(np.uint8)
    return np.stack([difference // 256, difference % 256], axis=-3).astype(np.uint8)


@settings(max_examples=60, deadline=None)
@given(bits=st.sampled_from([8, 16]), data=st.data())
def test_stored_codes_are_row_differences_in_byte_planes_and_come_back_exactly(bits, data):
    kind = np.uint8 if bits == 8 else np.uint16
    shape = data.draw(st.tuples(st.integers(1, 3), st.integers(1, 2), st.integers(1, 9), st.integers(1, 7)))
    # extremes included: differences wrap
    codes = data.draw(hnp.arrays(kind, shape, elements=st.integers(0, code_levels(bits))))
    stored = np.stack([stored_codes(image) for image in codes])
    assert stored.dtype == np.uint8 and stored.shape == stored_shape(*shape, bits)
    np.testing.assert_array_equal(stored, np.stack([_reference_stored(image) for image in codes]))
    back = codes_from_stored(stored, bits)
    assert back.dtype == kind
    np.testing.assert_array_equal(back, codes)


@pytest.mark.parametrize("kind", [np.uint8, np.uint16])
def test_a_band_of_rows_with_the_row_above_it_is_stored_as_the_whole_image_stores_it(kind):
    """What the rate search samples: a band taken with the row above it, its first stored row dropped."""
    codes = RNG.integers(0, np.iinfo(kind).max + 1, size=(2, 30, 11)).astype(kind)
    whole = stored_codes(codes)
    band = stored_codes(codes[:, 11:20])[..., 1:, :]
    np.testing.assert_array_equal(band, whole[..., 12:20, :])
    assert deflated_size(band) == deflated_size(whole[..., 12:20, :])


def test_smooth_16_bit_codes_store_smaller_and_faster_than_as_they_are():
    """The point of the layout: a smooth basis image with a little noise (what the residual's basis
    images look like) takes fewer bytes than its codes deflated as they are at zlib's default level."""
    yy, xx = np.mgrid[0:200, 0:300] / 200.0
    image = np.sin(5 * xx + 2 * yy) * np.exp(-((xx - 0.7) ** 2 + (yy - 0.5) ** 2) * 3) + 2e-4 * RNG.normal(size=xx.shape)
    codes = np.round((image - image.min()) / (image.max() - image.min()) * 65535).astype(np.uint16)[None]
    assert stored_bytes(codes) < 0.9 * len(zlib.compress(codes.tobytes(), 6))


def _smooth_stack(n: int, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 3 * xx + i) * np.cos((i % 5 + 1) * 2 * yy) for i in range(8)])
    stack = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 8)) * 0.8 ** np.arange(8), patterns)[..., None] + 1.0
    return stack + 1e-3 * RNG.normal(size=stack.shape)


@pytest.mark.parametrize("bits", [8, 16])
def test_the_sampled_bytes_are_the_whole_images_stored_bytes_at_the_sampled_rows(bits):
    """A sampled ``RateSample`` deflates each band of rows as the file stores those rows (the first row
    of a band less the row above it, not as it is)."""
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    sample = RateSample(principal, 3)
    assert not sample.exact
    steps = principal.spans[:3] / code_levels(bits) * 7.0
    counted = sample.rows[sample.counted]
    stack = quantised_stack(principal, steps, bits=bits)
    expected = sum(deflated_size(stored_codes(code.transpose(2, 0, 1))[..., counted, :]) for code in stack.codes)
    assert sample.bytes(steps, bits=bits) == pytest.approx(expected * 320 / len(counted) + sample.per_image * 3, rel=1e-12)
    assert RateSample(principal, 3, whole=True).bytes(steps, bits=bits) == float(component_bytes(stack).sum())


def _codes_entry(field, stack, path):
    """(ZipInfo, raw bytes, the stored array numpy reads) of the luminance codes entry of ``field``
    with ``stack`` as its residual, written to ``path``."""
    field = dataclasses.replace(field, residual=ResidualModel(luminance=stack))
    save_field(field, path)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("residual/Y_codes.npy")
        raw = archive.read(info)
    return info, raw, np.load(io.BytesIO(raw))


@pytest.mark.parametrize("bits", [8, 16])
def test_the_file_holds_the_stored_codes_in_the_bytes_the_budget_counted(bits, tmp_path):
    """``numpy.load`` reads the codes entry as the stored form: the ``.npy`` header's deflated piece,
    each image's (``deflated_piece``, run-length), then the stream's end. Its compressed size is what
    ``component_bytes`` counts and those two; the field loads the same codes back."""
    from test_field import make_field

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    stack = quantised_stack(principal, principal.spans / code_levels(bits) * 3.0, bits=bits)
    path = tmp_path / "f.whf"
    info, raw, stored = _codes_entry(field, stack, path)
    np.testing.assert_array_equal(stored, np.stack([stored_codes(code.transpose(2, 0, 1)) for code in stack.codes]))
    header = raw[: len(raw) - stored.nbytes]
    counted = float(component_bytes(stack).sum()) - stack.rank * (8 + 4 * len(stack.weights))
    assert info.compress_size == len(deflated_piece(header)) + counted + len(STREAM_END)
    assert zlib.decompressobj(-15).decompress(deflated_piece(header) + b"".join(deflated_piece(image) for image in stored) + STREAM_END) == raw
    np.testing.assert_array_equal(load_field(path).residual.luminance.codes, stack.codes)


@pytest.mark.parametrize("whole", [False, True])
def test_the_rate_search_keeps_the_pieces_the_file_then_stores(whole, tmp_path, monkeypatch):
    """``allocate``'s last measurement on every row keeps each image's deflated piece (the small image
    here is measured whole; the larger one in samples, then on every row); the writer stores those
    pieces without deflating the images again, and the file is the one written without them."""
    from test_field import make_field

    import warp_highlights.io.codes as codes_module
    from warp_highlights.residual.rate import StackPlan, allocate

    field = make_field() if whole else make_field(size=(160, 240))
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    assert RateSample(principal, 1).exact == whole
    plan = StackPlan(principal, 1.0, principal.count - 1)
    budget = 0.5 * float(component_bytes(quantised_stack(principal, principal.spans / code_levels(16), bits=16)).sum())
    _, (steps,) = allocate([plan], budget, bits=16)
    assert len(plan.deflated) == len(steps) > 0
    kept = quantised_stack(principal, steps, bits=16, deflated=plan.deflated)
    plain = quantised_stack(principal, steps, bits=16)
    assert plain.deflated is None
    for name in ("codes", "ranges", "weights", "mean_weights"):  # the pieces change nothing of the model
        np.testing.assert_array_equal(getattr(kept, name), getattr(plain, name))
    deflated = []
    real = codes_module.deflated_piece
    monkeypatch.setattr(codes_module, "deflated_piece", lambda data: deflated.append(len(data)) or real(data))
    _, kept_raw, _ = _codes_entry(field, kept, tmp_path / "kept.whf")
    assert deflated == []  # every image's piece was found
    _, plain_raw, _ = _codes_entry(field, plain, tmp_path / "plain.whf")
    assert len(deflated) == len(steps)  # without them, each image deflated here
    assert (tmp_path / "kept.whf").read_bytes() == (tmp_path / "plain.whf").read_bytes()


def test_pieces_kept_for_other_codes_are_not_used(tmp_path):
    """Pieces are found by content: a stack whose kept pieces are another quantisation's writes its own."""
    from test_field import make_field

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    coarse, fine = (principal.spans / code_levels(16) * factor for factor in (40.0, 2.0))
    store = DeflatedCodes()
    RateSample(principal, len(coarse), whole=True).bytes(coarse, bits=16, keep=store)
    stale = quantised_stack(principal, fine, bits=16, deflated=store)
    fresh = quantised_stack(principal, fine, bits=16)
    _codes_entry(field, stale, tmp_path / "stale.whf")
    _codes_entry(field, fresh, tmp_path / "fresh.whf")
    assert (tmp_path / "stale.whf").read_bytes() == (tmp_path / "fresh.whf").read_bytes()
    np.testing.assert_array_equal(load_field(tmp_path / "stale.whf").residual.luminance.codes, fresh.codes)


def test_only_a_sample_of_every_row_keeps_pieces():
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    with pytest.raises(ValueError, match="every row"):
        RateSample(principal, 3).bytes(principal.spans[:3] / 255, bits=8, keep=DeflatedCodes())


def test_the_latest_two_measurements_are_kept():
    """A search's answer is its last measurement or the one before: pieces of both are found, older
    ones are deflated again (and are the same bytes)."""
    rng = np.random.default_rng(8)
    images = [rng.integers(0, 4, size=(2, 9, 11), dtype=np.uint8) for _ in range(3)]
    store = DeflatedCodes()
    for image in images:
        store.keep({DeflatedCodes.key(image): b"kept"})
    assert len(store) == 1
    assert store.piece(images[2]) == b"kept" and store.piece(images[1]) == b"kept"
    assert store.piece(images[0]) == deflated_piece(images[0])  # dropped: deflated now


@pytest.mark.parametrize("chunk", [1 << 15, 7, 1])
@pytest.mark.parametrize("bits", [8, 16])
def test_codes_rounded_a_chunk_at_a_time_are_those_of_the_whole(monkeypatch, chunk, bits):
    """``quantised_codes`` (float64 a chunk at a time, from any strides) gives ``codes_in_place``'s codes
    on the whole images, ties and clipping included: flat images, and (P, R, W) views planes first."""
    import warp_highlights.residual.quantise as residual_module
    from warp_highlights.residual.quantise import codes_in_place, quantised_codes

    monkeypatch.setattr(residual_module, "_QUANTISE_CHUNK", chunk)
    levels = code_levels(bits)
    kind = np.uint8 if bits == 8 else np.uint16
    images = RNG.normal(size=(3, 9, 13, 2)).astype(np.float32)
    images[0, 0, 0, 0] = 0.5  # a tie of the rounding: (0.5 - 0) / 1 = 0.5 rounds to even
    low = np.array([0.0, -1.5, -3.0])
    step = np.array([1.0, 3.0 / levels * 2.0, 6.0 / levels])  # the second image clips at both ends
    for values in (images.reshape(3, -1), images.transpose(0, 3, 1, 2)):
        expected = codes_in_place(values.astype(np.float64), low.reshape((3,) + (1,) * (values.ndim - 1)),
                                  step.reshape((3,) + (1,) * (values.ndim - 1)), levels).astype(kind)
        got = quantised_codes(values, low, step, levels, out=np.empty(values.shape, kind))
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("whole", [False, True])
def test_a_rate_sample_deflates_each_image_once_per_step(monkeypatch, whole):
    """``RateSample.deflated``: each image's bytes at the sample's rows (a subset measures only its
    images, the same bytes, the others 0); an image measured before at the same step and bits is not
    deflated again, another step or bit depth is."""
    import warp_highlights.residual.rate as residual_module

    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    steps = principal.spans[:5] / code_levels(16) * np.array([2.0, 5.0, 9.0, 30.0, 4.0])
    calls = []
    real = residual_module.deflated_piece
    monkeypatch.setattr(residual_module, "deflated_piece", lambda data: calls.append(1) or real(data))
    sample = RateSample(principal, 5, whole=whole)
    assert sample.exact == whole
    subset = sample.deflated(steps, bits=16, images=np.array([3, 1, 3]))
    assert len(calls) == 2 and not subset[[0, 2, 4]].any() and subset[[1, 3]].all()
    every = sample.deflated(steps, bits=16)
    assert len(calls) == 5
    np.testing.assert_array_equal(every[[1, 3]], subset[[1, 3]])
    stack = quantised_stack(principal, steps, bits=16)
    counted = sample.rows[sample.counted] if not whole else np.arange(320)
    expected = [deflated_size(stored_codes(code.transpose(2, 0, 1))[..., counted, :]) for code in stack.codes]
    np.testing.assert_array_equal(every, expected)
    changed = steps.copy()
    changed[2] *= 2.0
    sample.deflated(changed, bits=16)
    assert len(calls) == 6
    coarse = principal.spans[:5] / 255 * np.array([2.0, 3.0, 4.0, 5.0, 6.0])  # steps both bit depths keep as they are
    sample.deflated(coarse, bits=16)
    assert len(calls) == 11
    sample.deflated(coarse, bits=8)
    assert len(calls) == 16
    assert sample.bytes(steps[:3], bits=16) == float(every[:3].sum()) * sample.scale + 3 * sample.per_image and len(calls) == 16


def test_a_kept_measurement_takes_the_pieces_it_holds_and_deflates_nothing_twice():
    """Measured again at the same steps, a whole sample keeps the same pieces without deflating; an
    image measured before without keeping its piece is not deflated again either: its bytes are
    remembered and its piece left to the field writer, which writes the same entry."""
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    steps = principal.spans[:4] / code_levels(16) * np.array([2.0, 5.0, 9.0, 30.0])
    sample = RateSample(principal, 4, whole=True)
    store = DeflatedCodes()
    early = sample.deflated(steps[:2], bits=16)  # images 0 and 1 measured, no pieces kept
    measured = []
    real = sample._measured
    sample._measured = lambda indices, *args, **kwargs: measured.append(indices.tolist()) or real(indices, *args, **kwargs)
    first = sample.deflated(steps, bits=16, keep=store)
    assert measured == [[2, 3]] and len(store) == 2 and np.array_equal(first[:2], early)
    pieces = dict(store._kept[0])
    assert np.array_equal(sample.deflated(steps, bits=16, keep=store), first) and measured[-1] == [] and store._kept[0] == pieces
    stack = quantised_stack(principal, steps, bits=16)
    stored = [stored_codes(code.transpose(2, 0, 1)) for code in stack.codes]
    assert list(pieces.values()) == [deflated_piece(image) for image in stored[2:]]
    np.testing.assert_array_equal(first, [len(deflated_piece(image)) for image in stored])


@settings(max_examples=60, deadline=None)
@given(indices=st.sets(st.integers(0, 60), min_size=1), size=st.integers(1, 7))
def test_index_runs_cover_every_index_once_in_runs_of_at_most_size(indices, size):
    from warp_highlights.residual.rate import _index_runs

    ordered = np.array(sorted(indices))
    runs = _index_runs(ordered, size)
    assert all(0 < run.stop - run.start <= size for run in runs)
    assert [i for run in runs for i in range(run.start, run.stop)] == ordered.tolist()


def test_runs_are_packed_into_groups_of_at_most_size_in_order():
    from warp_highlights.residual.rate import _index_runs, _packed

    runs = _index_runs(np.array([0, 8, 16, 17, 18, 19, 30, 40, 41]), 3)
    groups = _packed(runs, 3)
    assert all(sum(run.stop - run.start for run in group) <= 3 for group in groups)
    assert [run for group in groups for run in group] == runs
    assert groups[:2] == [[slice(0, 1), slice(8, 9)], [slice(16, 19)]]


@pytest.mark.parametrize("bits", [8, 16])
def test_pieces_written_past_the_zip_writer_make_the_file_it_would_write(bits, tmp_path, monkeypatch):
    """The codes' pieces go straight to the file, the entry's CRC summed from each image's (``io.crc``):
    the file is byte for byte the one the zip writer's own ``write`` makes, and its CRCs check."""
    from test_field import make_field

    import warp_highlights.io.fieldfile as fieldfile

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    stack = quantised_stack(principal, principal.spans / code_levels(bits) * 3.0, bits=bits)
    known = []
    real_known = fieldfile._known_entry
    monkeypatch.setattr(fieldfile, "_known_entry", lambda entry: known.append(real_known(entry)) or known[-1])
    _codes_entry(field, stack, tmp_path / "direct.whf")
    assert known == [True]  # this Python's zip writer is the one the direct path knows
    monkeypatch.setattr(fieldfile, "_known_entry", lambda entry: False)
    _codes_entry(field, stack, tmp_path / "written.whf")
    assert (tmp_path / "direct.whf").read_bytes() == (tmp_path / "written.whf").read_bytes()
    with zipfile.ZipFile(tmp_path / "direct.whf") as archive:
        assert archive.testzip() is None
    np.testing.assert_array_equal(load_field(tmp_path / "direct.whf").residual.luminance.codes, stack.codes)
