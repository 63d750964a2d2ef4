"""Reflectance fields on disk: load a dataset folder, and write one chunk by chunk.

The folder layout is described in ``docs/dataset-format.md``: a ``.lp`` light file listing the images,
optional ground-truth ``specular/`` and ``diffuse/`` EXRs named after each image's stem, optional
held-out lights (``heldout.lp``), ``mask.png`` and ``meta.json``.

This module holds one thing: a dataset folder on disk, read (``ReflectanceField``) and written
(``DatasetWriter``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import threading
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model.errors import InputError
from ..model.lights import LightSet
from ..model.memory import check_memory
from ..model.threads import (
    cancel_and_wait,
    child_initializer,
    core_count,
    mapped_empty,
    submit,
)
from .atomic import FolderTransaction, deferred_signals
from .images import (
    DEFAULT_MAX_PIXELS,
    ImageHeader,
    image_encoding,
    image_header,
    read_image,
    read_pixels,
    write_image,
)
from .lightfile import LIGHT_FILE_SUFFIXES, read_lights, write_lp

__all__ = ["HELDOUT_FOLDER", "DatasetWriter", "LoadStopped", "ReflectanceField", "capture_differences",
           "capture_fingerprint", "dataset_folder_entry", "find_heldout_folder", "find_light_file", "has_light_file"]


class LoadStopped(Exception):
    """``ReflectanceField.load`` stopped early because its caller set ``stop``."""

LOAD_WORKERS = min(32, core_count())
"""Threads that decode a dataset's images (the decoders release the GIL): one per core, at most 32
(the most cores measured; each holds an image being decoded, see ``_check_memory``). On a 16-core
host the 1,000-image 1920x1080 float16 EXR capture loads in 6.0 s with 16 threads, 7.2 s with 12 and
9.8-10.9 s with 8 (benchmarks/bench_load.py), so every core is used."""
DISPLAY_REFERRED_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
"""Image files that hold display values (8/16-bit photographs), as opposed to radiance (EXR/HDR)."""

_COMPONENTS = ("specular", "diffuse")
_GROUP_FOLDERS = {"lights": ("images", ""), "heldout": ("heldout", "h")}  # group -> (folder, stem prefix)

WRITER_THREAD_PREFIX = "write"
"""Name prefix of the threads that write a dataset's images."""


