"""The object model: what a highlight field is made of. Imports nothing above it (ARCHITECTURE.md).

- ``LightSet``: light directions (unit vectors towards the lights); Fibonacci sphere and dome sets.
- ``SphericalTriangulation``: the lights' spherical Delaunay triangulation; faces, edges, ``locate``.
- ``Location``: where query directions fall: face, its corner lights, barycentric weights.
- ``GaussianParams``: B sets of up to N 2D Gaussians as float64 NumPy arrays (host side, files, tests).
- ``GaussianBatch``: the same as structure-of-arrays Warp arrays, one batch for every kernel.
- ``GaussianArrays``: the ``wp.struct`` of a batch's arrays that kernels take.
- ``ConnectedComponents``: overlapping Gaussians of a set grouped, for the rigid retargeting phase.
- ``HighlightField``: the fitted model: lights, triangulation, Gaussians, paths, settings, report.
- ``DiffuseModel``: a field's diffuse part: per-pixel Lambertian planes, optionally the diffuse images.
- ``ResidualModel``: the images minus their moving highlights, for residual transfer; low rank or whole.
- ``LowRankStack``: n images as a mean plus weighted 8-bit basis images.
- ``MAX_CAPACITY``: most Gaussian slots per set a field may have.
- ``rotation_options``: the two signed rotations that turn one orientation into another (radians).
- ``path_centre``: centre of the arc a Gaussian's mean follows along an edge (image heights).
- ``circular_position``: a point a fraction of the way along that arc (image heights).
- ``move_sets``: Gaussian sets moved to query directions inside their triangles (float64, plain arrays).
- ``FitSettings``: every hyper-parameter of a fit, by stage; ``--set STAGE.NAME=VALUE`` edits it.
- ``RasterSettings``: Gaussian footprint cutoff, size floor and tile size of the rasterizer.
- ``SegmentationSettings``: the diffuse/specular split of the images.
- ``EstimationSettings``: Gaussians per light image: iterations, densification, capacity.
- ``AdamSettings``: learning rates of the Gaussian optimiser.
- ``StructureLossSettings``: the retargeting's structure term.
- ``ComponentSettings``: when two Gaussians belong to one connected component.
- ``RetargetSettings``: loss weights and iterations of retargeting.
- ``PathSettings``: straight-path threshold and the path-decision length scale.
- ``ResidualSettings``: residual transfer: compression, move decision, highlight colour.
- ``MapSettings``: which lights light a pixel for its normal and albedo (``warp-highlights maps``).
- ``REFERENCE_HEIGHT_PX``: the image height that pixel-valued settings refer to ("rpx").
- ``rpx_to_normalized``: reference pixels -> image heights.
- ``normalized_to_rpx``: image heights -> reference pixels.
- ``pixel_area_rpx2``: area of one pixel of an image of some height, in reference pixels squared.
- ``InputError``: the one exception for bad input; the command line prints it as one line.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "LightSet": "lights",
        **dict.fromkeys(["SphericalTriangulation", "Location"], "triangulation"),
        **dict.fromkeys(["GaussianParams", "GaussianBatch", "GaussianArrays"], "gaussians"),
        "ConnectedComponents": "components",
        **dict.fromkeys(["ResidualModel", "LowRankStack"], "residual"),
        **dict.fromkeys(["HighlightField", "DiffuseModel", "MAX_CAPACITY"], "field"),
        **dict.fromkeys(["rotation_options", "path_centre", "circular_position"], "arcs"),
        "move_sets": "interpolation",
        **dict.fromkeys(
            [
                "FitSettings", "RasterSettings", "SegmentationSettings", "EstimationSettings", "AdamSettings",
                "StructureLossSettings", "ComponentSettings", "RetargetSettings", "PathSettings", "ResidualSettings",
                "MapSettings", "REFERENCE_HEIGHT_PX", "rpx_to_normalized", "normalized_to_rpx", "pixel_area_rpx2"
            ],
            "config",
        ),
        "InputError": "errors",
    },
)
