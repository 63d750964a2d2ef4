"""Every Warp kernel of warp-highlights, one module per concern, each kernel beside its launch wrapper.

Installed as ``warp_highlights.kernels`` (see pyproject.toml). The kernels take the model's Gaussian
batches and settings and import nothing else of the package (ARCHITECTURE.md). A new kernel goes into
the module of its concern, with a float64 NumPy reference and a gradient check in the tests.

- ``raster``: the differentiable rasterizer of batched 2D Gaussian sets (``Rasterizer``).
- ``losses``: per-problem losses with hand-written adjoints (``LogL1Loss``, ``StructureLoss``, ``EnergyLoss``).
- ``optim``: batched Adam over every problem and slot, one launch per step (``GaussianAdam``).
- ``segmentation``: the robust per-pixel diffuse/specular split (``segment``).
- ``support``: how much of each retargeted Gaussian its target image holds (the move decision).
- ``retarget``: rigid motions of connected components and the image gather (retargeting phase 1).
- ``interpolation``: locate queries, interpolate Gaussian sets, compose relit images.
- ``upsample``: relit images larger than the field, composed from the field's arrays at its own size.
- ``baselines``: the classic RTI fits (PTM, HSH, RBF) as per-pixel linear maps: project and evaluate.
- ``neural``: a learned per-pixel residual (code + MLP, NeuralRTI-style) trained with tiles and the tape.
- ``raytrace``: the synthetic-data renderer's camera rays and shading over a ``wp.Mesh``.
- ``tape``: the calling thread's tape (``recording``, ``active_tape``), one Adam iteration on it, its CUDA-graph replay.
- ``chunks``: a batch of independent problems split over CPU threads (Warp runs a CPU launch on one).
- ``gram``: the residual's Gram matrices, projections and weight sums on a device (``DeviceProducts``).
- ``rows``: long float32 rows held on a device in parts of at most 2 GiB (``DeviceRows``).
- ``stacks``: the residual's normalised luminance and chroma stacks made and held on a device (``NormalisedStacks``).
- ``quantise``: principal images held on a device, quantised and stored there (``DeviceBasis``).
- ``regions``: the residual's connected regions labelled and measured on a device (``ResidualRegions``).
- ``transfer``: large device arrays into host pages mapped first (``to_host``); bands of a stack up and
  down an image's rows at a time (``rows_up``, ``rows_down``).
- ``warmup``: Warp started and a device's context made in a thread (``DeviceWarmup``); work in a thread
  (``InBackground``).
"""

from warp_highlights._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {},
    modules={
        "baselines": "baselines", "chunks": "chunks", "interpolation": "interpolation", "losses": "losses",
        "neural": "neural", "optim": "optim", "raster": "raster",
        "raytrace": "raytrace", "retarget": "retarget", "segmentation": "segmentation", "support": "support",
        "gram": "gram", "rows": "rows",
        "stacks": "stacks", "quantise": "quantise", "transfer": "transfer", "regions": "regions", "tape": "tape",
        "warmup": "warmup", "upsample": "upsample",
    },
)