@dataclass(eq=False)
class ReflectanceField:
    """Images of one object under many light directions, with optional ground truth.

    Attributes:
        images: ``(n, H, W)`` or ``(n, H, W, 3)`` float32 linear radiance, one image per light.
        lights: The ``n`` light directions (and image file names when loaded from disk).
        specular: Ground-truth specular component, same shape as ``images``, or None.
        diffuse: Ground-truth diffuse component, same shape as ``images``, or None.
        mask: ``(H, W)`` bool, True on the object, or None.
        heldout: Ground truth at other light directions (same image size), or None.
        meta: Free-form metadata (generator, shape, material, resolution, colour space).
        root: Folder the field was loaded from, or None.
        source: How the loaded files stored their values (``io.images.image_encoding`` of the first
            image: format, bits per channel, sRGB or linear, ICC profile, and ``size``: the files'
            [width, height], which ``load(size=...)`` shrinks from), or None (made in memory).
    """

    images: np.ndarray
    lights: LightSet
    specular: np.ndarray | None = None
    diffuse: np.ndarray | None = None
    mask: np.ndarray | None = None
    heldout: ReflectanceField | None = None
    meta: dict = field(default_factory=dict)
    root: Path | None = None
    source: dict | None = None

    def __post_init__(self) -> None:
        self.images = np.asarray(self.images, dtype=np.float32)
        if self.images.ndim not in (3, 4) or (self.images.ndim == 4 and self.images.shape[3] != 3):
            raise InputError(f"images must have shape (n, H, W) or (n, H, W, 3), got {self.images.shape}")
        if len(self.lights) != len(self.images):
            raise InputError(f"{len(self.images)} images for {len(self.lights)} light directions")
        for name in _COMPONENTS:
            component = getattr(self, name)
            if component is not None:
                component = np.asarray(component, dtype=np.float32)
                if component.shape != self.images.shape:
                    raise InputError(f"{name} has shape {component.shape}, images {self.images.shape}")
                setattr(self, name, component)
        if self.mask is not None:
            self.mask = np.asarray(self.mask, dtype=bool)
            if self.mask.shape != (self.height, self.width):
                raise InputError(f"mask has shape {self.mask.shape}, images are {self.height}x{self.width}")
        if self.heldout is not None and self.heldout.images.shape[1:] != self.images.shape[1:]:
            raise InputError(
                f"held-out images have shape {self.heldout.images.shape[1:]}, images {self.images.shape[1:]}"
            )
        if self.root is not None:
            self.root = Path(self.root)

    @property
    def light_count(self) -> int:
        """Number of images (lights)."""
        return self.images.shape[0]

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self.images.shape[1]

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self.images.shape[2]

    @property
    def channels(self) -> int:
        """1 for grayscale, 3 for RGB."""
        return 1 if self.images.ndim == 3 else self.images.shape[3]

    def summary(self) -> dict:
        """Counts, size, light coverage and value ranges, as ``warp-highlights info`` prints them."""
        from ..model.triangulation import SphericalTriangulation

        directions = self.lights.directions
        try:
            triangulation = SphericalTriangulation(directions)
        except InputError as error:
            raise InputError(f"{self.root}: {error}" if self.root is not None else str(error)) from None
        elevation = np.degrees(np.arcsin(np.clip(directions[:, 2], -1.0, 1.0)))
        summary = {
            "folder": str(self.root) if self.root is not None else None,
            "lights": self.light_count,
            "size": f"{self.width}x{self.height}",
            "channels": self.channels,
            "coverage": "dome (open boundary)" if triangulation.is_dome else "full sphere",
            "triangles": triangulation.face_count,
            "elevation_deg": [round(float(elevation.min()), 2), round(float(elevation.max()), 2)],
            "value_range": [float(self.images.min()), float(self.images.max())],
            "mean_value": float(self.images.mean()),
            "ground_truth": [name for name in _COMPONENTS if getattr(self, name) is not None],
            "mask_pixels": None if self.mask is None else int(self.mask.sum()),
            "heldout_lights": 0 if self.heldout is None else self.heldout.light_count,
        }
        if self.source:
            profile = self.source["profile"]
            summary["source"] = (f"{self.source['bits']}-bit {self.source['format']}, {self.source['values']} values"
                                 + (f", ICC profile '{profile}'" if profile else ""))
        if self.meta:
            summary["generator"] = self.meta.get("generator")
        return summary

    @classmethod
    def load(
        cls,
        folder,
        *,
        heldout=None,
        linear: bool = False,
        replace_nonfinite: bool = False,
        progress: bool = True,
        max_pixels: int | None = DEFAULT_MAX_PIXELS,
        size: tuple[int, int] | None = None,
        workers: int | None = None,
        components: bool = True,
        stop: threading.Event | None = None,
        before_decoding: Callable[[int], None] | None = None,
    ) -> ReflectanceField:
        """Load a dataset folder into memory (one preallocated float32 array per image stack).

        Before any pixel is decoded, every image's header is read: sizes and channel counts must agree,
        no image may exceed ``max_pixels``, and the float32 stacks must fit in the memory available
        (see ``_check_memory``). A capture whose images are all black, or all white (PNG/JPEG), is refused.
        Images are decoded by ``workers`` threads (the decoders release the GIL), each straight into
        the working ``size``.

        Args:
            folder: Dataset folder with ``lights.lp`` (or exactly one other ``.lp``) and its images.
            heldout: Another dataset folder holding the held-out lights and images; by default
                ``heldout.lp`` in ``folder``, when present; False loads none (what ``fit`` does).
            linear: PNG/JPEG values are linear already; skip the sRGB decode.
            replace_nonfinite: Replace NaN/inf pixels by 0 (with a warning) instead of failing.
            progress: Show a progress bar on stderr (only when it is a terminal).
            max_pixels: Refuse an image of more pixels (width x height) than this; None for no limit
                (see ``warp_highlights.io.images.DEFAULT_MAX_PIXELS``).
            size: (width, height) to shrink every image (and the mask) to as it is read, an area
                average (``io.resample``); None keeps the images' size. Same aspect ratio.
            workers: decoding threads; default ``LOAD_WORKERS``.
            stop: once set, the loading stops after the image it is checking, raising ``LoadStopped``
                (a caller loading in a thread whose own work failed).
            components: also load the ground-truth ``specular/`` and ``diffuse/`` images, when present
                (``fit`` does not use them).
            before_decoding: called with the float32 bytes the loaded stacks will take, once every
                header is read and before any image is decoded (it may wait, or raise to stop the loading).

        Raises:
            InputError: One line on any bad input: missing folder, image or light file, several
                ``.lp`` files, an image listed twice, images of different sizes or channel counts,
                an image over ``max_pixels``, not enough memory, a partial ground-truth set,
                non-finite pixels, all images black or all white, a bad mask or ``meta.json``.
        """
        from tqdm import tqdm

        from .resample import working_size

        folder = _existing_folder(folder)
        main = _ImageGroup.plan(find_light_file(folder))
        extra = None if heldout is False else _heldout_group(folder, heldout)
        groups = [main] if extra is None else [main, extra]
        if not components:
            groups = [dataclasses.replace(group, specular=None, diffuse=None) for group in groups]
        shape, headers = _planned_shape(groups, max_pixels)
        width, height = working_size(shape[1], shape[0], size)
        workers = LOAD_WORKERS if workers is None else int(workers)
        if workers < 1:
            raise InputError(f"workers must be >= 1, got {workers}")
        # a decoding thread's image, its finite mask, its shrunk copy
        _check_memory(folder, sum(g.file_count for g in groups), (height, width, *shape[2:]),
                      decoding=min(workers, sum(g.file_count for g in groups)) * int(1.5 * np.prod(shape)))
        if before_decoding is not None:
            before_decoding(sum(g.file_count for g in groups) * height * width * int(np.prod(shape[2:])) * 4)
        # while the images decode
        mask = submit(_read_mask, folder / "mask.png", (shape[0], shape[1]), max_pixels, size=(width, height))
        try:
            with tqdm(total=sum(g.file_count for g in groups), desc=f"loading {folder.name}", unit="image",
                      disable=None if progress else True, leave=False) as bar:
                reader = _StackReader(linear=linear, replace_nonfinite=replace_nonfinite, bar=bar,
                                      max_pixels=max_pixels, headers=headers,
                                      size=(width, height), workers=workers, stop=stop)
                fields = [cls(*reader.read_group(g), root=g.light_file.parent) for g in groups]
        except BaseException:  # a bad image or Ctrl-C: the mask's read not left running
            cancel_and_wait([mask])
            raise
        reader.report_nonfinite()
        _check_not_blank(groups[0], len(fields[0].images), *reader.ranges[groups[0].light_file])
        result = fields[0]
        result.heldout = fields[1] if extra is not None else None
        result.mask = mask.result()
        result.meta = _read_meta(folder / "meta.json")
        result.source = {**image_encoding(main.images[0], linear=linear), "size": [int(shape[1]), int(shape[0])]}
        return result

    @property
    def display_referred(self) -> bool:
        """True when every image came from a JPEG/PNG/TIFF/... file (a photograph's display values, whose
        1 need not be the capture's white), False for EXR/HDR radiance and images made in memory."""
        names = self.lights.filenames or []
        return bool(names) and all(str(name).lower().endswith(DISPLAY_REFERRED_SUFFIXES) for name in names)

    def split_every(self, k: int) -> ReflectanceField:
        """The k-fold hold-out protocol: lights 0, k, 2k, ... held out (``heldout``), the rest kept.

        The result shares no arrays with this field; its ``meta`` records ``heldout_protocol``.
        """
        k = int(k)
        if k < 2:
            raise InputError(f"--holdout-every must be at least 2 (every k-th light held out), got {k}")
        held = np.arange(self.light_count) % k == 0
        if self.light_count - held.sum() < 4:
            raise InputError(f"holding out every {k}th of {self.light_count} lights leaves "
                             f"{self.light_count - held.sum()}; a fit needs at least 4")

        def part(mask) -> ReflectanceField:
            pick = lambda a: None if a is None else a[mask].copy()
            return ReflectanceField(self.images[mask].copy(), self.lights.take(mask),
                                    specular=pick(self.specular), diffuse=pick(self.diffuse), mask=self.mask,
                                    root=self.root,
                                    source=self.source)

        train = part(~held)
        train.heldout = part(held)
        train.meta = {**(self.meta or {}), "heldout_protocol": f"every {k}th light (0, {k}, {2 * k}, ...) held out"}
        return train

    def save(self, folder, *, half: bool = False, overwrite: bool = False) -> Path:
        """Write the field as a dataset folder of EXR images (see :class:`DatasetWriter`).

        Args:
            folder: Target folder; replaced atomically when ``overwrite``.
            half: Store 16-bit half floats instead of float32.
            overwrite: Replace an existing non-empty folder.

        Returns:
            The dataset folder.
        """
        with DatasetWriter(folder, overwrite=overwrite, half=half) as writer:
            writer.write_images("lights", 0, self.images, self.specular, self.diffuse)
            heldout_lights = None
            if self.heldout is not None:
                writer.write_images("heldout", 0, self.heldout.images, self.heldout.specular, self.heldout.diffuse)
                heldout_lights = self.heldout.lights
            writer.finish(self.lights, heldout_lights, mask=self.mask, meta=self.meta or None)
        return Path(folder)


