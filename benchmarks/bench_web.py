"""Load and frame time of exported web viewers in headless Chromium (software GL: SwiftShader).

    python benchmarks/bench_web.py FIELD.whf [FIELD.whf ...]     # needs chromium and Playwright

Per field: export it (``warp_highlights.web.export_viewer``), serve it on 127.0.0.1, open it and
measure the time from navigation to the first relit image (drawn and one pixel read back, by the
page's clock), the time until every light's residual is
decoded (the page decodes them in the background while it already answers), then the mean time of a
frame over 30 light directions along an orbit (the light set, the Gaussians moved, the draw finished:
a one-pixel ``readPixels`` waits for it), and the export's size against the field file's. Prints a
Markdown table. ``--decode query`` measures the per-frame low-rank path instead; ``--screenshot PNG``
saves the first field's page (triangulation shown) as the README's picture.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warp_highlights.io.fieldfile import load_field
from warp_highlights.web.export import export_viewer
from warp_highlights.web.serve import make_server

SOFTWARE_GL = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
FRAMES = 30

TIMED_FRAMES = """(count) => {
  const gl = whViewer.gl, pixel = new Uint8Array(4), started = performance.now();
  for (let i = 0; i < count; i++) {
    const a = 2 * Math.PI * i / count;
    whViewer.setLight([0.6 * Math.cos(a), 0.6 * Math.sin(a), 0.8]);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
  }
  return (performance.now() - started) / count;
}"""


def measure(path: Path, browser, decode: str, screenshot: Path | None) -> dict:
    field = load_field(path)
    with tempfile.TemporaryDirectory() as folder:
        export_viewer(field, Path(folder))
        export_bytes = sum(p.stat().st_size for p in Path(folder).iterdir())
        server = make_server(folder, 0)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html?decode={decode}")
            page.wait_for_function("window.whViewer !== undefined || "
                                   "document.getElementById('status').textContent.startsWith('error')",
                                   timeout=120_000, polling=5)
            if page.evaluate("window.whViewer === undefined"):
                raise SystemExit(f"{path}: the page says {page.inner_text('#status')}")
            # the page's clock: from navigation to the first image drawn and read back
            first = page.evaluate("window.whFirstImageMs") / 1000
            page.wait_for_function("window.whReady === true", timeout=600_000, polling=20)
            ready = page.evaluate("window.whReadyMs") / 1000
            mode = page.evaluate("whViewer.mode")
            frame_ms = page.evaluate(TIMED_FRAMES, FRAMES)
            if screenshot is not None:
                page.check("#mesh")
                page.evaluate("whSetLight(0.45, 0.35, 0.82, 'circular')")
                page.screenshot(path=str(screenshot))
            page.close()
        finally:
            server.shutdown()
            server.server_close()
    return {"field": path.name, "size": f"{field.width}x{field.height}", "lights": field.light_count, "residual": mode,
            "first_s": first, "ready_s": ready,
            "frame_ms": frame_ms, "export_bytes": export_bytes, "field_bytes": path.stat().st_size}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fields", nargs="+", type=Path)
    parser.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    parser.add_argument("--decode", choices=("auto", "load", "query"), default="auto",
                        help="the page's low-rank decoding (default auto)")
    parser.add_argument("--screenshot", type=Path, help="save the first field's page here (PNG)")
    args = parser.parse_args()
    if args.chromium is None:
        raise SystemExit("no chromium found; apt install chromium (or pass --chromium PATH)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=args.chromium, args=SOFTWARE_GL)
        rows = [measure(path, browser, args.decode, args.screenshot if i == 0 else None)
                for i, path in enumerate(args.fields)]
        browser.close()
    print("\n| field | size | lights | page mode | first image (s) | all lights decoded (s) | frame (ms) | frames/s | "
          "export | field file |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['field']} | {r['size']} | {r['lights']} | {r['residual']} | {r['first_s']:.2f} | "
              f"{r['ready_s']:.2f} | {r['frame_ms']:.1f} | "
              f"{1000 / r['frame_ms']:.0f} | "
              f"{r['export_bytes'] / 1e6:.2f} MB | {r['field_bytes'] / 1e6:.2f} MB |")
    if any(math.isnan(r["frame_ms"]) for r in rows):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
