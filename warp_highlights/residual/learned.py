"""The learned residual (9 numbers per pixel and an MLP of code and light direction, ``kernels.neural``)
and its check: whether it keeps the moving Gaussians or learns the images alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.neural import NeuralDecoder, decode
from ..kernels.neural_training import train_decoders
from ..model.config import (
    LEARNED_ANEW_SHARE_CPU,
    LEARNED_ANEW_SHARE_CUDA,
    LEARNED_BATCH_CPU,
    LEARNED_BATCH_CUDA,
    LEARNED_EPOCHS_CPU,
    LEARNED_EPOCHS_CUDA,
    LEARNED_FINAL_RATE,
    LEARNED_RATE_CPU,
    LEARNED_RATE_CUDA,
    LEARNED_RESIDUAL_RATE,
    LEARNED_SECONDS_CPU,
    LEARNED_SECONDS_CUDA,
    LEARNED_STEPS_PER_EPOCH,
    LEARNED_TUNE_SECONDS_CPU,
    LEARNED_TUNE_SECONDS_CUDA,
    ResidualSettings,
)
from ..model.errors import InputError
from ..model.residual import (
    NeuralResidual,
    ResidualModel,
    learned_bounds,
)
from ..model.threads import parallel_map
from ..quality.metrics import srgb_psnr
from .cpu_training import decode_cpu, train_decoder_cpu
from .inputs import learned_target, residual_of, row_bands
from .opponent import decode_display, encode_display

__all__ = ["LearnedCheck", "bounded", "check_learned", "glides", "learn_residual", "tie_margin"]

_EVERY_FEW_EPOCHS = tuple(f"epoch {k}/" for k in (1, 10, 50, 100, 200, 400, 1000))  # the learned residual's log lines


def learn_residual(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, directions: np.ndarray, *,
                   factor: float,
                   settings: ResidualSettings, device, log=None, progress=None, used: np.ndarray | None = None,
                   initial: NeuralResidual | None = None, tune: bool = False,
                   highlights: np.ndarray | None = None,
                   specular: np.ndarray | None = None) -> tuple[ResidualModel, list[float]]:
    """A ``ResidualModel`` holding a learned residual of the (n, H, W, 3) images (field units) minus their own (n, H, W)
    highlights in colour c: ``kernels.neural`` trained on the residual in signed sRGB display units (the field's
    units over ``factor``) at the (n, 3) light directions, for ``settings.learned_seconds`` or ``learned_epochs`` at
    most (``learned_seconds``, ``learned_epochs``), as many samples a step as ``learned_batch`` gives, from
    ``learned_rate`` where ``own`` is all zero (the images learned alone) and ``learned_residual_rate`` where
    highlights were taken out (``residual_rate``); ``progress(1)`` after each epoch, ``log`` a line now and then;
    ``used``: the lights it learns from (default all). ``initial``: a model to go on training; ``tune``: for
    ``settings.learned_tune_epochs`` or ``learned_tune_seconds`` at the final learning rate (the learned check's
    winner learning the lights it left out). ``highlights``: (n, H, W) the Gaussians' luminance at each light (field
    units: each light's moved from the others, ``MoveCheck.moved_luminance``, or its own, as
    ``ResidualSettings.learned_seeing_inputs`` says): the decoder sees them and learns the
    images themselves (``own`` is not taken out). ``specular``: (n, H, W, 3) the segmentation's specular part (field
    units): under each light's own highlights the residual learns the diffuse part
    (``settings.diffuse_under_highlights``). Returns it and the loss per epoch."""
    sees = highlights is not None
    targets = _targets(images, np.zeros_like(own) if sees else own, None if sees else colour, factor,
                       None if sees else specular, settings.diffuse_under_highlights)
    n, height, width, _ = np.shape(images)
    start = None if initial is None else [NeuralDecoder(initial.codes.reshape(height * width, -1).astype(np.float32),
                                                        [np.asarray(w, np.float32) for w in initial.weights])]
    alone = sees or not np.any(own)  # no highlight taken out: the images themselves
    rate = learned_rate(settings, wp.get_device(device).is_cuda) if alone else residual_rate(settings)
    models, history = _train([targets], directions, settings=settings, device=device, log=log, progress=progress,
                             used=used, initial=start, tune=tune, rate=rate,
                             inputs=[_display_inputs(highlights, factor) if sees else None])
    return _residual_model(models[0], height, width, factor, n, colour), history[0]


def _display_inputs(highlights: np.ndarray, factor: float) -> np.ndarray:
    """(n, H W) float32 the Gaussians' luminance of (n, H, W) ``highlights`` (field units) in display units."""
    n = len(highlights)
    return np.ascontiguousarray(np.asarray(highlights, np.float32).reshape(n, -1) * np.float32(1.0 / factor))


