"""Build the walkthrough notebooks from the cell sources in this file, and optionally run them.

The ``.ipynb`` files in this folder are generated: edit the cells here, then rebuild and re-run::

    python notebooks/build_notebooks.py --execute            # both notebooks, outputs stored
    python notebooks/build_notebooks.py quickstart           # one notebook, sources only (no outputs)

``--execute`` runs each notebook top to bottom in a fresh ``python3`` kernel (nbclient) with a
temporary working folder, so nothing but the ``.ipynb`` file is written into the repository, and
stores the outputs with the volatile metadata (timings, kernel versions) stripped. The test
``tests/test_notebooks.py`` checks that the committed notebooks match these sources.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT_VARIABLE = "WARP_HIGHLIGHTS_NOTEBOOK_OUT"
"""Environment variable naming the folder a notebook writes into (a new temporary folder when unset)."""

KERNELSPEC = {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"}


def md(text: str) -> tuple[str, str]:
    return ("markdown", text.strip("\n"))


def code(text: str) -> tuple[str, str]:
    return ("code", text.strip("\n"))


# --- quickstart.ipynb -------------------------------------------------------------------------------

QUICKSTART = [
    md("""
# Quickstart: render, fit, relight, evaluate

This notebook runs the whole warp-highlights pipeline in Python on a small synthetic example:

1. **render** a reflectance field: the built-in donut, ray-traced under 48 light directions, with
   ground-truth specular and diffuse images;
2. **triangulate** the light directions on the sphere;
3. **fit** a highlight field: a few 2D Gaussians per light image, re-fitted onto every neighbouring
   light, plus the path each Gaussian takes between neighbours;
4. **relight** the donut from light directions that were never captured;
5. **compare** circular paths, straight paths and the alpha blend at a held-out light, and
   **evaluate** all three against rendered ground truth.

It is the same as `warp-highlights demo` (see `warp_highlights/cli/demo.py`), at a smaller size:
48 lights at 192 x 108 pixels instead of 64 at 240 x 135, so that it runs top to bottom in well under a
minute on a 2-core CPU. Everything runs on `wp.get_preferred_device()`: CUDA when present, else the
CPU. Files go into a temporary folder (or the folder named by `$WARP_HIGHLIGHTS_NOTEBOOK_OUT`), never
into the repository.
"""),
    code("""
%matplotlib inline
import os
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import warp as wp

import warp_highlights as wh
from warp_highlights.io.images import display_rgb8  # linear radiance -> 8-bit sRGB

plt.rcParams.update({"figure.dpi": 72, "font.size": 9, "axes.titlesize": 9})  # small inline PNGs
wp.config.log_level = wp.LOG_WARNING  # no greeting and no per-module compile lines; warnings stay
wp.init()
device = wp.get_preferred_device()
work = Path(os.environ.get("WARP_HIGHLIGHTS_NOTEBOOK_OUT") or tempfile.mkdtemp(prefix="wh-quickstart-"))
work.mkdir(parents=True, exist_ok=True)

LIGHTS, WIDTH, HEIGHT = 48, 192, 108
print(f"warp {wp.__version__}, warp-highlights {wh.__version__}, device: {device}")


def show(images, titles, *, panel_width=3.6, suptitle=None):
    \"\"\"Linear images side by side, clipped to [0, 1] and sRGB-encoded for the screen.\"\"\"
    height = panel_width * images[0].shape[0] / images[0].shape[1]
    fig, axes = plt.subplots(1, len(images), figsize=(panel_width * len(images), height + 0.4), squeeze=False)
    for ax, image, title in zip(axes[0], images, titles):
        ax.imshow(display_rgb8(image), interpolation="nearest")
        ax.set_title(title)
        ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle)
    fig.tight_layout()
    plt.show()
"""),
    md("""
## 1. Render a reflectance field

`render_dataset` ray-traces the donut with Warp (a BVH over the mesh, shadow rays per light) and
writes a dataset folder: one EXR per light, the specular and diffuse parts as ground truth, and
*held-out* images at the centroid of every triangle of the lights' triangulation, which the
evaluation compares with. The lights are a Fibonacci spiral over the whole sphere, so about half of
them light the donut from behind.
"""),
    code("""
from warp_highlights.synth.render import RenderSettings, render_dataset

t = time.perf_counter()
folder = render_dataset("donut", work / "donut", lights=wh.LightSet.fibonacci_sphere(LIGHTS),
                        settings=RenderSettings(width=WIDTH, height=HEIGHT), device=str(device), progress=False)
dataset = wh.ReflectanceField.load(folder, progress=False)
print(f"rendered and loaded in {time.perf_counter() - t:.1f} s")
info = dataset.summary()
for key in ("lights", "size", "channels", "coverage", "triangles", "ground_truth", "heldout_lights"):
    print(f"{key:>15}: {info[key]}")
"""),
    md("""
A contact sheet shows a few lights: each cell is the full image, its specular part and its diffuse
part (linear radiance, clipped to [0, 1] and sRGB-encoded). The specular highlights are what the
method models with Gaussians; the diffuse part gets a per-pixel Lambertian model.
"""),
    code("""
