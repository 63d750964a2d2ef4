"""A smaller decoder for a learned residual, distilled from the fitted one (``warp-highlights distil``).

The student is a decoder of fewer or narrower hidden layers (``model.residual.decoder_layer_shapes``) over
the same kind of per-pixel code, trained to reproduce the fitted decoder (the teacher), as DisK-NeuralRTI
distils NeuralRTI's: its targets are the teacher's outputs, in the same signed sRGB display units, at the
captured light directions and at as many new ones drawn inside the captured lights' triangles, drawn anew
every round, so it learns the relighting between the lights as well as at them. Its codes start as the
teacher's and learn along (``DistilSettings.learn_codes``). Training is NumPy float32 on the CPU (the
student is small; ``cpu_training``'s Adam and thread split), for ``DistilSettings.seconds`` or ``epochs``
at most. Its agreement with the teacher is measured in 8-bit sRGB PSNR on the residual at the captured
lights and at directions between them that it never learned from.

A teacher that sees the highlights (``NeuralResidual.sees_highlights``: it also takes sqrt(g), g of the moved
Gaussians' luminance g at the pixel, display units) gets a student that sees them too: both decode with the g of
each direction they are given, which the caller renders (``highlights``: the relighter's S' of the moved Gaussians,
field units; this layer draws no Gaussians).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..io.images import linear_to_srgb
from ..model.config import LEARNED_FINAL_RATE, DistilSettings
from ..model.errors import InputError
from ..model.memory import check_memory
from ..model.residual import (
    NEURAL_CODE_SIZE,
    NeuralResidual,
    decoder_layer_shapes,
    highlight_inputs,
    parse_hidden,
)
from ..model.threads import NUMPY_THREADS, blas_on_one_thread, parallel_map
from ..quality.metrics import psnr_8bit, srgb_psnr
from .cpu_training import CpuDecoder, _Adam
from .opponent import decode_display

__all__ = ["DistilReport", "decoder_multiply_adds", "directions_between", "distil_decoder", "distil_display_decoder",
           "parse_hidden"]

_NEEDS_HIGHLIGHTS = ("a learned residual that sees the highlights distils with them: pass highlights, the moved "
                     "Gaussians' luminance at given directions")
_NOVEL_SEED = 12_345  # the directions the agreement is measured at between the lights: the same for every student


@dataclass(frozen=True)
class DistilReport:
    """What a distillation did: the student's and teacher's hidden widths, multiply-adds per decoded pixel,
    epochs and seconds trained, and the student's 8-bit sRGB PSNR (dB) against the teacher's residual at
    the captured lights (``captured_psnr_db``) and at as many directions between them
    (``between_psnr_db``), means over the lights."""

    hidden: tuple[int, ...]
    teacher_hidden: tuple[int, ...]
    multiply_adds: int
    teacher_multiply_adds: int
    epochs: float
    seconds: float
    captured_psnr_db: float
    between_psnr_db: float

    def to_dict(self) -> dict:
        """Plain figures for the field's report (``report["distilled"]``)."""
        return {"hidden": list(self.hidden), "teacher_hidden": list(self.teacher_hidden),
                "multiply_adds": self.multiply_adds, "teacher_multiply_adds": self.teacher_multiply_adds,
                "epochs": round(self.epochs, 2), "seconds": round(self.seconds, 2),
                "captured_psnr_db": round(self.captured_psnr_db, 3), "between_psnr_db": round(self.between_psnr_db, 3)}


def decoder_multiply_adds(hidden, highlights: bool = False) -> int:
    """Multiply-adds of one decoded pixel and light through a decoder of ``hidden`` widths (that sees the highlights
    where ``highlights``)."""
    return int(sum(rows * cols for rows, cols in decoder_layer_shapes(hidden, highlights)[0::2]))