class DatasetWriter:
    """Streams a dataset to a hidden temporary folder, then moves it into place in one rename.

    Nothing already at ``folder`` is touched until :meth:`commit`; :meth:`abort` (or an exception
    inside a ``with`` block) removes the temporary folder. Images are named ``images/NNNN.exr`` and
    ``heldout/hNNNN.exr`` (4 digits, more when needed), their ground truth ``specular/<stem>.exr`` and
    ``diffuse/<stem>.exr``.

    Example:
        with DatasetWriter("out/donut") as writer:
            for start in range(0, n, 64):
                writer.write_images("lights", start, full, specular, diffuse)
            writer.finish(lights, heldout_lights, meta={"shape": "donut"})
        # leaving the block commits
    """

    def __init__(self, folder, *, overwrite: bool = False, half: bool = False):
        """Create the temporary folder beside ``folder``.

        Args:
            folder: Final dataset folder.
            overwrite: Allow replacing an existing dataset folder (at commit): one this project wrote
                (its manifest lists every file in it), never a folder holding other files.
            half: Store 16-bit half floats instead of float32.

        Raises:
            InputError: ``folder`` is a file, exists non-empty without ``overwrite``, holds files
                this project did not write, or cannot be written.
        """
        self.folder = Path(folder)
        self.overwrite = overwrite
        self.half = half
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self._transaction = FolderTransaction(self.folder, kind="dataset", overwrite=overwrite,
                                              legacy=dataset_folder_entry)
        self._tmp = self._transaction.temporary
        self._written = {group: {kind: set() for kind in ("full", *_COMPONENTS)} for group in _GROUP_FOLDERS}
        self._shape: tuple[int, ...] | None = None
        self._state = "open"

    def write_images(self, group: str, start_index: int, full, specular=None, diffuse=None) -> None:
        """Write a chunk of consecutive images.

        Args:
            group: ``"lights"`` or ``"heldout"``.
            start_index: Light index of the first image of the chunk.
            full: ``(k, H, W)`` or ``(k, H, W, 3)`` linear images.
            specular: Ground-truth specular component, same shape as ``full``, or None.
            diffuse: Ground-truth diffuse component, same shape as ``full``, or None.
        """
        self._require_state("open", "write_images")
        if group not in _GROUP_FOLDERS:
            raise ValueError(f"group must be 'lights' or 'heldout', got {group!r}")
        stacks = {"full": self._checked_stack(full)}
        for kind, stack in zip(_COMPONENTS, (specular, diffuse)):
            if stack is not None:
                stacks[kind] = self._checked_stack(stack)
                if stacks[kind].shape != stacks["full"].shape:
                    raise ValueError(f"{kind} chunk has shape {stacks[kind].shape}, images {stacks['full'].shape}")
        jobs = [
            (self._tmp / _image_name(group, kind, start_index + offset), image)
            for kind, stack in stacks.items()
            for offset, image in enumerate(stack)
        ]
        # EXR compression runs in C++ without the GIL: a few threads keep every core and the disk busy.
        pool = ThreadPoolExecutor(max_workers=min(len(jobs), 2 * core_count()) or 1,
                                  thread_name_prefix=WRITER_THREAD_PREFIX)
        try:
            # Signals held while threads start: one raised inside Thread.start (it waits for the thread)
            # leaves that thread out of the pool's records, so shutdown() would not wait for it to stop writing.
            with deferred_signals():
                futures = [pool.submit(write_image, path, image, half=self.half) for path, image in jobs]
            for future in futures:
                future.result()
        finally:  # on an error or a signal: no thread may still write once the folder is removed
            with deferred_signals():
                pool.shutdown(wait=True, cancel_futures=True)
        for kind, stack in stacks.items():
            self._written[group][kind].update(range(start_index, start_index + len(stack)))

    def finish(self, lights: LightSet, heldout_lights: LightSet | None, mask=None, meta=None) -> None:
        """Write the light files, mask and metadata once every image is written.

        Args:
            lights: The reflectance field's lights, one per written ``"lights"`` image.
            heldout_lights: The held-out lights, one per written ``"heldout"`` image, or None (an
                empty set counts as None: no ``heldout.lp`` is written).
            mask: ``(H, W)`` bool object mask, written as ``mask.png`` (white = object), or None.
            meta: JSON-serialisable dict written as ``meta.json`` (indent 2), or None.
        """
        self._require_state("open", "finish")
        for group, group_lights in (("lights", lights), ("heldout", heldout_lights)):
            count = 0 if group_lights is None else group_lights.light_count
            self._check_complete(group, count)
            if count:
                names = [_image_name(group, "full", i) for i in range(count)]
                write_lp(group_lights, self._tmp / f"{group}.lp", filenames=names)
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if self._shape is not None and mask.shape != self._shape[:2]:
                raise ValueError(f"mask has shape {mask.shape}, images {self._shape[:2]}")
            write_image(self._tmp / "mask.png", mask.astype(np.float32), linear=True)
        if meta is not None:
            text = json.dumps(meta, indent=2, default=_json_default)
            (self._tmp / "meta.json").write_text(text + "\n", encoding="utf-8")
        self._state = "finished"

    def commit(self) -> Path:
        """Move the finished dataset into place; an existing folder (with ``overwrite``) is swapped out
        and removed.

        Returns:
            The dataset folder.
        """
        self._require_state("finished", "commit")
        self._transaction.commit()
        self._state = "committed"
        return self.folder

    def abort(self) -> None:
        """Remove the temporary folder; the target folder is left as it was. Safe to call twice."""
        if self._state != "committed":
            self._transaction.abort()
            self._state = "aborted"

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif self._state in ("open", "finished"):
            try:
                self.commit()
            except BaseException:
                self.abort()
                raise

    def _require_state(self, state: str, action: str) -> None:
        if self._state != state:
            raise ValueError(f"DatasetWriter.{action}() needs a writer that is {state}, this one is {self._state}")

    def _checked_stack(self, stack) -> np.ndarray:
        stack = np.asarray(stack, dtype=np.float32)
        if stack.ndim not in (3, 4) or (stack.ndim == 4 and stack.shape[3] != 3):
            raise ValueError(f"image chunks must have shape (k, H, W) or (k, H, W, 3), got {stack.shape}")
        if self._shape is None:
            self._shape = stack.shape[1:]
        elif stack.shape[1:] != self._shape:
            raise ValueError(f"image chunk of shape {stack.shape[1:]} after chunks of shape {self._shape}")
        if not np.isfinite(stack).all():
            raise ValueError(
                f"image chunk holds {int((~np.isfinite(stack)).sum())} non-finite values; nothing is written")
        return stack

    def _check_complete(self, group: str, count: int) -> None:
        written = self._written[group]
        missing = sorted(set(range(count)) - written["full"])
        if missing:
            raise ValueError(f"{group}: no image written for light(s) {missing[:5]} of {count}")
        extra = sorted(written["full"] - set(range(count)))
        if extra:
            raise ValueError(f"{group}: images written for light(s) {extra[:5]} beyond the {count} lights")
        for kind in _COMPONENTS:
            if written[kind] and written[kind] != written["full"]:
                raise ValueError(f"{group}: {kind} images written for some lights but not all")


