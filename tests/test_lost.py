"""Lost Gaussians (``fit.lost``): each Gaussian's motion as a linear map of the half-vector's change, against a
per-slot float64 least-squares reference; lost slots placed where their motion expects them only outside the
frame or where the target holds them; the in-frame share against brute-force sampling."""

import numpy as np
import pytest
import warp as wp

from conftest import centred_blob_sets
from warp_highlights.fit.lost import expected_motion, in_frame_share, lost_slots, place_lost
from warp_highlights.fit.moving import decide_moving
from warp_highlights.kernels.search import half_vector_changes
from warp_highlights.model.config import RasterSettings, ResidualSettings
from warp_highlights.model.gaussians import GaussianParams


def _dome(count: int, rng) -> np.ndarray:
    elevation = rng.uniform(0.3, 1.4, count)
    azimuth = rng.uniform(0, 2 * np.pi, count)
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], 1)


def _every_pair(count: int) -> np.ndarray:
    return np.array([(i, j) for i in range(count) for j in range(count) if i != j], dtype=np.int64)


def _sets(count: int, capacity: int, rng) -> GaussianParams:
    sets = GaussianParams.empty(count, capacity)
    sets.active[:] = True
    sets.amplitude[:] = rng.uniform(0.5, 2.0, (count, capacity))
    sets.mean[:] = rng.uniform(0.3, 0.7, (count, capacity, 2))
    sets.sigma[:] = rng.uniform(0.01, 0.05, (count, capacity, 2))
    sets.theta[:] = rng.uniform(0, np.pi, (count, capacity))
    return sets


def _reference_motion(sources, retargeted, found, edges, directions, ridge):
    """Per light and slot, the ridge least-squares map in float64, one small solve at a time."""
    change = half_vector_changes(directions, edges)
    moved = retargeted.mean - sources.mean
    pairs = [(e, k) for e in range(len(edges)) for k in range(found.shape[1]) if found[e, k]]
    common = (sum(moved[e, k] @ change[e] for e, k in pairs) / sum(change[e] @ change[e] for e, k in pairs))
    pull = ridge * np.median(np.sum(change**2, axis=1)) + 1e-12
    out = np.zeros((len(directions), found.shape[1], 2, 2))
    for light in range(len(directions)):
        for slot in range(found.shape[1]):
            rows = [e for e in range(len(edges)) if edges[e, 0] == light and found[e, slot]]
            gram = pull * np.eye(2) + sum((np.outer(change[e], change[e]) for e in rows), np.zeros((2, 2)))
            products = pull * common * np.eye(2) + sum((np.outer(moved[e, slot], change[e]) for e in rows),
                                                       np.zeros((2, 2)))
            out[light, slot] = products @ np.linalg.inv(gram)
    return out


def test_expected_motion_matches_a_per_slot_least_squares_reference():
    rng = np.random.default_rng(3)
    directions = _dome(6, rng)
    edges = _every_pair(6)
    estimated = _sets(6, 3, rng)
    sources = estimated.take(edges[:, 0])
    retargeted = sources.copy()
    retargeted.mean += rng.normal(0, 0.05, retargeted.mean.shape)
    found = rng.uniform(size=sources.active.shape) > 0.3
    found[edges[:, 0] == 2, 1] = False  # a slot found nowhere takes the common map
    motion = expected_motion(sources, retargeted, found, edges, directions, ridge=0.25)
    reference = _reference_motion(sources, retargeted, found, edges, directions, 0.25)
    np.testing.assert_allclose(motion, reference, rtol=1e-9, atol=1e-12)
    common = reference[2, 1]
    np.testing.assert_allclose(common, common[0, 0] * np.eye(2), atol=1e-12)


def test_expected_motion_recovers_a_linear_map_the_highlights_follow():
    """Highlights that move by M dh on every edge give M back (a light with several edges: the ridge is small)."""
    rng = np.random.default_rng(5)
    directions = _dome(8, rng)
    edges = _every_pair(8)
    truth = np.array([[-0.9, 0.2], [0.1, -1.3]])
    sources = _sets(8, 2, rng).take(edges[:, 0])
    retargeted = sources.copy()
    retargeted.mean += (half_vector_changes(directions, edges) @ truth.T)[:, None, :]
    motion = expected_motion(sources, retargeted, sources.active, edges, directions, ridge=0.25)
    np.testing.assert_allclose(motion, np.broadcast_to(truth, motion.shape), atol=0.05)


