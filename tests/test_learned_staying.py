"""A decoder that sees the Gaussians (``residual.learned_sees_gaussians``) learns the highlights of those that do not
move from the images, and the field keeps only the moving ones."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import FAST_FIT


@pytest.mark.parametrize("sees", [False, True])
def test_the_staying_gaussians_are_left_to_a_decoder_that_sees_the_moving_ones(small_donut, monkeypatch, sees):
    """Held back by their motion coherence, some Gaussians stay: a decoder that sees the Gaussians does not get them
    as inputs (its inputs are the moving ones' own highlights) and the field keeps none that stays; a residual of the
    images less their own Gaussians has them taken out too, and the field keeps them, drawn in place."""
    import warp_highlights.fit.pipeline as pipeline
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings
    from warp_highlights.residual.inputs import render_own

    real_moving, real_learned = pipeline.check_moving, pipeline.check_learned
    taken = {}

    def moving_wins(*args, **kwargs):  # the verdict under test is the learned check's, not the move check's
        check = real_moving(*args, **kwargs)
        return dataclasses.replace(check, moving_psnr=check.blend_psnr + 1.0)

    def check_learned(images, own, *args, **kwargs):
        taken["own"] = own.copy()
        return real_learned(images, own, *args, **kwargs)

    monkeypatch.setattr(pipeline, "check_moving", moving_wins)
    monkeypatch.setattr(pipeline, "check_learned", check_learned)
    dataset = ReflectanceField.load(small_donut, progress=False)
    settings = FitSettings().with_overrides(FAST_FIT + [
        "residual.kind=learned", "residual.learned_epochs=2", "residual.learned_tune_epochs=1",
        "residual.learned_tie_margin_db=100", "residual.learned_glide_margin_db=100",
        "residual.learned_seeing_margin_db=100", "residual.move_coherence=0.8",
        "residual.learned_seeing_coherence=0.8", "residual.learned_seeing_travel=0",
        f"residual.learned_sees_gaussians={str(sees).lower()}"])
    field = pipeline.fit_field(dataset, device="cpu", settings=settings, progress=False, size=(48, 27))
    report = field.report["residual"]
    assert report["learned_check"]["keeps_gaussians"] and report["incoherent_gaussians"] > 0
    assert (field.moving & field.estimated.active).any()
    drawn = render_own(field.estimated, field.height, field.width, raster=FitSettings().raster, device="cpu")
    if sees:
        # nothing stays: every kept Gaussian moves, and the decoder's inputs are theirs alone
        assert report["staying_gaussians"] == 0 and report["left_gaussians"] >= report["incoherent_gaussians"]
        np.testing.assert_array_equal(field.estimated.active, field.moving)
        assert not (field.retargeted.active & ~field.moving[field.directed_edges[:, 0]]).any()
    else:
        assert report["left_gaussians"] == 0 and report["staying_gaussians"] >= report["incoherent_gaussians"]
        assert (field.estimated.active & ~field.moving).sum() == report["staying_gaussians"]
    np.testing.assert_allclose(taken["own"], drawn, rtol=1e-6, atol=1e-7)


def test_a_near_highlight_stays_and_a_far_one_moves():
    """``fit.moving.travel_in_sigmas``: the distance travelled over the source Gaussian's standard deviation along the
    way, against a float64 brute force (the density's second moment along the unit displacement); NaN on free slots;
    ``decide_moving``'s ``least_travel`` holds back the slots whose median over their outgoing edges is under it."""
    import warp as wp

    from warp_highlights.fit.moving import decide_moving, per_light_median, travel_in_sigmas
    from warp_highlights.model.config import RasterSettings, ResidualSettings
    from warp_highlights.model.gaussians import GaussianParams

    rng = np.random.default_rng(3)
    sources = GaussianParams.empty(4, 2)
    sources.active[:] = [[True, True], [True, False], [True, True], [True, True]]
    sources.amplitude[:] = 1.0
    sources.mean[:] = rng.uniform(0.3, 0.7, (4, 2, 2))
    sources.sigma[:] = rng.uniform(0.01, 0.05, (4, 2, 2))
    sources.theta[:] = rng.uniform(-np.pi, np.pi, (4, 2))
    targets = sources.copy()
    targets.mean = sources.mean + rng.normal(0, 0.05, (4, 2, 2))
    got = travel_in_sigmas(sources, targets)
    for e, n in np.ndindex(4, 2):
        if not sources.active[e, n]:
            assert np.isnan(got[e, n])
            continue
        d = targets.mean[e, n] - sources.mean[e, n]
        c, s = np.cos(sources.theta[e, n]), np.sin(sources.theta[e, n])
        rotation = np.array([[c, -s], [s, c]])
        covariance = rotation @ np.diag(sources.sigma[e, n] ** 2) @ rotation.T
        u = d / np.linalg.norm(d)
        assert got[e, n] == pytest.approx(np.linalg.norm(d) / np.sqrt(u @ covariance @ u), rel=1e-9)
    # per light: edges 0, 1 leave light 0, edges 2, 3 light 1
    edges = np.array([[0, 1], [0, 2], [1, 0], [1, 2]])
    median = per_light_median(got, edges, 3)
    np.testing.assert_allclose(median[0], np.nanmedian(got[:2], axis=0))
    np.testing.assert_allclose(median[1], np.nanmedian(got[2:], axis=0))
    assert np.isnan(median[2]).all()
    # decide_moving: three lights, their sources at the edges' source rows
    estimated = GaussianParams.empty(3, 2)
    estimated.active[:2] = True
    estimated.amplitude[:2] = 1.0
    estimated.mean[:2] = sources.mean[[0, 2]]
    estimated.sigma[:2] = sources.sigma[[0, 2]]
    estimated.theta[:2] = sources.theta[[0, 2]]
    edge_sources = estimated.take(edges[:, 0])
    retargeted = edge_sources.copy()
    retargeted.mean = edge_sources.mean + np.array([0.2, 0.0])  # every slot travels 0.2 image heights
    travel = per_light_median(travel_in_sigmas(edge_sources, retargeted), edges, 3)
    least = float(np.median(travel[:2]))
    specular = wp.zeros((3, 16, 16), dtype=float, device="cpu")
    decision = decide_moving(estimated, retargeted, edges, specular, settings=ResidualSettings(move_support=0),
                             raster=RasterSettings(), least_travel=least)
    np.testing.assert_array_equal(decision.moving, estimated.active & (travel >= least))
    np.testing.assert_array_equal(decision.near, estimated.active & (travel < least))
    assert decision.near.any() and decision.moving.any()
