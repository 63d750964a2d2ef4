"""Residual transfer (docs/method.md, The residual): the residual model, its compression, the move decision,
the highlight colour, the compose kernel against a float64 reference, exactness at captured lights,
the field file's version 2, and non-negative outputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st

import warp_highlights.fit.moving as moving_module
import warp_highlights.residual.build as build_module
import warp_highlights.residual.device as device_module
import warp_highlights.residual.rate as rate_module
from conftest import FAST_FIT
from reference import render as render_reference
from reference import widened
from warp_highlights.fit.moving import decide_moving
from warp_highlights.fit.pipeline import fit_field
from warp_highlights.io.dataset import ReflectanceField
from warp_highlights.io.fieldfile import FORMAT_VERSION, load_field, save_field
from warp_highlights.io.resample import resample_image
from warp_highlights.kernels.support import support_fractions
from warp_highlights.model.config import FitSettings, RasterSettings, ResidualSettings
from warp_highlights.model.errors import InputError
from warp_highlights.model.gaussians import GaussianBatch, GaussianParams
from warp_highlights.model.residual import ResidualModel
from warp_highlights.quality.metrics import srgb_psnr
from warp_highlights.relight.relighter import Relighter
from warp_highlights.residual.build import (
    CHROMA_GAIN,
    LUMINANCE_GAIN,
    NormalisedResidual,
    build_residual,
    captured_psnr,
)
from warp_highlights.residual.decode import (
    decoded_images,
    light_images,
    light_weights,
    stack_basis,
    stack_light_images,
)
from warp_highlights.residual.inputs import highlight_colour
from warp_highlights.residual.interpolation import residual_sigma
from warp_highlights.residual.opponent import from_opponent, to_opponent
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import fit_stack, quantised_stack
from warp_highlights.residual.rate import (
    RateSample,
    StackPlan,
    allocate,
    allocate_steps,
    component_bytes,
    entry_bytes,
    quantised_bytes,
    sampled_rows,
)

RNG = np.random.default_rng(15)


# --- the model ------------------------------------------------------------------------------------


def test_opponent_colour_round_trip():
    rgb = RNG.normal(size=(5, 4, 3))
    y, chroma = to_opponent(rgb)
    np.testing.assert_allclose(y, rgb @ [0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose(from_opponent(y, chroma), rgb, atol=1e-12)


def test_low_rank_stack_is_exact_for_a_stack_of_that_rank_up_to_8_bit_codes():
    """Rank 3 plus a constant image: a mean image and 3 basis images span it."""
    n, h, w = 12, 9, 7
    basis = RNG.normal(size=(3, h * w))
    stack = (RNG.normal(size=(n, 3)) @ basis + 0.5).reshape(n, h, w, 1)
    model = fit_stack(stack, 3)
    assert model.rank == 3 and model.codes.dtype == np.uint8
    error = np.abs(stack_light_images(model, np.eye(n)) - stack).max()
    # each basis image is off by at most half a code step; the weights are refitted to the codes
    step = (model.ranges[:, 1] - model.ranges[:, 0]).max() / 255
    assert error <= 0.5 * step * np.abs(model.weights).sum(axis=1).max() + 1e-3
    assert np.abs(stack_light_images(model, np.eye(n)) - stack).mean() < 0.25 * step * np.abs(model.weights).max()


def test_low_rank_error_falls_with_rank_and_the_mean_is_kept_as_float16():
    n, h, w = 20, 16, 12
    stack = RNG.random((n, h, w, 2)).astype(np.float32)
    errors = [float(np.sqrt(((stack_light_images(fit_stack(stack, k), np.eye(n)) - stack) ** 2).mean()))
              for k in (1, 4, 10, 19)]
    assert errors == sorted(errors, reverse=True)
    model = fit_stack(stack, 4)
    np.testing.assert_array_equal(model.mean, model.mean.astype(np.float16).astype(np.float32))


def test_residual_model_refuses_inconsistent_parts():
    stack = fit_stack(RNG.random((6, 4, 5, 1)), 2)
    with pytest.raises(InputError, match="exactly one"):
        ResidualModel()
    with pytest.raises(InputError, match="exactly one"):
        ResidualModel(images=np.zeros((6, 4, 5, 1)), luminance=stack)
    with pytest.raises(InputError, match="chroma"):
        ResidualModel(luminance=stack, chroma=fit_stack(RNG.random((6, 4, 5, 1)), 2))
    with pytest.raises(InputError, match="highlight colour"):
        ResidualModel(luminance=stack, highlight_colour=-np.ones((4, 5, 1)))
    with pytest.raises(InputError, match="non-finite"):
        ResidualModel(images=np.full((6, 4, 5, 1), np.nan))


def test_the_automatic_rank_keeps_the_residual_within_its_size_budget():
    n, h, w = 30, 36, 48
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * xx + i) * np.cos((i % 5 + 1) * yy) for i in range(20)])
    images = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 20)), patterns)[..., None] * [0.3, 0.2, 0.1] + 0.5
    images = images.astype(np.float32)
    own = np.zeros((n, h, w), np.float32)
    capture = n * h * w * 3
    ranks = []
    for budget in (0.03, 0.06, 0.12, 0.5):
        model = build_residual(images, own, None, settings=ResidualSettings(size_budget=budget, min_luminance_rank=1,
                                                                            min_captured_psnr_db=0), other_bytes=500)
        stored = 500 + entry_bytes(model.luminance.mean.astype(np.float16)) + component_bytes(model.luminance).sum()
        stored += entry_bytes(model.chroma.mean.astype(np.float16)) + component_bytes(model.chroma).sum()
        assert stored <= budget * capture or model.luminance.rank == 1
        ranks.append(model.luminance.rank)
    assert ranks == sorted(ranks) and ranks[0] < ranks[-1] <= ResidualSettings().max_luminance_rank
    floored = build_residual(images, own, None, settings=ResidualSettings(size_budget=0.01, min_captured_psnr_db=0),
                             other_bytes=500)
    assert floored.luminance.rank == ResidualSettings().min_luminance_rank  # the floor holds whatever the budget
    fixed = build_residual(images, own, None, settings=ResidualSettings(luminance_rank=5))
    assert fixed.luminance.rank == 5


def test_the_budget_grows_until_the_captured_lights_come_back_at_the_floor(monkeypatch):
    """A stack of texture-like noise (no low rank to find) within 20% of the capture comes back far below 40 dB; the
    floor grows the budget by half at a time until it holds (or the cap binds), and the report says where it ended;
    ``captured_psnr`` is the decoded residual plus the own highlights scored against the images."""
    n, h, w = 12, 24, 32
    images = (0.3 + 0.1 * RNG.random((n, h, w, 3))).astype(np.float32)
    own = np.zeros((n, h, w), np.float32)
    own[:, 8:12, 10:14] = 0.2
    tint = np.ones((h, w, 3), np.float32)
    plain = build_residual(images, own, None, settings=ResidualSettings(size_budget=0.2, min_captured_psnr_db=0))
    assert captured_psnr(plain, images, own, tint) < 36
    report = {}
    grown = build_residual(images, own, None, settings=ResidualSettings(size_budget=0.2), report=report)
    assert report["captured_psnr_db"] >= 40 and 0.2 < report["size_budget"] <= 1.0
    decoded = decoded_images(grown).astype(np.float32) + own[..., None] * tint
    reference = np.mean([srgb_psnr(decoded[i], images[i]) for i in range(n)])
    assert report["captured_psnr_db"] == pytest.approx(reference, abs=1e-3)
    capped = {}
    build_residual(images, own, None, settings=ResidualSettings(size_budget=0.2, max_size_budget=0.4), report=capped)
    assert capped["size_budget"] == pytest.approx(0.4) and capped["captured_psnr_db"] < 40
    monkeypatch.setattr(build_module, "SCORED_LIGHTS", 5)  # of many lights, 5 spread evenly are scored
    spread = [0, 3, 6, 8, 11]
    assert captured_psnr(grown, images, own, tint) == pytest.approx(
        np.mean([srgb_psnr(decoded[i], images[i]) for i in spread]), abs=1e-3)
    monkeypatch.undo()
    darker = {}  # display units: the same images shown at half their brightness
    build_residual(images, own, None, settings=ResidualSettings(size_budget=1.0), display_scale=0.5, report=darker)
    assert darker["captured_psnr_db"] != pytest.approx(report["captured_psnr_db"], abs=0.01)


def test_a_fit_whose_residual_needs_more_than_its_budget_says_so(small_donut):
    """The fit's report has the low-rank residual's budget and its captured lights' score; where the floor grew the
    budget, the fit says so in one line (a floor set out of reach here: the budget grows to the cap)."""
    from conftest import FAST_FIT
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField

    dataset = ReflectanceField.load(small_donut, progress=False)
    said = []
    field = fit_field(dataset, device="cpu", progress=False, log=said.append,
                      settings=FitSettings().with_overrides(FAST_FIT + ["residual.kind=lowrank",
                                                                        "residual.min_captured_psnr_db=99",
                                                                        "residual.max_size_budget=0.5"]))
    residual = field.report["residual"]
    assert residual["size_budget"] == pytest.approx(0.5) and residual["captured_psnr_db"] < 99
    grew = [line for line in said if line.startswith("the residual gave the captured lights back")]
    assert grew == [f"the residual gave the captured lights back at under 99 dB within 24% of the capture; it takes "
                    f"50% ({residual['captured_psnr_db']:.1f} dB)"]
    plain = fit_field(dataset, device="cpu", progress=False, log=said.append,
                      settings=FitSettings().with_overrides(FAST_FIT + ["residual.kind=lowrank"]))
    assert plain.report["residual"]["size_budget"] == pytest.approx(0.24)
    assert plain.report["residual"]["captured_psnr_db"] >= 40


def _patterned_stack(n, h, w, planes, rank, decay):
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * xx + i) * np.cos((i % 5 + 1) * yy) for i in range(rank)])
    weights = RNG.normal(size=(n, rank)) * decay ** np.arange(rank)
    stack = np.einsum("nk,khw->nhw", weights, patterns)[..., None] * np.linspace(1.0, 0.5, planes) + 1.0
    return stack + 1e-3 * RNG.normal(size=stack.shape)


def test_quantisation_step_gives_the_distortion_it_was_chosen_for():
    """Each kept basis image, quantised with StackPlan's step, adds gain E M step^2 / 12 of squared
    error (float64 reference: the quantised stack against the unquantised projection)."""
    n, h, w = 24, 40, 48
    principal = PrincipalImages.of(_patterned_stack(n, h, w, 1, 10, 0.7))
    plan = StackPlan(principal, 1.0, principal.count - 1)
    distortion = 1e-4 * principal.energies[1]
    steps = plan.steps(distortion, 65535)
    energies = principal.energies[1 : len(steps) + 1]
    # kept: exactly those above it
    assert np.all(energies > distortion) and principal.energies[len(steps) + 1] <= distortion
    pixels = principal.values
    np.testing.assert_allclose(energies * pixels * steps**2 / 12, distortion, rtol=1e-9)
    basis = principal.directions[1 : len(steps) + 1]
    quantised = np.round(basis / steps[:, None]) * steps[:, None]
    noise = (quantised - basis) ** 2
    added = energies * noise.sum(axis=1)  # what each image's noise costs the images weighing it
    assert np.all(np.abs(added / distortion - 1) < 0.15), added / distortion
    floored = StackPlan(principal, 1.0, principal.count - 1, floor=len(steps) + 3).steps(distortion, 65535)
    assert len(floored) == len(steps) + 3 and np.allclose(floored[: len(steps)], steps)
    assert len(StackPlan(principal, 1.0, 2).steps(distortion, 65535)) == 2  # the cap holds


def test_predicted_distortion_is_the_stack_s_error():
    """StackPlan.distortion (what build_residual chooses the bits by) is the squared error of the
    quantised stack at its lights, normalised by their scale (float64 reference), within 25%, for
    8- and 16-bit codes and for images left out."""
    n, h, w = 24, 40, 48
    stack = _patterned_stack(n, h, w, 1, 10, 0.7)
    principal = PrincipalImages.of(stack)
    flat = stack.reshape(n, -1)
    scale = np.sqrt(np.mean(flat**2, axis=1))
    plan = StackPlan(principal, 1.0, principal.count - 1)
    for bits, share in ((8, 1e-3), (16, 1e-4), (16, 1e-7)):
        steps = plan.steps(share * principal.energies[1], 65535 if bits == 16 else 255)
        model = quantised_stack(principal, steps, bits=bits)
        error = np.sum(((stack_light_images(model, np.eye(n)).reshape(n, -1) - flat) / scale[:, None]) ** 2)
        predicted = plan.distortion(steps)
        assert 0.75 < error / predicted < 1.25, (bits, share, error, predicted)


def test_the_bits_are_those_of_the_lower_predicted_error_and_16_are_tried_only_where_they_can_be_finer(monkeypatch):
    """A noisy stack on a tight budget keeps 8-bit codes without a 16-bit search (its 8-bit steps are
    coarser than the codes' finest); a smooth stack on a generous one gets 16-bit codes, and gives the
    captured images back better than the 8-bit choice (float64 error)."""
    n, h, w = 24, 32, 40
    own = np.zeros((n, h, w), np.float32)
    searched = []
    real = build_module.allocate
    monkeypatch.setattr(build_module, "allocate",
                        lambda plans, budget, *, bits: searched.append(bits) or real(plans, budget, bits=bits))
    noisy = (1.0 + 0.3 * RNG.normal(size=(n, h, w, 1))).astype(np.float32)
    model = build_residual(noisy, own, None, settings=ResidualSettings(size_budget=0.1, min_luminance_rank=1,
                                                                        min_captured_psnr_db=0))
    assert searched == [8] and model.luminance.bits == 8
    smooth = _patterned_stack(n, h, w, 1, 12, 0.8).astype(np.float32)
    searched.clear()
    chosen = build_residual(smooth, own, None, settings=ResidualSettings(size_budget=1.0))
    assert searched == [8, 16] and chosen.luminance.bits == 16
    errors = {}
    for bits in (8, 16):
        forced = build_residual(smooth, own, None, settings=ResidualSettings(size_budget=1.0, basis_bits=bits))
        errors[bits] = float(np.mean((light_images(forced, np.eye(n)) - smooth) ** 2))
    assert errors[16] < errors[8], errors


def test_the_search_lands_in_the_window_under_the_budget():
    """On exact bytes, the search stays within the budget and spends nearly all of it (it aims at 1%
    under; compressed bytes are not smooth in the steps, so a few % where no step lands closer), wherever
    the budget is between the floor alone and everything kept; its distortion gives its steps."""
    n, h, w = 30, 36, 48
    principal = PrincipalImages.of(_patterned_stack(n, h, w, 1, 16, 0.8))
    plan = StackPlan(principal, 1.0, principal.count - 1)
    for bits in (8, 16):
        levels = 255 if bits == 8 else 65535
        finest = quantised_bytes(principal, plan.steps(1e-30 * principal.energies[1], levels), bits=bits)
        for share in (0.1, 0.3, 0.6, 0.9):
            log_distortion, (steps,) = allocate([plan], share * finest, bits=bits)
            stored = quantised_bytes(principal, steps, bits=bits)
            assert 0.97 * share * finest <= stored <= share * finest, (bits, share, stored / (share * finest))
            np.testing.assert_array_equal(steps, plan.steps(np.exp(log_distortion), levels))


def test_the_normalised_residual_read_block_by_block_is_the_held_stack():
    """NormalisedResidual's blocks, at any columns (pixel boundaries or not), are the float32 values
    of the normalised luminance and chroma a held stack keeps."""
    n, h, w = 7, 5, 6
    images = RNG.uniform(0.0, 1.0, size=(n, h, w, 3)).astype(np.float32)
    own = RNG.uniform(0.0, 0.5, size=(n, h, w)).astype(np.float32)
    tint = RNG.uniform(0.5, 1.5, size=(h, w, 3)).astype(np.float32)
    scale = RNG.uniform(0.2, 1.0, size=(h, w)).astype(np.float32)
    y, chroma = to_opponent(images - own[..., None] * tint[None])
    held = {"luminance": (y / scale).astype(np.float32).reshape(n, -1),
            "chroma": (chroma / scale[..., None]).astype(np.float32).reshape(n, -1)}
    for kind, flat in held.items():
        source = NormalisedResidual(images, own, tint, scale, kind)
        assert source.light_count == n and source.shape == (h, w, 1 if kind == "luminance" else 2)
        for start, stop in ((0, flat.shape[1]), (3, 4), (1, 18), (5, flat.shape[1] - 1)):
            np.testing.assert_array_equal(source.block(slice(start, stop)), flat[:, start:stop].astype(np.float64))


@pytest.mark.parametrize("channels", [3, 1])
def test_a_residual_too_large_to_hold_is_compressed_from_the_images_bit_for_bit(monkeypatch, channels):
    """Where the normalised stacks would take too much of the memory (HELD_STACK_SHARE), the principal
    images, the codes and the weights are exactly those of the held stacks."""
    n, h, w = 20, 24, 30
    stack = _patterned_stack(n, h, w, channels, 10, 0.8).astype(np.float32)
    own = np.clip(RNG.normal(0.1, 0.05, size=(n, h, w)), 0, None).astype(np.float32)
    colour = RNG.uniform(0.8, 1.2, size=(h, w, channels)).astype(np.float32) if channels == 3 else None
    settings = ResidualSettings(size_budget=0.5)
    held = build_residual(stack, own, colour, settings=settings)
    monkeypatch.setattr(build_module, "HELD_STACK_SHARE", 0.0)
    streamed = build_residual(stack, own, colour, settings=settings)
    for a, b in ((held.luminance, streamed.luminance), (held.chroma, streamed.chroma)):
        if a is None:
            assert b is None
            continue
        for name in ("mean", "codes", "ranges", "weights", "mean_weights"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(held.scale, streamed.scale)


def test_allocation_fits_the_budget_and_spends_it_where_the_energy_is():
    n, h, w = 30, 36, 48
    strong = PrincipalImages.of(_patterned_stack(n, h, w, 1, 16, 0.8))
    weak = PrincipalImages.of(1.0 + 0.05 * (_patterned_stack(n, h, w, 2, 16, 0.8) - 1.0))
    plans = [StackPlan(strong, LUMINANCE_GAIN, strong.count - 1), StackPlan(weak, CHROMA_GAIN, weak.count - 1)]
    spent = []
    for budget in (2e3, 8e3, 3e4, 1e5):
        steps = allocate_steps(plans, budget, bits=8)
        stacks = [quantised_stack(plan.principal, step, bits=8) for plan, step in zip(plans, steps)]
        stored = sum(float(component_bytes(stack).sum()) for stack in stacks)
        assert stored <= budget
        assert stacks[0].rank >= stacks[1].rank  # the luminance's images remove more per byte
        spent.append((stored, stacks[0].rank + stacks[1].rank))
    assert [s for s, _ in spent] == sorted(s for s, _ in spent) and spent[0][1] < spent[-1][1]
    assert spent[-2][0] > 0.9 * 3e4  # a budget that binds is nearly spent
    nothing = allocate_steps(plans, 0.0, bits=8)
    assert all(len(step) == 0 for step in nothing)


def test_allocation_beats_keeping_whole_8_bit_images_at_the_same_bytes():
    """The rate-distortion choice gives the stack back at least as well as the best rank whose
    images, 8 bits over their range, fit the same bytes, and better (float64 error at the captured lights)."""
    n, h, w = 32, 40, 48
    stack = _patterned_stack(n, h, w, 1, 24, 0.85)
    principal = PrincipalImages.of(stack)
    plan = StackPlan(principal, 1.0, principal.count - 1)
    whole = [fit_stack(stack, rank) for rank in range(principal.count)]
    whole_bytes = [float(component_bytes(model).sum()) for model in whole]

    def error(model):
        return float(np.mean((stack_light_images(model, np.eye(n)) - stack) ** 2))

    for budget in (3e3, 1e4, 2e4):  # budgets that bind: the 24-component stack's every image at 8 bits takes 28 kB
        allocated = quantised_stack(principal, allocate_steps([plan], budget, bits=8)[0], bits=8)
        best_whole = min(error(model) for model, size in zip(whole, whole_bytes) if size <= budget)
        assert float(component_bytes(allocated).sum()) <= budget
        assert error(allocated) <= 0.5 * best_whole, (budget, error(allocated), best_whole)  # 6-50 times lower here


def test_principal_images_are_the_stack_s_principal_directions():
    n, h, w = 10, 8, 6
    stack = RNG.normal(size=(n, h, w, 2))
    scale = RNG.uniform(0.5, 2.0, size=n)
    principal = PrincipalImages.of(stack, scale)
    normalised = stack.reshape(n, -1).astype(np.float32) / scale[:, None]  # the stack is kept as float32
    singular = np.linalg.svd(normalised, compute_uv=False)
    np.testing.assert_allclose(principal.energies, singular**2, rtol=1e-9, atol=1e-9)
    directions = principal.directions.astype(np.float64)
    np.testing.assert_allclose(directions @ directions.T, np.eye(n), atol=1e-6)  # float32 directions
    np.testing.assert_allclose(principal.spans, np.ptp(directions[1:], axis=1))
    assert principal.count == n and principal.shape == (8, 6, 2)
    assert LUMINANCE_GAIN == 3.0 and 1.0 < CHROMA_GAIN < 1.1
    black = PrincipalImages.of(np.zeros((4, 3, 3, 1)))
    assert black.count == 1 and np.all(black.mean == 0)


def test_principal_images_and_quantisation_in_blocks_match_a_float64_reference(monkeypatch):
    """With blocks of a few columns (the stack's products a block at a time), the principal images,
    the codes and the fitted weights are those of one float64 product over the whole stack."""
    import warp_highlights.residual.principal as model_residual

    n, h, w = 12, 9, 11
    stack = _patterned_stack(n, h, w, 2, 8, 0.7).astype(np.float32)
    monkeypatch.setattr(model_residual, "_BLOCK_VALUES", 3 * n)  # 3 columns a block, the last one shorter
    principal = PrincipalImages.of(stack)
    flat = stack.reshape(n, -1).astype(np.float64)
    scale = np.sqrt(np.mean(flat**2, axis=1))
    normalised = flat / scale[:, None]
    values, vectors = np.linalg.eigh(normalised @ normalised.T)
    order = np.argsort(values)[::-1]
    np.testing.assert_allclose(principal.energies, values[order], rtol=1e-8)  # the Gram matrix summed block by block
    reference = (vectors[:, order].T @ normalised) / np.sqrt(values[order])[:, None]
    reference *= np.sign(np.sum(reference * principal.directions, axis=1))[:, None]  # a direction's sign is arbitrary
    np.testing.assert_allclose(principal.directions, reference, atol=1e-6)
    steps = principal.spans[:5] / 255
    stack_model = quantised_stack(principal, steps, bits=8)
    codes = np.round((principal.directions[1:6].astype(np.float64)
                      - principal.directions[1:6].min(axis=1, keepdims=True)) / steps[:, None])
    np.testing.assert_array_equal(stack_model.codes.reshape(5, -1), codes.clip(0, 255))
    design = np.concatenate([stack_model.mean.reshape(1, -1),
                             stack_basis(stack_model).reshape(5, -1)]).astype(np.float64)
    solution = np.linalg.solve(design @ design.T + 1e-12 * np.trace(design @ design.T) * np.eye(6), design @ flat.T)
    np.testing.assert_allclose(stack_model.weights, solution[1:].T, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(stack_model.mean_weights, solution[0], rtol=1e-5)


def test_the_budget_buys_chroma_basis_images_where_colour_changes_with_the_light():
    """A stack whose colour swings with the light gets chroma rank; a grey one (chroma 0) none."""
    n, h, w = 24, 32, 40
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * xx + i) * np.cos((i % 4 + 1) * yy) for i in range(12)])
    grey = 0.5 + 0.2 * np.einsum("nk,khw->nhw", RNG.normal(size=(n, 12)), patterns)
    tint = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 12)), patterns[::-1]) * 0.15
    coloured = np.stack([grey + tint, grey - 0.3 * tint, grey - tint], axis=-1).astype(np.float32)
    own = np.zeros((n, h, w), np.float32)
    settings = ResidualSettings(size_budget=2.0, basis_bits=16)
    model = build_residual(coloured, own, None, settings=settings)
    assert model.chroma.rank >= 8, model.chroma.rank
    back = light_images(model, np.eye(n))
    assert np.abs(back - coloured).max() < 5e-3
    flat = build_residual(np.repeat(grey[..., None], 3, axis=-1).astype(np.float32), own, None, settings=settings)
    assert flat.chroma.rank <= 1 and flat.luminance.rank >= 8


@pytest.mark.parametrize("bits", [8, 16])
def test_the_residual_decoded_on_a_device_is_the_host_s(bits, device):
    """``decode_residual`` (the codes dequantised and every light decoded by kernels) gives the images
    ``decoded_images`` gives on the host, to float16 rounding: colour (luminance and chroma) and grey."""
    from warp_highlights.residual.device import decode_residual

    n, h, w = 9, 10, 12
    images = RNG.uniform(0.0, 1.0, size=(n, h, w, 3)).astype(np.float32)
    for planes in (3, 1):
        settings = ResidualSettings(luminance_rank=4, chroma_rank=2, basis_bits=bits)
        model = build_residual(images[..., :planes], np.zeros((n, h, w), np.float32), None, settings=settings)
        assert model.scale is not None and model.luminance.bits == bits
        decoded = decode_residual(model, device).numpy()
        host = decoded_images(model).reshape(n, h * w, planes)
        assert decoded.dtype == np.float16 and decoded.shape == host.shape
        np.testing.assert_allclose(decoded.astype(np.float32), host.astype(np.float32), rtol=2e-3, atol=2e-3)


def test_a_relighter_decodes_on_the_device_where_the_basis_fits_beside_the_images(monkeypatch):
    """``residual.device.decodes_on_device``: the residual's own size, and its float32 basis, codes and float16 images
    within the share of the free device memory; else the host decodes."""

    n, h, w = 9, 10, 12
    images = RNG.uniform(0.0, 1.0, size=(n, h, w, 3)).astype(np.float32)
    model = build_residual(images, np.zeros((n, h, w), np.float32), None,
                           settings=ResidualSettings(luminance_rank=4, chroma_rank=2, basis_bits=16))
    pixels = h * w
    needed = 4 * pixels * (4 * 1 + 2 * 2) + model.chroma.codes.nbytes + 2 * n * pixels * 3
    for free, expected in ((None, False), (needed / 0.75 - 1, False), (needed / 0.75 + 1, True)):
        monkeypatch.setattr(device_module, "device_free_memory", lambda device, free=free: free)
        assert device_module.decodes_on_device(model, w, h, "cuda:0") == expected, free
    monkeypatch.setattr(device_module, "device_free_memory", lambda device: 1 << 40)
    assert not device_module.decodes_on_device(model, w // 2, h // 2, "cuda:0")  # another size: resampled on the host
    assert not device_module.decodes_on_device(ResidualModel(images=images), w, h, "cuda:0")


@pytest.mark.parametrize("band_values", [1 << 20, 96])
def test_decoded_images_match_the_float64_reference(band_values, monkeypatch):
    """Decoded a block of lights at a time, in bands of rows (one band; bands of 2 rows here)."""
    import warp_highlights.residual.decode as residual_module

    monkeypatch.setattr(residual_module, "DECODE_BAND_VALUES", band_values)
    n, h, w = 9, 10, 12
    images = RNG.uniform(0.0, 1.0, size=(n, h, w, 3)).astype(np.float32)
    model = build_residual(images, np.zeros((n, h, w), np.float32), None,
                           settings=ResidualSettings(luminance_rank=4, chroma_rank=2))
    decoded = decoded_images(model, block=4)
    assert decoded.dtype == np.float16 and decoded.shape == (n, h, w, 3)
    np.testing.assert_allclose(decoded, light_images(model, np.eye(n)), atol=2e-3)
    grey = build_residual(images[..., :1], np.zeros((n, h, w), np.float32), None,
                          settings=ResidualSettings(luminance_rank=3))
    np.testing.assert_allclose(decoded_images(grey), light_images(grey, np.eye(n)), atol=2e-3)
    whole = ResidualModel(images=images)
    assert decoded_images(whole) is whole.images


def test_the_default_field_is_at_most_a_quarter_of_the_8_bit_capture(donut_fields, tmp_path):
    dataset, fits = donut_fields
    field = fits["lowrank"]
    written = save_field(field, tmp_path / "f.whf")
    capture = dataset.light_count * field.width * field.height * dataset.channels
    assert written <= 0.25 * capture, (written, capture)


# --- fit-time decisions ---------------------------------------------------------------------------


def _support_reference(params: GaussianParams, targets, images, raster: RasterSettings) -> np.ndarray:
    """float64: sum min(g, S) / sum g per slot, each Gaussian drawn alone at weight 1."""
    out = np.full(params.active.shape, -1.0)
    for b, p in zip(*np.nonzero(params.active)):
        one = params.take([b])
        one.active[:] = False
        one.active[0, p] = True
        g = render_reference(one, images.shape[1], images.shape[2], raster)[0]
        if g.sum() > 0:
            out[b, p] = np.minimum(g, np.maximum(images[targets[b]], 0)).sum() / g.sum()
    return out


def test_support_matches_the_float64_reference(device):
    h, w = 30, 40
    params = GaussianParams.empty(3, 4)
    params.active[:, :3] = True
    params.amplitude[:, :3] = RNG.uniform(0.5, 1.2, (3, 3))
    params.mean[:, :3] = RNG.uniform([0.2, 0.2], [1.1, 0.8], (3, 3, 2))
    params.sigma[:, :3] = RNG.uniform(0.02, 0.08, (3, 3, 2))
    params.theta[:, :3] = RNG.uniform(0, np.pi, (3, 3))
    images = RNG.uniform(0, 0.8, (2, h, w)).astype(np.float32)
    targets = np.array([1, 0, 1])
    raster = RasterSettings()
    batch = GaussianBatch.from_numpy(params, device=device, requires_grad=False)
    got = support_fractions(batch, targets, wp.array(images, dtype=float, device=device), settings=raster)
    expected = _support_reference(params, targets, images.astype(np.float64), raster)
    np.testing.assert_allclose(got, expected, atol=2e-5)
    assert np.all(got[~params.active] == -1)


def test_a_gaussian_whose_retargeting_lands_on_nothing_stays_in_the_residual():
    """Light 0 has two Gaussians; on both of its edges one lands on the neighbour's highlight, the other on black."""
    h, w = 40, 40
    edges = np.array([[0, 1], [0, 2], [1, 0], [2, 0]], dtype=np.int32)
    estimated = GaussianParams.empty(3, 2)
    estimated.active[0] = True
    estimated.amplitude[0] = 1.0
    estimated.mean[0] = [[0.3, 0.3], [0.7, 0.7]]
    estimated.sigma[0] = 0.05
    retargeted = estimated.take(edges[:, 0])
    retargeted.mean[:2, 1] = [0.75, 0.72]
    specular = np.zeros((3, h, w), np.float32)
    for target in (1, 2):  # each neighbour holds a highlight where Gaussian 0 goes, nothing where 1 goes
        specular[target] = (render_reference(estimated.take([0]), h, w, RasterSettings())[0]
                            * (np.arange(w)[None, :] < 20))
    decision = decide_moving(estimated, retargeted, edges, wp.array(specular, dtype=float, device="cpu"),
                             settings=ResidualSettings(), raster=RasterSettings())
    assert decision.moving[0].tolist() == [True, False]
    everything = decide_moving(estimated, retargeted, edges, wp.array(specular, dtype=float, device="cpu"),
                               settings=ResidualSettings(move_support=0.0), raster=RasterSettings())
    assert everything.moving[0].tolist() == [True, True]


def test_highlight_colour_recovers_a_tint_and_stays_white_without_highlights():
    n, h, w = 6, 5, 8
    own = np.zeros((n, h, w), np.float32)
    own[:, :, :4] = RNG.uniform(0.2, 1.0, (n, h, 4))
    tint = np.array([1.3, 0.9, 0.6])
    tint = tint / (tint @ [0.2126, 0.7152, 0.0722])
    specular = own[..., None] * tint
    colour = highlight_colour(specular, own, prior=1e-4)
    np.testing.assert_allclose(colour[:, :4], np.broadcast_to(tint, (h, 4, 3)), atol=0.02)
    np.testing.assert_allclose(colour[:, 4:], 1.0, atol=0.02)


# --- relighting: compose against a float64 reference, exactness, non-negativity --------------------


@pytest.fixture(scope="module")
def donut_fields(small_donut, tmp_path_factory):
    """The small donut fitted twice: low-rank residual ("auto" on a CPU that learns none, ``FAST_FIT``) and
    uncompressed; with its dataset."""
    dataset = ReflectanceField.load(small_donut, progress=False)
    fits = {}
    for name, extra in (("lowrank", ["residual.interpolation=triangle"]), ("images", ["residual.kind=images"])):
        fits[name] = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT + extra), device="cpu",
                               progress=False)
    # the same residual weighed with radial basis weights over every light
    lowrank = fits["lowrank"]
    sigma = residual_sigma(lowrank.residual, lowrank.lights.directions)
    fits["rbf"] = dataclasses.replace(lowrank, residual=dataclasses.replace(lowrank.residual, rbf_sigma=sigma))
    return dataset, fits


