"""What decides the learned check: the moved Gaussians or the residual learned with them.

The learned check (``residual.learned.check_learned``) leaves a few lights out and scores, there, the learned
residual plus the Gaussians moved from the other lights against the images learned alone. This script fits a
capture with the learned residual, records the check's inputs as the fit passes them, and scores at the same
left-out lights what other residuals would give with the same moved Gaussians:

- ``exact``: the residual the check learns at that light (the image less its own Gaussians, the diffuse part
  under them), exact: only the moved Gaussians err;
- ``ptm``, ``hsh2``, ``hsh3``, ``rbf``: that residual fitted by the RTI baselines over the other lights (linear,
  band-limited in the light direction: PTM and HSH of low order, RBF with sigma by leave-one-out), with the
  moved Gaussians, and without them;
- the same baselines fitted to the images alone;
- the moved Gaussians' light over the light's own Gaussians' (1: as bright as fitted there; a median over the lights).

Where ``exact`` is low the Gaussians' move loses whatever the residual; where a band-limited residual plus the
Gaussians scores above the learned residual plus the Gaussians, a decoder whose light dependence is band-limited
would win the check. 8-bit sRGB PSNR (dB), means over the check's lights.

    python benchmarks/bench_check_parts.py        # the sharp donut, bumpy donut, tiled teapot (16 lights), dome sample
    python benchmarks/bench_check_parts.py --cases teapot-tiles:dome49 --size 320x180
    python benchmarks/bench_check_parts.py --device cuda:0 --size 480x270     # fitted on a GPU
    python benchmarks/bench_check_parts.py --set residual.diffuse_under_highlights=0

Cases: ``SCENE:CAPTURE`` of ``bench_motion.py`` (rendered at ``--size``, default its CPU size) or
``dome-sample`` (the rendered dome sample's 49 lights at 160x160). Prints one Markdown table; writes
bench_check_parts.json to $OUT (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_motion  # noqa: E402
import bench_quality  # noqa: E402

from warp_highlights.fit import pipeline  # noqa: E402
from warp_highlights.io.dataset import ReflectanceField  # noqa: E402
from warp_highlights.model.config import FitSettings  # noqa: E402
from warp_highlights.model.threads import parallel_map  # noqa: E402
from warp_highlights.quality.metrics import srgb_psnr  # noqa: E402
from warp_highlights.relight.baselines import fit_baseline, minimum_lights  # noqa: E402
from warp_highlights.residual.inputs import learned_target  # noqa: E402

BASELINES = ("ptm", "hsh2", "hsh3", "rbf")
DOME_SAMPLE_SIZE = (160, 160)


def load(case: str, size: tuple[int, int] | None, device: str) -> tuple[ReflectanceField, dict]:
    """The capture of ``case`` and how to fit it: at which size, and for a render (linear, white = 1) at which
    exposure, as ``bench_quality.py`` and ``bench_motion.py`` fit them."""
    if case == "dome-sample":
        return bench_quality.load_case("synth", "cpu", device), {"size": DOME_SAMPLE_SIZE}
    scene, _, capture = case.partition(":")
    if scene not in bench_motion.SCENES or capture not in bench_motion.CAPTURES:
        raise SystemExit(f"unknown case '{case}': use dome-sample or SCENE:CAPTURE of {', '.join(bench_motion.SCENES)}"
                         f" and {', '.join(bench_motion.CAPTURES)}")
    shape, material = bench_motion.SCENES[scene]
    width, height = size or bench_motion.SCALES["cpu"][0]
    renderer = bench_motion.Renderer(bench_motion.make_shape(shape), material=material,
                                     settings=bench_motion.RenderSettings(width=width, height=height,
                                                                          samples_per_pixel=4),
                                     rotation=bench_motion.view_rotation(shape), device=device)
    lights = bench_motion.CAPTURES[capture]()
    captured = renderer.render(lights.directions)
    return ReflectanceField(images=captured.full, lights=lights, specular=captured.specular,
                            diffuse=captured.diffuse, mask=renderer.mask), {"exposure": 1.0}


def recorded_check(dataset: ReflectanceField, fit: dict, settings: FitSettings,
                   device: str) -> tuple[dict, object] | None:
    """Fits ``dataset`` (``fit``: ``fit_field``'s size or exposure) and returns the learned check's arguments and
    its result (None: the fit ran no learned check)."""
    calls = []
    original = pipeline.check_learned

    def record(*args, **kwargs):
        result = original(*args, **kwargs)
        calls.append((args, kwargs, result))
        return result

    with mock.patch.object(pipeline, "check_learned", side_effect=record):
        pipeline.fit_field(dataset, device=device, progress=False, settings=settings, **fit)
    if not calls:
        return None
    args, kwargs, result = calls[0]
    names = ("images", "own", "colour", "directions", "lights", "highlights")
    return {**dict(zip(names, args)), **kwargs}, result


def parts(check: dict, level: float) -> dict[str, float]:
    """Mean 8-bit sRGB PSNR (dB) at the check's lights of each baseline's residual with and without the moved
    Gaussians, and ``moved_energy``: the median over those lights of the moved Gaussians' light over the light's own
    Gaussians'."""
    images, own, directions = check["images"], check["own"], np.asarray(check["directions"], np.float64)
    lights, moved = np.asarray(check["lights"], np.int64), np.asarray(check["highlights"], np.float32)
    colour, specular, scale = check.get("colour"), check.get("specular"), 1.0 / float(check["factor"])
    tint = np.ones((1, 1, 3), np.float32) if colour is None else np.asarray(colour, np.float32)
    used = np.setdiff1d(np.arange(len(images)), lights)

    residuals = np.stack(parallel_map(
        lambda i: learned_target(images[i], own[i], tint, None if specular is None else specular[i], level),
        range(len(images))))
    truth = np.asarray(images[lights], np.float32) * scale

    def score(predicted: np.ndarray) -> float:
        return float(np.mean([srgb_psnr(np.maximum(p, 0.0) * scale, t) for p, t in zip(predicted, truth)]))

    drawn = np.asarray(own[lights], np.float64)[..., None] * tint  # each check light's own Gaussians, tinted
    out = {"moved_energy": float(np.median(moved.reshape(len(lights), -1).sum(axis=1)
                                           / np.maximum(drawn.reshape(len(lights), -1).sum(axis=1), 1e-12)))}
    for method in BASELINES:
        if len(used) < minimum_lights(method):
            continue
        fitted = fit_baseline(method, residuals[used], directions[used], device="cpu").relight(directions[lights])
        out[f"{method}+gaussians"] = score(fitted + moved)
        out[f"{method} residual"] = score(fitted)
        alone = fit_baseline(method, np.asarray(images[used], np.float32), directions[used], device="cpu")
        out[f"{method} images"] = score(alone.relight(directions[lights]))
    return out


def table(rows: list[dict]) -> str:
    head = ("| case | check lights | learned + Gaussians | learned images | exact + Gaussians | moved / own light | "
            + " | ".join(f"{m} + Gaussians / {m} residual / {m} images" for m in BASELINES) + " |")
    lines = [head, "|" + "---|" * (6 + len(BASELINES))]
    for r in rows:
        p = r["parts"]
        cells = [" / ".join(f"{p[k]:.2f}" if k in p else "" for k in (f"{m}+gaussians", f"{m} residual", f"{m} images"))
                 for m in BASELINES]
        lines.append(f"| {r['case']} | {r['lights']} | {r['with_gaussians']:.2f} | {r['images_alone']:.2f} | "
                     f"{p['exact']:.2f} | {p['moved_energy']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default="donut-sharp:dome16,bumpy-metal:dome16,teapot-tiles:dome16,dome-sample")
    parser.add_argument("--device", default=None, help="Warp device to fit on (default: Warp's)")
    parser.add_argument("--size", default=None, metavar="WxH", help="the renders' size (default 160x90)")
    parser.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="a fit setting, as `fit --set` takes it (repeatable); the residual is learned")
    args = parser.parse_args()
    size = bench_motion.render_size(parser, args.size)
    wp.init()
    device = str(wp.get_device(args.device))
    settings = FitSettings().with_overrides(["residual.kind=learned", *args.set])
    out = Path(os.environ.get("OUT") or Path(__file__).resolve().parent / "results")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in [c for c in args.cases.split(",") if c]:
        started = time.perf_counter()
        dataset, fit = load(case, size, device)
        recorded = recorded_check(dataset, fit, settings, device)
        if recorded is None:
            print(f"{case}: the fit ran no learned check (no Gaussian moved, or the move check dropped them)")
            continue
        check, result = recorded
        report = result.report()
        rows.append({"case": case, "lights": report["lights"], "with_gaussians": report["with_gaussians_psnr_db"],
                     "images_alone": report["images_alone_psnr_db"],
                     "parts": {"exact": report["exact_residual_psnr_db"],
                               **parts(check, settings.residual.diffuse_under_highlights)}})
        print(f"{case}: {time.perf_counter() - started:.0f} s")
    if rows:
        print(table(rows))
    (out / "bench_check_parts.json").write_text(json.dumps({"device": device, "size": args.size, "settings": args.set,
                                                            "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
