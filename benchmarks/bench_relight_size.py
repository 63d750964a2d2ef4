"""Relighting larger than the field: the whole ``relight`` command's wall time and peak memory, and specks.

    python benchmarks/bench_relight_size.py [--field FIELD] [--sizes 1920x1080,3840x2160,7680x4320]
        [--reference CHECKOUT] [--specks FIELD --speck-width 320 --test-lights FILE.lp]

Without ``--field`` it renders a donut (49 dome lights, 384x216) and fits it at 192x108 on the CPU (about
two minutes on 2 cores) in a temporary folder. For each size it runs ``warp-highlights relight FIELD --light
0.3,0.5,1 --size WxH -o out.png`` as a new process under ``/usr/bin/time -v`` (wall seconds, peak resident
memory) and prints the line the command prints (its own time, relighting and writing). ``--reference`` runs
the same commands with another checkout of the package (``PYTHONPATH=CHECKOUT``), e.g. a ``git worktree`` of
an earlier commit, and reports the largest difference between the two images in 16-bit PNG levels.

``--specks FIELD`` relights the field at every light of the field and of ``--test-lights`` at ``--speck-width``
pixels wide, for several ``raster.upsampled_min_sigma_px``, and prints how far the image rises above the
field's own image enlarged (8-bit sRGB levels) and the largest one-pixel outlier above its 3 x 3 median.

Prints tables; writes every figure to $OUT/bench_relight_size.json when OUT is set.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _command(arguments: list) -> list[str]:
    return [sys.executable, "-m", "warp_highlights", *map(str, arguments)]


def _environment(checkout: Path) -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(checkout), os.environ.get("PYTHONPATH")])))


def timed_relight(field: Path, size: str, out: Path, checkout: Path) -> dict:
    """One ``relight`` as a new process under ``/usr/bin/time -v``: wall seconds, peak resident MB, its line."""
    done = subprocess.run(["/usr/bin/time", "-v", *_command(["relight", field, "--light", "0.3,0.5,1", "--size", size,
                                                            "-o", out, "--overwrite", "-q"])],
                          capture_output=True, text=True, env=_environment(checkout), cwd=out.parent)
    if done.returncode != 0:
        raise SystemExit(f"relight failed ({checkout}):\n{done.stderr[-2000:]}")
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", done.stderr)
    hours, minutes, seconds = (float(g) if g else 0.0 for g in wall.groups())
    peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr).group(1))
    return {"wall_s": round(3600 * hours + 60 * minutes + seconds, 2), "peak_mb": round(peak / 1024, 1),
            "line": done.stdout.strip().splitlines()[-1]}


def png_levels(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    image = oiio.ImageInput.open(str(path))
    pixels = np.asarray(image.read_image(0, 0, 0, image.spec().nchannels, "uint16"), dtype=np.int64)
    image.close()
    return pixels


def made_field(work: Path) -> Path:
    """A donut rendered at 384x216 under 49 dome lights, fitted at 192x108 on the CPU."""
    data, field = work / "donut", work / "donut.whf"
    for arguments in (["render", "donut", data, "--lights", "49", "--size", "384x216", "--dome", "--device", "cpu",
                       "-q"],
                      ["fit", data, "--size", "192x108", "-o", field, "--device", "cpu", "-q"]):
        subprocess.run(_command(arguments), check=True, env=_environment(REPO))
    return field


def specks(field_path: Path, width: int, test_lights: Path | None, minima: list[float]) -> list[dict]:
    """Per ``upsampled_min_sigma_px``: the most the larger image rises above the field's image enlarged, and its
    largest one-pixel outlier, over the field's lights and ``test_lights`` (8-bit sRGB levels)."""
    from scipy.ndimage import median_filter

    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.io.images import encode_levels
    from warp_highlights.io.lightfile import read_lp
    from warp_highlights.io.resample import resample_image
    from warp_highlights.relight.relighter import Relighter

    field = load_field(field_path)
    height = round(field.height * width / field.width)
    lights = field.lights.directions
    if test_lights is not None:
        lights = np.concatenate([read_lp(test_lights, check_files=False).directions, lights])
    small = Relighter(field, device="cpu", scale=1 / field.exposure).relight(lights)
    enlarged = [encode_levels(resample_image(image, width, height), 255, linear=False).astype(np.int64)
                for image in small.full]
    rows = []
    for least in minima:
        raster = dataclasses.replace(field.fit_settings().raster, upsampled_min_sigma_px=least)
        big = Relighter(field, device="cpu", size=(width, height), scale=1 / field.exposure, raster=raster)
        images = big.relight(lights).full
        above = outlier = 0
        for image, reference in zip(images, enlarged):
            levels = encode_levels(image, 255, linear=False).astype(np.int64)
            above = max(above, int((levels - reference).max()))
            outlier = max(outlier, int((levels - median_filter(levels, size=(3, 3, 1))).max()))
        rows.append({"upsampled_min_sigma_px": least, "lights": len(lights), "above_enlarged": above,
                     "one_pixel_outlier": outlier})
    return rows


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--field", type=Path, help="field to relight (default: a donut fitted at 192x108 here)")
    parser.add_argument("--sizes", default="1920x1080,3840x2160,7680x4320", help="output sizes, comma-separated")
    parser.add_argument("--reference", type=Path, help="another checkout of the package to run the same commands")
    parser.add_argument("--specks", type=Path, metavar="FIELD", help="measure specks of this field relit larger")
    parser.add_argument("--speck-width", type=int, default=320, help="width the speck field is relit at (320)")
    parser.add_argument("--test-lights", type=Path, help=".lp of more lights for --specks (e.g. a Test/ folder's)")
    parser.add_argument("--minima", default="0,0.5,0.6,0.7,0.8,1.0",
                        help="raster.upsampled_min_sigma_px values for --specks")
    args = parser.parse_args()

    results = {"machine": machine()}
    with tempfile.TemporaryDirectory(prefix="bench-relight-size-") as folder:
        work = Path(folder)
        if args.specks is None or args.field is not None or args.reference is not None:
            field = (args.field or made_field(work)).resolve()
            print(f"# relight {field.name} --light 0.3,0.5,1 --size WxH -o out.png; {results['machine']}")
            print("| size | package | wall s | peak MB | the command's line | max diff (16-bit levels) |")
            print("|---|---|---|---|---|---|")
            rows = []
            for size in args.sizes.split(","):
                ours = timed_relight(field, size, work / f"ours-{size}.png", REPO)
                row = {"size": size, "ours": ours}
                print(f"| {size} | this | {ours['wall_s']} | {ours['peak_mb']} | {ours['line']} | |")
                if args.reference is not None:
                    theirs = timed_relight(field, size, work / f"ref-{size}.png", args.reference.resolve())
                    diff = int(np.abs(png_levels(work / f"ours-{size}.png")
                                      - png_levels(work / f"ref-{size}.png")).max())
                    row.update(reference=theirs, max_diff_16bit=diff)
                    print(f"| {size} | reference | {theirs['wall_s']} | {theirs['peak_mb']} | {theirs['line']} | "
                          f"{diff} |")
                rows.append(row)
            results["relight"] = rows
        if args.specks is not None:
            minima = [float(v) for v in args.minima.split(",")]
            rows = specks(args.specks, args.speck_width, args.test_lights, minima)
            print(f"\n# specks: {args.specks.name} relit {args.speck_width} px wide at {rows[0]['lights']} lights")
            print("| upsampled_min_sigma_px | most above the field's image enlarged | largest one-pixel outlier |")
            print("|---|---|---|")
            for row in rows:
                print(f"| {row['upsampled_min_sigma_px']:g} | {row['above_enlarged']} | {row['one_pixel_outlier']} |")
            results["specks"] = rows
    out = os.environ.get("OUT")
    if out:
        Path(out, "bench_relight_size.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