def _reference_full(field, directions, scale) -> np.ndarray:
    """float64 residual transfer: blended residual + c(x) S', S' from the relighter's own interpolated sets."""
    residual = light_images(field.residual, light_weights(field.residual, field.triangulation, directions))
    relighter = Relighter(field, device="cpu")
    sets = relighter.interpolated_sets(directions)
    specular = render_reference(sets, field.height, field.width, field.fit_settings().raster)
    colour = 1.0 if field.residual.highlight_colour is None else field.residual.highlight_colour.astype(np.float64)
    return scale * np.maximum(residual + colour * specular[..., None], 0.0)


@pytest.mark.parametrize("kind, decode",
                         [("lowrank", "query"), ("lowrank", "load"), ("lowrank", "auto"), ("images", "auto"),
                          ("rbf", "query"), ("rbf", "auto")])
def test_compose_matches_the_float64_reference(donut_fields, kind, decode, device):
    _, fits = donut_fields
    field = fits[kind]
    directions = np.array([[0.3, 0.2, 0.9], [-0.6, 0.1, 0.5], [0.1, -0.9, -0.3]])
    got = Relighter(field, device=device, scale=2.0, residual_decode=decode).relight(directions).full
    expected = _reference_full(field, directions, 2.0)
    tolerance = 1e-4 if decode == "query" else 2e-3  # else float16 residual images on the device
    np.testing.assert_allclose(got, expected, atol=tolerance * max(1.0, np.abs(expected).max()))


