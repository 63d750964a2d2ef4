"""The residual's normalised stacks made on a Warp device (``kernels.stacks``) against the host's
float64 NumPy (``residual.inputs.residual_of`` and ``residual_scale``, ``residual.opponent.to_opponent``), and the
principal images and stacks made from them against those of the host's stacks."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warp_highlights.kernels.rows as rows_module
import warp_highlights.kernels.stacks as stacks_module
from warp_highlights.kernels.gram import DeviceProducts
from warp_highlights.kernels.stacks import NormalisedStacks
from warp_highlights.model.config import ResidualSettings
from warp_highlights.residual.build import build_residual
from warp_highlights.residual.decode import light_images, stack_light_images
from warp_highlights.residual.inputs import residual_of, residual_scale
from warp_highlights.residual.inputs import (
    scale_of_mean_square as _scale_of_mean_square,
)
from warp_highlights.residual.opponent import to_opponent
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import quantised_stack

RNG = np.random.default_rng(41)


def _capture(n: int, height: int, width: int, channels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth images with bright spots, their own highlights (some lights' pixels black) and a tint."""
    rows, columns = np.mgrid[0:height, 0:width] / max(height, width)
    images = np.empty((n, height, width, channels), np.float32)
    for i in range(n):
        spot = np.exp(-((rows - RNG.uniform(0, 1)) ** 2 + (columns - RNG.uniform(0, 1)) ** 2) / 0.02)
        images[i] = (0.2 + 0.5 * rows + 2.0 * spot)[..., None] * RNG.uniform(0.5, 1.0, size=channels)
    images[:, : height // 4, : width // 4] = 0.0  # a black corner: the scale's floor
    own = (0.3 * images.mean(axis=-1) * (RNG.uniform(size=(n, height, width)) > 0.5)).astype(np.float32)
    tint = RNG.uniform(0.6, 1.4, size=(height, width, channels)).astype(np.float32)
    return images, own, tint


def _host_planes(images, own, tint):
    """(scale, squares, luminance (n, H, W, 1), chroma (n, H, W, 2) or None) as build_residual's host pass makes
    them."""
    residual = residual_of(images, own, tint)
    if images.shape[-1] == 1:
        y, chroma = residual[..., 0].astype(np.float64), None
    else:
        y, chroma = to_opponent(residual)
    scale = residual_scale(y)
    normalised = y / scale
    squares = np.sum(normalised**2, axis=(1, 2))
    return (scale, squares, normalised[..., None].astype(np.float32),
            None if chroma is None else (chroma / scale[..., None]).astype(np.float32))


@pytest.mark.parametrize("channels", [3, 1])
def test_device_stacks_are_the_host_s_to_a_float32_rounding(device, channels, monkeypatch):
    """Bands of a few rows (``BAND_VALUES`` made small) over lights split in parts: the scale bit for
    bit but where a sum order flips a float16 rounding, the planes and the lights' squares to a float32 rounding."""
    n, height, width = 7, 23, 17
    images, own, tint = _capture(n, height, width, channels)
    monkeypatch.setattr(stacks_module, "BAND_VALUES", 5 * n * width * channels)  # five rows a band, the last one short
    monkeypatch.setattr(rows_module, "PART_BYTES", 3 * 4 * height * width * 2)  # three lights a part
    made = NormalisedStacks.make(images, own, tint, DeviceProducts(device), scale_of=_scale_of_mean_square)
    scale, squares, luminance, chroma = _host_planes(images, own, tint)
    held = made.luminance.block(slice(0, height * width)).reshape(n, height, width, 1)
    # the CPU device: the host's arithmetic in the host's order but for the sums
    exact = not wp.get_device(device).is_cuda
    if exact:
        np.testing.assert_array_equal(made.scale, scale)
        np.testing.assert_array_equal(held, luminance)
    assert np.mean(made.scale == scale) > 0.99
    np.testing.assert_allclose(made.scale, scale, rtol=2**-10)  # at most a float16 step where a tie flipped
    same = made.scale == scale  # compare the planes where the scales agree
    np.testing.assert_allclose(held[:, same], luminance[:, same], rtol=2e-6, atol=1e-6)
    np.testing.assert_allclose(made.squares, squares, rtol=1e-5)
    # the lights split as the chroma rows split
    assert (made.luminance.shape == (height, width, 1) and made.luminance.light_count == n
            and len(made.luminance.rows.parts) == (3 if channels == 3 else 2))
    if channels == 1:
        assert made.chroma is None
        return
    held_chroma = made.chroma.block(slice(0, height * width * 2)).reshape(n, height, width, 2)
    if exact:
        np.testing.assert_array_equal(held_chroma, chroma)
    np.testing.assert_allclose(held_chroma[:, same], chroma[:, same], rtol=2e-6, atol=1e-6)
    part = made.chroma.on_device(slice(10, 50))  # a column block there, as the products read it
    assert isinstance(part, wp.array) and part.shape == (n, 40)
    np.testing.assert_array_equal(part.numpy(), held_chroma.reshape(n, -1)[:, 10:50])


@pytest.mark.parametrize("channels", [3, 1])
@pytest.mark.parametrize("held_own", [True, False])
def test_stacks_from_images_held_there_are_those_from_uploaded_bands(device, held_own, channels, monkeypatch):
    """Images (and own highlights) on the device already: each band read as a view of them, the stacks the
    same bit for bit as from the uploaded bands (several bands, the last one short)."""
    n, height, width = 6, 19, 13
    images, own, tint = _capture(n, height, width, channels)
    monkeypatch.setattr(stacks_module, "BAND_VALUES", 4 * n * width * channels)
    uploads = []
    real = stacks_module._rows_up
    monkeypatch.setattr(stacks_module, "_rows_up", lambda *args: uploads.append(1) or real(*args))
    uploaded = NormalisedStacks.make(images, own, tint, DeviceProducts(device), scale_of=_scale_of_mean_square)
    bands = len(uploads) // 2
    uploads.clear()
    held_images = wp.array(images.reshape(n, height * width, channels), dtype=wp.float32, device=device)
    held = wp.array(own.reshape(n, height * width), dtype=wp.float32, device=device) if held_own else None
    there = NormalisedStacks.make(images, own, tint, DeviceProducts(device), scale_of=_scale_of_mean_square,
                                  held_images=held_images, held_own=held)
    assert bands >= 4 and len(uploads) == (0 if held_own else bands)  # only what is not held goes up
    np.testing.assert_array_equal(there.scale, uploaded.scale)
    np.testing.assert_array_equal(there.squares, uploaded.squares)
    for name, planes in (("luminance", 1), ("chroma", 2)) if channels == 3 else (("luminance", 1),):
        values = slice(0, height * width * planes)
        np.testing.assert_array_equal(getattr(there, name).block(values), getattr(uploaded, name).block(values))


def test_principal_images_of_device_stacks_are_those_of_the_host_stacks(device):
    """The principal images, codes and weights from the held stacks: the host stacks' to the stacks' rounding."""
    n, height, width = 12, 20, 24
    images, own, tint = _capture(n, height, width, 3)
    products = DeviceProducts(device)
    made = NormalisedStacks.make(images, own, tint, products, scale_of=_scale_of_mean_square)
    _, squares, luminance, _ = _host_planes(images, own, tint)
    light_scale = np.sqrt(squares / (height * width))
    there = PrincipalImages.of_source(made.luminance, np.sqrt(made.squares / (height * width)), products=products)
    host = PrincipalImages.of(luminance, light_scale)
    np.testing.assert_allclose(there.energies[:6], host.energies[:6], rtol=1e-4)
    for a, b in zip(there.host_directions()[:4], host.directions[:4]):
        np.testing.assert_allclose(a * np.sign(float(a @ b)), b, atol=1e-4)
    steps = host.spans[:4] / 255
    stack = quantised_stack(there, steps, bits=8)
    reference = quantised_stack(host, steps, bits=8)
    assert np.mean(stack.codes == reference.codes) > 0.99
    np.testing.assert_allclose(stack_light_images(stack, np.eye(n)), stack_light_images(reference, np.eye(n)),
                               atol=2e-2 * np.abs(stack_light_images(reference, np.eye(n))).max())


@pytest.mark.parametrize("what_is_held", ["stacks and principal images", "stacks"])
def test_build_residual_with_held_stacks_is_the_host_path_on_the_cpu_device(monkeypatch, what_is_held):
    """``build_residual`` with its products on the CPU device (where CUDA would hold them): the stacks
    and principal images held there, or the stacks alone (no room left for their principal images),
    against the same products with nothing held (no room at all: the host's stacks, uploaded a block
    at a time): the same scale bit for bit, and the same model but for the lights' sums of squares,
    which the held path takes of the float32 planes (1e-8 of each light's scale: the principal
    images and their ranges a float32 rounding apart, a code here and there)."""
    import warp_highlights.residual.build as residual_module

    n, height, width = 10, 26, 31
    images, own, tint = _capture(n, height, width, 3)
    settings = ResidualSettings()
    made = []
    original = NormalisedStacks.make
    monkeypatch.setattr(residual_module, "_device_products", lambda device: DeviceProducts("cpu"))
    monkeypatch.setattr(NormalisedStacks, "make", classmethod(lambda cls, *a, **k: made.append(1) or original(*a, **k)))
    with monkeypatch.context() as nothing:
        nothing.setattr(DeviceProducts, "holds", lambda self, nbytes: False)
        reference = build_residual(images, own, tint, settings=settings, device="cpu")
    assert not made
    if what_is_held == "stacks":
        monkeypatch.setattr(DeviceProducts, "held_directions", lambda self, count, shape: None)
    there = build_residual(images, own, tint, settings=settings, device="cpu")
    assert made == [1]
    np.testing.assert_array_equal(there.scale, reference.scale)
    for name in ("luminance", "chroma"):
        a, b = getattr(there, name), getattr(reference, name)
        assert a.codes.shape == b.codes.shape and np.count_nonzero(a.codes != b.codes) <= 1e-3 * a.codes.size
        np.testing.assert_allclose(a.ranges, b.ranges, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(a.weights, b.weights, rtol=0, atol=1e-5 * np.abs(b.weights).max(initial=1.0))
        np.testing.assert_allclose(a.mean_weights, b.mean_weights, rtol=1e-5)


def test_build_residual_on_cuda_matches_the_host(device):
    """The whole compression with the stacks made on a CUDA device: the same ranks and bits, and each
    light's decoded residual within a few codes of the host's."""
    if not wp.get_device(device).is_cuda:
        pytest.skip("build_residual holds its stacks on CUDA devices only")
    n, height, width = 16, 30, 40
    images, own, tint = _capture(n, height, width, 3)
    settings = ResidualSettings()
    there = build_residual(images, own, tint, settings=settings, device=device)
    host = build_residual(images, own, tint, settings=settings)
    assert there.luminance.rank == host.luminance.rank and there.luminance.bits == host.luminance.bits
    np.testing.assert_allclose(there.scale, host.scale, rtol=2**-10)
    a, b = light_images(there, np.eye(n)), light_images(host, np.eye(n))
    np.testing.assert_allclose(a, b, atol=0.02 * np.abs(b).max())
