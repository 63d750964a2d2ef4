"""The stack's products on a Warp device (``kernels.gram``) against float64 NumPy, and the principal
images and weights summed there against the host's BLAS."""

from __future__ import annotations

import numpy as np
import pytest

from warp_highlights.kernels.gram import DeviceProducts
from warp_highlights.residual.build import NormalisedResidual
from warp_highlights.residual.principal import PrincipalImages
from warp_highlights.residual.quantise import quantised_stack

RNG = np.random.default_rng(21)


def test_cross_sums_are_float64_products_of_the_float32_blocks(device):
    """Sizes that fill no tile evenly (the loads beyond the arrays read zeros), summed over two blocks."""
    products = DeviceProducts(device)
    a = RNG.normal(size=(45, 1700)).astype(np.float32)
    b = RNG.normal(size=(37, 1700)).astype(np.float32)
    total = products.cross_sum(45, 37)
    total.add(products.upload(a[:, :1100]), products.upload(b[:, :1100]))
    total.add(products.upload(a[:, 1100:]), products.upload(b[:, 1100:]))
    reference = a.astype(np.float64) @ b.astype(np.float64).T
    np.testing.assert_allclose(total.value(), reference, rtol=0, atol=1e-12 * np.abs(reference).max())
    gram = products.cross_sum(45, 45)
    gram.add(products.upload(a))
    np.testing.assert_allclose(gram.value(), a.astype(np.float64) @ a.astype(np.float64).T, rtol=1e-13, atol=1e-10)
    with pytest.raises(ValueError, match="do not add"):
        total.add(products.upload(a))
    with pytest.raises(ValueError, match="not both"):
        gram.add(products.upload(a), products.upload(a))
    again = products.cross_sum(45, 45)
    again.add(products.upload(a))
    assert again.value().tobytes() == gram.value().tobytes()  # the same order of sums every run
    assert np.array_equal(gram.value(), gram.value().T)


def test_long_rows_are_summed_by_every_part(device):
    """Rows longer than PARTS depth tiles: each part sums several tiles, the last one partly filled."""
    from warp_highlights.kernels.gram import PARTS, TILE_DEPTH

    products = DeviceProducts(device)
    a = RNG.normal(size=(3, PARTS * TILE_DEPTH * 2 + 77)).astype(np.float32)
    gram = products.cross_sum(3, 3)
    gram.add(products.upload(a))
    reference = a.astype(np.float64) @ a.astype(np.float64).T
    np.testing.assert_allclose(gram.value(), reference, rtol=1e-13)


def test_projections_are_float64_sums_kept_as_float32(device):
    products = DeviceProducts(device)
    matrix = RNG.normal(size=(33, 45))
    block = RNG.normal(size=(45, 700)).astype(np.float32)
    projected = products.project(matrix, block)
    reference = matrix @ block.astype(np.float64)
    assert projected.dtype == np.float32 and projected.shape == (33, 700)
    np.testing.assert_allclose(projected, reference, rtol=1e-6, atol=1e-6 * np.abs(reference).max())
    # the matrix is uploaded once for equal matrices, again when it changes (even in place)
    np.testing.assert_array_equal(products.project(matrix.copy(), block), projected)
    matrix[3, 7] += 1.0
    np.testing.assert_allclose(products.project(matrix, block)[3], matrix[3] @ block.astype(np.float64), rtol=1e-6,
                               atol=1e-5)
    with pytest.raises(ValueError, match="kept on the device"):
        products.project(matrix, block, host=False)


def test_strided_blocks_in_turn_and_projections_into_views(device):
    """Column blocks of a held stack (strided views) uploaded one after another, through the two
    staging buffers in turn (each refilled while the other's copy may still run), and projections
    written into column views of a larger array: the products of the whole stack."""
    products = DeviceProducts(device)
    stack = RNG.normal(size=(19, 9000)).astype(np.float32)
    edges = [0, 700, 2100, 2150, 4000, 6500, 8999, 9000]
    gram = products.cross_sum(19, 19)
    for start, stop in zip(edges, edges[1:]):
        gram.add(products.upload(stack[:, start:stop]))
    reference = stack.astype(np.float64) @ stack.astype(np.float64).T
    np.testing.assert_allclose(gram.value(), reference, rtol=1e-13, atol=1e-10)
    matrix = RNG.normal(size=(6, 19))
    out = np.full((6, 9000), np.nan, np.float32)
    for start, stop in zip(edges, edges[1:]):
        assert products.project(matrix, stack[:, start:stop], out=out[:, start:stop]) is not None
    expected = matrix @ stack.astype(np.float64)
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    with pytest.raises(ValueError, match="cannot go into"):
        products.project(matrix, stack[:, :10], out=out[:, :11])


