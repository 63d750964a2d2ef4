"""The residual's rate search: how many basis images each stack keeps and how finely each is quantised so
that the whole field file fits its size budget, every kept image adding the same squared RGB error.
The bytes are the compressed codes as the field file stores them: estimated from sampled rows,
calibrated on whole images, and measured exactly before the answer is taken.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..io.codes import CompressedCodes, compressed_chunk, stored_bytes, stored_codes
from ..io.fieldfile import array_entry_bytes
from ..model.gaussians import GaussianParams
from ..model.residual import (
    LowRankStack,
    code_levels,
)
from ..model.threads import (
    NUMPY_THREADS,
    cancel_and_wait,
    gather,
    mapped_empty,
    parallel_map,
    submit,
)
from .inputs import BAND_VALUES
from .principal import PrincipalImages
from .quantise import clamped_steps, quantised_codes

__all__ = ["FILE_BYTES", "LIGHT_BYTES", "RateSample", "StackPlan", "allocate", "allocate_steps", "component_bytes",
           "entry_bytes", "finest_within", "gaussian_bytes", "quantised_bytes", "sampled_rows"]

_TASKS_PER_THREAD = 4
"""The rate search hands out a group's images in about this many tasks per thread (one small image a task
costs more to hand out than to compress)."""
_STORED_GROUP_BYTES = 1 << 26
"""The rate search's stored codes made on a device: up to this many bytes a group (64 MiB, two groups held),
so that small images come in a few launches and copies rather than one round of them per ``NUMPY_THREADS``
images; at least ``NUMPY_THREADS`` images a group (one per compressing thread) whatever their size."""
_PARAMETER_BYTES = 24  # six float32 per Gaussian
_PATH_BYTES = 12  # delta and centre (float32) per retargeted Gaussian
FILE_BYTES = 6144
"""The header, the zip's own records and the rest of a field file's small entries, bytes."""
LIGHT_BYTES = 48
"""A light's direction (float64) and its two faces (int32), bytes."""
_BUDGET_SLACK = 0.01  # allocate_steps stops once the bytes are within this share under the budget
_SEARCH_STEPS = 16  # _search's evaluations at most
_SEARCH_DEPTH = 35.0
"""The search's finest distortion: this far (natural log) under the top energy, far below any 16-bit
quantisation noise."""
_SEARCH_START = 12.0
"""A first search starts this far under the top energy: where the default budget binds, the searches of
``benchmarks/bench_residual.py`` and ``bench_quality.py`` end about this far under."""
_SEARCH_STRIDE = 8.0  # a secant step moves the log distortion at most this far ...
_SEARCH_MIN_STEP = 0.05  # ... and at least this far
_MODEL_TOLERANCE = 1e-9  # _modelled_distortion's roots (offset in bits, log distortion) to within this
_MODEL_OFFSET_RANGE = 40.0  # the model's constant bits a value is sought within this far of none
_SEARCH_NARROWEST = 1e-3
"""_search stops once the bracket is narrower than this (log distortion: a 0.1% change of the steps' squares)."""
_SEARCH_GUARD = 0.02  # a regula falsi step within this share of the bracket from an end bisects instead
_BYTES_PER_HALVING = 1.0 / 8.0
"""Stored bytes a value gains per halving of its step (one bit: the high-rate rule): the first step's slope
where the high-rate model of the bytes (``_modelled_distortion``) fits no offset."""
_SLOPE_FLOOR = 0.02  # the smallest fall of log bytes per unit of log distortion a secant step assumes
_RATE_BAND_ROWS = 8  # the rate search compresses bands of this many whole rows ...
_RATE_SHARE = 0.0625
"""... together this share of the rows. The sampled bytes are calibrated on whole images, so they need to
follow the bytes' trend, not their level; a 16th of the rows leaves a margin over the 32nd that already
follows it once calibrated."""
_RATE_MIN_VALUES = 1 << 13
"""... and at least this many values a basis image; else every row (a small image is compressed whole)."""
_RATE_ROUNDS = 3
"""Searches on the calibrated sampled bytes, each followed by an exact measurement, before a search on exact bytes."""
_ESTIMATE_SLACK = 0.004
"""The searches on calibrated sampled bytes stop within this share of the middle of the budget's window (their
errors are a fraction of a percent)."""
_FIRST_SLACK = 0.05
"""The first search, on uncalibrated sampled bytes (a few percent off), stops within this share under the budget."""
_CALIBRATION_EVERY = 8
"""The first search's answer: every this many-th kept image compressed whole, to scale the sampled bytes ..."""
_CALIBRATION_LEAST = 8  # ... at least this many images a stack (every image of a stack of fewer than twice as many)
_FINEST_MARGIN = 0.05
"""``finest_within`` trusts sampled bytes this far under the budget (uncalibrated samples are a few percent off the
whole images; a wrong "plain" choice is measured on every row after all)."""