from warp_highlights.view.preview import contact_sheet

sheet = contact_sheet(dataset, count=6, thumb_height=HEIGHT, columns=2)
plt.figure(figsize=(sheet.shape[1] / 72, sheet.shape[0] / 72))
plt.imshow(sheet)
plt.axis("off")
plt.show()
"""),
    md("""
## 2. Triangulate the light directions

The light directions are the vertices of a spherical Delaunay triangulation. A new light direction
falls into one triangle; its three corners are the captured lights it is interpolated from, with
barycentric weights. Every triangle has three edges, each used in both directions: the fit re-fits
every light's Gaussians onto each neighbour's image, once per *directed* edge.
"""),
    code("""
triangulation = wh.SphericalTriangulation(dataset.lights.directions)
print(f"{triangulation.light_count} lights, {triangulation.face_count} triangles, "
      f"{len(triangulation.edges())} edges, {len(triangulation.directed_edges())} directed edges, "
      f"{'dome' if triangulation.is_dome else 'full sphere'}")

query = np.array([[0.45, 0.35, 0.82]])
location = triangulation.locate(query)
print(f"the direction {np.round(query[0] / np.linalg.norm(query), 3).tolist()} lies in triangle {location.faces[0]}: "
      f"lights {location.vertices[0].tolist()} with weights {np.round(location.barycentric[0], 3).tolist()}")
"""),
    md("""
## 3. Fit the highlight field

`fit_field` runs every stage of the precomputation, each batched over all lights or all directed
edges:

- **segmentation** splits every image into diffuse and specular parts (a per-pixel Lambertian fit
  that ignores outliers);
- **estimation** fits a few Gaussians to every light's specular image, adding Gaussians where the
  residual is large and removing useless ones;
- **retargeting** moves each light's Gaussians onto every neighbour's image, first rigidly per
  connected group, then freely, keeping slot p of the source as slot p of the result;
- **paths** decides, once per Gaussian and directed edge, which way it turns and around which centre.

The default settings are used but for the residual: `residual.kind=lowrank` keeps it a low-rank compression of
the images less their highlights, so that at this size the fit takes 10-20 s on a 2-core CPU, nearly all of it in
estimation and retargeting. The default (`wh.FitSettings()`) learns the residual, in seconds on a GPU and in about
two minutes on a 2-core CPU, and keeps the moving Gaussians only where a check on left-out lights finds them better
than the images learned alone. `FitSettings().with_overrides(["estimation.iterations=300", ...])` changes any
setting, as `--set` does on the command line.
"""),
    code("""
t = time.perf_counter()
settings = wh.FitSettings().with_overrides(["residual.kind=lowrank"])
field = wh.fit_field(dataset, settings=settings, device=device, log=lambda line: print("  " + line))
print(f"fit in {time.perf_counter() - t:.1f} s\\n")
print(field.describe())
size = wh.save_field(field, work / "donut.whf")
print(f"saved donut.whf: {size / 1e3:.0f} kB")
"""),
    md("""
**Gaussians per light.** Most lights get a handful of Gaussians. A light close to the image plane
(about 90 degrees from the camera axis) makes long curved highlights along the ring, which take many
narrow ones. Below: the count per light against the light's angle from the camera axis, then the
light with the most Gaussians: its ground-truth specular image, its Gaussians drawn by the
project's rasterizer, and their 2-sigma ellipses (positions and sizes are stored in image heights,
so they are scaled by the image height to pixels).
"""),
    code("""
from matplotlib.patches import Ellipse

from warp_highlights.relight.evaluation import luminance

counts = field.counts
angle = np.degrees(np.arccos(np.clip(dataset.lights.directions[:, 2], -1, 1)))
fig, ax = plt.subplots(figsize=(6, 2.6))
ax.scatter(angle, counts, s=14)
ax.set(xlabel="angle between the light and the camera axis (deg)", ylabel="Gaussians",
       title=f"Gaussians per light: mean {counts.mean():.1f}, max {counts.max()}")
fig.tight_layout()
plt.show()

busiest = int(np.argmax(counts))
one = field.estimated.take([busiest])  # GaussianParams of one light: positions and sizes in image heights
raster = wh.Rasterizer(field.height, field.width, device=device)
fitted = raster.render(wh.GaussianBatch.from_numpy(one, device=device, requires_grad=False)).numpy()[0]
truth = luminance(dataset.specular[busiest : busiest + 1])[0]  # luminance() takes a stack
rows, cols = np.nonzero(truth > 0.02)
crop = np.s_[max(rows.min() - 6, 0) : rows.max() + 7, max(cols.min() - 6, 0) : cols.max() + 7]
top, left = crop[0].start, crop[1].start

fig, axes = plt.subplots(1, 3, figsize=(12, 3.4 * (crop[0].stop - top) / (crop[1].stop - left) + 0.5))
panels = ((truth, "ground-truth specular"), (fitted, "the fitted Gaussians, rasterized"),
          (0.4 * fitted, "their 2-sigma ellipses"))
