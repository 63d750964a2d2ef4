"""Hyper-parameters of the method, in one place, in resolution-independent units.

Units (docs/method.md, Units and conventions): Gaussian positions and sizes are *normalised by image height* (the image
spans y in (0, 1)); user-facing lengths are in *reference pixels* (rpx), 1 rpx = 1/270 of the image
height, so the thesis' values (it worked at 480 x 270) hold at every resolution. Lengths are converted
from rpx to normalised units here and nowhere else.

Where the thesis gives a value it is the default; every other default says how it was chosen.
This module holds one thing: the settings of a fit (one frozen dataclass per stage), their checks and
the overrides that edit them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from .errors import InputError

__all__ = [
    "REFERENCE_HEIGHT_PX",
    "AdamSettings",
    "ComponentSettings",
    "DistilSettings",
    "EstimationSettings",
    "FitSettings",
    "MapSettings",
    "PathSettings",
    "RasterSettings",
    "ResidualSettings",
    "RetargetSettings",
    "SegmentationSettings",
    "StructureLossSettings",
    "normalized_to_rpx",
    "pixel_area_rpx2",
    "rpx_to_normalized",
]

REFERENCE_HEIGHT_PX = 270
"""Image height, in pixels, that defines one reference pixel (the thesis' working height)."""


def rpx_to_normalized(length_rpx: float) -> float:
    """A length in reference pixels as a length in image heights."""
    return float(length_rpx) / REFERENCE_HEIGHT_PX


def normalized_to_rpx(length: float) -> float:
    """A length in image heights as a length in reference pixels."""
    return float(length) * REFERENCE_HEIGHT_PX


def pixel_area_rpx2(height_px: int) -> float:
    """Area of one pixel of an image ``height_px`` pixels tall, in rpx^2 (1 at the thesis' 270 rows).

    Image sums (the fit loss) are weighted by it so they measure the same thing at every resolution.
    """
    return (REFERENCE_HEIGHT_PX / float(height_px)) ** 2


MAX_ITERATIONS = 100_000
"""Most optimiser iterations a stage accepts (about 100x the defaults: hours on a laptop CPU); more is
a typing mistake rather than a fit."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


@dataclass(frozen=True)
class RasterSettings:
    """How Gaussians are drawn (docs/method.md, Building blocks).

    Attributes:
        cutoff: truncation radius in Mahalanobis units. Beyond it a Gaussian is exactly zero; inside,
            the cut-off level exp(-cutoff^2 / 2) is subtracted and the rest rescaled so the peak stays
            a^2 and the Gaussian falls to zero continuously (no jump for the optimiser or the
            gradient check). The change from the untruncated Gaussian is at most
            a^2 exp(-cutoff^2 / 2) anywhere (3.4e-4 a^2 at the default 4, method.md's value).
        sigma_eps_rpx2: epsilon added to sigma^2 in the covariance, rpx^2. The thesis leaves it
            unspecified; 0.01 rpx^2 (a floor of 0.1 rpx on the standard deviation) keeps a collapsed
            Gaussian finite without changing any Gaussian wider than half a pixel by more than 2%.
            A Gaussian that collapses between pixel centres draws nothing and gets no gradient; the
            estimation's pruning removes Gaussians narrower than 0.05 pixel.
        tile_size: culling tile edge in pixels, a power of two (a performance knob; it never changes
            the image). 8, 16 and 32 measure within 2% of each other on the CPU and on an NVIDIA H200
            (benchmarks/bench_raster.py --tile-sizes 8,16,32); 16 is the middle one.
        upsampled_min_sigma_px: drawn larger than the field, a Gaussian is at least this wide along each
            axis, in the field's pixels, with a^2 sigma_x sigma_y kept (the same light). A narrower one is
            not resolved by the field's pixels (the fit saw it only at their centres) and, sampled finer,
            shows as a bright speck: on the dome sample fitted at 192 x 192 and relit at 320 x 320 at its
            69 lights, a Gaussian of 0.29 px rose 30 levels (8-bit sRGB) above the field's own image
            enlarged. 0.5 px leaves 16 levels, 0.6 px 10, 0.7 px 7 (and one-pixel outliers of 11 levels
            above their 3 x 3 median, as 1.0 px leaves: the texture's own); 0.7 is the least that gets
            there (benchmarks/bench_relight_size.py --specks). The image at the field's size, and any
            Gaussian at least this wide, are unchanged.
    """

    cutoff: float = 4.0
    sigma_eps_rpx2: float = 0.01
    tile_size: int = 16
    upsampled_min_sigma_px: float = 0.7

    def __post_init__(self):
        _require(math.isfinite(self.cutoff) and 1.0 <= self.cutoff <= 12.0,
                 f"cutoff must be in [1, 12] Mahalanobis units, got {self.cutoff}")
        _require(math.isfinite(self.sigma_eps_rpx2) and self.sigma_eps_rpx2 > 0,
                 f"sigma_eps_rpx2 must be > 0, got {self.sigma_eps_rpx2}")
        _require(self.tile_size in (4, 8, 16, 32), f"tile_size must be 4, 8, 16 or 32 pixels, got {self.tile_size}")
        _require(math.isfinite(self.upsampled_min_sigma_px) and 0.0 <= self.upsampled_min_sigma_px <= 4.0,
                 f"upsampled_min_sigma_px must be in [0, 4] pixels, got {self.upsampled_min_sigma_px}")

    @property
    def sigma_eps(self) -> float:
        """The covariance epsilon in normalised units (image heights squared)."""
        return self.sigma_eps_rpx2 / REFERENCE_HEIGHT_PX**2

    @property
    def cutoff_level(self) -> float:
        """exp(-cutoff^2 / 2): the fraction of the peak at which a Gaussian is cut."""
        return math.exp(-0.5 * self.cutoff**2)


@dataclass(frozen=True)
class StructureLossSettings:
    """The structure loss of retargeting (docs/method.md, Fitting step 5).

    Attributes:
        gamma_per_rpx: steepness of the neighbourhood weight h; thesis value 4 (per rpx).
        threshold_rpx: distance m at which h = 1/2; thesis value 15 rpx.
        scale_eps_rpx: epsilon in the scale factor's denominator, rpx; only guards an all-coincident
            reference set (1e-6 rpx is far below any distance that matters).
    """

    gamma_per_rpx: float = 4.0
    threshold_rpx: float = 15.0
    scale_eps_rpx: float = 1e-6

    def __post_init__(self):
        _require(math.isfinite(self.gamma_per_rpx) and self.gamma_per_rpx > 0,
                 f"gamma_per_rpx must be > 0, got {self.gamma_per_rpx}")
        _require(math.isfinite(self.threshold_rpx) and self.threshold_rpx > 0,
                 f"threshold_rpx must be > 0, got {self.threshold_rpx}")
        _require(math.isfinite(self.scale_eps_rpx) and self.scale_eps_rpx > 0,
                 f"scale_eps_rpx must be > 0, got {self.scale_eps_rpx}")


@dataclass(frozen=True)
class AdamSettings:
    """Adam (Kingma and Ba 2014) with one learning rate per parameter group.

    Learning rates are step sizes: Adam moves a parameter by about one learning rate per iteration
    when its gradient keeps its sign. Lengths are in rpx, so they mean the same at every resolution.
    The thesis gives none. The defaults come from benchmarks/tune_adam.py (results in
    benchmarks/README.md): 36 settings x 64 trials of recovering three Gaussians (sigma 2-20 rpx)
    started 4 rpx, 30% and 0.25 rad off. This setting and the same with lr_amplitude 0.05 were the
    fastest (median 40 iterations) of the four that recovered all 64 within 1000 iterations; the
    smaller amplitude step was kept. Estimation and retargeting may retune them.

    Attributes:
        lr_amplitude: step of a (the square root of the peak intensity).
        lr_mean_rpx: step of the mean, rpx.
        lr_sigma_rpx: step of sigma_x, sigma_y, rpx.
        lr_theta: step of the rotation, radians.
        beta1, beta2, epsilon: Adam's moment decay rates and denominator guard (the usual values).
    """

    lr_amplitude: float = 0.02
    lr_mean_rpx: float = 0.25
    lr_sigma_rpx: float = 0.25
    lr_theta: float = 0.01
    beta1: float = 0.9
    beta2: float = 0.999
    epsilon: float = 1e-8

    def __post_init__(self):
        for name in ("lr_amplitude", "lr_mean_rpx", "lr_sigma_rpx", "lr_theta", "epsilon"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value >= 0, f"{name} must be a finite number >= 0, got {value}")
        for name in ("beta1", "beta2"):
            value = getattr(self, name)
            _require(math.isfinite(value) and 0 <= value < 1, f"{name} must be in [0, 1), got {value}")


@dataclass(frozen=True)
class SegmentationSettings:
    """Diffuse/specular split per pixel (docs/method.md, Fitting step 1; thesis values).

    Attributes:
        valid_threshold: a light counts for a pixel's Lambertian fit when its value is at least this
            (linear radiance; thesis t_seg = 0.05): darker samples are shadowed or unlit.
        outlier_factor: after each fit, lights whose residual exceeds this many times the median
            residual are left out of the next fit (thesis: 2).
        outlier_floor: the outlier limit is never below this (linear radiance). Neither method.md nor
            the thesis has it: on an exactly Lambertian pixel the residuals are float32 rounding
            noise (~1e-6), and twice their median would drop lights on noise alone, refit on fewer
            lights and run to the iteration cap. 1e-4 is far below any visible highlight.
        nonnegative_ambient: the ambient term k_a is kept >= 0 (where a fit's k_a comes out negative, nbar is
            fitted alone with k_a = 0, the least-squares minimum under that bound); the thesis fits it freely.
            Light adds up, so a negative ambient only ever explains a highlight: with few lit samples (a
            sparse capture, a broad lobe) the free fit takes the top light's highlight into a steep normal
            and a negative offset and leaves it out of the specular part. Measured on the dome sample fitted
            on 16, 25 and 49 of its lights (docs/method.md, Fitting step 1, has the figures and the command).
        max_iterations: cap on the fits per pixel, the first included (method.md: 10).
        min_valid_lights: pixels with fewer valid lights are all diffuse (4 unknowns need 4 lights).
        diffuse_floor, diffuse_offset: the fitted diffuse becomes max(D~, floor) + offset before
            D = min(I, D~) (thesis: 0.05 and 0.01), so noise on dark pixels stays diffuse.
    """

    valid_threshold: float = 0.05
    outlier_factor: float = 2.0
    outlier_floor: float = 1e-4
    nonnegative_ambient: bool = True
    max_iterations: int = 10
    min_valid_lights: int = 4
    diffuse_floor: float = 0.05
    diffuse_offset: float = 0.01

    def __post_init__(self):
        _require(math.isfinite(self.valid_threshold) and self.valid_threshold >= 0,
                 f"valid_threshold must be >= 0, got {self.valid_threshold}")
        _require(math.isfinite(self.outlier_factor) and self.outlier_factor >= 1,
                 f"outlier_factor must be >= 1, got {self.outlier_factor}")
        _require(1 <= int(self.max_iterations) <= 100, f"max_iterations must be in [1, 100], got {self.max_iterations}")
        _require(int(self.min_valid_lights) >= 4,
                 f"min_valid_lights must be >= 4 (the fit has 4 unknowns), got {self.min_valid_lights}")
        for name in ("diffuse_floor", "diffuse_offset", "outlier_floor"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value >= 0, f"{name} must be >= 0, got {value}")


@dataclass(frozen=True)
class EstimationSettings:
    """Fitting a few Gaussians to every specular image (docs/method.md, Fitting step 2).

    iterations, densify_every, densify_until, residual_threshold and capacity are method.md's values
    (the thesis' schedule and t_est). The region-size floor, the per-round cap and the pruning limits
    are ours: set by hand on the 64-light 240x135 donut, where they dropped single-pixel noise regions
    and collapsed Gaussians without losing a visible highlight; they were not swept.

    Attributes:
        iterations: Adam steps in all (T_est).
        densify_every: iterations between two add/prune rounds (K_add); the first round is at 0.
        densify_until: no add/prune round at or after this iteration (T_add); a final prune runs at
            the end.
        residual_threshold: a pixel whose residual S - R exceeds this (linear radiance, thesis
            t_est = 0.2) belongs to a region that gets a new Gaussian.
        min_region_area_rpx2: regions smaller than this (rpx^2) get no Gaussian: single noisy pixels
            would otherwise each get one.
        max_new_per_round: at most this many Gaussians are added to a set per round, largest
            regions first, so a set grows only as fast as Adam can place what it has.
        prune_energy: Gaussians with less energy than this (intensity x rpx^2) are removed, as are
            Gaussians whose centre left the image by more than prune_outside_sigmas of their size,
            Gaussians narrower than 0.05 pixel across (they reach almost no pixel centre, so they
            neither draw nor learn) and Gaussians with non-finite parameters.
        capacity: slots per set (padding; a set never holds more Gaussians).
        max_pixels_per_rpx: the Gaussians are estimated and retargeted on the specular images shrunk
            by a whole factor (area average) until a reference pixel is at most this many pixels
            across, i.e. at most this x 270 rows; the residual keeps the working size. The method's
            lengths are in rpx and its finest (the 0.1 rpx sigma floor, regions of 4 rpx^2) are
            resolved at 2, so larger images only cost time and memory: 1920x1080 and 3840x2160
            captures are fitted at 960x540. 0: never shrink. Every capture up to 540 rows (the
            samples, the 480x270 renders) is fitted at its own size.
        adam: learning rates (AdamSettings).
    """

    iterations: int = 1000
    densify_every: int = 100
    densify_until: int = 600
    residual_threshold: float = 0.2
    min_region_area_rpx2: float = 4.0
    max_new_per_round: int = 8
    prune_energy: float = 1.0
    prune_outside_sigmas: float = 2.0
    capacity: int = 64
    max_pixels_per_rpx: float = 2.0
    adam: AdamSettings = AdamSettings()

    def __post_init__(self):
        _require(1 <= int(self.iterations) <= MAX_ITERATIONS,
                 f"iterations must be in [1, {MAX_ITERATIONS}], got {self.iterations}")
        _require(1 <= int(self.densify_every) <= MAX_ITERATIONS,
                 f"densify_every must be in [1, {MAX_ITERATIONS}], got {self.densify_every}")
        _require(1 <= int(self.densify_until) <= MAX_ITERATIONS,
                 f"densify_until must be in [1, {MAX_ITERATIONS}] (no add round means no Gaussians), got "
                 f"{self.densify_until}")
        _require(math.isfinite(self.residual_threshold) and self.residual_threshold > 0,
                 f"residual_threshold must be > 0, got {self.residual_threshold}")
        _require(math.isfinite(self.min_region_area_rpx2) and self.min_region_area_rpx2 >= 0,
                 f"min_region_area_rpx2 must be >= 0, got {self.min_region_area_rpx2}")
        _require(int(self.max_new_per_round) >= 1, f"max_new_per_round must be >= 1, got {self.max_new_per_round}")
        _require(math.isfinite(self.prune_energy) and self.prune_energy >= 0,
                 f"prune_energy must be >= 0, got {self.prune_energy}")
        _require(math.isfinite(self.prune_outside_sigmas) and self.prune_outside_sigmas >= 0,
                 f"prune_outside_sigmas must be >= 0, got {self.prune_outside_sigmas}")
        _require(1 <= int(self.capacity) <= 1024, f"capacity must be in [1, 1024], got {self.capacity}")
        _require(math.isfinite(self.max_pixels_per_rpx) and self.max_pixels_per_rpx >= 0,
                 f"max_pixels_per_rpx must be >= 0 (0: never shrink), got {self.max_pixels_per_rpx}")

    def gaussian_size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) the Gaussians are fitted at for a ``width`` x ``height`` working size: shrunk
        by the smallest whole factor that leaves at most ``max_pixels_per_rpx`` x 270 rows."""
        rows = self.max_pixels_per_rpx * REFERENCE_HEIGHT_PX
        if self.max_pixels_per_rpx <= 0 or height <= rows:
            return width, height
        factor = math.ceil(height / rows)
        return max(1, round(width / factor)), max(1, round(height / factor))


@dataclass(frozen=True)
class ComponentSettings:
    """Connected components of a Gaussian set (docs/method.md, Fitting step 4).

    Attributes:
        level: two Gaussians touch when their ellipses at this Mahalanobis distance intersect
            (method.md: k = 2).
    """

    level: float = 2.0

    def __post_init__(self):
        _require(math.isfinite(self.level) and self.level > 0, f"level must be > 0, got {self.level}")


@dataclass(frozen=True)
class RetargetSettings:
    """Re-fitting every estimated set onto its neighbours' specular images (docs/method.md, Fitting step 5).

    The defaults come from benchmarks/sweep_retarget.py on the 250-light 480x270 donut (on an NVIDIA
    H100; tables in benchmarks/README.md), scored by what the fit is for: the PSNR of the circular
    interpolation at all 496 triangle centroids against the rendered ground truth. The interpolation
    quality was flat in c_str (within 0.03 dB from 0 to 1) while the structure loss fell from 39 to
    0.2 rpx^2; c_str = 0.1 keeps it at 4 rpx^2 without stiffening the sets. Any c_ene >= 1e-3 cost
    0.3-2 dB, so the energy term stays as a light tie (1e-4, indistinguishable from 0). Short phases
    scored best (50 + 150 iterations ahead of 200 + 500 and 400 + 800): longer fits chase each
    target's detail at the cost of the correspondence the paths rely on. The 64-light 240x135 sweep
    on the CPU agreed: the defaults scored above every swept setting there.

    Attributes:
        rigid_iterations: phase 1 steps (T1): one translation and rotation per connected component.
        iterations: phase 2 steps (T2): every parameter, loss c_fit L_fit + c_str L_str + c_ene L_ene.
        c_fit, c_str, c_ene: weights of the three phase-2 terms (L_fit and L_str in rpx^2 units,
            L_ene in (intensity x rpx^2)^2).
        lr_translation_rpx, lr_rotation: Adam steps of phase 1 (rpx, radians); the translation step
            is 4x estimation's mean step because a whole component travels up to tens of rpx between
            neighbouring lights.
        adam: phase 2 learning rates.
        structure: the structure loss' neighbourhood weights.
        components: when two Gaussians belong to one component.
        search_radius, search_step_rpx, search_prior, search_side, search_gain, search_margin,
            search_exclusion_rpx: phase 1's start (``kernels/search.py``): every component tries the offsets
            of a grid of ``search_step_rpx`` within ``search_radius`` image heights, each scored by its
            overlap with the target blurred by the step, times a prior of width ``search_prior`` image
            heights along the way the half-vector moves the highlight on the image and ``search_side``
            across it; it starts from the best where that scores ``search_gain`` times staying (it has
            all but lost its highlight) and ``search_margin`` times every offset further than
            ``search_exclusion_rpx`` from it (an ambiguous match, e.g. among the glints of a bumpy
            surface, keeps its place). Between far-apart lights a sharp highlight moves further than
            its size and the rigid phase's gradient finds nothing to follow: on the sharp donut of
            benchmarks/bench_motion.py (160x90, 16 dome lights) no Gaussian moved without the search
            and the field equalled the blend (28.2 dB along the paths); with it 205 moved and it scored
            31.7 dB. The values were set on that benchmark's sharp donut and tiled teapot (16 and 49
            lights) against bench_quality's 64-light donut and teapot, which the search must leave
            alone: a smaller gain or a wider prior cost the tiled teapot up to 1.4 dB at 49 lights
            (highlights that vanish on its matte tiles were sent to other highlights). 0 radius: no
            search (the rigid phase from the source, as method.md describes).
        vanish_share: a retargeted Gaussian that kept less than this share of its energy found nothing to follow on
            the target (its highlight vanishes there: a matte tile, a shadow, a lobe that leaves the frame) and is put
            back at its source, so that along that edge it fades in place as the blend does instead of shrinking to a
            point somewhere else (``fit.retargeting.restore_vanished``); 0: none put back. 0.01: on the 2-core CPU
            (``benchmarks/bench_motion.py --scenes donut-sharp,teapot-tiles,bumpy-metal,coin,sphere-broad --captures
            dome16 --frames 48 --set residual.kind=lowrank``, and with ``--set retarget.vanish_share=0``; 160x90) 0
            moved 392 Gaussians of the coin, which the move check had kept still, and lost 1.60 dB along the paths
            (29.72 -> 28.12); it lowered the tiled teapot's ghost share (0.352 -> 0.314) at the same PSNR and moved
            the others' scores by at most 0.02 dB; the dome sample fitted on 25 and 49 of its lights (``--scenes ""
            --photos dome-sample``, the same two settings) scored 35.99 -> 36.45 and 42.14 -> 41.87 dB at its Test
            lights (``benchmarks/results/motion-cpu/bench_motion-vanish-share-{0.01,0}-7151c63.json``).
        follow_lost: a retargeted Gaussian that lost its highlight (vanished, or pushed out of the picture by
            retargeting) goes, with its source's shape and brightness, where its own motion expects the highlight on
            the target, if that is outside the frame (it glides off the picture's edge instead of fading in place),
            or inside it where the target's specular part holds it (``residual.move_support``: a highlight that
            travelled further than the search followed); elsewhere it stays as before (``fit.lost``: each Gaussian's
            motion fitted as a linear map of the half-vector's change, from the edges on which it kept its
            highlight). The dome sample (a flat object under a perspective camera: its highlight crosses the frame
            and leaves it below 50 degrees) fitted on 16, 25 and 49 of its lights with a low-rank residual, 8-bit
            sRGB PSNR at its Test lights (2-core CPU, 160x160, ``python benchmarks/bench_motion.py --scenes ""
            --photos dome-sample --set residual.kind=lowrank``, and with ``--set retarget.follow_lost=false``;
            moving Gaussians in brackets): 29.57 (0) -> 29.89 (6), 35.99 (56) -> 36.30 (66), 42.14 (135) -> 43.21
            (150); its move check at 49 lights, moving against blending, 38.33 -> 41.43 against 35.71 dB. On an H100
            at 320x320 (``--scale gpu --device cuda:0``) the learned check's moved Gaussians at 49 lights scored
            28.67 -> 34.87 dB against 43.89-44.66 for the images learned alone, so the GPU default still keeps none
            there. The 16-light renders of ``benchmarks/bench_motion.py`` (``--captures dome16 --frames 48 --set
            residual.kind=lowrank``, mean PSNR along the three paths) moved within 0.1 dB on the CPU (the tiled
            teapot 30.64 -> 30.72, ghost share 0.352 -> 0.340) and within 0.2 on an H100 at 480x270 (the tiled
            teapot 30.06 -> 30.22, the bumpy donut 27.42 -> 27.23); a highlight that crosses a flat object and
            leaves the frame (``tests/test_lost.py``, 25 dome lights) is relit along a path at half the RMS error.
        lost_share: a retargeted Gaussian with less than this share of the light that it had inside the frame at
            its source still inside it has left the picture (``fit.lost.lost_slots``). 0.1, the share of
            ``residual.move_support``: a Gaussian left with a tenth of its light in the picture has all but left it.
        motion_ridge: how strongly each Gaussian's fitted motion is pulled towards the capture's common isotropic
            one, in shares of the median edge's squared half-vector change (0.25: a quarter of one edge's
            evidence, so a Gaussian found on two edges or more follows its own).
    """

    rigid_iterations: int = 50
    iterations: int = 150
    c_fit: float = 1.0
    c_str: float = 0.1
    c_ene: float = 1e-4
    lr_translation_rpx: float = 1.0
    lr_rotation: float = 0.01
    adam: AdamSettings = AdamSettings()
    structure: StructureLossSettings = StructureLossSettings()
    components: ComponentSettings = ComponentSettings()
    vanish_share: float = 0.01
    follow_lost: bool = True
    lost_share: float = 0.1
    motion_ridge: float = 0.25
    search_radius: float = 0.35
    search_step_rpx: float = 4.0
    search_prior: float = 0.1
    search_side: float = 0.05
    search_gain: float = 20.0
    search_margin: float = 1.5
    search_exclusion_rpx: float = 12.0

    def __post_init__(self):
        _require(math.isfinite(self.vanish_share) and 0 <= self.vanish_share < 1,
                 f"vanish_share must be in [0, 1), got {self.vanish_share}")
        _require(math.isfinite(self.lost_share) and 0 <= self.lost_share <= 1,
                 f"lost_share must be in [0, 1], got {self.lost_share}")
        _require(math.isfinite(self.motion_ridge) and self.motion_ridge > 0,
                 f"motion_ridge must be > 0, got {self.motion_ridge}")
        _require(math.isfinite(self.search_radius) and 0 <= self.search_radius <= 2,
                 f"search_radius must be in [0, 2] image heights, got {self.search_radius}")
        _require(math.isfinite(self.search_step_rpx) and 0.5 <= self.search_step_rpx <= 270,
                 f"search_step_rpx must be in [0.5, 270], got {self.search_step_rpx}")
        _require(math.isfinite(self.search_prior) and self.search_prior > 0,
                 f"search_prior must be > 0, got {self.search_prior}")
        _require(math.isfinite(self.search_side) and self.search_side > 0,
                 f"search_side must be > 0, got {self.search_side}")
        _require(math.isfinite(self.search_gain) and self.search_gain >= 1,
                 f"search_gain must be >= 1, got {self.search_gain}")
        _require(math.isfinite(self.search_margin) and self.search_margin >= 1,
                 f"search_margin must be >= 1, got {self.search_margin}")
        _require(math.isfinite(self.search_exclusion_rpx) and self.search_exclusion_rpx >= 0,
                 f"search_exclusion_rpx must be >= 0, got {self.search_exclusion_rpx}")
        _require(0 <= int(self.rigid_iterations) <= MAX_ITERATIONS,
                 f"rigid_iterations must be in [0, {MAX_ITERATIONS}], got {self.rigid_iterations}")
        _require(0 <= int(self.iterations) <= MAX_ITERATIONS,
                 f"iterations must be in [0, {MAX_ITERATIONS}], got {self.iterations}")
        for name in ("c_fit", "c_str", "c_ene", "lr_translation_rpx", "lr_rotation"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value >= 0, f"{name} must be a finite number >= 0, got {value}")


@dataclass(frozen=True)
class PathSettings:
    """Which way each Gaussian turns along a triangle edge (docs/method.md, Fitting step 6).

    Attributes:
        straight_below: |rotation| (radians) under which the path is the straight segment (no centre).
        length_scale_rpx: unit of the distances in the propagation weights xi = 1 / (1 + rho^2 + rhobar^2)
            (method.md: 15 rpx).
        compare_rotations: what the neighbour vote's sign phi_pq compares: the positive rotation
            options delta+ of the two Gaussians (True, default) or their orientations theta_A in
            [0, pi) (False: method.md / thesis eq. 3.27 as written). Chosen by evaluation: with
            orientations, two near-parallel Gaussians either side of the 0/pi wrap vote against each
            other, and 4.5% of the donut's Gaussians took the longer turn (a needle swinging through
            90 degrees mid-triangle, visible in animations); comparing rotations left 0% and raised
            the circular PSNR of the 64-light 240x135 donut from 38.13 to 38.89 dB
            (benchmarks/thesis_experiments.py; docs/method.md, "Fitting", step 6).
    """

    straight_below: float = 1e-4
    length_scale_rpx: float = 15.0
    compare_rotations: bool = True

    def __post_init__(self):
        _require(math.isfinite(self.straight_below) and self.straight_below >= 0,
                 f"straight_below must be >= 0, got {self.straight_below}")
        _require(math.isfinite(self.length_scale_rpx) and self.length_scale_rpx > 0,
                 f"length_scale_rpx must be > 0, got {self.length_scale_rpx}")


RESIDUAL_KINDS = ("auto", "lowrank", "learned", "images", "none")
"""What a fit keeps beyond its moving highlights (``ResidualSettings.kind``); "auto" is resolved when it starts."""

RESIDUAL_INTERPOLATIONS = ("auto", "triangle", "rbf")
"""How relighting weighs a low-rank residual's captured lights (``ResidualSettings.interpolation``)."""
SEEING_INPUTS = ("moved", "own")
"""Which Gaussians a decoder that sees them learns each captured light with
(``ResidualSettings.learned_seeing_inputs``)."""

LEARNED_BATCH_CUDA = 1 << 16
"""Samples per Adam step of a learned residual on CUDA when ``ResidualSettings.learned_batch`` is 0."""
LEARNED_BATCH_CPU = 1 << 12
"""The same on the CPU (``ResidualSettings.learned_batch`` says where both came from)."""
LEARNED_STEPS_PER_EPOCH = 64
"""On CUDA, a small capture's batch is cut (down to ``LEARNED_BATCH_CPU``) so that an epoch holds at least this
many Adam steps (``residual.learned.learned_batch``). At 65,536 samples a step, 160x90 renders of 16 or 49 lights
took 4 or 11 steps an epoch and their learned residual stayed far below the one the CPU learns at 4,096 a step;
at 4,096 (56 and 172 steps) the GPU default gained 2.3-14.5 dB along the paths of ``benchmarks/bench_motion.py``
(the table in docs/method.md). The dome sample (320x320, 49 lights) takes 77 steps an epoch at 65,536 and keeps
its batch."""
LEARNED_EPOCHS_CUDA = 260
"""A learned residual's epochs on CUDA when ``ResidualSettings.learned_epochs`` is 0."""
LEARNED_EPOCHS_CPU = 200
"""The same on the CPU (``ResidualSettings.learned_epochs`` says where both came from)."""
LEARNED_RATE_CUDA = 1e-2
"""The learning rate at the start of the schedule of images learned alone (no Gaussian kept) on CUDA when
``ResidualSettings.learned_rate`` is 0."""
LEARNED_RATE_CPU = 1e-2
"""The same on the CPU (``ResidualSettings.learned_rate`` says where both came from)."""
LEARNED_RESIDUAL_RATE = 1e-2
"""The learning rate at the start of the schedule of a residual with moving Gaussians taken out, on every device, in
the field and in the learned check (whose images-alone model starts at ``ResidualSettings.learned_rate``: each
candidate at its own rate), where ``ResidualSettings.learned_residual_rate`` is 0; that setting says where it came
from."""
LEARNED_FINAL_RATE = 3e-4
"""The learning rate at the end of a learned residual's schedule (``ResidualSettings.learned_epochs``), and the rate
at which the learned check's winner goes on learning from every light."""
LEARNED_SECONDS_CUDA = 7.5
"""A learned residual's training time at most on CUDA when ``ResidualSettings.learned_seconds`` is 0, seconds."""
LEARNED_SECONDS_CPU = 100.0
"""The same on the CPU (``ResidualSettings.learned_seconds`` says where both came from)."""
LEARNED_TUNE_SECONDS_CUDA = 5.0
"""The learned check's winner's time on every light at most on CUDA when ``learned_tune_seconds`` is 0, seconds."""
LEARNED_TUNE_SECONDS_CPU = 12.5
"""The same on the CPU."""
LEARNED_ANEW_SHARE_CUDA = 0.0
"""``ResidualSettings.learned_anew_share`` on CUDA when the setting is negative: the learned check's winner never tunes
there, the decided residual always learns anew (it says where the value came from)."""
LEARNED_ANEW_SHARE_CPU = 0.15
"""The same on the CPU."""
LEARNED_TILE = (64, 8, 256)
"""The learned residual's training step on the device (``kernels.neural_training.make_train_tiles``): samples
per tile, tiles per block (the weights' gradients add up in the block), threads per block; the fastest of
those ``benchmarks/bench_learned_training.py --parts tiles`` and ``--parts launches`` try on an NVIDIA H200
(279.6 million samples a second; (64, 8, 192) as fast, 288 threads or more do not launch). An optional fourth
number asks the compiler for registers enough for that many blocks a multiprocessor (CUDA's launch bounds; ``--tiles
"64,8,256,2"`` measures it)."""
LEARNED_TENSOR_CORES = True
"""Whether the learned residual trains on a CUDA GPU's tensor cores where it has them (compute capability 8.0 or
newer: ``kernels.neural_tensor_cores``, TF32 products with float32 sums) rather than through Warp's tile products
(``LEARNED_TILE``): on an NVIDIA H100 the dome sample learned at 776 million samples a second against 290 million
through the tile products and 33.8 million for PyTorch's eager step of the same model in the same run, 47.41 dB at its
Test lights after 100 epochs against 47.56 and 47.57, its first step 0.7 s on an empty kernel cache against 6.0 s
(``benchmarks/bench_learned_training.py --parts launches,kernel,torch --mathdx 0``; Warp's tile products through
cuBLASDx, its own way to the tensor cores, compile for minutes: ``LEARNED_MATHDX``)."""
LEARNED_TENSOR_PASSES = 4
"""Passes of 128 samples a block of the tensor-core step takes: a step of 65,536 samples is then 128 blocks, one wave
on an H100's 132 multiprocessors (one block each: the block's 214 KiB of shared memory). On an NVIDIA H100 a step
took 82.9 us with 4 passes and 97.1 us with 2 (256 blocks, two waves;
``benchmarks/bench_learned_training.py --parts launches --passes 2,4``)."""
LEARNED_MATHDX = False
"""Whether the learned residual's tile products use cuBLASDx (``enable_mathdx_gemm``): on an NVIDIA H200 it
makes the first training step compile for minutes and trains slower: 147 million samples a second against
202 million with Warp's own products at the time (276 million since the step's shared-memory reads spread over the
banks), the first step 160 s on an empty kernel cache (the step of
``LEARNED_TILE``; ``benchmarks/bench_learned_training.py --parts kernel --mathdx 1``)."""


@dataclass(frozen=True)
class ResidualSettings:
    """What a field keeps of the images beyond its moving highlights: residual transfer (docs/method.md, The residual).

    Attributes:
        kind: what relighting adds the moved highlights to (``RESIDUAL_KINDS``), resolved once when a fit
            starts (``residual.kind.resolve_kind``): "lowrank" stores the residual images as low-rank
            luminance and chroma stacks with 8- or 16-bit bases within ``size_budget``; "learned" learns
            them (9 numbers per pixel and an MLP of code + direction, NeuralRTI's model, ``kernels.neural``);
            "images" keeps them uncompressed as float16 (exact at the captured lights, as large as the alpha
            blend's input); "none" keeps no residual (relight with a diffuse model instead). "auto"
            (default): learned on a CUDA device, and on the CPU where its training time holds enough epochs of the
            capture (``cpu_learned_epochs``), else low rank; the learned residual scored higher at held-out lights on
            the samples (``benchmarks/bench_quality.py``, with ``--set residual.kind=...``; docs/method.md, The
            residual).
        size_budget: the largest share of the 8-bit capture (lights x pixels x channels bytes) the
            whole field file may take: the residual's basis images, their number and their
            quantisation (``residual.rate.allocate_steps``) are chosen to fill what the Gaussians,
            paths and the rest leave. A field should stay within a quarter of its capture; the estimate
            counts the deflated basis images as the file stores them and the file's own overhead, and
            with 0.24 the eight fields of benchmarks/bench_quality.py (samples and renders, CPU and GPU
            sizes) take 23.2-24.0% of their captures (its "share" column). A larger share gains the
            statue's full images little.
        min_captured_psnr_db: where the field within ``size_budget`` gives the captured lights back below
            this (mean 8-bit sRGB PSNR of the residual and the lights' own highlights against their images), the
            budget grows by half at a time, up to ``max_size_budget``, until they come back at this or better:
            40, because with it a held-out light loses at most a few hundredths of a dB to compression. At 24%
            the textured, glossy multi-object sample (49 lights, 160x160, no Gaussians kept) gave its captured
            lights back at 23.6 dB and scored 22.37 dB at its held-out lights against the alpha blend's 24.69;
            at 50 / 70 / 100%: 34.8 / 43.0 / 54.1 dB and 24.51 / 24.67 / 24.69. The coin photographs (1 in 5
            held out): 29.4 dB and 21.83 against 22.51 at 24%, 43.6 dB and 22.48 at 50%. The dome sample (59.7 dB)
            and the statue (47.0 dB) keep 24% (2-core CPU, ``benchmarks/bench_quality.py --cases coin,multi --set
            residual.min_captured_psnr_db=0 --set residual.size_budget=...``; the JSON's ``residual`` has the
            captured lights' score). 0 turns the floor off.
        max_size_budget: how far ``min_captured_psnr_db`` may grow the budget: 1, the 8-bit capture's size
            (what the alpha blend keeps).
        luminance_rank: basis images of the luminance, each quantised over its whole range; 0
            (default) lets the budget decide.
        min_luminance_rank: the automatic rank's floor, whatever the budget (those beyond what it
            allows at 8 bits over their range): at small working sizes the Gaussians alone can take
            most of the budget (the statue at 68x64 relit with rank 1 fell far below the alpha blend),
            and 8 basis images cost little there.
        max_luminance_rank: cap on the automatic rank (each rank costs the relight one multiply-add
            per pixel and plane). 255, so that the size budget decides: a low cap suits the dome
            sample, whose residual needs few images, but the full-sphere donut gains up to rank 58 at
            64 lights, and a cap of 64 left the 250-light donut under the alpha blend (its dark
            back-lit images need the rank; ``benchmarks/bench_quality.py --set
            residual.max_luminance_rank=64``).
        basis_bits: bits of the stored basis images' codes, 8 or 16; 0 (default) fits both within
            the budget and keeps the one of lower predicted squared error (``StackPlan.distortion``),
            and fits only 8 where their steps are all coarser than the codes' finest (16-bit codes
            would store the same quantisation in more bytes): 16 bits let the leading images be
            quantised finer than their range over 255 (8-bit bases quantised over their range hold the
            64-light donut back even at full rank), 8 bits cost less where they need not be. The
            prediction picks the width that the measured 8-bit sRGB error of both candidates picks, on
            both samples and the donuts over budgets from 0.08 to 1.
        chroma_rank: basis images of the chroma (B - Y, R - Y); 0 (default) lets the budget decide,
            with the luminance's (``residual.rate.allocate_steps``: every kept image of either stack
            adds the same squared RGB error). A small fixed rank (3 or 6) loses much of the 250-light
            donut, whose colour changes with the light.
        move_support: a Gaussian moves only where, on the median outgoing edge, at least this share
            of its retargeted self lies on the neighbour's specular image (``kernels.support``);
            otherwise it stays where it is and blends like the alpha baseline. 0 lets every Gaussian move.
            0.1 (default): the move check on left-out lights decides for the capture, and this test
            only holds back what lands almost wholly off the neighbour's highlight. At 0.5 the dome sample
            fitted on 25 spread lights held back the Gaussian that carries most of the light (33.69 dB
            at its Test lights, 35.99 at 0.1, the blend 32.34), and the renders of
            ``benchmarks/bench_motion.py`` moved 3-62 fewer Gaussians and changed by under 0.05 dB
            (2-core CPU; the table in benchmarks/README.md, bench_motion.py).
        move_coherence: a Gaussian whose motion coherence (``fit.coherence``: the share of its retargeted
            displacements that a linear map of the half-vector's change explains, about 0 for glints that hop to a
            random neighbour, 1 for a highlight that glides) is below this stays in place and blends; -1 (default):
            off, every Gaussian is free of it. The fit reports the median either way (``residual.motion_coherence``):
            on the renders of ``benchmarks/bench_motion.py`` at 16 / 49 lights the bumpy donut's Gaussians have 0.47 /
            0.39, the tiled teapot's 0.68 / 0.72, the sharp donut's 0.96 / 0.97, the broad sphere's 0.98 at 16. Off,
            because holding glints back gained too little for what it cost where highlights glide far: at 0 / 0.3 /
            0.5 / 0.7 the bumpy donut of 16 lights went from 27.64 dB along the paths (529 moving Gaussians) to 27.73 /
            27.92 / 28.03 / 28.09 (436 / 347 / 259 / 160; the alpha blend 28.33), the sharp donut from 31.75 to 31.75 /
            31.73 / 31.69 / 31.48, the tiled teapot from 30.78 to 30.75 / 30.75 / 30.75 / 30.64, and at 49 lights at
            0.3 the sharp donut lost 0.23 dB (37.03 -> 36.80); the dome sample on 25 spread lights at 0.5 held back
            one Gaussian more than at 0.3, the top light's broad glow, which sweeps across the frame and past its edge
            (not linearly), and fell from 36.30 to 34.48 dB at its Test lights, 36.36 at 0.3 (2-core CPU, low-rank
            residual, ``benchmarks/bench_motion.py --scenes donut-sharp,teapot-tiles,bumpy-metal --captures dome16 --set
            residual.kind=lowrank --set residual.move_coherence=...``, and ``--captures dome49``, ``--scenes ""
            --photos dome-sample``).
        check_lights: captured lights left out one at a time to check that moving beats blending on
            this capture (``fit.validation``): each is relit from the triangle of the other lights
            that holds it, with the Gaussians moved (its missing edges retargeted) and with the
            corners' images blended; where moving scores lower (mean 8-bit sRGB PSNR), the
            highlights stay in the residual and the field keeps no Gaussians. 48 (default) checks
            every light of the statue sample (43 fitted lights), where moving loses to blending at the
            left-out lights as at the held-out ones, and 48 spread lights of larger captures (the dome
            sample and the 250-light renders, where moving is ahead; ``benchmarks/bench_quality.py``
            records which fields keep their Gaussians); each light costs the fit about 3-4 retargeted
            edges. 0 skips the check.
        highlight_colour: estimate a per-pixel highlight colour c(x) from the specular part
            (metals, coloured plastics); False keeps white highlights.
        colour_prior: pull of c(x) towards white, as the weight of a white sample in units of
            (display white)^2 per light: where the Gaussians draw little, c(x) stays white.
        learned_seconds: the learned residual's training time at most, seconds (the learned check's two
            models together, or the one model without it; compiling the kernels is not counted); 0 (default)
            by device: 7.5 on CUDA, so that the statue sample (43 lights, 567x534, 13 million samples an
            epoch), where training binds, fits in 9.8 s on an NVIDIA H200 (``fit_field``, its images loaded; the
            whole command of its 54 lights takes 14.3 s, within 15). Longer training scores higher there, at a
            time: at a learning rate of 3e-3 (before ``learned_rate``), 31.91 / 32.17 / 32.38 dB
            at its held-out lights with 7.5 / 10 / 12 s (the alpha blend 32.06), ``fit_field`` 11.4 / 14.2 /
            15.7 s (``benchmarks/bench_quality.py --scale gpu --cases statue --set
            residual.learned_seconds=...``); the dome sample trains 246-247 of its 260 epochs within 7.5 s. 100
            on the CPU, so that a whole fit of a 192-pixel capture of about 40 lights stays within 3 minutes on 2
            cores: the statue at 192x181 (1 light in 5 held out) learned 51 epochs in 100 s, 33.56 dB at its held-out
            lights, its fit 152.8 s, where 120 s gave 49 epochs, 33.60 dB and a fit of 200.0 s (2-core CPU,
            ``benchmarks/bench_quality.py --cases statue --set residual.kind=learned --set
            residual.learned_seconds=...``; NumPy trains 0.5-0.8 million samples a second there,
            ``benchmarks/bench_cpu_learned.py``).
        learned_rate: the learning rate at the start of the schedule of images learned alone (no Gaussian kept),
            decaying geometrically to 3e-4 (``LEARNED_FINAL_RATE``) over ``learned_epochs``, in the field and for the
            learned check's images-alone model; a residual with moving Gaussians (the check's other model too) starts at
            3e-3 (``LEARNED_RESIDUAL_RATE``). 0 (default) by device: 1e-2 on CUDA and on the CPU. On an NVIDIA H200,
            where training stops at ``learned_seconds`` far from converged, 3e-3 / 1e-2 / 2e-2 scored 31.84 / 33.26 /
            31.75 dB on the statue (43 lights, 567x534; the alpha blend 32.06; 7e-3: 32.84) and 26.02 / 27.02 / 26.63 on
            the coin (``benchmarks/bench_quality.py --scale gpu --cases statue,coin --set residual.learned_rate=...``);
            with the learned check at the same rates, the dome sample 48.67 / 48.96 / 50.70
            (``benchmarks/results/bench_quality_h200_learned_rate_sweep.json``). Where the check drops the Gaussians its
            images-alone model is the field's residual: with that model at 3e-3, then at 1e-2, the tiled teapot of 49
            lights scored 33.70 and 35.37 dB along the paths (the learned residual alone 36.32-36.35;
            ``benchmarks/bench_motion.py --scale gpu --scenes teapot-tiles,donut-sharp --captures dome49``) and the dome
            sample 48.57 and 48.97 at its Test lights (``warp-highlights evaluate``); the first at 435a60e, the second
            with each model at its own rate (``benchmarks/results/motion-gpu/bench_motion-dome49-check-rates.json``). On
            a 2-core CPU the statue at 192x181 scored 33.35 with 3e-3 and 34.52 with 1e-2 (``benchmarks/bench_quality.py
            --cases statue --set residual.kind=learned --set residual.learned_rate=...``).
        learned_residual_rate: the learning rate at the start of the schedule of a residual with moving Gaussians
            taken out (in the field, and the learned check's model with the Gaussians); 0 (default):
            ``LEARNED_RESIDUAL_RATE``, 1e-2, the images' own. Under its highlights such a residual learns the diffuse
            part (``diffuse_under_highlights``): shading and cast shadows, which a slow start leaves unlearned. Along
            the paths of ``benchmarks/bench_motion.py`` (``--set residual.learned_residual_rate=...``), 3e-3 / 1e-2 /
            2e-2 on a 2-core CPU at 160x90: the sharp donut 33.39 / 34.98 / 35.55 dB at 16 lights (213 moving
            Gaussians; the learned residual alone 31.42) and 39.88 / 41.95 / 41.42 at 49 (658 moving); at 2e-2 the
            bumpy donut of 16 lights kept its 510 Gaussians and fell from 31.82 to 28.66 dB; every other render kept
            its verdict, within 0.03 dB. With the Gaussians kept (``--set residual.learned_tie_margin_db=100``) the
            sharp donut of 16 lights scored 33.29 and 35.38 dB at 3e-3 and 1e-2 at 320x180 on the CPU (the learned
            residual alone 32.52); at 480x270 on an NVIDIA H100 (``--scale gpu``) 34.29 dB at 1e-2, the learned
            residual alone 31.52 (at 3e-3, in an earlier run, 31.66 against 31.43). The samples score as they did
            (``benchmarks/bench_quality.py``: the Gaussians are not kept there).
            Before ``diffuse_under_highlights`` the residual held what the Gaussians missed and 1e-2 lowered the
            250-light donut's check (41.65 to 38.22 dB on an NVIDIA H200): 3e-3 was the default then.
        learned_epochs: the epochs of the learning rate's schedule (from ``learned_rate`` to 3e-4), at most; 0
            (default) by device: 260 on CUDA, where the dome sample's images learned alone reach 44.09 /
            46.50 / 47.56 / 48.57 dB at its Test lights after 25 / 50 / 100 / 200 epochs (5.2 s for 200)
            and its whole fit 48.23 dB with 200 and 48.68 dB with 260 (14.0 s), 48.66 with 280
            (``benchmarks/bench_learned_training.py``); 200 on the CPU, where ``learned_seconds`` ends
            training first on a 192-pixel capture. Where the time ends training first, a schedule that ends within
            it scores lower: the statue at 567x534 (43 lights, 88 epochs in 7.5 s on an NVIDIA H200) scored 31.43 /
            31.59 / 31.71 / 31.90 dB at its held-out lights with a schedule of 80 / 110 / 140 / 260 epochs
            (``benchmarks/bench_quality.py --scale gpu --cases statue --set residual.learned_epochs=...``): far
            from converged, it gains more from the higher rate than from the rate's last decay.
        learned_batch: (light, pixel) samples per Adam step; 0 (default) by device: 65,536 on CUDA
            (131,072 ran 4% faster but reached 44.17 dB after 50 epochs against 46.50), less for a small
            capture, so that an epoch holds ``LEARNED_STEPS_PER_EPOCH`` steps (not under 4,096), 4,096 on the CPU
            (as good as 2,048 after 180 s on the dome sample and the statue, 48.66 / 34.48 dB against
            48.73 / 34.46, at 1.4 times its samples a second; 8,192 fell to 33.31 dB on the statue:
            ``benchmarks/bench_cpu_learned.py``).
        learned_check: where the move check keeps the Gaussians, up to this many of its left-out lights
            decide whether the learned residual keeps them too (``residual.learned.check_learned``):
            two models learn without those lights, side by side on CUDA, the residual (scored with the
            Gaussians moved there) and the images alone (NeuralRTI); the better one goes on learning from
            every light. The lights lie inside the others' dome and no two share an edge of the triangulation
            (``fit.validation.apart_inside``: 3 of a 16-light dome, 6 of 25 or 49), so each is predicted from its
            captured neighbours as a light between them would be. 6, an eighth of the dome sample's 49 lights: on an
            NVIDIA H100 the two kinds differed by 7 dB on the dome sample (the images alone ahead) and by
            2.3 dB the other way on the 250-light donut (``benchmarks/bench_neural_residual.py``), far more
            than 6 lights' spread. 0, or a capture with no light inside the others' dome, keeps the Gaussians
            unchecked (one model, trained once).
        learned_tune_seconds: how long the check's winner goes on learning from every light, the
            left-out ones included, at the final learning rate (3e-4), seconds at most; 0 (default) by
            device: 5 on CUDA, 12.5 on the CPU (two thirds and an eighth of ``learned_seconds``).
        learned_tune_epochs: its epochs at most: 40, about a sixth of ``learned_epochs``.
        learned_anew_share: where the check's lights are more than this share of the capture, settled or not, the
            decided residual learns anew from every light instead of tuning the check's winner
            (``residual.learned.learns_anew``); negative (default, -1): by device, 0 on CUDA (always anew) and
            0.15 on the CPU (3 of 16 lights, 6 of 25, not 6 of 49). On CUDA learning anew costs at most
            ``learned_seconds`` (7.5 s) more, and at 49 lights (6 left out, 0.12) it raised the fields along the paths
            of ``benchmarks/bench_motion.py`` (480x270, NVIDIA H100) from 52.82 to 55.01 dB on the broad sphere, 38.21
            to 39.33 on the sharp donut (its Gaussians kept) and 35.55 to 36.41 on the tiled teapot, each then level
            with the learned residual alone or above it, and the dome sample from 48.98-49.04 to 49.25 dB at its Test
            lights, its warm fit 10.2 s -> 15.7 s (``--scale gpu --device cuda:0 --captures dome49 --scenes
            sphere-broad,donut-sharp,teapot-tiles --set residual.learned_anew_share=0``; benchmarks/README.md). On a
            2-core CPU learning anew took the dome sample's fit at 160x160 to 243 s and 49.31 dB at its Test lights
            (tuned: 155 s, 49.77 dB; ``benchmarks/bench_quality.py --cases synth --set residual.learned_anew_share=0``),
            beyond the 3 minutes a 2-core machine has for it, though it raised the 49-light broad sphere along the
            paths from 53.79 to 54.95 dB (learned alone 54.07; ``benchmarks/bench_motion.py --scenes sphere-broad
            --captures dome49 --learned``, and the ``--set``), so there the share is 0.15: about the share that the
            40 tune epochs are of CUDA's 260 (6 of 39 lights, 0.154, learn anew). On a 2-core CPU at 3 of 16 lights,
            learning anew raised the learned field along the paths of ``benchmarks/bench_motion.py`` from 32.12 to
            33.31 dB on the sharp donut (its Gaussians kept), 31.00 to 32.48 on the tiled teapot, 29.98 to 31.81 on
            the bumpy donut and 45.36 to 47.35 on the broad sphere, the fit 50-53 s -> 68-72 s (``--scenes
            donut-sharp,teapot-tiles,bumpy-metal,sphere-broad --captures dome16 --set residual.kind=learned``, and
            ``--set residual.learned_anew_share=1`` to tune).
        learned_settle_fraction: after this fraction of ``learned_epochs`` the check's two models are
            scored, and on CUDA again after each such fraction while both learn; once their order has settled
            (``learned_settle_margin_db``), the loser stops and the winner learns on alone, in half the time a
            step of both takes (on an NVIDIA H200 the dome sample's check, unsettled after 65 epochs in one
            run, trained both to the time limit and scored 48.57 dB, against 48.82-48.95 where it settled).
            0.25: the ranking turns
            early in training (after a few tens of steps the residual with its Gaussians leads on the
            dome sample, after thousands the images alone do); at the end the images alone led by 8.0 dB
            after a 60-epoch run, 9.4 dB after 120 and 11.5-12.6 dB after 200, and runs that settled at
            epoch 50-70 left the residual at 35.9-36.1 dB against the images alone's final 45.5-46.4
            (``bench_learned_training.py``, the fits' reports).
        learned_settle_margin_db: the gap in mean 8-bit sRGB PSNR at the check's lights that counts as
            settled, dB: 3, well under the dome sample's gaps at the end of runs of 60 to 200 epochs
            (8.0-12.6 dB) and above the 2.3 dB by which the 250-light donut's two kinds ended apart: such
            a close race learns both to the end. (How far a gap moves after a quarter of training has not
            been measured on captures beyond these two.)
        learned_tie_margin_db: the learned check keeps the moving Gaussians unless the images learned alone lead at
            its left-out lights by more than this, dB (mean 8-bit sRGB PSNR); negative: unless the residual with the
            Gaussians leads by at least as much. -0.5: with 3 or 6 lights checked a few tenths of a dB either way says
            little, and Gaussians that move onto the wrong places cost far more than dropping good ones. On a 2-core
            CPU (``benchmarks/bench_motion.py --scenes donut-sharp,bumpy-metal,teapot-tiles --captures
            dome16,dome49``, 160x90, ``diffuse_under_highlights`` on) the bumpy donut's residual with its 510
            Gaussians led by 0.29 dB at the 3 lights of 16, was kept under a margin of 0.5 and scored 28.04 dB along
            the paths, against 31.81 with them dropped under -0.5; the sharp donut led by 1.06 dB at 16 lights (kept:
            33.39 dB, the learned residual alone 31.42 in benchmarks/README.md) and by 1.71 at 49 on an NVIDIA H100
            (480x270: 40.05 dB against 38.30); the other checks of those runs were 0.5-3.3 dB behind, the dome
            sample's 8-16 dB. 0.5, in the Gaussians' favour, was the margin while the residual's decoder spread each
            light's misfit of the Gaussians between the lights and the check's lights were spread over the whole dome
            (the sharp donut on 16 lights then tied at 17.3-17.5 against 17.5-17.6 dB on an NVIDIA H200).
        learned_glide_coherence: where the capture's Gaussians glide, their median motion coherence
            (``fit.coherence``, measured over every light's edges) at least this, the learned check keeps them unless
            the images learned alone lead at its left-out lights by more than ``learned_glide_margin_db`` instead of
            ``learned_tie_margin_db``; above 1: off. The check's few lights (3 of 16) tie both where keeping the
            Gaussians pays along the paths and where it costs; a glide is where moving them is right, and the measure
            that tells glides from glints uses every light. 0.9: the smooth renders of ``benchmarks/bench_motion.py``
            glide at 0.96-0.998 (the sharp donut, the broad sphere; 16 and 49 lights), the tiled teapot and the bumpy
            donut at 0.39-0.74, the samples at 0.23-0.74 (the dome sample 0.73-0.74; 2-core CPU and NVIDIA H100,
            ``--captures dome16,dome49``, ``benchmarks/bench_quality.py``).
        learned_glide_margin_db: ``learned_tie_margin_db`` where the Gaussians glide (``learned_glide_coherence``), dB.
            0.5, midway between the closest checks of a glide that pays and one that costs, at 16 lights: the sharp
            donut's Gaussians tie at the check's 3 lights, 0.16 dB ahead on an NVIDIA H100 (480x270) and 0.28 on a
            2-core CPU (320x180), and keeping them scores 34.18 against 31.31 dB for the learned residual alone along
            the paths of ``benchmarks/bench_motion.py`` (H100, ``--scale gpu --captures dome16``) and 34.82 against
            32.18 (CPU, ``--size 320x180 --scenes donut-sharp --captures dome16 --learned``); the broad sphere's are
            1.11 dB behind on the H100 (2.93 on the CPU at 160x90), and kept by force they score 42.99 against 47.11
            (``--set residual.learned_tie_margin_db=100 --set residual.learned_glide_margin_db=100``).
            benchmarks/README.md has the table.
        learned_sees_gaussians: the learned check's model with the moving Gaussians is a decoder that sees them (their
            luminance at the pixel among its inputs, ``model.residual.highlight_inputs``) and learns the images
            themselves, and the learned check alone decides whether the field keeps them (the move check's verdict
            weighs moving against blending the images, which such a decoder does not do); the Gaussians that do not
            move (``move_support``, ``learned_seeing_coherence``, ``learned_seeing_travel``) are not among its inputs
            and the field does not keep them: it learns those highlights from the images, as the images learned alone
            do. Off (default), it is a residual of the images less each light's own Gaussians, with the moved ones
            added to it. On the 16-light renders of ``benchmarks/bench_motion.py`` (2-core CPU, 160x90, ``--scenes
            sphere-broad,donut-sharp,bumpy-metal,teapot-tiles --captures dome16 --learned --set
            residual.learned_sees_gaussians=true``) it scored 47.34 / 33.86 / 31.81 / 32.67 dB along the paths with
            0 / 183 / 0 / 70 moving Gaussians and ghost shares 0.076 / 0.272 / 0.159 / 0.330, against 47.34 / 35.02 /
            31.81 / 32.48 (0 / 215 / 0 / 0; ghosts 0.076 / 0.322 / 0.159 / 0.468) for the default and 47.34 / 31.42 /
            31.81 / 32.48 for the images learned alone: fewer ghosts, and the teapot's highlights move, but 1.16 dB
            less on the sharp donut, so it stays off (benchmarks/README.md, bench_motion.py).
        learned_seeing_inputs: the Gaussians a decoder that sees them (``learned_sees_gaussians``) learns each captured
            light with: "own" (default), each light's own fitted Gaussians, as a query at that light gets them, so that
            it learns to draw the highlight where the Gaussians put it (the learned check still scores it with the
            moved ones at its left-out lights, and the move check then draws those lights alone); "moved", each light's
            moved there from its triangle in the other lights' triangulation, so that it learns how far an
            interpolated highlight can be trusted. On the renders of ``benchmarks/bench_motion.py`` (2-core CPU,
            160x90, 16 lights, ``--set residual.learned_sees_gaussians=true`` with each, before
            ``learned_seeing_coherence`` and ``learned_seeing_travel``) "own" kept the sharp donut's Gaussians with
            fewer ghosts (ghost share 0.249 against 0.286) and 34.45 against 32.88 dB along the paths; it kept 23
            Gaussians of the broad sphere and lost 1.46 dB there, which ``learned_seeing_travel`` holds back.
        learned_seeing_coherence: ``move_coherence`` for a decoder that sees the Gaussians (``learned_sees_gaussians``):
            a Gaussian whose motion coherence (``fit.coherence``) is below this stays, and the decoder learns its
            highlight from the images. 0.8: on the 16-light renders of ``benchmarks/bench_motion.py`` (2-core CPU,
            160x90, ``--scenes donut-sharp,bumpy-metal,teapot-tiles --captures dome16 --learned --set
            residual.learned_sees_gaussians=true --set residual.learned_seeing_travel=0``) the learned check kept 183 /
            118 / 94 moving Gaussians on the sharp donut, the bumpy donut and the tiled teapot, which scored 33.86 /
            32.22 / 32.58 dB along the paths against 31.42 / 31.81 / 32.48 for the images learned alone (ghost share
            of the teapot 0.318 against 0.468); without it the check dropped the teapot's and the bumpy donut's
            (benchmarks/README.md). -1: off.
        learned_seeing_travel: a Gaussian moves, for a decoder that sees the Gaussians, only where its highlight
            travels at least this many of its own standard deviations (along the way) on the median of its outgoing
            edges (``fit.moving.travel_in_sigmas``); nearer, a cross-fade of the neighbours is nearly a move, and the
            decoder learns the highlight from the images. 4.0: on the 16-light renders of
            ``benchmarks/bench_motion.py`` (2-core CPU, 160x90) at 0 the broad sphere kept 23 and scored 45.88 dB
            along the paths against 47.34 for the images learned alone; at 4.0 its check dropped the few left and it
            scored 47.34, and the sharp donut kept its 183 (``--set residual.learned_sees_gaussians=true``, and with
            ``--set residual.learned_seeing_travel=0``). 0: off.
        learned_seeing_margin_db: ``learned_tie_margin_db`` where the model with the Gaussians is a decoder that sees
            them (``learned_sees_gaussians``): both it and the images alone learn the images, so a tie tells nothing
            of the Gaussians, and the images alone keep the field unless it scores at least as high. 0: on the tiled
            teapot of ``benchmarks/bench_motion.py`` (16 lights, 2-core CPU) the decoder that sees them scored 27.00
            against 27.19 dB at the check's 3 lights, was kept under a 0.5 dB margin, and scored 31.63 dB along the
            paths against the images alone's 32.48; the sharp and the bumpy donut led at the check (28.21 against
            27.55, 24.33 against 24.01) and along the paths (32.88 against 31.42, 32.02 against 31.81).
        learned_bounds: keep a learned residual's relit values, per pixel and channel, within the range of what it
            learned at the captured lights (the images less their own highlights) widened on either side by the images'
            own range (``model.residual.learned_bounds``, stored in the field; the decoder's own values there would
            carry its error, a haze of a few 8-bit levels over a black background). On by default: with 16 lights the
            decoder lit the black background of the renders of ``benchmarks/bench_motion.py`` on some frames (2-core
            CPU, ``--scenes donut-sharp,teapot-tiles --captures dome16 --set residual.kind=learned``, and with ``--set
            residual.learned_bounds=false``: along the paths the sharp donut's field 32.58 -> 33.14 dB, SSIM 0.851 ->
            0.920; the tiled teapot 30.64 -> 30.92 dB, SSIM 0.858 -> 0.932). The dome sample and the statue score the
            same either way (the CPU, ``benchmarks/bench_quality.py --cases synth,statue --set residual.kind=learned``):
            the span on either side leaves a highlight that is brighter between two lights than at either its peak.
        diffuse_under_highlights: where a light's own moving Gaussians are at least this share of their brightest
            pixel at that light, a learned residual with the Gaussians taken out learns the segmentation's diffuse part
            there (the image less its specular part) rather than the image less the Gaussians
            (``residual.inputs.diffuse_under_highlights``); 0: off. A few Gaussians do not fit a sharp highlight's
            shape exactly, and what they miss (the specular part less them, dark where they overshoot, bright where
            they fall short) is a light's own: between the lights a decoder spreads it over the object as speckles
            that no highlight carries, and the more pixels a highlight covers the more of it there is. 0.02, the
            share below which ``quality.motion`` counts a frame as showing no highlight (``NONE_LEVEL``). On the sharp
            donut of ``benchmarks/bench_motion.py`` at 16 lights (2-core CPU, ``--set residual.learned_check=0 --set
            residual.learned_seconds=400`` at 320x180) the field along the paths went from 32.06 to 33.29 dB and its
            ghost share from 0.58 to 0.38 (the learned residual alone 32.56 / 0.25); at 160x90 with the defaults
            from 33.31 to 33.39 dB.
        interpolation: how relighting weighs the captured lights of a low-rank residual: "triangle" (default), the
            barycentric weights of the query's triangle (the alpha blend's: local, a light's image reaches only
            its own triangles); "rbf", Gaussian radial basis weights over every light (``model.rbf``, sigma by
            leave-one-out: smooth across triangles); "auto": whichever predicts the fit's left-out lights better
            (``residual.interpolation``, ``interpolation_margin_db``). "auto" took the radial basis on 4 of the 10
            renders of ``benchmarks/bench_motion.py`` (2-core CPU, ``--set residual.interpolation=auto``): along
            the paths the broad sphere went 34.23 -> 36.76 dB (16 lights) and 40.50 -> 43.17 (49), the sharp
            donut 31.72 -> 32.26 (16), the tiled teapot 30.69 -> 30.58 (16), but SSIM fell on all four (by
            0.007-0.012: 0.9763 -> 0.9640, 0.9885 -> 0.9816, 0.9626 -> 0.9503, 0.9676 -> 0.9558), and on the
            four samples (``benchmarks/bench_quality.py``) it kept the triangle's. Hence the default stays the
            triangle's until the choice weighs SSIM too.
        interpolation_margin_db: "auto" takes the radial basis weights where they predict the left-out lights
            (each from the other lights, the same light's own highlights added to both) at least this much
            better in mean 8-bit sRGB PSNR, dB. 0.1: a tie keeps the local triangle blend, whose images
            equal the captured ones at the lights (a regularised radial basis misses them by a little).
        cpu_learned_epochs: where "auto" fits a colour capture on the CPU, the residual is learned, as on CUDA (the
            learned check decides whether it keeps the moving Gaussians), if its training time (``learned_seconds``)
            holds at least this many epochs of the capture at the pace the CPU trains at when the fit starts, and at
            most its schedule's (``residual.kind.cpu_epochs``); else it is low rank; 0: always low rank. A learned
            residual that has had its epochs interpolates the images between the lights better than the low-rank
            one, and a short one worse. The samples learned alone for 120 s on a 2-core machine, against
            the low-rank residual (8-bit sRGB PSNR / SSIM at the held-out lights, ``benchmarks/bench_quality.py
            --cases statue,coin,multi --set residual.kind=learned``): the coin photographs 27.06 / 0.834 after 43
            epochs against 22.51 / 0.776; the statue 32.79 / 0.931 after 31 epochs against 33.03 / 0.935, and 34.09
            / 0.945 after 80 (the same machine earlier that day, at 2.6 times the pace); the multi-object sample
            25.14 / 0.801 after 36 epochs (25.61 / 0.824 after 118) against 24.68 / 0.846. The pace is timed over 32
            steps before the fit would learn (``residual.cpu_training.training_rate``), which counted 41-44, 29-33
            and 37-41 epochs in 120 s for the three on that machine: 36 epochs in 120 s, between the statue's 31
            (below) and the coin's 43 (far above), learns the coin photographs and the multi-object sample and keeps
            the statue low rank there; 30, the same pace in the 100 s of ``learned_seconds``. Where Gaussians move,
            the learned residual and its check score higher too (2-core CPU, 2026-12-05): the dome sample 48.99 /
            0.993 at its Test lights in a 155 s fit, against 42.14 / 0.979 for the low-rank field and its 135 moving
            Gaussians (docs/method.md, The residual); along the paths of ``benchmarks/bench_motion.py`` 0.05-14.76 dB
            above the low-rank field on its ten renders, the sharp donut's moving Gaussians kept
            (benchmarks/README.md).
    """

    kind: str = "auto"
    size_budget: float = 0.24
    min_captured_psnr_db: float = 40.0
    max_size_budget: float = 1.0
    luminance_rank: int = 0
    max_luminance_rank: int = 255
    min_luminance_rank: int = 8
    basis_bits: int = 0
    chroma_rank: int = 0
    move_support: float = 0.1
    move_coherence: float = -1.0
    check_lights: int = 48
    highlight_colour: bool = True
    colour_prior: float = 0.01
    learned_seconds: float = 0.0
    learned_rate: float = 0.0
    learned_residual_rate: float = 0.0
    learned_epochs: int = 0
    learned_batch: int = 0
    learned_check: int = 6
    learned_tune_seconds: float = 0.0
    learned_tune_epochs: int = 40
    learned_anew_share: float = -1.0
    learned_settle_fraction: float = 0.25
    learned_settle_margin_db: float = 3.0
    learned_tie_margin_db: float = -0.5
    learned_glide_coherence: float = 0.9
    learned_glide_margin_db: float = 0.5
    learned_sees_gaussians: bool = False
    learned_seeing_coherence: float = 0.8
    learned_seeing_travel: float = 4.0
    learned_seeing_inputs: str = "own"
    learned_seeing_margin_db: float = 0.0
    learned_bounds: bool = True
    diffuse_under_highlights: float = 0.02
    interpolation: str = "triangle"
    interpolation_margin_db: float = 0.1
    cpu_learned_epochs: int = 30

    def __post_init__(self):
        _require(self.kind in RESIDUAL_KINDS, f"kind must be one of {', '.join(RESIDUAL_KINDS)}, got '{self.kind}'")
        _require(self.interpolation in RESIDUAL_INTERPOLATIONS,
                 f"interpolation must be one of {', '.join(RESIDUAL_INTERPOLATIONS)}, got '{self.interpolation}'")
        _require(math.isfinite(self.interpolation_margin_db) and self.interpolation_margin_db >= 0,
                 f"interpolation_margin_db must be >= 0, got {self.interpolation_margin_db}")
        _require(math.isfinite(self.size_budget) and 0 < self.size_budget <= 10,
                 f"size_budget must be in (0, 10], got {self.size_budget}")
        _require(math.isfinite(self.min_captured_psnr_db) and 0 <= self.min_captured_psnr_db <= 100,
                 f"min_captured_psnr_db must be in [0, 100] (0: no floor), got {self.min_captured_psnr_db}")
        _require(math.isfinite(self.max_size_budget) and 0 < self.max_size_budget <= 10,
                 f"max_size_budget must be in (0, 10], got {self.max_size_budget}")
        _require(0 <= int(self.luminance_rank) <= 1024,
                 f"luminance_rank must be in [0, 1024], got {self.luminance_rank}")
        _require(1 <= int(self.max_luminance_rank) <= 1024,
                 f"max_luminance_rank must be in [1, 1024], got {self.max_luminance_rank}")
        _require(1 <= int(self.min_luminance_rank) <= int(self.max_luminance_rank),
                 f"min_luminance_rank must be in [1, max_luminance_rank], got {self.min_luminance_rank}")
        _require(0 <= int(self.chroma_rank) <= 1024, f"chroma_rank must be in [0, 1024], got {self.chroma_rank}")
        _require(int(self.basis_bits) in (0, 8, 16), f"basis_bits must be 0 (choose), 8 or 16, got {self.basis_bits}")
        _require(math.isfinite(self.move_support) and 0 <= self.move_support <= 1,
                 f"move_support must be in [0, 1], got {self.move_support}")
        _require(math.isfinite(self.move_coherence) and -1 <= self.move_coherence <= 1,
                 f"move_coherence must be in [-1, 1] (-1: off), got {self.move_coherence}")
        _require(math.isfinite(self.learned_seeing_travel) and self.learned_seeing_travel >= 0,
                 f"learned_seeing_travel must be >= 0 standard deviations (0: off), got {self.learned_seeing_travel}")
        _require(math.isfinite(self.learned_seeing_coherence) and -1 <= self.learned_seeing_coherence <= 1,
                 f"learned_seeing_coherence must be in [-1, 1] (-1: off), got {self.learned_seeing_coherence}")
        _require(0 <= int(self.check_lights) <= 100000, f"check_lights must be in [0, 100000], got {self.check_lights}")
        _require(math.isfinite(self.colour_prior) and self.colour_prior > 0,
                 f"colour_prior must be > 0, got {self.colour_prior}")
        _require(math.isfinite(self.learned_seconds) and self.learned_seconds >= 0,
                 f"learned_seconds must be >= 0 (0: by device), got {self.learned_seconds}")
        _require(math.isfinite(self.learned_rate) and 0 <= self.learned_rate <= 1,
                 f"learned_rate must be in [0, 1] (0: by device), got {self.learned_rate}")
        _require(math.isfinite(self.learned_residual_rate) and 0 <= self.learned_residual_rate <= 1,
                 f"learned_residual_rate must be in [0, 1] (0: the default), got {self.learned_residual_rate}")
        _require(0 <= int(self.learned_epochs) <= 100000,
                 f"learned_epochs must be in [0, 100000] (0: by device), got {self.learned_epochs}")
        _require(0 <= int(self.learned_batch) <= 1 << 24,
                 f"learned_batch must be in [0, 16777216], got {self.learned_batch}")
        _require(0 <= int(self.learned_check) <= 1000, f"learned_check must be in [0, 1000], got {self.learned_check}")
        _require(math.isfinite(self.learned_tune_seconds) and self.learned_tune_seconds >= 0,
                 f"learned_tune_seconds must be >= 0 (0: by device), got {self.learned_tune_seconds}")
        _require(math.isfinite(self.learned_anew_share) and self.learned_anew_share <= 1,
                 f"learned_anew_share must be in [0, 1], or negative for the device's default, got "
                 f"{self.learned_anew_share}")
        _require(1 <= int(self.learned_tune_epochs) <= 100000,
                 f"learned_tune_epochs must be in [1, 100000], got {self.learned_tune_epochs}")
        _require(math.isfinite(self.learned_settle_fraction) and 0 < self.learned_settle_fraction <= 1,
                 f"learned_settle_fraction must be in (0, 1], got {self.learned_settle_fraction}")
        _require(math.isfinite(self.learned_settle_margin_db) and self.learned_settle_margin_db >= 0,
                 f"learned_settle_margin_db must be >= 0, got {self.learned_settle_margin_db}")
        _require(math.isfinite(self.learned_tie_margin_db),
                 f"learned_tie_margin_db must be a finite number of dB, got {self.learned_tie_margin_db}")
        _require(math.isfinite(self.learned_glide_coherence) and -1 <= self.learned_glide_coherence <= 2,
                 f"learned_glide_coherence must be in [-1, 2] (above 1: off), got {self.learned_glide_coherence}")
        _require(math.isfinite(self.learned_glide_margin_db),
                 f"learned_glide_margin_db must be a finite number of dB, got {self.learned_glide_margin_db}")
        _require(self.learned_seeing_inputs in SEEING_INPUTS,
                 f"learned_seeing_inputs must be one of {', '.join(SEEING_INPUTS)}, got '{self.learned_seeing_inputs}'")
        _require(math.isfinite(self.learned_seeing_margin_db) and self.learned_seeing_margin_db >= 0,
                 f"learned_seeing_margin_db must be >= 0, got {self.learned_seeing_margin_db}")
        _require(self.cpu_learned_epochs >= 0, f"cpu_learned_epochs must be >= 0, got {self.cpu_learned_epochs}")
        _require(math.isfinite(self.diffuse_under_highlights) and 0 <= self.diffuse_under_highlights <= 1,
                 f"diffuse_under_highlights must be in [0, 1] (0: off), got {self.diffuse_under_highlights}")


@dataclass(frozen=True)
class DistilSettings:
    """A smaller decoder distilled from a learned residual's (``residual.distil``, ``warp-highlights distil``).

    Attributes:
        hidden: the student's hidden layers' widths. (24, 24, 24): 3.5 times fewer multiply-adds than the fitted
            decoder; distilled for 60 epochs on a 2-core CPU, the dome sample's Test lights lost 0.02 dB (48.59
            against 48.61) and the statue's held-out lights 1.28 dB (33.26 against 34.54, above its low-rank
            field's 33.01). Depth matters more than width: 16-16-16 lost 0.14 and 1.67 dB, 16-16 0.22 and
            2.68, 48-48 0.50 and 1.73, one hidden layer 8 and 3 (``benchmarks/bench_decoder_size.py``).
        seconds: training time at most (0: no limit but ``epochs``). 120: the 60 epochs of a 24-24-24 student
            took 118 s for the dome sample at 160x160 and 146 s for the statue at 192x181 on 2 cores.
        epochs: passes over the pool's (direction, pixel) samples at most; the learning rate falls from
            ``rate`` to 3e-4 (``LEARNED_FINAL_RATE``) over them (or over ``seconds`` where that ends first).
        rate: the learning rate at the start: 3e-3, the fitted decoder's rate when the students'
            figures above were measured.
        epochs_per_round: the new directions between the lights are drawn anew every this many epochs.
        pool_factor: a round's directions are the captured ones and (``pool_factor`` - 1) times as many
            between them (2: as many new as captured; the student learns the relighting between the
            lights, where the teacher's outputs are as cheap as at them).
        batch: samples a step (the fitted decoder's CPU batch, ``BATCH_CPU``).
        learn_codes: the per-pixel codes learn along with the student (from the teacher's), rather than stay
            the teacher's: a 24-24-24 student of the statue (192x181, every 5th light held out) scored 33.04
            dB at the held-out lights with its codes learning and 32.37 dB with the teacher's (34.27), and
            came to 37.96 against 35.58 dB of its teacher at the captured lights
            (``bench_decoder_size.py --cases statue --students 24,24,24 --fixed-codes``).
        seed: the student's first weights and the samples drawn.
    """

    hidden: tuple = (24, 24, 24)
    seconds: float = 120.0
    epochs: int = 60
    rate: float = 3e-3
    epochs_per_round: int = 4
    pool_factor: float = 2.0
    batch: int = 4096
    learn_codes: bool = True
    seed: int = 0

    def __post_init__(self):
        _require(1 <= len(self.hidden) <= 3 and all(int(w) >= 1 for w in self.hidden),
                 f"hidden must hold 1 to 3 widths of at least 1, got {self.hidden}")
        _require(math.isfinite(self.seconds) and self.seconds >= 0, f"seconds must be >= 0, got {self.seconds}")
        _require(int(self.epochs) >= 1 and int(self.epochs_per_round) >= 1,
                 f"epochs and epochs_per_round must be >= 1, got {self.epochs} and {self.epochs_per_round}")
        _require(math.isfinite(self.pool_factor) and self.pool_factor > 1,
                 f"pool_factor must be > 1, got {self.pool_factor}")
        _require(int(self.batch) >= 1, f"batch must be >= 1, got {self.batch}")
        _require(math.isfinite(self.rate) and 0 < self.rate <= 1, f"rate must be in (0, 1], got {self.rate}")


FLATTEN_MODES = ("trend", "level")
"""``maps --flatten`` choices: ``trend`` removes the normals' slopes' linear trend over the image and
keeps the object's median tilt; ``level`` removes that tilt too (a base that faces the camera)."""


@dataclass(frozen=True)
class MapSettings:
    """Surface maps of a fitted field (``relight.maps``, ``warp-highlights maps``): which lights count
    in a pixel's photometric-stereo fit of its normal and albedo, and when a pixel's own lights do not
    determine them.

    Chosen on the dome sample (against the normal map its renderer wrote, flattened) and the rendered
    sphere (against the analytic normals), from the captured images themselves: with one threshold
    for the whole image, segmentation's 0.05, the dark dome sample (median pixel 0.025) kept too few
    lights, and its normals erred several times more than with a threshold relative to each pixel
    (tests/test_maps.py holds both captures to their normals). The shadow fit and the checks after it
    were chosen on the statue sample (its creases, lit by a quarter of the lights or fewer) and a
    rendered donut under 64 dome lights (its hole in cast shadow; against the renderer's normals), and
    leave every pixel of the dome sample as it was.

    Attributes:
        lit_percentile: a pixel's typical lit value is this percentile of its luminance over the lights
            (75: a quarter of the lights may be highlights, three quarters shadow); a neighbourhood's
            typical albedo is this percentile of its pixels' (``neighbourhood``).
        lit_fraction: a light lights the pixel when its value is at least this share of the typical
            one (0.1: the rendered sphere's ambient 0.02 under an albedo of 0.6 is 3%; at 5% of the
            75th percentile, shadowed samples counted and bent its normals).
        black_level: a pixel whose typical lit value is below this (linear, the field's units, where
            display white is about 1) is black: no normal. 0.001 is 8-bit sRGB level 4; below it an
            8-bit capture holds no shading to fit, and a compressed residual's noise on a black
            background made "normals" there.
        outlier_factor: after each fit, lit lights whose residual exceeds this many times the median
            one leave the next fit (highlights); segmentation's rule (thesis: 2).
        outlier_floor: the outlier limit is never below this share of the typical lit value (an
            exactly Lambertian pixel's residuals are rounding noise, as in segmentation's floor).
        iterations: fits per pixel at most, the first included (the sets stop changing in 2-4 on the
            samples).
        min_lit_lights: pixels lit by fewer lights have no normal of their own (3 unknowns; one more
            lets an outlier show); a shadow fit needs as many sunlit ones.
        saturation: a light whose value reaches this share of the capture's white in any channel is
            left out of the pixel's fit (clipped: its shading is unknown). Only for captures in 8- or
            16-bit files (PNG, JPEG, sRGB TIFF), whose white is 1 times the fit's exposure; 0.98
            (8-bit sRGB level 252) leaves room for the residual's error near white. 1.6% of the coin
            sample's lights are clipped; left out, its normals stray less from their 5x5 median
            (6.06 -> 5.99 degrees, mean inside the coin).
        min_explained: a fit that explains less than this share of its values' variance (R^2, beyond
            ``noise_tolerance``) is suspect where it is also dark (``dark_ratio``), and a shadow fit
            must explain at least as much. A pixel in cast shadow under most lights, fitted to its
            ambient values, explains 0.26-0.70 (5th-95th percentile of the statue sample's dark
            dots) and under 0.2 in the rendered donut's hole; every pixel of the dome sample explains
            over 0.92 and 95% of the statue's over 0.86. Metal explains less everywhere (the coin's
            median 0.6), which is why a suspect fit must be dark as well.
        noise_tolerance: residuals up to this share of the mean value used always count as explained
            (8-bit quantisation and JPEG noise: about 1% of mid-grey values), so a fit of nearly equal
            values (a surface facing one ring of lights) is not refused for their small variance.
        dark_ratio: a suspect fit's albedo is under this share of its neighbourhood's, and a shadow fit's
            within a factor 1 / ``dark_ratio`` of it (0.5: the shadow fits accepted on the statue
            sample have 0.68-1.5 of their neighbourhood's albedo, 5th-95th percentile).
        shadow_percentile: the shadow fit starts from the lights at least ``shadow_fraction`` of this
            percentile of the pixel's values (90: the brightest tenth, above a pixel's cast shadows
            when a tenth of the lights or more are sunlit, and below its few highlights).
        shadow_fraction: see ``shadow_percentile``; a sunlit light has n . w at least this (0.25: the
            statue's shadowed values are 7-30% of its sunlit ones, the room's ambient light).
        shadow_ratio: in the shadow fit, a light whose value is below this share of the fitted shading
            is in cast shadow and leaves the next fit (0.3: the cast-shadowed lights are at 0.2 of it
            on the statue sample and 0.08 in the donut's hole (medians), the kept lights at 0.55 or
            more on the statue, 1st percentile).
        shadow_window: the shadow fit is kept only where at least ``shadow_support`` pixels of the
            (2 ``shadow_window`` + 1)^2 window around a pixel (itself included) took it too: a cast
            shadow covers a region. 2 and 5: in 5x5 windows the statue's shadow fits have a median of
            10 such pixels and the donut's 17, while on the coin's rim single pixels fitted their
            highlights (median 2, bright dots in the albedo).
        shadow_support: see ``shadow_window``.
        min_spread: the smallest eigenvalue of the sum of w w^T over the lights of a pixel's fit (w
            their directions; a count of lights) must be at least this, or the normal is not
            determined: 0.1 refuses lights within about 10 degrees of each other, along which 1%
            noise turns the normal by 2 degrees or more (one pixel of the donut and the coin samples
            each).
        neighbourhood: the window radius, in pixels at the field's working size, of a fit's
            neighbourhood albedo (``dark_ratio``), and the farthest an undetermined pixel of the
            object takes its neighbours' normal and albedo. 8: the statue's creases are 2-6 pixels
            wide at 567x534.
        lean_hint_deg: ``maps`` without ``--flatten`` suggests it when the slopes' linear trend turns
            the normals at the frame's corners more than this many degrees (``NormalLean.edge_deg``).
            4: the dome sample's near lights turn its nearly flat relief's normals 5.4 degrees at the
            corners (3.2 degrees median from its renderer's normals, 0.4 flattened); the coin sample's
            trend is 1.9. Curved objects have a trend of their own (the rendered donut's 48), which
            is why this only suggests.
    """

    lit_percentile: float = 75.0
    lit_fraction: float = 0.1
    black_level: float = 0.001
    outlier_factor: float = 2.0
    outlier_floor: float = 1e-3
    iterations: int = 5
    min_lit_lights: int = 4
    saturation: float = 0.98
    min_explained: float = 0.8
    noise_tolerance: float = 0.02
    shadow_percentile: float = 90.0
    shadow_fraction: float = 0.25
    shadow_ratio: float = 0.3
    min_spread: float = 0.1
    dark_ratio: float = 0.5
    shadow_window: int = 2
    shadow_support: int = 5
    neighbourhood: int = 8
    lean_hint_deg: float = 4.0

    def __post_init__(self):
        _require(math.isfinite(self.lean_hint_deg) and self.lean_hint_deg >= 0,
                 f"lean_hint_deg must be >= 0, got {self.lean_hint_deg}")
        _require(math.isfinite(self.lit_percentile) and 0 <= self.lit_percentile <= 100,
                 f"lit_percentile must be in [0, 100], got {self.lit_percentile}")
        _require(math.isfinite(self.lit_fraction) and 0 <= self.lit_fraction < 1,
                 f"lit_fraction must be in [0, 1), got {self.lit_fraction}")
        _require(math.isfinite(self.black_level) and self.black_level >= 0,
                 f"black_level must be >= 0, got {self.black_level}")
        _require(math.isfinite(self.outlier_factor) and self.outlier_factor >= 1,
                 f"outlier_factor must be >= 1, got {self.outlier_factor}")
        _require(math.isfinite(self.outlier_floor) and self.outlier_floor >= 0,
                 f"outlier_floor must be >= 0, got {self.outlier_floor}")
        _require(1 <= int(self.iterations) <= 100, f"iterations must be in [1, 100], got {self.iterations}")
        _require(int(self.min_lit_lights) >= 3,
                 f"min_lit_lights must be >= 3 (a normal and an albedo), got {self.min_lit_lights}")
        _require(math.isfinite(self.saturation) and self.saturation > 0,
                 f"saturation must be > 0 (a share of white), got {self.saturation}")
        _require(math.isfinite(self.min_explained) and self.min_explained <= 1,
                 f"min_explained must be <= 1 (a share of variance), got {self.min_explained}")
        _require(math.isfinite(self.noise_tolerance) and self.noise_tolerance >= 0,
                 f"noise_tolerance must be >= 0, got {self.noise_tolerance}")
        _require(math.isfinite(self.shadow_percentile) and 0 <= self.shadow_percentile <= 100,
                 f"shadow_percentile must be in [0, 100], got {self.shadow_percentile}")
        _require(math.isfinite(self.shadow_fraction) and 0 <= self.shadow_fraction < 1,
                 f"shadow_fraction must be in [0, 1), got {self.shadow_fraction}")
        _require(math.isfinite(self.shadow_ratio) and 0 <= self.shadow_ratio < 1,
                 f"shadow_ratio must be in [0, 1), got {self.shadow_ratio}")
        _require(math.isfinite(self.min_spread) and self.min_spread >= 0,
                 f"min_spread must be >= 0, got {self.min_spread}")
        _require(math.isfinite(self.dark_ratio) and self.dark_ratio >= 0,
                 f"dark_ratio must be >= 0, got {self.dark_ratio}")
        _require(0 <= int(self.shadow_window) <= 100, f"shadow_window must be in [0, 100], got {self.shadow_window}")
        _require(int(self.shadow_support) >= 1, f"shadow_support must be >= 1, got {self.shadow_support}")
        _require(0 <= int(self.neighbourhood) <= 10_000,
                 f"neighbourhood must be in [0, 10000] pixels, got {self.neighbourhood}")


@dataclass(frozen=True)
class FitSettings:
    """Every hyper-parameter of a fit, grouped by stage; ``with_overrides`` applies 'stage.name=value' edits."""

    segmentation: SegmentationSettings = SegmentationSettings()
    estimation: EstimationSettings = EstimationSettings()
    retarget: RetargetSettings = RetargetSettings()
    paths: PathSettings = PathSettings()
    raster: RasterSettings = RasterSettings()
    residual: ResidualSettings = ResidualSettings()

    def to_dict(self) -> dict:
        """Nested plain dict (JSON-able), as stored in a highlight field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> FitSettings:
        """Inverse of ``to_dict``; unknown keys are an ``InputError``. Settings stored by fields written
        before ``ResidualSettings.kind`` (its booleans ``compressed``, ``learned``, ``learned_on_cuda``) read as
        the kind they stood for, and renamed ones (``RESIDUAL_RENAMED``) under today's names."""
        if isinstance(values, dict) and isinstance(values.get("residual"), dict):
            values = {**values, "residual": _renamed(_residual_kind_of_booleans(values["residual"]),
                                                     RESIDUAL_RENAMED)}
        return _build(cls, values, "settings")

    def with_overrides(self, overrides: list[str]) -> FitSettings:
        """Apply edits such as ``"retarget.c_str=0.01"`` or ``"estimation.adam.lr_mean_rpx=0.5"``."""
        values = self.to_dict()
        for text in overrides:
            key, sep, raw = text.partition("=")
            path = [part.strip() for part in key.strip().split(".")]
            if not sep or not all(path):
                raise InputError(f"override '{text}' is not STAGE.NAME=VALUE, e.g. retarget.c_str=0.01")
            node = values
            for part in path[:-1]:
                if not isinstance(node.get(part), dict):
                    raise InputError(
                        f"override '{text}': no settings group '{part}'; groups: {', '.join(_groups(values))}")
                node = node[part]
            name = path[-1]
            if name not in node or isinstance(node[name], dict):
                settings = [k for k, v in node.items() if not isinstance(v, dict)]
                choices = (f"choose from: {', '.join(settings)}" if settings
                           else f"'{name}' is a group; name a setting in it, e.g. {name}.<setting>")
                raise InputError(f"override '{text}': no setting '{name}' here; {choices}")
            node[name] = _parse_like(node[name], raw.strip(), text)
        return FitSettings.from_dict(values)


RESIDUAL_BOOLEANS = ("compressed", "learned", "learned_on_cuda")
"""The residual settings that ``ResidualSettings.kind`` replaced, as older field files store them."""


RESIDUAL_RENAMED = {"still_learned_epochs": "cpu_learned_epochs"}
"""Residual settings under the names older field files store them: old name -> today's."""


def _renamed(values: dict, names: dict) -> dict:
    """``values`` with each key of ``names`` under its new name (where the new one is not there already)."""
    return {names.get(key, key) if names.get(key) not in values else key: value for key, value in values.items()}


def _residual_kind_of_booleans(values: dict) -> dict:
    """Residual settings with the older booleans (``RESIDUAL_BOOLEANS``) replaced by the ``kind`` they chose."""
    if not any(name in values for name in RESIDUAL_BOOLEANS) or "kind" in values:
        return values
    compressed, learned, on_cuda = (values.get(name, default)
                                    for name, default in zip(RESIDUAL_BOOLEANS, (True, False, True)))
    kind = ("learned" if learned is True else "images" if compressed is False else "auto" if on_cuda is True
            else "lowrank")
    return {"kind": kind, **{name: value for name, value in values.items() if name not in RESIDUAL_BOOLEANS}}


def _groups(values: dict, prefix: str = "") -> list[str]:
    names = []
    for key, value in values.items():
        if isinstance(value, dict):
            names.append(prefix + key)
            names.extend(_groups(value, prefix + key + "."))
    return names


def _parse_like(current, raw: str, text: str):
    if isinstance(current, str):
        return raw
    try:
        if isinstance(current, bool):
            if raw.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            return raw.lower() in ("true", "1")
        if isinstance(current, int):
            return int(raw)
        return float(raw)
    except ValueError:
        kind = {bool: "true or false", int: "an integer", float: "a number"}[type(current)]
        raise InputError(f"override '{text}': '{raw}' is not {kind}") from None


def _build(cls, values: dict, where: str):
    if not isinstance(values, dict):
        raise InputError(f"{where} must be a mapping, got {type(values).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise InputError(f"{where}: unknown setting(s) {', '.join(unknown)}")
    kwargs = {}
    for name, value in values.items():
        default = known[name].default
        if hasattr(default, "__dataclass_fields__"):
            kwargs[name] = _build(type(default), value, f"{where}.{name}")
        else:
            kwargs[name] = _checked_value(default, value, f"{where}.{name}")
    return cls(**kwargs)


def _checked_value(default, value, where: str):
    """``value`` as the type of ``default`` (bool, int or float); anything else is an ``InputError``."""
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if isinstance(default, bool) and isinstance(value, bool):
        return value
    if isinstance(default, int) and not isinstance(default, bool) and is_number and float(value).is_integer():
        return int(value)
    if isinstance(default, float) and is_number:
        return float(value)
    if isinstance(default, str) and isinstance(value, str):
        return value
    kind = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}[type(default)]
    raise InputError(f"{where} must be {kind}, got {value!r}")