def _blob(height: int, width: int, centre, sigma: float) -> np.ndarray:
    y, x = (np.mgrid[0:height, 0:width] + 0.5) / height
    return np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2)).astype(np.float32)


def test_lost_gaussians_go_where_their_motion_expects_them_outside_the_frame_or_where_the_target_holds_them():
    """A highlight that moves by -1.5 dh. Edge 0 (to a light far to the right): expected off the frame's left edge,
    sent there. Edge 1 (a light just beside): expected inside, where the target shows nothing: stays as it was.
    Edge 2: expected inside, where the target has the highlight: placed there. Edge 3: found, untouched."""
    directions = np.array([[0.0, 0.0, 1.0], [0.9, 0.0, 0.436], [0.05, 0.0, 0.999], [0.0, 0.3, 0.954],
                           [-0.3, 0.0, 0.954]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    edges = np.array([[0, 1], [0, 2], [0, 3], [0, 4]])
    sources = GaussianParams.empty(4, 1)
    sources.active[:] = True
    sources.amplitude[:] = 1.0
    sources.mean[:] = [0.2, 0.5]
    sources.sigma[:] = 0.03
    sets = sources.copy()
    sets.mean[2, 0] = [-0.5, 0.5]  # pushed out of the frame the wrong way
    truth = -1.5 * np.eye(2)
    change = half_vector_changes(directions, edges)
    expected = sources.mean[:, 0] + change @ truth.T
    sets.mean[3, 0] = expected[3]  # found on the last light
    height, width = 90, 160
    images = np.zeros((5, height, width), np.float32)
    images[3] = _blob(height, width, expected[2], 0.03)
    images[4] = _blob(height, width, expected[3], 0.03)
    lost = np.array([[True], [True], [True], [False]])
    motion = np.broadcast_to(truth, (5, 1, 2, 2)).copy()
    out, left, followed = place_lost(sources, sets, lost, edges, directions, motion,
                                     wp.array(images, dtype=float, device="cpu"), landing=0.1,
                                     raster=RasterSettings())
    assert expected[0, 0] < 0 and 0 < expected[1, 0] < width / height and 0 < expected[2, 0] < width / height
    assert left.ravel().tolist() == [True, False, False, False]
    assert followed.ravel().tolist() == [False, False, True, False]
    np.testing.assert_allclose(out.mean[[0, 2], 0], expected[[0, 2]])
    np.testing.assert_array_equal(out.mean[[1, 3]], sets.mean[[1, 3]])
    for name in ("amplitude", "sigma", "theta", "weight", "active"):
        np.testing.assert_array_equal(getattr(out, name), getattr(sets, name))
    unchanged, none, nothing = place_lost(sources, sets, np.zeros_like(lost), edges, directions, motion,
                                          wp.array(images, dtype=float, device="cpu"), landing=0.1,
                                          raster=RasterSettings())
    assert unchanged is sets and not none.any() and not nothing.any()


def test_in_frame_share_matches_brute_force_sampling_and_finds_the_lost():
    rng = np.random.default_rng(11)
    sets = _sets(40, 1, rng)
    sets.mean[:, 0] = rng.uniform(-0.3, 2.0, (40, 2))
    sets.sigma[:, 0] = rng.uniform(0.01, 0.2, (40, 2))
    aspect = 16 / 9
    share = in_frame_share(sets, aspect)
    z = rng.standard_normal((200_000, 2))
    z = z[np.all(np.abs(z) <= 3, axis=1)]
    for b in range(40):
        c, s = np.cos(sets.theta[b, 0]), np.sin(sets.theta[b, 0])
        local = z * np.abs(sets.sigma[b, 0])
        points = sets.mean[b, 0] + np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], 1)
        inside = np.mean((points[:, 0] >= 0) & (points[:, 0] <= aspect) & (points[:, 1] >= 0) & (points[:, 1] <= 1))
        assert share[b, 0] == pytest.approx(inside, abs=0.03)
    sources = sets.copy()
    sources.mean[:, 0] = [0.5, 0.5]
    vanished = np.zeros((40, 1), bool)
    vanished[0] = True
    lost = lost_slots(sources, sets, vanished, aspect, 0.1)
    assert lost[0, 0] and np.array_equal(lost[1:, 0], share[1:, 0] < 0.1 * in_frame_share(sources, aspect)[1:, 0])