def entry_bytes(array: np.ndarray) -> int:
    """Bytes of ``array`` as the field file stores it (``io.fieldfile.array_entry_bytes``)."""
    return array_entry_bytes(array)


def gaussian_bytes(estimated: GaussianParams, retargeted: GaussianParams) -> int:
    """Stored bytes of a field's Gaussians and paths before compress (an upper bound of what they take)."""
    return (int(estimated.active.sum()) * (_PARAMETER_BYTES + 2)
            + int(retargeted.active.sum()) * (_PARAMETER_BYTES + _PATH_BYTES) + 2 * len(estimated.active))


def component_bytes(stack: LowRankStack) -> np.ndarray:
    """(k,) stored bytes of each basis image of ``stack``: its codes' Blosc chunk (planes first, as the
    file stores them: ``io.codes``), its range and its per-light weights."""
    return np.array([stored_bytes(code.transpose(2, 0, 1)) + 8 + 4 * len(stack.weights) for code in stack.codes],
                    dtype=np.float64)


@dataclass(frozen=True)
class StackPlan:
    """One stack's share of the rate-distortion allocation: its principal images, the squared RGB
    error per unit of its energy (``gain``), and how many basis images it may and must keep."""

    principal: PrincipalImages
    gain: float
    most: int
    floor: int = 0
    # the last exact measurement's chunks
    chunks: CompressedCodes = dataclasses.field(default_factory=CompressedCodes, repr=False, compare=False)

    @property
    def energies(self) -> np.ndarray:
        """(most,) the weighted energies (``gain`` E) of the basis images the plan may keep."""
        return self.gain * self.principal.energies[1 : self.most + 1]

    def steps(self, distortion: float, levels: int) -> np.ndarray:
        """Quantisation steps of the basis images kept at ``distortion`` (squared RGB error, normalised
        units, that each kept image may add; an image of energy below it is dropped, which removes
        less): ``step = sqrt(12 D / (gain E M))``, uniform noise of variance step^2 / 12 over its M
        values costing gain E M step^2 / 12 = D. The floor's images, kept whatever D, at 8 bits over their range."""
        energies = self.energies
        chosen = int(np.count_nonzero(energies > distortion))
        kept = max(chosen, min(self.floor, len(energies)))
        pixels = self.principal.values
        steps = np.sqrt(12.0 * distortion / np.maximum(energies[:kept] * pixels, 1e-300))
        steps[chosen:] = self.principal.spans[chosen:kept] / 255  # the floor's: 8 bits over the whole range
        return np.maximum(steps, self.principal.spans[:kept] / levels)

    def distortion(self, steps: np.ndarray) -> float:
        """Squared RGB error (normalised units) the model of ``steps`` predicts for this stack: each kept
        image's quantisation noise, ``gain E M step^2 / 12``, plus the energy of every image left out."""
        energies = self.gain * self.principal.energies[1:]
        kept = len(steps)
        pixels = self.principal.values
        return float(np.sum(energies[:kept] * pixels * np.square(steps) / 12.0) + np.sum(energies[kept:]))

    def changing_values(self, steps: np.ndarray, levels: int) -> int:
        """Values of the kept images whose step follows the distortion (not held at the codes' finest,
        ``span / levels``): what a change of the distortion re-quantises."""
        floors = self.principal.spans[: len(steps)] / levels
        return int(np.count_nonzero(steps > floors * (1.0 + 1e-9))) * self.principal.values


