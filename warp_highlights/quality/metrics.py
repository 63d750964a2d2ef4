"""Image quality, the one place it is computed: PSNR on linear values, and PSNR and SSIM on images
as shown in 8-bit sRGB, the way RTI tools are compared (estimation, the move and learned checks,
evaluation and the benchmarks all score through here).

A layer of its own (``quality``): it needs io (the 8-bit sRGB encoding, ``io.images.display_rgb8``)
and the model (the thread pool), and both fit and relight score with it, which io, a layer of files,
should not hold. The kernels' device-side errors (``kernels.losses.clipped_mse``, ``kernels.scores``)
are turned into dB here by their callers, so the kernels import neither this nor io.

- ``psnr``: dB with peak 1 over the last two axes of linear values clipped to [0, 1], at most ``cap``.
- ``psnr_excluding_black``: (Q,) dB per image of a stack; NaN where both images are all black.
- ``psnr_8bit``: dB (peak 255, at most 100) of two 8-bit images.
- ``srgb_psnr``: dB of two linear images as shown in 8-bit sRGB (``display_rgb8``).
- ``ssim_8bit``: scikit-image's SSIM (7 x 7 window, smaller for tiny images) of two 8-bit RGB images.
- ``srgb_scores``: (Q,) PSNR and SSIM of linear image stacks shown in 8-bit sRGB.
- ``scoring_processes``: a scope in which ``srgb_scores`` of large stacks runs in worker processes.
"""

from __future__ import annotations

import contextlib
import logging
import signal

import numpy as np

from ..io.images import display_rgb8
from ..model.threads import core_count, parallel_map

__all__ = ["psnr", "psnr_8bit", "psnr_excluding_black", "psnr_of_mse", "scoring_processes", "srgb_psnr", "srgb_scores",
           "ssim_8bit"]


def psnr(image, reference, *, cap: float = 100.0) -> np.ndarray:
    """PSNR in dB with peak 1 over the last two axes, both clipped to [0, 1]; identical images give ``cap``."""
    a = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    b = np.clip(np.asarray(reference, dtype=np.float64), 0.0, 1.0)
    return psnr_of_mse(((a - b) ** 2).mean(axis=(-2, -1)), cap=cap)


def psnr_of_mse(mse, *, cap: float = 100.0) -> np.ndarray:
    """PSNR in dB, peak 1, of mean squared errors (e.g. ``kernels.losses.clipped_mse``'s); 0 gives ``cap``."""
    with np.errstate(divide="ignore"):
        return np.minimum(10.0 * np.log10(1.0 / np.asarray(mse, dtype=np.float64)), cap)


def psnr_excluding_black(images: np.ndarray, truth: np.ndarray, *, cap: float = 100.0) -> np.ndarray:
    """(Q,) PSNR in dB (peak 1, both clipped to [0, 1], at most ``cap``); NaN where both are all zero.

    Works on (Q, H, W) or (Q, H, W, C) stacks.
    """
    images, truth = np.asarray(images), np.asarray(truth)
    if images.shape != truth.shape:
        raise ValueError(f"images {images.shape} and truth {truth.shape} differ in shape")

    # one image in float64 at a time: float64 copies of a whole stack cost time and memory
    def one(q: int) -> tuple[float, bool]:
        a = np.clip(images[q].astype(np.float64).reshape(-1), 0.0, 1.0)
        b = np.clip(truth[q].astype(np.float64).reshape(-1), 0.0, 1.0)
        return float(((a - b) ** 2).mean()), bool(a.max() <= 0.0 and b.max() <= 0.0)

    mse, black = ((np.array(values) for values in zip(*parallel_map(one, range(len(images))))) if len(images)
                  else (np.zeros(0), np.zeros(0, bool)))
    with np.errstate(divide="ignore"):
        value = np.minimum(10.0 * np.log10(1.0 / mse), cap)
    return np.where(black, np.nan, value)


