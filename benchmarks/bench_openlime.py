"""``export --format openlime`` on the two samples: each model's size, export time and its images as OpenLIME
computes them (``web.openlime.relight_openlime``: the page matches it to 35 dB or better, ``tests/test_openlime.py``)
at the held-out lights, in 8-bit sRGB PSNR / SSIM, next to the same fits unquantised.

    python benchmarks/bench_openlime.py                        # both samples, with the neural layer: ~10 min, 2 cores
    python benchmarks/bench_openlime.py --cases synth --no-neural
    python benchmarks/bench_openlime.py --page                 # each export opened in OpenLIME too (Chromium)

``--page`` opens every export in OpenLIME 1.2.6 (``$WARP_HIGHLIGHTS_OPENLIME``, default ../shared/tools/openlime; not
part of this project) in headless Chromium, sets 5 light directions, and prints the 8-bit PSNR of its canvas
against ``relight_openlime`` (least and mean) and its console errors; it writes
``results/images/openlime-CASE.png``: OpenLIME's canvas (top) over the reference (bottom) at the light
(0.3, 0.5), one column a model.

The dome sample at 160 x 160 at its Test lights, the statue at 192 x 181 with every 5th light held out
(``bench_quality.load_case``). ptm, hsh and rbf are fitted to the captured lights' sRGB values; the neural layer
is a learned residual fitted with ``fit --residual learned`` on this CPU (``--teacher-seconds``), then distilled
into OpenLIME's decoder for ``--distil-seconds``; its row gives the field's own score beside it (what the
distillation and the 8-bit codes cost).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import http.server
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import SIZES, load_case  # noqa: E402

from warp_highlights.fit.pipeline import fit_field  # noqa: E402
from warp_highlights.io.images import linear_to_srgb, srgb_to_linear  # noqa: E402
from warp_highlights.model.config import FitSettings  # noqa: E402
from warp_highlights.quality.metrics import psnr_8bit, srgb_scores  # noqa: E402
from warp_highlights.relight.baselines import fit_baseline  # noqa: E402
from warp_highlights.relight.evaluation import resize_stack  # noqa: E402
from warp_highlights.relight.relighter import Relighter  # noqa: E402
from warp_highlights.web.openlime import (  # noqa: E402
    OPENLIME_MODELS,
    export_openlime,
    export_openlime_neural,
    relight_openlime,
)

UNQUANTISED = {"ptm": "ptm", "hsh": "hsh3", "rbf": None}  # the project's own fit of the same model, unquantised
PAGE = Path(__file__).resolve().parents[1] / "tests" / "data" / "openlime-page.html"
OPENLIME = Path(os.environ.get("WARP_HIGHLIGHTS_OPENLIME",
                               Path(__file__).resolve().parents[2] / "shared" / "tools" / "openlime"))
PAGE_LIGHTS = [(0.3, 0.5), (-0.5, 0.2), (0.1, -0.7), (0.0, 0.0), (-0.6, -0.6)]


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def page_scores(browser, export: Path) -> tuple[float, float, int, np.ndarray]:
    """OpenLIME's canvas against ``relight_openlime`` at ``PAGE_LIGHTS``: least and mean 8-bit PSNR (dB), console
    errors, and (canvas over reference) at the first light."""
    info = json.loads((export / "info.json").read_text())
    lights = np.array([(x, y, np.sqrt(max(0.0, 1 - x * x - y * y))) for x, y in PAGE_LIGHTS])
    expected = np.round(255 * np.clip(relight_openlime(export, lights), 0, 1)).astype(np.uint8)
    with tempfile.TemporaryDirectory() as site:
        shutil.copy(OPENLIME / "openlime.min.js", site)
        shutil.copytree(export, Path(site) / "data")
        shutil.copy(PAGE, Path(site) / "index.html")
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=site))
        threading.Thread(target=server.serve_forever, daemon=True).start()
        tab, errors = browser.new_page(), []
        tab.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
        tab.on("pageerror", lambda error: errors.append(str(error)))
        try:
            tab.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            tab.wait_for_function("window.olReady === true", timeout=120_000)
            canvases = [np.array(tab.evaluate(f"relightAt({x}, {y})"), np.uint8).reshape(info["height"],
                                                                                        info["width"], 4)[..., :3]
                        for x, y in PAGE_LIGHTS]
        finally:
            tab.close()
            server.shutdown()
            server.server_close()
    scores = [psnr_8bit(c, e) for c, e in zip(canvases, expected)]
    return min(scores), float(np.mean(scores)), len(errors), np.concatenate([canvases[0], expected[0]], axis=0)


def score(relit_srgb: np.ndarray, truth_linear: np.ndarray) -> tuple[float, float]:
    """Mean 8-bit sRGB PSNR / SSIM of display values against linear truth."""
    psnr, ssim = srgb_scores(srgb_to_linear(np.clip(relit_srgb, 0, 1)), truth_linear)
    return float(np.mean(psnr)), float(np.mean(ssim))


def _say(row: dict) -> None:
    """A row as it comes, its page strip left out."""
    print({key: (value[:3] if key == "page" and value is not None else value) for key, value in row.items()},
          flush=True)


def run(case: str, args, browser=None) -> list[dict]:
    dataset = load_case(case, "cpu", "cpu")
    width, height = SIZES[case][0]
    images = resize_stack(dataset.images, width, height)
    truth = resize_stack(dataset.heldout.images, width, height)
    values = linear_to_srgb(np.clip(images, 0, 1))
    held = dataset.heldout.lights.directions
    rows = []
    for model in OPENLIME_MODELS:
        with tempfile.TemporaryDirectory() as folder:
            started = time.perf_counter()
            export_openlime(values, dataset.lights.directions, folder, model=model)
            seconds = time.perf_counter() - started
            size = sum(p.stat().st_size for p in Path(folder).iterdir())
            psnr, ssim = score(relight_openlime(folder, held), truth)
            page = page_scores(browser, Path(folder)) if browser is not None else None
        own = ""
        if UNQUANTISED[model]:
            fitted = fit_baseline(UNQUANTISED[model], values, dataset.lights.directions, device="cpu")
            own = "%.2f" % score(fitted.relight(held), truth)[0]
        rows.append(dict(case=case, model=model, kb=size / 1e3, seconds=seconds, psnr=psnr, ssim=ssim, own=own,
                         page=page))
        _say(rows[-1])
    if args.neural:
        settings = FitSettings().with_overrides(["residual.kind=learned",
                                                 f"residual.learned_seconds={args.teacher_seconds}"])
        field = fit_field(dataset, device="cpu", size=(width, height), settings=settings, progress=False)
        own = Relighter(field, device="cpu").relight(held).full / field.exposure
        own_psnr = float(np.mean(srgb_scores(np.clip(own, 0, None), truth)[0]))
        with tempfile.TemporaryDirectory() as folder:
            started = time.perf_counter()
            _, figures = export_openlime_neural(field, folder, seconds=args.distil_seconds)
            seconds = time.perf_counter() - started
            size = sum(p.stat().st_size for p in Path(folder).iterdir())
            psnr, ssim = score(relight_openlime(folder, held), truth)
            page = page_scores(browser, Path(folder)) if browser is not None else None
        rows.append(dict(case=case, model="neural", kb=size / 1e3, seconds=seconds, psnr=psnr, ssim=ssim,
                         own="%.2f (the field)" % own_psnr, note=figures, page=page))
        _say(rows[-1])
    if browser is not None:
        strip = np.concatenate([row["page"][3] for row in rows], axis=1)
        Image.fromarray(strip).save(Path(__file__).parent / "results" / "images" / f"openlime-{case}.png")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="synth,statue")
    parser.add_argument("--no-neural", dest="neural", action="store_false")
    parser.add_argument("--teacher-seconds", type=float, default=120.0)
    parser.add_argument("--distil-seconds", type=float, default=120.0)
    parser.add_argument("--page", action="store_true", help="open each export in OpenLIME (headless Chromium)")
    args = parser.parse_args()
    if args.page:
        from playwright.sync_api import sync_playwright

        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        with sync_playwright() as driver:
            software_gl = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
            browser = driver.chromium.launch(executable_path=chromium, args=software_gl)
            rows = [row for case in args.cases.split(",") for row in run(case, args, browser)]
            browser.close()
    else:
        rows = [row for case in args.cases.split(",") for row in run(case, args)]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    print(f"\n{platform.machine()} {platform.node()}, {datetime.date.today()}, commit {commit}\n")
    print("| capture | model | size (kB) | export (s) | PSNR / SSIM at held-out lights | unquantised | OpenLIME's "
          "canvas against the reference: least / mean PSNR, console errors |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        page = "" if row["page"] is None else f"{row['page'][0]:.2f} / {row['page'][1]:.2f}, {row['page'][2]}"
        print(f"| {row['case']} | {row['model']} | {row['kb']:.0f} | {row['seconds']:.1f} | "
              f"{row['psnr']:.2f} / {row['ssim']:.4f} | {row['own']} | {page} |")


if __name__ == "__main__":
    main()