def sampled_rows(height: int, width: int, planes: int) -> np.ndarray:
    """Rows of an (H, W, P) basis image that the rate search compresses: bands of ``_RATE_BAND_ROWS``
    whole rows, one in the middle of each of equal strips of the image, together ``_RATE_SHARE`` of
    the rows and at least ``_RATE_MIN_VALUES`` values; every row where that is half of them or more."""
    wanted = max(int(np.ceil(_RATE_SHARE * height)), int(np.ceil(_RATE_MIN_VALUES / max(width * planes, 1))))
    bands = int(np.ceil(wanted / _RATE_BAND_ROWS))
    if 2 * bands * _RATE_BAND_ROWS >= height:
        return np.arange(height)
    centres = (np.arange(bands) + 0.5) * height / bands  # one band in the middle of each of ``bands`` equal strips
    starts = np.clip(np.round(centres - 0.5 * _RATE_BAND_ROWS), 0, height - _RATE_BAND_ROWS).astype(np.int64)
    return (starts[:, None] + np.arange(_RATE_BAND_ROWS)).ravel()


class RateSample:
    """What the rate search compresses of a ``PrincipalImages``' first ``count`` basis images: their
    ``sampled_rows`` (every row where ``whole``), planes first and stored as the file stores them
    (``io.codes``: a band's first row less the row above it, quantised for that), quantised from
    the whole images' minima and spans as ``quantise_basis`` does. ``bytes`` estimates a quantisation's
    stored bytes from them; on every row it is exactly ``component_bytes`` of ``quantise.quantised_stack``.
    Where the principal images are held on a device (``PrincipalImages.held``), they are quantised
    and stored there, and the host compresses what comes back."""

    def __init__(self, principal: PrincipalImages, count: int, *, whole: bool = False):
        height, width, planes = principal.shape
        self.shape = (count,) + tuple(principal.shape)
        self.held = principal.held  # the images quantised there; else the host's copy, here:
        self.images = None if self.held is not None else principal.directions[1 : 1 + count].reshape(self.shape)
        self.low = principal.lows[:count].astype(np.float64)  # float64, as quantise_basis has them
        self.span = principal.highs[:count].astype(np.float64) - self.low
        if whole:
            self.rows, self.counted = slice(None), slice(None)
            self.stored_rows = np.arange(height)
            self.above = self.stored_rows - 1
        else:  # each band quantised with the row above it, which its first row's stored difference needs
            counted = sampled_rows(height, width, planes)
            above = np.setdiff1d(counted - 1, counted)
            self.rows = np.union1d(counted, above[above >= 0])
            self.counted = np.isin(self.rows, counted)
            positions = np.flatnonzero(self.counted)
            # the rows the sample counts, each less the row before it in ``rows``
            self.stored_rows = self.rows[positions]
            self.above = np.where(positions > 0, self.rows[np.maximum(positions - 1, 0)], -1)
        # whole image bytes per sampled byte
        self.scale = 1.0 if whole else height / int(np.count_nonzero(self.counted))
        self.values = (height if whole else len(self.rows)) * width * planes  # values an image quantises
        self.per_image = 8 + 4 * principal.light_count  # the range and the per-light weights
        self._stored: np.ndarray | None = None  # two groups of the held images' stored codes, host memory used again
        # (image, step, bits) -> (compressed bytes, content key or None): what was measured
        self._memo: dict[tuple, tuple] = {}

    @property
    def exact(self) -> bool:
        return self.scale == 1.0

    def bytes(self, steps: np.ndarray, *, bits: int, keep: CompressedCodes | None = None,
              calibration: float = 1.0) -> float:
        """Stored bytes of the first len(``steps``) basis images quantised with ``steps`` at ``bits``
        (``chunks``, scaled to the whole images and by ``calibration``, the whole images' bytes per
        scaled sampled byte, with each image's range and weights). ``keep`` (an ``exact`` sample only):
        hold the images' compressed chunks there, in place of what it held, for the field writer."""
        return (calibration * float(self.chunk_bytes(steps, bits=bits, keep=keep).sum()) * self.scale
                + self.per_image * len(steps))

    def chunk_bytes(self, steps: np.ndarray, *, bits: int, keep: CompressedCodes | None = None,
                 images: np.ndarray | None = None) -> np.ndarray:
        """(len(``steps``),) int64 stored bytes (``io.codes.chunk_size``) of each of the first len(``steps``) basis
        images at the sample's rows (not scaled), quantised with ``steps`` at ``bits``; ``images``: only these indices
        (the others 0). Compressed in threads (Blosc lets go of the GIL off the main thread). An image is compressed
        once per step and bits: a measurement remembers each image's bytes, and a later one at the same step
        takes them instead of compressing it again (and, where ``keep`` is given, its chunk where ``keep``
        still holds it: else the field writer compresses that image, if it is kept)."""
        if keep is not None and not self.exact:
            raise ValueError("only a sample of every row can keep its compressed chunks")
        count = len(steps)
        lengths = np.zeros(count, np.int64)
        if not count:
            if keep is not None:
                keep.keep({})
            return lengths
        levels = code_levels(bits)
        steps = clamped_steps(steps, self.span[:count], levels)
        wanted = np.arange(count) if images is None else np.unique(np.asarray(images, np.int64))
        if len(wanted) and (wanted[0] < 0 or wanted[-1] >= count):
            raise IndexError(f"images {wanted.tolist()} are not all among the {count} measured")
        chunks, measure = {}, []
        for index in wanted.tolist():
            known = self._memo.get((index, float(steps[index]), bits))
            if known is None:
                measure.append(index)
                continue
            lengths[index] = known[0]
            chunk = None if keep is None or known[1] is None else keep.held(known[1])
            # else not held (dropped, or never kept): the field writer compresses it, where it is kept
            if chunk is not None:
                chunks[known[1]] = chunk
        for index, length, key, chunk in self._measured(np.asarray(measure, np.int64), steps, bits,
                                                        keyed=keep is not None):
            lengths[index] = length
            self._memo[(index, float(steps[index]), bits)] = (length, key)
            if keep is not None:
                chunks[key] = chunk
        if keep is not None:
            keep.keep(chunks)
        return lengths

    def release(self) -> None:
        """Let go of the host memory the device's stored codes come down into (two groups of images: 1 GB
        for a 4K stack's whole chroma images), made again by the next measurement."""
        self._stored = None

    def _measured(self, indices: np.ndarray, steps: np.ndarray, bits: int, *, keyed: bool) -> list:
        """(index, compressed bytes, content key or None, chunk or None) of each image ``indices`` (sorted),
        the key and chunk where ``keyed``; runs of consecutive images a few at a time."""
        if not len(indices):
            return []
        kind = np.uint8 if bits == 8 else np.uint16

        def compress(index: int, image: np.ndarray) -> tuple:
            chunk = compressed_chunk(image)
            return (index, len(chunk), CompressedCodes.key(image), chunk) if keyed else (index, len(chunk), None, None)

        if self.held is not None:
            return self._stored_from_device(indices, steps, bits,
                                              lambda images: [compress(index, image) for index, image in images])
        levels = code_levels(bits)

        # a few images in a few NumPy calls (small images: a call per image would hold the GIL more than it works)
        def group(images: slice) -> list:
            # (c, P, rows, W), rounded in float64 as quantise_basis rounds
            rows = self.images[images][:, self.rows].transpose(0, 3, 1, 2)
            codes = quantised_codes(rows, self.low[images], steps[images], levels, out=np.empty(rows.shape, kind))
            stored = stored_codes(codes)[..., self.counted, :]  # each band's first row less the row above it
            return [compress(images.start + offset, image) for offset, image in enumerate(stored)]

        size = max(1, min(-(-len(indices) // NUMPY_THREADS), BAND_VALUES // max(self.values, 1)))
        return [entry for part in parallel_map(group, _index_runs(indices, size)) for entry in part]

    def _stored_from_device(self, indices: np.ndarray, steps: np.ndarray, bits: int, chunks) -> list:
        """The entries ``chunks`` makes of the held images ``indices`` (it takes a list of (index, stored codes) and
        returns an entry for each), the images quantised with ``steps`` and stored at the sample's rows: a
        group of at least ``NUMPY_THREADS`` images (more, up to ``_STORED_GROUP_BYTES``, where they are
        small; a launch for each run of consecutive images) at a time made there (``HeldDirections.stored``)
        into one of two slots of host memory, compressed in threads (a few images a task) while the next
        group is made and copied into the other."""
        _, width, planes = self.shape[1:]
        tail = (planes,) + ((2,) if bits == 16 else ()) + (len(self.stored_rows), width)
        per_image = int(np.prod(tail))
        group = min(len(indices), max(1, NUMPY_THREADS, _STORED_GROUP_BYTES // max(per_image, 1)))
        if self._stored is None or self._stored.size < 2 * group * per_image:
            self._stored = None
            self._stored = mapped_empty(2 * group * per_image, np.uint8)
        results, pending = [], [[], []]
        try:
            for number, runs in enumerate(_packed(_index_runs(indices, group), group)):
                slot, count = number % 2, sum(run.stop - run.start for run in runs)
                gather(pending[slot])  # the slot's last group compressed: free to fill again
                offset = slot * group * per_image
                stored = self._stored[offset : offset + count * per_image].reshape((count,) + tail)
                at = 0
                for run in runs:  # a run of consecutive images a launch
                    size = run.stop - run.start
                    self.held.stored(1 + run.start, self.low[run], steps[run], bits, self.stored_rows, self.above,
                                     out=stored[at : at + size])
                    at += size
                images = list(zip([index for run in runs for index in range(run.start, run.stop)], stored))
                # a few images a task: small images cost more to hand out than to compress
                share = max(1, -(-len(images) // (_TASKS_PER_THREAD * NUMPY_THREADS)))
                pending[slot] = []
                # the shared threads; each tracked as it is submitted (Ctrl-C)
                for start in range(0, len(images), share):
                    pending[slot].append(submit(chunks, images[start : start + share]))
                    results.append(pending[slot][-1])
        except BaseException:  # an error or Ctrl-C: the chunks not started dropped, the running ones waited for
            cancel_and_wait(results)
            raise
        return [entry for part in gather(results) for entry in part]


def _packed(runs: list[slice], size: int) -> list[list[slice]]:
    """Consecutive ``runs`` (each at most ``size`` long) in groups of at most ``size`` indices together
    (every 8th image of a stack, one a run, still compressed ``size`` at a time)."""
    groups, group, count = [], [], 0
    for run in runs:
        if group and count + run.stop - run.start > size:
            groups.append(group)
            group, count = [], 0
        group.append(run)
        count += run.stop - run.start
    if group:
        groups.append(group)
    return groups


def _index_runs(indices: np.ndarray, size: int) -> list[slice]:
    """Sorted ``indices`` as slices of consecutive indices, each at most ``size`` long."""
    breaks = np.flatnonzero(np.diff(indices) != 1) + 1
    runs = []
    for run in np.split(indices, breaks):
        first, last = int(run[0]), int(run[-1]) + 1
        runs += [slice(start, min(start + size, last)) for start in range(first, last, size)]
    return runs


def quantised_bytes(principal: PrincipalImages, steps: np.ndarray, *, bits: int,
                    keep: CompressedCodes | None = None) -> float:
    """Stored bytes of ``principal``'s first basis images quantised with ``steps`` as
    ``quantise.quantised_stack`` does (``component_bytes``, without fitting the weights): every row
    compressed (the chunks held in ``keep`` when given)."""
    return RateSample(principal, len(steps), whole=True).bytes(steps, bits=bits, keep=keep)


def allocate_steps(plans: list[StackPlan], budget_bytes: float, *, bits: int) -> list[np.ndarray]:
    """Quantisation steps of every plan's basis images within ``budget_bytes``: the smallest common
    distortion whose images fit (reverse water-filling: every kept image adds the same squared RGB
    error, so the bytes go where they remove the most error). See :func:`allocate`."""
    return allocate(plans, budget_bytes, bits=bits)[1]


def allocate(plans: list[StackPlan], budget_bytes: float, *, bits: int) -> tuple[float, list[np.ndarray]]:
    """``allocate_steps``' choice and its common distortion (squared RGB error per kept image,
    normalised units; ``inf`` for the floor alone).

    Each plan's ``chunks`` keeps the chunks of the last measurement made on every row (the field
    writer stores them rather than compressing the same codes again). The compressed bytes fall with the
    log distortion, nearly linearly: ``_search`` takes secant steps on log bytes, then Illinois regula
    falsi once the budget is bracketed. It runs on bytes estimated from ``sampled_rows`` (a sixteenth
    of a large image's rows), each plan's sampled bytes scaled by its whole images' bytes per sampled
    byte: first by none, then by those of every ``_CALIBRATION_EVERY``-th kept image compressed whole at
    that search's answer (the samples' bands run 2-6% over or under whole images, alike for every
    image of a capture), then by those of the exact bytes of the last answer, until the exact bytes
    are within 1% under the budget or ``_RATE_ROUNDS`` searches have run; then the search runs on the
    exact bytes. The budget holds for the exact bytes (unless even the floor alone exceeds it). No
    image is compressed twice at the same step (``RateSample.chunk_bytes``); the whole images' host buffers
    are let go after each measurement."""
    levels = code_levels(bits)
    top = _top_energy(plans)
    if top <= 0 or budget_bytes <= 0:  # the floor alone
        return np.inf, [plan.steps(np.inf, levels) for plan in plans]
    samples = _rate_samples(plans)
    if all(sample.exact for sample in samples):
        return _search(plans, budget_bytes, levels, top, lambda steps: sum(sample.bytes(step, bits=bits,
                                                                                        keep=plan.chunks)
                                                                           for plan, sample, step in zip(plans, samples,
                                                                                                         steps)))[:2]
    wholes = [sample if sample.exact else RateSample(plan.principal, sample.shape[0], whole=True)
              for plan, sample in zip(plans, samples)]
    ratios = np.ones(len(plans))  # each plan's whole-image bytes per (scaled) sampled byte

    def estimated(steps: list[np.ndarray]) -> float:  # a sample of every row keeps its chunks, as ``exact`` does
        return sum(sample.bytes(step, bits=bits, keep=plan.chunks if sample.exact else None, calibration=calibration)
                   for plan, sample, step, calibration in zip(plans, samples, steps, ratios))

    def exact(steps: list[np.ndarray]) -> float:
        try:
            return sum(whole.bytes(step, bits=bits, keep=plan.chunks)
                       for plan, whole, step in zip(plans, wholes, steps))
        finally:
            for whole in wholes:
                whole.release()

    def ratio(plan: StackPlan, sample: RateSample, whole: RateSample, step: np.ndarray,
              images: np.ndarray | None = None) -> float:
        """Whole bytes per scaled sampled byte of ``images`` (all: an exact measurement's, remembered, nothing
        compressed or kept again; a subset: compressed whole now, their chunks kept for the exact measurement that
        follows)."""
        # remembered: nothing compressed again
        sampled = float(sample.chunk_bytes(step, bits=bits, images=images).sum()) * sample.scale
        try:
            exact_bytes = float(whole.chunk_bytes(step, bits=bits, images=images,
                                               keep=None if images is None else plan.chunks).sum())
        finally:
            whole.release()
        return exact_bytes / sampled if sampled > 0 else 1.0

    # everything kept, as finely as the codes go
    finest = [plan.steps(np.exp(np.log(top) - _SEARCH_DEPTH), levels) for plan in plans]
    # where to calibrate: near the answer will do
    start, _, _ = _search(plans, budget_bytes, levels, top, estimated, slack=_FIRST_SLACK)
    steps = [plan.steps(np.exp(start), levels) for plan in plans]
    for index, (plan, sample, whole, step) in enumerate(zip(plans, samples, wholes, steps)):
        if not sample.exact and len(step):
            every = max(1, min(_CALIBRATION_EVERY, len(step) // _CALIBRATION_LEAST))
            ratios[index] = ratio(plan, sample, whole, step, np.arange(every // 2, len(step), every))
    # the estimates' window in the middle of the budget's
    aim = (1.0 - 0.5 * (_BUDGET_SLACK - _ESTIMATE_SLACK)) * budget_bytes
    for _ in range(_RATE_ROUNDS):
        log_distortion, steps, _ = _search(plans, aim, levels, top, estimated, start=start, slack=_ESTIMATE_SLACK)
        stored = exact(steps)
        if (1.0 - _BUDGET_SLACK) * budget_bytes <= stored <= budget_bytes:
            return log_distortion, steps
        if stored <= budget_bytes and all(len(a) == len(b) and np.array_equal(a, b) for a, b in zip(steps, finest)):
            return log_distortion, steps  # nothing more to buy
        for index, (plan, sample, whole, step) in enumerate(zip(plans, samples, wholes, steps)):
            if not sample.exact and len(step):
                ratios[index] = ratio(plan, sample, whole, step)
        start = log_distortion
    # the sample misled the search (a rare image's bytes): search on exact bytes
    return _search(plans, budget_bytes, levels, top, exact, start=start)[:2]


def _top_energy(plans: list[StackPlan]) -> float:
    """The largest weighted energy of any basis image the plans may keep (0 when none)."""
    return max((float(plan.energies.max()) for plan in plans if plan.energies.size), default=0.0)


def _rate_samples(plans: list[StackPlan]) -> list[RateSample]:
    """The ``RateSample`` of each plan's images that any distortion may keep."""
    return [RateSample(plan.principal, max(int(np.count_nonzero(plan.energies > 0)),
                                           min(plan.floor, len(plan.energies)))) for plan in plans]


def finest_within(plans: list[StackPlan], budget_bytes: float, *, bits: int) -> tuple[float, list[np.ndarray]] | None:
    """``allocate``'s choice where it is plain from the sampled bytes alone: every image kept as finely as
    ``bits``-bit codes go, when those bytes are at least ``_FINEST_MARGIN`` under the budget (then
    ``allocate`` ends there too, unless the sample misjudges the whole images by that much); else None.
    Checked on every row only by ``allocate``: for a caller that may not keep this choice. Small images,
    which the rate search compresses whole, are left to ``allocate`` (nothing to save, one compress to lose)."""
    levels = code_levels(bits)
    top = _top_energy(plans)
    samples = _rate_samples(plans)
    if top <= 0 or budget_bytes <= 0 or all(sample.exact for sample in samples):
        return None
    log_distortion = np.log(top) - _SEARCH_DEPTH
    steps = [plan.steps(np.exp(log_distortion), levels) for plan in plans]
    sampled = sum(sample.bytes(step, bits=bits) for sample, step in zip(samples, steps))
    return (log_distortion, steps) if sampled <= (1.0 - _FINEST_MARGIN) * budget_bytes else None


def _search(plans: list[StackPlan], limit: float, levels: int, top: float, measure, *,
            start: float | None = None, slack: float = _BUDGET_SLACK) -> tuple[float, list[np.ndarray], float]:
    """(log distortion, steps, their measured bytes) of the smallest common distortion whose ``measure``d bytes are at
    most ``limit``, stopping within ``slack`` (a share) under it: secant steps on log bytes from ``start``
    (default ``_SEARCH_START`` under the top energy; the first step to where ``_modelled_distortion`` meets
    the middle of the window, else its slope from ``_BYTES_PER_HALVING``), Illinois regula falsi once the
    limit is bracketed, until the bracket is narrower than ``_SEARCH_NARROWEST`` (the bytes jump across
    it, as where an image enters the kept set: its fitting end is the answer). Everything kept as finely
    as the codes go, when that fits; the floor alone when even that does not."""
    # from far below any 16-bit quantisation noise to nothing kept (but the floor)
    lowest, highest = np.log(top) - _SEARCH_DEPTH, np.log(top) + 1.0
    target = np.log(1.0 - 0.5 * slack)  # log(bytes / limit) in the middle of the window

    def excess(log_distortion: float) -> tuple[float, float, list[np.ndarray]]:
        steps = [plan.steps(np.exp(log_distortion), levels) for plan in plans]
        total = measure(steps)
        return np.log(max(total, 1.0) / limit) - target, total, steps

    x = float(np.clip(np.log(top) - _SEARCH_START if start is None else start, lowest, highest))
    fits = over = None  # (x, excess) of the bracket's ends: bytes within the limit / over it
    best: tuple[float, list[np.ndarray], float] | None = None
    previous = None
    side = 0
    for _ in range(_SEARCH_STEPS):
        f, total, steps = excess(x)
        if total <= limit:
            if best is None or x < best[0]:
                best = (x, steps, total)
            if total >= (1.0 - slack) * limit or x <= lowest:
                break
            fits = (x, f)
            if side == 1 and over is not None:
                over = (over[0], 0.5 * over[1])  # Illinois: the other end has stayed twice; halve its weight
            side = 1
        else:
            if x >= highest:
                break  # even the floor alone does not fit
            over = (x, f)
            if side == -1 and fits is not None:
                fits = (fits[0], 0.5 * fits[1])
            side = -1
        if fits is not None and over is not None:  # bracketed: regula falsi, bisecting near the ends
            (a, fa), (b, fb) = over, fits
            if abs(b - a) < _SEARCH_NARROWEST:
                break  # a jump of the bytes, no distortion between: the fitting end
            width = b - a
            middle = b - fb * width / (fb - fa) if fb != fa else 0.5 * (a + b)
            x = middle if a + _SEARCH_GUARD * width < middle < b - _SEARCH_GUARD * width else 0.5 * (a + b)
        else:
            modelled = (None if previous is not None
                        else _modelled_distortion(plans, levels, x, total, limit * np.exp(target), lowest, highest))
            # the first step: to where the high-rate model, fitted to this measurement, meets the window's middle
            if modelled is not None:
                slope = -f / (modelled - x) if modelled != x else -_SLOPE_FLOOR
            elif previous is not None and previous[0] != x and previous[1] != f:
                slope = (f - previous[1]) / (x - previous[0])
            else:  # bytes fall by _BYTES_PER_HALVING a value that follows the distortion, per halving of the step
                values = sum(plan.changing_values(step, levels) for plan, step in zip(plans, steps))
                # the step goes as sqrt(distortion)
                slope = -_BYTES_PER_HALVING / (2.0 * np.log(2.0)) * values / max(total, 1.0)
            step = -f / min(slope, -_SLOPE_FLOOR)
            step = float(np.clip(step, -_SEARCH_STRIDE, _SEARCH_STRIDE))
            step = step if abs(step) >= _SEARCH_MIN_STEP else np.copysign(_SEARCH_MIN_STEP, step)
            previous = (x, f)
            x = float(np.clip(x + step, lowest, highest))
            if x == previous[0]:
                break
    if best is None:  # nothing measured fits: the floor alone, if even that does not fit
        _, total, steps = excess(highest)
        return highest, steps, total
    return best


def _modelled_bytes(plans: list[StackPlan], levels: int, log_distortion: float, offset: float) -> float:
    """Stored bytes the high-rate model gives at ``log_distortion``: each kept image's M values at
    ``offset - log2(step sqrt(M))`` bits (at least none; a unit image's values have an RMS of
    1 / sqrt(M), and a smooth density quantised with a step s costs log2(RMS / s) plus a constant
    bits a value, here ``offset``), with its range and weights."""
    total = 0.0
    for plan in plans:
        steps = plan.steps(np.exp(log_distortion), levels)
        values = plan.principal.values
        total += values * float(np.maximum(offset - np.log2(steps * np.sqrt(values)), 0.0).sum()) / 8.0
        total += (8 + 4 * plan.principal.light_count) * len(steps)
    return total


def _modelled_distortion(plans: list[StackPlan], levels: int, log_distortion: float, measured: float, goal: float,
                         lowest: float, highest: float) -> float | None:
    """The log distortion at which ``_modelled_bytes``, its offset fitted to the ``measured`` bytes at
    ``log_distortion``, gives ``goal`` bytes (within [``lowest``, ``highest``]: an end where the goal
    lies beyond it); None where no offset fits the measurement (nothing kept, or bytes the ranges and
    weights alone exceed). Both roots by Brent's method (the model's bytes rise with the offset and
    fall with the distortion)."""
    from scipy.optimize import (
        brentq,  # only the sampled rate search needs it (the fit command imports it while its images load)
    )

    def fitted(offset: float) -> float:
        return _modelled_bytes(plans, levels, log_distortion, offset) - measured

    if not fitted(-_MODEL_OFFSET_RANGE) < 0 < fitted(_MODEL_OFFSET_RANGE):
        return None
    offset = brentq(fitted, -_MODEL_OFFSET_RANGE, _MODEL_OFFSET_RANGE, xtol=_MODEL_TOLERANCE)

    def short(x: float) -> float:
        return goal - _modelled_bytes(plans, levels, x, offset)

    if short(lowest) >= 0:
        return lowest  # even everything kept as finely as the codes go is under the goal
    if short(highest) <= 0:
        return highest
    return brentq(short, lowest, highest, xtol=_MODEL_TOLERANCE)