def _stack(n: int, h: int, w: int, planes: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / h
    patterns = np.stack([np.sin((i + 1) * 2 * xx + i) * np.cos((i % 4 + 1) * yy) for i in range(12)])
    weights = RNG.normal(size=(n, 12)) * 0.6 ** np.arange(12)
    stack = np.einsum("nk,khw->nhw", weights, patterns)[..., None] * np.linspace(1.0, 0.6, planes) + 0.5
    return (stack + 1e-3 * RNG.normal(size=stack.shape)).astype(np.float32)


def _same_images(a: PrincipalImages, b: PrincipalImages, count: int) -> None:
    np.testing.assert_allclose(a.energies, b.energies, rtol=1e-9, atol=1e-12 * a.energies[0])
    # a direction's sign is the eigensolver's choice
    for x, y in zip(a.host_directions()[:count], b.host_directions()[:count]):
        np.testing.assert_allclose(x * np.sign(float(x @ y)), y, atol=2e-6)


@pytest.mark.parametrize("held", [True, False])
def test_principal_images_and_weights_summed_on_the_device_are_the_host_s(device, held):
    """The same principal images (directions to float32 rounding, energies to 1e-9) and the same fitted
    weights whether the products are summed by the host's BLAS or on ``device``; from a held stack and
    from a ``NormalisedResidual`` computed a block at a time."""
    n, h, w = 24, 36, 52
    stack = _stack(n, h, w, 2)
    light_scale = np.sqrt(np.mean(np.square(stack.astype(np.float64)), axis=(1, 2, 3)))
    products = DeviceProducts(device)
    if held:
        host = PrincipalImages.of(stack, light_scale)
        there = PrincipalImages.of(stack, light_scale, products=products)
    else:
        # three channels
        images = np.concatenate([stack[..., :1], stack[..., 1:] * 0.5, stack[..., :1] * 0.25], axis=-1)
        own, tint, scale = np.zeros((n, h, w), np.float32), np.ones((1, 1, 3), np.float32), np.ones((h, w), np.float32)
        host = PrincipalImages.of_source(NormalisedResidual(images, own, tint, scale, "chroma"), light_scale)
        there = PrincipalImages.of_source(NormalisedResidual(images, own, tint, scale, "chroma"), light_scale,
                                          products=products)
    assert host.products is None and there.products is products
    _same_images(host, there, 8)
    steps = host.spans[:6] / 65535 * 40.0
    a = quantised_stack(host, steps, bits=16)
    b = quantised_stack(there, steps, bits=16)
    assert np.mean(a.codes == b.codes) > 0.999  # the directions differ by float32 rounding: a code here and there
    np.testing.assert_allclose(a.weights, b.weights, rtol=0, atol=1e-4 * np.abs(a.weights).max())
    np.testing.assert_allclose(a.mean_weights, b.mean_weights, rtol=1e-5)
    # the same codes: the sums differ, and
    same = quantised_stack(dataclass_with(there, products=None, held=None), steps, bits=16)
    # the decoded planes by a rounding where the device fuses their multiply-add
    np.testing.assert_array_equal(b.codes, same.codes)
    fused = 1e-6 if products.device.is_cuda else 1e-9  # CUDA may fuse the decoded planes' multiply-add
    np.testing.assert_allclose(b.weights, same.weights, rtol=0, atol=fused * np.abs(same.weights).max())


def dataclass_with(principal: PrincipalImages, **changes) -> PrincipalImages:
    import dataclasses

    if changes.get("held", principal.held) is None:  # without its device copy: the directions on the host
        changes.setdefault("directions", principal.host_directions())
    return dataclasses.replace(principal, **changes)


def test_a_staging_array_is_uploaded_before_anything_else(device):
    """``staging`` fills a page-locked buffer on CUDA: another upload or a projection before its own
    upload is refused (it would take that buffer); on the CPU it is a plain array."""
    products = DeviceProducts(device)
    block = RNG.normal(size=(5, 40)).astype(np.float32)
    staged = products.staging((5, 40))
    staged[...] = block
    np.testing.assert_array_equal(products.upload(staged).numpy(), block)
    if not products.device.is_cuda:
        return
    products.staging((5, 40))
    with pytest.raises(RuntimeError, match="uploaded before"):
        products.upload(block)
