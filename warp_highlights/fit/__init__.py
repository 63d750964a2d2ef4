"""Fitting: a reflectance field -> a highlight field (docs/method.md, Fitting), stage by stage.

The pipeline is ``segment -> estimate -> retarget -> decide_paths -> decide_moving -> check_moving -> build_residual``;
``fit_field`` runs all of it.
Each stage takes and returns a whole batch (every light, every directed edge). Imports the model,
io and the kernels (ARCHITECTURE.md).

- ``fit_field``: the whole precomputation: dataset -> ``HighlightField`` (report included).
- ``segment``: stage 1: every image -> diffuse and specular parts (a Warp kernel, from ``kernels``).
- ``estimate``: stage 2: a few Gaussians per specular image, every light in one batch.
- ``EstimationResult``: the estimated sets with their loss and PSNR per light.
- ``retarget``: stage 3: re-fit every estimated set onto each neighbouring light's specular image.
- ``RetargetResult``: the retargeted sets of every directed edge with their losses.
- ``decide_paths``: stage 4: which way each Gaussian turns along each directed edge.
- ``PathDecisions``: the chosen rotations and arc centres.
- ``decide_moving``: stage 5: which Gaussians move (their retargeting lands on the neighbours' highlights).
- ``MoveDecision``: the move flags and the support of every retargeted Gaussian.
- ``plan_check``: the captured lights left out to check that moving pays, and the edges they need.
- ``check_moving``: stage 5b: moving against blending at those lights (``MoveCheck``).
- ``MoveCheck``: both predictions' 8-bit sRGB PSNR per left-out light and the verdict.
- ``build_residual``: stage 6: each image minus its own highlights, compressed (``ResidualModel``; from ``residual``).
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "fit_field": "pipeline",
        "segment": "..kernels.segmentation",
        **dict.fromkeys(["estimate", "EstimationResult"], "estimation"),
        **dict.fromkeys(["retarget", "RetargetResult"], "retargeting"),
        **dict.fromkeys(["decide_paths", "PathDecisions"], "paths"),
        **dict.fromkeys(["decide_moving", "MoveDecision"], "moving"),
        "build_residual": "..residual.build",
        **dict.fromkeys(["plan_check", "check_moving", "MoveCheck"], "validation"),
    },
)