for ax, (image, title) in zip(axes, panels):
    ax.imshow(display_rgb8(image[crop]), interpolation="nearest")
    ax.set_title(f"light {busiest}: {title}")
    ax.axis("off")
H = field.height
for p in np.flatnonzero(one.active[0]):
    (x, y), (sx, sy) = one.mean[0, p] * H - 0.5 - [left, top], np.abs(one.sigma[0, p]) * H  # pixel units of the crop
    axes[2].add_patch(Ellipse((x, y), 4 * sx, 4 * sy, angle=np.degrees(one.theta[0, p]), fill=False,
                              color="tab:orange", lw=1.0))
fig.tight_layout()
plt.show()
"""),
    md("""
## 4. Relight from a new direction

`wh.relight_field(field, directions)` takes any light directions (x right, y up, z towards the
camera). It finds each direction's triangle, moves every corner's Gaussians along their stored paths
by the barycentric weights, rasterizes them, and adds them, in the highlights' colour c(x), to the
field's residual blended for that direction: `I' = residual + c(x) S'`. It returns
NumPy images (`RelitImages`: `.full`, `.specular`, `.faces`, `.barycentric`).
"""),
    code("""
relit = wh.relight_field(field, query, device=device)
show([relit.full[0], relit.specular[0]], ["relit image I' = residual + c(x) S'", "its highlights S'"],
     suptitle=f"light {np.round(query[0] / np.linalg.norm(query), 2).tolist()} (not one of the {LIGHTS} lights)")
"""),
    md("""
The highlights move continuously with the light. Four directions on a circle at 35 degrees
elevation (the orbit `warp-highlights animate --path orbit:35` draws), one batch of queries:
"""),
    code("""
from warp_highlights.view.light_paths import orbit

directions = orbit(35.0, 4)
frames = wh.relight_field(field, directions, device=device)
show(list(frames.full), [f"azimuth {a:.0f} deg" for a in np.linspace(0, 360, 4, endpoint=False)], panel_width=3.2)
"""),
    md("""
## 5. Circular paths, straight paths and the alpha blend

Three ways to make the highlights of a direction inside a triangle:

- **circular** (the method): each Gaussian travels along its stored circular arc towards the two
  other corners and turns as it goes;
- **straight**: the same Gaussians, with their positions blended along straight lines;
- **alpha**: no Gaussians at all; the three corner lights' specular images are blended with the
  barycentric weights (the baseline), which leaves three faded copies of a moving highlight.

The alpha blend needs the per-light images, which the field does not store: `alpha_inputs` segments
the dataset once and a `Relighter` holds everything on the device. Here is a held-out light, one of
the triangle centroids rendered as ground truth, where the corners are as far away as they get.
"""),
    code("""
from warp_highlights.relight.evaluation import psnr_excluding_black
from warp_highlights.relight.relighter import alpha_inputs

alpha_specular, alpha_images = alpha_inputs(field, dataset, device=device)
relighter = wh.Relighter(field, device=device, alpha_specular=alpha_specular, alpha_images=alpha_images)

heldout = dataset.heldout
toward = np.array([0.3, 0.45, 0.85]) / np.linalg.norm([0.3, 0.45, 0.85])
q = int(np.argmax(heldout.lights.directions @ toward))  # the held-out centroid nearest to a front-top light
truth = luminance(heldout.specular[q : q + 1])[0]
methods = ("circular", "straight", "alpha")
# one (3,) direction: (H, W)
results = {m: relighter.relight(heldout.lights.directions[q], method=m, full=False).specular for m in methods}
psnr = {m: float(psnr_excluding_black(results[m][None], truth[None])[0]) for m in methods}
panels = [truth] + [results[m] for m in methods]
rows, cols = np.nonzero(np.max(panels, axis=0) > 0.02)  # crop to the highlights
crop = np.s_[max(rows.min() - 6, 0) : rows.max() + 7, max(cols.min() - 6, 0) : cols.max() + 7]
show([image[crop] for image in panels], ["ground truth"] + [f"{m}: {psnr[m]:.1f} dB" for m in methods], panel_width=3.0,
     suptitle=f"highlights S' at held-out light {q}, "
              f"direction {np.round(heldout.lights.directions[q], 2).tolist()} (cropped)")
"""),
    md("""
## 6. Evaluate at every held-out light

`evaluate_field` relights every held-out direction with each method and scores it against the
rendered ground truth: PSNR (peak 1, images clipped to [0, 1]) of the highlights S' against the
ground-truth specular luminance, and of the full image I' against the held-out image. It returns an
`Evaluation`; `to_dict()` is the JSON report that `warp-highlights evaluate` writes.
"""),
    code("""
from IPython.display import Image, Markdown, display

t = time.perf_counter()
evaluation = wh.evaluate_field(field, dataset, device=device, alpha_stacks=(alpha_specular, alpha_images))
print(f"evaluated {len(evaluation.directions)} held-out lights in {time.perf_counter() - t:.1f} s")

