"""Image quality, computed in one place: PSNR of linear values, PSNR and SSIM of images as shown in
8-bit sRGB. Imports io (the sRGB encoding) and the model; fit and relight both score with it
(ARCHITECTURE.md).

- ``psnr``: dB with peak 1 over the last two axes of linear values clipped to [0, 1].
- ``psnr_of_mse``: dB with peak 1 of mean squared errors (e.g. ``kernels.losses.clipped_mse``'s).
- ``psnr_excluding_black``: (Q,) dB per image of a stack; NaN where both images are all black.
- ``psnr_8bit``: dB (peak 255, at most 100) of two 8-bit images.
- ``srgb_psnr``: dB of two linear images as shown in 8-bit sRGB.
- ``ssim_8bit``: scikit-image's SSIM of two 8-bit RGB images.
- ``srgb_scores``: (Q,) PSNR and SSIM of linear image stacks shown in 8-bit sRGB.
- ``scoring_processes``: a scope in which ``srgb_scores`` of large stacks runs in worker processes.
- ``motion_scores``: ghosts, position error and flicker of relit frames along a light path.
- ``MotionScores``: those scores per frame, and their means.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {**dict.fromkeys(
        ["psnr", "psnr_of_mse", "psnr_excluding_black", "psnr_8bit", "srgb_psnr", "ssim_8bit", "srgb_scores",
         "scoring_processes"],
        "metrics",
    ),
     **dict.fromkeys(["motion_scores", "MotionScores"], "motion")},
)