def _reference_full_larger(field, directions, scale, width: int, height: int, *, apart: bool) -> np.ndarray:
    """``_reference_full`` at a larger output size, as the field's arrays resampled to it on the host
    (``resample_image``) compose: the residual (its linear part and its per-pixel scale ``apart`` when the
    low-rank basis is read per query, else the decoded images) and c(x) each resampled."""
    weights = light_weights(field.residual, field.triangulation, directions)
    residual = light_images(field.residual, weights).astype(np.float64)
    lowrank_scale = apart and field.residual.scale is not None
    if lowrank_scale:  # decoded = scale x linear part: the two are resampled apart
        residual = residual / field.residual.scale[None, ..., None]
    grown = np.stack([resample_image(image, width, height) for image in residual]).astype(np.float64)
    if lowrank_scale:
        grown *= resample_image(field.residual.scale, width, height)[None, ..., None]
    raster = field.fit_settings().raster
    sets = widened(Relighter(field, device="cpu").interpolated_sets(directions),
                   raster.upsampled_min_sigma_px / field.height, raster.sigma_eps)
    specular = render_reference(sets, height, width, raster)
    colour = (1.0 if field.residual.highlight_colour is None
              else resample_image(field.residual.highlight_colour, width, height).astype(np.float64))
    return scale * np.maximum(grown + colour * specular[..., None], 0.0)


