"""Shared fixtures: Warp devices to test on, the sample datasets, small captures and fields, headless Chromium, and the
figures ``view.plots`` draws."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def sample_data_root() -> Path:
    """Folder with the real RTI samples: $WARP_HIGHLIGHTS_DATA, else ../shared/data beside the project."""
    return Path(os.environ.get("WARP_HIGHLIGHTS_DATA", PROJECT_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_root() -> Path:
    root = sample_data_root()
    if not root.is_dir():
        pytest.skip(f"sample datasets not found at {root} (set WARP_HIGHLIGHTS_DATA)")
    return root


def _devices() -> list[str]:
    import warp as wp

    wp.init()
    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


@pytest.fixture(params=_devices())
def device(request) -> str:
    """Every device-generic test runs on the CPU, and on CUDA when present."""
    return request.param


@pytest.fixture(scope="session")
def small_donut(tmp_path_factory) -> Path:
    """A rendered donut dataset small enough for CPU fits in tests: 32 Fibonacci lights, 96 x 54, centroid ground
    truth."""
    from warp_highlights.model.lights import LightSet
    from warp_highlights.synth.render import (
        RenderSettings,
        default_material,
        render_dataset,
    )

    folder = tmp_path_factory.mktemp("data") / "donut"
    return render_dataset(
        "donut",
        folder,
        lights=LightSet.fibonacci_sphere(32),
        material=default_material("donut"),
        settings=RenderSettings(width=96, height=54),
        device="cpu",
        progress=False,
    )


FAST_FIT = [
    "estimation.iterations=300",
    "estimation.densify_until=200",
    "estimation.densify_every=50",
    "retarget.rigid_iterations=40",
    "retarget.iterations=80",
    "residual.cpu_learned_epochs=0",
]
"""Overrides that keep a test fit of ``small_donut`` to a few seconds on one CPU core ("auto" keeps a low-rank
residual on the CPU: these tests need a field, not a trained decoder)."""


@pytest.fixture(scope="session")
def small_field(small_donut, tmp_path_factory) -> Path:
    """A quick fit of ``small_donut`` (``FAST_FIT``, diffuse images kept), saved as a .whf file."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.fieldfile import save_field
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    field = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT), device="cpu", diffuse="images",
                      progress=False)
    path = tmp_path_factory.mktemp("field") / "donut.whf"
    save_field(field, path)
    return path


TINY_FIT = [
    "--set", "estimation.iterations=60",
    "--set", "estimation.densify_until=40",
    "--set", "estimation.densify_every=10",
    "--set", "retarget.rigid_iterations=10",
    "--set", "retarget.iterations=20",
    "--set", "residual.cpu_learned_epochs=0",
]  # fmt: skip
"""``fit`` options for a fit of a few tenths of a second (the reliability tests need a field, not a good one)."""


@pytest.fixture(scope="session")
def tiny_sphere(tmp_path_factory) -> tuple[Path, Path]:
    """``(dataset, field)``: a 16-light 32x18 sphere with held-out centroids and a ``TINY_FIT`` of it
    (diffuse images kept), made through the command line."""
    from warp_highlights.cli import main

    root = tmp_path_factory.mktemp("tiny-sphere")
    data, field = root / "sphere", root / "sphere.whf"
    assert main(["render", "sphere", str(data), "--lights", "16", "--size", "32x18", "--samples", "1", "--device",
                 "cpu", "-q"]) == 0
    assert main(["fit", str(data), "-o", str(field), "--diffuse", "images", "--device", "cpu", "-q", *TINY_FIT]) == 0
    return data, field


@pytest.fixture
def drawn_figures(monkeypatch) -> dict:
    """Every figure ``view.plots`` writes during the test, by file name, to find its panels in the PNG."""
    from warp_highlights.view import plots

    figures = {}
    save = plots._save

    def keep(fig, path):
        figures[Path(path).name] = fig
        return save(fig, path)

    monkeypatch.setattr(plots, "_save", keep)
    return figures


