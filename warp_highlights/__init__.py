"""warp-highlights: relight reflectance fields with moving specular highlights, built on NVIDIA Warp."""

from __future__ import annotations

import importlib.util as _importlib_util
import sys as _sys
from pathlib import Path as _Path

__version__ = "0.1.0"


def _attach_checkout_kernels() -> None:
    """Make ``warp_highlights.kernels`` importable when running from a source checkout via PYTHONPATH.

    An install maps the top-level kernels/ folder to this subpackage (pyproject.toml); on a machine
    where the project is only on PYTHONPATH (the lent GPU machine), the mapping is done here.
    """
    name = f"{__name__}.kernels"
    folder = _Path(__file__).resolve().parent.parent / "kernels"
    if name in _sys.modules or _importlib_util.find_spec(name) is not None or not (folder / "__init__.py").is_file():
        return
    spec = _importlib_util.spec_from_file_location(name, folder / "__init__.py", submodule_search_locations=[str(folder)])
    module = _importlib_util.module_from_spec(spec)
    _sys.modules[name] = module
    spec.loader.exec_module(module)


_attach_checkout_kernels()

# Public API, imported on first use so that `import warp_highlights` stays light (the CLI parses its
# arguments before Warp loads).
_EXPORTS = {
    "AdamSettings": "config",
    "ComponentSettings": "config",
    "EstimationSettings": "config",
    "FitSettings": "config",
    "PathSettings": "config",
    "RasterSettings": "config",
    "RetargetSettings": "config",
    "SegmentationSettings": "config",
    "StructureLossSettings": "config",
    "ConnectedComponents": "components",
    "DiffuseModel": "field",
    "HighlightField": "field",
    "Location": "triangulation",
    "decide_paths": "paths",
    "estimate": "estimation",
    "fit_field": "fit",
    "retarget": "retarget",
    "segment": "kernels.segmentation",
    "GaussianBatch": "gaussians",
    "GaussianParams": "gaussians",
    "LightSet": "lights",
    "ReflectanceField": "dataset",
    "Renderer": "render",
    "SphericalTriangulation": "triangulation",
    "InputError": "errors",
    "Rasterizer": "kernels.raster",
    "LogL1Loss": "kernels.losses",
    "StructureLoss": "kernels.losses",
    "EnergyLoss": "kernels.losses",
    "GaussianAdam": "kernels.optim",
    "Relighter": "relight",
    "RelitImages": "relight",
    "Evaluation": "evaluation",
    "evaluate_field": "evaluation",
}
__all__ = [
    "AdamSettings",
    "ComponentSettings",
    "ConnectedComponents",
    "DiffuseModel",
    "EnergyLoss",
    "EstimationSettings",
    "Evaluation",
    "FitSettings",
    "GaussianAdam",
    "GaussianBatch",
    "GaussianParams",
    "HighlightField",
    "InputError",
    "LightSet",
    "Location",
    "LogL1Loss",
    "PathSettings",
    "RasterSettings",
    "Rasterizer",
    "ReflectanceField",
    "Relighter",
    "RelitImages",
    "Renderer",
    "RetargetSettings",
    "SegmentationSettings",
    "SphericalTriangulation",
    "StructureLoss",
    "StructureLossSettings",
    "__version__",
    "decide_paths",
    "estimate",
    "evaluate_field",
    "fit_field",
    "retarget",
    "segment",
]


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
