"""Volume rendering against closed forms: homogeneous slab and uniform-density sphere."""

from __future__ import annotations

from typing import Callable

import pytest
import torch

from adnerf.analytic import (
    UniformBox,
    UniformSphere,
    homogeneous_depth,
    homogeneous_opacity,
)
from adnerf.bench.render import bench_render
from adnerf.cameras import intrinsics_matrix, pixel_rays
from adnerf.compositor import composite
from adnerf.rays import RaySamples
from adnerf.renderer import VolumeRenderer
from adnerf.samplers import NearFarBounds, SphereBounds, ray_aabb, stratified_edges


def _slab_rays(dtype: torch.dtype):
    # Oblique rays from the origin through a slab z in [2, 3] that is wide in x and y.
    K = intrinsics_matrix(20.0, 20.0, 8.0, 8.0, dtype=dtype)
    return pixel_rays(K, 16, 16).flatten()


@pytest.mark.parametrize("sigma", [1e-3, 0.5, 4.0, 1e3])
def test_slab_with_aligned_intervals_is_exact(sigma: float, dtype: torch.dtype) -> None:
    """Piecewise-constant density integrated over intervals that align with it: exact opacity."""
    rays = _slab_rays(dtype)
    slab = UniformBox(torch.tensor([-50.0, -50.0, 2.0], dtype=dtype), torch.tensor([50.0, 50.0, 3.0], dtype=dtype), sigma)
    truth_opacity, truth_depth, hit = slab.truth(rays.origins, rays.directions)
    assert hit.all()
    # Intervals: [0, entry], 32 inside the slab, [exit, exit + 1].
    entry, exit_, _ = ray_aabb(rays.origins, rays.directions, slab.aabb_min, slab.aabb_max)
    inside = stratified_edges(entry, exit_, 32)
    edges = torch.cat([torch.zeros_like(entry)[:, None], inside, (exit_ + 1)[:, None]], dim=-1)
    samples = RaySamples.from_edges(rays, edges)
    density = torch.zeros_like(samples.t_starts)
    density[:, 1:-1] = sigma
    out = composite(torch.ones(*density.shape, 3, dtype=dtype), density, samples.t_starts, samples.t_ends)
    rtol = 4e-6 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(out.opacity, truth_opacity, rtol=rtol, atol=rtol * 1e-3)
    # Weights sum to the opacity, residual transmittance to the rest.
    torch.testing.assert_close(out.weights.sum(-1) + out.residual_transmittance, torch.ones_like(out.opacity), rtol=rtol, atol=rtol)
    # Midpoint-rule depth inside a homogeneous medium: second order in the interval length.
    chord = exit_ - entry
    err = (out.depth - truth_depth).abs()
    bound = sigma * (chord / 32) ** 2 / 12 * 1.01 + 1e-5 * truth_depth * (dtype == torch.float32) + 1e-12
    assert (err <= bound).all(), (err - bound).max()


def test_sphere_depth_converges_at_second_order(report: Callable[[str], None]) -> None:
    """Intervals spanning exactly the chord: opacity exact, depth error ~ sigma delta^2 / 12."""
    dtype = torch.float64
    K = intrinsics_matrix(40.0, 40.0, 16.0, 16.0, dtype=dtype)
    rays = pixel_rays(K, 32, 32).flatten()
    sphere = UniformSphere(torch.tensor([0.1, -0.2, 3.0], dtype=dtype), 1.0, 3.0)
    truth_opacity, truth_depth, hit = sphere.truth(rays.origins, rays.directions)
    rays = rays[hit]
    truth_opacity, truth_depth = truth_opacity[hit], truth_depth[hit]
    bounds = SphereBounds(sphere.center, sphere.radius)
    errors = []
    for n in (4, 8, 16, 32, 64):
        renderer = VolumeRenderer(bounds, n_coarse=n, n_fine=0)
        out = renderer.render_rays(rays, lambda p, d: _uniform(p, sphere.sigma)).final
        torch.testing.assert_close(out.opacity, truth_opacity, rtol=1e-13, atol=1e-15)
        errors.append((out.depth - truth_depth).abs().max().item())
        report(f"sphere, chord-aligned intervals, S={n:>3}: max |depth error| = {errors[-1]:.3e}")
    ratios = [a / b for a, b in zip(errors, errors[1:])]
    assert all(3.6 < r < 4.4 for r in ratios), ratios