# --- loading helper functions -------------------------------------------------------------------


@dataclass
class _ImageGroup:
    """The files of one light set: its light file, images and optional ground-truth components."""

    light_file: Path
    lights: LightSet
    images: list[Path]
    specular: list[Path] | None
    diffuse: list[Path] | None

    @classmethod
    def plan(cls, light_file: Path) -> _ImageGroup:
        lights = read_lights(light_file, check_files=True)
        images = [light_file.parent / name for name in lights.filenames]
        specular, diffuse = (_component_paths(light_file.parent, kind, images) for kind in _COMPONENTS)
        return cls(light_file, lights, images, specular, diffuse)

    @property
    def file_count(self) -> int:
        return sum(len(paths) for paths in (self.images, self.specular, self.diffuse) if paths)


class _ShapeCheck:
    """Checks that every image shares the first one's size and channel count."""

    def __init__(self):
        self.first: tuple[Path, tuple[int, ...]] | None = None

    def check(self, path: Path, shape: tuple[int, ...]) -> None:
        if self.first is None:
            self.first = (path, shape)
            return
        first_path, first_shape = self.first
        if shape[:2] != first_shape[:2]:
            raise InputError(
                f"{path}: image is {shape[1]}x{shape[0]} but the first image {first_path} is "
                f"{first_shape[1]}x{first_shape[0]}; all images must share one size"
            )
        if len(shape) != len(first_shape):
            raise InputError(
                f"{path}: image has {_channel_count(shape)} channel(s) but the first image {first_path} "
                f"has {_channel_count(first_shape)}; use all grayscale or all RGB"
            )


