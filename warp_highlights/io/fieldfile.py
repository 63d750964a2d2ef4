"""The highlight field's file: ``save_field``, ``load_field``; the one place that knows its layout. It holds
one thing, the file format (every version's reader and the current writer), so it stays one module.

The model it stores is :class:`warp_highlights.model.field.HighlightField` (``docs/file-format.md``).

File format (version 9; any file name, ``.whf`` suggested): a zip archive written through
``zipfile``'s documented API, atomically (temporary file in the same folder, fsync, rename). Its first
entry is ``header.json``; every other entry is a standard little-endian ``.npy`` array: deflated by the
zip (``numpy.load`` can open those), or, for the basis codes and arrays of 64 KiB or more, the
``.npy`` file in Blosc chunks (``numcodecs.Blosc``), stored as they are in ``X.npy.blosc``, with each
chunk's bytes in ``X.lengths.npy``: the chunks decoded one after another are the ``.npy`` file. The
table names each array ``X.npy`` whichever way it is stored.

==============================  ===============  =================================================
entry                           dtype, shape     contents
==============================  ===============  =================================================
``header.json``                 UTF-8 JSON       magic ``"warp-highlights field"``, format version,
                                                 library version, counts, image size, dome flag,
                                                 diffuse layout, light file names, settings, report
``lights/directions.npy``       <f8 (n, 3)       unit light directions (exact)
``triangulation/faces.npy``     <i4 (F, 3)       faces, wound outwards
``gaussians/estimated_counts``  <u2 (n,)         active Gaussians per light
``gaussians/estimated_slots``   <u2 (K,)         slot of each active Gaussian, light-major, increasing
``gaussians/estimated.npy``     <f4 (K, 6)       a, mu_x, mu_y, sigma_x, sigma_y, theta per Gaussian
``gaussians/retargeted.npy``    <f4 (K_r, 6)     the same for the retargeted sets, edge-major; the
                                                 slots of edge (i, j) are those of light i
``paths/delta.npy``             <f4 (K_r,)       signed rotation per retargeted Gaussian (radians)
``paths/centre.npy``            <f4 (K_r, 2)     rotation centre (image heights)
``diffuse/lambert.npy``         <f2 (C, 4, H, W) optional: nbar_x, nbar_y, nbar_z, k_a planes per
                                or <f4           channel (float16 by default, see ``save_field``)
``diffuse/images.npy``          <f2 (n, C, H, W) optional: diffuse image of every light
``gaussians/moving.npy``        <u1 (K,)         version 2, optional: 1 where an estimated Gaussian
                                                 moves, 0 where it blends in place
``residual/images.npy``         <f2 (n, C, H, W) version 2, optional: uncompressed residual images
``residual/Y_mean.npy``         <f2 or <f4       low-rank residual: mean plane(s) of the luminance
                                (P, H, W)        (P = 1) and ``C_`` chroma (P = 2) stacks
``residual/Y_codes.npy.blosc``  <u1              version 5: the 8- or 16-bit basis images of that
                                (k, P, H, W) or  stack as ``io.codes`` stores them: each row less the
                                (k, P, 2, H, W)  row above (the first as it is), modulo 2^bits, zigzag-
                                                 mapped; 16-bit values as high and low byte planes;
                                                 a Blosc chunk for the ``.npy`` header, then one
                                                 per basis image (``io.codes``; their lengths in
                                                 ``Y_codes.lengths.npy``). Version 4: ``Y_codes.npy``, the
                                                 differences without the zigzag, deflated. Versions
                                                 2 and 3: the codes themselves, <u1 or <u2
                                                 (k, P, H, W)
``residual/Y_ranges.npy``       <f4 (k, 2)       (low, high) of each basis image
``residual/Y_weights.npy``      <f4 (n, k)       per-light weights
``residual/Y_mean_weights.npy`` <f4 (n,)         per-light weight of the mean plane(s)
``residual/colour.npy``         <u1 (C, H, W)    optional: highlight colour c(x), code x COLOUR_STEP
``residual/scale.npy``          <f2 (H, W)       optional: per-pixel scale s(x) of the low-rank stacks
``residual/learned_codes.npy``  <f2 (9, H, W)    version 3, optional: a learned residual's per-pixel
                                                 codes (header ``residual.learned``: unit, lights)
``residual/learned_w0.npy``,    <f4              its MLP's weights and biases, one pair per layer
``..._b0``, ... ``..._b3``                       (``model.residual.decoder_layer_shapes`` of the
                                                 header's ``residual.learned.hidden``: version 6;
                                                 before, the fitted decoder's ``NEURAL_HIDDEN``;
                                                 w0 two columns wider where ``highlights``)
``residual/learned_bounds.npy`` <f2 (2, 3, H, W) version 7, where ``residual.learned.bounds`` is true:
                                                 the lowest and highest value of the relit residual
                                                 per pixel and channel (``learned_bounds``)
==============================  ===============  =================================================

(The ``gaussians/`` count and slot entries end in ``.npy`` too.) The diffuse arrays are stored as
planes (channel-first), which compresses smooth images several times better than the interleaved
in-memory layout. Only active Gaussians are stored.
The directed edges are not stored: they are ``triangulation.directed_edges()``. Weights are not stored:
a fitted set has weight 1 everywhere. Free slots are not stored: they read back as zeros (weight 1), and
the constructor clears them in the same way, so a saved and loaded field equals the original exactly
(except the Lambertian diffuse model, which is stored as float16 unless ``lambert_half=False``).

Version 1 (before residual transfer) has no ``gaussians/moving`` and no ``residual/`` entries; it
loads with every Gaussian moving and no residual (relighting then uses its diffuse model).

Version 2 files have no learned residual; they load unchanged.

Version 3 files store the basis codes as they are (see ``residual/Y_codes.npy.blosc``); they load unchanged.

Version 4 files store the basis codes' row differences without the zigzag in a deflated
``residual/Y_codes.npy`` (``io.codes.codes_from_differences`` reads them), and every array as a
deflated ``.npy`` entry; they load unchanged.

Version 5 files have no ``residual.learned.hidden``: their decoder is the fitted one (``NEURAL_HIDDEN``, eight
arrays); they load unchanged.

Version 6 files have no ``residual/learned_bounds``: their learned residual relights unbounded, as it did.

Version 7 files have no header entry ``residual.rbf_sigma`` (version 8: null, or the radial basis width with
which a low-rank residual's lights are weighed, ``ResidualModel.rbf_sigma``): they relight with the triangle's
weights, as they did.

Version 8 files have no header entry ``residual.learned.highlights`` (version 9: true where the decoder also takes
the Gaussians' luminance at the pixel, ``model.residual.highlight_inputs``: its w0 has two more columns, and its
values are the whole image): their decoder takes the code and the direction, as it did.

A new format version: raise ``FORMAT_VERSION``, write the new layout, and keep reading every older
version in ``_build_field`` (``load_field`` refuses files newer than ``FORMAT_VERSION``).
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
import zlib
from collections import deque
from pathlib import Path

import numpy as np

from .. import __version__
from ..model.config import RESIDUAL_BOOLEANS
from ..model.errors import InputError
from ..model.field import MAX_CAPACITY, DiffuseModel, HighlightField
from ..model.gaussians import GaussianParams
from ..model.lights import LightSet
from ..model.residual import (
    NEURAL_CODE_SIZE,
    NEURAL_HIDDEN,
    NEURAL_MAX_HIDDEN,
    LowRankStack,
    NeuralResidual,
    ResidualModel,
    colour_codes,
    colour_from_codes,
    decoder_layer_shapes,
)
from ..model.threads import NUMPY_THREADS, cancel_and_wait, submit
from ..model.triangulation import SphericalTriangulation
from .atomic import atomic_file, describe_os_error
from .codes import (
    CompressedCodes,
    codes_codec,
    codes_from_differences,
    codes_from_stored,
    compressed_chunk,
    stored_codes,
    stored_shape,
)

__all__ = ["FORMAT_VERSION", "MAGIC", "array_entry_bytes", "field_size_report", "load_field", "save_field"]

MAGIC = "warp-highlights field"
"""The ``magic`` string in every field file's header."""