@pytest.mark.parametrize("kind, decode", [("lowrank", "query"), ("lowrank", "load"), ("images", "auto"),
                                          ("rbf", "query")])
def test_a_larger_output_is_the_host_resampled_composition(donut_fields, kind, decode, device, monkeypatch):
    """Relit at 2.5 times the field's size from its arrays at their own size: the image the arrays resampled on
    the host give (float rounding; float16 images where they are decoded once), and no array is resampled to
    the output size on the host."""
    import warp_highlights.relight.relighter as relighter_module

    _, fits = donut_fields
    field = fits[kind]
    width, height = round(2.5 * field.width), round(2.5 * field.height)
    sizes = []

    def recording(image, w, h):
        sizes.append((w, h))
        return resample_image(image, w, h)

    monkeypatch.setattr(relighter_module, "resample_image", recording)
    directions = np.array([[0.3, 0.2, 0.9], [-0.6, 0.1, 0.5], [0.1, -0.9, -0.3]])
    relighter = Relighter(field, device=device, size=(width, height), scale=2.0, residual_decode=decode)
    got = relighter.relight(directions).full
    assert relighter.upsampled and (width, height) not in sizes
    expected = _reference_full_larger(field, directions, 2.0, width, height, apart=decode == "query")
    tolerance = 1e-4 if decode == "query" else 2e-3  # else float16 residual images
    np.testing.assert_allclose(got, expected, atol=tolerance * max(1.0, np.abs(expected).max()))
    assert got.min() >= 0


