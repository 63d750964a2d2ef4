"""Relighting: a highlight field -> images for any light direction (method.md sections 6-7).

Per query: locate it in the triangulation, move the corner lights' Gaussians along their stored paths,
rasterize them, add the diffuse part. Imports the model, io, the kernels and synth (to render ground
truth for an evaluation), never fit (ARCHITECTURE.md).

- ``Relighter``: a field uploaded once to a device; any batch of directions -> ``RelitImages``.
- ``RelitImages``: relit specular and full images, with each query's face and barycentric weights.
- ``relight_field``: one call from a field and directions to ``RelitImages`` (keeps a ``Relighter``).
- ``RELIGHT_METHODS``: ``circular`` (the method), ``straight`` (its ablation), ``alpha`` (the blend).
- ``DIFFUSE_MODES``: where the diffuse part comes from: ``auto``, ``lambert``, ``images``, ``none``.
- ``alpha_inputs``: the per-light images the alpha blend needs, from a dataset at the field's size.
- ``interpolate_sets``: the interpolated Gaussian sets of queries, float64 NumPy (the reference).
- ``INTERPOLATION_METHODS``: ``circular`` and ``straight``.
- ``evaluate_field``: score methods against held-out ground truth: PSNR per query, summaries.
- ``Evaluation``: what ``evaluate_field`` measured; ``to_dict()`` is the JSON report.
- ``psnr_excluding_black``: PSNR per image (dB, peak 1); NaN where both images are all black.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["Relighter", "RelitImages", "relight_field", "RELIGHT_METHODS", "DIFFUSE_MODES", "alpha_inputs"], "relighter"),
        **dict.fromkeys(["interpolate_sets", "INTERPOLATION_METHODS"], "interpolation"),
        **dict.fromkeys(["evaluate_field", "Evaluation", "psnr_excluding_black"], "evaluation"),
    },
)