@pytest.mark.parametrize("left", [False, True])
def test_slots_sent_out_of_the_frame_leave_the_move_support_median(left):
    """One Gaussian with three outgoing edges: lands on one, partly beside the target's highlight on the second,
    draws nothing on the third. Counted as 0 the third edge makes the median the second's share; sent out of the
    frame, it leaves the median, which is then the mean of the first two."""
    sources, targets = centred_blob_sets(2, 1)
    edges = np.array([[0, 1], [0, 1], [0, 1], [1, 0]])
    retargeted = sources.take(edges[:, 0])
    retargeted.mean[1, 0] = [0.8, 0.5]  # half beside the target's highlight
    retargeted.mean[2, 0] = [-1.0, 0.5]  # out of the frame: draws nothing
    left_frame = np.zeros((4, 1), bool)
    left_frame[2] = left
    decision = decide_moving(sources, retargeted, edges, targets, settings=ResidualSettings(move_support=0.5),
                             raster=RasterSettings(), left_frame=left_frame)
    assert np.isnan(decision.support[2, 0]) == left
    assert decision.support[0, 0] == pytest.approx(1.0, abs=0.01) and decision.support[1, 0] < 0.2
    assert decision.moving[0, 0] == left


def _crossing_highlight(directions: np.ndarray, size: int) -> np.ndarray:
    """(n, size, size, 3) a flat object's images whose highlight (sigma 0.06 image heights) sits at 0.5 + 1.2 h
    on the image (h the half-vector's image-plane part): it crosses the frame and leaves it below about 45
    degrees, as on a flat object under a perspective camera; a matte part that follows the light's elevation."""
    half = directions + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    centre = np.stack([0.5 + 1.2 * half[:, 0], 0.5 - 1.2 * half[:, 1]], -1)
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    glint = np.exp(-((x - centre[:, 0, None, None]) ** 2 + (y - centre[:, 1, None, None]) ** 2) / (2 * 0.06**2))
    matte = 0.2 * np.clip(directions[:, 2], 0, 1)[:, None, None]
    return np.repeat((matte + 0.8 * glint)[..., None], 3, axis=-1).astype(np.float32)


def test_a_highlight_that_crosses_and_leaves_the_frame_is_followed_along_a_path():
    """25 dome lights, 16 of which see the highlight: with the lost Gaussians followed, the relit images along a
    path from the zenith to 20 degrees are at least 1.6 times closer to the truth (RMS) than without, and the
    fit says how many it sent out of the frame and how many it placed inside."""
    import warp_highlights as wh
    from warp_highlights.fit.pipeline import fit_field
    from warp_highlights.io.dataset import ReflectanceField
    from warp_highlights.model.config import FitSettings
    from warp_highlights.model.lights import LightSet

    lights = LightSet.fibonacci_dome(25)
    dataset = ReflectanceField(images=_crossing_highlight(lights.directions, 64), lights=lights)
    elevation = np.radians(np.linspace(85, 20, 27))
    path = np.stack([np.cos(elevation), np.zeros_like(elevation), np.sin(elevation)], 1)
    truth = _crossing_highlight(path, 64)
    errors, reports = {}, {}
    for follow in (True, False):
        settings = FitSettings().with_overrides([f"retarget.follow_lost={str(follow).lower()}",
                                                 "residual.kind=lowrank"])
        field = fit_field(dataset, settings=settings, device="cpu", exposure=1.0)
        errors[follow] = float(np.sqrt(np.mean((wh.relight_field(field, path).full - truth) ** 2)))
        reports[follow] = field.report["retargeting"]
    assert errors[True] * 1.6 < errors[False], errors
    assert reports[True]["left_frame_slots"] > 0 and reports[True]["followed_slots"] > 0
    assert reports[False]["left_frame_slots"] == reports[False]["followed_slots"] == 0


def test_in_frame_share_is_the_same_in_blocks(monkeypatch):
    """Many sets are sampled a block of rows at a time, with the same shares."""
    import warp_highlights.fit.lost as lost

    rng = np.random.default_rng(2)
    sets = _sets(50, 3, rng)
    sets.mean[:] = rng.uniform(-0.3, 2.0, (50, 3, 2))
    whole = in_frame_share(sets, 16 / 9)
    monkeypatch.setattr(lost, "_SAMPLES_AT_ONCE", 1000)
    np.testing.assert_array_equal(in_frame_share(sets, 16 / 9), whole)
