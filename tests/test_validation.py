"""The fit's leave-one-out check of moving against blending (``fit.validation``): the left-out lights and
their triangles against brute force, the edges it retargets, and its verdict on scenes where moving must
win and must lose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from reference import render as render_reference
from warp_highlights.fit.validation import (
    apart_inside,
    check_moving,
    leave_one_out,
    plan_check,
    spread_lights,
)
from warp_highlights.model.config import FitSettings, RasterSettings, RetargetSettings
from warp_highlights.model.gaussians import GaussianParams
from warp_highlights.model.lights import LightSet
from warp_highlights.model.triangulation import SphericalTriangulation


def _greedy_reference(directions: np.ndarray, count: int) -> list[int]:
    """Farthest-point sampling by explicit loops: each pick has the largest angle to its nearest pick."""
    centre = directions.sum(axis=0)
    chosen = [int(np.argmax([d @ centre for d in directions]))]
    while len(chosen) < count:
        best, best_angle = None, -1.0
        for index, direction in enumerate(directions):
            nearest = min(np.arccos(np.clip(direction @ directions[c], -1, 1)) for c in chosen)
            if nearest > best_angle + 1e-12:
                best, best_angle = index, nearest
        chosen.append(best)
    return sorted(chosen)


def test_spread_lights_is_farthest_point_sampling():
    directions = LightSet.fibonacci_dome(40).directions
    assert spread_lights(directions, 12).tolist() == _greedy_reference(directions, 12)
    assert spread_lights(directions, 40).tolist() == list(range(40))
    assert spread_lights(directions, 99).tolist() == list(range(40))
    assert spread_lights(directions, 0).size == 0


def test_each_left_out_light_lies_in_a_face_of_the_other_lights_triangulation():
    directions = LightSet.fibonacci_sphere(24).directions
    loo = leave_one_out(directions, np.arange(24))
    assert loo.lights.tolist() == list(range(24))
    for light, corners, weights in zip(loo.lights, loo.vertices, loo.barycentric):
        others = np.delete(np.arange(24), light)
        assert light not in corners
        faces = {tuple(sorted(others[face])) for face in SphericalTriangulation(directions[others]).faces}
        assert tuple(sorted(corners)) in faces
        assert np.all(weights >= -1e-12) and abs(weights.sum() - 1) < 1e-12
        point = weights @ directions[corners]  # on the face's plane, along the left-out direction
        np.testing.assert_allclose(point / np.linalg.norm(point), directions[light], atol=1e-9)


def _random_dome(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.15
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


@pytest.mark.parametrize("name, directions", [
    ("dome16", LightSet.fibonacci_dome(16).directions),
    ("dome49", LightSet.fibonacci_dome(49).directions),
    ("sphere40", LightSet.fibonacci_sphere(40).directions),
    ("random30", _random_dome(30, 3)),
    ("random60", _random_dome(60, 8)),
])
def test_lights_left_out_together_lie_between_captured_neighbours(name, directions):
    """``apart_inside`` against brute force: left out all at once, every chosen light lies inside the rest's
    dome, in the very triangle (and at the weights) it has when left out alone; no two share an edge; every
    inside light not chosen touches a chosen one (nothing more could be added); the first is the inside light
    farthest from the rim (on a sphere, nearest the lights' mean direction)."""
    n = len(directions)
    triangulation = SphericalTriangulation(directions)
    loo = leave_one_out(directions, np.arange(n))
    rows = apart_inside(loo, triangulation)
    assert len(rows) and len(set(rows.tolist())) == len(rows)
    chosen = loo.lights[rows]
    rest = np.setdiff1d(np.arange(n), chosen)
    location = SphericalTriangulation(directions[rest]).locate(directions[chosen])
    assert not location.clamped.any()
    for row, corners, weights in zip(rows, rest[location.vertices], location.barycentric):
        alone = dict(zip(loo.vertices[row].tolist(), loo.barycentric[row]))
        assert sorted(alone) == sorted(corners.tolist())
        np.testing.assert_allclose([alone[c] for c in corners.tolist()], weights, atol=1e-9)
    touching = {(int(a), int(b)) for a, b in triangulation.directed_edges()}
    for a in chosen:
        for b in chosen:
            assert (int(a), int(b)) not in touching
    inside = loo.lights[loo.inside]
    for light in np.setdiff1d(inside, chosen):
        assert any((int(light), int(c)) in touching for c in chosen)
    rim = np.unique(triangulation.boundary_edges())
    if len(rim):
        away = [min(np.arccos(np.clip(directions[light] @ directions[r], -1, 1)) for r in rim) for light in inside]
        assert chosen[0] == inside[int(np.argmax(away))]
    else:
        centre = directions.sum(axis=0)
        assert chosen[0] == int(np.argmax(directions @ centre))


def test_no_light_is_taken_where_every_left_out_light_lies_on_the_rim():
    directions = LightSet.fibonacci_dome(16).directions
    loo = leave_one_out(directions, np.arange(16))
    rim_only = dataclasses.replace(loo, inside=np.zeros(len(loo.lights), bool))
    assert apart_inside(rim_only, SphericalTriangulation(directions)).size == 0


def test_the_plan_retargets_exactly_the_triangle_edges_the_capture_lacks():
    directions = LightSet.fibonacci_dome(30).directions
    edges = SphericalTriangulation(directions).directed_edges()
    plan = plan_check(directions, edges, 10)
    assert len(plan.loo.lights) == 10
    needed = {(int(a), int(b)) for corners in plan.loo.vertices for a in corners for b in corners if a != b}
    expected = sorted(needed - {tuple(e) for e in edges.tolist()})
    assert [tuple(e) for e in plan.missing.tolist()] == expected
    assert len(plan_check(directions, edges, 0).loo.lights) == 0


# --- the verdict on scenes built by hand ------------------------------------------------------------

SIZE = 40
RASTER = RasterSettings()


def _highlight_at(direction: np.ndarray) -> np.ndarray:
    """Where the scene's one highlight sits under a light (image heights): it follows the light."""
    return 0.5 + 0.3 * direction[:2]


def _one_gaussian_sets(means: np.ndarray) -> GaussianParams:
    sets = GaussianParams.empty(len(means), 1)
    sets.active[:] = True
    sets.amplitude[:] = 1.0
    sets.mean[:, 0] = means
    sets.sigma[:] = 0.06
    return sets


def _scene():
    """A dome of 16 lights over a grey plane whose one highlight moves with the light; every directed
    edge between two lights given (nothing to retarget), each light's Gaussian exactly on its highlight."""
    directions = LightSet.fibonacci_dome(16, min_elevation_deg=30).directions
    n = len(directions)
    edges = np.array([(a, b) for a in range(n) for b in range(n) if a != b], dtype=np.int32)
    estimated = _one_gaussian_sets(np.array([_highlight_at(d) for d in directions]))
    own = render_reference(estimated, SIZE, SIZE, RASTER).astype(np.float32)
    images = (0.2 + own)[..., None].repeat(3, axis=3).astype(np.float32)
    return directions, edges, estimated, own, images


def _check(directions, edges, estimated, retargeted, own, images, *, moving=None, keep=0):
    settings = dataclasses.replace(FitSettings(), retarget=RetargetSettings(rigid_iterations=0, iterations=0))
    plan = plan_check(directions, edges, 16)
    assert len(plan.missing) == 0
    return check_moving(plan, estimated, retargeted, edges, np.zeros(retargeted.active.shape, np.float32),
                        estimated.active.copy() if moving is None else moving, wp.array(own, dtype=float, device="cpu"),
                        images, own, None, factor=1.0, settings=settings, device="cpu", keep=keep)


def test_moving_wins_where_the_gaussians_follow_the_highlight():
    directions, edges, estimated, own, images = _scene()
    retargeted = _one_gaussian_sets(np.array([_highlight_at(directions[b]) for b in edges[:, 1]]))
    check = _check(directions, edges, estimated, retargeted, own, images)
    assert len(check.lights) == 16 and check.moves
    assert check.moving_psnr.mean() > check.blend_psnr.mean() + 3.0
    assert check.report()["moves"] is True and check.report()["lights"] == 16


def test_the_check_keeps_the_moved_highlights_it_is_asked_for():
    """``keep``: the moved highlights of that many checked lights, spread over them; over the plane's
    flat 0.2 (every corner's residual), they give the moving prediction's score back."""
    from warp_highlights.quality.metrics import srgb_psnr

    directions, edges, estimated, own, images = _scene()
    retargeted = _one_gaussian_sets(np.array([_highlight_at(directions[b]) for b in edges[:, 1]]))
    check = _check(directions, edges, estimated, retargeted, own, images, keep=4)
    plan = plan_check(directions, edges, 16)
    assert check.kept_lights.tolist() == sorted(plan.loo.lights[plan.apart[:4]].tolist())
    assert check.kept_highlights.shape == (4, SIZE, SIZE, 3) and check.kept_highlights.max() > 0.5
    for light, drawn in zip(check.kept_lights, check.kept_highlights):
        row = int(np.flatnonzero(check.lights == light)[0])
        assert srgb_psnr(0.2 + drawn, images[light]) == pytest.approx(check.moving_psnr[row], abs=1e-3)
    assert len(_check(directions, edges, estimated, retargeted, own, images).kept_lights) == 0


def test_blending_wins_where_the_retargeted_gaussians_go_astray():
    directions, edges, estimated, own, images = _scene()
    astray = np.array([_highlight_at(directions[b]) + [0.35, -0.3] for b in edges[:, 1]])
    check = _check(directions, edges, estimated, _one_gaussian_sets(astray), own, images)
    assert not check.moves
    assert check.moving_psnr.mean() < check.blend_psnr.mean()


def test_gaussians_that_stay_predict_what_blending_predicts():
    """Nothing moves on its path (every retargeted set is its source set) or nothing is allowed to move:
    both predictions are the blend of the corners' images."""
    directions, edges, estimated, own, images = _scene()
    still = estimated.take(edges[:, 0])
    check = _check(directions, edges, estimated, still, own, images)
    np.testing.assert_allclose(check.moving_psnr, check.blend_psnr, atol=0.05)
    retargeted = _one_gaussian_sets(np.array([_highlight_at(directions[b]) for b in edges[:, 1]]))
    frozen = _check(directions, edges, estimated, retargeted, own, images, moving=np.zeros((16, 1), bool))
    assert len(frozen.lights) == 0 and frozen.moves  # nothing moves: nothing to check


def test_the_moving_prediction_is_what_the_relighter_draws_over_the_other_lights(small_donut, monkeypatch):
    """For left-out lights of a real fit (retargeted missing edges, Gaussians that stay, highlight colour),
    the check's moving prediction scores what the Relighter gives for a field built over the other lights."""
    import warp_highlights.fit.pipeline as pipeline
    from conftest import FAST_FIT
    from warp_highlights.fit.lost import lost_slots, place_lost
    from warp_highlights.fit.paths import decide_paths
    from warp_highlights.fit.retargeting import restore_vanished, retarget
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.field import HighlightField
    from warp_highlights.model.residual import ResidualModel
    from warp_highlights.quality.metrics import srgb_psnr
    from warp_highlights.relight.relighter import Relighter

    calls = {}
    original = pipeline.check_moving

    def recorded(*args, **kwargs):
        calls["args"], calls["kwargs"] = args, kwargs
        calls["check"] = original(*args, **kwargs)
        return calls["check"]

    monkeypatch.setattr(pipeline, "check_moving", recorded)
    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + ["residual.check_lights=5", "residual.move_support=0.7"])
    pipeline.fit_field(dataset, settings=settings, device="cpu", progress=False)
    plan, estimated, retargeted, edges, _, moving, specular, images, own, colour = calls["args"]
    check, factor = calls["check"], calls["kwargs"]["factor"]
    assert len(plan.missing) > 0 and len(check.lights) == 5
    assert colour is not None and moving.sum() < estimated.active.sum()  # some Gaussians stay in place

    directions = dataset.lights.directions
    n = len(directions)
    triangulations = {j: SphericalTriangulation(directions[np.delete(np.arange(n), j)]) for j in check.lights}
    wanted = {(int(a), int(b)) for j, tri in triangulations.items()
              for a, b in np.delete(np.arange(n), j)[tri.directed_edges()]}
    extra = np.array(sorted(wanted - {tuple(e) for e in edges.tolist()}), dtype=np.int32)
    more = retarget(estimated, specular, extra, settings=settings.retarget, raster=settings.raster, device="cpu",
                    directions=directions).params
    more, vanished = restore_vanished(estimated.take(extra[:, 0]), more, settings.retarget.vanish_share,
                                      sigma_eps=settings.raster.sigma_eps)
    # the lost ones placed where their motion expects them, as the fit's own edges' are
    motion = calls["kwargs"]["motion"]
    assert motion is not None
    lost = lost_slots(estimated.take(extra[:, 0]), more, vanished, specular.shape[2] / specular.shape[1],
                      settings.retarget.lost_share)
    more, _, _ = place_lost(estimated.take(extra[:, 0]), more, lost, extra, directions, motion, specular,
                            landing=settings.residual.move_support, raster=settings.raster)
    every_edge = np.concatenate([edges, extra])
    every_set = GaussianParams.concatenate([retargeted, more], axis=0)
    paths = decide_paths(estimated.take(every_edge[:, 0]), every_set, settings.paths)
    row_of = {tuple(e): i for i, e in enumerate(every_edge.tolist())}
    residual = images - own[..., None] * colour
    for light, moving_psnr in zip(check.lights, check.moving_psnr):
        others = np.delete(np.arange(n), light)
        tri = triangulations[light]
        local = tri.directed_edges()
        rows = [row_of[(int(a), int(b))] for a, b in others[local]]
        field = HighlightField(
            lights=LightSet(directions[others]), triangulation=tri, width=images.shape[2], height=images.shape[1],
            estimated=estimated.take(others), directed_edges=local, retargeted=every_set.take(rows),
            path_delta=paths.delta[rows].astype(np.float32), path_centre=paths.centre[rows].astype(np.float32),
            settings=settings.to_dict(), report={},
            residual=ResidualModel(images=residual[others].astype(np.float16), highlight_colour=colour),
            moving=moving[others],
        )
        relit = Relighter(field, device="cpu", scale=1.0 / factor).relight(directions[light][None]).full[0]
        assert abs(srgb_psnr(relit, images[light] / factor) - moving_psnr) < 0.05


