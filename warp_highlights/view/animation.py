"""Animation writers: frames of a highlight field relit along a light path (``light_paths``) written as GIF,
animated WebP or PNG (APNG), MP4 or a folder of frames.

The writers stream: frames come from any iterable (a generator of relit images) and at most a few
are held at a time. Frames are linear float images ``(H, W)`` or ``(H, W, 3)``, 1.0 = display white;
they are clipped to [0, 1] and sRGB-encoded for GIF, WebP, APNG, MP4 and PNG, kept linear for EXR.
WebP and APNG hold every frame in memory until the file is written (Pillow's encoders take them all
at once), which is checked against the memory available when the frame count is known. Every output
is written to a temporary sibling (file or folder) and renamed into place when complete, so a failed
or interrupted write leaves nothing behind and an existing output untouched.

Pillow is imported inside the functions that use it; MP4 is written through the ``imageio-ffmpeg``
package (the ``video`` extra), which brings its own ffmpeg.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from ..io.atomic import (
    atomic_file,
    atomic_folder,
    check_file_target,
    check_folder_target,
)
from ..io.images import encode_levels, write_image
from ..model.errors import InputError
from .light_paths import (
    checked_frame_count,
    finite_number,
)

__all__ = ["ANIMATION_OUTPUTS", "animation_kind", "check_animation_output", "write_animation"]

ANIMATION_OUTPUTS = (".gif, .webp, .apng, .mp4, or a folder (a name without suffix, or an existing folder) "
                     "of PNG/EXR frames")
"""What :func:`write_animation` can write, for messages and help texts."""


_GIF_PALETTE_FRAMES = 8  # frames sampled (the first ones) to build the one GIF palette
_GIF_PALETTE_PIXELS = 1 << 21  # at most this many sampled pixels go into the palette quantiser
_GIF_GRAY_ENTRIES = 32  # palette entries reserved for a gray ramp (highlights, shadows of later frames)
_FRAME_DIGITS = 4  # digits of frame numbers in file names, more when there are more frames
_FRAME_NAME = re.compile(r"^frame_\d+\.(png|exr)$")
_FRAMES_FORMATS = ("png", "exr")

DEFAULT_LONGER_SIDE = {"gif": 480, "webp": 480, "apng": 480, "mp4": 1920, "frames": None}
"""Longer side (pixels) of each panel of an animation whose size is not given; the field's size when it
is smaller, never grown. GIF, WebP and APNG go into web pages, slides and messages, where inline
animations are commonly at most 480 px wide, and their files grow with the pixels; MP4 at most 1080p, what
players and sites take; frames folders (for further work) keep the field's size (None)."""


# --- light paths ----------------------------------------------------------------------------------


# --- writers --------------------------------------------------------------------------------------


def animation_kind(path) -> str:
    """What :func:`write_animation` writes to ``path``, from its suffix.

    Args:
        path: ``*.gif``, ``*.webp``, ``*.apng``, ``*.mp4``, or a folder: an existing folder or a name
            without suffix.

    Returns:
        ``"gif"``, ``"webp"``, ``"apng"``, ``"mp4"`` or ``"frames"``.

    Raises:
        InputError: Any other suffix (e.g. ``.avi``); the message lists the supported outputs.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".gif", ".webp", ".apng", ".mp4"):
        return suffix[1:]
    if suffix == "" or path.is_dir():
        return "frames"
    raise InputError(f"{path}: cannot write an animation as {path.suffix!r}; supported: {ANIMATION_OUTPUTS}")


def default_animation_size(kind: str, width: int, height: int) -> tuple[int, int]:
    """(width, height) of an animation of ``kind`` (see :func:`animation_kind`) relit from a field of
    ``width`` x ``height`` when no size is given: shrunk to :data:`DEFAULT_LONGER_SIDE` on its longer side,
    the aspect ratio kept to half a pixel (so a field thinner than 1 : that side gets a one-pixel short
    side and a longer long one); the field's own size when it is no larger."""
    longest = DEFAULT_LONGER_SIDE[kind]
    if longest is None or max(width, height) <= longest:
        return width, height
    # the shorter side rounded down first, the longer one from it: at most ``longest``, the ratio kept to half a pixel
    if width >= height:
        shorter = max(1, math.floor(height * longest / width))
        return round(width * shorter / height), shorter
    shorter = max(1, math.floor(width * longest / height))
    return shorter, round(height * shorter / width)


