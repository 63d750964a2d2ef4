"""A collection's summary: ``collection.json`` for programs and ``index.html``, a gallery for people."""

from __future__ import annotations

import html
import json
import math
import time
from pathlib import Path

from .. import __version__
from ..io.atomic import atomic_file

__all__ = ["COLLECTION_JSON", "GALLERY_METHODS", "INDEX_HTML", "summary", "write_gallery"]

COLLECTION_JSON = "collection.json"
INDEX_HTML = "index.html"
GALLERY_METHODS = ("circular", "alpha", "ptm", "hsh3", "rbf")
"""The gallery's score columns: the field, the alpha blend of its lights and the RTI baselines (8-bit sRGB PSNR of
the full images at the held-out lights); ``collection.json`` has every method evaluated."""


def summary(records: list[dict]) -> dict:
    """Counts, and per method the mean over the scored captures of their mean PSNR; how often the field beats the
    blend."""
    ok = [r for r in records if r.get("status") == "ok"]
    scored = [r for r in ok if r.get("scores")]
    methods: dict[str, list[float]] = {}
    for record in scored:
        for method, score in record["scores"]["methods"].items():
            if isinstance(score.get("psnr_db"), (int, float)):
                methods.setdefault(method, []).append(score["psnr_db"])
    wins = [_psnr(r, "circular") > _psnr(r, "alpha") for r in scored
            if _psnr(r, "circular") is not None and _psnr(r, "alpha") is not None]
    return {
        "captures": len(records),
        "finished": len(ok),
        "failed": len(records) - len(ok),
        "mean_psnr_db": {m: round(sum(v) / len(v), 2) for m, v in methods.items()},
        "circular_beats_alpha": f"{sum(wins)} of {len(wins)}" if wins else None,
        "fit_seconds": round(sum(r.get("fit_seconds") or 0.0 for r in ok), 1),
    }


def write_gallery(output, records: list[dict], *, title: str | None = None) -> tuple[Path, Path]:
    """Write ``collection.json`` and ``index.html`` into ``output`` (each under a temporary name, then renamed)."""
    output = Path(output)
    title = title or output.resolve().name
    data = {"version": __version__, "generated": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "title": title,
            "summary": summary(records), "captures": records}
    with atomic_file(output / COLLECTION_JSON) as temporary:
        temporary.write_text(json.dumps(data, indent=2, allow_nan=False))
    with atomic_file(output / INDEX_HTML) as temporary:
        temporary.write_text(_page(title, data))
    return output / COLLECTION_JSON, output / INDEX_HTML


def _psnr(record: dict, method: str):
    score = ((record.get("scores") or {}).get("methods") or {}).get(method) or {}
    value = score.get("psnr_db")
    return value if isinstance(value, (int, float)) and math.isfinite(value) else None


def _page(title: str, data: dict) -> str:
    e = html.escape
    s = data["summary"]
    means = " · ".join(f"{e(m)} {v:.2f} dB" for m, v in s["mean_psnr_db"].items() if m in GALLERY_METHODS)
    rows = []
    for record in data["captures"]:
        name = e(record["name"])
        if record.get("status") != "ok":
            rows.append(f'<tr class="failed"><td></td><td>{name}</td><td '
                        f'colspan="{4 + len(GALLERY_METHODS) + 1}">failed at '
                        f'{e(str(record.get("step") or "?"))}: {e(str(record.get("error") or ""))}</td></tr>')
            continue
        scores = [_psnr(record, m) for m in GALLERY_METHODS]
        best = max((v for v in scores if v is not None), default=None)
        cells = "".join(
            f'<td class="num{" best" if v is not None and v == best else ""}">{"" if v is None else f"{v:.2f}"}</td>'
            for v in scores)
        size = record.get("size") or ["?", "?"]
        viewer = (record.get("files") or {}).get("viewer")
        link = f'<a href="{e(record["name"])}/{e(viewer)}">viewer</a>' if viewer else ""
        evaluation = (record.get("files") or {}).get("evaluation")
        # its plots and report.json
        report = (f' · <a href="{e(record["name"])}/{e(str(Path(evaluation).parent))}/">evaluation</a>' if evaluation
                  else "")
        gaussians = record.get("gaussians_per_light")
        rows.append(
            f'<tr><td><img src="{name}/thumbnail.png" alt="{name}" loading="lazy"></td><td>{name}</td>'
            f'<td class="num">{e(str(record.get("lights")))}</td><td '
            f'class="num">{e(str(size[0]))}x{e(str(size[1]))}</td>'
            f'<td class="num">{"" if gaussians is None else f"{gaussians:.1f}"}</td>'
            f'<td class="num">{record.get("fit_seconds") or 0:.1f}</td>{cells}<td>{link}{report}</td></tr>')
    heads = "".join(f'<th class="num">{e(m)}</th>' for m in GALLERY_METHODS)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{e(title)}: warp-highlights collection</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body {{ font: 14px system-ui, sans-serif; margin: 1.5em; color: #222; }}
table {{ border-collapse: collapse; }}
th, td {{ padding: 4px 8px; border-bottom: 1px solid #ddd; vertical-align: middle; text-align: left; }}
th {{ background: #f4f4f4; position: sticky; top: 0; }}
td.num, th.num {{ text-align: right; font-variant-numeric: tabular-nums; }}
td.best {{ font-weight: bold; }}
tr.failed td {{ color: #a00; }}
img {{ max-width: 160px; display: block; }}
</style></head><body>
<h1>{e(title)}</h1>
<p>{s["finished"]} of {s["captures"]} captures finished{f', {s["failed"]} failed' if s["failed"] else ''};
fitting took {s["fit_seconds"]:.0f} s in all.
{f'Mean 8-bit sRGB PSNR of the full images at the held-out lights: {means}.' if means else ''}
{f'The moving highlights beat the alpha blend on {e(s["circular_beats_alpha"])} captures.'
   if s["circular_beats_alpha"] else ''}
The viewers need a web server: <code>warp-highlights serve {e(title)}</code>.
Figures for programs: <a href="{COLLECTION_JSON}">{COLLECTION_JSON}</a>.</p>
<table>
<thead><tr><th></th><th>capture</th><th class="num">lights</th><th class="num">size</th>
<th class="num">Gaussians / light</th><th class="num">fit (s)</th>{heads}<th></th></tr>
<tr><th></th><th></th><th></th><th></th><th></th><th></th>
<th class="num" colspan="{len(GALLERY_METHODS)}">PSNR (dB) at held-out lights, 8-bit sRGB</th><th></th></tr></thead>
<tbody>
{chr(10).join(rows)}
</tbody></table>
<p><small>warp-highlights {e(data["version"])}, {e(data["generated"])}</small></p>
</body></html>
"""