summary = evaluation.summary()
rows = ["| images | method | mean PSNR (dB) | 5th pct | 95th pct |", "|---|---|---|---|---|"]
for kind, label in (("specular", "highlights S'"), ("full", "full images I'")):
    for method in methods:
        s = summary[kind][method]
        rows.append(f"| {label} | {method} | {s['mean']:.2f} | {s['p5']:.2f} | {s['p95']:.2f} |")
shares = summary["specular"]
rows.append("")
rows.append(f"On the highlights, circular beats the alpha blend at {100 * shares['circular_beats_alpha']:.0f}% "
            f"of the held-out lights and straight paths at {100 * shares['circular_beats_straight']:.0f}%.")
display(Markdown("\\n".join(rows)))
"""),
    md("""
The `warp_highlights.view.plots` functions write the report's figures as PNG files; here the PSNR
distribution of the three methods over all held-out lights.
"""),
    code("""
from warp_highlights.view.plots import plot_psnr_distributions

png = plot_psnr_distributions(evaluation.specular_psnr, work / "psnr-specular.png",
                              title=f"Specular PSNR at {len(evaluation.directions)} held-out lights "
                                    f"(donut, {LIGHTS} lights)")
display(Image(filename=str(png), width=720))
"""),
    md("""
## 7. Look at the light sphere and the paths

`warp_highlights.view.viz` draws the same objects with pyvista. `plot_triangulation` shows the light
sphere: every light (orange), the triangulation's edges, the held-out light of section 5 (yellow) and
its triangle (blue); the grey arrow points at the camera. `plot_paths` shows that triangle's Gaussians
over the image plane, one colour per Gaussian: the circular arc each one follows towards the two other
corners (thick), the straight segment (thin), where it starts (dot) and where it is at this light
(outline, 1 sigma). The static backend puts a picture in the notebook; `pv.set_jupyter_backend("trame")`
(with `pip install 'pyvista[jupyter]'`) makes it interactive, and `warp-highlights view FIELD` opens
the light designer, where dragging the light re-renders the image.
"""),
    code("""
import pyvista as pv

from warp_highlights.view import viz

pv.set_jupyter_backend("static")
light = heldout.lights.directions[q]
plotter = viz.new_plotter(shape=(1, 2), window_size=(1100, 460))  # a pyvista.Plotter (off screen without a display)
viz.plot_triangulation(field, plotter=plotter, direction=light)
plotter.subplot(0, 1)
viz.plot_paths(field, light, plotter=plotter, background=results["circular"])
plotter.show()
"""),
    md("""
The geometry is plain NumPy too: `gaussian_paths` gives every path of a triangle as points in image
heights, so you can measure the paths yourself. How far the Gaussians of this triangle travel, and
how much the arcs bend away from the straight segments:
"""),
    code("""
face = int(field.triangulation.locate(light).faces)
paths = viz.gaussian_paths(field, face)
arc = np.linalg.norm(np.diff(paths.circular, axis=1), axis=2).sum(axis=1) * field.height  # pixels
chord = np.linalg.norm(paths.end - paths.start, axis=1) * field.height
bend = np.abs(np.degrees(paths.delta))
rows = ["| path | from light | to light | chord (px) | arc (px) | turn (deg) |", "|---|---|---|---|---|---|"]
for p in np.argsort(-chord)[:6]:
    rows.append(f"| Gaussian {paths.gaussian[p]} | {paths.vertices[paths.corner[p]]} | "
                f"{paths.vertices[paths.target[p]]} | {chord[p]:.1f} | {arc[p]:.1f} | {bend[p]:.1f} |")
display(Markdown(f"{paths.path_count} paths in triangle {face}; the six longest:\\n\\n" + "\\n".join(rows)))
"""),
]


# --- custom_loss_kernel.ipynb -----------------------------------------------------------------------

CUSTOM_LOSS = [
    md("""
# A custom loss as a Warp kernel

For people who write kernels for warp-highlights. This notebook

1. writes a loss as a plain `@wp.kernel` with no hand-written adjoint;
2. renders a `GaussianBatch` with the project's `Rasterizer` and records the rasterizer and the loss
   on one `wp.Tape`. Warp differentiates the loss kernel by itself; the rasterizer brings its own
   hand-written adjoint (recorded with `Tape.record_func`, see `kernels/raster.py`), and
   `tape.backward` chains the two into the parameter gradients in `batch.amplitude.grad`,
   `batch.mean.grad`, ...;
3. checks those gradients against central finite differences in float64;
4. fits Gaussians with `GaussianAdam` using the new loss, and compares with the built-in `LogL1Loss`.

Everything is small and runs in seconds on a CPU (`wp.get_preferred_device()`: CUDA when present).
Nothing is written to disk.
"""),
    code("""
%matplotlib inline
import time

import matplotlib.pyplot as plt
import numpy as np
import warp as wp
from IPython.display import Markdown, display

import warp_highlights as wh
from warp_highlights.model.config import pixel_area_rpx2, rpx_to_normalized

plt.rcParams.update({"figure.dpi": 72, "font.size": 9, "axes.titlesize": 9})  # small inline PNGs
wp.config.log_level = wp.LOG_WARNING  # no greeting and no per-module compile lines; warnings stay
wp.init()
device = wp.get_preferred_device()
print(f"warp {wp.__version__}, warp-highlights {wh.__version__}, device: {device}")
"""),
    md("""