FORMAT_VERSION = 9
"""Version of the file format that ``save_field`` writes; ``load_field`` reads this and older versions."""

_CHUNKED_BYTES = 1 << 16
"""Arrays of at least this many bytes (64 KiB: the residual's mean, scale and colour planes of a 320x320
field and larger, the weights and Gaussians of a few hundred lights) are stored in Blosc chunks made in
threads before the writer reaches them; smaller ones deflated by the zip (the time a zip entry's
deflate takes on the writer's thread, serially, was most of a dome field's save)."""
_CHUNK_BYTES = 1 << 22  # such an array is cut into chunks of about this many bytes (4 MiB), a thread compressing each
_ARRAY_LEVEL = 1
"""Zstandard level inside those chunks, after Blosc's byte shuffle: on float16 diffuse images, fewer bytes than
zlib's level 6 in a fraction of its time; higher levels save a few percent more in several times the time
(``benchmarks/bench_codes.py``)."""
_CHUNKED = ".blosc"
"""What a chunked ``.npy`` entry's name adds to the array's name (``X.npy.blosc``, its chunks' lengths in
``X.lengths.npy``)."""

_HEADER = "header.json"
_DIRECTIONS = "lights/directions.npy"
_FACES = "triangulation/faces.npy"
_ESTIMATED_COUNTS = "gaussians/estimated_counts.npy"
_ESTIMATED_SLOTS = "gaussians/estimated_slots.npy"
_ESTIMATED = "gaussians/estimated.npy"
_RETARGETED = "gaussians/retargeted.npy"
_PATH_DELTA = "paths/delta.npy"
_PATH_CENTRE = "paths/centre.npy"
_LAMBERT = "diffuse/lambert.npy"
_IMAGES = "diffuse/images.npy"
_MOVING = "gaussians/moving.npy"
_RESIDUAL_IMAGES = "residual/images.npy"
_RESIDUAL_COLOUR = "residual/colour.npy"
_RESIDUAL_SCALE = "residual/scale.npy"
_LEARNED_CODES = "residual/learned_codes.npy"
_LEARNED_BOUNDS = "residual/learned_bounds.npy"


def _learned_weight_names(layers: int) -> tuple[str, ...]:
    """The entries of a learned residual's decoder of ``layers`` layers (hidden and output): w0, b0, ..."""
    return tuple(f"residual/learned_{kind}{layer}.npy" for layer in range(layers) for kind in ("w", "b"))


_STACK_PREFIX = {"luminance": "residual/Y_", "chroma": "residual/C_"}

_PARAMETER_COLUMNS = ("amplitude", "mean_x", "mean_y", "sigma_x", "sigma_y", "theta")
_PARTS = ("header", "lights", "triangulation", "gaussians", "paths", "diffuse", "residual")
_MAX_HEADER_BYTES = 64 * 2**20
_FLOAT16_MAX = float(np.finfo(np.float16).max)
_UNIT_TOLERANCE = 1e-6  # stored light directions must be unit vectors to this accuracy
_ZIP_LOCAL_HEADER = b"PK\x03\x04"
_ZIP_NAME_OFFSET = 30  # a zip local file header is 30 bytes, then the entry name
# entry dates are fixed, so that the same field always gives the same bytes
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def save_field(field: HighlightField, path, *, lambert_half: bool = True) -> int:
    """Write the field to one file, atomically; returns the bytes written.

    The file is first written to a hidden temporary file in the target's folder, flushed to disk,
    then renamed over ``path``; on any error (or Ctrl-C) the temporary file is removed and an
    existing file at ``path`` is left as it was. Missing parent folders are created.

    Args:
        field: The field to store.
        path: Target file (any name; ``.whf`` suggested).
        lambert_half: Store the Lambertian diffuse model as float16 (half the size; about 3
            significant digits, so it loads back rounded to float16). False stores it exactly.
            Values beyond the float16 range are always stored as float32.

    Raises:
        InputError: ``path`` is a folder, or the file cannot be written (permissions, disk full).
    """
    if not isinstance(field, HighlightField):
        raise InputError(f"save_field needs a HighlightField, got {type(field).__name__}")
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path} is a folder; give a file name such as field.whf")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path, checked=False, durable=True) as tmp, open(tmp, "xb") as stream:
            sizes = _write_archive(field, stream, lambert_half=lambert_half)
    except OSError as exc:
        raise InputError(describe_os_error(exc, path=path)) from None
    field.file_sizes, field.file_path = sizes, path
    return sizes["total"]