@pytest.mark.parametrize("kind", ["lowrank", "learned"])
def test_a_fit_whose_gaussians_all_stay_keeps_none(small_donut, monkeypatch, kind):
    """Where no Gaussian moves, the field keeps none: drawn in place they would only be blended, as the residual
    is, and a learned residual would have to learn the images less their highlights (the dome sample on 16
    lights: 29.52 dB at its Test lights with its unmoving Gaussians kept, 32.80 without, on an H200)."""
    import warp_highlights.fit.pipeline as pipeline
    from conftest import FAST_FIT
    from warp_highlights.fit.moving import MoveDecision
    from warp_highlights.io.dataset import ReflectanceField

    original = pipeline.decide_moving
    monkeypatch.setattr(pipeline, "decide_moving",
                        lambda *args, **kwargs: MoveDecision(np.zeros_like(original(*args, **kwargs).moving),
                                                             np.zeros(0), np.zeros(0, bool), np.zeros(0, bool)))
    dataset = ReflectanceField.load(small_donut, progress=False)
    extra = ["residual.learned_epochs=2"] if kind == "learned" else []
    settings = FitSettings().with_overrides(FAST_FIT + [f"residual.kind={kind}"] + extra)
    field = pipeline.fit_field(dataset, settings=settings, device="cpu")
    assert field.report["estimation"]["gaussians_per_light"]["max"] > 0  # there were Gaussians to keep
    assert field.report["residual"]["kept_gaussians"] == 0 and not field.estimated.active.any()
    assert field.residual.highlight_colour is None
