"""Inverse-CDF sampling follows the piecewise-constant PDF (Kolmogorov-Smirnov), sorted, in bounds."""

from __future__ import annotations

import math

import torch

from adnerf.rays import RayBundle
from adnerf.samplers import (
    ImportanceSampler,
    NearFarBounds,
    StratifiedSampler,
    sample_pdf,
)


def _pdf_case(dtype: torch.dtype):
    g = torch.Generator().manual_seed(1)
    widths = torch.rand(12, generator=g, dtype=torch.float64) + 0.05
    bins = torch.cat([torch.zeros(1, dtype=torch.float64), widths.cumsum(0)]) + 2.0
    weights = torch.rand(12, generator=g, dtype=torch.float64)
    weights[[0, 3, 4, 11]] = 0.0  # empty bins, also at the ends
    return bins.to(dtype), weights.to(dtype)


def _true_cdf(x: torch.Tensor, bins: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The exact CDF of the piecewise-constant PDF, evaluated independently bin by bin."""
    p = weights / weights.sum()
    out = torch.zeros_like(x)
    for i in range(weights.shape[0]):
        lo, hi = bins[i], bins[i + 1]
        out = out + p[i] * ((x - lo) / (hi - lo)).clamp(0, 1)
    return out


def test_random_samples_pass_kolmogorov_smirnov(dtype: torch.dtype) -> None:
    bins, weights = _pdf_case(dtype)
    n = 20000
    s = sample_pdf(bins, weights, n, generator=torch.Generator().manual_seed(7)).double()
    F = _true_cdf(s, bins.double(), weights.double())
    empirical_hi = torch.arange(1, n + 1, dtype=torch.float64) / n
    d = torch.maximum((empirical_hi - F).abs(), (F - (empirical_hi - 1 / n)).abs()).max().item()
    # 99.9% critical value of the one-sample KS statistic.
    assert d < 1.95 / math.sqrt(n), d


def test_deterministic_quantiles_are_exact(dtype: torch.dtype) -> None:
    bins, weights = _pdf_case(dtype)
    n = 101
    s = sample_pdf(bins, weights, n, deterministic=True).double()
    F = _true_cdf(s, bins.double(), weights.double())
    u = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(F, u, rtol=0, atol=tol)
    # No sample falls in an empty bin.
    idx = torch.searchsorted(bins.double(), s, right=True) - 1
    assert (weights.double()[idx.clamp(0, 11)] > 0).all()


def test_sorted_inside_bounds_and_no_gradient(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(2)
    bins = torch.sort(torch.rand(50, 33, generator=g, dtype=dtype) * 4 + 1, dim=-1).values.requires_grad_(True)
    weights = torch.rand(50, 32, generator=g, dtype=dtype).requires_grad_(True)
    s = sample_pdf(bins, weights, 64)
    assert not s.requires_grad
    assert (s[:, 1:] >= s[:, :-1]).all()
    assert (s >= bins[:, :1]).all() and (s <= bins[:, -1:]).all()


def test_zero_weight_rays_spread_over_the_whole_interval(dtype: torch.dtype) -> None:
    bins = torch.linspace(1.0, 3.0, 17, dtype=dtype).expand(4, 17)
    for weights in (torch.zeros(4, 16, dtype=dtype), -torch.ones(4, 16, dtype=dtype)):
        s = sample_pdf(bins, weights, 8, deterministic=True)
        expected = 1.0 + 2.0 * (torch.arange(8, dtype=dtype) + 0.5) / 8
        torch.testing.assert_close(s, expected.expand(4, 8))
        r = sample_pdf(bins, weights, 1000, generator=torch.Generator().manual_seed(0))
        assert torch.isfinite(r).all() and r.min() >= 1 and r.max() <= 3
        assert r[:, :100].max() < 1.5 and r[:, -100:].min() > 2.5  # spread, not collapsed


def test_degenerate_bins_are_safe(dtype: torch.dtype) -> None:
    # Zero-width bins (a ray that missed its bounds has all edges equal) give no NaN.
    bins = torch.full((3, 9), 2.0, dtype=dtype)
    s = sample_pdf(bins, torch.rand(3, 8, dtype=dtype), 16)
    assert torch.equal(s, torch.full((3, 16), 2.0, dtype=dtype))
    bins = torch.tensor([[0.0, 1.0, 1.0, 1.0, 2.0]], dtype=dtype)
    s = sample_pdf(bins, torch.tensor([[1.0, 5.0, 0.0, 1.0]], dtype=dtype), 50)
    assert torch.isfinite(s).all() and (s[:, 1:] >= s[:, :-1]).all()


def test_importance_sampler_merges_and_concentrates() -> None:
    rays = RayBundle(torch.zeros(2, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64))
    coarse = StratifiedSampler(16, NearFarBounds(1.0, 5.0))(rays)
    w = torch.zeros(2, 16, dtype=torch.float64)
    w[:, 8] = 1.0  # all mass in [3, 3.25]
    fine = ImportanceSampler(32)(coarse, w)
    assert fine.t_starts.shape == (2, 48)
    assert torch.equal(fine.t_starts[:, 0], coarse.t_starts[:, 0]) and torch.equal(fine.t_ends[:, -1], coarse.t_ends[:, -1])
    assert (fine.t_ends == fine.t_starts.roll(-1, dims=-1))[:, :-1].all()  # contiguous
    new = fine.t_mids
    assert ((new > 2.75) & (new < 3.5)).sum() >= 32  # the blurred support [2.75, 3.5] gets the new samples
