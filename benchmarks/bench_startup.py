"""Time what a user waits for before any work: ``--help`` of every command, an argument error, and
``import warp_highlights`` (aim: under 0.5 s on a 2-core CPU, Warp not imported).

    python benchmarks/bench_startup.py [--repeat 5]

Each row runs a fresh Python process ``--repeat`` times and prints the median wall time, and whether
Warp, SciPy or pyvista were imported (``-X importtime`` of one more run). Writes $OUT/bench_startup.json
when OUT is set.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROWS = [
    ("import warp_highlights", ["-c", "import warp_highlights"]),
    ("warp-highlights --help", ["-m", "warp_highlights", "--help"]),
    *[(f"warp-highlights {c} --help", ["-m", "warp_highlights", c, "--help"])
      for c in ("render", "info", "sheet", "fit", "relight", "animate", "evaluate", "collection", "view", "demo")],
    ("warp-highlights fit --size big (usage error)",
     ["-m", "warp_highlights", "fit", "x", "-o", "y.whf", "--size", "big"]),
]
HEAVY = ("warp", "scipy", "pyvista")


def heavy_imports(arguments: list[str]) -> list[str]:
    """Which of ``HEAVY`` the process imported (from ``-X importtime``)."""
    run = subprocess.run([sys.executable, "-X", "importtime", *arguments], capture_output=True, text=True)
    names = {line.split("|")[-1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    return [h for h in HEAVY if h in names]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    rows = []
    for label, arguments in ROWS:
        seconds = []
        for _ in range(args.repeat):
            started = time.perf_counter()
            subprocess.run([sys.executable, *arguments], capture_output=True)
            seconds.append(time.perf_counter() - started)
        rows.append({"what": label, "median_s": statistics.median(seconds), "max_s": max(seconds),
                     "imports": heavy_imports(arguments)})
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"median of {args.repeat} fresh processes\n")
    print("| what | median (s) | max (s) | imported of warp/scipy/pyvista |")
    print("|---|---|---|---|")
    for row in rows:
        print(
            f"| `{row['what']}` | {row['median_s']:.2f} | {row['max_s']:.2f} | {', '.join(row['imports']) or 'none'} |")
    if os.environ.get("OUT"):
        out = Path(os.environ["OUT"]) / "bench_startup.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"cpu_count": os.cpu_count(), "python": platform.python_version(), "rows": rows},
                                  indent=1))


if __name__ == "__main__":
    main()