def directions_between(directions: np.ndarray, faces: np.ndarray, count: int, rng) -> np.ndarray:
    """(count, 3) unit directions drawn uniformly in barycentric coordinates inside random faces (F, 3) of
    the (n, 3) light directions' triangulation: where relighting interpolates."""
    faces = np.asarray(faces, dtype=np.int64)
    if not len(faces):
        raise InputError("the field's lights have no triangle to draw directions between")
    picked = faces[rng.integers(0, len(faces), count)]
    weights = rng.dirichlet(np.ones(3), count)
    points = np.einsum("qk,qkd->qd", weights, np.asarray(directions, np.float64)[picked])
    return (points / np.linalg.norm(points, axis=1, keepdims=True)).astype(np.float32)


def distil_decoder(learned: NeuralResidual, hidden, directions: np.ndarray, faces: np.ndarray, *,
                   settings: DistilSettings | None = None, log=None, progress=None,
                   highlights=None) -> tuple[NeuralResidual, DistilReport]:
    """A ``NeuralResidual`` with a decoder of ``hidden`` widths (None: ``settings.hidden``) and ``learned``'s codes
    (learning along where ``settings.learn_codes``), trained to reproduce ``learned``'s at the field's (n, 3) light
    ``directions`` and between them (inside the triangulation's ``faces``), and its ``DistilReport``.
    ``progress(fraction)`` as training goes, ``log`` a line a round. ``highlights``: (D, 3) unit directions ->
    (D, H, W) the moved Gaussians' luminance there (field units, the relighter's S'), required where ``learned``
    sees the highlights: the student then sees them too."""
    settings = settings or DistilSettings()
    hidden = parse_hidden(",".join(str(int(w)) for w in (settings.hidden if hidden is None else hidden)))
    codes = learned.codes.reshape(-1, NEURAL_CODE_SIZE).astype(np.float32)
    teacher = CpuDecoder(codes, learned.weights)
    seen = _display_luminance(learned, highlights)
    parameters, epochs, seconds = _train_student(lambda pool, g: teacher.decode(pool, highlights=g), codes, hidden,
                                                 directions, faces, settings=settings,
                                                 learn_codes=settings.learn_codes, planar=False, highlights=seen,
                                                 sees=learned.sees_highlights, log=log, progress=progress)
    student_codes = learned.codes
    if settings.learn_codes:
        student_codes = parameters.views(parameters.flat)[-1].reshape(learned.codes.shape).astype(np.float16)
    # the capture's range, which bounds the student's values as it bounds the fitted decoder's
    student = NeuralResidual(student_codes, tuple(parameters.weights()), learned.unit, learned.light_count,
                             learned.bounds)
    between = directions_between(directions, faces, len(directions), np.random.default_rng(_NOVEL_SEED))
    sees = learned.sees_highlights
    report = DistilReport(hidden=hidden, teacher_hidden=learned.hidden,
                          multiply_adds=decoder_multiply_adds(hidden, sees),
                          teacher_multiply_adds=decoder_multiply_adds(learned.hidden, sees), epochs=epochs,
                          seconds=seconds, captured_psnr_db=agreement(student, learned, directions, highlights),
                          between_psnr_db=agreement(student, learned, between, highlights))
    return student, report


def _display_luminance(learned: NeuralResidual, highlights):
    """(D, 3) directions -> (D, P) float32 g, the moved Gaussians' luminance in display units (``highlights``' over
    the unit), for a ``learned`` that sees the highlights; None for one that does not."""
    if not learned.sees_highlights:
        return None
    if highlights is None:
        raise InputError(_NEEDS_HIGHLIGHTS)
    pixels = learned.codes.shape[0] * learned.codes.shape[1]
    return lambda pool: (np.asarray(highlights(np.asarray(pool, np.float32)), np.float32).reshape(len(pool), pixels)
                         / np.float32(learned.unit))