## The loss: L2 with more weight on the highlight core

A highlight is a small bright core on a wide, dim tail. A plain L2 loss over the image counts every
tail pixel as much as a core pixel, and there are many more of them. This loss gives the pixels
where the *target* is bright a larger weight:

$$L_b = A \\sum_{x} w_b(x)\\,\\big(R_b(x) - S_b(x)\\big)^2, \\qquad
w_b(x) = 1 + \\frac{k}{1 + e^{-(S_b(x) - t)/s}}$$

with R the rendered Gaussians of problem b, S its target, t = 0.5 the level where a pixel counts as
core, k = 9 (core pixels weigh up to 10 times as much) and s = 0.1 the softness of the step. A is
the pixel area in reference pixels squared (`pixel_area_rpx2`), as in `LogL1Loss`, so the loss
measures the same at every resolution.

The kernel has one thread per pixel, and each thread adds its term into the problem's entry of
`loss` with `wp.atomic_add`. That is all: Warp generates the adjoint, which adds
`2 A w (R - S) * loss.grad[b]` to `image.grad`. The weights depend only on the target, so they are
computed once, with NumPy.
"""),
    code("""
@wp.kernel
def core_weighted_l2(
    image: wp.array3d(dtype=float),   # (B, H, W) rendered Gaussians R
    target: wp.array3d(dtype=float),  # (B, H, W) target S
    weight: wp.array3d(dtype=float),  # (B, H, W) w(S)
    area: float,                      # pixel area in rpx^2
    loss: wp.array(dtype=float),      # (B,) one loss per problem, accumulated
):
    b, row, col = wp.tid()
    difference = image[b, row, col] - target[b, row, col]
    wp.atomic_add(loss, b, area * weight[b, row, col] * difference * difference)


class CoreWeightedL2:
    \"\"\"Per-problem loss against fixed targets (B, H, W), called like ``wh.LogL1Loss``.\"\"\"

    def __init__(self, target, *, core=0.5, boost=9.0, softness=0.1, device=None):
        target = np.asarray(target, dtype=np.float32)
        weight = 1.0 + boost / (1.0 + np.exp(-(target.astype(np.float64) - core) / softness))
        self.device = wp.get_device(device)
        self.target = wp.array(target, dtype=float, device=self.device)
        self.weight = wp.array(weight.astype(np.float32), dtype=float, device=self.device)
        self.area = pixel_area_rpx2(target.shape[1])

    def __call__(self, image: wp.array) -> wp.array:
        # requires_grad: the loss' gradient (ones, from tape.backward) flows from here into image.grad
        loss = wp.zeros(image.shape[0], dtype=float, device=self.device, requires_grad=True)
        wp.launch(core_weighted_l2, dim=image.shape, inputs=[image, self.target, self.weight, self.area],
                  outputs=[loss], device=self.device)
        return loss
"""),
    md("""
## Gradients through the rasterizer

A small problem: one set of two Gaussians on a 48 x 36 image. The target is the rendering of the
true set; the batch holds a perturbed copy. Positions and sizes are in image heights (the image
spans y in (0, 1)), rotations in radians, and each Gaussian peaks at `weight * amplitude^2`.

Inside `with wp.Tape()`, `Rasterizer.render` records its adjoint and `wp.launch` records the loss
kernel. `tape.backward(grads={loss: ones})` then runs them in reverse order.
"""),
    code("""
HEIGHT, WIDTH = 36, 48
truth = wh.GaussianParams.from_sets([{"amplitude": [1.2, 0.7], "mean": [[0.55, 0.45], [0.85, 0.60]],
                                      "sigma": [[0.06, 0.025], [0.05, 0.05]], "theta": [0.5, 0.0]}])
start = truth.copy()
start.amplitude *= [0.9, 1.1]
start.mean += [[0.02, -0.015], [-0.01, 0.02]]
start.sigma *= [[1.2, 0.8], [0.9, 1.1]]
start.theta += [0.2, 0.3]
start.weight[:] = [1.1, 0.9]

raster = wh.Rasterizer(HEIGHT, WIDTH, device=device)
target = raster.render(wh.GaussianBatch.from_numpy(truth, device=device, requires_grad=False)).numpy()
loss_fn = CoreWeightedL2(target, device=device)
batch = wh.GaussianBatch.from_numpy(start, device=device)  # requires_grad=True by default

with wp.Tape() as tape:
    image = raster.render(batch)
    loss = loss_fn(image)
tape.backward(grads={loss: wp.ones_like(loss)})
analytic = batch.gradients()  # float64 copies of batch.<parameter>.grad

print(f"loss {loss.numpy()[0]:.3f}")
print("on the tape, in recording order:")
for entry in tape.launches:
    if isinstance(entry, list):
        kind = f"kernel {entry[0].key} (adjoint generated by Warp)"
    else:
        kind = f"{entry.__qualname__} (hand-written adjoint, record_func)"
    print("  ", kind)
