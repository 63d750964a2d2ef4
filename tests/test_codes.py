"""How the field file stores basis codes (``io.codes``): zigzag row differences in byte planes, a
Blosc chunk per image; the rate search counts the bytes the file holds."""

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
    CompressedCodes,
    chunk_size,
    codes_from_differences,
    codes_from_stored,
    compressed_chunk,
    stored_bytes,
    stored_codes,
    stored_shape,
)
from warp_highlights.io.fieldfile import load_field, save_field
from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import ResidualModel, code_levels
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import quantised_stack
from warp_highlights.residual.rate import RateSample, component_bytes

RNG = np.random.default_rng(14)


def _reference_differences(codes: np.ndarray, *, zigzag: bool) -> np.ndarray:
    """The stored form in plain integer arithmetic: (P, R, W) codes -> row differences mod 2^bits, read
    as signed and zigzag-mapped where asked (format 5; format 4 without), then byte planes."""
    bits = 8 * codes.dtype.itemsize
    values = codes.astype(np.int64)
    above = np.concatenate([np.zeros_like(values[..., :1, :]), values[..., :-1, :]], axis=-2)
    difference = (values - above) % (1 << bits)
    if zigzag:
        signed = np.where(difference >= 1 << (bits - 1), difference - (1 << bits), difference)
        difference = np.where(signed >= 0, 2 * signed, -2 * signed - 1)
    if bits == 8:
        return difference.astype(np.uint8)
    return np.stack([difference // 256, difference % 256], axis=-3).astype(np.uint8)


@settings(max_examples=60, deadline=None)
@given(bits=st.sampled_from([8, 16]), data=st.data())
def test_stored_codes_are_zigzag_row_differences_in_byte_planes_and_come_back_exactly(bits, data):
    kind = np.uint8 if bits == 8 else np.uint16
    shape = data.draw(st.tuples(st.integers(0, 3), st.integers(1, 2), st.integers(1, 9), st.integers(1, 7)))
    # extremes included: differences wrap
    codes = data.draw(hnp.arrays(kind, shape, elements=st.integers(0, code_levels(bits))))
    stored = stored_codes(codes)
    assert stored.dtype == np.uint8 and stored.shape == stored_shape(*shape, bits)
    np.testing.assert_array_equal(stored, _reference_differences(codes, zigzag=True).reshape(stored.shape))
    back = codes_from_stored(stored, bits)
    assert back.dtype == kind
    np.testing.assert_array_equal(back, codes)


@pytest.mark.parametrize("bits", [8, 16])
def test_format_4_differences_come_back_exactly(bits):
    """``codes_from_differences`` reads version 4's layout: row differences mod 2^bits, no zigzag."""
    kind = np.uint8 if bits == 8 else np.uint16
    codes = RNG.integers(0, code_levels(bits) + 1, size=(3, 2, 17, 5)).astype(kind)
    stored = np.stack([_reference_differences(image, zigzag=False) for image in codes])
    assert stored.shape == stored_shape(3, 2, 17, 5, bits)
    np.testing.assert_array_equal(codes_from_differences(stored, bits), codes)


def test_small_differences_of_either_sign_leave_the_high_plane_zero():
    """The point of the zigzag: a difference of -1 is 1, not 0xFFFF, so the high byte plane of smooth
    16-bit codes is all zeros and the low plane holds each difference's sign with its size."""
    codes = np.array([[[1000, 1000], [999, 1001], [1000, 1000], [1127, 873]]], np.uint16)
    stored = stored_codes(codes)
    np.testing.assert_array_equal(stored[0, 0, 1:], 0)
    np.testing.assert_array_equal(stored[0, 1, 1:], [[1, 2], [2, 1], [254, 253]])


@pytest.mark.parametrize("kind", [np.uint8, np.uint16])
def test_a_band_of_rows_with_the_row_above_it_is_stored_as_the_whole_image_stores_it(kind):
    """What the rate search samples: a band taken with the row above it, its first stored row dropped."""
    codes = RNG.integers(0, np.iinfo(kind).max + 1, size=(2, 30, 11)).astype(kind)
    whole = stored_codes(codes)
    band = stored_codes(codes[:, 11:20])[..., 1:, :]
    np.testing.assert_array_equal(band, whole[..., 12:20, :])
    assert chunk_size(band) == chunk_size(whole[..., 12:20, :])


def _run_length_v4(codes: np.ndarray) -> int:
    """Format 4's bytes for (P, H, W) codes: row differences without the zigzag, raw deflate run-length only."""
    compressor = zlib.compressobj(6, zlib.DEFLATED, -15, 8, zlib.Z_RLE)
    data = _reference_differences(codes, zigzag=False).tobytes()
    return len(compressor.compress(data) + compressor.flush(zlib.Z_SYNC_FLUSH))


def test_smooth_16_bit_codes_store_smaller_than_as_they_are_and_than_format_4():
    """The point of the layout: a smooth basis image with a little noise (what the residual's basis
    images look like: a few codes from row to row) takes fewer bytes than its codes deflated as they
    are at zlib's default level (format 3) and than format 4's run-length deflate of its row
    differences (where rows differ by hundreds of codes, the two layouts are within 5%)."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:200, 0:300] / 200.0
    image = np.sin(5 * xx + 2 * yy) * np.exp(-((xx - 0.7) ** 2 + (yy - 0.5) ** 2) * 3)
    image = (image - image.min()) / (image.max() - image.min()) + 2e-3 * rng.normal(size=xx.shape)
    codes = np.round(np.clip(image, 0.0, None) * 1000).astype(np.uint16)[None]
    assert stored_bytes(codes) < 0.6 * len(zlib.compress(codes.tobytes(), 6))
    assert stored_bytes(codes) < 0.9 * _run_length_v4(codes)


def test_a_chunk_is_one_blosc_chunk_of_the_stored_bytes_made_alike_on_any_thread():
    from numcodecs import Blosc

    from warp_highlights.model.threads import parallel_map

    stored = stored_codes(RNG.integers(0, 40, size=(2, 13, 9)).astype(np.uint16))
    chunk = compressed_chunk(stored)
    assert bytes(Blosc().decode(chunk)) == stored.tobytes()
    assert chunk_size(stored) == len(chunk) and stored_bytes(codes_from_stored(stored[None], 16)[0]) == len(chunk)
    large = stored_codes(RNG.integers(0, 9, size=(1, 700, 900)).astype(np.uint16))  # several blocks
    # the main thread's (Blosc's threads) and the workers'
    assert set(parallel_map(compressed_chunk, [large] * 4)) == {compressed_chunk(large)}


def _smooth_stack(n: int, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 3 * xx + i) * np.cos((i % 5 + 1) * 2 * yy) for i in range(8)])
    stack = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 8)) * 0.8 ** np.arange(8), patterns)[..., None] + 1.0
    return stack + 1e-3 * RNG.normal(size=stack.shape)


@pytest.mark.parametrize("bits", [8, 16])
def test_the_sampled_bytes_are_the_whole_images_stored_bytes_at_the_sampled_rows(bits):
    """A sampled ``RateSample`` compresses each band of rows as the file stores those rows (the first
    row of a band less the row above it, not as it is)."""
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    sample = RateSample(principal, 3)
    assert not sample.exact
    steps = principal.spans[:3] / code_levels(bits) * 7.0
    counted = sample.rows[sample.counted]
    stack = quantised_stack(principal, steps, bits=bits)
    expected = sum(chunk_size(stored_codes(code.transpose(2, 0, 1))[..., counted, :]) for code in stack.codes)
    assert (sample.bytes(steps, bits=bits)
            == pytest.approx(expected * 320 / len(counted) + sample.per_image * 3, rel=1e-12))
    assert RateSample(principal, 3, whole=True).bytes(steps, bits=bits) == float(component_bytes(stack).sum())


def _decoded(raw: bytes, lengths) -> bytes:
    """The chunks of a chunked entry decoded one after another."""
    from numcodecs import Blosc

    ends = np.cumsum(lengths)
    return b"".join(bytes(Blosc().decode(raw[end - length : end])) for end, length in zip(ends, lengths))


def _codes_entry(field, stack, path):
    """(ZipInfo, raw bytes, chunk lengths, the stored array the entry's ``.npy`` holds) of the luminance
    codes entry of ``field`` with ``stack`` as its residual, written to ``path``."""
    field = dataclasses.replace(field, residual=ResidualModel(luminance=stack))
    save_field(field, path)
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None  # every entry's CRC holds
        info = archive.getinfo("residual/Y_codes.npy.blosc")
        raw = archive.read(info)
        lengths = np.load(io.BytesIO(archive.read("residual/Y_codes.lengths.npy")))
        assert "residual/Y_codes.npy" not in archive.namelist()
    return info, raw, lengths, np.load(io.BytesIO(_decoded(raw, lengths)))


@pytest.mark.parametrize(("bits", "size", "rank"),
                         [(8, None, None), (16, None, None), (16, (23, 7), None), (8, (9, 31), None), (16, None, 0)])
def test_the_file_holds_the_stored_codes_in_the_bytes_the_budget_counted(bits, size, rank, tmp_path):
    """The codes entry is stored as it is (no zip compression): the chunk of the ``.npy`` header of the
    stored array, then each image's chunk, their lengths in ``Y_codes.lengths.npy``. Its size is the
    header's chunk plus what ``component_bytes`` counts; decoded, it is the ``.npy`` file; the field
    loads the same codes back (odd sizes, and a stack of no basis image too)."""
    from test_field import make_field

    field = make_field() if size is None else make_field(size=size)
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    steps = principal.spans / code_levels(bits) * 3.0
    stack = quantised_stack(principal, steps[:rank], bits=bits)
    info, raw, lengths, stored = _codes_entry(field, stack, tmp_path / "f.whf")
    assert info.compress_type == zipfile.ZIP_STORED and info.file_size == info.compress_size == len(raw)
    assert stored.shape == stored_shape(stack.rank, 1, field.height, field.width, bits)
    np.testing.assert_array_equal(stored, stored_codes(stack.codes.transpose(0, 3, 1, 2)))
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": stored.shape})
    chunks = [compressed_chunk(header.getvalue())] + [compressed_chunk(image) for image in stored]
    assert raw == b"".join(chunks) and lengths.tolist() == [len(chunk) for chunk in chunks]
    counted = float(component_bytes(stack).sum()) - stack.rank * (8 + 4 * len(stack.weights))
    assert info.compress_size == len(chunks[0]) + counted
    loaded = load_field(tmp_path / "f.whf").residual.luminance
    np.testing.assert_array_equal(loaded.codes, stack.codes)
    assert loaded.codes.dtype == stack.codes.dtype


def test_damaged_or_cut_codes_give_the_corrupt_file_error(tmp_path):
    """Bytes flipped inside the codes entry, or the file cut inside it: one line naming the file."""
    from test_field import make_field

    field = make_field(size=(40, 30))
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    stack = quantised_stack(principal, principal.spans[:4] / code_levels(16) * 2.0, bits=16)
    path = tmp_path / "f.whf"
    info, raw, _, _ = _codes_entry(field, stack, path)
    data = path.read_bytes()
    start = info.header_offset + 30 + len(info.filename)  # the entry's data after its local header
    for position in np.linspace(start, start + len(raw) - 1, 12).astype(int):
        damaged = bytearray(data)
        damaged[position] ^= 0x5A
        path.write_bytes(bytes(damaged))
        with pytest.raises(InputError, match="corrupt field file") as error:
            load_field(path)
        assert str(path) in str(error.value) and "\n" not in str(error.value)
    for cut in (start + 5, start + len(raw) // 2, start + len(raw) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(InputError, match="truncated or corrupt"):
            load_field(path)


def test_a_codes_entry_with_data_after_its_chunks_or_wrong_lengths_is_corrupt(tmp_path):
    from test_field import make_field

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    stack = quantised_stack(principal, principal.spans[:2] / 255.0, bits=8)
    path = tmp_path / "f.whf"
    _codes_entry(field, stack, path)
    with zipfile.ZipFile(path) as archive:
        entries = {info: archive.read(info) for info in archive.infolist()}
    extended = tmp_path / "extended.whf"
    with zipfile.ZipFile(extended, "w") as archive:
        for info, data in entries.items():
            if info.filename.endswith("codes.npy.blosc"):
                data += compressed_chunk(b"more")
            elif info.filename.endswith("codes.lengths.npy"):
                lengths = np.load(io.BytesIO(data))
                buffer = io.BytesIO()
                np.save(buffer, np.append(lengths, len(compressed_chunk(b"more"))))
                data = buffer.getvalue()
            archive.writestr(info, data)
    with pytest.raises(InputError, match="has data after its array"):
        load_field(extended)
    with zipfile.ZipFile(path) as archive, zipfile.ZipFile(tmp_path / "lengths.whf", "w") as copy:
        for info in archive.infolist():  # lengths that do not add up to the entry
            data = archive.read(info)
            if info.filename.endswith("codes.lengths.npy"):
                buffer = io.BytesIO()
                np.save(buffer, np.load(io.BytesIO(data)) + 1)
                data = buffer.getvalue()
            copy.writestr(info, data)
    with pytest.raises(InputError, match="does not give the chunks"):
        load_field(tmp_path / "lengths.whf")


@pytest.mark.parametrize("whole", [False, True])
def test_the_rate_search_keeps_the_chunks_the_file_then_stores(whole, tmp_path, monkeypatch):
    """``allocate``'s last measurement on every row keeps each image's chunk (the small image here is
    measured whole; the larger one in samples, then on every row); the writer stores those chunks
    without compressing the images again, and the file is the one written without them."""
    import warp_highlights.io.codes as codes_module
    from test_field import make_field
    from warp_highlights.residual.rate import StackPlan, allocate

    field = make_field() if whole else make_field(size=(160, 240))
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    assert RateSample(principal, 1).exact == whole
    plan = StackPlan(principal, 1.0, principal.count - 1)
    budget = 0.5 * float(component_bytes(quantised_stack(principal, principal.spans / code_levels(16), bits=16)).sum())
    _, (steps,) = allocate([plan], budget, bits=16)
    assert len(plan.chunks) == len(steps) > 0
    kept = quantised_stack(principal, steps, bits=16, chunks=plan.chunks)
    plain = quantised_stack(principal, steps, bits=16)
    assert plain.chunks is None
    for name in ("codes", "ranges", "weights", "mean_weights"):  # the chunks change nothing of the model
        np.testing.assert_array_equal(getattr(kept, name), getattr(plain, name))
    compressed = []
    real = codes_module.compressed_chunk
    monkeypatch.setattr(codes_module, "compressed_chunk", lambda data: compressed.append(len(data)) or real(data))
    kept_info, _, _, _ = _codes_entry(field, kept, tmp_path / "kept.whf")
    assert compressed == []  # every image's chunk was found
    _codes_entry(field, plain, tmp_path / "plain.whf")
    assert len(compressed) == len(steps)  # without them, each image compressed here
    assert (tmp_path / "kept.whf").read_bytes() == (tmp_path / "plain.whf").read_bytes()
    # what the budget held to is what the entry holds: the measured chunks and the header's
    measured = float(component_bytes(kept).sum()) - kept.rank * (8 + 4 * len(kept.weights))
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False,
                                                  "shape": stored_shape(kept.rank, 1, field.height, field.width, 16)})
    assert kept_info.compress_size == measured + len(real(header.getvalue()))


def test_chunks_kept_for_other_codes_are_not_used(tmp_path):
    """Chunks are found by content: a stack whose kept chunks are another quantisation's writes its own."""
    from test_field import make_field

    field = make_field()
    principal = PrincipalImages.of(_smooth_stack(field.light_count, field.height, field.width))
    coarse, fine = (principal.spans / code_levels(16) * factor for factor in (40.0, 2.0))
    store = CompressedCodes()
    RateSample(principal, len(coarse), whole=True).bytes(coarse, bits=16, keep=store)
    stale = quantised_stack(principal, fine, bits=16, chunks=store)
    fresh = quantised_stack(principal, fine, bits=16)
    _codes_entry(field, stale, tmp_path / "stale.whf")
    _codes_entry(field, fresh, tmp_path / "fresh.whf")
    assert (tmp_path / "stale.whf").read_bytes() == (tmp_path / "fresh.whf").read_bytes()
    np.testing.assert_array_equal(load_field(tmp_path / "stale.whf").residual.luminance.codes, fresh.codes)


def test_only_a_sample_of_every_row_keeps_chunks():
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    with pytest.raises(ValueError, match="every row"):
        RateSample(principal, 3).bytes(principal.spans[:3] / 255, bits=8, keep=CompressedCodes())


def test_the_latest_two_measurements_are_kept():
    """A search's answer is its last measurement or the one before: chunks of both are found, older
    ones are compressed again (and are the same bytes)."""
    rng = np.random.default_rng(8)
    images = [rng.integers(0, 4, size=(2, 9, 11), dtype=np.uint8) for _ in range(3)]
    store = CompressedCodes()
    for image in images:
        store.keep({CompressedCodes.key(image): b"kept"})
    assert len(store) == 1
    assert store.chunk(images[2]) == b"kept" and store.chunk(images[1]) == b"kept"
    assert store.chunk(images[0]) == compressed_chunk(images[0])  # dropped: compressed now


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
def test_a_rate_sample_compresses_each_image_once_per_step(monkeypatch, whole):
    """``RateSample.chunk_bytes``: each image's bytes at the sample's rows (a subset measures only its
    images, the same bytes, the others 0); an image measured before at the same step and bits is not
    compressed again, another step or bit depth is."""
    import warp_highlights.residual.rate as residual_module

    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    steps = principal.spans[:5] / code_levels(16) * np.array([2.0, 5.0, 9.0, 30.0, 4.0])
    calls = []
    real = residual_module.compressed_chunk
    monkeypatch.setattr(residual_module, "compressed_chunk", lambda data: calls.append(1) or real(data))
    sample = RateSample(principal, 5, whole=whole)
    assert sample.exact == whole
    subset = sample.chunk_bytes(steps, bits=16, images=np.array([3, 1, 3]))
    assert len(calls) == 2 and not subset[[0, 2, 4]].any() and subset[[1, 3]].all()
    every = sample.chunk_bytes(steps, bits=16)
    assert len(calls) == 5
    np.testing.assert_array_equal(every[[1, 3]], subset[[1, 3]])
    stack = quantised_stack(principal, steps, bits=16)
    counted = sample.rows[sample.counted] if not whole else np.arange(320)
    expected = [chunk_size(stored_codes(code.transpose(2, 0, 1))[..., counted, :]) for code in stack.codes]
    np.testing.assert_array_equal(every, expected)
    changed = steps.copy()
    changed[2] *= 2.0
    sample.chunk_bytes(changed, bits=16)
    assert len(calls) == 6
    coarse = principal.spans[:5] / 255 * np.array([2.0, 3.0, 4.0, 5.0, 6.0])  # steps both bit depths keep as they are
    sample.chunk_bytes(coarse, bits=16)
    assert len(calls) == 11
    sample.chunk_bytes(coarse, bits=8)
    assert len(calls) == 16
    assert (sample.bytes(steps[:3], bits=16) == float(every[:3].sum()) * sample.scale + 3 * sample.per_image
            and len(calls) == 16)


def test_a_kept_measurement_takes_the_chunks_it_holds_and_compresses_nothing_twice():
    """Measured again at the same steps, a whole sample keeps the same chunks without compressing; an
    image measured before without keeping its chunk is not compressed again either: its bytes are
    remembered and its chunk left to the field writer, which writes the same entry."""
    principal = PrincipalImages.of(_smooth_stack(12, 320, 200))
    steps = principal.spans[:4] / code_levels(16) * np.array([2.0, 5.0, 9.0, 30.0])
    sample = RateSample(principal, 4, whole=True)
    store = CompressedCodes()
    early = sample.chunk_bytes(steps[:2], bits=16)  # images 0 and 1 measured, no chunks kept
    measured = []
    real = sample._measured
    sample._measured = (lambda indices, *args, **kwargs: measured.append(indices.tolist())
                        or real(indices, *args, **kwargs))
    first = sample.chunk_bytes(steps, bits=16, keep=store)
    assert measured == [[2, 3]] and len(store) == 2 and np.array_equal(first[:2], early)
    chunks = dict(store._kept[0])
    assert (np.array_equal(sample.chunk_bytes(steps, bits=16, keep=store), first) and measured[-1] == []
            and store._kept[0] == chunks)
    stack = quantised_stack(principal, steps, bits=16)
    stored = [stored_codes(code.transpose(2, 0, 1)) for code in stack.codes]
    assert list(chunks.values()) == [compressed_chunk(image) for image in stored[2:]]
    np.testing.assert_array_equal(first, [len(compressed_chunk(image)) for image in stored])


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