def check_animation_output(path, *, overwrite: bool = False, frames_format: str = "png") -> str:
    """Every check :func:`write_animation` makes before the first frame, for a CLI to run up front;
    also that the output's folder exists and takes files (``write_animation`` creates a missing one).

    Args:
        path: The output (see :func:`animation_kind`).
        overwrite: Replace an existing output.
        frames_format: ``"png"`` or ``"exr"``; only folders take ``"exr"``.

    Returns:
        The output kind, ``"gif"``, ``"mp4"`` or ``"frames"``.

    Raises:
        InputError: Unknown output type, an existing output without ``overwrite``, a folder holding
            files this project did not write, a missing or unwritable folder, a bad ``frames_format``,
            or MP4 without ffmpeg.
    """
    path = Path(path)
    kind = animation_kind(path)
    if frames_format not in _FRAMES_FORMATS:
        raise InputError(f"frames_format must be 'png' or 'exr', got {frames_format!r}")
    if frames_format != "png" and kind != "frames":
        raise InputError(f"{path}: frames_format={frames_format!r} is for frame folders; give a folder name")
    _check_target(path, kind, overwrite=overwrite)
    if kind == "mp4":
        _imageio_ffmpeg()
    return kind


def write_animation(
    frames: Iterable,
    path,
    *,
    fps: float = 24.0,
    frame_count: int | None = None,
    overwrite: bool = False,
    progress: Callable[[int], object] | None = None,
    frames_format: str = "png",
) -> Path:
    """Write frames as an animated GIF, an MP4 video or a folder of numbered images, atomically.

    GIF: one 256-colour palette for every frame (adaptive, from the first 8 frames, plus a gray
    ramp; exact gray levels for grayscale frames), no dithering, so still regions never flicker; loops
    forever; every frame is kept, identical ones too. WebP (lossless) and APNG: every 8-bit sRGB
    colour exactly, looping forever, through Pillow. MP4: H.264 (libx264, yuv420p, BT.709), odd sizes padded to even by
    repeating the last row/column. Folder: ``frame_0000.png`` ... (8-bit sRGB) or ``frame_0000.exr`` (linear float32).

    Args:
        frames: Iterable of linear float images, ``(H, W)`` or ``(H, W, 3)``, all the same shape;
            1.0 = display white, values outside [0, 1] are clipped (except in EXR). Consumed once,
            streamed: a generator is fine.
        path: Output: ``*.gif``, ``*.webp``, ``*.apng``, ``*.mp4``, or a folder (see :func:`animation_kind`).
        fps: Frames per second; GIF takes at most 50 (its clock counts hundredths of a second, and
            the frame durations alternate to keep the average rate exact).
        frame_count: Number of frames ``frames`` yields, when known (default ``len(frames)`` where it
            has one); a different count is an error, and it sets the digits of frame file names.
        overwrite: Replace an existing output (a folder only when this project wrote it: its manifest
            lists every file in it, unchanged).
        progress: Called with the number of frames written so far, after each frame.
        frames_format: Folder output only: ``"png"`` or ``"exr"``.

    Returns:
        The written path.

    Raises:
        InputError: Unknown output type, existing output without ``overwrite``, no frames, a frame of
            another shape or with non-finite values (index named), a bad ``fps``, MP4 without ffmpeg
            or an ffmpeg failure. Nothing is written then (but a missing folder for the output, made
            first); an existing output stays as it was.
    """
    path = Path(path)
    animation_kind(path)  # an unknown output type is refused before any folder is made
    path.parent.mkdir(parents=True, exist_ok=True)
    kind = check_animation_output(path, overwrite=overwrite, frames_format=frames_format)
    fps = _checked_fps(fps, kind)
    if frame_count is None and hasattr(frames, "__len__"):
        frame_count = len(frames) or None  # an empty sequence is reported as "no frames" below
    if frame_count is not None:
        frame_count = checked_frame_count(frame_count)
    report = progress if progress is not None else (lambda done: None)
    checked = _checked_frames(frames, frame_count)
    if kind == "frames":
        with atomic_folder(path, kind="animation frames", overwrite=overwrite, legacy=_is_frame_name) as tmp:
            _write_frames(checked, tmp, frames_format=frames_format, frame_count=frame_count, progress=report)
    else:
        writer = {"gif": _write_gif, "mp4": _write_mp4, "webp": _write_webp, "apng": _write_apng}[kind]
        if kind in ("webp", "apng") and frame_count is not None:  # they hold every frame: sized from the first
            first = next(checked)
            _check_held_frames(frame_count, first.shape, kind)
            checked = itertools.chain([first], checked)
        with atomic_file(path, overwrite=overwrite) as tmp:
            writer(checked, tmp, fps=fps, progress=report)
    return path