def _planned_shape(groups: list[_ImageGroup],
                   max_pixels: int | None) -> tuple[tuple[int, ...], dict[Path, ImageHeader]]:
    """The common image shape, ``(H, W)`` or ``(H, W, 3)``, from every image's header (no pixel decoded), and
    the headers by path (the decoders do not read them again)."""
    shapes = _ShapeCheck()
    headers: dict[Path, ImageHeader] = {}
    for group in groups:
        for paths in (group.images, group.specular, group.diffuse):
            for path in paths or ():
                headers[path] = image_header(path, max_pixels=max_pixels)
                shapes.check(path, headers[path].shape)
    return shapes.first[1], headers


def _check_memory(folder: Path, file_count: int, shape: tuple[int, ...], *, decoding: int = 0) -> None:
    """Refuse a load whose float32 stacks of ``shape`` (the working size), plus ``decoding`` float32
    values of images being decoded at their own size, exceed the available memory."""
    size = "x".join(str(n) for n in (shape[1], shape[0], *shape[2:]))
    check_memory((file_count * int(np.prod(shape)) + max(decoding, 2 * int(np.prod(shape)))) * 4, f"{folder}: loading",
                 "free memory, use a machine with more, or downscale the images",
                 detail=f"{file_count} images of {size} as float32")


def _check_not_blank(group: _ImageGroup, count: int, low: float, high: float) -> None:
    """Refuse a capture of ``count`` images whose values (``low`` to ``high``) are all black, or all at
    the white level 1 (PNG and JPEG only: an EXR's values may lie above 1 everywhere); a few black
    images among good ones are fine."""
    if high <= 0.0:
        raise InputError(
            f"{group.light_file}: all {count} images are entirely black (every pixel 0); the capture holds "
            "no light: check the exposure, the lens cap and the file names"
        )
    integer_coded = all(path.suffix.lower() != ".exr" for path in group.images)
    if integer_coded and low >= 1.0:
        raise InputError(
            f"{group.light_file}: all {count} images are entirely white (every pixel at the white level); "
            "the capture is over-exposed: shoot again with a shorter exposure or a dimmer light"
        )


