"""The residual: what each captured image holds beyond its own moving highlights, which relighting adds
the moved highlights to (residual transfer, docs/method.md, The residual). Built by a fit, decoded by relighting;
the data classes it fills are ``model.residual``'s. Imports the model, io and the kernels (ARCHITECTURE.md).

- ``resolve_kind``: ``ResidualSettings.kind`` ("auto", ...) -> the concrete kind for a device and a capture.
- ``CONCRETE_KINDS``: the kinds a fitted field can have: lowrank, learned, images, none.
- ``render_own``: every light's own highlights drawn from its Gaussians, (n, H, W) float32.
- ``highlight_colour``: the per-pixel highlight colour c(x) from the specular part.
- ``residual_of``: R = I - c(x) R(x; G): images less their own highlights.
- ``build_residual``: the low-rank residual within the size budget, or the images themselves (float16).
- ``PrincipalImages``: the principal images of a stack (an uncentred PCA through the Gram matrix).
- ``quantised_stack``: a ``LowRankStack`` of principal images quantised with given steps, weights fitted.
- ``fit_stack``: a ``LowRankStack`` of a given rank of an (n, H, W, P) array.
- ``allocate``: the rate search: each stack's kept images and their steps within a byte budget.
- ``StackPlan``: a stack's energies and gains, which the rate search allocates over.
- ``learn_residual``: the learned residual (codes and an MLP), trained on the residual images.
- ``check_learned``: whether the learned residual keeps the moving Gaussians or learns the images alone.
- ``LearnedCheck``: what ``check_learned`` measured at its left-out lights.
- ``choose_interpolation``: the triangle's or radial basis weights for a low-rank residual, by leave-one-out.
- ``InterpolationChoice``: what ``choose_interpolation`` measured at its left-out lights.
- ``decoded_images``: every captured light's residual image, float16.
- ``light_images``: the residual blended with per-light weights, float64 (the reference).
- ``light_weights``: the per-light weights relighting blends the residual with at query directions, float64.
- ``learned_images``: a learned residual at query directions, float64 (the reference).
- ``decode_residual``: a low-rank residual's images decoded on a Warp device.
- ``to_opponent``: linear RGB -> luminance and chroma (B - Y, R - Y); ``from_opponent`` the inverse.
- ``from_opponent``: luminance and chroma -> linear RGB.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["resolve_kind", "CONCRETE_KINDS"], "kind"),
        **dict.fromkeys(["render_own", "highlight_colour", "residual_of"], "inputs"),
        "build_residual": "build",
        "PrincipalImages": "principal",
        **dict.fromkeys(["quantised_stack", "fit_stack"], "quantise"),
        **dict.fromkeys(["allocate", "StackPlan"], "rate"),
        **dict.fromkeys(["learn_residual", "check_learned", "LearnedCheck"], "learned"),
        **dict.fromkeys(["choose_interpolation", "InterpolationChoice"], "interpolation"),
        **dict.fromkeys(["decoded_images", "light_images", "light_weights", "learned_images"], "decode"),
        "decode_residual": "device",
        **dict.fromkeys(["to_opponent", "from_opponent"], "opponent"),
    },
)
