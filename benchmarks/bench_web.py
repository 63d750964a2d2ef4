"""Load and frame time of exported web viewers in headless Chromium (software GL: SwiftShader).

    python benchmarks/bench_web.py FIELD.whf [FIELD.whf ...]     # needs chromium and Playwright

Per field: export it (``warp_highlights.web.export_viewer``), serve it on 127.0.0.1, open it and
measure the time from navigation to the first relit image, then the mean time of a frame over 30
light directions along an orbit (the light set, the Gaussians moved, the draw finished: a one-pixel
``readPixels`` waits for it), and the export's size against the field file's. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import threading
import time
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


def measure(path: Path, browser) -> dict:
    field = load_field(path)
    with tempfile.TemporaryDirectory() as folder:
        export_viewer(field, Path(folder))
        export_bytes = sum(p.stat().st_size for p in Path(folder).iterdir())
        server = make_server(folder, 0)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            page = browser.new_page()
            started = time.perf_counter()
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            page.wait_for_function("window.whViewer !== undefined", timeout=120_000)
            page.evaluate("() => { const p = new Uint8Array(4); whViewer.gl.readPixels(0, 0, 1, 1, whViewer.gl.RGBA, whViewer.gl.UNSIGNED_BYTE, p); }")
            first = time.perf_counter() - started
            frame_ms = page.evaluate(TIMED_FRAMES, FRAMES)
            page.close()
        finally:
            server.shutdown()
            server.server_close()
    return {"field": path.name, "size": f"{field.width}x{field.height}", "lights": field.light_count, "first_s": first,
            "frame_ms": frame_ms, "export_bytes": export_bytes, "field_bytes": path.stat().st_size}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fields", nargs="+", type=Path)
    parser.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    args = parser.parse_args()
    if args.chromium is None:
        raise SystemExit("no chromium found; apt install chromium (or pass --chromium PATH)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=args.chromium, args=SOFTWARE_GL)
        rows = [measure(path, browser) for path in args.fields]
        browser.close()
    print("\n| field | size | lights | first image (s) | frame (ms) | frames/s | export | field file |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['field']} | {r['size']} | {r['lights']} | {r['first_s']:.2f} | {r['frame_ms']:.1f} | {1000 / r['frame_ms']:.0f} | "
              f"{r['export_bytes'] / 1e6:.2f} MB | {r['field_bytes'] / 1e6:.2f} MB |")
    if any(math.isnan(r["frame_ms"]) for r in rows):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