class _StackReader:
    """Reads image stacks into preallocated float32 arrays, checking size, channels and finiteness."""

    def __init__(self, *, linear: bool, replace_nonfinite: bool, bar, max_pixels: int | None = DEFAULT_MAX_PIXELS,
                 size: tuple[int, int] | None = None, workers: int = 1, stop: threading.Event | None = None,
                 headers: dict[Path, ImageHeader] | None = None):
        self.stop = stop
        self.headers = headers or {}  # read and checked already: not read again
        self.linear = linear
        self.replace_nonfinite = replace_nonfinite
        self.bar = bar
        self.max_pixels = max_pixels
        self.size = size
        self.workers = workers
        self.shapes = _ShapeCheck()
        self.nonfinite_count = 0
        self.nonfinite_file: Path | None = None
        self.ranges: dict[Path, tuple[float, float]] = {}  # by light file: the smallest and largest value of its images

    def read_group(self, group: _ImageGroup) -> tuple:
        """(images, lights, specular, diffuse) of one group, in ``ReflectanceField`` field order. The
        images' smallest and largest values are kept in ``ranges[group.light_file]``."""
        images, low, high = self.read_stack(group.images)
        specular, diffuse = (self.read_stack(p)[0] if p else None for p in (group.specular, group.diffuse))
        self.ranges[group.light_file] = (low, high)
        return images, group.lights, specular, diffuse

    def read_stack(self, paths: list[Path]) -> tuple[np.ndarray, float, float]:
        """(stack, smallest value, largest value) of the images at ``paths``: decoded by ``workers``
        threads, each copying its image straight into its place in the stack (one thread copying them
        all would take as long as the decoding on a 1,000-image capture), checked in file order."""
        holder: dict = {}
        lock = threading.Lock()

        def place(index: int, path: Path) -> tuple:  # one thread's work: decode, then copy into the stack
            if self.stop is not None and self.stop.is_set():
                raise LoadStopped(f"loading stopped before {path}")  # not decoded: the caller has given up
            path, shape, bad, values = self._decode(path)
            with lock:  # the first image decoded sizes the stack
                if "stack" not in holder:
                    # its pages mapped by threads
                    holder["stack"] = mapped_empty((len(paths), *values.shape), np.float32)
            stack = holder["stack"]
            # the check in file order refuses this image or the one that sized the stack
            if values.shape != stack.shape[1:]:
                return path, shape, bad or 0, values.shape, np.inf, -np.inf
            image = stack[index]
            # widened to float32 as it is copied (a half EXR's values exactly)
            np.copyto(image, values, casting="unsafe")
            low, high = float(image.min()), float(image.max())
            if bad is None:  # counted here: min and max carry any NaN or infinity, so finite ones need no count
                bad = 0
                if not (math.isfinite(low) and math.isfinite(high)):
                    nonfinite = ~np.isfinite(image)
                    bad = int(nonfinite.sum())
                    if self.replace_nonfinite:
                        image[nonfinite] = 0.0
                        low, high = float(image.min()), float(image.max())
            return path, shape, bad, values.shape, low, high

        low, high = np.inf, -np.inf
        first: tuple | None = None  # the first image's path and decoded shape
        pool = ThreadPoolExecutor(max_workers=max(1, min(self.workers, len(paths))), thread_name_prefix="load",
                                  # loaded from a worker: its threads' maps run in place
                                  initializer=child_initializer())
        try:
            for path, shape, bad, decoded, image_low, image_high in pool.map(place, range(len(paths)), paths):
                if self.stop is not None and self.stop.is_set():
                    raise LoadStopped(f"loading stopped at {path}")
                self.shapes.check(path, shape)
                first = first or (path, decoded)
                if decoded != first[1]:  # a stored shape that passed the check but decoded to another one
                    raise InputError(f"{path}: decoded to shape {decoded} but the first image {first[0]} "
                                     f"to {first[1]}; "
                                     "save both in one format")
                if bad:
                    self.nonfinite_count += bad
                    self.nonfinite_file = self.nonfinite_file or path
                low, high = min(low, image_low), max(high, image_high)
                self.bar.update()
        finally:  # an error or Ctrl-C: drop the images not started yet
            pool.shutdown(wait=True, cancel_futures=True)
        return holder.get("stack"), low, high  # no paths: no stack, as before

    def _decode(self, path: Path) -> tuple:
        """(path, shape as stored, non-finite values, values at the working size). Where the file has the
        working size, its values as stored (``read_pixels``: a half EXR's float16), counted where they are
        copied into the stack (None here); else float32, counted (and replaced, if asked) before resampling.
        Each call here that lets go of the GIL must take it back, which beside the pipeline's imports can
        wait a whole switch interval (5 ms): the fewer such calls an image makes, the sooner the capture loads."""
        from .resample import resample_image

        pixels = read_pixels(path, linear=self.linear, max_pixels=self.max_pixels, header=self.headers.get(path))
        shape = pixels.shape
        if self.size is None or (shape[1], shape[0]) == tuple(self.size):
            return path, shape, None, pixels
        image = pixels.astype(np.float32)
        bad = ~np.isfinite(image)
        count = int(bad.sum())
        if count and self.replace_nonfinite:
            image[bad] = 0.0
        return path, shape, count, resample_image(image, *self.size)

    def report_nonfinite(self) -> None:
        """Raise (or warn, when replacing) about the non-finite pixels seen so far."""
        if not self.nonfinite_count:
            return
        what = f"{self.nonfinite_count} non-finite pixel values (NaN or inf), first in {self.nonfinite_file}"
        if not self.replace_nonfinite:
            raise InputError(f"{what}; the command line does not replace them: fix or re-export those images "
                             "with finite values, or load the capture in Python with "
                             "ReflectanceField.load(folder, replace_nonfinite=True), which replaces them by 0")
        warnings.warn(f"{what}; replaced by 0", stacklevel=3)


def _channel_count(shape: tuple[int, ...]) -> int:
    return 1 if len(shape) == 2 else shape[2]


def _existing_folder(folder) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: dataset folder not found")
    return folder


def find_light_file(folder: Path) -> Path:
    """A dataset folder's light file: ``lights.lp``, else the one ``*.lp`` other than ``heldout.lp``, else the one
    relight ``*.relight`` project, else the one ``*.dome`` (``InputError`` for none, or several of the first kind
    found)."""
    if (folder / "lights.lp").is_file():
        return folder / "lights.lp"
    for suffix in LIGHT_FILE_SUFFIXES:
        candidates = sorted(p for p in folder.iterdir()
                            if p.suffix.lower() == suffix and p.name != "heldout.lp" and p.is_file())
        if len(candidates) > 1:
            names = ", ".join(p.name for p in candidates)
            raise InputError(f"{folder}: several light files ({names}); keep one or name it lights.lp")
        if candidates:
            return candidates[0]
    raise InputError(f"{folder}: no light file (lights.lp or another .lp, or relight's .relight or .dome) in the "
                     "dataset folder")