def test_residual_transfer_gives_back_the_captured_images(donut_fields):
    dataset, fits = donut_fields
    field = fits["images"]
    relit = Relighter(field, device="cpu").relight(dataset.lights.directions).full
    truth = np.maximum(dataset.images, 0.0)
    mse = ((np.clip(relit, 0, 1) - np.clip(truth, 0, 1)) ** 2).mean(axis=(1, 2, 3))
    psnr = 10 * np.log10(1.0 / np.maximum(mse, 1e-20))
    assert psnr.min() >= 45.0, psnr.min()


def test_the_fit_reports_its_move_check_and_obeys_it(donut_fields):
    dataset, fits = donut_fields
    for field in fits.values():
        residual = field.report["residual"]
        check = residual["move_check"]
        assert 0 < check["lights"] <= min(48, dataset.light_count)
        if abs(check["moving_psnr_db"] - check["blend_psnr_db"]) > 0.001:  # the report rounds to 0.001 dB
            assert check["moves"] == (check["moving_psnr_db"] > check["blend_psnr_db"])
        assert (residual["moving_gaussians"] > 0) == check["moves"]
        assert int(field.moving_mask.sum()) == residual["moving_gaussians"]
        assert 0.0 <= residual["moving_specular_share"] <= 1.0
        assert (residual["moving_specular_share"] > 0.2) == check["moves"]  # the donut's highlights are Gaussians


def test_the_moving_share_is_what_the_moving_gaussians_draw_of_the_specular_energy(monkeypatch):
    """Against the float64 reference rasterizer: one moving Gaussian of three draws a known part of a
    specular stack."""
    from warp_highlights.fit.pipeline import moving_energy_share

    gaussians = GaussianParams.empty(2, 2)
    gaussians = dataclasses.replace(gaussians, amplitude=np.array([[0.8, 0.5], [0.6, 0.0]]),
                                    mean=np.array([[[0.5, 0.5], [1.2, 0.4]], [[0.9, 0.6], [0.0, 0.0]]]),
                                    sigma=np.full((2, 2, 2), 0.08), active=np.array([[True, True], [True, False]]))
    moving = np.array([[True, False], [False, False]])
    raster = RasterSettings()
    specular = render_reference(gaussians, 40, 72, raster) + 0.05  # all drawn, plus what no Gaussian explains
    only = dataclasses.replace(gaussians, amplitude=np.where(moving, gaussians.amplitude, 0.0))
    expected = render_reference(only, 40, 72, raster).sum() / specular.sum()
    share = moving_energy_share(gaussians, moving, wp.array(specular.astype(np.float32), device="cpu"), raster=raster,
                                device="cpu")
    assert 0.1 < share < 0.9 and share == pytest.approx(expected, rel=1e-4)  # float32 sums
    import warp_highlights.fit.pipeline as pipeline

    monkeypatch.setattr(pipeline, "_SHARE_BYTES", 1)  # one light's images at a time: the same share
    both = moving | np.array([[False, False], [True, False]])  # a moving Gaussian in each light
    only = dataclasses.replace(gaussians, amplitude=np.where(both, gaussians.amplitude, 0.0))
    assert moving_energy_share(gaussians, both, wp.array(specular.astype(np.float32), device="cpu"), raster=raster,
                               device="cpu") == pytest.approx(render_reference(only, 40, 72, raster).sum()
                                                              / specular.sum(), rel=1e-4)
    assert moving_energy_share(gaussians, moving & False, wp.array(specular.astype(np.float32), device="cpu"),
                               raster=raster, device="cpu") == 0.0