def panel_pixels(figure, png) -> list[tuple[str, object]]:
    """``(title, pixels)`` of every titled panel of ``figure``, in order: the RGB pixels of the inner 80% of
    the panel, read from the PNG the figure was written to (same DPI, so figure pixels are PNG pixels)."""
    import numpy as np
    from PIL import Image

    with Image.open(png) as image:
        pixels = np.asarray(image.convert("RGB"))
    height = pixels.shape[0]
    assert abs(height - figure.bbox.height) < 1
    panels = []
    for ax in figure.axes:
        if not ax.get_title():
            continue
        box = ax.get_window_extent()
        dx, dy = 0.1 * box.width, 0.1 * box.height
        rows = slice(round(height - box.y1 + dy), round(height - box.y0 - dy))
        columns = slice(round(box.x0 + dx), round(box.x1 - dx))
        panels.append((ax.get_title(), pixels[rows, columns]))
    return panels


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SOFTWARE_GL = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


@pytest.fixture(scope="session")
def browser():
    """Headless Chromium (software GL) through Playwright, for the session; skips where either is absent."""
    if CHROMIUM is None:
        pytest.skip("no chromium on the PATH (apt install chromium)")
    playwright = pytest.importorskip("playwright.sync_api",
                                     reason="Playwright for Python is not installed (pip install playwright)")
    with playwright.sync_playwright() as driver:
        launched = driver.chromium.launch(executable_path=CHROMIUM, args=SOFTWARE_GL)
        yield launched
        launched.close()


@pytest.fixture(scope="session")
def small_learned_field(small_donut, tmp_path_factory):
    """The small donut fitted with a learned residual (``FAST_FIT``, a few epochs) and saved: (field, path). Its
    learned check keeps the moving Gaussians whatever it scores (tie margins beyond any gap, gliding or not): over so
    few epochs its verdict says little, and the tests of what a learned field holds need them."""
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.io.fieldfile import save_field
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=learned", "residual.learned_epochs=6",
                                                     "residual.learned_tune_epochs=2",
                                                     "residual.learned_tie_margin_db=100",
                                                     "residual.learned_glide_margin_db=100"])
    field = fit_field(dataset, device="cpu", settings=settings, progress=False)
    path = tmp_path_factory.mktemp("learned") / "learned.whf"
    save_field(field, path)
    return field, path


def smooth_plate(count: int = 25, height: int = 12, width: int = 20):
    """(n, H, W, 3) float32 display values in [0.05, 0.95] of a smooth bumpy Lambertian plate under a Fibonacci dome
    of ``count`` lights above 15 degrees (what JPEG planes and 8-bit coefficients keep, as a photograph's do), and
    the (n, 3) lights."""
    import numpy as np

    from warp_highlights.model.lights import LightSet

    lights = LightSet.fibonacci_dome(count, min_elevation_deg=15).directions
    v, u = np.mgrid[0:height, 0:width] / max(height, width)
    normal = np.stack([0.4 * np.sin(5 * u), 0.3 * np.cos(4 * v), np.ones_like(u)], axis=2)
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    albedo = np.stack([0.5 + 0.3 * u, 0.6 + 0.2 * v, 0.4 + 0.3 * u * v], axis=2)
    shade = np.clip(np.einsum("hwk,nk->nhw", normal, lights), 0, 1)[..., None]
    return (0.05 + 0.9 * albedo * shade).astype(np.float32), lights


def write_capture(folder: Path, values, lights) -> Path:
    """``folder`` made a capture: the (n, H, W, 3) display values as PNGs im00.png ... and their lights.lp."""
    from warp_highlights.io.images import srgb_to_linear, write_image
    from warp_highlights.io.lightfile import write_lp
    from warp_highlights.model.lights import LightSet

    folder.mkdir(parents=True)
    names = [f"im{i:02d}.png" for i in range(len(lights))]
    for name, image in zip(names, values):
        write_image(folder / name, srgb_to_linear(image))
    write_lp(LightSet(lights), folder / "lights.lp", filenames=names)
    return folder


def centred_blob_sets(problems: int, slots: int, size: int = 32):
    """``problems`` sets of ``slots`` equal Gaussians (sigma 0.08 image heights, amplitude 1) at the centre of a
    ``size`` x ``size`` image, and a (2, size, size) CPU stack of two images holding the same Gaussian there: a
    target every slot lands on."""
    import numpy as np
    import warp as wp

    from warp_highlights.model.gaussians import GaussianParams

    sets = GaussianParams.empty(problems, slots)
    sets.active[:] = True
    sets.amplitude[:] = 1.0
    sets.mean[:] = [0.5, 0.5]
    sets.sigma[:] = 0.08
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    blob = np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / (2 * 0.08**2)).astype(np.float32)
    return sets, wp.array(np.stack([blob, blob]), dtype=float, device="cpu")