# --- path helper functions ------------------------------------------------------------------------


# --- light path spec parsing ------------------------------------------------------------------------


# --- writer helper functions ------------------------------------------------------------------------


def _checked_fps(fps, kind: str) -> float:
    fps = finite_number(fps, "fps")
    if fps <= 0.0:
        raise InputError(f"fps must be positive, got {fps:g}")
    if kind == "gif" and not 100.0 / 65535.0 <= fps <= 50.0:
        raise InputError(f"a GIF plays at 0.0016 to 50 frames per second, got fps={fps:g}; write .mp4 for more")
    return fps


def _check_target(path: Path, kind: str, *, overwrite: bool) -> None:
    """InputError unless ``path`` may be written: new, or replaceable with ``overwrite`` (a frames
    folder only when this project wrote it)."""
    if kind == "frames":
        check_folder_target(path, overwrite=overwrite, legacy=_is_frame_name)
    else:
        if path.is_dir():
            raise InputError(f"{path} is a folder; choose a file name for the {kind.upper()} animation")
        check_file_target(path, overwrite=overwrite)


def _is_frame_name(relative: str) -> bool:
    """A frame file (``frame_0007.png``): how a frames folder written before manifests existed is recognised."""
    return bool(_FRAME_NAME.match(relative))


def _checked_frames(frames: Iterable, frame_count: int | None) -> Iterator[np.ndarray]:
    """Yield float32 frames, checking shape, finiteness and count; InputError names the frame index."""
    shape = None
    index = -1
    for index, frame in enumerate(frames):
        image = np.asarray(frame, dtype=np.float32)
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or 0 in image.shape:
            raise InputError(f"frame {index} has shape {image.shape}; expected (H, W) or (H, W, 3)")
        if shape is None:
            shape = image.shape
        elif image.shape != shape:
            raise InputError(f"frame {index} has shape {image.shape} but frame 0 has {shape}; all frames must match")
        if not np.isfinite(image).all():
            raise InputError(f"frame {index} has NaN or infinite values; fix the frames, nothing was written")
        yield image
    if index < 0:
        raise InputError("no frames to write; the light path or the frame source is empty")
    if frame_count is not None and index + 1 != frame_count:
        raise InputError(f"got {index + 1} frames but frame_count says {frame_count}")


def _write_frames(
    frames: Iterator[np.ndarray], folder: Path, *, frames_format: str, frame_count: int | None, progress
) -> None:
    """Numbered frames ``frame_0000.png`` ... into ``folder`` (more digits when there are more frames)."""
    digits = max(_FRAME_DIGITS, len(str(frame_count - 1))) if frame_count else _FRAME_DIGITS
    count = 0
    for count, image in enumerate(frames, start=1):
        write_image(folder / f"frame_{count - 1:0{digits}d}.{frames_format}", image)
        progress(count)
    if len(str(count - 1)) > digits:  # more frames than announced: pad every name to one width
        wide = len(str(count - 1))
        for i in range(count):
            old = folder / f"frame_{i:0{digits}d}.{frames_format}"
            old.rename(folder / f"frame_{i:0{wide}d}.{frames_format}")


def _srgb8(image: np.ndarray) -> np.ndarray:
    """Linear float frame -> uint8 sRGB codes (clipped to [0, 1])."""
    return encode_levels(image, 255, linear=False)


def _frame_durations(fps: float, ticks_per_second: float) -> Iterator[int]:
    """Frame durations in ticks (1/100 s for GIF, ms for WebP and APNG) whose running sum tracks
    ``k / fps`` (e.g. 4, 4, 5 centiseconds, or 42, 41, 42 ms, at 24 fps)."""
    for k in itertools.count():
        yield round(ticks_per_second * (k + 1) / fps) - round(ticks_per_second * k / fps)