def _uniform(positions: torch.Tensor, sigma: float):
    from adnerf.fields import FieldOutput

    return FieldOutput(torch.ones_like(positions), torch.full_like(positions[..., 0], sigma))


def test_sphere_in_fixed_bounds_converges(report: Callable[[str], None]) -> None:
    """Fixed near/far (the sphere's boundary falls inside intervals): first-order convergence."""
    dtype = torch.float64
    K = intrinsics_matrix(40.0, 40.0, 16.0, 16.0, dtype=dtype)
    rays = pixel_rays(K, 32, 32).flatten()
    sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=dtype), 1.0, 2.0)
    truth_opacity, truth_depth, hit = sphere.truth(rays.origins, rays.directions)
    errs = []
    for n in (16, 64, 256, 1024):
        out = VolumeRenderer(NearFarBounds(1.0, 5.0), n_coarse=n, n_fine=0).render_rays(rays, sphere).final
        e = ((out.opacity - truth_opacity).abs()[hit].sum() / truth_opacity[hit].sum()).item()
        errs.append(e)
        report(f"sphere sigma=2, fixed [1, 5], S={n:>4}: opacity rel err = {e:.3e}")
        # Rays that miss the sphere render nothing.
        assert (out.opacity[~hit] == 0).all()
    assert errs[-1] < 2e-3 and all(b < a for a, b in zip(errs, errs[1:]))


def test_importance_sampling_beats_stratified_at_equal_samples(report: Callable[[str], None]) -> None:
    # 64 px: at 32 px the few boundary pixels of deterministic stratified sampling alias into
    # partly cancelling opacity errors, which says nothing about the samplers.
    rows = bench_render((16, 64), size=64, repeats=1, dtype=torch.float64)
    by = {(r.samples_per_ray, r.method): r for r in rows}
    for n in (16, 64):
        s, i = by[(n, "stratified")], by[(n, "importance")]
        report(f"bench sphere S={n}: opacity err strat {s.opacity_rel_err:.2e} vs imp {i.opacity_rel_err:.2e}; depth {s.depth_rel_err:.2e} vs {i.depth_rel_err:.2e}")
        assert i.depth_rel_err < s.depth_rel_err
        assert i.opacity_rel_err < s.opacity_rel_err
    assert by[(64, "importance")].depth_rel_err < by[(16, "importance")].depth_rel_err


def test_closed_forms_limits() -> None:
    chord = torch.tensor([0.0, 1e-8, 1.0, 2.0], dtype=torch.float64)
    t0 = torch.full_like(chord, 5.0)
    # Thin limit: depth is the chord's midpoint; opaque limit: the entry point.
    torch.testing.assert_close(homogeneous_depth(1e-9, t0, chord), t0 + chord / 2 - 1e-9 * chord**2 / 12, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(homogeneous_depth(1e9, t0[2:], chord[2:]), t0[2:] + 1e-9, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(homogeneous_opacity(1e-20, chord), 1e-20 * chord, rtol=1e-12, atol=0)
    # Both branches of the depth formula agree at the switch point.
    x = torch.tensor([1e-2 * (1 - 1e-9), 1e-2 * (1 + 1e-9)], dtype=torch.float64)
    d = homogeneous_depth(1.0, torch.zeros(2, dtype=torch.float64), x)
    expected = x * (0.5 - x / 12 + x**3 / 720 - x**5 / 30240)
    torch.testing.assert_close(d, expected, rtol=1e-13, atol=0)