print("d loss / d mean of Gaussian 0 (batch.mean.grad[0, 0]):", batch.mean.grad.numpy()[0, 0])

fig, axes = plt.subplots(1, 3, figsize=(9, 2.4))
pictures = (target[0], image.numpy()[0], loss_fn.weight.numpy()[0])
for ax, picture, title in zip(axes, pictures, ("target S", "start R", "weight w(S)")):
    ax.imshow(picture, cmap="magma")
    ax.set_title(title)
    ax.axis("off")
plt.show()
"""),
    md("""
## Check against central finite differences in float64

The Warp rasterizer works in float32, too coarse for finite differences. So the check re-renders in
float64 with NumPy: the same truncated Gaussian as `kernels/raster.py` (cut at Mahalanobis distance
4, the cut-off level subtracted so it falls to zero continuously), then the same loss. First the two
renderers must agree; then every parameter of every Gaussian is moved by +-1e-6.
"""),
    code("""
settings = raster.settings  # cut-off and covariance epsilon, as the rasterizer uses them


def render64(params, height, width):
    \"\"\"(B, H, W) float64 image of the active Gaussians, truncated like the Warp rasterizer.\"\"\"
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = (cols + 0.5) / height, (rows + 0.5) / height  # pixel centres in image heights
    tau = settings.cutoff_level
    out = np.zeros((params.problem_count, height, width))
    for b in range(params.problem_count):
        for p in np.flatnonzero(params.active[b]):
            c, s = np.cos(params.theta[b, p]), np.sin(params.theta[b, p])
            dx, dy = x - params.mean[b, p, 0], y - params.mean[b, p, 1]
            u, v = c * dx + s * dy, c * dy - s * dx  # offset in the Gaussian's principal frame
            d2 = (u**2 / (params.sigma[b, p, 0] ** 2 + settings.sigma_eps)
                  + v**2 / (params.sigma[b, p, 1] ** 2 + settings.sigma_eps))
            peak = params.weight[b, p] * params.amplitude[b, p] ** 2
            out[b] += np.where(d2 < settings.cutoff**2, peak * (np.exp(-0.5 * d2) - tau) / (1.0 - tau), 0.0)
    return out


current = batch.numpy()  # float64 copy of the (float32) parameters the tape saw
weight64, target64 = loss_fn.weight.numpy().astype(np.float64), target.astype(np.float64)


def loss64(params):
    return float((loss_fn.area * weight64 * (render64(params, HEIGHT, WIDTH) - target64) ** 2).sum())


difference = np.abs(render64(current, HEIGHT, WIDTH) - image.numpy()).max()
print(f"largest |float64 render - Warp render|: {difference:.2e} (peak {image.numpy().max():.2f})")
print(f"loss: float64 {loss64(current):.4f}, Warp {loss.numpy()[0]:.4f}")
"""),
    code("""
STEP = 1e-6
rows = ["| parameter | tape (float32) | finite differences (float64) | relative error |", "|---|---:|---:|---:|"]
errors = []
for name in ("amplitude", "mean", "sigma", "theta", "weight"):
    values = getattr(current, name)
    for index in np.ndindex(values.shape):
        plus, minus = current.copy(), current.copy()
        getattr(plus, name)[index] += STEP
        getattr(minus, name)[index] -= STEP
        numeric = (loss64(plus) - loss64(minus)) / (2 * STEP)
        error = abs(analytic[name][index] - numeric) / abs(numeric)
        errors.append(error)
        label = f"{name}[{index[1]}]" + (f".{'xy'[index[2]]}" if len(index) == 3 else "")
        rows.append(f"| `{label}` | {analytic[name][index]:.6g} | {numeric:.6g} | {error:.1e} |")
display(Markdown("\\n".join(rows)))
print(f"largest relative error: {max(errors):.1e}")
assert max(errors) < 1e-3, "the tape's gradient disagrees with finite differences"
"""),
    md("""
The gradients agree to float32 precision: Warp's automatic adjoint of `core_weighted_l2` and the
rasterizer's hand-written adjoint compose through the tape without any glue code.

## Fit with GaussianAdam

Now the loss drives a fit: three problems in one batch (one launch per kernel for all three), each
a highlight-like set (an arc of three needles, a sharp core beside a broad glow, one long streak) at
160 x 90 pixels. The start is the true set with every Gaussian moved by a random offset of about 8
reference pixels per coordinate, its sizes scaled by 0.7 to 1.4 and turned by about 0.3 rad.
`GaussianAdam` takes one step per iteration from the gradients in the batch (its learning rates are per
parameter group, lengths in reference pixels: `wh.AdamSettings`). `tape.zero()` clears the gradients for the next step.
"""),
    code("""