def distil_display_decoder(learned: NeuralResidual, codes: np.ndarray, hidden, directions: np.ndarray,
                           faces: np.ndarray, *, exposure: float, settings: DistilSettings | None = None, log=None,
                           progress=None, highlights=None) -> tuple[list[np.ndarray], dict]:
    """A decoder of ``hidden`` widths over the (H, W, 9) ``codes`` (kept as given: e.g. ``learned``'s as a viewer
    stores them) that takes the light as (x, y, 0) and gives the relit image's 8-bit-ready sRGB display values
    in [0, 1]: ``learned``'s residual (field units) over ``exposure``, clipped to [0, 1] and sRGB-encoded, as
    OpenLIME's neural layer draws. Trained at the (n, 3) light ``directions`` and between them (inside
    ``faces``). ``highlights`` as ``distil_decoder`` takes it, for a ``learned`` that sees the highlights: the teacher
    decodes with the moved Gaussians of each direction; the student takes code and light only. Returns its weights
    and biases (``decoder_layer_shapes`` order) and figures: epochs, seconds, the lights, and the 8-bit PSNR (dB) of
    its image against the teacher's at the captured lights and between them (``captured_psnr_db``,
    ``between_psnr_db``)."""
    settings = settings or DistilSettings()
    hidden = parse_hidden(",".join(str(int(w)) for w in hidden))
    teacher = CpuDecoder(learned.codes.reshape(-1, NEURAL_CODE_SIZE).astype(np.float32), learned.weights)
    height, width, _ = learned.codes.shape
    seen = _display_luminance(learned, highlights)

    def shown(pool: np.ndarray, g: np.ndarray | None) -> np.ndarray:  # (D, P, 3) the teacher's image, sRGB in [0, 1]
        values = decode_display(teacher.decode(pool, highlights=g)).reshape(len(pool), height, width, 3)
        values = learned.within_bounds(values * np.float32(learned.unit)).reshape(len(pool), -1, 3)
        return linear_to_srgb(np.clip(values / np.float32(exposure), 0.0, 1.0)).astype(np.float32)

    flat_codes = np.asarray(codes, np.float32).reshape(-1, NEURAL_CODE_SIZE)
    parameters, epochs, seconds = _train_student(shown, flat_codes, hidden, directions, faces, settings=settings,
                                                 learn_codes=False, planar=True, highlights=seen, log=log,
                                                 progress=progress)
    weights = parameters.weights()
    student = CpuDecoder(flat_codes, weights)

    def score(queries: np.ndarray) -> float:
        queries = np.asarray(queries, np.float32)
        mine = np.clip(student.decode(_planar(queries)), 0.0, 1.0)
        theirs = shown(queries, None if seen is None else seen(queries))
        return float(np.mean([psnr_8bit(np.round(255 * a).astype(np.uint8), np.round(255 * b).astype(np.uint8))
                              for a, b in zip(mine, theirs)]))

    between = directions_between(directions, faces, len(directions), np.random.default_rng(_NOVEL_SEED))
    return weights, {"hidden": list(hidden), "lights": len(directions), "epochs": round(epochs, 2),
                     "seconds": round(seconds, 2),
                     "captured_psnr_db": round(score(directions), 3), "between_psnr_db": round(score(between), 3)}


def _planar(directions: np.ndarray) -> np.ndarray:
    """Directions as (x, y, 0): the light as OpenLIME's neural layer passes it."""
    planar = np.array(directions, np.float32)
    planar[..., 2] = 0.0
    return planar


