"""Relighting: a highlight field -> images for any light direction (docs/method.md, Relighting and Evaluation).

Per query: locate it in the triangulation, move the corner lights' Gaussians along their stored paths,
rasterize them, add them to the blended residual (residual transfer). Imports the model, io, the kernels and synth (to
render ground truth for an evaluation), never fit (ARCHITECTURE.md).

- ``Relighter``: a field uploaded once to a device; any batch of directions -> ``RelitImages``.
- ``RelitImages``: relit specular and full images, with each query's face and barycentric weights.
- ``relight_field``: one call from a field and directions to ``RelitImages`` (keeps a ``Relighter``).
- ``RELIGHT_METHODS``: ``circular`` (the method), ``straight`` (its ablation), ``alpha`` (the blend).
- ``DIFFUSE_MODES``: what S' is added to: ``auto``, ``residual``, ``lambert``, ``images``, ``none``.
- ``alpha_inputs``: the per-light images the alpha blend needs, from a dataset at the field's size.
- ``interpolate_sets``: the interpolated Gaussian sets of queries, float64 NumPy (the reference).
- ``INTERPOLATION_METHODS``: ``circular`` and ``straight``.
- ``evaluate_field``: score methods against held-out ground truth: PSNR per query, summaries.
- ``Evaluation``: what ``evaluate_field`` measured; ``to_dict()`` is the JSON report.
- ``score_path``: a field scored along a light path against ground truth rendered at every frame (motion too).
- ``path_renderer``: the renderer that made a dataset, for that ground truth.
- ``psnr_excluding_black``: PSNR per image (dB, peak 1); NaN where both images are all black.
- ``srgb_scores``: PSNR and SSIM per image of linear images shown as 8-bit sRGB.
- ``fit_baseline``: fit an RTI baseline (PTM, HSH, RBF) to images and light directions on a device.
- ``BaselineModel``: a fitted baseline's coefficient planes; ``relight(directions)`` -> images.
- ``BASELINE_METHODS``: ``ptm``, ``hsh2``, ``hsh3`` (hemispherical harmonics), ``rbf`` (Gaussian RBF).
- ``baseline_basis``: the PTM or HSH basis values of light directions, float64 NumPy.
- ``choose_rbf_sigma``: the RBF width with the least leave-one-out error (Rippa's closed form).
- ``surface_maps``: per-pixel normals, albedo and highlight colour of a field (``warp-highlights maps``).
- ``SurfaceMaps``: what ``surface_maps`` returns, with the mask of estimated pixels.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["Relighter", "RelitImages", "relight_field", "RELIGHT_METHODS", "DIFFUSE_MODES",
                         "alpha_inputs"], "relighter"),
        **dict.fromkeys(["interpolate_sets", "INTERPOLATION_METHODS"], "interpolation"),
        **dict.fromkeys(["evaluate_field", "Evaluation", "psnr_excluding_black", "srgb_scores"], "evaluation"),
        **dict.fromkeys(["fit_baseline", "BaselineModel", "BASELINE_METHODS", "baseline_basis", "choose_rbf_sigma"],
                        "baselines"),
        **dict.fromkeys(["surface_maps", "SurfaceMaps"], "maps"),
        **dict.fromkeys(["score_path", "path_renderer"], "path_scores"),
    },
)