HEIGHT, WIDTH, STEPS = 90, 160, 400
truth = wh.GaussianParams.from_sets([
    {"amplitude": [1.3, 1.1, 0.9], "mean": [[0.55, 0.40], [0.80, 0.32], [1.05, 0.40]],  # an arc of three needles
     "sigma": [[0.05, 0.015], [0.06, 0.015], [0.05, 0.015]], "theta": [-0.4, 0.0, 0.4]},
    {"amplitude": [1.5, 0.6], "mean": [[0.70, 0.50], [1.10, 0.55]],  # a sharp core beside a broad glow
     "sigma": [[0.02, 0.02], [0.08, 0.04]], "theta": [0.0, 0.3]},
    {"amplitude": [1.2], "mean": [[0.90, 0.45]], "sigma": [[0.18, 0.02]], "theta": [0.7]},  # one long streak
], capacity=3)
raster = wh.Rasterizer(HEIGHT, WIDTH, device=device)
targets = raster.render(wh.GaussianBatch.from_numpy(truth, device=device, requires_grad=False)).numpy()

rng = np.random.default_rng(7)
start = truth.copy()
on = start.active
start.mean += np.where(on[..., None], rng.normal(0.0, rpx_to_normalized(8.0), start.mean.shape), 0.0)
start.sigma *= np.where(on[..., None], rng.uniform(0.7, 1.4, start.sigma.shape), 1.0)
start.theta += np.where(on, rng.normal(0.0, 0.3, start.theta.shape), 0.0)
start.amplitude *= np.where(on, rng.uniform(0.8, 1.2, start.amplitude.shape), 1.0)


def position_error_rpx(params):
    \"\"\"(B,) mean distance, in reference pixels, of each problem's Gaussians from the true ones.\"\"\"
    distance = np.linalg.norm(params.mean - truth.mean, axis=-1) / rpx_to_normalized(1.0)
    return np.array([distance[b, truth.active[b]].mean() for b in range(truth.problem_count)])


def fit(loss_fn, steps=STEPS):
    batch = wh.GaussianBatch.from_numpy(start, device=device)
    adam = wh.GaussianAdam(batch)
    losses, errors = [], [position_error_rpx(start)]
    started = time.perf_counter()
    for _ in range(steps):
        with wp.Tape() as tape:
            loss = loss_fn(raster.render(batch))
        tape.backward(grads={loss: wp.ones_like(loss)})
        adam.step()
        tape.zero()
        losses.append(loss.numpy())
        errors.append(position_error_rpx(batch.numpy()))
    seconds = time.perf_counter() - started
    return {"batch": batch, "loss": np.array(losses), "error": np.array(errors), "ms_per_step": 1e3 * seconds / steps}


core = fit(CoreWeightedL2(targets, device=device))
print(f"{STEPS} steps, {core['ms_per_step']:.1f} ms per step "
      "(forward, backward, Adam and the host copies for the curves)")
print("position error (rpx) per problem, start -> end:", np.round(core["error"][0], 2), "->",
      np.round(core["error"][-1], 3))
"""),
    code("""
fig, axes = plt.subplots(1, 2, figsize=(10, 3))
names = ("arc", "core + glow", "streak")
for b, name in enumerate(names):
    axes[0].semilogy(core["loss"][:, b], label=name)
    axes[1].semilogy(core["error"][:, b], label=name)
axes[0].set(xlabel="Adam step", ylabel="core-weighted L2", title="loss per problem")
axes[1].set(xlabel="Adam step", ylabel="rpx", title="mean distance from the true positions")
axes[0].legend()
fig.tight_layout()
plt.show()

before = raster.render(wh.GaussianBatch.from_numpy(start, device=device, requires_grad=False)).numpy()
after = raster.render(core["batch"]).numpy()
fig, axes = plt.subplots(3, 3, figsize=(9.5, 5.2))
for b in range(3):
    pictures = ((targets[b], "target"), (before[b], "start"), (after[b], f"after {STEPS} steps"))
    for c, (picture, title) in enumerate(pictures):
        axes[b, c].imshow(picture, cmap="magma", vmin=0.0, vmax=targets.max())
        axes[b, c].set_title(f"{names[b]}: {title}")
        axes[b, c].axis("off")
fig.tight_layout()
plt.show()
"""),
    md("""
## The same fit with the built-in LogL1Loss