def _train_student(targets_of, codes: np.ndarray, hidden: tuple[int, ...], directions: np.ndarray,
                   faces: np.ndarray, *, settings: DistilSettings, learn_codes: bool, planar: bool, highlights=None,
                   sees: bool = False, log=None, progress=None) -> tuple[_Student, float, float]:
    """A student of ``hidden`` widths over the (P, 9) ``codes`` (learning along where ``learn_codes``) trained on
    ``targets_of(pool, g)`` (D, P, 3) at the (n, 3) ``directions`` and new ones between them each round (its input
    the directions as (x, y, 0) where ``planar``); g: ``highlights(pool)`` (D, P) display units, or None without
    ``highlights``; where ``sees``, the student takes sqrt(g), g after the direction. Returns it, its epochs and
    seconds."""
    directions = np.asarray(directions, np.float32)
    rng = np.random.default_rng(settings.seed)
    parameters = _Student(hidden, rng, codes if learn_codes else None, sees=sees)
    adam = _Adam(parameters.flat.size, threads=NUMPY_THREADS)
    pixels = len(codes)
    batch = int(settings.batch)
    pool_size = len(directions) + max(1, int(round(len(directions) * (settings.pool_factor - 1))))
    steps_per_round = max(1, int(np.ceil(pixels * pool_size * settings.epochs_per_round / batch)))
    rounds = max(1, int(np.ceil(settings.epochs / settings.epochs_per_round)))
    total_steps = rounds * steps_per_round
    started = time.perf_counter()
    step, epochs, spent = 0, 0.0, 0.0
    check_memory(pool_size * pixels * (3 * 2 + (4 if highlights is not None else 0)),
                 f"distilling a decoder of {pixels} pixels", "distil a field fitted at a smaller --size",
                 detail="the teacher's outputs at the lights and between them"
                        + (" and the highlights' luminance there" if highlights is not None else ""))
    with blas_on_one_thread() as threads:
        workers = [_Worker(parameters) for _ in range(threads)]
        for round_index in range(rounds):
            novel = directions_between(directions, faces, pool_size - len(directions), rng)
            pool = np.concatenate([directions, novel])
            seen = None if highlights is None else highlights(pool)  # (D, P) g, display units
            targets = targets_of(pool, seen).astype(np.float16)  # (D, P, 3)
            inputs = _planar(pool) if planar else pool
            for _ in range(steps_per_round):
                spent = (time.perf_counter() - started) / settings.seconds if settings.seconds else 0.0
                done = max(step / max(total_steps - 1, 1), spent)
                if spent >= 1.0:
                    break
                rate = settings.rate * (LEARNED_FINAL_RATE / settings.rate) ** min(done, 1.0)
                lights = rng.integers(0, len(pool), batch)
                chosen = rng.integers(0, pixels, batch)
                shards = np.array_split(np.arange(batch), len(workers))
                current = parameters.views(parameters.flat)[-1] if learn_codes else codes
                parallel_map(lambda k: workers[k].gradient(current[chosen[shards[k]]], chosen[shards[k]],
                                                           _student_inputs(inputs, seen if sees else None,
                                                                           lights[shards[k]], chosen[shards[k]]),
                                                           targets[lights[shards[k]], chosen[shards[k]]]),
                             range(len(workers)))
                parameters.grad[:] = sum(worker.grad for worker in workers) / np.float32(batch)
                adam.step(parameters.flat, parameters.grad, rate)
                step += 1
                if progress is not None:
                    progress(min(done, 1.0))
            epochs = step * batch / (pixels * pool_size)  # passes over a pool's samples
            if log is not None:
                log(f"distil: round {round_index + 1}/{rounds}, {epochs:.1f} epochs, "
                    f"{time.perf_counter() - started:.1f} s")
            if spent >= 1.0:
                break
    return parameters, epochs, time.perf_counter() - started