HELDOUT_FOLDER = "Test"
"""A capture's held-out lights in a folder of their own (the SynthRTI layout: ``Dome/`` beside ``Test/``, or
``Test/`` inside the capture); ``heldout.lp`` inside the capture (what ``render`` writes) works as well."""


def has_light_file(folder: Path) -> bool:
    """Whether ``folder`` is a folder holding a light file (a ``*.lp`` other than ``heldout.lp``, a ``*.relight`` or a
    ``*.dome``)."""
    try:
        return (folder.is_dir()
                and any(p.suffix.lower() in LIGHT_FILE_SUFFIXES and p.name != "heldout.lp" and p.is_file()
                        for p in folder.iterdir()))
    except OSError:
        return False


def find_heldout_folder(folder) -> Path | None:
    """The folder of held-out lights and images that belongs to the capture in ``folder``: a ``Test/`` beside it
    (``OBJECT/Dome`` and ``OBJECT/Test``, where ``OBJECT`` holds no light file and no other capture), else a
    ``Test/`` inside it; None for neither (``heldout.lp`` in the folder is ``ReflectanceField.load``'s own)."""
    folder = Path(os.path.abspath(folder))
    sibling = folder.parent / HELDOUT_FOLDER
    if (folder.name != HELDOUT_FOLDER and has_light_file(sibling) and not has_light_file(folder.parent)
            and _only_capture_beside(sibling)):
        return sibling
    inside = folder / HELDOUT_FOLDER
    return inside if has_light_file(inside) else None


def _only_capture_beside(heldout: Path) -> bool:
    """Whether exactly one folder beside ``heldout`` (a ``Test/``) has a light file: the capture it belongs to."""
    try:
        return sum(1 for p in heldout.parent.iterdir()
                   if p.is_dir() and p.name != HELDOUT_FOLDER and has_light_file(p)) == 1
    except OSError:
        return False


def _heldout_group(folder: Path, heldout) -> _ImageGroup | None:
    if heldout is not None:
        return _ImageGroup.plan(find_light_file(_existing_folder(heldout)))
    if (folder / "heldout.lp").is_file():
        return _ImageGroup.plan(folder / "heldout.lp")
    return None


def _component_paths(folder: Path, kind: str, images: list[Path]) -> list[Path] | None:
    """``<folder>/<kind>/<image stem>.exr`` for every image, None when there are none at all."""
    paths = [folder / kind / f"{image.stem}.exr" for image in images]
    present = [path.is_file() for path in paths]
    if not any(present):
        return None
    if not all(present):
        index = present.index(False)
        raise InputError(
            f"{paths[index]}: missing {kind} image for {images[index].name}; "
            f"provide {kind}/ images for all {len(images)} lights or none"
        )
    return paths


def _read_mask(path: Path, shape: tuple[int, int], max_pixels: int | None = DEFAULT_MAX_PIXELS, *,
               size: tuple[int, int] | None = None) -> np.ndarray | None:
    """The object mask (images' ``shape``), at the working ``size`` when given: pixels at least half inside."""
    from .resample import resample_image

    if not path.is_file():
        return None
    mask = read_image(path, linear=True, max_pixels=max_pixels)
    if mask.ndim == 3:
        mask = mask.mean(axis=2)
    if mask.shape != shape:
        raise InputError(
            f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} but the images are {shape[1]}x{shape[0]}"
        )
    if size is not None and (mask.shape[1], mask.shape[0]) != tuple(size):
        mask = resample_image(mask, *size)
    return mask >= 0.5


def _read_meta(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason})") from exc
    except RecursionError:
        raise InputError(
            f"{path}: JSON nested too deeply to read; it is damaged or not a dataset's meta.json") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path}: expected a JSON object {{...}}, got {type(meta).__name__}")
    return meta


# --- writing helper functions -------------------------------------------------------------------


def _image_name(group: str, kind: str, index: int) -> str:
    """Relative path of an image: ``images/0007.exr``, ``specular/h0007.exr``, ..."""
    folder, prefix = _GROUP_FOLDERS[group]
    return f"{folder if kind == 'full' else kind}/{prefix}{index:04d}.exr"


_DATASET_FILES = frozenset({"lights.lp", "heldout.lp", "mask.png", "meta.json"})
_DATASET_IMAGE = re.compile(r"^(images/\d{4,}|heldout/h\d{4,}|(specular|diffuse)/h?\d{4,})\.exr$")


def dataset_folder_entry(relative: str) -> bool:
    """Whether ``relative`` (a path inside the folder, ``images/0007.exr``) is a file a dataset folder
    holds: a folder written before manifests existed is replaceable when every file is one of these."""
    return relative in _DATASET_FILES or bool(_DATASET_IMAGE.match(relative))


