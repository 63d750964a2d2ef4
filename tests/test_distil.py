"""Smaller decoders (``model.residual`` decoder shapes, ``residual.distil``, ``warp-highlights distil``): the
embedding in the fitted decoder's shape against a float64 reference, the student's gradient against central
differences, a distillation that learns its teacher, the field file and the command."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from warp_highlights.model.errors import InputError
from warp_highlights.model.residual import (
    NEURAL_HIDDEN,
    NEURAL_INPUTS,
    NEURAL_LAYER_SHAPES,
    NeuralResidual,
    decoder_layer_shapes,
    decoder_widths,
    parse_hidden,
    standard_decoder,
)

SHAPES = [(16,), (24, 24), (8, 40), (48, 16, 8), (1,), (48, 48)]


def _elu(v):
    return np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))


def _reference(weights, x: np.ndarray) -> np.ndarray:
    """float64 decoder of any shape: (inputs, N) -> (3, N)."""
    h = x
    weights = [np.asarray(w, np.float64) for w in weights]
    for w, b in zip(weights[0:-2:2], weights[1:-2:2]):
        h = _elu(w @ h + b)
    return weights[-2] @ h + weights[-1]


def _random_decoder(hidden, seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    return [(rng.normal(size=shape) * scale / np.sqrt(shape[1] if i % 2 == 0 else 4)).astype(np.float32)
            for i, shape in enumerate(decoder_layer_shapes(hidden))]


@pytest.mark.parametrize("hidden", SHAPES)
def test_a_smaller_decoder_embeds_exactly_in_the_fitted_decoder_s_shape(hidden):
    weights = _random_decoder(hidden, scale=2.0)
    assert decoder_widths(weights) == hidden
    standard = standard_decoder(weights)
    assert [w.shape for w in standard] == list(NEURAL_LAYER_SHAPES)
    x = np.random.default_rng(1).normal(size=(12, 2000)) * 3.0  # far into ELU's negative side too
    want = _reference(weights, x)
    np.testing.assert_allclose(_reference(standard, x), want, atol=1e-5 * max(1.0, np.abs(want).max()))
    fitted = _random_decoder(NEURAL_HIDDEN)
    assert all(a is b or np.array_equal(a, b) for a, b in zip(standard_decoder(fitted), fitted))


def test_decoder_shapes_are_checked():
    codes = np.zeros((3, 4, 9), np.float16)
    assert NeuralResidual(codes, tuple(_random_decoder((24, 24))), 1.0, 5).hidden == (24, 24)
    with pytest.raises(InputError, match="1 to 3 hidden layers"):
        NeuralResidual(codes, tuple(_random_decoder((8, 8, 8, 8))), 1.0, 5)
    with pytest.raises(InputError, match="1 to 48 units"):
        NeuralResidual(codes, tuple(_random_decoder((64,))), 1.0, 5)
    broken = _random_decoder((24, 24))
    broken[2] = broken[2][:, :20]  # the second layer no longer takes the first's 24 values
    with pytest.raises(InputError, match="shapes"):
        NeuralResidual(codes, tuple(broken), 1.0, 5)
    assert parse_hidden("24,24") == (24, 24) and parse_hidden("16") == (16,)
    for bad in ("", "0", "49", "8,8,8,8", "a,b", "24;24"):
        with pytest.raises(InputError, match="hidden layers"):
            parse_hidden(bad)


@pytest.mark.parametrize("hidden", [(16,), (24, 24), (48, 16, 8)])
def test_the_cpu_decoder_of_a_smaller_decoder_matches_its_reference(hidden):
    from warp_highlights.residual.cpu_training import CpuDecoder, CpuQueryDecoder
    from warp_highlights.residual.decode import learned_images

    rng = np.random.default_rng(2)
    codes = rng.normal(size=(6, 7, 9)).astype(np.float16)
    learned = NeuralResidual(codes, tuple(_random_decoder(hidden)), 1.7, 5)
    directions = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]], np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    x = np.concatenate([np.repeat(codes.reshape(1, -1, 9).astype(np.float64), 2, axis=0),
                        np.repeat(directions[:, None, :], 42, axis=1)], axis=2)
    want = np.stack([_reference(learned.weights, x[q].T).T for q in range(2)])
    np.testing.assert_allclose(CpuDecoder(codes.reshape(-1, 9), learned.weights).decode(directions), want,
                               atol=2e-5, rtol=1e-4)
    out = np.zeros((2, 42, 3), np.float16)
    CpuQueryDecoder(codes.reshape(-1, 9), learned.weights, learned.unit).decode(directions, out)
    reference = learned_images(learned, directions).reshape(2, 42, 3)
    np.testing.assert_allclose(out, reference, atol=2e-3 * max(1.0, np.abs(reference).max()))


@pytest.mark.parametrize(("learns_codes", "sees"), [(False, False), (True, False), (True, True)])
def test_the_student_s_gradient_matches_central_differences(learns_codes, sees):
    """Weights, biases and (where they learn) the codes of the rows' pixels, some pixels taken twice; a student that
    sees the highlights takes sqrt(g), g after the direction."""
    from warp_highlights.model.residual import highlight_inputs
    from warp_highlights.residual.distil import _Student, _Worker

    rng = np.random.default_rng(4)
    codes = rng.normal(size=(4, 9))
    student = _Student((5, 4), np.random.default_rng(3), codes if learns_codes else None, sees=sees)
    student.flat = student.flat.astype(np.float64)
    student.grad = np.zeros_like(student.flat)
    worker = _Worker(student)
    pixels = np.array([0, 2, 2, 3, 1, 0, 2, 3, 3, 1, 2])
    directions, targets = rng.normal(size=(11, 3)), rng.normal(size=(11, 3))
    if sees:
        directions = np.concatenate([directions, highlight_inputs(rng.uniform(0.0, 3.0, 11))], axis=1)

    def current_codes():
        return student.views(student.flat)[-1] if learns_codes else codes

    def loss() -> float:
        x = np.concatenate([current_codes()[pixels], directions], axis=1).T
        weights = student.views(student.flat)[:len(student.shapes) - learns_codes]
        return 0.5 * float(np.sum((_reference(weights, x).T - targets) ** 2))

    worker.gradient(current_codes()[pixels], pixels, directions, targets)
    analytic = worker.grad.copy()
    weight_count = sum(rows * cols for rows, cols in decoder_layer_shapes((5, 4), sees))
    assert analytic.size == weight_count + learns_codes * codes.size
    step = 1e-6
    for i in range(student.flat.size):
        kept = student.flat[i]
        student.flat[i] = kept + step
        up = loss()
        student.flat[i] = kept - step
        down = loss()
        student.flat[i] = kept
        assert analytic[i] == pytest.approx((up - down) / (2 * step), rel=1e-5, abs=1e-6), i


def test_directions_between_lie_inside_the_lights_triangles():
    from warp_highlights.model.lights import LightSet
    from warp_highlights.model.triangulation import SphericalTriangulation
    from warp_highlights.residual.distil import directions_between

    lights = LightSet.fibonacci_sphere(40).directions
    lights = lights[lights[:, 2] > 0.1]
    triangulation = SphericalTriangulation(lights)
    drawn = directions_between(lights, triangulation.faces, 300, np.random.default_rng(5))
    assert drawn.shape == (300, 3) and np.allclose(np.linalg.norm(drawn, axis=1), 1.0, atol=1e-6)
    located = triangulation.locate(drawn)  # inside the captured triangles: barycentric weights >= 0
    assert np.all(located.barycentric >= -1e-6)
    assert drawn[:, 2].min() > lights[:, 2].min() - 1e-6
    with pytest.raises(InputError, match="triangle"):
        directions_between(lights, np.zeros((0, 3), np.int64), 3, np.random.default_rng(0))


@pytest.fixture(scope="module")
def learned_field(small_learned_field):
    """The small donut fitted with a learned residual: (field, path) (``conftest.small_learned_field``)."""
    return small_learned_field


def _plain(learned: NeuralResidual) -> NeuralResidual:
    """``learned`` with a decoder of code and direction only (w0's first 12 columns)."""
    import dataclasses

    return dataclasses.replace(learned, weights=(learned.weights[0][:, :NEURAL_INPUTS], *learned.weights[1:]))


def _seeing(learned: NeuralResidual, seed: int = 6) -> NeuralResidual:
    """``learned`` with a decoder that sees the highlights: as it is, or w0's 12 columns and two non-zero ones for
    sqrt(g), g."""
    import dataclasses

    if learned.sees_highlights:
        return learned
    w0 = learned.weights[0]
    extra = np.random.default_rng(seed).normal(0.0, 1.0, (len(w0), 2)).astype(np.float32)
    return dataclasses.replace(learned, weights=(np.concatenate([w0, extra], axis=1), *learned.weights[1:]))


def _saved(field, learned: NeuralResidual, path):
    """``field`` with ``learned`` as its residual's, saved at ``path``: (field, path)."""
    import dataclasses

    from warp_highlights.io.fieldfile import save_field

    field = dataclasses.replace(field, residual=dataclasses.replace(field.residual, learned=learned))
    save_field(field, path)
    return field, path


@pytest.mark.slow
def test_a_distilled_decoder_learns_its_teacher(learned_field):
    from warp_highlights.model.config import DistilSettings
    from warp_highlights.residual.distil import agreement, distil_decoder

    field, _ = learned_field
    teacher = _plain(field.residual.learned)
    directions, faces = field.lights.directions, field.triangulation.faces
    untrained, _ = distil_decoder(teacher, (24, 24), directions, faces, settings=DistilSettings(epochs=1, seconds=0,
                                                                                              epochs_per_round=1))
    lines = []
    student, report = distil_decoder(teacher, (24, 24), directions, faces,
                                     settings=DistilSettings(epochs=12, seconds=0), log=lines.append)
    assert student.hidden == (24, 24) and student.codes.shape == teacher.codes.shape
    assert not np.array_equal(student.codes, teacher.codes)  # they learn too (DistilSettings.learn_codes)
    assert student.unit == teacher.unit and student.light_count == teacher.light_count
    assert report.multiply_adds == 12 * 24 + 24 * 24 + 24 * 3 and report.teacher_multiply_adds == 5328
    assert report.epochs == pytest.approx(12, rel=0.01) and len(lines) == 3
    # training brings it closer to the teacher, at the lights and between them
    first = agreement(untrained, teacher, directions)
    assert report.captured_psnr_db > first + 3.0 and report.between_psnr_db > 30.0
    again, _ = distil_decoder(teacher, (24, 24), directions, faces, settings=DistilSettings(epochs=12, seconds=0))
    for a, b in zip((again.codes, *again.weights), (student.codes, *student.weights)):  # the seed fixes every draw
        np.testing.assert_array_equal(a, b)
    fixed, fixed_report = distil_decoder(teacher, (24, 24), directions, faces,
                                         settings=DistilSettings(epochs=12, seconds=0, learn_codes=False))
    assert np.array_equal(fixed.codes, teacher.codes) and fixed_report.captured_psnr_db > first + 3.0


def _display_images(learned: NeuralResidual, directions: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(Q, H, W, 3) a decoder's display values (at least 0) at (Q, 3) directions with (Q, P) g (display units)."""
    from warp_highlights.residual.cpu_training import CpuDecoder
    from warp_highlights.residual.opponent import decode_display

    decoder = CpuDecoder(learned.codes.reshape(-1, 9).astype(np.float32), learned.weights)
    values = decode_display(decoder.decode(np.asarray(directions, np.float32), highlights=g))
    return np.maximum(values, 0.0).reshape(len(directions), *learned.codes.shape[:2], 3)


def test_a_student_of_a_decoder_that_sees_the_highlights_sees_them_too(learned_field):
    """Its w0 has 14 columns; teacher and student decode with the Gaussians moved to each direction, and the student
    learns the teacher's images with them (without them it is further off)."""
    from warp_highlights.cli.distil import _moved_highlights
    from warp_highlights.model.config import DistilSettings
    from warp_highlights.quality.metrics import srgb_psnr
    from warp_highlights.residual.distil import agreement, distil_decoder

    field, _ = learned_field
    teacher = _seeing(field.residual.learned)
    directions, faces = field.lights.directions, field.triangulation.faces
    highlights = _moved_highlights(field)
    assert highlights(directions[:2]).shape == (2, field.height, field.width)
    untrained, _ = distil_decoder(teacher, (24, 24), directions, faces, highlights=highlights,
                                  settings=DistilSettings(epochs=1, seconds=0, epochs_per_round=1))
    student, report = distil_decoder(teacher, (24, 24), directions, faces, highlights=highlights,
                                     settings=DistilSettings(epochs=12, seconds=0))
    assert student.sees_highlights and [w.shape for w in student.weights[:2]] == [(24, 14), (24, 1)]
    assert report.multiply_adds == 14 * 24 + 24 * 24 + 24 * 3 and report.teacher_multiply_adds == 5424
    first = agreement(untrained, teacher, directions, highlights)
    assert report.captured_psnr_db > first + 3.0 and report.between_psnr_db > 30.0, (first, report)
    assert report.captured_psnr_db == pytest.approx(agreement(student, teacher, directions, highlights))
    # the student's highlights are its inputs: without them (g = 0) it gives the teacher's images back worse
    g = highlights(directions).reshape(len(directions), -1) / np.float32(teacher.unit)
    theirs, seen, blind = (_display_images(model, directions, g if sees else np.zeros_like(g))
                           for model, sees in ((teacher, True), (student, True), (student, False)))
    scores = [np.mean([srgb_psnr(a, b) for a, b in zip(mine, theirs)]) for mine in (seen, blind)]
    assert scores[0] == pytest.approx(report.captured_psnr_db, abs=0.01) and scores[1] < scores[0] - 3.0, scores
    with pytest.raises(InputError, match="pass highlights") as refused:
        distil_decoder(teacher, (24, 24), directions, faces, settings=DistilSettings(epochs=1, seconds=0))
    assert "\n" not in str(refused.value)


def test_distil_command_distils_a_decoder_that_sees_the_highlights(learned_field, tmp_path, capsys):
    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import load_field

    field, _ = learned_field
    _, path = _saved(field, _seeing(field.residual.learned), tmp_path / "seeing.whf")
    assert load_field(path).residual.learned.sees_highlights
    output = tmp_path / "small.whf"
    assert main(["distil", str(path), "-o", str(output), "--hidden", "16,16", "--seconds", "3", "-q"]) == 0
    said = capsys.readouterr().out
    assert "decoder 16-16" in said and "it sees the highlights" in said and "\n" not in said.strip()
    small = load_field(output).residual.learned
    assert small.hidden == (16, 16) and small.sees_highlights and small.weights[0].shape == (16, 14)


def test_distil_command_writes_a_field_that_saves_loads_and_relights(learned_field, tmp_path, capsys):
    from warp_highlights.cli import main
    from warp_highlights.io.fieldfile import load_field
    from warp_highlights.relight.relighter import Relighter
    from warp_highlights.residual.decode import learned_images

    field, path = _saved(learned_field[0], _plain(learned_field[0].residual.learned), tmp_path / "plain.whf")
    output = tmp_path / "small.whf"
    assert main(["distil", str(path), "-o", str(output), "--hidden", "16,16", "--seconds", "3", "-q"]) == 0
    said = capsys.readouterr().out
    assert "decoder 16-16" in said and "dB at the" in said
    small = load_field(output)
    assert small.residual.learned.hidden == (16, 16)
    distilled = small.report["distilled"]
    # it stops at the first epoch's end past the bound: at most about one epoch over (a busy machine's epochs are long)
    assert distilled["hidden"] == [16, 16] and distilled["seconds"] <= 3.0 + max(0.5, 1.5 * 3.0 / distilled["epochs"])
    with zipfile.ZipFile(output) as archive:
        header = json.loads(archive.read("header.json"))
        assert header["residual"]["learned"]["hidden"] == [16, 16]
        assert "residual/learned_w2.npy" in archive.namelist() and "residual/learned_w3.npy" not in archive.namelist()
    np.testing.assert_array_equal(small.estimated.mean, field.estimated.mean)  # the rest as it was
    directions = np.array([[0.3, 0.2, 0.93]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    relit = Relighter(small, device="cpu").relight(directions).full
    highlights = Relighter(small, device="cpu", diffuse="none").relight(directions).full
    want = np.clip(learned_images(small.residual.learned, directions) + highlights, 0.0, None)
    np.testing.assert_allclose(relit, want, atol=2e-3 * max(1.0, float(np.abs(want).max())))
    assert main(["info", str(output)]) == 0
    said = capsys.readouterr().out
    assert "hidden layers 16-16" in said and "distilled from 48-48-48" in said


def test_distil_command_refuses_what_it_cannot_do(learned_field, tiny_sphere, tmp_path, capsys):
    from warp_highlights.cli import main

    _, path = learned_field
    _, lowrank = tiny_sphere  # a low-rank field
    for argv, expected in (([str(lowrank), "-o", str(tmp_path / "a.whf")], "--residual learned"),
                           ([str(path), "-o", str(tmp_path / "b.whf"), "--hidden", "64"], "hidden layers"),
                           ([str(path), "-o", str(tmp_path / "c.whf"), "--seconds", "0"], "--seconds"),
                           ([str(path), "-o", str(path)], "")):
        assert main(["distil", *argv, "-q"]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and expected in error[0]
    assert list(tmp_path.iterdir()) == []


def test_a_version_5_learned_field_reads_as_the_fitted_decoder(learned_field, tmp_path):
    from test_field import load_error, rewrite
    from warp_highlights.io.fieldfile import load_field

    field, path = learned_field
    older = tmp_path / "older.whf"
    data = path.read_bytes()

    def without_widths(header):
        learned = {k: v for k, v in header["residual"]["learned"].items() if k != "hidden"}
        return {**header, "format_version": 5, "residual": {**header["residual"], "learned": learned}}

    rewrite(data, older, header=without_widths)
    assert load_field(older).residual.learned.hidden == NEURAL_HIDDEN
    for hidden in ([24, 24], [0], "48"):
        rewrite(data, older, header=lambda h: {**h, "residual": {
            **h["residual"], "learned": {**h["residual"]["learned"], "hidden": hidden}}})
        assert "residual.learned" in load_error(older) or "learned_w" in load_error(older)


@pytest.mark.parametrize("hidden", [(24, 24), (13,)])
def test_a_field_with_a_smaller_decoder_relights_as_its_reference_on_every_device(learned_field, hidden, device):
    """On the CPU the smaller decoder runs at its own size; on CUDA embedded in the fitted decoder's kernels."""
    import dataclasses

    from warp_highlights.relight.relighter import Relighter
    from warp_highlights.residual.decode import learned_images

    field, _ = learned_field
    teacher = field.residual.learned
    student = NeuralResidual(teacher.codes, tuple(_random_decoder(hidden, seed=9)), teacher.unit, teacher.light_count)
    small = dataclasses.replace(field, residual=dataclasses.replace(field.residual, learned=student))
    directions = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86], [0.0, -0.7, 0.71]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    relit = Relighter(small, device=device).relight(directions).full
    highlights = Relighter(small, device=device, diffuse="none").relight(directions).full
    want = np.clip(learned_images(student, directions) + highlights, 0.0, None)
    assert np.all(np.isfinite(relit)) and relit.min() >= 0
    np.testing.assert_allclose(relit, want, atol=2e-3 * max(1.0, float(np.abs(want).max())))