def test_where_blending_wins_the_check_the_field_keeps_no_gaussians_and_gives_back_the_images(donut_fields, monkeypatch,
                                                                                              tmp_path):
    """The move check's verdict is obeyed: no Gaussian kept, no highlight colour, the residual is the images."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.fit.validation import MoveCheck

    dataset, _ = donut_fields
    lost = MoveCheck(np.arange(3), np.full(3, 30.0), np.full(3, 31.0), 0)
    monkeypatch.setattr(pipeline, "check_moving", lambda *args, **kwargs: lost)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.kind=images"])
    field = fit_field(dataset, settings=settings, device="cpu", progress=False)
    residual = field.report["residual"]
    assert (residual["move_check"]["moves"] is False
            and residual["moving_gaussians"] == residual["staying_gaussians"] == 0)
    assert not field.estimated.active.any() and not field.retargeted.active.any() and not field.moving_mask.any()
    assert field.residual.highlight_colour is None
    np.testing.assert_allclose(field.residual.images.astype(np.float32),
                               dataset.images.astype(np.float16).astype(np.float32))
    relit = Relighter(field, device="cpu").relight(dataset.lights.directions[:4]).full
    np.testing.assert_allclose(relit, np.maximum(field.residual.images[:4].astype(np.float32), 0.0), atol=1e-6)
    save_field(field, tmp_path / "blend.whf")
    back = load_field(tmp_path / "blend.whf")
    assert not back.estimated.active.any() and not back.moving_mask.any()
    np.testing.assert_array_equal(Relighter(back, device="cpu").relight(dataset.lights.directions[:4]).full, relit)


@pytest.mark.slow
def test_auto_learns_the_residual_on_the_cpu_where_its_time_holds_the_epochs(donut_fields, monkeypatch):
    """"auto" on the CPU learns the residual where the training time holds ``cpu_learned_epochs`` of the capture at
    the CPU's pace, as on CUDA (the learned check decides on the moving Gaussians), and says so; with the setting at 0,
    above the schedule's epochs or above what the pace allows it is low rank, and says why."""
    import warp_highlights.fit.pipeline as pipeline

    dataset, _ = donut_fields
    lines = []
    fast = FAST_FIT + ["residual.learned_epochs=3", "residual.learned_tune_epochs=1", "residual.cpu_learned_epochs=3"]
    field = fit_field(dataset, settings=FitSettings().with_overrides(fast), device="cpu", progress=False,
                      log=lines.append)
    assert any(line.startswith("the residual is learned (about 3 epochs in 100 s") for line in lines)
    assert field.report["residual_kind"] == {"requested": "auto", "resolved": "learned"}
    assert field.fit_settings().residual.kind == "learned" and field.residual.learned is not None
    assert field.report["residual"]["cpu_epochs"] == 3.0
    assert field.report["residual"]["learned_check"] is not None  # the Gaussians moved: the check decided
    relit = Relighter(field, device="cpu").relight(dataset.lights.directions[:3]).full
    assert np.isfinite(relit).all() and relit.min() >= 0.0
    kept = fit_field(dataset, settings=FitSettings().with_overrides(fast + ["residual.cpu_learned_epochs=0"]),
                     device="cpu", progress=False)
    assert kept.report["residual_kind"]["resolved"] == "lowrank" and kept.residual.learned is None
    assert kept.report["residual"]["cpu_epochs"] is None
    # a schedule shorter than the epochs asked for never gets them: low rank
    short = fit_field(dataset, settings=FitSettings().with_overrides(fast + ["residual.cpu_learned_epochs=4"]),
                      device="cpu", progress=False)
    assert short.report["residual_kind"]["resolved"] == "lowrank" and short.report["residual"]["cpu_epochs"] == 3.0
    # a pace that the time does not hold the epochs at keeps it low rank, and says why
    monkeypatch.setattr(pipeline, "cpu_epochs", lambda *args, **kwargs: 12.0)
    lines.clear()
    slow = fit_field(dataset, settings=FitSettings().with_overrides(FAST_FIT + ["residual.cpu_learned_epochs=30"]),
                     device="cpu", progress=False, log=lines.append)
    assert slow.report["residual_kind"]["resolved"] == "lowrank" and slow.report["residual"]["cpu_epochs"] == 12.0
    assert any("the residual is low rank (about 12 epochs in 100 s" in line for line in lines)
    assert slow.moving_mask.any()  # low rank, the Gaussians still move


def test_the_default_field_relights_every_captured_light_close_to_its_image(donut_fields):
    dataset, fits = donut_fields
    field = fits["lowrank"]
    assert field.residual.kind == "lowrank" and field.report["residual"]["luminance_rank"] >= 1
    # "auto", resolved once when the fit started: low rank on the CPU where it learns no residual (``FAST_FIT``), as
    # the report and the stored settings say
    assert field.report["residual_kind"] == {"requested": "auto", "resolved": "lowrank"}
    assert field.fit_settings().residual.kind == "lowrank"
    assert fits["images"].residual.kind == fits["images"].report["residual_kind"]["resolved"] == "images"
    relit = Relighter(field, device="cpu").relight(dataset.lights.directions).full
    mse = ((np.clip(relit, 0, 1) - np.clip(dataset.images, 0, 1)) ** 2).mean(axis=(1, 2, 3))
    assert 10 * np.log10(1.0 / mse.max()) >= 30.0


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_no_output_pixel_is_negative_or_non_finite(donut_fields, direction):
    _, fits = donut_fields
    for field in fits.values():
        relit = Relighter(field, device="cpu").relight(np.asarray(direction))
        assert np.all(np.isfinite(relit.full)) and relit.full.min() >= 0.0
        assert np.all(np.isfinite(relit.specular))


# --- the field file ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["lowrank", "images"])
@pytest.mark.parametrize("written_as", ["current", "version 3", "version 2"])
def test_residual_file_round_trip(donut_fields, kind, written_as, tmp_path):
    """Fields round-trip; a version-3 file (the basis codes stored as they are) and a version-2 file
    (before learned residuals, too: no ``residual.learned``) load the same."""
    from test_field import rewrite

    _, fits = donut_fields
    field = fits[kind]
    path = tmp_path / "f.whf"
    save_field(field, path)
    if written_as != "current":
        assert FORMAT_VERSION == 9
        version = int(written_as.split()[1])
        data = path.read_bytes()
        def residual_before(r):  # no learned residual before version 3, no decoder widths before 6, no bounds before 7
            learned = r.get("learned")
            r = {key: value for key, value in r.items() if key != "learned" or version > 2}
            if "learned" in r and learned is not None:
                r["learned"] = {key: value for key, value in learned.items() if key not in ("hidden", "bounds")}
            return r

        stacks = {name: getattr(field.residual, name) for name in ("luminance", "chroma")
                  if getattr(field.residual, name) is not None}
        # as they are
        codes = {f"residual__{'Y' if name == 'luminance' else 'C'}_codes": stack.codes.transpose(0, 3, 1, 2)
                 for name, stack in stacks.items()}
        # version 5's
        chunked = [f"residual/{prefix}_codes{suffix}" for prefix in ("Y", "C")
                   for suffix in (".npy.blosc", ".lengths.npy")]
        rewrite(data, path, header=lambda h: {**h, "format_version": version,
                                              "residual": residual_before(h["residual"])}, drop=chunked, **codes)
    back = load_field(path)
    np.testing.assert_array_equal(back.moving, field.moving)
    a, b = field.residual, back.residual
    assert a.kind == b.kind and a.channels == b.channels
    if a.kind == "lowrank":
        for name in ("luminance", "chroma"):
            for part in ("mean", "codes", "ranges", "weights"):
                np.testing.assert_array_equal(getattr(getattr(a, name), part), getattr(getattr(b, name), part))
    else:
        np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.highlight_colour, b.highlight_colour)
    if a.kind == "lowrank":
        assert a.scale is not None and a.scale.min() > 0
        np.testing.assert_array_equal(a.scale, b.scale)
    directions = np.array([[0.2, 0.4, 0.8]])
    np.testing.assert_array_equal(Relighter(field, device="cpu").relight(directions).full,
                                  Relighter(back, device="cpu").relight(directions).full)
    assert back.file_sizes["residual"] > 0


def test_a_field_without_chroma_basis_images_round_trips_and_relights(donut_fields, tmp_path):
    """The budget may leave the chroma its mean image alone (rank 0)."""
    dataset, fits = donut_fields
    field = fits["lowrank"]
    residual = field.residual
    _, opponent = to_opponent(light_images(residual, np.eye(field.light_count)))
    chroma = fit_stack(opponent / residual.scale[..., None], 0)
    assert chroma.rank == 0 and chroma.codes.shape == (0, field.height, field.width, 2)
    plain = dataclasses.replace(field, residual=dataclasses.replace(residual, chroma=chroma))
    save_field(plain, tmp_path / "f.whf")
    back = load_field(tmp_path / "f.whf")
    assert back.residual.chroma.rank == 0
    directions = np.array([[0.2, 0.4, 0.8], [-0.5, 0.3, 0.4]])
    for decode in ("query", "load"):
        relit = Relighter(back, device="cpu", residual_decode=decode).relight(directions).full
        np.testing.assert_allclose(relit, _reference_full(plain, directions, 1.0),
                                   atol=2e-3 * max(1.0, float(relit.max())))


def test_an_unknown_residual_decode_is_refused(donut_fields):
    _, fits = donut_fields
    with pytest.raises(InputError, match="residual_decode must be one of auto, query, load"):
        Relighter(fits["lowrank"], device="cpu", residual_decode="lazy")


