"""Unit tests of the containers, samplers, compositor and occupancy grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adnerf.compositor import Layer, composite, composite_layers, over
from adnerf.occupancy import OccupancyGrid
from adnerf.rays import RayBundle, RaySamples
from adnerf.samplers import (
    AABBBounds,
    NearFarBounds,
    SphereBounds,
    StratifiedSampler,
    blur_weights,
    stratified_edges,
)


def _rays(n: int = 5, dtype: torch.dtype = torch.float64) -> RayBundle:
    d = torch.nn.functional.normalize(0.1 * torch.randn(n, 3, dtype=dtype, generator=torch.Generator().manual_seed(0)) + torch.tensor([0, 0, 1.0], dtype=dtype), dim=-1)
    return RayBundle(torch.zeros(n, 3, dtype=dtype), d)


def test_ray_bundle_shapes_and_indexing() -> None:
    rays = RayBundle(torch.zeros(3, 3), torch.ones(4, 3, 3))
    assert rays.shape == (4, 3)
    assert rays.flatten().origins.shape == (12, 3)
    assert rays[1].shape == (3,)
    assert rays.at(torch.ones(4, 3, 2)).shape == (4, 3, 2, 3)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        RayBundle(torch.zeros(3, 2), torch.zeros(3, 3))


def test_ray_samples_geometry() -> None:
    rays = _rays()
    edges = torch.linspace(1, 3, 5, dtype=torch.float64).expand(5, 5)
    s = RaySamples.from_edges(rays, edges)
    assert torch.equal(s.edges, edges)
    torch.testing.assert_close(s.deltas, torch.full((5, 4), 0.5, dtype=torch.float64))
    p = s.positions()
    torch.testing.assert_close(torch.linalg.vector_norm(p, dim=-1), s.t_mids)


def test_stratified_edges_cover_bounds_and_jitter() -> None:
    near = torch.tensor([1.0, 2.0], dtype=torch.float64)
    far = torch.tensor([3.0, 2.0], dtype=torch.float64)  # the second ray is empty
    det = stratified_edges(near, far, 8)
    torch.testing.assert_close(det[0], torch.linspace(1, 3, 9, dtype=torch.float64))
    assert torch.equal(det[1], torch.full((9,), 2.0, dtype=torch.float64))
    jit = stratified_edges(near, far, 8, jitter=True, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(jit, det)
    assert torch.equal(jit[:, 0], near) and torch.equal(jit[:, -1], far)
    assert (jit[:, 1:] >= jit[:, :-1]).all()
    # Jittered interior boundaries stay within half a step of their uniform positions.
    assert (jit[0] - det[0]).abs().max() <= 0.5 * 2 / 8
    with pytest.raises(ValueError):
        stratified_edges(near, far, 0)


def test_bounds_strategies() -> None:
    rays = _rays()
    near, far = NearFarBounds(0.5, 2.0)(rays)
    assert torch.equal(near, torch.full((5,), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError):
        NearFarBounds(2.0, 1.0)
    c = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
    n_s, f_s = SphereBounds(c, 1.0)(rays)
    n_b, f_b = AABBBounds(c - 1, c + 1)(rays)
    hit = f_s > n_s
    assert hit.any()
    # The sphere lies inside its bounding box: its interval is inside the box's.
    assert (n_b[hit] <= n_s[hit] + 1e-12).all() and (f_s[hit] <= f_b[hit] + 1e-12).all()
    samples = StratifiedSampler(16, SphereBounds(c, 1.0))(rays)
    assert samples.t_starts.shape == (5, 16)


def test_blur_weights_spreads_to_neighbours() -> None:
    w = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0])
    b = blur_weights(w)
    assert b.tolist() == [0.0, 0.5, 1.0, 0.5, 0.0]
    assert torch.equal(blur_weights(torch.zeros(2, 4)), torch.zeros(2, 4))


def test_composite_background_and_depth_fallback() -> None:
    t = torch.linspace(0, 4, 5, dtype=torch.float64).expand(2, 5)
    dens = torch.tensor([[0.0, 0.0, 1e9, 0.0], [0.0] * 4], dtype=torch.float64)
    colors = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64).expand(2, 4, 3)
    bg = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    out = composite(colors, dens, t[:, :-1], t[:, 1:], bg)
    torch.testing.assert_close(out.rgb[0], colors[0, 0])
    torch.testing.assert_close(out.rgb[1], bg[1])
    assert out.opacity.tolist() == [1.0, 0.0]
    assert out.depth[0].item() == pytest.approx(2.5) and out.depth[1].item() == 4.0
    with pytest.raises(ValueError):
        composite(colors[:, :3], dens, t[:, :-1], t[:, 1:])


def test_over_is_associative_and_order_matters() -> None:
    g = torch.Generator().manual_seed(0)

    def layer() -> Layer:
        a = torch.rand(6, generator=g, dtype=torch.float64)
        return Layer(torch.rand(6, 3, generator=g, dtype=torch.float64) * a[:, None], a)

    a, b, c = layer(), layer(), layer()
    left, right = over(over(a, b), c), over(a, over(b, c))
    torch.testing.assert_close(left.rgb, right.rgb)
    torch.testing.assert_close(left.opacity, right.opacity)
    assert not torch.allclose(over(a, b).rgb, over(b, a).rgb)
    # An opaque front hides the back; a transparent front shows it.
    opaque = Layer.opaque(torch.rand(6, 3, generator=g, dtype=torch.float64))
    torch.testing.assert_close(over(opaque, a).rgb, opaque.rgb)
    clear = Layer(torch.zeros(6, 3, dtype=torch.float64), torch.zeros(6, dtype=torch.float64))
    torch.testing.assert_close(over(clear, a).rgb, a.rgb)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    stacked = composite_layers([a, b], bg)
    torch.testing.assert_close(stacked.opacity, torch.ones(6, dtype=torch.float64))
    with pytest.raises(ValueError):
        composite_layers([])


def test_occupancy_grid_marks_an_analytic_sphere() -> None:
    grid = OccupancyGrid((-1, -1, -1), (1, 1, 1), resolution=16, threshold=0.5)
    assert grid.is_occupied(torch.zeros(1, 3)).all()  # before any update, everything is occupied
    frac = grid.update(lambda p: (p.norm(dim=-1) < 0.5).double() * 10, jitter=False)
    # Fraction of cell centres inside the sphere ~ volume ratio (4/3 pi 0.5^3) / 8.
    assert abs(frac - 4 / 3 * torch.pi * 0.125 / 8) < 0.02
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9], [2.0, 0.0, 0.0]])
    assert grid.is_occupied(pts).tolist() == [True, False, False]
    before = int(grid.occupied.sum())
    grid.dilate(1)
    assert int(grid.occupied.sum()) > before
    with pytest.raises(ValueError):
        OccupancyGrid((0, 0, 0), (1, 0, 1))


def test_synth_texture_lookup_takes_more_points_than_remap_allows_in_a_row() -> None:
    """cv2.remap refuses maps 32767 or more wide; a 512 px scene looks up ~100k points at once."""
    import cv2

    from adnerf.synth import _sample

    rng = np.random.default_rng(0)
    image = rng.random((40, 50, 3)).astype(np.float32)
    u, v = rng.uniform(0, 49, 70_001), rng.uniform(0, 39, 70_001)
    got = _sample(image, u, v)
    assert got.shape == (70_001, 3)
    part = slice(69_000, 70_001)
    ref = cv2.remap(image, u[part].astype(np.float32)[None], v[part].astype(np.float32)[None], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)[0]
    np.testing.assert_array_equal(got[part], ref)