def _json_default(value):
    """NumPy scalars and arrays -> plain Python for ``json.dumps``."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"meta value of type {type(value).__name__} is not JSON-serialisable")


FINGERPRINT_GRID = 8
"""A fingerprint's content digest of an image: the mean of each cell of an 8x8 grid over the image (fewer
cells along a side shorter than 8 pixels), channels averaged, scaled by the brightest cell, in 8 bits."""
FINGERPRINT_TOLERANCE = 12
"""Largest difference, in 8-bit levels of the brightest cell, between a recorded and a recomputed digest
cell that still counts as the same image: a cell averages 1/64 of the image, so decoders that differ by a
level or two per pixel (JPEG builds) agree well within it, while another object or a moved one differs by
tens of levels (the 32-light donut and sphere renders of the tests: 255)."""


def _text_digest(lines) -> str:
    return hashlib.sha256("\n".join(lines).encode("utf-8")).hexdigest()[:16]


def _image_digest(path: Path) -> str:
    """One image's content digest (see ``FINGERPRINT_GRID``): hex text of 8-bit cells, row by row."""
    from .resample import resample_image

    image = np.nan_to_num(read_image(path, linear=True, max_pixels=None).astype(np.float64),
                          nan=0.0, posinf=0.0, neginf=0.0)
    if image.ndim == 3:
        image = image.mean(axis=2)
    rows, columns = min(FINGERPRINT_GRID, image.shape[0]), min(FINGERPRINT_GRID, image.shape[1])
    cells = resample_image(image.astype(np.float32), columns, rows).astype(np.float64)  # each cell its area's mean
    top = cells.max()
    scaled = np.clip(cells / top, 0.0, 1.0) if top > 0 else np.zeros_like(cells)
    return bytes(np.rint(255.0 * scaled).astype(np.uint8).ravel()).hex()


def capture_fingerprint(dataset: ReflectanceField) -> dict:
    """What identifies the capture a dataset was loaded from, as JSON values for a field's report.

    The rule: the fingerprint describes the dataset's light file (``lights.lp`` or its one ``.lp``) and the
    image files it lists, all of them, as stored: never the held-out lights (``heldout.lp``, which ``fit``
    does not read) nor the split of ``--holdout-every`` (computed before it, so a field fitted to part of a
    capture matches the whole), and not the working size, ``--linear`` or the exposure. Keys: ``lights``
    (count), ``directions`` (a hash of the directions rounded to 4 decimals), ``names`` (a hash of the image
    names), ``size`` (the files' [width, height] in pixels), ``channels``, and ``digest``: the ``images``
    (indices of the first, middle and last image) and their ``cells`` (``_image_digest``; compared within
    ``FINGERPRINT_TOLERANCE``, not hashed, so another decoder of the same files still matches).

    Raises:
        InputError: the dataset was not loaded from a folder (no root or image names).
    """
    names = dataset.lights.filenames
    if dataset.root is None or not names:
        raise InputError("a capture's fingerprint needs a dataset loaded from a folder (its light file and images)")
    directions = np.round(np.asarray(dataset.lights.directions, dtype=np.float64), 4) + 0.0  # no -0.0
    size = (dataset.source or {}).get("size") or [dataset.width, dataset.height]
    count = len(names)
    indices = sorted({0, count // 2, count - 1})
    return {
        "lights": count,
        "directions": _text_digest(",".join(f"{v:.4f}" for v in row) for row in directions),
        "names": _text_digest(str(name).replace("\\", "/") for name in names),
        "size": [int(size[0]), int(size[1])],
        "channels": dataset.channels,
        "digest": {"images": indices, "cells": [_image_digest(dataset.root / names[i]) for i in indices]},
    }


def capture_differences(recorded: dict, current: dict) -> list[str]:
    """How the capture ``current`` (``capture_fingerprint``) differs from the ``recorded`` one, in words
    (empty: the same capture)."""
    differences = []
    if recorded.get("lights") != current["lights"]:
        differences.append(f"{current['lights']} lights, not {recorded.get('lights')}")
    elif recorded.get("directions") != current["directions"]:
        differences.append("other light directions")
    if recorded.get("names") != current["names"]:
        differences.append("other image names")
    if list(recorded.get("size") or []) != current["size"] or recorded.get("channels") != current["channels"]:
        width, height = (list(recorded.get("size") or []) + ["?", "?"])[:2]
        differences.append(f"{current['size'][0]}x{current['size'][1]} images of {current['channels']} channels, "
                           f"not {width}x{height} of {recorded.get('channels')}")
    digest, now = recorded.get("digest") or {}, current["digest"]
    if digest.get("images") == now["images"] and len(digest.get("cells") or []) == len(now["cells"]):
        for index, old, new in zip(now["images"], digest["cells"], now["cells"]):
            try:
                apart = np.abs(np.frombuffer(bytes.fromhex(old), np.uint8).astype(int)
                               - np.frombuffer(bytes.fromhex(new), np.uint8).astype(int))
            except ValueError:  # a digest of another shape (another grid)
                apart = np.array([255])
            if apart.size == 0 or apart.max() > FINGERPRINT_TOLERANCE:
                differences.append(f"other pixels (image {index} differs by up to "
                                   f"{int(apart.max()) if apart.size else 255} of 255 levels)")
                break
    return differences
