"""The core imports with warp + numpy + scipy only, as from a plain checkout on a GPU machine."""

from __future__ import annotations

import subprocess
import sys

OPTIONAL = ("PIL", "OpenEXR", "OpenImageIO", "pyvista", "vtk", "tqdm")

SCRIPT = f"""
import importlib.abc, sys

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {OPTIONAL!r}:
            raise ImportError("blocked optional dependency: " + name)
        return None

sys.meta_path.insert(0, Block())
import warp
warp.config.log_level = warp.LOG_WARNING
import warp_highlights.kernels.raytrace
from warp_highlights.io import dataset
from warp_highlights.model import lights, triangulation
from warp_highlights.synth import render, shapes
from warp_highlights.synth.render import Renderer, RenderSettings
image = Renderer(shapes.teapot(subdivisions=4), settings=RenderSettings(width=16, height=9), device="cpu").render(
    lights.LightSet.fibonacci_sphere(4).directions
)
assert image.full.shape == (4, 9, 16, 3)
import warp_highlights as wh
params = wh.GaussianParams.from_sets([dict(amplitude=[1.0], mean=[[0.8, 0.5]], sigma=[[0.05, 0.03]], theta=[0.2])])
batch = wh.GaussianBatch.from_numpy(params, device="cpu")
raster = wh.Rasterizer(9, 16, device="cpu")
fit = wh.LogL1Loss(raster.render(batch).numpy() * 0.5, device="cpu")
with warp.Tape() as tape:
    loss = fit(raster.render(batch))
tape.backward(loss=loss)
wh.GaussianAdam(batch).step()
data = wh.ReflectanceField(images=image.full, lights=lights.LightSet.fibonacci_sphere(4))
quick = wh.FitSettings().with_overrides(["estimation.iterations=3", "retarget.rigid_iterations=2",
                                         "retarget.iterations=2", "residual.cpu_learned_epochs=0"])
field = wh.fit_field(data, settings=quick, device="cpu")
import tempfile, pathlib
with tempfile.TemporaryDirectory() as folder:
    wh.save_field(field, pathlib.Path(folder) / "f.whf")
    assert wh.load_field(pathlib.Path(folder) / "f.whf").light_count == 4
    assert wh.relight_field(field, [0.0, 0.0, 1.0], device="cpu").specular.shape == (9, 16)
print("core ok")
"""


def test_core_imports_without_optional_dependencies():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr
    assert "core ok" in result.stdout


API_0_1 = (
    "AdamSettings ComponentSettings ConnectedComponents DiffuseModel EnergyLoss EstimationSettings Evaluation "
    "FitSettings GaussianAdam GaussianBatch GaussianParams HighlightField InputError LightSet Location LogL1Loss "
    "PathSettings RasterSettings Rasterizer ReflectanceField Relighter RelitImages Renderer RetargetSettings "
    "SegmentationSettings SphericalTriangulation StructureLoss StructureLossSettings __version__ decide_paths "
    "estimate evaluate_field fit_field retarget segment"
).split()
"""The top-level names of 0.1, before the sub-package layout: they stay."""


def test_public_api_names_resolve():
    import warp_highlights

    assert set(API_0_1) <= set(warp_highlights.__all__)
    for name in warp_highlights.__all__:
        assert getattr(warp_highlights, name) is not None, name


def test_importing_the_package_loads_nothing_heavy():
    """``import warp_highlights`` (and the command line's module) must not load Warp, NumPy or pyvista:
    names load on first use."""
    script = (
        "import sys, warp_highlights, warp_highlights.cli, warp_highlights.model, warp_highlights.view;"
        "print(sorted({'warp', 'numpy', 'scipy', 'pyvista', 'PIL'} & set(sys.modules)))"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_a_fit_does_not_load_what_only_training_needs():
    """The fit and the relighter load ``warp.optim`` (Warp's sparse and solver kernels, 0.25 s of a start)
    only where a learned residual is trained."""
    script = (
        "import sys, warp_highlights.fit.pipeline, warp_highlights.relight.relighter, warp_highlights.cli.fit;"
        "print(sorted({'warp.optim', 'warp.sparse'} & set(sys.modules)))"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_distribution_ships_its_licence_and_type_marker():
    """The wheel carries LICENSE (``license-files``) and ``py.typed`` (PEP 561), both present in the tree."""
    from pathlib import Path

    import pytest

    tomllib = pytest.importorskip("tomllib")
    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())
    assert project["project"]["license"] == "MIT" and project["project"]["license-files"] == ["LICENSE"]
    assert "MIT License" in (root / "LICENSE").read_text()
    assert "py.typed" in project["tool"]["setuptools"]["package-data"]["warp_highlights"]
    assert (root / "warp_highlights" / "py.typed").is_file()
