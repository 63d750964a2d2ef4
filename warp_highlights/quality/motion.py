"""What a person sees when the light moves: how the highlights of relit frames along a light path follow
the ground truth's. Where a still-image score cannot tell a gliding highlight from one that fades out
in one place and in at another, these can:

- ghost share: light added where the truth has no highlight (a cross-fade's second copy, a highlight
  left behind), over the truth's highlight energy;
- visible ghost share: the same, counting only pixels where the added light is itself as bright as
  the faintest highlight (``NONE_LEVEL`` of the peak): a copy of a highlight that can be seen, not the
  faint error of the shading spread over the object, which over a whole object can outweigh a small,
  sharp highlight's energy (``VISIBLE_GHOST_LEVEL``);
- position error: how far each of the truth's highlights is from where the frame puts it, in
  reference pixels (1 rpx = 1/270 of the image height, docs/method.md);
- flicker: frame-to-frame change unlike the truth's (a highlight that jumps, pops or stutters, then
  stands still): per step, how much the RMS change between consecutive frames differs from the
  truth's, in 8-bit sRGB levels. A highlight that glides a little off its place changes as much as
  the truth does and does not flicker.

All on luminance (Rec. 709 weights) of linear frames, float64 NumPy; one call scores a whole path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..io.images import display_rgb8
from ..model.residual import LUMINANCE_WEIGHTS

__all__ = ["HIGHLIGHT_LEVEL", "NONE_LEVEL", "REFERENCE_HEIGHT_PX", "VISIBLE_GHOST_LEVEL", "MotionScores", "flicker",
           "highlight_motion", "motion_scores", "visible_ghost_share"]

HIGHLIGHT_LEVEL = 0.25
"""A truth pixel belongs to a highlight where its specular luminance is at least this share of the
frame's brightest specular pixel: the core of a lobe, not its faint tails (a quarter of the peak is
where a Gaussian lobe is ~1.7 sigma out)."""
NONE_LEVEL = 0.02
"""Where the truth's specular luminance is below this share of its frame's peak, the truth shows no
highlight: light added there is a ghost."""
VISIBLE_GHOST_LEVEL = NONE_LEVEL
"""Light added where the truth shows no highlight counts as a visible ghost where it is at least this share of
the frame's specular peak: where the truth would itself show a highlight. Below it lies the faint error of the
shading: on the sharp donut at 16 lights (``python benchmarks/bench_motion.py --scenes donut-sharp --captures
dome16 --learned``, 2-core CPU) it makes 73% of the default field's ghost share and 94% of the learned
residual's alone, against 29% of the alpha blend's, whose second copies are plain to see."""
REFERENCE_HEIGHT_PX = 270
"""Image height at which 1 rpx is one pixel (docs/method.md)."""


@dataclass(frozen=True)
class MotionScores:
    """Per-frame motion scores of one method along one path.

    Attributes:
        ghost_share: (F,) light added where the truth has no highlight, over the truth's specular
            energy (linear luminance sums; NaN where the truth has no highlight at all).
        visible_ghost_share: (F,) the part of it where the added light is at least
            ``VISIBLE_GHOST_LEVEL`` of the frame's specular peak.
        position_error_rpx: (F,) energy-weighted mean distance of the truth's highlights from the
            frame's (rpx; NaN where the truth has none).
        flicker: (F - 1,) |RMS(frame[t+1] - frame[t]) - RMS(truth[t+1] - truth[t])|, 8-bit sRGB levels.
    """

    ghost_share: np.ndarray
    position_error_rpx: np.ndarray
    flicker: np.ndarray
    visible_ghost_share: np.ndarray

    def summary(self) -> dict:
        """Means over the frames (NaN frames left out), rounded for a table."""
        def mean(values):
            values = np.asarray(values, dtype=np.float64)
            finite = values[np.isfinite(values)]
            return round(float(finite.mean()), 4) if finite.size else None

        return {"ghost_share": mean(self.ghost_share), "visible_ghost_share": mean(self.visible_ghost_share),
                "position_error_rpx": mean(self.position_error_rpx), "flicker_levels": mean(self.flicker)}


def _luminance(stack: np.ndarray) -> np.ndarray:
    stack = np.asarray(stack, dtype=np.float64)
    if stack.ndim == 4:
        return stack @ np.asarray(LUMINANCE_WEIGHTS, dtype=np.float64)
    return stack


def highlight_motion(frames: np.ndarray, truth: np.ndarray, truth_specular: np.ndarray,
                     truth_diffuse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) ghost share and (F,) position error (rpx) of relit ``frames`` against the truth.

    Args:
        frames, truth: (F, H, W) or (F, H, W, C) linear images: the method's and the ground truth.
        truth_specular, truth_diffuse: the truth's specular and diffuse parts (same shapes): where the
            highlights are, and what the frame shows besides them.

    The frame's highlight is what it shows above the truth's diffuse part. Each connected highlight
    of the truth (pixels at ``HIGHLIGHT_LEVEL`` of the peak or more) is compared within its box
    grown by its own size on every side: the distance of the centroids of the truth's specular and
    the frame's highlight there, weighted by the truth highlight's energy.
    """
    shown, true_full = _luminance(frames), _luminance(truth)
    specular, diffuse = np.maximum(_luminance(truth_specular), 0.0), _luminance(truth_diffuse)
    count, height = len(shown), shown.shape[1]
    ghost = np.full(count, np.nan)
    error = np.full(count, np.nan)
    rows, cols = np.mgrid[0:height, 0:shown.shape[2]].astype(np.float64)
    for f in range(count):
        peak = float(specular[f].max())
        if peak <= 0.0:
            continue
        total = float(specular[f].sum())
        none = specular[f] < NONE_LEVEL * peak
        ghost[f] = float(np.maximum(shown[f] - true_full[f], 0.0)[none].sum()) / total
        labels, found = ndimage.label(specular[f] >= HIGHLIGHT_LEVEL * peak)
        if found == 0:
            continue
        excess = np.maximum(shown[f] - diffuse[f], 0.0)
        distances, weights = [], []
        for index, box in enumerate(ndimage.find_objects(labels), start=1):
            grow_r, grow_c = box[0].stop - box[0].start, box[1].stop - box[1].start
            window = (slice(max(box[0].start - grow_r, 0), box[0].stop + grow_r),
                      slice(max(box[1].start - grow_c, 0), box[1].stop + grow_c))
            true_part = specular[f][window]
            true_energy = np.where(labels[window] == index, true_part, 0.0).sum()
            shown_part = excess[window]
            shown_energy = shown_part.sum()
            if shown_energy <= 0.0:  # nothing there at all: the highlight is as far off as its window
                distances.append(float(np.hypot(*true_part.shape)))
            else:
                true_centre = (np.array([(true_part * rows[window]).sum(), (true_part * cols[window]).sum()])
                               / true_part.sum())
                shown_centre = (np.array([(shown_part * rows[window]).sum(), (shown_part * cols[window]).sum()])
                                / shown_energy)
                distances.append(float(np.linalg.norm(true_centre - shown_centre)))
            weights.append(true_energy)
        error[f] = float(np.average(distances, weights=weights)) * REFERENCE_HEIGHT_PX / height
    return ghost, error