def test_a_residual_entry_of_the_wrong_shape_is_one_line(donut_fields, tmp_path):
    import zipfile

    _, fits = donut_fields
    path = tmp_path / "f.whf"
    save_field(fits["lowrank"], path)
    damaged = tmp_path / "damaged.whf"
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(damaged, "w") as target:
        for info in source.infolist():
            data = source.read(info)
            if info.filename == "residual/Y_weights.npy":
                import io

                buffer = io.BytesIO()
                np.save(buffer, np.zeros((3, 1), "<f4"))
                data = buffer.getvalue()
            target.writestr(info, data)
    with pytest.raises(InputError, match=r"Y_weights.*shape") as error:
        load_field(damaged)
    assert "\n" not in str(error.value)


@pytest.fixture(scope="module")
def sample_fields(data_root):
    """Both real samples fitted small and fast (64 px high, few iterations): (field, held-out dataset)."""
    from conftest import TINY_FIT

    overrides = [value for flag, value in zip(TINY_FIT[::2], TINY_FIT[1::2])]
    fields = []
    for name, heldout in (("synthrti-object1-material5/Dome", "synthrti-object1-material5/Test"),
                          ("realrti-item11", None)):
        folder = data_root / name
        if not folder.is_dir():
            pytest.skip(f"sample {name} not found under {data_root} (set WARP_HIGHLIGHTS_DATA)")
        dataset = ReflectanceField.load(folder, heldout=None if heldout is None else data_root / heldout,
                                        progress=False)
        if heldout is None:
            dataset = dataset.split_every(5)
        size = (round(64 * dataset.width / dataset.height), 64)
        field = fit_field(dataset, settings=FitSettings().with_overrides(overrides), size=size, device="cpu",
                          progress=False)
        fields.append((field, dataset))
    return fields


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_no_output_pixel_of_the_samples_is_negative_or_non_finite(sample_fields, direction):
    for field, _ in sample_fields:
        relit = Relighter(field, device="cpu", scale=1.0 / field.exposure).relight(np.asarray(direction))
        assert np.all(np.isfinite(relit.full)) and relit.full.min() >= 0.0


def test_the_samples_relit_at_their_held_out_lights_beat_the_per_pixel_fits(sample_fields):
    """A smoke check of the whole chain on real data at 64 px: the field is not far from the alpha
    blend and ahead of PTM (benchmarks/bench_quality.py is the measurement)."""
    from warp_highlights.relight.evaluation import evaluate_field

    for field, dataset in sample_fields:
        summary = evaluate_field(field, dataset, device="cpu", methods=("circular", "alpha"), barycentric_face=None,
                                 baselines=("ptm",)).summary()
        srgb = summary["full_srgb"]
        assert srgb["circular"]["mean"] > srgb["ptm"]["mean"]
        assert srgb["circular"]["mean"] > srgb["alpha"]["mean"] - 2.5


def test_16_bit_bases_quantise_finer_and_round_trip_through_the_file(donut_fields, tmp_path):
    from dataclasses import replace as replaced

    n, h, w = 12, 9, 7
    stack = (RNG.normal(size=(n, 3)) @ RNG.normal(size=(3, h * w)) + 0.5).reshape(n, h, w, 1)
    errors = {bits: np.abs(stack_light_images(fit_stack(stack, 3, bits=bits), np.eye(n)) - stack).max()
              for bits in (8, 16)}
    # 16-bit codes leave the float16 mean image as the larger error (about 1e-3 here)
    assert fit_stack(stack, 3, bits=16).codes.dtype == np.uint16 and errors[16] < errors[8] / 8
    with pytest.raises(InputError, match="8 or 16"):
        fit_stack(stack, 3, bits=12)
    _, fits = donut_fields
    field = fits["lowrank"]
    residual = field.residual
    sixteen = ResidualModel(
        luminance=fit_stack(stack_light_images(residual.luminance, np.eye(field.light_count)), 4, bits=16),
        chroma=fit_stack(stack_light_images(residual.chroma, np.eye(field.light_count)), 2, bits=16),
        highlight_colour=residual.highlight_colour, scale=residual.scale,
    )
    path = tmp_path / "sixteen.whf"
    save_field(replaced(field, residual=sixteen), path)
    back = load_field(path).residual
    assert back.luminance.bits == 16 and back.chroma.bits == 16
    np.testing.assert_array_equal(back.luminance.codes, sixteen.luminance.codes)
    np.testing.assert_array_equal(back.chroma.mean_weights, sixteen.chroma.mean_weights)


def test_sampled_rows_are_spread_bands_or_every_row():
    assert np.array_equal(sampled_rows(54, 96, 1), np.arange(54))  # a small image is compressed whole
    rows = sampled_rows(1080, 1920, 1)
    assert len(rows) % 8 == 0 and len(rows) >= rate_module._RATE_SHARE * 1080 and len(np.unique(rows)) == len(rows)
    bands = rows.reshape(-1, 8)
    # whole bands, none at the very edges
    assert np.all(np.diff(bands, axis=1) == 1) and rows.min() > 0 and rows.max() < 1079
    strips = np.floor(bands.mean(axis=1) / (1080 / len(bands)))
    assert np.array_equal(strips, np.arange(len(bands)))  # one band in each equal strip


def test_the_sampled_rate_search_keeps_the_exact_budget(monkeypatch):
    """On images large enough for the rate search to deflate a sample of rows, the exact bytes of its
    choice stay within the budget and spend as much of it as a search on exact bytes does."""
    n, h, w = 40, 320, 256
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 3 * xx + i) * np.cos((i % 5 + 1) * 2 * yy)
                         * np.exp(-((xx - 0.4) ** 2 + (yy - 0.5) ** 2) * (i % 3 + 1))
                         for i in range(24)])
    stack = np.einsum("nk,khw->nhw", RNG.normal(size=(n, 24)) * 0.85 ** np.arange(24), patterns)[..., None] + 1.0
    stack = stack + 1e-3 * RNG.normal(size=stack.shape)
    principal = PrincipalImages.of(stack)
    plan = StackPlan(principal, 1.0, principal.count - 1)
    assert not RateSample(principal, 4).exact
    for bits in (8, 16):
        for budget in (2e4, 6e4, 2e5):
            steps = allocate_steps([plan], budget, bits=bits)[0]
            stored = quantised_bytes(principal, steps, bits=bits)
            with monkeypatch.context() as patch:
                patch.setattr(rate_module, "_RATE_MIN_VALUES", 1 << 40)  # every row: the exact search
                assert RateSample(principal, 4).exact
                exact = quantised_bytes(principal, allocate_steps([plan], budget, bits=bits)[0], bits=bits)
            assert exact <= stored <= budget or 0.99 * exact <= stored <= budget, (bits, budget, stored, exact)
            assert stored == float(component_bytes(quantised_stack(principal, steps, bits=bits)).sum())


def test_where_the_finest_8_bit_codes_plainly_fit_only_16_bits_are_searched_and_the_result_is_the_same(monkeypatch):
    """On images large enough for a sampled rate search, a generous budget holds every basis image at the
    finest 8-bit step by the sampled bytes alone: the 8-bit search and its deflate of every row are
    skipped (16-bit codes beat them), and the residual is bit for bit the one with both searches."""
    n, h, w = 16, 256, 1024
    own = np.zeros((n, h, w), np.float32)
    smooth = _patterned_stack(n, h, w, 1, 10, 0.8).astype(np.float32)
    searched = []
    real = build_module.allocate
    monkeypatch.setattr(build_module, "allocate",
                        lambda plans, budget, *, bits: searched.append(bits) or real(plans, budget, bits=bits))
    settings = ResidualSettings(size_budget=1.0)
    quick = build_residual(smooth, own, None, settings=settings)
    assert searched == [16] and quick.luminance.bits == 16
    searched.clear()
    monkeypatch.setattr(build_module, "finest_within", lambda plans, budget, *, bits: None)
    both = build_residual(smooth, own, None, settings=settings)
    assert searched == [8, 16]
    assert (np.array_equal(quick.luminance.codes, both.luminance.codes)
            and np.array_equal(quick.luminance.weights, both.luminance.weights))


@settings(max_examples=80, deadline=None)
@given(lights=st.integers(1, 6), edges=st.integers(1, 9), slots=st.integers(1, 5), seed=st.integers(0, 2**31 - 1),
       empty=st.floats(0.0, 1.0))
