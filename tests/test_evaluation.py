"""Evaluation against held-out ground truth (docs/method.md, Evaluation): PSNR, statistics, the barycentric sweep."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from conftest import panel_pixels
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.fieldfile import load_field
from warp_highlights.model.errors import InputError
from warp_highlights.model.lights import LightSet
from warp_highlights.relight.evaluation import (
    Evaluation,
    barycentric_grid,
    evaluate_field,
    luminance,
    psnr_excluding_black,
    summarize,
    win_share,
)
from warp_highlights.relight.relighter import Relighter, alpha_inputs

REC709 = np.array([0.2126, 0.7152, 0.0722])


# --- PSNR and statistics ---------------------------------------------------------------------------


def test_psnr_of_a_known_mse():
    truth = np.zeros((2, 4, 5))
    images = np.zeros((2, 4, 5))
    images[0, 0, :] = 0.5  # 5 of 20 pixels off by 0.5: mse = 0.25 * 5 / 20
    truth[1] = 0.25
    images[1] = 0.35  # every pixel off by 0.1: mse = 0.01
    psnr = psnr_excluding_black(images, truth)
    assert psnr.shape == (2,)
    assert psnr[0] == pytest.approx(10 * math.log10(1 / 0.0625))
    assert psnr[1] == pytest.approx(20.0)


def test_psnr_works_on_colour_stacks_and_both_orders():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.0, 1.0, (3, 6, 7, 3))
    images = np.clip(truth + rng.normal(0.0, 0.05, truth.shape), 0.0, 1.0)
    mse = ((images - truth) ** 2).reshape(3, -1).mean(axis=1)
    np.testing.assert_allclose(psnr_excluding_black(images, truth), 10 * np.log10(1 / mse), rtol=1e-12)
    np.testing.assert_allclose(psnr_excluding_black(truth, images), psnr_excluding_black(images, truth))


def test_psnr_is_nan_only_where_both_are_black():
    truth = np.zeros((3, 4, 4))
    images = np.zeros((3, 4, 4))
    truth[1, 2, 2] = 1.0  # truth lit, image black: finite
    images[2, 0, 0] = 1.0  # image lit, truth black: finite
    psnr = psnr_excluding_black(images, truth)
    assert np.isnan(psnr[0])
    assert psnr[1] == pytest.approx(10 * math.log10(16)) and psnr[2] == pytest.approx(10 * math.log10(16))


def test_psnr_clips_both_images_to_the_unit_range():
    truth = np.full((2, 3, 3), 1.0)
    images = np.full((2, 3, 3), 1.0)
    images[0] = 7.5  # clipped to 1: identical -> capped
    truth[1] = -2.0  # clipped to 0: off by 1 everywhere -> 0 dB
    images[1] = 3.0
    psnr = psnr_excluding_black(images, truth)
    assert psnr[0] == 100.0
    assert psnr[1] == pytest.approx(0.0)
    # negative values are black: a negative image against black truth is excluded
    assert np.isnan(psnr_excluding_black(np.full((1, 2, 2), -1.0), np.zeros((1, 2, 2)))[0])


def test_psnr_is_capped():
    truth = np.full((3, 4, 4), 0.5)
    images = truth.copy()
    images[1, 0, 0] += 1e-7  # 10 log10(16 / 1e-14) = 152 dB -> cap
    images[2, 0, 0] += 0.04  # 10 log10(16 / 0.0016) = 40 dB, under any cap
    psnr = psnr_excluding_black(images, truth)
    assert psnr[0] == 100.0 and psnr[1] == 100.0
    assert psnr[2] == pytest.approx(40.0)
    assert psnr_excluding_black(images, truth, cap=30.0).tolist() == pytest.approx([30.0, 30.0, 30.0])


def test_summarize_matches_numpy():
    rng = np.random.default_rng(0)
    values = rng.normal(30.0, 5.0, 41)
    values[[3, 17, 29]] = np.nan
    stats = summarize(values)
    finite = values[np.isfinite(values)]
    assert stats["count"] == 38 and stats["excluded"] == 3
    assert stats["mean"] == pytest.approx(finite.mean())
    assert stats["median"] == pytest.approx(np.median(finite))
    assert stats["p5"] == pytest.approx(np.percentile(finite, 5))
    assert stats["p95"] == pytest.approx(np.percentile(finite, 95))
    assert (stats["min"], stats["max"]) == (pytest.approx(finite.min()), pytest.approx(finite.max()))
    assert all(type(stats[k]) is float for k in ("mean", "median", "p5", "p95", "min", "max"))


def test_summarize_of_nothing_finite():
    stats = summarize([np.nan, np.nan])
    assert stats["count"] == 0 and stats["excluded"] == 2
    assert stats["mean"] is None and stats["p95"] is None
    json.dumps(stats, allow_nan=False)


def test_win_share_drops_nans_and_does_not_count_ties():
    first = np.array([30.0, 20.0, 25.0, np.nan, 40.0, 10.0])
    second = np.array([29.0, 20.0, 26.0, 50.0, np.nan, 5.0])
    # finite in both: rows 0, 1, 2, 5; strictly higher: rows 0 and 5 (row 1 is a tie)
    assert win_share(first, second) == pytest.approx(0.5)
    assert win_share(second, first) == pytest.approx(0.25)
    assert win_share([np.nan, 1.0], [2.0, np.nan]) is None


def test_barycentric_grid():
    for steps in (1, 2, 3, 10):
        grid = barycentric_grid(steps)
        assert grid.shape == ((steps + 1) * (steps + 2) // 2, 3)
        np.testing.assert_allclose(grid.sum(axis=1), 1.0)
        assert grid.min() >= 0.0
        for corner in np.eye(3):
            assert np.any(np.all(np.isclose(grid, corner), axis=1)), (steps, corner)
        assert len(np.unique(np.round(grid * steps).astype(int), axis=0)) == len(grid)  # no repeats
        np.testing.assert_allclose(grid * steps, np.round(grid * steps), atol=1e-12)  # on the lattice
    assert any(np.allclose(row, 1 / 3) for row in barycentric_grid(3))
    for bad in (0, -2):
        with pytest.raises(InputError, match="steps"):
            barycentric_grid(bad)


def test_to_dict_of_an_evaluation_with_excluded_queries_is_strict_json():
    evaluation = Evaluation(
        directions=np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
        faces=np.array([0, 1, 2]),
        barycentric=np.full((3, 3), 1 / 3),
        specular_psnr={"circular": np.array([30.0, np.nan, 40.0]), "alpha": np.array([20.0, np.nan, 45.0])},
        gaussians_per_light=np.array([2, 3, 4]),
        barycentric_sweep={"skipped": "no renderer"},
    )
    report = json.loads(json.dumps(evaluation.to_dict(), allow_nan=False))
    assert report["per_query"]["specular_psnr"]["circular"] == [30.0, None, 40.0]
    assert report["summary"]["specular"]["circular"]["excluded"] == 1
    assert report["summary"]["specular"]["circular_beats_alpha"] == pytest.approx(0.5)
    assert report["gaussians"]["per_light"]["total"] == 9 and report["gaussians"]["per_query"] is None
    assert report["barycentric_sweep"] == {"skipped": "no renderer"}


# --- evaluate_field on a fitted donut --------------------------------------------------------------


@pytest.fixture(scope="module")
def donut(small_field, small_donut):
    return load_field(small_field), ReflectanceField.load(small_donut, progress=False)


@pytest.fixture(scope="module")
def evaluation(donut):
    field, dataset = donut
    return evaluate_field(field, dataset, device="cpu", barycentric_steps=2)


@pytest.fixture(scope="module")
def alpha_specular(donut):
    field, dataset = donut
    return alpha_inputs(field, dataset, device="cpu")[0]


def _truth_specular(stack: np.ndarray) -> np.ndarray:
    return np.asarray(stack, dtype=np.float64) @ REC709


def test_evaluation_shapes_and_summary(evaluation, donut):
    field, dataset = donut
    q = dataset.heldout.light_count
    assert q == 2 * field.light_count - 4  # the centroids of a closed sphere's faces
    assert (evaluation.directions.shape == (q, 3) and evaluation.faces.shape == (q,)
            and evaluation.barycentric.shape == (q, 3))
    for scores in (evaluation.specular_psnr, evaluation.full_psnr):
        assert set(scores) == {"circular", "straight", "alpha"}
        for values in scores.values():
            assert values.shape == (q,) and np.all(np.isfinite(values))
    summary = evaluation.summary()
    assert set(summary) == {"specular", "full", "full_srgb", "full_ssim"}
    assert set(summary["specular"]) == {"circular", "straight", "alpha", "circular_beats_alpha",
                                        "circular_beats_straight", "straight_beats_alpha"}
    assert summary["specular"]["circular"]["count"] == q
    assert summary["specular"]["circular"]["mean"] == pytest.approx(evaluation.specular_psnr["circular"].mean())
    assert (summary["specular"]["circular_beats_alpha"]
            == pytest.approx(np.mean(evaluation.specular_psnr["circular"] > evaluation.specular_psnr["alpha"])))
    # the method beats its baseline on this easy object (thesis Fig. 4.9)
    assert summary["specular"]["circular"]["mean"] > summary["specular"]["alpha"]["mean"]
    assert evaluation.gaussians_per_light.tolist() == field.estimated.counts.tolist()
    assert evaluation.gaussians_per_query.shape == (q,) and evaluation.gaussians_per_query.min() >= 1
    assert set(evaluation.examples) == {"circular", "straight", "alpha", "truth"}
    assert evaluation.examples["truth"].shape == (len(evaluation.example_queries), field.height, field.width)
    assert evaluation.info["heldout"] == q and evaluation.info["measured"] == ["specular", "full"]


def _figure_words(figure) -> str:
    """Every title and text of a figure, one string."""
    words = [figure.get_suptitle(), *(t.get_text() for t in figure.texts)]
    for ax in figure.axes:
        words += [ax.get_title(), *(t.get_text() for t in ax.texts)]
    return "\n".join(words)


def _check_example_panels(figure, png, evaluation) -> list[str]:
    """No panel of examples.png is one flat value: where the method's S' is flat its note is written in
    the panel (the notes are returned), elsewhere the image is drawn."""
    order = [k for k in ("truth", "circular", "straight", "alpha") if k in evaluation.examples]
    panels = panel_pixels(figure, png)
    assert len(panels) == len(order) * len(evaluation.example_queries)
    notes = []
    for index, (title, pixels) in enumerate(panels):
        row, key = divmod(index, len(order))
        assert title.startswith(f"#{evaluation.example_queries[row]} {order[key]}")
        assert np.ptp(pixels) > 0, f"panel {title!r} of examples.png is blank"
        image = evaluation.examples[order[key]][row]
        ax = [a for a in figure.axes if a.get_title() == title][0]
        if np.ptp(image) > 0.01:
            assert ax.images and not ax.texts
        elif not ax.images:
            notes.append(ax.texts[0].get_text().replace("\n", " "))
    return notes


def test_pictures_of_a_field_that_keeps_no_gaussians_say_so(tmp_path, drawn_figures):
    """A field whose highlights all stay in its residual: S' of circular and straight is zero, so their
    panels of examples.png say that the field moves no highlights; the counts histogram sits on 0 .. 1
    and its title says none is kept; the full-image PSNR names the model (residual + highlights)."""
    from warp_highlights.cli.relight import write_evaluation

    rng = np.random.default_rng(5)
    queries, lights, height, width = 11, 43, 18, 16
    scores = {m: rng.normal(38.0, 2.0, queries) for m in ("circular", "straight", "alpha", "ptm")}
    picked = np.array([0, 3, 7, 10])
    evaluation = Evaluation(
        directions=np.tile([0.0, 0.0, 1.0], (queries, 1)), faces=np.arange(queries),
        barycentric=np.full((queries, 3), 1 / 3), full_psnr=scores,
        full_srgb_psnr={m: v - 6.0 for m, v in scores.items()}, full_ssim={m: np.full(queries, 0.9) for m in scores},
        full_examples={m: rng.random((3, height, width, 3)) for m in ("truth", *scores)},
        full_example_queries=np.array([5, 4, 2]),
        gaussians_per_light=np.zeros(lights, int), gaussians_per_query=np.zeros(queries, int),
        example_queries=picked,
        examples={"circular": np.zeros((4, height, width)), "straight": np.zeros((4, height, width)),
                  "alpha": rng.random((4, height, width)) * 0.3},
        info={"heldout": queries, "highlights_added_to": "residual", "moving_gaussians": 0},
    )
    folder = tmp_path / "ev"
    written = write_evaluation(folder, evaluation, evaluation.to_dict(), overwrite=False, title="statue")
    assert {"examples.png", "gaussian-counts.png", "psnr-full.png", "worst-lights.png"} <= set(written)

    notes = _check_example_panels(drawn_figures["examples.png"], folder / "examples.png", evaluation)
    assert len(notes) == 8  # circular and straight at every example light
    assert all(note.startswith("the field moves no highlights") and "residual" in note for note in notes)

    counts = drawn_figures["gaussian-counts.png"]
    assert counts.get_suptitle().endswith("no Gaussians kept: every light's highlights are in the residual")
    for ax in counts.axes:
        assert ax.get_xlim() == pytest.approx((-0.5, 1.5))

    full = _figure_words(drawn_figures["psnr-full.png"])
    assert "PSNR of the full images I' = residual + highlights at 11 held-out lights" in full
    assert "circular, straight: the blended residual alone (the field keeps no Gaussians" in full
    for figure in drawn_figures.values():
        assert "D' + S'" not in _figure_words(figure)


def test_every_example_panel_of_a_fitted_field_shows_something(evaluation, tmp_path, drawn_figures):
    """The fitted donut (it keeps Gaussians): every panel of examples.png is drawn or, where its S' is
    flat, says why; the full-image PSNR names the model the field relights with."""
    from warp_highlights.cli.relight import write_evaluation

    folder = tmp_path / "ev"
    write_evaluation(folder, evaluation, evaluation.to_dict(), overwrite=False, title="donut")
    notes = _check_example_panels(drawn_figures["examples.png"], folder / "examples.png", evaluation)
    assert not any("moves no highlights" in note for note in notes)
    added = {"residual": "residual", "images": "diffuse images", "lambert": "Lambertian diffuse"}
    base = added[evaluation.info["highlights_added_to"]]
    words = _figure_words(drawn_figures["psnr-full.png"])
    assert f"I' = {base} + highlights" in words and "Gaussians moved along circular or straight paths" in words
    assert "no Gaussians kept" not in drawn_figures["gaussian-counts.png"].get_suptitle()


def test_alpha_psnr_matches_a_numpy_blend(evaluation, donut, alpha_specular):
    field, dataset = donut
    heldout = dataset.heldout
    location = field.triangulation.locate(heldout.lights.directions)  # the host locate, not the kernel's
    np.testing.assert_array_equal(evaluation.faces, location.faces)
    corners = field.triangulation.faces[location.faces]  # (Q, 3) lights
    blend = np.einsum("qk,qkhw->qhw", location.barycentric, alpha_specular[corners].astype(np.float64))
    exposure = float(field.report.get("exposure") or 1.0)
    expected = psnr_excluding_black(blend, _truth_specular(heldout.specular) * exposure)
    np.testing.assert_allclose(evaluation.specular_psnr["alpha"], expected, atol=1e-3)


def test_the_centroids_blend_their_three_corners_equally(evaluation):
    np.testing.assert_allclose(evaluation.barycentric, 1 / 3, atol=1e-5)
    assert sorted(evaluation.faces.tolist()) == list(range(len(evaluation.faces)))


@pytest.mark.parametrize("method", ["circular", "straight"])
def test_gaussian_psnr_matches_the_relighter(evaluation, donut, method):
    field, dataset = donut
    relighter = Relighter(field, device="cpu")
    relit = relighter.relight(dataset.heldout.lights.directions, method=method)
    specular_truth = _truth_specular(dataset.heldout.specular)
    np.testing.assert_allclose(evaluation.specular_psnr[method], psnr_excluding_black(relit.specular, specular_truth),
                               atol=1e-3)
    np.testing.assert_allclose(evaluation.full_psnr[method], psnr_excluding_black(relit.full, dataset.heldout.images),
                               atol=1e-3)
    rows = evaluation.example_queries
    np.testing.assert_allclose(evaluation.examples[method], relit.specular[rows], atol=1e-6)


def test_circular_and_straight_differ(evaluation):
    assert not np.allclose(evaluation.specular_psnr["circular"], evaluation.specular_psnr["straight"])


def test_report_is_strict_json(evaluation, donut):
    field, _ = donut
    report = json.loads(json.dumps(evaluation.to_dict(), allow_nan=False))
    assert (report["summary"]["specular"]["circular"]["mean"]
            == pytest.approx(evaluation.summary()["specular"]["circular"]["mean"]))
    assert report["size"] == [field.width, field.height] and report["lights"] == field.light_count
    assert report["methods"] == ["circular", "straight", "alpha"]
    assert len(report["per_query"]["directions"]) == len(evaluation.directions)
    sweep = report["barycentric_sweep"]
    assert len(sweep["weights"]) == 6 and set(sweep["summary"]) == {"circular", "straight", "alpha"}


def test_auto_barycentric_sweep(evaluation, donut):
    field, _ = donut
    sweep = evaluation.barycentric_sweep
    assert "skipped" not in sweep
    assert sweep["weights"].shape == (6, 3)
    np.testing.assert_array_equal(sweep["vertices"], field.triangulation.faces[sweep["face"]])
    assert set(sweep["specular_psnr"]) == {"circular", "straight", "alpha"}
    for values in sweep["specular_psnr"].values():
        assert values.shape == (6,) and np.all(np.isfinite(values))
    # "auto" is the face of the held-out query with the median circular - alpha gain
    gain = evaluation.specular_psnr["circular"] - evaluation.specular_psnr["alpha"]
    median = np.argsort(gain)[len(gain) // 2]
    assert sweep["face"] == evaluation.faces[median]


def test_sweep_of_a_chosen_face_alpha_is_exact_at_its_corners(donut, evaluation, alpha_specular):
    field, dataset = donut
    face = int((evaluation.barycentric_sweep["face"] + 7) % field.triangulation.face_count)
    result = evaluate_field(field, dataset, device="cpu", barycentric_face=face, barycentric_steps=3, example_count=0)
    sweep = result.barycentric_sweep
    assert sweep["face"] == face and sweep["weights"].shape == (10, 3)
    weights, scores = sweep["weights"], sweep["specular_psnr"]
    corners = [int(np.flatnonzero(np.isclose(weights[:, k], 1.0))[0]) for k in range(3)]
    centre = int(np.flatnonzero(np.all(np.isclose(weights, 1 / 3), axis=1))[0])
    # at a corner the alpha blend is that light's segmented specular; the ground truth rendered anew from
    # meta.json is the dataset's own specular image of that light
    for k, row in enumerate(corners):
        light = int(sweep["vertices"][k])
        own = psnr_excluding_black(alpha_specular[light][None], _truth_specular(dataset.specular[light][None]))[0]
        assert scores["alpha"][row] == pytest.approx(own, abs=0.05)
        assert scores["alpha"][row] > scores["alpha"][centre] + 3.0
    # the centre is the held-out centroid of that face: same ground truth, same scores
    query = int(np.flatnonzero(evaluation.faces == face)[0])
    for method in ("circular", "straight", "alpha"):
        assert scores[method][centre] == pytest.approx(evaluation.specular_psnr[method][query], abs=0.05)


def test_sweep_of_a_face_that_does_not_exist(donut):
    field, dataset = donut
    count = field.triangulation.face_count
    with pytest.raises(InputError, match=f"triangle {count} does not exist") as error:
        evaluate_field(field, dataset, device="cpu", methods=("circular",), barycentric_face=count, barycentric_steps=2)
    assert "\n" not in str(error.value)


def test_methods_subset_and_no_sweep(donut):
    field, dataset = donut
    result = evaluate_field(field, dataset, device="cpu", methods=("circular",), barycentric_face=None)
    assert set(result.specular_psnr) == {"circular"} and result.barycentric_sweep is None
    assert "circular_beats_alpha" not in result.summary()["specular"]
    skipped = evaluate_field(field, dataset, device="cpu", methods=("circular", "straight"), barycentric_steps=2)
    assert "skipped" in skipped.barycentric_sweep  # "auto" needs the alpha scores
    json.dumps(skipped.to_dict(), allow_nan=False)
    with pytest.raises(InputError, match="method"):
        evaluate_field(field, dataset, device="cpu", methods=("circular", "cubic"))


def test_a_dataset_with_other_lights_is_refused(donut):
    field, dataset = donut
    other = ReflectanceField(images=np.zeros((16, field.height, field.width, 3), np.float32),
                             lights=LightSet.fibonacci_sphere(16))
    with pytest.raises(InputError, match="32 lights but the dataset has 16") as error:
        evaluate_field(field, other, device="cpu")
    assert "\n" not in str(error.value)
    turned = LightSet(dataset.lights.directions[:, [1, 0, 2]])
    moved = ReflectanceField(images=dataset.images, lights=turned, heldout=dataset.heldout)
    with pytest.raises(InputError, match="differ") as error:
        evaluate_field(field, moved, device="cpu")
    assert "\n" not in str(error.value)


def test_a_dataset_without_heldout_lights_is_refused(donut):
    field, dataset = donut
    with pytest.raises(InputError, match="held-out") as error:
        evaluate_field(field, dataclasses.replace(dataset, heldout=None), device="cpu")
    assert "\n" not in str(error.value)


def test_luminance():
    stack = np.random.default_rng(1).uniform(0, 1, (2, 3, 4, 3)).astype(np.float32)
    np.testing.assert_allclose(luminance(stack), stack @ REC709.astype(np.float32), rtol=1e-6)
    gray = stack[..., 0]
    np.testing.assert_array_equal(luminance(gray), gray)


# --- the sweep's ground truth, and a field fitted with an exposure ----------------------------------


def test_renderer_from_meta_reproduces_the_datasets_images(donut):
    from warp_highlights.synth.render import renderer_from_meta

    _, dataset = donut
    renderer = renderer_from_meta(dataset.meta, device="cpu")
    assert renderer is not None
    lights = [0, 11, 27]
    rendered = renderer.render(dataset.lights.directions[lights])
    np.testing.assert_allclose(rendered.specular, dataset.specular[lights], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(rendered.full, dataset.images[lights], rtol=1e-5, atol=1e-6)
    assert renderer_from_meta({}) is None
    assert renderer_from_meta(dataset.meta | {"shape": "bunny.ply"}) is None  # meshes are not rebuilt
    assert renderer_from_meta(dataset.meta | {"material": {"shine": 3}}) is None
    assert renderer_from_meta(dataset.meta | {"view_rotation": [1, 2]}) is None


@pytest.fixture(scope="module")
def exposed(small_donut):
    """A field fitted with exposure 2 (its radiance is twice the dataset's), at half size."""
    from conftest import FAST_FIT
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.model.config import FitSettings

    dataset = ReflectanceField.load(small_donut, progress=False)
    field = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT), device="cpu", diffuse="images",
                      exposure=2.0,
                      size=(48, 27), progress=False)
    assert field.report["exposure"] == 2.0
    return field, dataset