def visible_ghost_share(frames: np.ndarray, truth: np.ndarray, truth_specular: np.ndarray) -> np.ndarray:
    """(F,) light added where the truth has no highlight (below ``NONE_LEVEL`` of the frame's specular peak),
    counted only where it is at least ``VISIBLE_GHOST_LEVEL`` of that peak, over the truth's specular energy
    (linear luminance sums; NaN where the truth has no highlight at all)."""
    added = np.maximum(_luminance(frames) - _luminance(truth), 0.0)
    specular = np.maximum(_luminance(truth_specular), 0.0)
    peak = specular.reshape(len(specular), -1).max(axis=1)[:, None, None]
    total = specular.reshape(len(specular), -1).sum(axis=1)
    seen = (specular < NONE_LEVEL * peak) & (added >= VISIBLE_GHOST_LEVEL * peak)
    ghost = np.where(seen, added, 0.0).reshape(len(added), -1).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(peak[:, 0, 0] > 0.0, ghost / np.where(total > 0.0, total, 1.0), np.nan)


def flicker(frames: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(F - 1,) per step between consecutive frames, the RMS change over pixels and channels (8-bit sRGB
    levels, ``display_rgb8``) minus the truth's, in absolute value: 0 when the frames change as much as
    the truth does at every step."""
    def steps(stack):
        codes = np.stack([display_rgb8(frame) for frame in stack]).astype(np.float64)
        change = np.diff(codes, axis=0)
        return np.sqrt((change**2).reshape(len(change), -1).mean(axis=1))

    return np.abs(steps(frames) - steps(truth))


def motion_scores(frames: np.ndarray, truth: np.ndarray, truth_specular: np.ndarray,
                  truth_diffuse: np.ndarray) -> MotionScores:
    """Every motion score of ``frames`` along a path (``highlight_motion``, ``visible_ghost_share`` and
    ``flicker``)."""
    ghost, error = highlight_motion(frames, truth, truth_specular, truth_diffuse)
    return MotionScores(ghost, error, flicker(frames, truth), visible_ghost_share(frames, truth, truth_specular))