def load_field(path) -> HighlightField:
    """Read a field file written by ``save_field`` (this or any earlier format version).

    Raises:
        InputError: one line naming the file: missing or unreadable, not a field file, written by
            a newer version, truncated, or corrupt (failed checksum, missing entry, wrong dtype or
            shape, out-of-range index, non-finite value, inconsistent counts).
    """
    path = Path(path)
    if path.exists() and not path.is_dir() and not path.is_file():  # a FIFO or a device would block or never end
        raise InputError(
            f"{path} is not a regular file (a pipe or a device?); give a field file written by warp-highlights fit")
    try:
        stream = open(path, "rb")  # noqa: SIM115 (closed below; open errors reported apart from read errors)
    except FileNotFoundError:
        raise InputError(f"{path}: field file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path} is a folder, not a field file") from None
    except OSError as exc:
        raise InputError(
            f"{path}: cannot read the field file ({exc.strerror or exc})"
        ) from None
    with stream:
        try:
            field = _read_field(path, stream)
        except (InputError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001 (zipfile, zlib, numpy or json internals: damaged bytes)
            raise _corrupt(path, f"{type(exc).__name__}: {exc}") from None
    try:
        field.fit_settings()
    except InputError as error:
        raise _corrupt(path, f"stored settings: {error}") from None
    return field


def field_size_report(field: HighlightField) -> dict:
    """Bytes per part as stored (compressed): header, lights, triangulation, gaussians, paths,
    diffuse, container (zip headers and directory) and total.

    The sizes of the field's last ``save_field`` or ``load_field`` (``field.file_sizes``); for a field
    never saved or loaded, the sizes that ``save_field`` would write, measured without writing a file.
    """
    if field.file_sizes is None:
        return _write_archive(field, _CountingSink(), lambert_half=True)
    return dict(field.file_sizes)


def _header(field: HighlightField, diffuse_layout: dict | None, residual_layout: dict | None) -> dict:
    return {
        "magic": MAGIC,
        "format_version": FORMAT_VERSION,
        "library_version": __version__,
        "light_count": field.light_count,
        "is_dome": bool(field.triangulation.is_dome),
        "face_count": field.triangulation.face_count,
        "directed_edge_count": field.edge_count,
        "capacity": field.capacity,
        "width": field.width,
        "height": field.height,
        "estimated_gaussian_count": int(field.estimated.active.sum()),
        "retargeted_gaussian_count": int(field.retargeted.active.sum()),
        "parameter_columns": list(_PARAMETER_COLUMNS),
        "diffuse": diffuse_layout,
        "residual": residual_layout,
        "moving": field.moving is not None,
        "light_filenames": field.lights.filenames,
        "settings": field.settings,
        "report": field.report,
    }


def _write_archive(field: HighlightField, stream, *, lambert_half: bool) -> dict:
    """Write the zip archive to a binary stream; returns the size report."""
    # row-major order: light by light (edge by edge), slots increasing; load scatters the same way
    est_rows, est_slots = np.nonzero(field.estimated.active)
    ret_rows, ret_slots = np.nonzero(field.retargeted.active)
    arrays = [
        (_DIRECTIONS, field.lights.directions.astype("<f8")),
        (_FACES, field.triangulation.faces.astype("<i4")),
        (_ESTIMATED_COUNTS, field.counts.astype("<u2")),
        (_ESTIMATED_SLOTS, est_slots.astype("<u2")),
        (_ESTIMATED, _pack(field.estimated, est_rows, est_slots)),
        (_RETARGETED, _pack(field.retargeted, ret_rows, ret_slots)),
        (_PATH_DELTA, field.path_delta[ret_rows, ret_slots].astype("<f4")),
        (_PATH_CENTRE, field.path_centre[ret_rows, ret_slots].astype("<f4")),
    ]
    diffuse_layout = None
    if field.diffuse is not None:
        lambert = field.diffuse.lambert
        half = lambert_half and float(np.abs(lambert).max()) <= _FLOAT16_MAX
        diffuse_layout = {
            "channels": field.diffuse.channel_count,
            "lambert_dtype": "float16" if half else "float32",
            "images": field.diffuse.images is not None,
        }
        planes = lambert.transpose(2, 3, 0, 1).astype("<f2" if half else "<f4")
        arrays.append((_LAMBERT, planes))
        if field.diffuse.images is not None:
            images = field.diffuse.images.transpose(0, 3, 1, 2).astype("<f2")
            arrays.append((_IMAGES, images))
    if field.moving is not None:
        arrays.append((_MOVING, field.moving[est_rows, est_slots].astype("<u1")))
    residual_layout = None
    if field.residual is not None:
        residual_layout, residual_arrays = _residual_entries(field.residual)
        arrays.extend(residual_arrays)
    header = json.dumps(
        _header(field, diffuse_layout, residual_layout), indent=1, allow_nan=False
    ).encode("utf-8")
    entries = [(name, _chunked(array)) for name, array in arrays]
    chunked = [entry for _, entry in entries if isinstance(entry, _Ahead)]
    try:
        # each chunked entry's first chunks made in threads while the writer stores the entries before it
        for chunks in chunked:
            chunks.start(2)
        with zipfile.ZipFile(stream, "w") as archive:
            with archive.open(_entry_info(_HEADER), "w") as entry:
                entry.write(header)
            for name, entry in entries:
                if isinstance(entry, _Ahead):
                    _write_chunks(archive, name, entry)
                else:
                    _write_array(archive, name, entry)
            infos = archive.infolist()
    except BaseException:  # an error or Ctrl-C: nothing left compressing behind
        for chunks in chunked:
            chunks.cancel()
        raise
    return _size_report(infos, stream.tell())


# --- writing helpers -------------------------------------------------------------------------------


def _residual_entries(residual: ResidualModel) -> tuple[dict, list]:
    """The header layout and the (name, array) entries of a residual model, planes channel-first."""
    layout = {"channels": residual.channels, "compressed": residual.kind == "lowrank",
              "highlight_colour": residual.highlight_colour is not None,
              "scale": residual.scale is not None, "rbf_sigma": residual.rbf_sigma}
    arrays = []
    layout["learned"] = None
    if residual.learned is not None:
        learned = residual.learned
        layout["learned"] = {"unit": learned.unit, "lights": learned.light_count, "hidden": list(learned.hidden),
                             "bounds": learned.bounds is not None, "highlights": learned.sees_highlights}
        arrays.append((_LEARNED_CODES, learned.codes.transpose(2, 0, 1).astype("<f2")))
        if learned.bounds is not None:
            arrays.append((_LEARNED_BOUNDS, learned.bounds.transpose(0, 3, 1, 2).astype("<f2")))
        names = _learned_weight_names(len(learned.hidden) + 1)
        arrays += [(name, weight.astype("<f4")) for name, weight in zip(names, learned.weights)]
    if residual.images is not None:
        arrays.append((_RESIDUAL_IMAGES, residual.images.transpose(0, 3, 1, 2).astype("<f2")))
    for name in ("luminance", "chroma"):
        stack = getattr(residual, name)
        layout[name] = None
        if stack is None:
            continue
        half = bool(np.array_equal(stack.mean.astype(np.float16).astype(np.float32), stack.mean))
        layout[name] = {"rank": stack.rank, "mean_dtype": "float16" if half else "float32", "bits": stack.bits}
        prefix = _STACK_PREFIX[name]
        arrays += [
            (prefix + "mean.npy", stack.mean.transpose(2, 0, 1).astype("<f2" if half else "<f4")),
            (prefix + "codes.npy", stack),  # a Blosc chunk an image, as io.codes stores them (_CodeChunks)
            (prefix + "ranges.npy", stack.ranges.astype("<f4")),
            (prefix + "weights.npy", stack.weights.astype("<f4")),
            (prefix + "mean_weights.npy", stack.mean_weights.astype("<f4")),
        ]
    if residual.scale is not None:
        arrays.append((_RESIDUAL_SCALE, residual.scale.astype("<f2")))
    if residual.highlight_colour is not None:
        codes = colour_codes(residual.highlight_colour)
        arrays.append((_RESIDUAL_COLOUR, codes.transpose(2, 0, 1)))
    return layout, arrays


def _pack(params: GaussianParams, rows: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """(K, 6) little-endian float32 rows [a, mu_x, mu_y, sigma_x, sigma_y, theta] of the given slots."""
    columns = [
        params.amplitude[rows, slots],
        params.mean[rows, slots, 0],
        params.mean[rows, slots, 1],
        params.sigma[rows, slots, 0],
        params.sigma[rows, slots, 1],
        params.theta[rows, slots],
    ]
    return np.stack(columns, axis=1).astype("<f4")


def _entry_info(name: str, compress_type: int = zipfile.ZIP_DEFLATED) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
    info.compress_type = compress_type
    info.external_attr = 0o644 << 16
    return info


class _Ahead:
    """``function(i)`` for i in 0 .. ``count`` - 1, in order, made in threads at most ``2 NUMPY_THREADS``
    ahead of the one who iterates (``start`` submits the first ones early)."""

    def __init__(self, function, count: int):
        self.function, self.count = function, count
        self._next = 0
        self._pending: deque = deque()

    def start(self, ahead: int | None = None) -> None:
        """Submit what is next, up to ``ahead`` (default ``2 NUMPY_THREADS``) waiting."""
        ahead = 2 * max(1, NUMPY_THREADS) if ahead is None else ahead
        while len(self._pending) < ahead and self._next < self.count:
            self._pending.append(submit(self.function, self._next))
            self._next += 1

    def __iter__(self):
        self.start()
        while self._pending:
            result = self._pending[0].result()
            self._pending.popleft()
            self.start()
            yield result

    def cancel(self) -> None:
        """Drop what is not started, wait for what is running."""
        cancel_and_wait(list(self._pending))
        self._pending.clear()


class _CodeChunks(_Ahead):
    """A low-rank stack's (k, H, W, P) basis codes as ``io.codes`` stores them: the Blosc chunk of the
    ``.npy`` header of the stored (``stored_shape``) uint8 array, then each image's chunk, in order,
    taken from the stack's ``chunks`` (what the fit's rate search compressed,
    ``io.codes.CompressedCodes``) or compressed here, in threads."""

    def __init__(self, stack: LowRankStack):
        self.codes = stack.codes
        self.chunks = stack.chunks if stack.chunks is not None else CompressedCodes()
        rank, height, width, planes = self.codes.shape
        self.shape = stored_shape(rank, planes, height, width, 8 if self.codes.dtype == np.uint8 else 16)
        self.nbytes = math.prod(self.shape)
        super().__init__(self._chunk, 1 + rank)

    def _chunk(self, index: int) -> bytes:
        if index == 0:
            return compressed_chunk(_npy_header(np.uint8, self.shape))
        # Blosc (off the main thread) and hashlib let go of the GIL
        return self.chunks.chunk(stored_codes(self.codes[index - 1].transpose(2, 0, 1)))


class _ArrayChunks(_Ahead):
    """An array's ``.npy`` file in Blosc chunks (Zstandard at ``_ARRAY_LEVEL`` after Blosc's byte
    shuffle): its header, then parts of about ``_CHUNK_BYTES`` (whole rows, copied in C order from
    any strides), each compressed on a worker thread: there Blosc compresses on that thread alone, so
    a chunk is the same bytes each time (Blosc's own threads place its blocks in the order they finish)."""

    def __init__(self, array: np.ndarray):
        from numcodecs import Blosc  # the codec, imported where an array is written in chunks

        self.array = array
        self.nbytes = array.nbytes
        self.codec = Blosc(cname="zstd", clevel=_ARRAY_LEVEL, shuffle=Blosc.SHUFFLE)
        self.rows = max(1, _CHUNK_BYTES // max(1, array[:1].nbytes))
        super().__init__(self.chunk, 1 + -(-len(array) // self.rows))

    def chunk(self, index: int) -> bytes:
        """Chunk ``index``: 0 the ``.npy`` header, then the parts of ``rows`` rows."""
        if index == 0:
            return bytes(self.codec.encode(np.frombuffer(_npy_header(self.array.dtype, self.array.shape), np.uint8)))
        return bytes(self.codec.encode(np.ascontiguousarray(self.array[(index - 1) * self.rows : index * self.rows])))


def _chunked(array):
    """How an array is written: a stack's codes as ``_CodeChunks``, an array of ``_CHUNKED_BYTES`` or
    more (not 0-d) as ``_ArrayChunks``, any other as it is (deflated by the zip)."""
    if isinstance(array, LowRankStack):
        return _CodeChunks(array)
    array = np.asarray(array)
    if array.flags.f_contiguous and not array.flags.c_contiguous:
        array = np.ascontiguousarray(array)  # kept in C order
    return _ArrayChunks(array) if array.nbytes >= _CHUNKED_BYTES and array.ndim else array


def array_entry_bytes(array: np.ndarray) -> int:
    """Bytes ``save_field`` stores for ``array`` as one entry's data: its Blosc chunks and their lengths where it is
    chunked (``_CHUNKED_BYTES`` or more), else its ``.npy`` file deflated as the zip deflates it (zlib's default
    level). The zip's own records are not counted. Made on the calling thread (callable from a worker's)."""
    chunks = _chunked(array)
    if isinstance(chunks, _ArrayChunks):
        return sum(len(chunks.chunk(index)) for index in range(chunks.count)) + _DEFLATED_LENGTH_BYTES * chunks.count
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, chunks, allow_pickle=False)
    compressor = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, -15)
    return len(compressor.compress(buffer.getbuffer())) + len(compressor.flush())


_DEFLATED_LENGTH_BYTES = 8
"""A chunk's length in its array's ``.lengths.npy`` entry (<i8, before deflate: an upper bound)."""


def _npy_header(dtype: np.dtype, shape: tuple) -> bytes:
    """The ``.npy`` header (format 1.0) of a C-ordered array of ``dtype`` and ``shape``."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                  "fortran_order": False,
                                                  "shape": tuple(shape)})
    return buffer.getvalue()


def _write_array(archive: zipfile.ZipFile, name: str, array: np.ndarray) -> None:
    """One ``.npy`` entry the zip deflates (zip64 where it may pass the 2 GiB limit of plain zip)."""
    with archive.open(_entry_info(name), "w", force_zip64=array.nbytes > 2**30) as entry:
        # a strided view is written in buffered chunks, never copied whole
        np.lib.format.write_array(entry, array, allow_pickle=False)


def _write_chunks(archive: zipfile.ZipFile, name: str, chunks: _Ahead) -> None:
    """``name`` (``X.npy``) as ``X.npy.blosc``, the Blosc ``chunks`` one after another, stored as they are,
    and ``X.lengths.npy``, each chunk's bytes (<i8)."""
    lengths = []
    with archive.open(_entry_info(name + _CHUNKED, zipfile.ZIP_STORED), "w",
                      force_zip64=chunks.nbytes > 2**30) as entry:
        for chunk in chunks:
            entry.write(chunk)
            lengths.append(len(chunk))
    _write_array(archive, _lengths_name(name), np.array(lengths, "<i8"))


def _lengths_name(name: str) -> str:
    """The entry of a chunked array's chunk lengths: ``X.lengths.npy`` for ``X.npy``."""
    return name.removesuffix(".npy") + ".lengths.npy"


def _size_report(infos: list[zipfile.ZipInfo], total: int) -> dict:
    sizes = dict.fromkeys(_PARTS, 0)
    for info in infos:
        part = "header" if info.filename == _HEADER else info.filename.split("/")[0]
        if part in sizes:
            sizes[part] += info.compress_size
    sizes["container"] = total - sum(sizes.values())
    sizes["total"] = total
    return sizes


class _CountingSink:
    """A write-only, seekable stream that keeps only its size (to measure a file without writing it)."""

    def __init__(self):
        self._position = 0
        self._size = 0

    def write(self, data) -> int:
        length = memoryview(data).nbytes
        self._position += length
        self._size = max(self._size, self._position)
        return length

    def tell(self) -> int:
        return self._position

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self._position, 2: self._size}[whence]
        self._position = base + offset
        return self._position

    def seekable(self) -> bool:
        return True

    def flush(self) -> None:
        pass


# --- reading ---------------------------------------------------------------------------------------


def _corrupt(path: Path, what: str) -> InputError:
    return InputError(
        f"{path}: corrupt field file: {what}; write it again (or restore a copy)"
    )


def _not_a_field(path: Path, what: str) -> InputError:
    return InputError(f"{path}: not a warp-highlights field file ({what})")


def _sniff(head: bytes) -> str:
    """A few words on what a file that is not a zip archive looks like."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "a PNG image"
    if head.startswith(b"\xff\xd8\xff"):
        return "a JPEG image"
    if head.startswith(b"\x76\x2f\x31\x01"):
        return "an OpenEXR image"
    if head.startswith(b"\x93NUMPY"):
        return "a NumPy .npy array"
    if all(byte >= 0x20 or byte in b"\t\r\n" for byte in head):
        return "a text file"
    return "unrecognised binary content"


def _read_field(path: Path, stream) -> HighlightField:
    head = stream.read(64)
    if not head:
        raise InputError(f"{path}: empty file, not a warp-highlights field file")
    if not head.startswith(_ZIP_LOCAL_HEADER):
        raise _not_a_field(path, _sniff(head))
    # our files start with the local header of header.json; a cut may leave part of the name
    ours = _HEADER.encode().startswith(
        head[_ZIP_NAME_OFFSET : _ZIP_NAME_OFFSET + len(_HEADER)]
    )
    stream.seek(0)
    try:
        archive = zipfile.ZipFile(stream)
    except (
        zipfile.BadZipFile,
        EOFError,
        OSError,
        ValueError,
        NotImplementedError,
    ) as exc:
        if ours:
            raise InputError(
                f"{path}: truncated or corrupt field file (its zip directory cannot be read: {exc}); write it again"
            ) from None
        raise _not_a_field(path, f"a damaged zip archive: {exc}") from None
    with archive:
        names = set(archive.namelist())
        if _HEADER not in names:
            raise _not_a_field(path, f"a zip archive without {_HEADER}")
        header = _read_header(path, archive)
        return _build_field(path, archive, names, header, stream)


def _resolved_residual_kind(settings: dict, residual: ResidualModel | None) -> dict:
    """Settings stored before ``ResidualSettings.kind`` (its booleans ``RESIDUAL_BOOLEANS``): the kind the field
    holds in their place, as a fit now stores the kind it resolved."""
    group = settings.get("residual")
    if not isinstance(group, dict) or "kind" in group or not any(name in group for name in RESIDUAL_BOOLEANS):
        return settings
    kept = {name: value for name, value in group.items() if name not in RESIDUAL_BOOLEANS}
    return {**settings, "residual": {"kind": "none" if residual is None else residual.kind, **kept}}


def _read_header(path: Path, archive: zipfile.ZipFile) -> dict:
    info = archive.getinfo(_HEADER)
    if info.file_size > _MAX_HEADER_BYTES:
        raise _corrupt(path, f"{_HEADER} is {info.file_size} bytes")
    with archive.open(info) as entry:
        raw = entry.read(_MAX_HEADER_BYTES + 1)
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: absurdly deep nesting
        raise _corrupt(path, f"{_HEADER} is not valid JSON ({type(exc).__name__})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise _not_a_field(path, f"{_HEADER} lacks the magic string {MAGIC!r}")
    version = header.get("format_version")
    if not _is_int(version) or version < 1:
        raise _corrupt(
            path, f"format_version must be a positive integer, got {version!r}"
        )
    if version > FORMAT_VERSION:
        raise InputError(
            f"{path}: written by a newer warp-highlights (library {header.get('library_version')!s}, field format "
            f"{version}; this version {__version__} reads format {FORMAT_VERSION}); upgrade warp-highlights"
        )
    return header


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    """A finite JSON number (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _header_int(
    path: Path, header: dict, key: str, minimum: int, maximum: int | None = None
) -> int:
    value = header.get(key)
    if (
        not _is_int(value)
        or value < minimum
        or (maximum is not None and value > maximum)
    ):
        upper = "" if maximum is None else f"..{maximum}"
        raise _corrupt(
            path,
            f"header entry {key!r} must be an integer in {minimum}{upper or ' or more'}, got {value!r}",
        )
    return value


def _header_value(path: Path, header: dict, key: str, kinds: tuple, description: str):
    value = header.get(key)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        raise _corrupt(
            path, f"header entry {key!r} must be {description}, got {value!r}"
        )
    return value


def _read_array(
    path: Path,
    archive: zipfile.ZipFile,
    names: set,
    name: str,
    dtype: str,
    shape: tuple,
) -> np.ndarray:
    """Read one ``.npy`` entry (deflated by the zip, or in Blosc chunks: ``name`` + ``.blosc``),
    checking its dtype and shape before reading the data."""
    chunked = name not in names and name + _CHUNKED in names
    if name not in names and not chunked:
        raise _corrupt(path, f"entry {name} is missing")
    expected = np.dtype(dtype)
    with archive.open(name + _CHUNKED if chunked else name) as entry:
        reader = _Chunks(entry, _chunk_lengths(path, archive, names, name)) if chunked else entry
        try:
            version = np.lib.format.read_magic(reader)
            if version == (1, 0):
                stored_shape, fortran, stored_dtype = np.lib.format.read_array_header_1_0(reader)
            elif version == (2, 0):
                stored_shape, fortran, stored_dtype = np.lib.format.read_array_header_2_0(reader)
            else:
                raise ValueError(f"unsupported .npy version {version}")
        except ValueError as exc:
            raise _corrupt(path, f"entry {name} is not a valid .npy array ({exc})") from None
        if stored_dtype != expected:
            raise _corrupt(path, f"entry {name} holds {stored_dtype.str} data, expected {expected.str}")
        if fortran:
            raise _corrupt(path, f"entry {name} is stored in Fortran order")
        if tuple(stored_shape) != tuple(shape):
            raise _corrupt(path, f"entry {name} has shape {tuple(stored_shape)}, expected {tuple(shape)}")
        size = math.prod(shape) * expected.itemsize
        data = _read_exactly(reader, size)
        if len(data) != size:
            raise _corrupt(path, f"entry {name} is truncated")
        if reader.read(1) or entry.read(1):  # reading the zip entry to its end also completes its checksum test
            raise _corrupt(path, f"entry {name} has data after its array")
    array = np.frombuffer(data, dtype=expected).reshape(shape).astype(expected.newbyteorder("="))
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise _corrupt(path, f"entry {name} has non-finite values")
    return array


def _chunk_lengths(path: Path, archive: zipfile.ZipFile, names: set, name: str) -> np.ndarray:
    """The chunk lengths of the chunked ``.npy`` entry of ``name``: positive, summing to its stored bytes."""
    lengths_name = _lengths_name(name)
    if lengths_name not in names:
        raise _corrupt(path, f"entry {lengths_name} is missing")
    count = archive.getinfo(lengths_name).file_size  # a bound: 8 bytes a chunk and a header
    lengths = _read_array(path, archive, names, lengths_name, "<i8", (_npy_length(path, archive, lengths_name, count),))
    if lengths.size == 0 or lengths.min() <= 0 or int(lengths.sum()) != archive.getinfo(name + _CHUNKED).file_size:
        raise _corrupt(path, f"entry {lengths_name} does not give the chunks of {name + _CHUNKED}")
    return lengths


def _npy_length(path: Path, archive: zipfile.ZipFile, name: str, bound: int) -> int:
    """The length of the 1-d ``.npy`` entry ``name`` from its header (its data read by ``_read_array``)."""
    with archive.open(name) as entry:
        try:
            version = np.lib.format.read_magic(entry)
            header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape = header(entry)[0]
        except ValueError as exc:
            raise _corrupt(path, f"entry {name} is not a valid .npy array ({exc})") from None
    if len(shape) != 1 or not 0 <= shape[0] <= bound:
        raise _corrupt(path, f"entry {name} has shape {shape}, expected one length a chunk")
    return int(shape[0])


class _Chunks:
    """The bytes of a chunked entry's Blosc chunks decoded one after another (a readable stream). The
    entry is read whole first, so that its zip checksum is tested before any chunk is decoded."""

    def __init__(self, entry, lengths: np.ndarray):
        self.data = memoryview(entry.read())
        self.ends = np.cumsum(lengths)
        if len(self.data) != int(self.ends[-1]):
            raise zipfile.BadZipFile("the chunks' lengths do not add up to the entry")
        self.next = 0
        self.buffer = b""
        self.at = 0
        self.codec = codes_codec()  # any Blosc codec decodes any Blosc chunk: its header says how it was made

    def read(self, size: int = -1) -> bytes:
        parts = []
        while size != 0:
            if self.at == len(self.buffer):
                if self.next == len(self.ends):
                    break
                start = int(self.ends[self.next - 1]) if self.next else 0
                self.buffer, self.at = bytes(self.codec.decode(self.data[start : int(self.ends[self.next])])), 0
                self.next += 1
                continue
            take = len(self.buffer) - self.at if size < 0 else min(size, len(self.buffer) - self.at)
            parts.append(self.buffer[self.at : self.at + take])
            self.at += take
            size -= take if size > 0 else 0
        return b"".join(parts)

    def readinto(self, buffer) -> int:
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)


def _read_exactly(stream, size: int) -> bytearray:
    """``size`` bytes of ``stream`` (fewer where it ends first), read into one buffer."""
    data = bytearray(size)
    done = 0
    with memoryview(data) as view:
        while done < size:
            got = stream.readinto(view[done:])
            if not got:
                break
            done += got
    return data if done == size else data[:done]


def _build_field(
    path: Path, archive: zipfile.ZipFile, names: set, header: dict, stream
) -> HighlightField:
    n = _header_int(path, header, "light_count", 3)
    face_count = _header_int(path, header, "face_count", 1)
    edge_count = _header_int(path, header, "directed_edge_count", 2)
    capacity = _header_int(path, header, "capacity", 1, MAX_CAPACITY)
    width = _header_int(path, header, "width", 1)
    height = _header_int(path, header, "height", 1)
    estimated_total = _header_int(
        path, header, "estimated_gaussian_count", 0, n * capacity
    )
    retargeted_total = _header_int(
        path, header, "retargeted_gaussian_count", 0, edge_count * capacity
    )
    is_dome = _header_value(path, header, "is_dome", (bool,), "true or false")
    settings = _header_value(path, header, "settings", (dict,), "a JSON object")
    report = _header_value(path, header, "report", (dict,), "a JSON object")
    filenames = header.get("light_filenames")
    if filenames is not None and (
        not isinstance(filenames, list)
        or len(filenames) != n
        or not all(isinstance(f, str) for f in filenames)
    ):
        raise _corrupt(
            path, f"header entry 'light_filenames' must be null or {n} strings"
        )
    diffuse_layout = header.get("diffuse")
    if diffuse_layout is not None:
        if not isinstance(diffuse_layout, dict):
            raise _corrupt(path, "header entry 'diffuse' must be null or a JSON object")
        channels = _header_int(path, diffuse_layout, "channels", 1)
        lambert_dtype = diffuse_layout.get("lambert_dtype")
        if lambert_dtype not in ("float16", "float32"):
            raise _corrupt(
                path,
                f"diffuse lambert_dtype must be 'float16' or 'float32', got {lambert_dtype!r}",
            )
        with_images = _header_value(
            path, diffuse_layout, "images", (bool,), "true or false"
        )

    def read(name, dtype, shape):
        return _read_array(path, archive, names, name, dtype, shape)

    directions = read(_DIRECTIONS, "<f8", (n, 3))
    if np.any(np.abs(np.linalg.norm(directions, axis=1) - 1.0) > _UNIT_TOLERANCE):
        raise _corrupt(
            path, f"entry {_DIRECTIONS} holds vectors that are not unit length"
        )
    faces = read(_FACES, "<i4", (face_count, 3))
    if faces.min() < 0 or faces.max() >= n:
        raise _corrupt(path, f"entry {_FACES} has vertex indices outside 0..{n - 1}")
    try:
        lights = LightSet(directions, filenames)
        triangulation = SphericalTriangulation.from_faces(directions, faces)
    except InputError as exc:
        raise _corrupt(path, str(exc)) from None
    # keep the stored directions bit for bit (normalising a unit vector again may change its last bit)
    lights.directions = directions
    triangulation.directions = directions
    if triangulation.is_dome != is_dome:
        raise _corrupt(
            path,
            f"the header says is_dome={is_dome} but the faces say {triangulation.is_dome}",
        )
    directed = triangulation.directed_edges()
    if len(directed) != edge_count:
        raise _corrupt(
            path,
            f"the faces give {len(directed)} directed edges but the header says {edge_count}",
        )

    counts = read(_ESTIMATED_COUNTS, "<u2", (n,)).astype(np.int64)
    if counts.max() > capacity or counts.sum() != estimated_total:
        raise _corrupt(
            path,
            f"entry {_ESTIMATED_COUNTS} does not match the capacity and the Gaussian count",
        )
    slots = read(_ESTIMATED_SLOTS, "<u2", (estimated_total,)).astype(np.int64)
    owners = np.repeat(np.arange(n), counts)
    if estimated_total and (
        slots.max() >= capacity
        or np.any((slots[1:] <= slots[:-1]) & (owners[1:] == owners[:-1]))
    ):
        raise _corrupt(
            path,
            f"entry {_ESTIMATED_SLOTS} has slot indices out of range or out of order",
        )
    estimated_active = np.zeros((n, capacity), dtype=bool)
    estimated_active[owners, slots] = True
    retargeted_active = estimated_active[directed[:, 0]]
    if int(retargeted_active.sum()) != retargeted_total:
        raise _corrupt(
            path,
            "the retargeted Gaussian count in the header does not match the estimated slots",
        )

    estimated = _unpack(read(_ESTIMATED, "<f4", (estimated_total, 6)), estimated_active)
    retargeted = _unpack(
        read(_RETARGETED, "<f4", (retargeted_total, 6)), retargeted_active
    )
    rows, cols = np.nonzero(retargeted_active)
    path_delta = np.zeros((edge_count, capacity), dtype=np.float32)
    path_delta[rows, cols] = read(_PATH_DELTA, "<f4", (retargeted_total,))
    path_centre = np.zeros((edge_count, capacity, 2), dtype=np.float32)
    path_centre[rows, cols] = read(_PATH_CENTRE, "<f4", (retargeted_total, 2))

    diffuse = None
    if diffuse_layout is not None:
        lambert_code = "<f2" if lambert_dtype == "float16" else "<f4"
        planes = read(_LAMBERT, lambert_code, (channels, 4, height, width))
        lambert = planes.transpose(2, 3, 0, 1)
        images = None
        if with_images:
            images = read(_IMAGES, "<f2", (n, channels, height, width)).transpose(
                0, 2, 3, 1
            )
        try:
            diffuse = DiffuseModel(lambert, images)
        except InputError as exc:
            raise _corrupt(path, str(exc)) from None

    moving = None
    if header.get("moving", False) is not False:
        if header.get("moving") is not True:
            raise _corrupt(path, f"header entry 'moving' must be true or false, got {header.get('moving')!r}")
        flags = read(_MOVING, "<u1", (estimated_total,))
        if flags.size and flags.max() > 1:
            raise _corrupt(path, f"entry {_MOVING} must hold 0 or 1")
        moving = np.zeros((n, capacity), dtype=bool)
        moving[owners, slots] = flags.astype(bool)
    residual = None
    residual_layout = header.get("residual")
    if residual_layout is not None:
        residual = _read_residual(path, residual_layout, read, n, height, width, header["format_version"])

    settings = _resolved_residual_kind(settings, residual)
    try:
        field = HighlightField(
            lights=lights,
            triangulation=triangulation,
            width=width,
            height=height,
            estimated=estimated,
            directed_edges=directed,
            retargeted=retargeted,
            path_delta=path_delta,
            path_centre=path_centre,
            settings=settings,
            report=report,
            diffuse=diffuse,
            residual=residual,
            moving=moving,
        )
    except InputError as exc:
        raise _corrupt(path, str(exc)) from None
    stream.seek(0, os.SEEK_END)
    field.file_sizes = _size_report(archive.infolist(), stream.tell())
    field.file_path = path
    return field


def _read_residual(path: Path, layout, read, n: int, height: int, width: int, version: int) -> ResidualModel:
    """The residual model of a version-2 to -5 file, from its header layout and entries."""
    if not isinstance(layout, dict):
        raise _corrupt(path, "header entry 'residual' must be null or a JSON object")
    channels = _header_int(path, layout, "channels", 1, 3)
    compressed = _header_value(path, layout, "compressed", (bool,), "true or false")
    with_colour = _header_value(path, layout, "highlight_colour", (bool,), "true or false")
    images, stacks, learned = None, {}, None
    if layout.get("learned") is not None:
        part = layout["learned"]
        if (not isinstance(part, dict) or not isinstance(part.get("unit"), (int, float))
            or not math.isfinite(part["unit"]) or part["unit"] <= 0):
            raise _corrupt(path, "header entry residual.learned must be null or hold a unit > 0 and a light count")
        lights = _header_int(path, part, "lights", 1, 10**7)
        codes = read(_LEARNED_CODES, "<f2", (NEURAL_CODE_SIZE, height, width)).transpose(1, 2, 0)
        hidden = part.get("hidden", list(NEURAL_HIDDEN))
        if (not isinstance(hidden, list) or not 1 <= len(hidden) <= NEURAL_MAX_HIDDEN
                or not all(_is_int(w) and 1 <= w <= NEURAL_HIDDEN[0] for w in hidden)):
            raise _corrupt(path, f"header entry residual.learned.hidden must list 1 to {NEURAL_MAX_HIDDEN} layer "
                                 f"widths of 1 to {NEURAL_HIDDEN[0]}, got {hidden!r}")
        sees = part.get("highlights", False)
        if not isinstance(sees, bool):
            raise _corrupt(path, f"header entry residual.learned.highlights must be true or false, got {sees!r}")
        weights = tuple(read(name, "<f4", shape) for name, shape in zip(_learned_weight_names(len(hidden) + 1),
                                                                       decoder_layer_shapes(hidden, sees)))
        bounded = part.get("bounds", False)
        if not isinstance(bounded, bool):
            raise _corrupt(path, f"header entry residual.learned.bounds must be true or false, got {bounded!r}")
        bounds = read(_LEARNED_BOUNDS, "<f2", (2, 3, height, width)).transpose(0, 2, 3, 1) if bounded else None
        try:
            learned = NeuralResidual(codes, weights, float(part["unit"]), lights, bounds)
        except InputError as exc:
            raise _corrupt(path, str(exc)) from None
    elif not compressed:
        images = read(_RESIDUAL_IMAGES, "<f2", (n, channels, height, width)).transpose(0, 2, 3, 1)
    else:
        for name, planes in (("luminance", 1), ("chroma", 2)):
            part = layout.get(name)
            if part is None:
                continue
            if not isinstance(part, dict) or part.get("mean_dtype") not in ("float16", "float32"):
                raise _corrupt(path, f"header entry residual.{name} must be null or hold a rank and a mean_dtype")
            rank = _header_int(path, part, "rank", 0, n)
            bits = part.get("bits", 8)
            if bits not in (8, 16):
                raise _corrupt(path, f"header entry residual.{name}.bits must be 8 or 16, got {bits!r}")
            prefix = _STACK_PREFIX[name]
            mean = read(prefix + "mean.npy", "<f2" if part["mean_dtype"] == "float16" else "<f4",
                        (planes, height, width))
            if version >= 4:  # version 5: the differences zigzag-mapped (io.codes); 4: as they are
                stored = read(prefix + "codes.npy", "<u1", stored_shape(rank, planes, height, width, bits))
                codes = codes_from_stored(stored, bits) if version >= 5 else codes_from_differences(stored, bits)
            else:
                codes = read(prefix + "codes.npy", "<u1" if bits == 8 else "<u2", (rank, planes, height, width))
            stacks[name] = LowRankStack(
                mean=mean.transpose(1, 2, 0).astype(np.float32),
                codes=codes.transpose(0, 2, 3, 1),
                ranges=read(prefix + "ranges.npy", "<f4", (rank, 2)),
                weights=read(prefix + "weights.npy", "<f4", (n, rank)),
                mean_weights=read(prefix + "mean_weights.npy", "<f4", (n,)),
            )
        if "luminance" not in stacks or (channels == 3) != ("chroma" in stacks):
            raise _corrupt(path, f"a compressed {channels}-channel residual needs a luminance "
                                 f"stack{' and a chroma stack' if channels == 3 else ' only'}")
    scale = None
    if layout.get("scale", False) is not False:
        if layout.get("scale") is not True:
            raise _corrupt(path, f"header entry residual.scale must be true or false, got {layout.get('scale')!r}")
        scale = read(_RESIDUAL_SCALE, "<f2", (height, width)).astype(np.float32)
    colour = None
    if with_colour:
        colour = colour_from_codes(read(_RESIDUAL_COLOUR, "<u1", (channels, height, width)).transpose(1, 2, 0))
    sigma = layout.get("rbf_sigma")  # version 8
    if sigma is not None and (not _is_number(sigma) or not 0 < sigma <= 4):
        raise _corrupt(path, f"header entry residual.rbf_sigma must be null or a number in (0, 4], got {sigma!r}")
    try:
        return ResidualModel(images=images, luminance=stacks.get("luminance"), chroma=stacks.get("chroma"),
                             highlight_colour=colour, scale=scale,
                             learned=learned, rbf_sigma=sigma)
    except InputError as exc:
        raise _corrupt(path, str(exc)) from None


def _unpack(rows: np.ndarray, active: np.ndarray) -> GaussianParams:
    """Inverse of ``_pack``: scatter (K, 6) rows into the active slots (row-major order) of a batch."""
    params = GaussianParams.empty(*active.shape)
    r, s = np.nonzero(active)
    values = rows.astype(np.float64)
    params.amplitude[r, s] = values[:, 0]
    params.mean[r, s] = values[:, 1:3]
    params.sigma[r, s] = values[:, 3:5]
    params.theta[r, s] = values[:, 5]
    params.active = active
    return params