def _targets(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, factor: float,
             specular: np.ndarray | None = None, level: float = 0.0) -> np.ndarray:
    """(n, H*W, 3) float32: the residual of the images minus their own highlights in colour c, in signed sRGB
    display units (the field's units over ``factor``), a light at a time on each thread; with the (n, H, W, 3)
    ``specular`` part, the diffuse part where a light's own highlights are at least ``level`` of their brightest
    (``inputs.diffuse_under_highlights``)."""
    if np.ndim(images) != 4 or np.shape(images)[3] != 3:
        raise InputError("a learned residual needs colour (RGB) images; fit grey captures with --residual lowrank")
    n, height, width, _ = np.shape(images)
    tint = np.ones((1, 1, 3), np.float32) if colour is None else colour
    out = np.empty((n, height * width, 3), np.float32)

    def light(i: int) -> None:
        residual = learned_target(images[i], own[i], tint, None if specular is None else specular[i], level)
        residual /= np.float32(factor)
        encode_display(residual, out=out[i])

    parallel_map(light, range(n))
    return out


def _residual_model(model: NeuralDecoder, height: int, width: int, factor: float, lights: int,
                    colour: np.ndarray | None, bounds: np.ndarray | None = None) -> ResidualModel:
    learned = NeuralResidual(model.codes.reshape(height, width, -1).astype(np.float16), tuple(model.weights),
                             float(factor), lights, bounds)
    return ResidualModel(learned=learned, highlight_colour=colour)


def _train(targets: list[np.ndarray], directions: np.ndarray, *, settings: ResidualSettings, device, log=None,
           progress=None, used=None, initial: list[NeuralDecoder] | None = None,
           tune: bool = False, settle=None, settle_used=None,
           rate: float | tuple = LEARNED_RESIDUAL_RATE,
           inputs: list | None = None,
           stop_when_settled: bool = False) -> tuple[list[NeuralDecoder], list[list[float]]]:
    """Decoders for each of the (n, P, 3) ``targets``, side by side in the same launches on CUDA, one after the other
    on the CPU, the learning rate from ``rate`` (one for every model, or one each; ``LEARNED_FINAL_RATE`` where
    ``tune``); returns them and each one's loss per epoch. ``settle(models)``, called after each
    ``learned_settle_fraction`` of the epochs while both learn (on the CPU once, in two parts:
    ``_train_settling_on_cpu``), returns the index of the one model to go on, or None; that one learns from the
    ``settle_used`` lights from then on (default ``used``), or, ``stop_when_settled``, every model stops there.
    ``inputs``: per model None or the (n, P) Gaussians' luminance (display units) that it sees (one array for every
    model that sees them)."""
    device = wp.get_device(device)
    inputs = [None] * len(targets) if inputs is None else list(inputs)
    seen = next((g for g in inputs if g is not None), None)
    learning = [len(targets) if device.is_cuda else 1]  # models that advance the bar an epoch

    def say(message: str) -> None:  # once an epoch, for every model learning
        if progress is not None:
            progress(learning[0])
        if log is not None and message.startswith(_EVERY_FEW_EPOCHS):
            log(f"learned residual: {message}")

    on_cuda = device.is_cuda
    seconds = learned_seconds(settings, on_cuda, tune)
    epochs = int(settings.learned_tune_epochs) if tune else learned_epochs(settings, on_cuda)
    starts = np.broadcast_to(np.asarray(LEARNED_FINAL_RATE if tune else rate, np.float64), (len(targets),))
    rates = {"lr": tuple(map(float, starts)), "final_lr": LEARNED_FINAL_RATE, "epochs": epochs}
    samples = (len(targets[0]) if used is None else len(used)) * np.shape(targets[0])[1]
    batch = learned_batch(settings, on_cuda, samples)
    options = dict(device=device, batch=batch, log=say, used=used, seconds=seconds, **rates)
    epoch = max(1, round(settings.learned_settle_fraction * rates["epochs"]))
    if on_cuda:
        def settled(models):
            kept = settle(models)
            learning[0] = len(targets) if kept is None else 1
            return kept

        models, history = train_decoders(np.stack(targets), directions, initial=initial,
                                         settle=None if settle is None else settled, settle_epoch=epoch,
                                         settle_used=settle_used, highlights=seen,
                                         sees=[g is not None for g in inputs], stop_when_settled=stop_when_settled,
                                         **options)
        return models, [list(map(float, history[:, m])) for m in range(len(targets))]
    if settle is None or len(targets) < 2 or epoch >= rates["epochs"]:
        trained = [train_decoder_cpu(target, directions, initial=None if initial is None else initial[m],
                                     highlights=inputs[m],
                                     **{**options, "lr": options["lr"][m], "seconds": seconds / len(targets)})
                   for m, target in enumerate(targets)]
        return [model for model, _ in trained], [history for _, history in trained]
    return _train_settling_on_cpu(targets, directions, initial, options, epoch, settle, settle_used, inputs,
                                  stop_when_settled)


