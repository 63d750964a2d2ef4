"""The learned residual (9 numbers per pixel and an MLP of code and light direction, ``kernels.neural``)
and its check: whether it keeps the moving Gaussians or learns the images alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels.neural import NeuralDecoder, train_decoder
from ..model.config import LEARNED_BATCH_CPU, LEARNED_BATCH_CUDA, ResidualSettings
from ..model.errors import InputError
from ..model.residual import (
    NeuralResidual,
    ResidualModel,
)
from ..quality.metrics import srgb_psnr
from .decode import learned_images
from .inputs import residual_of
from .opponent import encode_display

__all__ = ["LearnedCheck", "check_learned", "learn_residual"]

_TUNE_RATE = 3e-4  # the learned check's winner goes on at the final learning rate of train_decoder's schedule
_EVERY_FEW_EPOCHS = tuple(f"epoch {k}/" for k in (1, 10, 50, 100, 200, 400, 1000))  # the learned residual's log lines


def learn_residual(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, directions: np.ndarray, *,
                   factor: float,
                   settings: ResidualSettings, device, log=None, progress=None, used: np.ndarray | None = None,
                   initial: NeuralResidual | None = None, tune: bool = False) -> tuple[ResidualModel, list[float]]:
    """A ``ResidualModel`` holding a learned residual of the (n, H, W, 3) images (field units) minus their
    own (n, H, W) highlights in colour c: ``kernels.neural`` trained on the residual in signed sRGB
    display units (the field's units over ``factor``) at the (n, 3) light directions, for
    ``settings.learned_seconds`` or ``learned_epochs`` at most, ``learned_batch`` samples a step; ``progress(1)`` after
    each epoch, ``log`` a line now and then; ``used``: the lights it learns from (default all). ``initial``: a model to
    go on training; ``tune``: for ``settings.learned_tune_seconds`` at the final learning rate (the learned
    check's winner learning the lights it left out). Returns it and the loss per epoch."""
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[3] != 3:
        raise InputError("a learned residual needs colour (RGB) images; fit grey captures with --residual lowrank")
    n, height, width, _ = images.shape
    tint = np.ones((1, 1, 3), np.float32) if colour is None else colour
    targets = encode_display(residual_of(images, own, tint) / np.float32(factor)).reshape(n, height * width, 3)

    def say(message: str) -> None:  # once an epoch
        if progress is not None:
            progress(1)
        if log is not None and message.startswith(_EVERY_FEW_EPOCHS):
            log(f"learned residual: {message}")

    rates = ({"lr": _TUNE_RATE, "final_lr": _TUNE_RATE, "seconds": float(settings.learned_tune_seconds)} if tune
             else {"seconds": float(settings.learned_seconds)})
    start = None if initial is None else NeuralDecoder(initial.codes.reshape(height * width, -1).astype(np.float32),
                                                       [np.asarray(w, np.float32) for w in initial.weights])
    batch = int(settings.learned_batch) or (LEARNED_BATCH_CUDA if wp.get_device(device).is_cuda else LEARNED_BATCH_CPU)
    model, history = train_decoder(targets, directions, device=device, epochs=int(settings.learned_epochs), batch=batch,
                                   log=say, used=used,
                                   initial=start, **rates)
    learned = NeuralResidual(model.codes.reshape(height, width, -1).astype(np.float16), tuple(model.weights),
                             float(factor), n)
    return ResidualModel(learned=learned, highlight_colour=colour), history


@dataclass(frozen=True)
class LearnedCheck:
    """What ``check_learned`` measured at its left-out lights (m,): 8-bit sRGB PSNR (dB) of the learned
    residual plus the moved highlights (``with_gaussians``) and of the images learned alone, and the
    winner's model (learned without those lights)."""

    lights: np.ndarray
    with_gaussians: np.ndarray
    images_alone: np.ndarray
    winner: ResidualModel | None = None

    @property
    def keeps_gaussians(self) -> bool:
        """True unless the images learned alone scored higher on average (no light checked: True)."""
        return not len(self.lights) or float(np.mean(self.with_gaussians)) >= float(np.mean(self.images_alone))

    def report(self) -> dict:
        """Plain figures for the fit report: the lights checked, the verdict and, where any were checked, both
        models' mean scores."""
        scores = {}
        if len(self.lights):
            scores = {"with_gaussians_psnr_db": round(float(np.mean(self.with_gaussians)), 3),
                      "images_alone_psnr_db": round(float(np.mean(self.images_alone)), 3)}
        return {"lights": int(len(self.lights)), **scores, "keeps_gaussians": self.keeps_gaussians}


def check_learned(images: np.ndarray, own: np.ndarray, colour: np.ndarray | None, directions: np.ndarray,
                  lights: np.ndarray,
                  highlights: np.ndarray, *, factor: float, settings: ResidualSettings, device,
                  progress=None) -> LearnedCheck:
    """Whether a learned residual should keep the moving Gaussians: two models learn, each as long as
    ``learn_residual`` would, from every light but ``lights`` (m,): one the residual of the (n, H, W, 3)
    images (field units) minus their own (n, H, W) highlights in colour c, the other the images alone
    (NeuralRTI). At each left-out light the first plus ``highlights`` (m, H, W, 3), the Gaussians moved
    there from the other lights' triangle (``MoveCheck.kept_highlights``), and the second are scored
    against the image in 8-bit sRGB. Both train in full because the ranking changes with training
    (a short run favours the residual, whose Gaussians carry the highlights from the start).
    ``progress(1)`` after each epoch."""
    lights = np.asarray(lights, dtype=np.int64)
    if not len(lights):
        return LearnedCheck(lights, np.zeros(0), np.zeros(0))
    used = np.setdiff1d(np.arange(len(images)), lights)
    scale = np.float32(1.0 / factor)
    truth = np.asarray(images[lights], np.float32) * scale
    scores, models = [], []
    for own_images, tint, added in ((own, colour, highlights), (np.zeros_like(own), None, np.zeros_like(highlights))):
        model, _ = learn_residual(images, own_images, tint, directions, factor=factor, settings=settings, device=device,
                                  progress=progress, used=used)
        # as the relighter clamps
        predicted = np.maximum(learned_images(model.learned, directions[lights]) + added, 0.0)
        scores.append(np.array([srgb_psnr(p * scale, t) for p, t in zip(predicted, truth)]))
        models.append(model)
    check = LearnedCheck(lights, scores[0], scores[1])
    return dataclasses.replace(check, winner=models[0] if check.keeps_gaussians else models[1])