def test_the_move_decision_s_median_is_numpy_s_nanmedian(lights, edges, slots, seed, empty):
    """``_nan_median`` (sorted, NaN last) gives np.nanmedian's values bit for bit, NaN where a column is empty."""
    import warnings

    rng = np.random.default_rng(seed)
    values = rng.normal(size=(lights, edges, slots)).round(2)  # ties too
    values[rng.random(values.shape) < empty] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nanmedian(values, axis=1)
    np.testing.assert_array_equal(moving_module._nan_median(values), expected)


def _sampled_principal(seed: int) -> PrincipalImages:
    """Principal images of a 40-light 320x256 stack: large enough for the rate search to sample rows."""
    rng = np.random.default_rng(seed)
    n, h, w = 40, 320, 256
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 3 * xx + i) * np.cos((i % 5 + 1) * 2 * yy)
                         * np.exp(-((xx - 0.4) ** 2 + (yy - 0.5) ** 2) * (i % 3 + 1))
                         for i in range(24)])
    stack = np.einsum("nk,khw->nhw", rng.normal(size=(n, 24)) * 0.85 ** np.arange(24), patterns)[..., None] + 1.0
    return PrincipalImages.of(stack + 1e-3 * rng.normal(size=stack.shape))


def test_the_rate_search_deflates_no_image_twice_at_one_step_and_keeps_the_budget(monkeypatch):
    """On images large enough for a sampled search, no image of any sample is compressed twice at the same
    step and bits, and the exact bytes of the answer stay within the budget (within 1% under it where
    no image's entry makes the bytes jump by more than that: most budgets here)."""
    principal = _sampled_principal(2)
    plan = StackPlan(principal, 1.0, principal.count - 1)
    assert not RateSample(principal, 4).exact
    measured = []
    real = RateSample._measured

    def recorded(self, indices, steps, bits, *, keyed):
        measured.extend((id(self), int(i), float(steps[i]), bits) for i in indices)
        return real(self, indices, steps, bits, keyed=keyed)

    monkeypatch.setattr(RateSample, "_measured", recorded)
    shares = []
    for bits in (8, 16):
        for budget in (1e5, 2e5, 4e5):
            measured.clear()
            steps = allocate_steps([plan], budget, bits=bits)[0]
            assert len(measured) == len(set(measured))
            stored = quantised_bytes(principal, steps, bits=bits)
            assert stored <= budget
            shares.append(stored / budget)
    assert sum(share >= 0.99 for share in shares) >= 5, shares


@pytest.mark.parametrize("budget", [2e5, 4e5])
def test_calibration_absorbs_a_sample_s_bias_in_one_exact_measurement(monkeypatch, budget):
    """A sample whose bytes run 6% over every whole image's (as bands of rows can, alike for every image
    of a capture): scaled by the whole bytes of a few images, the search's first exact measurement
    lands in the budget's 1% window (uncalibrated, it would land about 6% under it and measure again)."""
    principal = _sampled_principal(2)
    plan = StackPlan(principal, 1.0, principal.count - 1)
    real_chunk_bytes, real_bytes = RateSample.chunk_bytes, RateSample.bytes
    whole = RateSample(principal, principal.count - 1, whole=True)
    exact = []

    # the sample: each image's whole bytes, 6% over, per sampled row
    def biased(self, steps, *, bits, keep=None, images=None):
        if self.exact:
            return real_chunk_bytes(self, steps, bits=bits, keep=keep, images=images)
        return np.rint(real_chunk_bytes(whole, steps, bits=bits, images=images) * 1.06 / self.scale).astype(np.int64)

    def counted(self, steps, *, bits, keep=None, calibration=1.0):
        exact.append(self.exact)
        return real_bytes(self, steps, bits=bits, keep=keep, calibration=calibration)

    monkeypatch.setattr(RateSample, "chunk_bytes", biased)
    monkeypatch.setattr(RateSample, "bytes", counted)
    steps = allocate_steps([plan], budget, bits=16)[0]
    assert exact.count(True) == 1
    monkeypatch.setattr(RateSample, "bytes", real_bytes)
    assert 0.99 * budget <= quantised_bytes(principal, steps, bits=16) <= budget


def test_the_modelled_first_step_meets_the_goal_of_the_model_it_fits():
    """``_modelled_distortion``: for bytes the model itself gives at one distortion, the distortion where
    it gives the goal (roots to 1e-9; where an image enters the kept set, the model's bytes jump by its
    range and weights, and the goal may lie in the jump: its two sides then bracket it); None where the
    bytes are under the ranges' and weights' own."""
    principal = PrincipalImages.of(_patterned_stack(30, 36, 48, 1, 16, 0.8))
    plans = [StackPlan(principal, 3.0, principal.count - 1)]
    levels = 65535
    top = np.log(plans[0].energies.max())
    lowest, highest = top - 35.0, top + 1.0
    measured = rate_module._modelled_bytes(plans, levels, top - 6.0, 3.5)
    for goal_share in (0.5, 2.0, 4.0):
        goal = goal_share * measured
        x = rate_module._modelled_distortion(plans, levels, top - 6.0, measured, goal, lowest, highest)
        sides = [rate_module._modelled_bytes(plans, levels, x + dx, 3.5) for dx in (-1e-7, 0.0, 1e-7)]
        assert min(sides) * (1 - 1e-6) <= goal <= max(sides) * (1 + 1e-6)
    assert rate_module._modelled_distortion(plans, levels, top - 6.0, 1.0, measured, lowest, highest) is None


@pytest.mark.parametrize("device", ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else []))
def test_own_highlights_past_one_launch_are_drawn_in_parts_into_one_stack(device, monkeypatch):
    """Lights whose images pass one launch's 2^31 pixels (100 photographs of 24 megapixels) are drawn a
    launch's worth at a time into one (n, H, W) array: forced here by a bound of 2 images; every pixel
    is the one batch's, bit for bit, none left from the empty allocation."""
    from warp_highlights.kernels.raster import Rasterizer
    from warp_highlights.residual.inputs import render_own_on_device

    rng = np.random.default_rng(11)
    sets = GaussianParams.empty(5, 3)
    sets.active[:, :2] = True
    sets.amplitude[:, :2] = rng.uniform(0.5, 1.5, (5, 2))
    sets.mean[:, :2] = rng.uniform(0.2, 1.2, (5, 2, 2))
    sets.sigma[:, :2] = rng.uniform(0.03, 0.2, (5, 2, 2))
    sets.theta[:, :2] = rng.uniform(0, 3, (5, 2))
    whole = render_own_on_device(sets, 27, 48, raster=RasterSettings(), device=device).numpy()
    monkeypatch.setattr(Rasterizer, "problems_per_launch", property(lambda self: 2))
    parts = render_own_on_device(sets, 27, 48, raster=RasterSettings(), device=device)
    assert parts.shape == (5, 27, 48)
    np.testing.assert_array_equal(parts.numpy(), whole)
    assert (whole.reshape(5, -1).max(axis=1) > 0.1).all()


def test_the_learned_checks_winner_learns_anew_where_its_unseen_lights_are_many():
    from warp_highlights.model.config import ResidualSettings
    from warp_highlights.residual.learned import learns_anew

    settings = ResidualSettings()  # learned_anew_share by device: 0.15 on the CPU, 0 on CUDA
    assert not learns_anew(settings, 6, 250, False) and not learns_anew(settings, 6, 49, False)  # 0.024, 0.122
    assert learns_anew(settings, 3, 16, False) and learns_anew(settings, 6, 25, False)  # 0.19, 0.24
    assert not learns_anew(settings, 6, 40, False) and learns_anew(settings, 6, 39, False)  # 0.150, 0.154
    assert learns_anew(settings, 6, 49, True) and learns_anew(settings, 1, 250, True)  # always on CUDA
    for on_cuda in (False, True):  # a share set is the same on every device
        assert not learns_anew(ResidualSettings(learned_anew_share=0.5), 6, 16, on_cuda)
        assert learns_anew(ResidualSettings(learned_anew_share=0.0), 1, 250, on_cuda)
        assert not learns_anew(ResidualSettings(learned_anew_share=0.15), 6, 49, on_cuda)


def test_decoded_images_round_alike_whatever_the_blas_threads():
    """A low-rank residual decoded once per light is the same bit for bit whether the BLAS library may thread its
    products or not (it blocks a float32 product by its thread count): relighting on one core gives the images of
    relighting on all of them."""
    import threadpoolctl

    rng = np.random.default_rng(3)
    stack = rng.normal(size=(24, 90, 160, 1)).astype(np.float32)
    residual = ResidualModel(luminance=fit_stack(stack, 20, bits=16))
    free = decoded_images(residual)
    with threadpoolctl.threadpool_limits(limits=1, user_api="blas"):
        single = decoded_images(residual)
    np.testing.assert_array_equal(free, single)