def learned_batch(settings: ResidualSettings, on_cuda: bool, samples: int) -> int:
    """(light, pixel) samples per Adam step for an epoch of ``samples``: the setting, or where it is 0 the device's
    default, on CUDA cut for a small capture so that an epoch holds ``LEARNED_STEPS_PER_EPOCH`` steps, never below
    the CPU's batch."""
    if int(settings.learned_batch):
        return int(settings.learned_batch)
    if not on_cuda:
        return LEARNED_BATCH_CPU
    return int(min(LEARNED_BATCH_CUDA, max(LEARNED_BATCH_CPU, int(samples) // LEARNED_STEPS_PER_EPOCH)))


def learned_epochs(settings: ResidualSettings, on_cuda: bool) -> int:
    """The epochs of the learning rate's schedule: the setting, or where it is 0 the device's default."""
    return int(settings.learned_epochs) or (LEARNED_EPOCHS_CUDA if on_cuda else LEARNED_EPOCHS_CPU)


def learned_rate(settings: ResidualSettings, on_cuda: bool) -> float:
    """The learning rate at the start of the images' schedule where they are learned alone: the setting, or where
    it is 0 the device's default."""
    return float(settings.learned_rate) or (LEARNED_RATE_CUDA if on_cuda else LEARNED_RATE_CPU)


def residual_rate(settings: ResidualSettings) -> float:
    """The learning rate at the start of the schedule of a residual with moving Gaussians taken out: the setting, or
    where it is 0 ``LEARNED_RESIDUAL_RATE`` (on every device)."""
    return float(settings.learned_residual_rate) or LEARNED_RESIDUAL_RATE


def learns_anew(settings: ResidualSettings, unseen: int, light_count: int, on_cuda: bool) -> bool:
    """Whether the learned check's winner, trained without ``unseen`` of ``light_count`` lights, should learn anew
    from every light rather than tune: where those lights are more than ``settings.learned_anew_share`` of the
    capture (negative: the device's share, ``LEARNED_ANEW_SHARE_CUDA`` / ``_CPU``). A model fitted to 10 of 16 lights
    and tuned on all 16 stayed 2 dB below one that learned all 16 from the start (benchmarks/bench_motion.py, bumpy
    donut); on CUDA, 6 of 49 left out and tuned stayed 0.9-2.2 dB below."""
    share = float(settings.learned_anew_share)
    if share < 0:
        share = LEARNED_ANEW_SHARE_CUDA if on_cuda else LEARNED_ANEW_SHARE_CPU
    return unseen / max(light_count, 1) > share


def learned_seconds(settings: ResidualSettings, on_cuda: bool, tune: bool = False) -> float:
    """The training time at most, seconds: the setting, or where it is 0 the device's default."""
    if tune:
        return float(settings.learned_tune_seconds) or (LEARNED_TUNE_SECONDS_CUDA if on_cuda
                                                       else LEARNED_TUNE_SECONDS_CPU)
    return float(settings.learned_seconds) or (LEARNED_SECONDS_CUDA if on_cuda else LEARNED_SECONDS_CPU)


def _train_settling_on_cpu(targets, directions, initial, options: dict, settle_epoch: int, settle,
                           settle_used=None, inputs=None, stop_when_settled: bool = False):
    """The learned check's models on the CPU, one after the other in two parts: each its first ``settle_epoch``
    epochs of the schedule, then, once ``settle`` has scored them, the rest for the winner alone (or for both; none
    where settled and ``stop_when_settled``).
    The second part goes on from the first's models with each model's schedule of learning rates (``options["lr"]``:
    one first rate each), its Adam moments new, a lone winner from the ``settle_used`` lights (default the first
    part's); the time is shared in proportion to the epochs each part learns."""
    epochs, final_lr = options["epochs"], options["final_lr"]

    def rate_at(m: int, epoch: int) -> float:  # model m's learning rate at that epoch of its schedule
        return options["lr"][m] * (final_lr / options["lr"][m]) ** (epoch / max(epochs - 1, 1))

    count, seconds = len(targets), options["seconds"]
    share = seconds / (count * settle_epoch + (epochs - settle_epoch))  # seconds an epoch if one wins
    models, histories = [], []
    for m, target in enumerate(targets):
        first = dict(options, epochs=settle_epoch, lr=options["lr"][m], final_lr=rate_at(m, settle_epoch - 1),
                     seconds=share * settle_epoch)
        model, history = train_decoder_cpu(target, directions, initial=None if initial is None else initial[m],
                                           highlights=None if inputs is None else inputs[m], **first)
        models.append(model)
        histories.append(history)
    kept = settle(models)
    if kept is not None and stop_when_settled:
        return models, histories
    going_on = range(count) if kept is None else [int(kept)]
    rest = dict(options, epochs=epochs - settle_epoch,
                seconds=max(share, (seconds - share * count * settle_epoch) / len(going_on)))
    if kept is not None and settle_used is not None:
        rest["used"] = settle_used
    for m in going_on:
        models[m], history = train_decoder_cpu(targets[m], directions, initial=models[m],
                                               highlights=None if inputs is None else inputs[m],
                                               **{**rest, "lr": rate_at(m, settle_epoch)})
        histories[m] = histories[m] + history
    return models, histories


@dataclass(frozen=True)
class LearnedCheck:
    """What ``check_learned`` measured at its left-out lights (m,): 8-bit sRGB PSNR (dB) of the model with the
    moved highlights (``with_gaussians``: a decoder that sees them, or a learned residual they are added to) and of
    the images learned alone, and the winner's model; ``settled_epoch``: the epoch after which the loser stopped
    learning, its order settled (None: both learned to the end, without those lights), and the scores are those of
    that epoch; ``learned_every_light``: the winner learned from every light after it (the check's lights too), so
    it needs no more training; ``history``: its loss per epoch; ``tie_margin_db``: how far the images alone may lead
    (negative: how far they must trail) and the Gaussians still be kept (``tie_margin``: ``learned_tie_margin_db``,
    ``learned_glide_margin_db`` or ``learned_seeing_margin_db``);
    ``sees_gaussians``: the model with the Gaussians was a decoder that sees them (``check_learned``'s ``seen``);
    ``glides``: the capture's Gaussians glide with the light (``tie_margin``), so the glide's margin applied;
    ``exact_residual``: (m,) the scores of that model with its residual exact at each left-out light
    (``exact_residual_scores``: what moving the Gaussians there costs by itself; None for a decoder that sees them)."""

    lights: np.ndarray
    with_gaussians: np.ndarray
    images_alone: np.ndarray
    winner: ResidualModel | None = None
    settled_epoch: int | None = None
    learned_every_light: bool = False
    history: tuple = ()
    tie_margin_db: float = 0.0
    sees_gaussians: bool = False
    exact_residual: np.ndarray | None = None
    glides: bool = False

    @property
    def keeps_gaussians(self) -> bool:
        """True unless the images learned alone scored higher on average by more than ``tie_margin_db`` (negative:
        unless the model with the Gaussians scored higher by at least its magnitude; no light checked: True)."""
        return not len(self.lights) or (float(np.mean(self.with_gaussians))
                                        >= float(np.mean(self.images_alone)) - self.tie_margin_db)

    def report(self) -> dict:
        """Plain figures for the fit report: the lights checked, the verdict and, where any were checked, both
        models' mean scores (and the first's with its residual exact, where measured), and each light's."""
        scores = {}
        if len(self.lights):
            scores = {"with_gaussians_psnr_db": round(float(np.mean(self.with_gaussians)), 3),
                      "images_alone_psnr_db": round(float(np.mean(self.images_alone)), 3)}
            # each light's too: where the verdict comes from
            per_light = {"light": [int(j) for j in self.lights],
                         "with_gaussians_psnr_db": [round(float(v), 2) for v in self.with_gaussians],
                         "images_alone_psnr_db": [round(float(v), 2) for v in self.images_alone]}
            if self.exact_residual is not None and len(self.exact_residual):
                scores["exact_residual_psnr_db"] = round(float(np.mean(self.exact_residual)), 3)
                per_light["exact_residual_psnr_db"] = [round(float(v), 2) for v in self.exact_residual]
            scores["per_light"] = per_light
        return {"lights": int(len(self.lights)), **scores, "keeps_gaussians": self.keeps_gaussians,
                "tie_margin_db": float(self.tie_margin_db), "glides": self.glides,
                "sees_gaussians": self.sees_gaussians, "settled_epoch": self.settled_epoch}


def tie_margin(settings: ResidualSettings, *, sees: bool = False, coherence: float | None = None) -> float:
    """How far the images learned alone may lead the model with the Gaussians at the learned check's lights (dB) and
    the Gaussians still be kept: ``learned_seeing_margin_db`` for a decoder that sees them (it learns the images as
    the other does: no lead is granted to it), ``learned_glide_margin_db`` where the capture's median motion
    ``coherence`` reaches ``learned_glide_coherence`` (the Gaussians glide with the light), else
    ``learned_tie_margin_db``."""
    if sees:
        return settings.learned_seeing_margin_db
    return settings.learned_glide_margin_db if glides(settings, coherence) else settings.learned_tie_margin_db


def glides(settings: ResidualSettings, coherence: float | None) -> bool:
    """Whether a capture's Gaussians glide with the light: their median motion ``coherence`` (None: not measured)
    reaches ``learned_glide_coherence``."""
    return coherence is not None and bool(np.isfinite(coherence)) and coherence >= settings.learned_glide_coherence


def check_learned(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, directions: np.ndarray,
                  lights: np.ndarray,
                  highlights: np.ndarray, *, factor: float, settings: ResidualSettings, device,
                  progress=None, seen: np.ndarray | None = None, winner_kept: bool = True,
                  specular: np.ndarray | None = None, coherence: float | None = None) -> LearnedCheck:
    """Whether a learned residual should keep the moving Gaussians: two models learn, each as long as
    ``learn_residual`` would, from every light but ``lights`` (m,): one the residual of the (n, H, W, 3)
    images (field units) minus their own (n, H, W) highlights in colour c, the other the images alone
    (NeuralRTI); on CUDA both learn side by side in the same launches. At each left-out light the first plus
    ``highlights`` (m, H, W, 3), the Gaussians moved there from the other lights' triangle
    (``MoveCheck.kept_highlights``), and the second are scored against the image in 8-bit sRGB. Both train in
    until their order has settled (a gap of ``learned_settle_margin_db`` or more, asked after each
    ``learned_settle_fraction`` of the epochs on CUDA, after the first on the CPU; else both to the end), as it
    changes with training (a short run favours the residual, whose Gaussians carry the highlights from the start).
    ``progress(1)`` after each epoch.

    ``seen``: (n, H, W) each light's Gaussians (field units, untinted): at ``lights`` those moved there from the other
    lights (``MoveCheck.moved_luminance``), at the others the moved ones or their own
    (``ResidualSettings.learned_seeing_inputs``). Given, the first model is a decoder that sees the Gaussians (their
    luminance is among its inputs) and learns the images themselves, as the second does: trained with ``seen`` at
    its lights and scored with ``seen`` at the left-out ones, the moved highlights there (``highlights`` is not
    used).

    ``winner_kept`` False (the field's residual will learn anew, ``learns_anew``): once the order has settled both
    models stop, and the winner is returned as it was then. ``specular``: as ``learn_residual`` takes it, for the
    first model. ``coherence``: the capture's median motion coherence (``fit.coherence``); where it reaches
    ``learned_glide_coherence`` the Gaussians glide and the tie margin is ``learned_glide_margin_db``
    (``tie_margin``)."""
    lights = np.asarray(lights, dtype=np.int64)
    if not len(lights):
        return LearnedCheck(lights, np.zeros(0), np.zeros(0))
    tie = tie_margin(settings, sees=seen is not None, coherence=coherence)
    gliding = seen is None and glides(settings, coherence)
    used = np.setdiff1d(np.arange(len(images)), lights)
    scale = np.float32(1.0 / factor)
    truth = np.asarray(images[lights], np.float32) * scale
    n, height, width, _ = np.shape(images)
    alone = _targets(images, np.zeros_like(own), None, factor)
    sees = seen is not None
    targets = [alone if sees else _targets(images, own, colour, factor, specular, settings.diffuse_under_highlights),
               alone]
    inputs = [_display_inputs(seen, factor) if sees else None, None]
    tints = (colour, None)
    added = (np.zeros_like(highlights) if sees else highlights, np.zeros_like(highlights))
    checked = (np.asarray(seen[lights], np.float32) if sees else None, None)  # the Gaussians a decoder sees there
    settled_at = []

    # each candidate is scored as the field would relight it: within the bounds (``learned_bounds``) of what it
    # learned, from the lights it learned (the left-out lights' images are not seen); once, before training
    limits = (None, None)
    if settings.learned_bounds:
        alone_bounds = residual_bounds(images[used], np.zeros_like(own[used]), None)
        limits = (alone_bounds if sees else residual_bounds(images[used], own[used], colour), alone_bounds)

    def score(models) -> list[np.ndarray]:
        rows = []
        for model, tint, extra, g, bounds in zip(models, tints, added, checked, limits):
            learned = _residual_model(model, height, width, factor, n, tint, bounds).learned
            decoded = learned.within_bounds(_decoded(learned, directions[lights], device, g))
            predicted = np.maximum(decoded + extra, 0.0)  # as relit
            rows.append(np.array([srgb_psnr(p * scale, t) for p, t in zip(predicted, truth)]))
        return rows

    asked = [0]

    def settle(models) -> int | None:  # the order settled well ahead of the end: the loser stops there
        asked[0] += 1  # after each learned_settle_fraction of the epochs on CUDA, once on the CPU
        first, second = score(models)
        gap = float(np.mean(first) - np.mean(second))
        if abs(gap) < settings.learned_settle_margin_db:
            return None
        settled_at.append((asked[0] * max(1, round(settings.learned_settle_fraction
                                                   * learned_epochs(settings, wp.get_device(device).is_cuda))),
                           first, second))
        return 0 if gap >= -tie else 1

    # once settled, the verdict is taken: the winner learns from every light for the rest of its schedule
    # each model from the first learning rate it would learn at in the field: the residual with its Gaussians
    # taken out at ``learned_residual_rate``, the images at ``learned_rate``
    images_rate = learned_rate(settings, wp.get_device(device).is_cuda)
    rates = (images_rate if sees else residual_rate(settings), images_rate)
    trained, histories = _train(targets, directions, settings=settings, device=device, progress=progress, used=used,
                                settle=settle, settle_used=np.arange(n), rate=rates, inputs=inputs,
                                stop_when_settled=not winner_kept)
    models = [_residual_model(model, height, width, factor, n, tint) for model, tint in zip(trained, tints)]
    if settled_at:  # scored when the order settled, while the left-out lights were still left out
        epoch, first, second = settled_at[0]
        check = LearnedCheck(lights, first, second, settled_epoch=epoch, learned_every_light=winner_kept,
                             tie_margin_db=tie, sees_gaussians=sees, glides=gliding)
    else:
        check = LearnedCheck(lights, *score(trained), tie_margin_db=tie, sees_gaussians=sees, glides=gliding)
    keeps = check.keeps_gaussians
    exact = None if sees else exact_residual_scores(images, own, colour, lights, highlights, factor=factor,
                                                    specular=specular, level=settings.diffuse_under_highlights)
    return dataclasses.replace(check, winner=models[0] if keeps else models[1],
                               history=tuple(histories[0 if keeps else 1]), exact_residual=exact)


def exact_residual_scores(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, lights: np.ndarray,
                          highlights: np.ndarray, *, factor: float, specular: np.ndarray | None = None,
                          level: float = 0.0) -> np.ndarray:
    """(m,) 8-bit sRGB PSNR (dB) at each left-out light of ``lights`` of what a learned residual with the Gaussians
    would show there if its residual were exact: the residual it learns at that light (the (n, H, W, 3) image less
    its own (n, H, W) highlights in colour c, or the diffuse part under them with the ``specular`` part, as
    ``_targets`` takes them), plus the (m, H, W, 3) ``highlights`` moved there from the other lights, against the
    image; field units, ``factor`` per display unit. Where it is low the Gaussians' move loses, whatever the residual
    learns; where it is high and the model's own score is not, the residual does."""
    tint = np.ones((1, 1, 3), np.float32) if colour is None else np.asarray(colour, np.float32)
    scale = np.float32(1.0 / factor)

    def light(k: int) -> float:
        j = int(lights[k])
        residual = learned_target(images[j], own[j], tint, None if specular is None else specular[j], level)
        shown = np.maximum(residual + np.asarray(highlights[k], np.float32), 0.0)  # as relit
        return srgb_psnr(shown * scale, np.asarray(images[j], np.float32) * scale)

    return np.array(parallel_map(light, range(len(lights))), dtype=np.float64)


def bounded(residual: ResidualModel, images: np.ndarray, own: np.ndarray, colour: np.ndarray | None) -> ResidualModel:
    """``residual`` with its learned residual's bounds (``residual_bounds``)."""
    learned = residual.learned
    bounds = residual_bounds(images, own, colour)
    return dataclasses.replace(residual, learned=dataclasses.replace(learned, bounds=bounds))


def residual_bounds(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None) -> np.ndarray:
    """A learned residual's bounds (``model.residual.learned_bounds``) from what it learned, per pixel and channel:
    the lowest and highest over the captured lights of the (n, H, W, 3) images (field units) less their own (n, H,
    W) highlights in colour c (None: white), widened by the images' own range, a band of rows at a time on each
    thread. The decoder's values are not used: its error at the captured lights (a faint haze over a background
    that every light leaves black) would widen the bounds by as much."""
    n, height, width, channels = np.shape(images)
    tint = None if colour is None else np.asarray(colour, np.float32)
    white = np.ones((1, 1, channels), np.float32)
    lowest = np.empty((height, width, channels), np.float32)
    highest, span = np.empty_like(lowest), np.empty_like(lowest)

    def band(rows: slice) -> None:
        low = high = darkest = brightest = None
        tint_rows = white if tint is None else tint[rows]
        for i in range(n):
            image = np.asarray(images[i, rows], np.float32)
            values = residual_of(image, own[i, rows], tint_rows)
            low = values if low is None else np.minimum(low, values)
            high = values if high is None else np.maximum(high, values)
            darkest = image if darkest is None else np.minimum(darkest, image)
            brightest = image if brightest is None else np.maximum(brightest, image)
        lowest[rows], highest[rows], span[rows] = low, high, brightest - darkest

    parallel_map(band, row_bands(images))
    return learned_bounds(lowest, highest, span)


def _decoded_display(learned: NeuralResidual, directions: np.ndarray, device,
                     highlights: np.ndarray | None = None) -> np.ndarray:
    """(Q, H W, 3) float32 the learned residual's decoder outputs (signed sRGB display units) at (Q, 3) directions,
    decoded on the device (NumPy on the CPU); ``highlights``: (Q, H, W) the Gaussians' luminance there (field units),
    for a decoder that sees them."""
    device = wp.get_device(device)
    height, width, _ = learned.codes.shape
    codes = learned.codes.reshape(height * width, -1).astype(np.float32)
    directions = np.asarray(directions, np.float32)
    inputs = None if highlights is None else _display_inputs(highlights, learned.unit)
    if device.is_cuda:
        return decode(NeuralDecoder(codes, list(learned.standard_weights)), directions, device=device,
                      highlights=inputs)
    return decode_cpu(codes, learned.weights, directions, inputs)


def _decoded(learned: NeuralResidual, directions: np.ndarray, device,
             highlights: np.ndarray | None = None) -> np.ndarray:
    """(Q, H, W, 3) the learned residual (field units) at (Q, 3) directions, decoded on the device (NumPy on the
    CPU); ``highlights`` as ``_decoded_display`` takes them."""
    height, width, _ = learned.codes.shape
    values = _decoded_display(learned, directions, device, highlights)
    return learned.unit * decode_display(values).reshape(len(values), height, width, 3)
