"""What a person sees when the light moves: every relighting method along dense light paths, against
ground truth rendered at every frame, on scenes made to hold what real captures hold.

    python benchmarks/bench_motion.py                                  # CPU size: 160x90, 16 and 49 dome lights
    python benchmarks/bench_motion.py --scale gpu --device cuda:0      # 480x270; 16, 25, 49 dome and 100 sphere lights
    python benchmarks/bench_motion.py --scenes coin,bumpy-metal --captures dome16
    python benchmarks/bench_motion.py --photos      # also the samples: photos with every k-th light held out (k = 2,
                                                    # 3, 5) and the dome sample on 16, 25, 49 spread lights
    python benchmarks/bench_motion.py --set retarget.search_radius=0   # any fit setting, as `fit --set` takes it
    python benchmarks/bench_motion.py --scenes "" --photos dome-sample  # the dome sample on 16, 25, 49 lights alone

Scenes (``synth`` renders; shape, lobe):
- ``donut-sharp``: the smooth donut, Blinn-Phong shininess 800: small bright highlights, no relief.
- ``bumpy-metal``: a donut with small bumps all over, GGX roughness 0.08 (polished metal): glints.
- ``coin``: a relief plate seen from above, worn bronze (GGX 0.15): slopes, ridges and beads.
- ``teapot-tiles``: the teapot in tiles of a glossy red glaze (GGX 0.1) and a pale, nearly matte one:
  texture and two materials, cast shadows.
- ``sphere-broad``: a sphere with a broad Blinn-Phong lobe (shininess 20): where moving should not
  matter, so no method may lose there.

Captures: Fibonacci domes of 16, 25 and 49 lights (10 degrees and up, as RTI domes are) and a
sphere of 100. Paths, each ``--frames`` long (96): an orbit at 35 degrees of elevation, and two great
circles over the top (from 15 degrees at azimuth 0 to 15 degrees at 180, and 90 to 270). Also the
capture's triangle centroids (the lights furthest from every captured one), as still images.

Methods: ``field`` (the default fit on this device: the low-rank residual on a CPU, the learned one
on CUDA), ``lowrank`` (on CUDA, where it is not the default), ``learned-alone`` (the learned residual
with no Gaussians at all: ``estimation.residual_threshold`` above any highlight; with ``--learned``,
the default on CUDA), ``alpha`` (the alpha blend of the captured images, same triangulation), and the
RTI baselines ``rbf`` and ``hsh3`` fitted to the same lights (``hsh2`` where a capture has < 16).

Per frame: 8-bit sRGB PSNR and SSIM of the whole image; the motion scores of
``warp_highlights.quality.motion`` per path: ghost share (light where the truth has no highlight,
over the truth's highlight energy), position error of the highlights (rpx), flicker (8-bit levels).
Prints one Markdown table (and one of the samples with ``--photos``); writes bench_motion.json and,
for the path where the field loses most to the alpha blend and the one where it gains most, a strip
of 6 frames (rows: truth, field, learned alone where fitted, blend) and a side-by-side GIF of every
frame (``worst.png``/``.gif``, ``best.png``/``.gif``, what they show in ``.txt``) to $OUT (default
benchmarks/results/motion-<scale>).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.fit.pipeline import fit_field
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.images import display_rgb8
from warp_highlights.model.config import FitSettings
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation
from warp_highlights.quality.metrics import srgb_scores
from warp_highlights.quality.motion import motion_scores
from warp_highlights.relight.baselines import fit_baseline
from warp_highlights.relight.relighter import Relighter, alpha_inputs
from warp_highlights.synth.render import Renderer, RenderSettings, default_material, view_rotation
from warp_highlights.synth.settings import Material
from warp_highlights.synth.shapes import make_shape
from warp_highlights.view.light_paths import great_circle, orbit

SCENES = {
    "donut-sharp": ("donut", Material(specular=0.6, shininess=800.0)),
    "bumpy-metal": ("bumpy", Material(albedo=(0.35, 0.26, 0.16), specular=0.7, roughness=0.08)),
    "coin": ("coin", default_material("coin")),
    "teapot-tiles": ("teapot", Material(albedo=(0.55, 0.12, 0.08), specular=0.5, roughness=0.1, texture="tiles",
                                        tile_size=0.25)),
    "sphere-broad": ("sphere", Material(albedo=(0.6, 0.6, 0.6), specular=0.5, shininess=20.0)),
}
CAPTURES = {
    "dome16": lambda: LightSet.fibonacci_dome(16),
    "dome25": lambda: LightSet.fibonacci_dome(25),
    "dome49": lambda: LightSet.fibonacci_dome(49),
    "sphere100": lambda: LightSet.fibonacci_sphere(100),
}
SCALES = {  # size, captures, samples per pixel
    "cpu": ((160, 90), ("dome16", "dome49"), 4),
    "gpu": ((480, 270), ("dome16", "dome25", "dome49", "sphere100"), 4),
}
LEARNED_ALONE = ["residual.kind=learned", "estimation.residual_threshold=1e9"]
PHOTOS = {"statue": ("realrti-item11", (192, 181)), "coin-photo": ("realrti-item10", (166, 168))}
SAMPLES = (*PHOTOS, "dome-sample")


def _checks(field) -> dict:
    """The fit's move check, learned check and median motion coherence (``fit.coherence``), as its report has them
    (empty where it has none)."""
    residual = (field.report or {}).get("residual") or {}
    return {name: residual[name] for name in ("move_check", "learned_check", "motion_coherence")
            if residual.get(name) is not None}


def _direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def light_paths(frames: int) -> dict[str, np.ndarray]:
    """The three paths of every scene: an orbit and two great circles over the top."""
    return {
        "orbit35": orbit(35.0, frames),
        "great0-180": great_circle(_direction(15, 0), _direction(15, 180), frames),
        "great90-270": great_circle(_direction(15, 90), _direction(15, 270), frames),
    }


def fit(dataset: ReflectanceField, device, overrides: list[str]) -> tuple[object, float]:
    settings = FitSettings().with_overrides(overrides)
    started = time.perf_counter()
    field = fit_field(dataset, settings=settings, device=device, exposure=1.0)
    return field, time.perf_counter() - started


def relight_with(field, directions: np.ndarray, device, *, alpha=None) -> np.ndarray:
    relighter = Relighter(field, device=device, scale=1.0 / field.exposure,
                          alpha_specular=None if alpha is None else alpha[0],
                          alpha_images=None if alpha is None else alpha[1])
    return relighter.relight(directions, method="circular" if alpha is None else "alpha").full


def score(frames: np.ndarray, truth, *, moving: bool) -> dict:
    """Frame scores and (along a path) the motion scores of one method."""
    psnr, ssim = srgb_scores(np.clip(frames, 0.0, None), truth.full)
    out = {"psnr": psnr, "ssim": ssim}
    motion = motion_scores(frames, truth.full, truth.specular, truth.diffuse)
    out["ghost"], out["position_rpx"] = motion.ghost_share, motion.position_error_rpx
    out["visible_ghost"] = motion.visible_ghost_share
    if moving:
        out["flicker"] = motion.flicker
    return out


def run_scene(scene: str, capture: str, scale: str, device, frames: int, learned: bool, pictures: Path | None,
              overrides: list[str], size: tuple[int, int] | None = None) -> dict:
    shape, material = SCENES[scene]
    (width, height), _, samples = SCALES[scale]
    width, height = size or (width, height)
    renderer = Renderer(make_shape(shape), material=material,
                        settings=RenderSettings(width=width, height=height, samples_per_pixel=samples),
                        rotation=view_rotation(shape), device=device)
    lights = CAPTURES[capture]()
    captured = renderer.render(lights.directions)
    dataset = ReflectanceField(images=captured.full, lights=lights, specular=captured.specular,
                               diffuse=captured.diffuse, mask=renderer.mask)
    fields, seconds = {}, {}
    cuda = wp.get_device(device).is_cuda
    fields["field"], seconds["field"] = fit(dataset, device, overrides)
    if cuda:
        fields["lowrank"], seconds["lowrank"] = fit(dataset, device, overrides + ["residual.kind=lowrank"])
    if learned or cuda:
        fields["learned-alone"], seconds["learned-alone"] = fit(dataset, device, overrides + LEARNED_ALONE)
    alpha = alpha_inputs(fields["field"], dataset, device=device)
    baselines = {name: fit_baseline(name, captured.full, lights.directions, device=device)
                 for name in ("rbf", "hsh3" if len(lights) >= 16 else "hsh2")}

    def methods(directions: np.ndarray) -> dict[str, np.ndarray]:
        out = {name: relight_with(f, directions, device) for name, f in fields.items()}
        out["alpha"] = relight_with(fields["field"], directions, device, alpha=alpha)
        out.update({name: model.relight(directions) for name, model in baselines.items()})
        return out

    paths = light_paths(frames)
    paths["centroids"] = SphericalTriangulation(lights.directions).centroid_directions()
    result = {"scene": scene, "capture": capture, "lights": len(lights), "size": [width, height],
              "fit_seconds": {k: round(v, 2) for k, v in seconds.items()},
              "moving": {k: int(f.moving_mask.sum()) for k, f in fields.items()},
              "gaussians": {k: int(f.counts.sum()) for k, f in fields.items()},
              "checks": {k: _checks(f) for k, f in fields.items()},
              "paths": {}}
    worst = best = None
    for path, directions in paths.items():
        truth = renderer.render(directions)
        relit = methods(directions)
        scores = {name: score(frames_, truth, moving=path != "centroids") for name, frames_ in relit.items()}
        result["paths"][path] = {name: _means(s) for name, s in scores.items()}
        if path != "centroids":
            gap = float(np.mean(scores["field"]["psnr"]) - np.mean(scores["alpha"]["psnr"]))
            if worst is None or gap < worst[0]:
                worst = (gap, path)
                _pictures(pictures / f"{scene}-{capture}-worst", path, truth, relit)
            if best is None or gap > best[0]:
                best = (gap, path)
                _pictures(pictures / f"{scene}-{capture}-best", path, truth, relit)
    result["worst_path"], result["worst_gap_db"] = worst[1], round(worst[0], 3)
    result["best_path"], result["best_gap_db"] = best[1], round(best[0], 3)
    return result


def _means(scores: dict) -> dict:
    return {k: (round(float(np.nanmean(v)), 4) if np.isfinite(v).any() else None) for k, v in scores.items()}


def _pictures(stem: Path, path: str, truth, relit: dict) -> None:
    """A strip of 6 frames (rows: truth, field, learned alone where fitted, alpha) and a GIF of them side by
    side, as ``stem.png`` and ``stem.gif`` (replacing earlier ones)."""
    from PIL import Image

    rows = [("truth", truth.full)] + [(name, relit[name]) for name in ("field", "learned-alone", "alpha")
                                      if name in relit]
    picks = np.linspace(0, len(truth.full) - 1, 6).round().astype(int)
    strip = np.concatenate([np.concatenate([display_rgb8(np.clip(images[i], 0, None)) for i in picks], axis=1)
                            for _, images in rows], axis=0)
    stem.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(strip).save(f"{stem}.png")
    frames = [Image.fromarray(np.concatenate([display_rgb8(np.clip(images[i], 0, None)) for _, images in rows],
                                             axis=1)) for i in range(len(truth.full))]
    frames[0].save(f"{stem}.gif", save_all=True, append_images=frames[1:], duration=60, loop=0)
    Path(f"{stem}.txt").write_text(f"path {path}; strip rows (6 frames along it) and GIF panels: "
                                   + ", ".join(name for name, _ in rows) + "\n")


def _photo_row(name: str, dataset: ReflectanceField, size, device, learned: bool, overrides: list[str],
               **labels) -> list[dict]:
    """The default field (and the learned residual alone) fitted and scored at the held-out lights."""
    from warp_highlights.relight.evaluation import evaluate_field

    rows = []
    fits = [overrides] + ([overrides + LEARNED_ALONE] if learned or wp.get_device(device).is_cuda else [])
    for kind, extra in zip(("field", "learned-alone"), fits):
        settings = FitSettings().with_overrides(extra)
        started = time.perf_counter()
        field = fit_field(dataset, settings=settings, device=device, size=size, exposure="auto")
        seconds = time.perf_counter() - started
        ev = evaluate_field(field, dataset, device=device, methods=("circular", "alpha"), barycentric_face=None,
                            baselines=("rbf", "hsh3" if dataset.light_count >= 16 else "hsh2") if kind == "field"
                            else (), progress=lambda _: None)
        rows.append({"photo": name, **labels, "lights": dataset.light_count, "fit": kind,
                     "fit_seconds": round(seconds, 2), "moving": int(field.moving_mask.sum()),
                     "checks": _checks(field),
                     "psnr": {m: round(float(np.mean(v)), 2) for m, v in ev.full_srgb_psnr.items()},
                     "ssim": {m: round(float(np.mean(v)), 4) for m, v in ev.full_ssim.items()}})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


def run_photos(scale: str, device, learned: bool, overrides: list[str], samples) -> list[dict]:
    """The sparse regime on the samples: the photographs with every k-th light held out, and the rendered
    dome sample fitted on 16, 25 and all 49 of its lights (spread by farthest-point sampling), scored
    at its 20 Test lights; still images at the held-out lights."""
    from warp_highlights.fit.validation import spread_lights

    data = Path(os.environ.get("WARP_HIGHLIGHTS_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
    rows = []
    for name, (folder, size) in PHOTOS.items():
        if name not in samples:
            continue
        whole = ReflectanceField.load(data / folder, progress=False)
        for k in (2, 3, 5):
            rows += _photo_row(name, whole.split_every(k), size if scale == "cpu" else None, device, learned,
                               overrides, every=k)
    folder = data / "synthrti-object1-material5"
    dome = (ReflectanceField.load(folder / "Dome", heldout=folder / "Test", progress=False)
            if "dome-sample" in samples else None)
    for count in (16, 25, 49) if dome is not None else ():
        chosen = spread_lights(dome.lights.directions, count)
        # the capture's own record kept (8-bit sRGB JPEGs: the baselines are fitted to the sRGB values)
        names = [dome.lights.filenames[i] for i in chosen]
        subset = dataclasses.replace(dome, images=dome.images[chosen],
                                     lights=LightSet(dome.lights.directions[chosen], names))
        rows += _photo_row("dome-sample", subset, (160, 160) if scale == "cpu" else None, device, learned, overrides,
                           spread=count)
    return rows


def table(results: list[dict]) -> str:
    """One Markdown row per (scene, capture, method): along the paths and at the centroids."""
    lines = ["| scene | lights | method | moving | path PSNR | path SSIM | ghost | visible ghost | position (rpx) | "
             "flicker | centroid PSNR |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        along = [p for p in r["paths"] if p != "centroids"]
        for method in r["paths"]["centroids"]:
            def mean(key, method=method):
                values = [r["paths"][p][method].get(key) for p in along]
                values = [v for v in values if v is not None]
                return float(np.mean(values)) if values else float("nan")

            moving = r["moving"].get(method, "")
            lines.append(f"| {r['scene']} | {r['capture']} | {method} | {moving} | {mean('psnr'):.2f} | "
                         f"{mean('ssim'):.4f} | {mean('ghost'):.3f} | {mean('visible_ghost'):.3f} | "
                         f"{mean('position_rpx'):.2f} | "
                         f"{mean('flicker'):.2f} | {r['paths']['centroids'][method]['psnr']:.2f} |")
    return "\n".join(lines)


def photo_table(rows: list[dict]) -> str:
    """One Markdown row per sample and light subset: 8-bit sRGB PSNR / SSIM at its held-out lights."""
    methods = ("circular", "alpha", "rbf", "hsh3", "hsh2")
    lines = ["| sample | lights fitted | fit | moving | " + " | ".join(methods) + " |",
             "|---|---|---|---|" + "---|" * len(methods)]
    for r in rows:
        subset = f"1 in {r['every']} held out" if "every" in r else f"{r['spread']} spread"
        cells = [f"{r['psnr'][m]:.2f} / {r['ssim'][m]:.3f}" if m in r["psnr"] else "" for m in methods]
        lines.append(f"| {r['photo']} | {r['lights']} ({subset}) | {r['fit']} | {r['moving']} | " + " | ".join(cells)
                     + " |")
    return "\n".join(lines)


def render_size(parser: argparse.ArgumentParser, text: str | None) -> tuple[int, int] | None:
    """``--size WxH`` as (width, height) of at least 16 pixels each (None where not given); else the parser's
    error (exit 2)."""
    if not text:
        return None
    try:
        size = tuple(int(v) for v in text.lower().split("x"))
    except ValueError:
        size = ()
    if len(size) != 2 or min(size) < 16:
        parser.error(f"--size takes WIDTHxHEIGHT of at least 16 pixels each, got '{text}'")
    return size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", choices=sorted(SCALES), default="cpu")
    parser.add_argument("--device", default=None)
    parser.add_argument("--scenes", default=",".join(SCENES),
                        help=f"comma-separated, of {', '.join(SCENES)}; empty: none (the samples alone, --photos)")
    parser.add_argument("--captures", default=None, help="comma-separated (default: the scale's)")
    parser.add_argument("--frames", type=int, default=96)
    parser.add_argument("--size", default=None, metavar="WxH", help="the renders' size (default: the scale's)")
    parser.add_argument("--learned", action="store_true", help="also the learned residual alone on a CPU (slow)")
    parser.add_argument("--photos", nargs="?", const=",".join(SAMPLES), default="",
                        help="also the samples (default all; or a comma-separated choice of "
                        f"{', '.join(SAMPLES)}): the photographs with every k-th light held out, the dome sample "
                        "on 16, 25 and 49 spread lights")
    parser.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="a fit setting for every fit, as `fit --set` takes it (repeatable)")
    args = parser.parse_args()
    wp.init()
    device = str(wp.get_device(args.device))
    out = Path(os.environ.get("OUT") or Path(__file__).resolve().parent / "results" / f"motion-{args.scale}")
    out.mkdir(parents=True, exist_ok=True)
    captures = args.captures.split(",") if args.captures else SCALES[args.scale][1]
    size = render_size(parser, args.size)
    scenes = [scene for scene in args.scenes.split(",") if scene]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        parser.error(f"unknown scenes {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        pictures = Path(scratch)
        for scene in scenes:
            for capture in captures:
                started = time.perf_counter()
                results.append(run_scene(scene, capture, args.scale, device, args.frames, args.learned, pictures,
                                         args.set, size))
                r = results[-1]
                print(f"{scene} {capture}: moving {r['moving']}, fits {r['fit_seconds']} s, "
                      f"{time.perf_counter() - started:.0f} s in all", file=sys.stderr, flush=True)
        # the pictures of the path where the field loses most to the blend, and of the one where it gains most
        for which, pick in (("worst", min), ("best", max)) if results else ():
            r = pick(results, key=lambda r, which=which: r[f"{which}_gap_db"])
            for suffix in (".png", ".gif", ".txt"):
                shutil.copyfile(pictures / f"{r['scene']}-{r['capture']}-{which}{suffix}", out / f"{which}{suffix}")
            print(f"{which} path: {r['scene']} {r['capture']} {r[f'{which}_path']} (field - alpha "
                  f"{r[f'{which}_gap_db']:+.2f} dB): {out / (which + '.gif')}", file=sys.stderr)
    photos = run_photos(args.scale, device, args.learned, args.set, args.photos.split(",")) if args.photos else []
    report = {"device": device, "scale": args.scale, "frames": args.frames, "date": time.strftime("%Y-%m-%d"),
              "settings": args.set,
              "results": results, "photos": photos}
    (out / "bench_motion.json").write_text(json.dumps(report, indent=1))
    if results:
        print(table(results))
    if photos:
        print()
        print(photo_table(photos))


if __name__ == "__main__":
    main()