def psnr_8bit(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB (peak 255, at most 100 for identical images) of two 8-bit images of one shape."""
    a, b = np.asanyarray(a), np.asanyarray(b)
    # integers throughout (the move check scores 96 images a fit): the sum is exact, as float64's was
    if a.dtype == b.dtype == np.uint8 and not (np.ma.isMaskedArray(a) or np.ma.isMaskedArray(b)):
        difference = np.subtract(a, b, dtype=np.int16)
        mse = int(np.square(difference, dtype=np.int32).sum(dtype=np.int64)) / max(difference.size, 1)
    else:
        mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return 100.0 if mse == 0 else min(100.0, 10.0 * np.log10(255.0**2 / mse))


def srgb_psnr(image, reference) -> float:
    """PSNR in dB (peak 255, at most 100 for identical images) of two linear images as shown in 8-bit sRGB
    (``display_rgb8``)."""
    return psnr_8bit(display_rgb8(image), display_rgb8(reference))


def ssim_8bit(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of 8-bit RGB image ``a`` against ``b`` (scikit-image, over the colour channels): a 7 x 7
    window, the largest odd one for images under 7 pixels, 1 for images under 3."""
    from skimage.metrics import structural_similarity

    small = min(a.shape[0], a.shape[1])
    window = min(7, small if small % 2 else small - 1) if small >= 3 else None  # odd, as SSIM needs
    return (1.0 if window is None
            else float(structural_similarity(b, a, channel_axis=-1, data_range=255, win_size=window)))


def srgb_scores(images: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q,) PSNR (dB, peak 255) and (Q,) SSIM of linear images shown as 8-bit sRGB (``display_rgb8``).

    Works on (Q, H, W) or (Q, H, W, C) stacks; PSNR is capped at 100 dB for identical images. Inside
    :func:`scoring_processes`, a stack of at least ``PROCESSES_FROM`` images is scored in its worker
    processes (the same values).
    """
    # the sRGB codes in threads (NumPy's loops let go of the GIL)
    codes = parallel_map(lambda q: (display_rgb8(images[q]), display_rgb8(truth[q])), range(len(images)))
    scores = _SCORING.map(codes) if _SCORING is not None and len(codes) >= PROCESSES_FROM else None
    if scores is None:  # SSIM's many short steps hold the GIL: threads reach a third of what processes do on 16 cores
        scores = parallel_map(_code_scores, codes)
    scores = np.array(scores, dtype=np.float64).reshape(-1, 2)
    return scores[:, 0].copy(), scores[:, 1].copy()


def _code_scores(pair: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """PSNR and SSIM of one pair of 8-bit images (in a worker process, or a thread)."""
    return psnr_8bit(*pair), ssim_8bit(*pair)


def _scores_of_chunk(pairs: list) -> list:
    return [_code_scores(pair) for pair in pairs]


SCORING_PROCESSES = 4
"""Worker processes of :func:`scoring_processes`, at most one per core. Scoring 124 image pairs of 480x270
on 16 cores, 8 or 16 processes were barely faster than 4, and threads were slower than processes (the
scores hold the GIL). Beyond 4, the parent's encoding and the pipes are the limit, and each process
holds its own copy of NumPy, SciPy and scikit-image."""

PROCESSES_FROM = 32
"""Images from which ``srgb_scores`` hands a stack to the worker processes: below, the pipes and the
processes' start (once per scope) cost more than the processes save."""

_SCORING: _ScoringPool | None = None


class _ScoringPool:
    """Worker processes for the scores, spawned on the first stack that needs them; ``map`` returns
    None (the caller scores in threads) where processes cannot be had (e.g. inside a daemonic process)."""

    def __init__(self, workers: int):
        self.workers = workers
        self.executor = None
        self.failed = False

    def map(self, codes: list) -> list | None:
        if self.failed:
            return None
        try:
            if self.executor is None:
                import multiprocessing
                from concurrent.futures import ProcessPoolExecutor

                self.executor = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                                    initializer=_ignore_interrupts)
                logging.getLogger(__name__).debug(f"scoring in {self.workers} worker processes")
            size = max(1, -(-len(codes) // (4 * self.workers)))  # a few chunks a process: even ends, few messages
            chunks = [codes[i : i + size] for i in range(0, len(codes), size)]
            return [score for chunk in self.executor.map(_scores_of_chunk, chunks) for score in chunk]
        except Exception as error:  # noqa: BLE001 (no processes here: threads do the same work)
            self.failed = True
            logging.getLogger(__name__).debug(f"scores in threads: worker processes unavailable ({error})")
            self.close()
            return None

    def close(self) -> None:
        executor, self.executor = self.executor, None
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)


def _ignore_interrupts() -> None:
    """In a worker process: Ctrl-C is the parent's to handle (no traceback per worker on the terminal)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def scoring_processes(workers: int | None = None):
    """Within: ``srgb_scores`` of ``PROCESSES_FROM`` images or more runs in ``workers`` processes
    (default ``SCORING_PROCESSES``, at most one per core; one core: threads), spawned on first need
    and stopped on leaving. Nested scopes share the outer one's processes.

    The processes are started by ``multiprocessing``'s spawn, which imports the main module again:
    a script needs its ``if __name__ == "__main__":`` guard (the ``evaluate`` command has one; a
    program read from stdin cannot be imported, and scores in threads after its workers' errors)."""
    global _SCORING
    if _SCORING is not None:
        yield
        return
    count = min(workers or SCORING_PROCESSES, core_count())
    _SCORING = _ScoringPool(count) if count >= 2 else None
    try:
        yield
    finally:
        pool, _SCORING = _SCORING, None
        if pool is not None:
            pool.close()