`wh.LogL1Loss` (the estimation's loss, log2-L1) is used the same way: a callable that returns one
loss per problem and records its backward on the tape. Its adjoint is hand-written (one thread per
row on the CPU, no per-pixel atomics); the custom loss relies on the one Warp generates. Loss values
of the two are not comparable, so the plot compares the distance from the true positions.
"""),
    code("""
log_l1 = fit(wh.LogL1Loss(targets, device=device))
print(f"LogL1Loss: {log_l1['ms_per_step']:.1f} ms per step; core-weighted L2: {core['ms_per_step']:.1f} ms per step")
print("position error after", STEPS, "steps (rpx): LogL1", np.round(log_l1["error"][-1], 3),
      " core-weighted L2", np.round(core["error"][-1], 3))

fig, ax = plt.subplots(figsize=(6, 3))
for b, name in enumerate(names):
    line, = ax.semilogy(core["error"][:, b], label=f"{name}, core-weighted L2")
    ax.semilogy(log_l1["error"][:, b], "--", color=line.get_color(), label=f"{name}, LogL1Loss")
ax.set(xlabel="Adam step", ylabel="rpx", title="mean distance from the true positions")
ax.legend(fontsize=7, ncol=2)
fig.tight_layout()
plt.show()
"""),
    md("""
Both losses bring the perturbed sets back to within a small fraction of a reference pixel, and
they end differently. The squared error is smooth at the optimum, so Adam's steps shrink with its
gradient and the arc and the core + glow converge to float32 precision; the L1 loss pulls equally
hard however close the fit is, so Adam keeps stepping around the optimum by a few hundredths of a
reference pixel. The long streak is the slow case for the squared error: sliding it along its own
axis changes the image little, and that weak pull fades further as the error shrinks. To make a custom
loss a built-in one, follow `kernels/losses.py`: keep the kernel off the tape (`record_tape=False`),
reduce per row rather than with one atomic per pixel, and register a hand-written backward with
`Tape.record_func`, checked against finite differences as above (the tests do that for every kernel with
`tests/reference.py`).
"""),
]


NOTEBOOKS = {"quickstart": QUICKSTART, "custom_loss_kernel": CUSTOM_LOSS}


# --- building and running ---------------------------------------------------------------------------


def build(name: str):
    """The notebook ``name`` with its cells and no outputs (an ``nbformat`` v4 node)."""
    import nbformat

    nb = nbformat.v4.new_notebook()
    cells = []
    for index, (kind, source) in enumerate(NOTEBOOKS[name]):
        cell = nbformat.v4.new_markdown_cell(source) if kind == "markdown" else nbformat.v4.new_code_cell(source)
        cell.id = f"{name.replace('_', '-')}-{index:02d}"  # stable ids keep diffs small
        cells.append(cell)
    nb.cells = cells
    nb.metadata = {"kernelspec": dict(KERNELSPEC), "language_info": {"name": "python"}}
    return nb


def execute(nb, *, workdir: Path, timeout: int = 600):
    """Run ``nb`` top to bottom in a fresh kernel started in ``workdir``; returns it with outputs.

    The kernel inherits this process' environment; ``$WARP_HIGHLIGHTS_NOTEBOOK_OUT`` is set to
    ``workdir`` so the notebook writes its files there.
    """
    from nbclient import NotebookClient

    env = dict(os.environ)
    env[OUT_VARIABLE] = str(workdir)
    env["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    client = NotebookClient(nb, timeout=timeout, kernel_name="python3", record_timing=False,
                            resources={"metadata": {"path": str(workdir)}})
    client.execute(env=env)
    return nb


def strip_volatile(nb):
    """Drop what changes from machine to machine or run to run (kernel versions, timings, Warp's note
    that there is no CUDA driver) and join consecutive stream outputs; keep the outputs."""
    nb.metadata = {"kernelspec": dict(KERNELSPEC), "language_info": {"name": "python"}}
    for cell in nb.cells:
        cell.metadata = {}
        outputs = []
        for output in cell.get("outputs", []):
            if output.get("output_type") == "stream" and output.get("name") == "stderr":
                # machine-specific: Warp's note that this machine has no CUDA driver
                # and tqdm's note that ipywidgets is not installed (pulled in by pyvista's notebook support)
                lines = output.text.splitlines(keepends=True)
                output.text = "".join(
                    line for k, line in enumerate(lines)
                    if not line.startswith("Warp CUDA warning") and "TqdmWarning: IProgress not found" not in line
                    and not (k > 0 and "TqdmWarning: IProgress not found" in lines[k - 1] and "notebook_tqdm" in line)
                )
                if not output.text:
                    continue
            output.get("metadata", {}).pop("execution", None)
            data = output.get("data", {})
            if "image/png" in data:
                data.pop("image/jpeg", None)  # pyvista's static backend sends both; keep the lossless one
            last = outputs[-1] if outputs else None
            if (last is not None and output.get("output_type") == "stream" and last.get("output_type") == "stream"
                and last.name == output.name):
                last.text += output.text  # one block per stream, as Jupyter shows it
            else:
                outputs.append(output)
        if cell.cell_type == "code":
            cell.outputs = outputs
    return nb


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"notebooks to build: {', '.join(NOTEBOOKS)} (default: all)")
    parser.add_argument("--execute", action="store_true", help="run each notebook and store its outputs")
    parser.add_argument("--timeout", type=int, default=600, help="seconds per cell when executing")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(NOTEBOOKS))
    if unknown:
        parser.error(f"no notebook named {', '.join(unknown)}; choose from {', '.join(NOTEBOOKS)}")
    import nbformat

    for name in args.names or list(NOTEBOOKS):
        nb = build(name)
        if args.execute:
            started = time.perf_counter()
            with tempfile.TemporaryDirectory(prefix=f"wh-{name}-") as workdir:
                execute(nb, workdir=Path(workdir), timeout=args.timeout)
            strip_volatile(nb)
            print(f"{name}: executed in {time.perf_counter() - started:.1f} s", file=sys.stderr)
        nbformat.validate(nb)
        target = HERE / f"{name}.ipynb"
        nbformat.write(nb, target)
        print(f"{name}: wrote {target.name} ({target.stat().st_size / 1e3:.0f} kB)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
