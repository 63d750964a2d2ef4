"""Field file bytes and ``save_field`` seconds: each field loaded and saved again, as the installed package
writes it. Uses only ``load_field`` and ``save_field``, so the same script measures any version of the
package (run it with another checkout on ``PYTHONPATH`` to compare file formats on the same fields).

    python benchmarks/bench_save.py FIELD.whf [FIELD.whf ...] [--repeat 5]

Prints one Markdown row per field: the format version written, the file's bytes and the residual's
share of them, and the best and median seconds of ``--repeat`` saves (the codes compressed in threads:
a loaded field keeps none of the chunks a fit's rate search made).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from warp_highlights.io.fieldfile import FORMAT_VERSION, field_size_report, load_field, save_field


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fields", nargs="+", type=Path)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print("| field | format | bytes | residual bytes | save best (s) | save median (s) |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for path in args.fields:
            field = load_field(path)
            target = Path(folder) / path.name
            seconds = []
            for _ in range(args.repeat):
                started = time.perf_counter()
                written = save_field(field, target)
                seconds.append(time.perf_counter() - started)
                target.unlink()
            save_field(field, target)
            residual = field_size_report(load_field(target)).get("residual")
            print(f"| {path.stem} | {FORMAT_VERSION} | {written:,} | {residual:,} | "
                  f"{min(seconds):.3f} | {statistics.median(seconds):.3f} |")
            target.unlink()


if __name__ == "__main__":
    main()