def _gif_palette(samples: list[np.ndarray]):
    """One ``P``-mode palette image for all frames from sampled uint8 RGB frames; None for grayscale.

    Half the adaptive entries follow how often colours occur (large areas stay smooth), half treat
    every distinct colour alike (small highlights and their halos get colours too); a gray ramp fills
    the rest, for whites and shadows the sample did not have.
    """
    from PIL import Image

    if samples[0].ndim == 2:
        return None
    mosaic = np.concatenate(samples, axis=0)
    stride = max(1, math.ceil(math.sqrt(mosaic.shape[0] * mosaic.shape[1] / _GIF_PALETTE_PIXELS)))
    mosaic = np.ascontiguousarray(mosaic[::stride, ::stride])
    distinct = np.unique(mosaic.reshape(-1, 3), axis=0)
    side = math.ceil(math.sqrt(len(distinct)))
    distinct = np.concatenate([distinct, np.repeat(distinct[:1], side * side - len(distinct), axis=0)])
    half = (256 - _GIF_GRAY_ENTRIES) // 2
    colours = _median_cut(Image.fromarray(mosaic), half) + _median_cut(
        Image.fromarray(distinct.reshape(side, side, 3)), half
    )
    gray = np.rint(np.linspace(0, 255, 256 - len(colours) // 3)).astype(int)
    colours += [int(v) for v in np.repeat(gray, 3)]
    palette = Image.new("P", (1, 1))
    palette.putpalette(colours)
    return palette


def _median_cut(image, count: int) -> list[int]:
    """Flat RGB list of the (at most ``count``) colours median cut picks for a Pillow RGB image."""
    from PIL import Image

    adaptive = image.quantize(count, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    entries = adaptive.getpalette()
    used = sorted(index for _, index in adaptive.getcolors(256))
    return [value for i in used for value in entries[3 * i : 3 * i + 3]]


def _gif_image(levels: np.ndarray, palette):
    """uint8 frame -> Pillow image with the shared palette (nearest colour, no dithering)."""
    from PIL import Image

    image = Image.fromarray(np.ascontiguousarray(levels))
    if palette is None:
        return image  # "L": GIF's gray palette holds every level exactly
    return image.quantize(palette=palette, dither=Image.Dither.NONE)


def _write_gif(frames: Iterator[np.ndarray], path: Path, *, fps: float, progress) -> None:
    """Stream a looping GIF: global palette from the first frames, then every frame without a local palette."""
    from PIL import GifImagePlugin

    head = [_srgb8(image) for image in itertools.islice(frames, _GIF_PALETTE_FRAMES)]
    palette = _gif_palette(head)
    durations = _frame_durations(fps, 100.0)
    with open(path, "wb") as fp:
        for done, levels in enumerate(itertools.chain(head, map(_srgb8, frames)), start=1):
            image = _gif_image(levels, palette)
            if done == 1:
                header, _ = GifImagePlugin.getheader(image, info={"loop": 0, "duration": 10})
                fp.writelines(header)
            fp.writelines(GifImagePlugin.getdata(image, duration=10 * next(durations)))
            progress(done)
        fp.write(b";")


def _check_held_frames(frame_count: int, shape: tuple[int, ...], kind: str) -> None:
    """InputError when ``frame_count`` 8-bit frames of ``shape`` would not fit in the memory available."""
    from ..model.memory import check_memory

    frame_bytes = int(np.prod(shape[:2])) * (3 if len(shape) == 3 else 1)
    check_memory(2 * frame_count * frame_bytes, f"a {kind.upper()} of {frame_count} frames",
                 "write fewer frames, a .gif, an .mp4 or a frames folder",
                 detail=f"{frame_count} frames of {shape[1]}x{shape[0]}, held twice by the encoder")


def _pillow_frames(frames: Iterator[np.ndarray], progress) -> list:
    """Every frame as a Pillow image of 8-bit sRGB codes (RGB or L)."""
    from PIL import Image

    images = []
    for done, image in enumerate(frames, start=1):
        images.append(Image.fromarray(_srgb8(image)))
        progress(done)
    return images


def _write_webp(frames: Iterator[np.ndarray], path: Path, *, fps: float, progress) -> None:
    """Animated lossless WebP through Pillow, looping forever (identical neighbours become one frame of their summed
    duration)."""
    images = _pillow_frames(frames, progress)
    images = [image if image.mode == "RGB" else image.convert("RGB") for image in images]  # WebP has no grey mode
    images[0].save(path, format="WEBP", save_all=True, append_images=images[1:], lossless=True, quality=100, method=4,
                   duration=list(itertools.islice(_frame_durations(fps, 1000.0), len(images))), loop=0)


def _write_apng(frames: Iterator[np.ndarray], path: Path, *, fps: float, progress) -> None:
    """Animated PNG through Pillow, looping forever (identical neighbours become one frame of their summed duration)."""
    images = _pillow_frames(frames, progress)
    images[0].save(path, format="PNG", save_all=True, append_images=images[1:],
                   duration=list(itertools.islice(_frame_durations(fps, 1000.0), len(images))),
                   loop=0, default_image=False, disposal=0, blend=0)


def _imageio_ffmpeg():
    """The ``imageio_ffmpeg`` module with a usable ffmpeg executable; InputError when it is missing."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        raise InputError(
            "writing .mp4 needs the imageio-ffmpeg package: `pip install imageio-ffmpeg` (or the video extra), "
            "or write .gif, .webp, .apng or a frames folder"
        ) from None
    return imageio_ffmpeg


# libx264 at visually lossless quality, BT.709 limited range (what players assume for HD video),
# the index at the front so that a browser plays the file while it downloads.
_MP4_OPTIONS = [
    "-vf", "scale=out_color_matrix=bt709:out_range=tv", "-crf", "18",
    "-colorspace", "bt709", "-color_primaries", "bt709", "-color_trc", "bt709",
    "-movflags", "+faststart", "-f", "mp4",
]  # fmt: skip


def _rgb24_even(image: np.ndarray) -> np.ndarray:
    """Linear frame -> uint8 sRGB (H', W', 3) with even H', W' (last row/column repeated)."""
    levels = _srgb8(image)
    if levels.ndim == 2:
        levels = np.repeat(levels[:, :, None], 3, axis=2)
    height, width = levels.shape[:2]
    return np.ascontiguousarray(np.pad(levels, ((0, height % 2), (0, width % 2), (0, 0)), mode="edge"))


def _write_mp4(frames: Iterator[np.ndarray], path: Path, *, fps: float, progress) -> None:
    """H.264 video through imageio-ffmpeg's frame writer, checked afterwards: ffmpeg's errors become an InputError.

    imageio-ffmpeg does not look at ffmpeg's exit status, so the video is read back: it must hold every
    frame sent. ffmpeg writes its errors into a log file (its ``FFREPORT`` variable), not onto the
    terminal; the error line quotes them.
    """
    imageio_ffmpeg = _imageio_ffmpeg()
    first = _rgb24_even(next(frames))
    height, width = first.shape[:2]
    with tempfile.TemporaryDirectory(prefix="warp-highlights-ffmpeg-") as folder:
        log = Path(folder) / "ffmpeg.log"
        writer = imageio_ffmpeg.write_frames(
            str(path), (width, height), fps=fps, codec="libx264", pix_fmt_out="yuv420p", quality=None,
            macro_block_size=1, ffmpeg_log_level="quiet", output_params=_MP4_OPTIONS,
        )  # fmt: skip
        sent, stopped = 0, False
        try:
            with _ffmpeg_report(log):
                writer.send(None)  # starts ffmpeg
            for sent, levels in enumerate(itertools.chain([first], map(_rgb24_even, frames)), start=1):
                writer.send(levels)
                progress(sent)
        except OSError:
            stopped = True  # ffmpeg stopped reading; its log says why
        finally:
            writer.close()  # waits for ffmpeg to finish the file
        failure = "it stopped reading frames" if stopped else _mp4_frame_shortfall(imageio_ffmpeg, path, sent)
        if failure:  # the cause, where ffmpeg logged one
            raise InputError(f"ffmpeg could not write the MP4 video ({_ffmpeg_errors(log) or failure})")


@contextlib.contextmanager
def _ffmpeg_report(log: Path):
    """While ffmpeg starts: its errors go to ``log`` (the ``FFREPORT`` variable, ``:`` and ``\\`` escaped)."""
    escaped = str(log).replace("\\", "\\\\").replace(":", "\\:")
    before = os.environ.get("FFREPORT")
    os.environ["FFREPORT"] = f"file={escaped}:level=16"  # 16: errors only
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("FFREPORT", None)
        else:
            os.environ["FFREPORT"] = before


def _ffmpeg_errors(log: Path) -> str:
    """The first and last error lines of an ffmpeg report (cause and summary), without ``[codec @ 0x..]``; "" when
    none."""
    try:
        text = log.read_text("utf-8", "replace")
    except FileNotFoundError:
        return ""
    lines = text.splitlines()
    header = next((i for i, line in enumerate(lines) if line.startswith("Command line:")), None)
    if header is not None:
        lines = lines[header + 2 :]  # the report's header and ffmpeg's command line
    lines = [re.sub(r"^\[[^\]]*\]\s*", "", line).strip() for line in lines]
    lines = [line for line in lines if line]
    if not lines:
        return ""
    return lines[0] if len(lines) == 1 else f"{lines[0]}; {lines[-1]}"


def _mp4_frame_shortfall(imageio_ffmpeg, path: Path, sent: int) -> str:
    """"" when the video at ``path`` holds ``sent`` frames, else what is wrong with it."""
    try:
        held, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (RuntimeError, OSError):
        return "the file it wrote cannot be read back"
    if held != sent:
        return f"the file it wrote holds {held} of {sent} frames"
    return ""
