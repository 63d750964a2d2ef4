"""Figures for the evaluation report (docs/method.md, Evaluation), written as PNG files.

PSNR distributions per interpolation method, per-query scatter of one method against another,
Gaussian counts, PSNR over the barycentric coordinates of an interpolation triangle, and image grids
for visual comparisons.

matplotlib is imported inside each function, so the core package imports without it. Only the object
API is used (:class:`matplotlib.figure.Figure` on a :class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`),
never pyplot: no global figure state, so the functions are headless and safe to call from several
threads. Every figure is written to a temporary file beside the target, which then replaces the
target, so a failed plot never leaves half a file or destroys an earlier one.

This module holds one thing: the evaluation report's figures.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_file
from ..io.images import display_rgb8
from ..model.errors import InputError

__all__ = [
    "barycentric_to_plane",
    "caption_fontsize",
    "plot_barycentric_psnr",
    "plot_gaussian_counts",
    "plot_image_grid",
    "plot_psnr_distributions",
    "plot_psnr_pairs",
]

_DPI = 120
"""Dots per inch of every figure; with :data:`_WIDTH_IN` the PNGs are about 1000 pixels wide."""
_WIDTH_IN = 8.5
_FOOTNOTE_PT = 8.0
_CHAR_WIDTH_EM = 0.6  # mean width of a caption character, in ems of its font (DejaVu Sans, digits and lower case)
_METHOD_COLOURS = {"circular": "#1f77b4", "straight": "#ff7f0e", "alpha": "#2ca02c"}
_OTHER_COLOURS = ("#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
_SQRT3_2 = math.sqrt(3.0) / 2.0
_CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, _SQRT3_2]])
"""Plane positions of the triangle corners A, B, C (unit side, A bottom left, B bottom right, C top)."""


def barycentric_to_plane(barycentric) -> np.ndarray:
    """Map barycentric weights onto an equilateral triangle of unit side in the plane.

    Corner A lies at (0, 0), B at (1, 0) and C at (1/2, sqrt(3)/2), so a row (lA, lB, lC) goes to
    ``lA * A + lB * B + lC * C``; the centroid (1/3, 1/3, 1/3) goes to (1/2, sqrt(3)/6).

    Args:
        barycentric: ``(K, 3)`` weights (lA, lB, lC); each row sums to 1.

    Returns:
        ``(K, 2)`` float64 plane coordinates (x, y), unitless.

    Raises:
        InputError: Not a ``(K, 3)`` array of finite values, or a row that does not sum to 1.
    """
    return _checked_barycentric("barycentric_to_plane", barycentric) @ _CORNERS


def plot_psnr_distributions(
    scores: Mapping[str, np.ndarray], path, *, title: str | None = None, excluded: int = 0,
    notes: Sequence[str] = (),
) -> Path:
    """Violin plot of the per-query PSNR of each interpolation method (thesis Fig. 4.3).

    One violin per method, in the mapping's order, with the mean (diamond) and the 5th-95th percentile
    range (bar) marked and written above it; the tick labels give each method's number of values.
    Non-finite values (NaN, or infinite PSNR of identical images) are dropped and counted in the
    footnote; a method without finite values is drawn as an empty, labelled slot.

    Args:
        scores: Method name -> 1-D per-query PSNR in dB (lengths may differ between methods).
        path: Target ``.png`` file; missing parent folders are made.
        title: Figure title; a default describes the plot.
        excluded: Number of queries left out before scoring because both the interpolated and the
            ground-truth image were all black (docs/method.md, Evaluation); stated in the footnote.
        notes: Further footnote lines (e.g. what each method's images are made of).

    Returns:
        The path of the written PNG.

    Raises:
        InputError: An empty mapping, a score array that is not 1-D, a negative ``excluded`` or a
            target that is not a ``.png`` file.
    """
    where = "plot_psnr_distributions"
    path = _checked_png_path(where, path)
    scores = _checked_scores(where, scores)
    if isinstance(excluded, bool) or not isinstance(excluded, (int, np.integer)) or excluded < 0:
        raise InputError(f"{where}: excluded must be a count >= 0, got {excluded!r}")
    finite = {name: _finite(values) for name, values in scores.items()}
    # the statistics boxes side by side: each fits its method's slot of the plot's width, padding included
    # (the percentiles on two lines where many methods make the slots narrow)
    slot_in = 0.8 * _WIDTH_IN / len(finite)
    stacked = caption_fontsize([_summary_text(_summary(v)) for v in finite.values() if v.size], slot_in) < 7.5
    texts = [_summary_text(_summary(values), stacked=stacked) for values in finite.values() if values.size]
    box_size = caption_fontsize(texts, slot_in, largest=8.5)

    fig = _new_figure(_WIDTH_IN, 5.6)
    ax = fig.add_subplot()
    positions = np.arange(1, len(finite) + 1, dtype=np.float64)
    everything = np.concatenate([*finite.values(), np.zeros(0)])
    for index, (position, (name, values)) in enumerate(zip(positions, finite.items(), strict=True)):
        colour = _method_colour(name, index)
        if values.size == 0:
            ax.text(position, 0.5, "no finite\nvalues", transform=ax.get_xaxis_transform(), ha="center",
                    va="center", color="0.4", fontsize=9, style="italic")
            continue
        if values.size >= 2 and np.ptp(values) > 0.0:
            parts = ax.violinplot([values], positions=[position], widths=0.75, showextrema=False)
            for body in parts["bodies"]:
                body.set_facecolor(colour)
                body.set_edgecolor(colour)
                body.set_alpha(0.45)
        else:  # a kernel density needs spread: draw a single value as a flat bar
            ax.hlines(values[0], position - 0.3, position + 0.3, color=colour, linewidth=3)
        stats = _summary(values)
        ax.vlines(position, stats["p5"], stats["p95"], color="black", linewidth=2.5, zorder=3)
        ax.hlines([stats["p5"], stats["p95"]], position - 0.1, position + 0.1, color="black", linewidth=1.5,
                  zorder=3)
        ax.scatter([position], [stats["mean"]], marker="D", s=36, facecolor="white", edgecolor="black",
                   zorder=4)
        ax.text(position, 0.98, _summary_text(stats, stacked=stacked), transform=ax.get_xaxis_transform(), ha="center",
                va="top", fontsize=box_size, bbox={"boxstyle": "round,pad=0.3", "facecolor": "white",
                                              "edgecolor": colour, "alpha": 0.9})

    ax.set_xticks(positions, [f"{name}\nn = {values.size}" for name, values in finite.items()])
    ax.set_xlim(0.4, len(finite) + 0.6)
    if everything.size:
        low, high = float(everything.min()), float(everything.max())
        span = max(high - low, 1.0)
        ax.set_ylim(low - 0.06 * span, high + 0.32 * span)  # head room for the statistics boxes
    ax.set_xlabel("interpolation method")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(title or "PSNR of interpolated images against ground truth")
    # in the footnote row, clear of the violins and the statistics boxes
    fig.legend(handles=_distribution_legend_handles(), loc="lower right", bbox_to_anchor=(0.995, 0.0), ncols=2,
               fontsize=8.5, frameon=False)

    lines = [notes] if isinstance(notes, str) else [str(line) for line in notes]  # above the legend's row
    dropped = {name: int(scores[name].size - values.size) for name, values in finite.items()}
    if any(dropped.values()):
        counts = ", ".join(f"{name} {count}" for name, count in dropped.items() if count)
        lines.append(f"Non-finite PSNR values dropped: {counts}.")
    lines.append(f"{excluded} quer{'y' if excluded == 1 else 'ies'} left out: interpolated and ground-truth image "
                 "both all black (docs/method.md).")
    _footnote(fig, lines)
    return _save(fig, path)


def plot_psnr_pairs(
    first: np.ndarray,
    second: np.ndarray,
    path,
    *,
    first_name: str = "circular",
    second_name: str = "alpha",
    title: str | None = None,
) -> Path:
    """Scatter of the per-query PSNR of one method against another, with the diagonal.

    Each point is one query: ``second`` on the x axis, ``first`` on the y axis, so points above the
    diagonal are queries where ``first`` scores higher. The share of those ("circular better on 90% of
    496") is written under the title. Queries with a non-finite value in either array are dropped and
    counted in the footnote.

    Args:
        first: 1-D per-query PSNR in dB of the first method.
        second: 1-D per-query PSNR in dB of the second method, same queries in the same order.
        path: Target ``.png`` file; missing parent folders are made.
        first_name: Name of the first method (y axis).
        second_name: Name of the second method (x axis).
        title: Figure title; a default names the two methods.

    Returns:
        The path of the written PNG.

    Raises:
        InputError: Arrays that are not 1-D, differ in length or are empty, or a target that is not a
            ``.png`` file.
    """
    where = "plot_psnr_pairs"
    path = _checked_png_path(where, path)
    first = _checked_vector(where, "first", first)
    second = _checked_vector(where, "second", second)
    if first.size != second.size:
        raise InputError(f"{where}: first has {first.size} values but second has {second.size}; pass the "
                         "same queries in the same order")
    if first.size == 0:
        raise InputError(f"{where}: first and second are empty; pass at least one query's PSNR")
    keep = np.isfinite(first) & np.isfinite(second)
    x, y = second[keep], first[keep]

    fig = _new_figure(_WIDTH_IN, 7.6)
    ax = fig.add_subplot()
    if x.size:
        low, high = float(min(x.min(), y.min())), float(max(x.max(), y.max()))
        pad = 0.05 * max(high - low, 1.0)
        low, high = low - pad, high + pad
        groups = ((y > x, f"{first_name} better", _method_colour(first_name, 0)),
                  (y < x, f"{second_name} better", _method_colour(second_name, 1)),
                  (y == x, "equal", "0.4"))
        for mask, label, colour in groups:
            if mask.any():
                ax.scatter(x[mask], y[mask], s=14, alpha=0.65, color=colour, edgecolor="none",
                           label=f"{label} ({int(mask.sum())})")
        ax.plot([low, high], [low, high], color="black", linewidth=1, linestyle="--", label="equal PSNR")
        ax.set_xlim(low, high)
        ax.set_ylim(low, high)
        ax.legend(loc="upper left", fontsize=9, framealpha=0.9)
    else:
        ax.text(0.5, 0.5, "no query with finite PSNR for both methods", transform=ax.transAxes, ha="center",
                va="center", color="0.4", style="italic")
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"{second_name} PSNR (dB)")
    ax.set_ylabel(f"{first_name} PSNR (dB)")
    ax.grid(alpha=0.3)
    heading = title or f"Per-query PSNR: {first_name} against {second_name}"
    ax.set_title(f"{heading}\n{_pair_caption(first, second, first_name)}")
    if first.size - x.size:
        _footnote(fig, [f"{first.size - x.size} of {first.size} queries dropped: non-finite PSNR in either method."])
    return _save(fig, path)


def plot_gaussian_counts(
    per_light: np.ndarray, path, *, per_query: np.ndarray | None = None, title: str | None = None,
    none_kept: str = "no Gaussians kept",
) -> Path:
    """Histogram of the number of Gaussians per light, optionally beside the count per interpolated query.

    Integer bins (one per count, centred on it) on an x axis from 0 to the largest count + 1 with
    integer ticks; the mean, median and maximum are drawn as lines and given in the legend. When every
    light's count is 0 the title says so (``none_kept``) and a panel of zeros draws no lines.

    Args:
        per_light: 1-D count of Gaussians in each light's estimated set (non-negative integers).
        path: Target ``.png`` file; missing parent folders are made.
        per_query: Optional 1-D count of active Gaussians in each interpolated query set; drawn as a
            second panel.
        title: Figure title; a default describes the plot.
        none_kept: What the title adds when every per-light count is 0 (e.g. where the highlights went).

    Returns:
        The path of the written PNG.

    Raises:
        InputError: Counts that are not a non-empty 1-D array of non-negative integers, or a target
            that is not a ``.png`` file.
    """
    where = "plot_gaussian_counts"
    path = _checked_png_path(where, path)
    panels = [(_checked_counts(where, "per_light", per_light), "Gaussians per light", "lights",
               "Estimated sets (one per light)")]
    if per_query is not None:
        panels.append((_checked_counts(where, "per_query", per_query), "active Gaussians per query", "queries",
                       "Interpolated sets (one per query)"))

    fig = _new_figure(_WIDTH_IN, 4.6)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (counts, xlabel, ylabel, heading) in zip(axes, panels, strict=True):
        _count_histogram(ax, counts)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"number of {ylabel}")
        ax.set_title(f"{heading}: {counts.size} {ylabel}", fontsize=10)
    heading = title or "Gaussians per set"
    fig.suptitle(f"{heading}\n{none_kept}" if panels[0][0].max() == 0 else heading)
    return _save(fig, path)


def plot_barycentric_psnr(
    barycentric: np.ndarray,
    scores: Mapping[str, np.ndarray],
    path,
    *,
    corner_labels: Sequence[str] = ("A", "B", "C"),
    title: str | None = None,
) -> Path:
    """PSNR over the barycentric coordinates of one interpolation triangle (thesis Fig. 4.12).

    The query points are mapped onto an equilateral triangle (:func:`barycentric_to_plane`) and each
    method's PSNR is shaded over their Delaunay triangulation (points drawn as dots; a scatter when
    fewer than three distinct, non-collinear points remain). The method panels share one colour scale.
    When both ``"circular"`` and ``"alpha"`` are given, a last panel shows ``circular - alpha`` on a
    diverging scale centred on 0 (blue: circular better). A star marks each panel's minimum.
    Non-finite values are dropped and counted in the footnote.

    Args:
        barycentric: ``(K, 3)`` weights (lA, lB, lC) of the query points; rows sum to 1.
        scores: Method name -> ``(K,)`` PSNR in dB at those points.
        path: Target ``.png`` file; missing parent folders are made.
        corner_labels: Names of the corners A, B, C (e.g. light names).
        title: Figure title; a default describes the plot.

    Returns:
        The path of the written PNG.

    Raises:
        InputError: Bad weights, an empty mapping, score arrays whose length is not K, three corner
            labels not given, or a target that is not a ``.png`` file.
    """
    where = "plot_barycentric_psnr"
    path = _checked_png_path(where, path)
    points = barycentric_to_plane(_checked_barycentric(where, barycentric))
    scores = _checked_scores(where, scores)
    for name, values in scores.items():
        if values.size != len(points):
            raise InputError(f"{where}: scores[{name!r}] has {values.size} values for {len(points)} barycentric "
                             "points; pass one PSNR per point")
    if isinstance(corner_labels, str) or len(corner_labels) != 3:
        raise InputError(f"{where}: corner_labels must be three names (A, B, C), got {corner_labels!r}")
    panels = list(scores.items())
    with_difference = "circular" in scores and "alpha" in scores
    if with_difference:
        panels.append(("circular - alpha", scores["circular"] - scores["alpha"]))

    everything = np.concatenate([_finite(values) for values in scores.values()])
    low, high = (float(everything.min()), float(everything.max())) if everything.size else (0.0, 1.0)
    if high - low < 1e-6:
        low, high = low - 0.5, high + 0.5
    width = max(_WIDTH_IN, 3.0 * len(panels) + 0.8)
    fig = _new_figure(width, 2.2 + 0.75 * min(width / len(panels), 5.0), layout="compressed")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    method_mappable = difference_mappable = None
    for index, (ax, (name, values)) in enumerate(zip(axes, panels, strict=True)):
        difference = with_difference and index == len(panels) - 1
        if difference:
            finite = values[np.isfinite(values)]
            bound = float(np.abs(finite).max()) if finite.size else 1.0
            bound = bound if bound > 1e-6 else 1.0
            style = {"cmap": "RdBu", "vmin": -bound, "vmax": bound}
        else:
            style = {"cmap": "viridis", "vmin": low, "vmax": high}
        mappable = _triangle_panel(ax, points, values, name, corner_labels, style, unit_sign=difference)
        if difference:
            difference_mappable = mappable or difference_mappable
        else:
            method_mappable = mappable or method_mappable
    method_axes = axes[: len(scores)]
    if method_mappable is not None:
        fig.colorbar(method_mappable, ax=list(method_axes), location="bottom", shrink=0.6, aspect=40,
                     label="PSNR (dB)")
    if difference_mappable is not None:
        fig.colorbar(difference_mappable, ax=axes[-1], location="bottom", shrink=0.9, aspect=20,
                     label="PSNR difference (dB)")
    fig.suptitle(title or f"PSNR at barycentric coordinates of the interpolation triangle ({len(points)} points)")

    notes = []
    dropped = {name: int(np.count_nonzero(~np.isfinite(values))) for name, values in scores.items()}
    if any(dropped.values()):
        counts = ", ".join(f"{name} {count}" for name, count in dropped.items() if count)
        notes.append(f"Non-finite PSNR values dropped: {counts}.")
    if with_difference:
        notes.append("circular - alpha > 0 (blue): circular closer to ground truth.")
    _footnote(fig, notes)
    return _save(fig, path)


def plot_image_grid(
    images: Sequence[np.ndarray], labels: Sequence[str], path, *, columns: int = 4, title: str | None = None,
    blank_notes: Sequence[str | None] | None = None,
) -> Path:
    """A grid of linear images shown sRGB-encoded, e.g. "truth / circular / straight / alpha".

    Values are clipped to [0, 1] (NaN shown as black) and encoded by :func:`images.display_rgb8`,
    so the figure shows them as an 8-bit sRGB PNG of the image would. A panel whose displayed image
    is one flat value and that has a note in ``blank_notes`` shows the note (on light grey, framed)
    instead of a flat square.

    Args:
        images: Linear float images, each ``(H, W)`` (grey) or ``(H, W, 3)`` (RGB); sizes may differ.
        labels: One caption per image ("\n" breaks it into lines); the font shrinks so that the
            longest line fits its panel.
        path: Target ``.png`` file; missing parent folders are made.
        columns: Images per row.
        title: Figure title; none by default.
        blank_notes: None, or one entry per image: what to write in its panel when the image shows as
            one flat value (e.g. why a method's highlights are empty), or None to draw it anyway.

    Returns:
        The path of the written PNG.

    Raises:
        InputError: No images, a label or note count different from the image count, an image of
            another shape, ``columns`` < 1, or a target that is not a ``.png`` file.
    """
    where = "plot_image_grid"
    path = _checked_png_path(where, path)
    images = [_checked_display_image(where, index, image) for index, image in enumerate(images)]
    labels = [str(label) for label in labels]
    if not images:
        raise InputError(f"{where}: no images given; pass at least one")
    if len(labels) != len(images):
        raise InputError(f"{where}: {len(images)} images but {len(labels)} labels; pass one label per image")
    notes = [None] * len(images) if blank_notes is None else [None if n is None else str(n) for n in blank_notes]
    if isinstance(blank_notes, str) or len(notes) != len(images):
        raise InputError(f"{where}: {len(images)} images but {len(notes)} blank notes; pass one note (or None) "
                         "per image")
    if isinstance(columns, bool) or not isinstance(columns, (int, np.integer)) or columns < 1:
        raise InputError(f"{where}: columns must be an integer >= 1, got {columns!r}")

    cols = min(int(columns), len(images))
    rows = math.ceil(len(images) / cols)
    aspect = max(image.shape[0] / image.shape[1] for image in images)
    panel_width = _WIDTH_IN / cols
    fontsize = caption_fontsize(labels, panel_width)
    caption = max(label.count("\n") + 1 for label in labels) * fontsize * 1.3 / 72.0 + 0.1
    height = rows * (panel_width * aspect + caption) + (0.45 if title else 0.1)
    fig = _new_figure(_WIDTH_IN, min(height, 40.0), layout="compressed")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes:
        ax.set_axis_off()
    for ax, image, label, note in zip(axes, images, labels, notes, strict=False):
        shown = display_rgb8(image)
        if note is not None and shown.min() == shown.max():
            _note_panel(ax, note, image.shape[0] / image.shape[1], panel_width)
        else:
            ax.imshow(shown, interpolation="nearest")
        ax.set_title(label, fontsize=fontsize)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def caption_fontsize(labels: Sequence[str], panel_width_in: float, *, largest: float = 10.0) -> float:
    """Font size (points) at which the longest line of ``labels`` fits ``panel_width_in`` inches, at most
    ``largest``."""
    longest = max((len(line) for label in labels for line in str(label).split("\n")), default=1)
    return min(largest, panel_width_in * 72.0 / (_CHAR_WIDTH_EM * max(longest, 1)))


# --- helper functions --------------------------------------------------------------------------


def _new_figure(width_in: float, height_in: float, *, layout: str = "constrained"):
    """A headless figure on its own Agg canvas at the report's DPI.

    ``layout="compressed"`` packs grids of fixed-aspect axes (triangles, images) without gaps.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=_DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically (temporary file beside it, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI, facecolor="white")
    return path


def _footnote(fig, lines: Sequence[str]) -> None:
    """Small left-aligned notes under the plot; the layout leaves room for them."""
    if not lines:
        return
    import textwrap

    characters = int(0.97 * fig.get_figwidth() * 72.0 / (_CHAR_WIDTH_EM * _FOOTNOTE_PT))
    lines = [wrapped for line in lines for wrapped in textwrap.wrap(line, characters, subsequent_indent="  ")]
    height_pt = fig.get_figheight() * 72.0
    share = min(0.3, (len(lines) * _FOOTNOTE_PT * 1.4 + 8.0) / height_pt)
    fig.get_layout_engine().set(rect=(0.0, share, 1.0, 1.0 - share))
    fig.text(0.01, 0.01, "\n".join(lines), ha="left", va="bottom", fontsize=_FOOTNOTE_PT, color="0.25")


def _checked_png_path(where: str, path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"{where}: {path}: figures are written as PNG; give a path ending in .png")
    return path


def _checked_vector(where: str, name: str, values) -> np.ndarray:
    try:
        values = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {name} is not an array of numbers ({exc})") from exc
    if values.ndim != 1:
        raise InputError(f"{where}: {name} has shape {values.shape}; expected a 1-D array (one value per query)")
    return values


def _checked_scores(where: str, scores) -> dict[str, np.ndarray]:
    if not isinstance(scores, Mapping) or not scores:
        raise InputError(f"{where}: scores must be a non-empty mapping of method name -> PSNR array, "
                         f"got {type(scores).__name__}{'' if scores else ' (empty)'}")
    return {str(name): _checked_vector(where, f"scores[{name!r}]", values) for name, values in scores.items()}


def _checked_counts(where: str, name: str, counts) -> np.ndarray:
    values = _checked_vector(where, name, counts)
    if values.size == 0:
        raise InputError(f"{where}: {name} is empty; pass one Gaussian count per set")
    if not np.all(np.isfinite(values)) or np.any(values < 0) or np.any(values != np.rint(values)):
        raise InputError(f"{where}: {name} must hold non-negative integer Gaussian counts")
    return values.astype(np.int64)


def _checked_barycentric(where: str, barycentric) -> np.ndarray:
    try:
        weights = np.asarray(barycentric, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: barycentric is not an array of numbers ({exc})") from exc
    if weights.ndim != 2 or weights.shape[1] != 3 or weights.shape[0] == 0:
        raise InputError(f"{where}: barycentric has shape {weights.shape}; expected (K, 3) weights with K >= 1")
    if not np.all(np.isfinite(weights)):
        raise InputError(f"{where}: barycentric holds NaN or infinite weights")
    worst = int(np.argmax(np.abs(weights.sum(axis=1) - 1.0)))
    if abs(weights[worst].sum() - 1.0) > 1e-3:
        raise InputError(f"{where}: barycentric row {worst} sums to {weights[worst].sum():.6g}; each row of "
                         "weights must sum to 1")
    return weights


def _checked_display_image(where: str, index: int, image) -> np.ndarray:
    try:
        array = np.asarray(image, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: images[{index}] is not an array of numbers ({exc})") from exc
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or 0 in array.shape:
        raise InputError(f"{where}: images[{index}] has shape {array.shape}; expected (H, W) or (H, W, 3)")
    return array


def _finite(values: np.ndarray) -> np.ndarray:
    return values[np.isfinite(values)]


def _summary(values: np.ndarray) -> dict[str, float]:
    """Mean and 5th / 95th percentiles of a non-empty array."""
    p5, p95 = np.percentile(values, [5.0, 95.0])
    return {"mean": float(np.mean(values)), "p5": float(p5), "p95": float(p95)}


def _summary_text(stats: Mapping[str, float], unit: str = "dB", *, stacked: bool = False) -> str:
    """Two lines: the mean, then the 5th and 95th percentiles (``stacked``: each percentile on its own line)."""
    between = "\n" if stacked else "  "
    return f"mean {stats['mean']:.1f} {unit}\n5%: {stats['p5']:.1f}{between}95%: {stats['p95']:.1f}"


def _pair_caption(first: np.ndarray, second: np.ndarray, first_name: str) -> str:
    """"circular better on 90% of 496": share of queries (both values finite) where ``first`` is higher."""
    keep = np.isfinite(first) & np.isfinite(second)
    total = int(np.count_nonzero(keep))
    if total == 0:
        return "no comparable queries"
    better = int(np.count_nonzero(first[keep] > second[keep]))
    return f"{first_name} better on {100.0 * better / total:.0f}% of {total}"


def _method_colour(name: str, index: int) -> str:
    return _METHOD_COLOURS.get(name, _OTHER_COLOURS[index % len(_OTHER_COLOURS)])


def _distribution_legend_handles() -> list:
    from matplotlib.lines import Line2D

    return [
        Line2D([], [], marker="D", linestyle="none", markerfacecolor="white", markeredgecolor="black",
               label="mean"),
        Line2D([], [], color="black", linewidth=2.5, label="5th - 95th percentile"),
    ]


def _count_histogram(ax, counts: np.ndarray) -> None:
    """Integer-bin histogram of ``counts`` on 0 .. max + 1, with mean, median and maximum lines (none
    when every count is 0: they would all lie on the one bar)."""
    from matplotlib.ticker import MaxNLocator

    high = int(counts.max())
    bins = np.arange(-0.5, high + 1.5)  # one bin per count 0 .. max, centred on it
    ax.hist(counts, bins=bins, color="#1f77b4", alpha=0.8, edgecolor="white" if len(bins) <= 80 else "none",
            linewidth=0.6)
    if high > 0:
        mean, median = float(counts.mean()), float(np.median(counts))
        ax.axvline(mean, color="black", linestyle="--", linewidth=1.2, label=f"mean {mean:.1f}")
        ax.axvline(median, color="#ff7f0e", linestyle=":", linewidth=1.8, label=f"median {median:g}")
        ax.axvline(high, color="#d62728", linestyle="-.", linewidth=1.2, label=f"max {high}")
        ax.legend(loc="upper left", fontsize=8.5, framealpha=0.9)
        ax.set_ylim(0, ax.get_ylim()[1] * 1.2)  # head room for the legend
    ax.set_xlim(-0.5, high + 1.5)  # counts 0 .. max + 1, each bar whole
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(axis="y", alpha=0.3)


def _note_panel(ax, note: str, aspect: float, panel_width_in: float) -> None:
    """``note`` written, wrapped to the panel, on a light grey framed panel of the image's aspect
    (height / width) in place of an image that would show one flat value."""
    import textwrap

    from matplotlib.patches import Rectangle

    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_box_aspect(aspect)
    ax.add_patch(Rectangle((0.0, 0.0), 1.0, 1.0, transform=ax.transAxes, facecolor="0.93", edgecolor="0.6",
                           linewidth=0.8, clip_on=False))
    width_pt, height_pt = 0.85 * panel_width_in * 72.0, 0.85 * panel_width_in * aspect * 72.0
    for size in (9.0, 8.0, 7.0, 6.0, 5.0):  # the largest font at which the wrapped note fits the panel
        text = textwrap.fill(note, max(8, int(width_pt / (_CHAR_WIDTH_EM * size))))
        if (text.count("\n") + 1) * size * 1.25 <= height_pt:
            break
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=size, color="0.2",
            style="italic", linespacing=1.25)


def _triangle_panel(ax, points, values, name, corner_labels, style, *, unit_sign: bool):
    """Shade ``values`` at ``points`` inside the unit triangle; return the colour mappable (None if empty)."""
    from matplotlib.tri import Triangulation

    ax.plot(*np.vstack([_CORNERS, _CORNERS[:1]]).T, color="black", linewidth=1)
    offsets = (((0.0, -0.04), "center", "top"), ((0.0, -0.04), "center", "top"), ((0.0, 0.04), "center", "bottom"))
    for corner, label, ((dx, dy), ha, va) in zip(_CORNERS, corner_labels, offsets, strict=True):
        ax.text(corner[0] + dx, corner[1] + dy, str(label), ha=ha, va=va, fontsize=10, fontweight="bold")
    ax.set_xlim(-0.2, 1.2)
    ax.set_ylim(-0.14, _SQRT3_2 + 0.12)
    ax.set_aspect("equal")
    ax.set_axis_off()

    keep = np.isfinite(values)
    if not keep.any():
        ax.set_title(f"{name}\nno finite values", fontsize=10)
        return None
    xy, shown = _merge_duplicates(points[keep], values[keep])
    mappable = None
    if len(xy) >= 3:
        try:
            mappable = ax.tripcolor(Triangulation(xy[:, 0], xy[:, 1]), shown, shading="gouraud", **style)
        except (RuntimeError, ValueError):  # collinear points: qhull cannot triangulate
            mappable = None
    if mappable is None:
        mappable = ax.scatter(xy[:, 0], xy[:, 1], c=shown, s=90, edgecolor="black", linewidth=0.4, **style)
    else:
        ax.scatter(xy[:, 0], xy[:, 1], s=3, color="black", alpha=0.35, linewidth=0)
    worst = int(np.argmin(shown))
    ax.scatter([xy[worst, 0]], [xy[worst, 1]], marker="*", s=200, facecolor="none", edgecolor="red",
               linewidth=1.3, zorder=5)
    sign = "+" if unit_sign else ""
    ax.set_title(f"{name}\nmean {np.mean(shown):{sign}.1f} dB, min {shown[worst]:{sign}.1f} dB (star)", fontsize=10)
    return mappable


def _merge_duplicates(xy: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Average the values of points that coincide (to 1e-9), which Delaunay triangulation would skip."""
    keys = np.round(xy / 1e-9).astype(np.int64)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    if len(unique) == len(xy):
        return xy, values
    sums = np.zeros(len(unique))
    np.add.at(sums, inverse, values)
    merged_xy = np.zeros((len(unique), 2))
    np.add.at(merged_xy, inverse, xy)
    counts = np.bincount(inverse, minlength=len(unique))
    return merged_xy / counts[:, None], sums / counts