def _student_inputs(inputs: np.ndarray, seen: np.ndarray | None, lights: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(B, 3) the samples' directions of the pool's ``inputs``, then where ``seen`` (D, P) is given (B, 2) sqrt(g), g
    of each sample's light and pixel."""
    if seen is None:
        return inputs[lights]
    return np.concatenate([inputs[lights], highlight_inputs(seen[lights, pixels])], axis=1)


def agreement(student: NeuralResidual, teacher: NeuralResidual, directions: np.ndarray, highlights=None) -> float:
    """Mean 8-bit sRGB PSNR (dB) of ``student``'s residual against ``teacher``'s at (Q, 3) directions (display
    units: the field's over its unit), each decoded with its own codes; ``highlights`` as ``distil_decoder`` takes it,
    for decoders that see the highlights."""
    height, width, _ = teacher.codes.shape
    models = (student, teacher)
    decoders = [CpuDecoder(model.codes.reshape(-1, NEURAL_CODE_SIZE).astype(np.float32), model.weights)
                for model in models]
    seeing = any(model.sees_highlights for model in models)
    if seeing and highlights is None:
        raise InputError(_NEEDS_HIGHLIGHTS)
    scores = []
    for direction in np.asarray(directions, np.float32).reshape(-1, 3):
        drawn = np.asarray(highlights(direction[None]), np.float32).reshape(1, -1) if seeing else None  # once
        images = []
        for decoder, model in zip(decoders, models):
            g = drawn / np.float32(model.unit) if model.sees_highlights else None  # display units
            values = decode_display(decoder.decode(direction[None], highlights=g)[0])
            images.append(np.maximum(values, 0.0).reshape(height, width, 3))
        scores.append(srgb_psnr(*images))
    return float(np.mean(scores))


class _Student:
    """The student decoder's weights and biases, then the per-pixel codes where they learn too, as views into
    one flat float32 vector (and its gradient's); the weights start uniform in +-1/sqrt(fan-in) as the
    fitted decoder's do, the codes as the teacher's. ``sees``: its first layer takes sqrt(g), g too."""

    def __init__(self, hidden: tuple[int, ...], rng, codes: np.ndarray | None = None, *, sees: bool = False):
        self.shapes = decoder_layer_shapes(hidden, sees)
        sizes = [rows * cols for rows, cols in self.shapes]
        fan_in = [self.shapes[i - i % 2][1] for i in range(len(self.shapes))]  # a bias: its weight's
        parts = [rng.uniform(-1.0, 1.0, size) / np.sqrt(fan) for size, fan in zip(sizes, fan_in)]
        self.learns_codes = codes is not None
        if self.learns_codes:
            parts.append(np.asarray(codes, np.float32).reshape(-1))
            self.shapes = (*self.shapes, np.shape(codes))
            sizes.append(int(np.size(codes)))
        self.flat = np.concatenate(parts).astype(np.float32)
        self.grad = np.zeros_like(self.flat)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])

    def views(self, vector: np.ndarray) -> list[np.ndarray]:
        """w0, b0, ... (and the codes) as views into ``vector``."""
        return [vector[a:b].reshape(s) for a, b, s in zip(self.offsets[:-1], self.offsets[1:], self.shapes)]

    def weights(self) -> list[np.ndarray]:
        """Copies of w0, b0, ... in ``decoder_layer_shapes`` order."""
        return [w.copy() for w in self.views(self.flat)[:len(self.shapes) - self.learns_codes]]


class _Worker:
    """One thread's share of a batch: the student's forward and backward pass over its samples (rows) and
    its own gradient of the flat vector (summed, not averaged)."""

    def __init__(self, student: _Student):
        self.student = student
        self.grad = np.zeros_like(student.flat)

    def gradient(self, codes: np.ndarray, pixels: np.ndarray | None, directions: np.ndarray,
                 targets: np.ndarray) -> None:
        """grad = d/dtheta of sum over the rows of |decoder(codes, directions) - targets|^2 / 2 (display units);
        ``directions``: (B, 3), or (B, 5) with sqrt(g), g for a student that sees the highlights; ``pixels``: the
        rows' pixels, whose codes' gradient it takes too where the student learns its codes."""
        parts = self.student.views(self.student.flat)
        grads = self.student.views(self.grad)
        layers = parts[:len(parts) - self.student.learns_codes]
        self.grad[:] = 0.0
        x = np.concatenate([codes, directions], axis=1)  # (B, 12), or (B, 14) with the highlights' inputs
        values, slopes = [x], []
        for w, b in zip(layers[0:-2:2], layers[1:-2:2]):
            z = values[-1] @ w.T + b[:, 0]
            e = np.expm1(np.minimum(z, 0.0))
            values.append(np.maximum(z, e))
            slopes.append(np.where(z > 0, np.float32(1.0), e + np.float32(1.0)))
        error = values[-1] @ layers[-2].T + layers[-1][:, 0] - targets.astype(np.float32)  # d loss / d output
        for k in range(len(layers) // 2 - 1, -1, -1):
            grads[2 * k][:] = error.T @ values[k]
            grads[2 * k + 1][:, 0] = error.sum(axis=0)
            if k:
                error = (error @ layers[2 * k]) * slopes[k - 1]
        if self.student.learns_codes:
            np.add.at(grads[-1], pixels, error @ layers[0][:, :NEURAL_CODE_SIZE])