def test_full_psnr_of_every_method_is_in_the_datasets_units(exposed):
    """I' of the alpha baseline is the blend of the captured images, as they were captured."""
    from warp_highlights.io.resample import resize_stack

    field, dataset = exposed
    result = evaluate_field(field, dataset, device="cpu", barycentric_face=None)
    truth = resize_stack(dataset.heldout.images, 48, 27)
    images = resize_stack(dataset.images, 48, 27).astype(np.float16).astype(np.float64)
    corners = field.triangulation.faces[result.faces]
    blend = np.einsum("qk,qkhwc->qhwc", result.barycentric, images[corners])
    np.testing.assert_allclose(result.full_psnr["alpha"], psnr_excluding_black(blend, truth), atol=0.01)
    # and the Gaussian methods are in the same units: all three score alike, none is off by a factor 2
    means = {m: np.mean(v) for m, v in result.full_psnr.items()}
    assert max(means.values()) - min(means.values()) < 6.0, means


@pytest.mark.slow
@pytest.mark.realdata
def test_evaluate_the_real_dome_capture_at_its_test_lights(data_root, tmp_path):
    """SynthRTI: fit the 49 dome lights at 80x80, score the 20 held-out Test lights (full images only)."""
    from conftest import FAST_FIT
    from warp_highlights.cli import main

    sample = data_root / "synthrti-object1-material5"
    field_path = tmp_path / "dome.whf"
    assert main(["fit", str(sample / "Dome"), "-o", str(field_path), "--size", "80x80", "-q",
                 *[a for o in FAST_FIT for a in ("--set", o)]]) == 0
    field = load_field(field_path)
    dataset = ReflectanceField.load(sample / "Dome", heldout=sample / "Test", progress=False)
    evaluation = evaluate_field(field, dataset, device="cpu", barycentric_face="auto")
    assert not evaluation.specular_psnr  # photographs: no specular ground truth
    summary = evaluation.summary()["full"]
    for method in ("circular", "straight", "alpha"):
        assert summary[method]["count"] == 20
        assert 15.0 < summary[method]["mean"] < 60.0
    assert evaluation.barycentric_sweep == {"skipped": "needs specular ground truth and the circular and alpha methods"}
    # the command finds Test/ beside Dome/ by itself (as a collection does) and scores the same lights
    out = tmp_path / "evaluation"
    assert main(["evaluate", str(field_path), str(sample / "Dome"), "-o", str(out), "--methods", "circular",
                 "--baselines", "none", "--triangle", "none", "--device", "cpu", "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["heldout"] == 20
    assert report["summary"]["full"]["circular"]["mean"] == pytest.approx(summary["circular"]["mean"], abs=1e-6)
