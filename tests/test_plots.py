"""Evaluation figures: PNGs that open, have content, are written atomically, and clean input errors."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from conftest import panel_pixels
from warp_highlights.model.errors import InputError
from warp_highlights.view import plots

pytest.importorskip("matplotlib")
Image = pytest.importorskip("PIL.Image")

METHODS = ("circular", "straight", "alpha")


def _png(path, *, min_width=900, min_height=300) -> np.ndarray:
    """Open ``path`` with Pillow, check it is a sizeable PNG with real content; return its RGB pixels."""
    with Image.open(path) as im:
        assert im.format == "PNG"
        width, height = im.size
        pixels = np.asarray(im.convert("RGB"))
    assert min_width <= width <= 1600
    assert min_height <= height <= 1600
    packed = pixels.astype(np.uint32) @ np.array([1 << 16, 1 << 8, 1], dtype=np.uint32)
    assert len(np.unique(packed)) > 20  # anti-aliased text, lines and fills, not a blank canvas
    return pixels


def _only_file(path) -> None:
    """The folder holds the figure and nothing else: no temporary file left behind."""
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


@pytest.fixture
def scores():
    rng = np.random.default_rng(0)
    base = rng.normal(34.0, 4.0, 60)
    return {name: base + rng.normal(shift, 1.0, 60) for name, shift in zip(METHODS, (2.0, 0.5, 0.0), strict=True)}


@pytest.fixture
def barycentric():
    rng = np.random.default_rng(1)
    weights = rng.dirichlet(np.ones(3), 30)
    weights[:4] = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1 / 3, 1 / 3, 1 / 3]]
    return weights


# --- barycentric mapping ---------------------------------------------------------------------------


def test_barycentric_to_plane_corners_centroid_and_edge_midpoint():
    weights = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0]]
    expected = [[0, 0], [1, 0], [0.5, np.sqrt(3) / 2], [0.5, np.sqrt(3) / 6], [0.5, 0.0]]
    np.testing.assert_allclose(plots.barycentric_to_plane(weights), expected, atol=1e-12)


def test_barycentric_to_plane_keeps_distances_of_a_unit_equilateral_triangle():
    a, b, c = plots.barycentric_to_plane(np.eye(3))
    assert [np.linalg.norm(a - b), np.linalg.norm(b - c), np.linalg.norm(c - a)] == pytest.approx([1, 1, 1])


@pytest.mark.parametrize(
    "weights", [np.ones(3) / 3, np.ones((4, 2)) / 2, np.zeros((0, 3)), [[0.5, 0.5, 0.5]], [[np.nan, 0.5, 0.5]]]
)
def test_barycentric_to_plane_rejects_bad_weights(weights):
    with pytest.raises(InputError, match="barycentric"):
        plots.barycentric_to_plane(weights)


# --- each figure ----------------------------------------------------------------------------------


def test_psnr_distributions(tmp_path, scores):
    path = tmp_path / "report" / "psnr.png"  # the missing folder is made
    assert plots.plot_psnr_distributions(scores, path, title="Donut, 256 lights", excluded=3) == path
    _png(path)
    _only_file(path)


def test_psnr_distributions_survives_nan_only_single_value_and_empty_methods(tmp_path, scores):
    lonely = {
        "circular": np.concatenate([scores["circular"], [np.nan, np.inf, -np.inf]]),
        "straight": np.full(10, np.nan),  # no finite value at all: an empty slot
        "alpha": np.array([31.0]),  # one value: no kernel density possible
        "constant": np.full(5, 40.0),  # no spread: no kernel density possible
        "empty": np.zeros(0),
    }
    _png(plots.plot_psnr_distributions(lonely, tmp_path / "psnr.png"))
    _png(plots.plot_psnr_distributions({"straight": np.full(4, np.nan)}, tmp_path / "nan.png"))


def test_psnr_pairs(tmp_path, scores):
    first = scores["circular"].copy()
    first[:2] = np.nan
    path = plots.plot_psnr_pairs(first, scores["alpha"], tmp_path / "pairs.png")
    _png(path)
    _png(plots.plot_psnr_pairs(np.full(3, np.nan), np.ones(3), tmp_path / "no_pairs.png"))


def test_pair_caption_counts_strictly_better_queries_among_finite_pairs():
    first = np.array([30.0, 31.0, 20.0, 25.0, np.nan, 40.0])
    second = np.array([29.0, 30.0, 21.0, 25.0, 10.0, np.inf])
    # finite pairs: 4; first strictly higher on 2 (the tie does not count)
    assert plots._pair_caption(first, second, "circular") == "circular better on 50% of 4"
    assert plots._pair_caption(np.full(2, np.nan), np.ones(2), "circular") == "no comparable queries"


def test_gaussian_counts(tmp_path):
    rng = np.random.default_rng(2)
    per_light = rng.poisson(24, 256)
    _png(plots.plot_gaussian_counts(per_light, tmp_path / "one.png"))
    # float arrays holding whole numbers are counts too
    _png(plots.plot_gaussian_counts(per_light.astype(np.float32), tmp_path / "two.png", per_query=rng.poisson(30, 500)))
    _png(plots.plot_gaussian_counts(np.array([7]), tmp_path / "single.png", title="one light"))


def _visible_ticks(axis_ax) -> np.ndarray:
    low, high = axis_ax.get_xlim()
    ticks = np.asarray(axis_ax.get_xticks())
    return ticks[(ticks >= low) & (ticks <= high)]


@pytest.mark.parametrize("counts", [np.array([9, 12, 12, 17, 41]), np.array([3]), np.zeros(43, int)])
def test_gaussian_count_axes_run_from_zero_to_the_largest_count_plus_one(tmp_path, drawn_figures, counts):
    """Counts are integers >= 0: the x axis covers 0 .. max + 1 (half a bar either side, so every bar is
    whole), with integer ticks, none negative; nothing is drawn left of 0."""
    plots.plot_gaussian_counts(counts, tmp_path / "counts.png", per_query=counts[:3])
    figure = drawn_figures["counts.png"]
    for ax in figure.axes:
        top = int(ax.get_xlim()[1] - 0.5)
        assert ax.get_xlim() == pytest.approx((-0.5, top + 0.5))
        assert top in (counts.max() + 1, counts[:3].max() + 1)
        ticks = _visible_ticks(ax)
        assert len(ticks) >= 2 and ticks.min() == 0 and np.all(ticks == np.round(ticks))
        bars = [patch for patch in ax.patches if patch.get_height() > 0]
        assert min(bar.get_x() for bar in bars) >= -0.5
        assert sum(bar.get_height() for bar in bars) == len(counts if ax is figure.axes[0] else counts[:3])


def test_gaussian_counts_say_when_none_is_kept(tmp_path, drawn_figures):
    note = "no Gaussians kept: every light's highlights are in the residual"
    plots.plot_gaussian_counts(np.zeros(43), tmp_path / "none.png", per_query=np.zeros(11), title="statue",
                               none_kept=note)
    figure = drawn_figures["none.png"]
    assert figure.get_suptitle() == f"statue\n{note}"
    for ax in figure.axes:
        assert ax.get_xlim() == pytest.approx((-0.5, 1.5))
        assert not ax.lines  # no mean, median and maximum lines piled on the one bar
    _png(tmp_path / "none.png")
    plots.plot_gaussian_counts(np.array([0, 4, 2]), tmp_path / "some.png", title="donut", none_kept=note)
    assert drawn_figures["some.png"].get_suptitle() == "donut"
    assert len(drawn_figures["some.png"].axes[0].lines) == 3


def test_barycentric_psnr_with_difference_panel(tmp_path, barycentric, scores):
    points = plots.barycentric_to_plane(barycentric)
    distance = np.linalg.norm(points - [0.5, 0.3], axis=1)
    per_point = {name: 40.0 - (8.0 + 6.0 * i) * distance for i, name in enumerate(METHODS)}
    per_point["straight"][5] = np.nan
    path = plots.plot_barycentric_psnr(barycentric, per_point, tmp_path / "tri.png", corner_labels=("L1", "L7", "L9"))
    pixels = _png(path)
    # the difference panel uses a diverging red/blue map: strongly blue pixels must be present
    red, green, blue = (pixels[..., i].astype(int) for i in range(3))
    assert np.count_nonzero((blue - red > 80) & (blue - green > 30)) > 100


def test_barycentric_psnr_falls_back_to_points_and_survives_nan(tmp_path):
    weights = np.array([[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0]])
    _png(plots.plot_barycentric_psnr(weights, {"circular": np.array([30.0, 32.0])}, tmp_path / "two.png"))
    collinear = np.array([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0]])  # with a duplicate
    nan_only = {"circular": np.arange(4.0), "alpha": np.full(4, np.nan)}
    _png(plots.plot_barycentric_psnr(collinear, nan_only, tmp_path / "line.png"))


def test_image_grid_shows_images_srgb_encoded_and_clipped(tmp_path):
    # one uniform image per figure: the figure's centre lies inside the image
    grey = plots.plot_image_grid([np.full((40, 40), 0.21404114)], ["grey"], tmp_path / "grey.png", columns=1)
    pixels = _png(grey, min_height=100)
    centre = pixels[pixels.shape[0] // 2, pixels.shape[1] // 2]
    np.testing.assert_allclose(centre, [128, 128, 128], atol=2)  # linear 0.214 -> sRGB 0.5

    over = np.full((40, 40, 3), [5.0, np.nan, 0.0])  # over-range -> 1, NaN -> 0
    pixels = _png(plots.plot_image_grid([over], ["over"], tmp_path / "over.png", columns=1), min_height=100)
    np.testing.assert_allclose(pixels[pixels.shape[0] // 2, pixels.shape[1] // 2], [255, 0, 0], atol=1)


def test_image_grid_of_comparisons(tmp_path):
    rng = np.random.default_rng(3)
    images = [rng.random((24, 32)) for _ in range(4)] + [rng.random((24, 32, 3)), rng.random((24, 32, 1))]
    labels = ["truth", "circular", "straight", "alpha", "rgb", "one channel"]
    _png(plots.plot_image_grid(images, labels, tmp_path / "grid.png", columns=4, title="query 3"))


def test_a_blank_panel_with_a_note_says_it_and_is_never_a_flat_square(tmp_path, drawn_figures):
    """A panel whose image shows as one flat value writes its note instead (text on a framed panel); an image
    with content is drawn even when it has a note; without a note a flat image is drawn as it is."""
    rng = np.random.default_rng(4)
    images = [np.zeros((30, 40)), rng.random((30, 40)) * 0.5, np.full((30, 40), 1e-6), np.zeros((30, 40))]
    labels = ["#0 circular", "#0 alpha", "#1 circular", "#1 flat, no note"]
    notes = ["the field moves no highlights", "never shown", "no highlight at this light", None]
    path = plots.plot_image_grid(images, labels, tmp_path / "grid.png", columns=2, blank_notes=notes)
    figure = drawn_figures["grid.png"]
    panels = dict(panel_pixels(figure, path))
    axes = {ax.get_title(): ax for ax in figure.axes}
    for label in ("#0 circular", "#1 circular"):
        assert [t.get_text().replace("\n", " ") for t in axes[label].texts] == [notes[labels.index(label)]]
        assert not axes[label].images and np.ptp(panels[label]) > 100  # dark text on light grey
    assert axes["#0 alpha"].images and not axes["#0 alpha"].texts and np.ptp(panels["#0 alpha"]) > 0
    assert axes["#1 flat, no note"].images and np.ptp(panels["#1 flat, no note"]) == 0
    with pytest.raises(InputError, match="4 images but 1 blank notes"):
        plots.plot_image_grid(images, labels, tmp_path / "bad.png", blank_notes=["one"])


def test_statistics_boxes_of_many_methods_stay_apart(tmp_path, drawn_figures, scores):
    """Seven methods (three of the field's, four baselines): no two statistics boxes overlap."""
    many = {**scores, **{name: scores["alpha"] - 3.0 for name in ("ptm", "hsh2", "hsh3", "rbf")}}
    plots.plot_psnr_distributions(many, tmp_path / "psnr.png", notes=["what each method's images are"])
    figure = drawn_figures["psnr.png"]
    boxes = sorted((text.get_bbox_patch().get_window_extent() for text in figure.axes[0].texts),
                   key=lambda box: box.x0)
    assert len(boxes) == 7
    assert all(left.x1 < right.x0 for left, right in zip(boxes, boxes[1:], strict=False))
    assert "what each method's images are" in figure.texts[-1].get_text()


def test_captions_of_a_wide_grid_fit_their_panels(tmp_path):
    """The worst-lights grid has 8 panels a row: every caption line, drawn at the chosen size, is
    narrower than its panel (measured with matplotlib's own text layout)."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextPath

    labels = [f"#{i} {key}\n{20 + i:.1f} dB" for i in range(3)
              for key in ("truth", "circular", "straight", "alpha", "ptm", "hsh2", "hsh3", "rbf")]
    panel = plots._WIDTH_IN / 8
    size = plots.caption_fontsize(labels, panel)
    assert 4.0 < size <= 10.0
    widest = max(TextPath((0, 0), line, size=size, prop=FontProperties(family="DejaVu Sans")).get_extents().width
                 for label in labels for line in label.split("\n"))
    assert widest <= panel * 72.0, (widest, panel * 72.0)
    assert plots.caption_fontsize(["a"], panel) == 10.0  # short captions keep the full size
    _png(plots.plot_image_grid([np.full((20, 30), 0.5)] * len(labels), labels, tmp_path / "wide.png", columns=8,
                               title="worst"))


# --- atomic writes --------------------------------------------------------------------------------


def test_an_existing_figure_is_replaced_on_success(tmp_path, scores):
    path = tmp_path / "psnr.png"
    path.write_bytes(b"old figure")
    plots.plot_psnr_pairs(scores["circular"], scores["alpha"], path)
    _png(path)
    _only_file(path)


def test_a_failed_write_keeps_the_old_figure_and_leaves_no_temp_file(tmp_path, scores, monkeypatch):
    from matplotlib.figure import Figure

    def broken_savefig(self, target, **kwargs):
        with open(target, "wb") as f:
            f.write(b"half a PNG")
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken_savefig)
    path = tmp_path / "psnr.png"
    path.write_bytes(b"old figure")
    with pytest.raises(RuntimeError, match="disk full"):
        plots.plot_psnr_distributions(scores, path)
    assert path.read_bytes() == b"old figure"
    _only_file(path)


def test_bad_input_writes_nothing(tmp_path):
    path = tmp_path / "psnr.png"
    path.write_bytes(b"old figure")
    with pytest.raises(InputError):
        plots.plot_psnr_distributions({}, path)
    assert path.read_bytes() == b"old figure"
    _only_file(path)


# --- input errors ---------------------------------------------------------------------------------


def _one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message and message
    return message


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda p: plots.plot_psnr_distributions({}, p), "non-empty mapping"),
        (lambda p: plots.plot_psnr_distributions([np.ones(3)], p), "mapping"),
        (lambda p: plots.plot_psnr_distributions({"alpha": np.ones((3, 2))}, p), r"scores\['alpha'\].*\(3, 2\)"),
        (lambda p: plots.plot_psnr_distributions({"alpha": np.ones(3)}, p, excluded=-1), "excluded"),
        (lambda p: plots.plot_psnr_distributions({"alpha": ["a", "b"]}, p), "not an array of numbers"),
        (lambda p: plots.plot_psnr_pairs(np.ones(3), np.ones(4), p), "3 values but second has 4"),
        (lambda p: plots.plot_psnr_pairs(np.ones((2, 2)), np.ones((2, 2)), p), "1-D"),
        (lambda p: plots.plot_psnr_pairs(np.ones(0), np.ones(0), p), "empty"),
        (lambda p: plots.plot_gaussian_counts(np.array([3, -1]), p), "non-negative integer"),
        (lambda p: plots.plot_gaussian_counts(np.array([3.5, 2.0]), p), "non-negative integer"),
        (lambda p: plots.plot_gaussian_counts(np.zeros(0), p), "empty"),
        (lambda p: plots.plot_gaussian_counts(np.ones(4), p, per_query=np.ones((2, 2))), "per_query"),
        (lambda p: plots.plot_barycentric_psnr(np.eye(3), {"alpha": np.ones(4)}, p), "4 values for 3"),
        (lambda p: plots.plot_barycentric_psnr(np.eye(3), {}, p), "non-empty mapping"),
        (lambda p: plots.plot_barycentric_psnr(np.eye(3)[:, :2], {"alpha": np.ones(3)}, p), r"\(3, 2\)"),
        (lambda p: plots.plot_barycentric_psnr(np.eye(3), {"alpha": np.ones(3)}, p, corner_labels="AB"), "corner"),
        (lambda p: plots.plot_image_grid([], [], p), "no images"),
        (lambda p: plots.plot_image_grid([np.ones((4, 4))], ["a", "b"], p), "1 images but 2 labels"),
        (lambda p: plots.plot_image_grid([np.ones((4, 4, 2))], ["a"], p), r"images\[0\].*\(4, 4, 2\)"),
        (lambda p: plots.plot_image_grid([np.ones((4, 4))], ["a"], p, columns=0), "columns"),
        (lambda p: plots.plot_psnr_pairs(np.ones(3), np.ones(3), p.with_suffix(".jpg")), r"\.png"),
    ],
)
def test_bad_inputs_raise_one_line_input_errors(tmp_path, call, match):
    with pytest.raises(InputError, match=match) as excinfo:
        call(tmp_path / "figure.png")
    _one_line(excinfo)
    assert not any(tmp_path.iterdir())


# --- headless, thread-safe, light import -----------------------------------------------------------


def test_figures_from_several_threads(tmp_path, scores):
    targets = [tmp_path / f"pairs{i}.png" for i in range(3)]
    with ThreadPoolExecutor(max_workers=3) as pool:
        futures = [pool.submit(plots.plot_psnr_pairs, scores["circular"], scores["alpha"], t) for t in targets]
        written = [future.result() for future in futures]  # re-raises an error from any thread
    assert written == targets
    for target in targets:
        _png(target)


def test_import_needs_no_matplotlib_and_plotting_never_touches_pyplot(tmp_path):
    script = (
        "import sys, numpy as np\n"
        "import warp_highlights.view.plots as plots\n"
        "assert 'matplotlib' not in sys.modules, 'imported matplotlib at module level'\n"
        f"plots.plot_gaussian_counts(np.arange(5), {str(tmp_path / 'c.png')!r})\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'used pyplot'\n"
    )
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, env=env,
                            timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "c.png").is_file()
