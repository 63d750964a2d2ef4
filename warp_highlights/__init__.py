"""warp-highlights: relight reflectance fields with moving specular highlights, built on NVIDIA Warp.

The package reads as the method's pipeline (ARCHITECTURE.md): ``model`` (what a highlight field is
made of), ``io`` (files), ``quality`` (PSNR, SSIM), ``kernels`` (every Warp kernel), ``fit`` (segment
-> estimate -> retarget -> decide paths), ``relight``, ``synth`` (synthetic data), ``view`` and ``cli``.
The names below are the everyday API; each sub-package's ``__init__`` lists what else it offers.
"""

from __future__ import annotations

import importlib.util as _importlib_util
import logging as _logging
import sys as _sys
from pathlib import Path as _Path

__version__ = "0.1.0"

# Library messages (stage timings, training progress) go to the "warp_highlights" logger at INFO; an
# application that configures logging sees them, one that does not sees nothing (the command line
# shows them on stderr, -q hides them, -v adds DEBUG).
_logging.getLogger(__name__).addHandler(_logging.NullHandler())


def _attach_checkout_kernels() -> None:
    """Make ``warp_highlights.kernels`` importable when running from a source checkout via PYTHONPATH.

    An install maps the top-level kernels/ folder to this subpackage (pyproject.toml); on a machine
    where the project is only on PYTHONPATH (a plain checkout, as the benchmarks run), the mapping is
    done here.
    """
    name = f"{__name__}.kernels"
    folder = _Path(__file__).resolve().parent.parent / "kernels"
    if name in _sys.modules or _importlib_util.find_spec(name) is not None or not (folder / "__init__.py").is_file():
        return
    spec = _importlib_util.spec_from_file_location(name, folder / "__init__.py",
                                                   submodule_search_locations=[str(folder)])
    module = _importlib_util.module_from_spec(spec)
    _sys.modules[name] = module
    spec.loader.exec_module(module)


_attach_checkout_kernels()

# The public API, imported on first use so that `import warp_highlights` stays light (the command line
# parses its arguments before Warp loads). Each name lives in the sub-package that says what it is
# (ARCHITECTURE.md); the sub-packages' own __init__ files list more.
from ._api import lazy_exports as _lazy_exports  # noqa: E402 (after the kernels are attached)

__getattr__, __dir__, _exported = _lazy_exports(
    __name__,
    {
        # the object model
        "LightSet": "model.lights",
        "SphericalTriangulation": "model.triangulation",
        "Location": "model.triangulation",
        "GaussianParams": "model.gaussians",
        "GaussianBatch": "model.gaussians",
        "ConnectedComponents": "model.components",
        "HighlightField": "model.field",
        "DiffuseModel": "model.field",
        "FitSettings": "model.config",
        "RasterSettings": "model.config",
        "SegmentationSettings": "model.config",
        "EstimationSettings": "model.config",
        "AdamSettings": "model.config",
        "StructureLossSettings": "model.config",
        "ComponentSettings": "model.config",
        "RetargetSettings": "model.config",
        "PathSettings": "model.config",
        "InputError": "model.errors",
        # files
        "read_lp": "io.lightfile",
        "read_lights": "io.lightfile",
        "write_lp": "io.lightfile",
        "ReflectanceField": "io.dataset",
        "save_field": "io.fieldfile",
        "load_field": "io.fieldfile",
        "field_size_report": "io.fieldfile",
        # the kernels' Python side
        "Rasterizer": "kernels.raster",
        "LogL1Loss": "kernels.losses",
        "StructureLoss": "kernels.losses",
        "EnergyLoss": "kernels.losses",
        "GaussianAdam": "kernels.optim",
        # fitting, stage by stage
        "segment": "kernels.segmentation",
        "estimate": "fit.estimation",
        "retarget": "fit.retargeting",
        "decide_paths": "fit.paths",
        "fit_field": "fit.pipeline",
        # relighting and evaluation
        "Relighter": "relight.relighter",
        "RelitImages": "relight.relighter",
        "relight_field": "relight.relighter",
        "Evaluation": "relight.evaluation",
        "evaluate_field": "relight.evaluation",
        "surface_maps": "relight.maps",
        "SurfaceMaps": "relight.maps",
        # synthetic data
        "Renderer": "synth.render",
    },
    modules={"viz": "view.viz"},
)
__all__ = ["__version__", *_exported]
