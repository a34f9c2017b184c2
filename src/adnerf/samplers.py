"""Where to sample along rays: near/far bounds, stratified and importance sampling.

All samplers produce :class:`~adnerf.rays.RaySamples`: contiguous intervals covering
``[near, far]`` of each ray, sorted. A ray that misses its bounding volume gets an *empty*
interval (``near == far``): every sample then has zero length, zero weight and no NaN anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from .pose import directions_to_canonical, to_canonical
from .rays import RayBundle, RaySamples
from .rng import uniform

__all__ = [
    "AABBBounds",
    "Bounds",
    "ImportanceSampler",
    "NearFarBounds",
    "PosedAABBBounds",
    "SphereBounds",
    "StratifiedSampler",
    "blur_weights",
    "ray_aabb",
    "ray_sphere",
    "sample_pdf",
    "stratified_edges",
]


def ray_aabb(origins: Tensor, directions: Tensor, aabb_min: Tensor, aabb_max: Tensor, near_min: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Intersect rays with an axis-aligned box (slab method, safe for axis-parallel rays).

    Args:
        origins: Ray origins ``(..., 3)``.
        directions: Ray directions ``(..., 3)`` (need not be unit; ``t`` is in their units).
        aabb_min: Box minimum corner ``(3,)``.
        aabb_max: Box maximum corner ``(3,)``.
        near_min: Smallest allowed ``t`` (0: nothing behind the origin).

    Returns:
        ``(near, far, hit)``, each of shape ``(...)``. Rays that miss (or whose hit lies wholly
        behind ``near_min``) get ``near == far`` (finite) and ``hit == False``.

    Example:
        >>> o, d = torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> lo, hi = torch.tensor([-1.0, -1.0, 2.0], dtype=torch.float64), torch.tensor([1.0, 1.0, 4.0], dtype=torch.float64)
        >>> ray_aabb(o, d, lo, hi)
        (tensor([2.], dtype=torch.float64), tensor([4.], dtype=torch.float64), tensor([True]))
    """
    lo = aabb_min.to(origins)
    hi = aabb_max.to(origins)
    nonzero = directions != 0
    safe_d = torch.where(nonzero, directions, torch.ones_like(directions))
    ta = (lo - origins) / safe_d
    tb = (hi - origins) / safe_d
    inside_slab = (origins >= lo) & (origins <= hi)
    inf = torch.full_like(ta, float("inf"))
    t_enter = torch.where(nonzero, torch.minimum(ta, tb), torch.where(inside_slab, -inf, inf))
    t_exit = torch.where(nonzero, torch.maximum(ta, tb), torch.where(inside_slab, inf, -inf))
    near = t_enter.amax(dim=-1).clamp_min(near_min)
    far = t_exit.amin(dim=-1)
    hit = far > near
    near = torch.where(hit, near, torch.full_like(near, near_min))
    far = torch.where(hit, far, near)
    return near, far, hit


def ray_sphere(origins: Tensor, directions: Tensor, center: Tensor, radius: float | Tensor, near_min: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Intersect rays with unit directions with a sphere.

    The half chord is computed as ``sqrt((r - p)(r + p))`` from the perpendicular distance ``p``
    of the centre to the ray, which keeps its digits for grazing rays (``p -> r``) where the
    textbook discriminant ``b^2 - c`` cancels catastrophically.

    Args:
        origins: Ray origins ``(..., 3)``.
        directions: Unit ray directions ``(..., 3)``.
        center: Sphere centre ``(3,)`` or ``(..., 3)``.
        radius: Sphere radius (scene units).
        near_min: Smallest allowed ``t``.

    Returns:
        ``(near, far, hit)`` of shape ``(...)``; misses get ``near == far`` and ``hit == False``.

    Example:
        >>> o, d = torch.zeros(2, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
        >>> near, far, hit = ray_sphere(o, d, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), 1.0)
        >>> near[0].item(), far[0].item(), hit.tolist()
        (2.0, 4.0, [True, False])
    """
    oc = center.to(origins) - origins
    t_closest = (oc * directions).sum(dim=-1)
    perp = oc - t_closest[..., None] * directions
    p = torch.linalg.vector_norm(perp, dim=-1)
    r = torch.as_tensor(radius, dtype=origins.dtype, device=origins.device)
    half_sq = (r - p) * (r + p)
    half = torch.sqrt(half_sq.clamp_min(0.0))
    near = (t_closest - half).clamp_min(near_min)
    far = t_closest + half
    hit = (half_sq > 0) & (far > near)
    near = torch.where(hit, near, torch.full_like(near, near_min))
    far = torch.where(hit, far, near)
    return near, far, hit


class Bounds(Protocol):
    """Computes per-ray ``(near, far)`` of shape ``(...)`` for a :class:`RayBundle`."""

    def __call__(self, rays: RayBundle) -> tuple[Tensor, Tensor]: ...


@dataclass
class NearFarBounds:
    """The same ``[near, far]`` for every ray (AD-NeRF's choice, from the head's distance)."""

    near: float
    far: float

    def __post_init__(self) -> None:
        if not (0 <= self.near < self.far):
            raise ValueError(f"need 0 <= near < far; got near={self.near}, far={self.far}")

    def __call__(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        ref = rays.origins[..., 0].expand(rays.shape)
        return torch.full_like(ref, self.near), torch.full_like(ref, self.far)


@dataclass
class AABBBounds:
    """Bounds from an axis-aligned box ``[aabb_min, aabb_max]`` (each ``(3,)``)."""

    aabb_min: Tensor
    aabb_max: Tensor
    near_min: float = 0.0

    def __call__(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        o, d = torch.broadcast_tensors(rays.origins, rays.directions)
        near, far, _ = ray_aabb(o, d, self.aabb_min, self.aabb_max, self.near_min)
        return near, far


@dataclass
class PosedAABBBounds:
    """Bounds from a box fixed in a rigidly moving frame (e.g. the head box in canonical space).

    A box point ``p`` sits at ``R p + t`` in the rays' frame. Rays are moved into the box frame
    with the inverse transform; a rigid map keeps distances, so the ``t`` values found there are the
    ``t`` values of the original rays. (A :class:`~adnerf.model.layers.RadianceLayer` moves its
    rays into the box frame once for all of its passes instead; this per-call form is the
    reference its crossing is tested against.)

    Attributes:
        aabb_min: Box minimum in the box frame ``(3,)``.
        aabb_max: Box maximum ``(3,)``.
        R: Rotation box frame -> ray frame ``(3, 3)`` (or broadcastable against the rays).
        t: Translation ``(3,)``.
        near_min: Smallest allowed ``t``.
    """

    aabb_min: Tensor
    aabb_max: Tensor
    R: Tensor
    t: Tensor
    near_min: float = 0.0

    def __call__(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        o, d = torch.broadcast_tensors(rays.origins, rays.directions)
        R = self.R.to(o)
        o_box = to_canonical(o, R, self.t.to(o))
        d_box = directions_to_canonical(d, R)
        near, far, _ = ray_aabb(o_box, d_box, self.aabb_min, self.aabb_max, self.near_min)
        return near, far


@dataclass
class SphereBounds:
    """Bounds from a sphere with ``center`` ``(3,)`` and ``radius``."""

    center: Tensor
    radius: float
    near_min: float = 0.0

    def __call__(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        o, d = torch.broadcast_tensors(rays.origins, rays.directions)
        near, far, _ = ray_sphere(o, d, self.center, self.radius, self.near_min)
        return near, far


def stratified_edges(near: Tensor, far: Tensor, n_samples: int, *, jitter: bool = False, generator: torch.Generator | None = None) -> Tensor:
    """Interval boundaries for stratified sampling of ``[near, far]``.

    Deterministic (evaluation): ``n_samples`` equal intervals. Jittered (training): each interior
    boundary is drawn uniformly between the midpoints of its neighbouring uniform intervals, so
    intervals stay contiguous, sorted and cover ``[near, far]`` exactly.

    Args:
        near: Interval starts ``(...)``.
        far: Interval ends ``(...)``, ``far >= near``.
        n_samples: Number of intervals ``S >= 1``.
        jitter: Randomise interior boundaries.
        generator: Optional random generator for reproducibility, on any device (see :mod:`adnerf.rng`).

    Returns:
        Boundaries of shape ``(..., S + 1)``.

    Example:
        >>> stratified_edges(torch.tensor([1.0]), torch.tensor([2.0]), 4)
        tensor([[1.0000, 1.2500, 1.5000, 1.7500, 2.0000]])
    """
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1; got {n_samples}")
    u = torch.linspace(0.0, 1.0, n_samples + 1, dtype=near.dtype, device=near.device)
    u = u.expand(*near.shape, n_samples + 1)
    if jitter and n_samples > 1:
        step = 1.0 / n_samples
        noise = uniform((*near.shape, n_samples - 1), dtype=near.dtype, device=near.device, generator=generator)
        interior = u[..., 1:-1] + (noise - 0.5) * step
        u = torch.cat([u[..., :1], interior, u[..., -1:]], dim=-1)
    return near[..., None] + (far - near)[..., None] * u


@torch.no_grad()
def sample_pdf(bins: Tensor, weights: Tensor, n_samples: int, deterministic: bool = False, generator: torch.Generator | None = None) -> Tensor:
    """Draw positions from the piecewise-constant PDF given by ``weights`` over ``bins``.

    Inverse-CDF sampling as in NeRF's coarse-to-fine scheme, without gradients. Negative weights
    count as zero; a ray whose weights are all zero samples its whole interval uniformly. Bins of
    zero width and zero-probability bins are never divided by.

    Args:
        bins: Sorted bin boundaries, shape ``(..., B + 1)``.
        weights: Non-negative bin weights, shape ``(..., B)``.
        n_samples: Number of positions per ray.
        deterministic: Use the stratified quantiles ``(k + 0.5) / n`` instead of random ones.
        generator: Optional random generator, on any device (see :mod:`adnerf.rng`).

    Returns:
        Sorted positions inside ``[bins[..., 0], bins[..., -1]]``, shape ``(..., n_samples)``,
        detached from the graph.

    Example:
        >>> bins = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
        >>> sample_pdf(bins, torch.tensor([[0.0, 1.0, 0.0]]), 4, deterministic=True)  # all weight in [1, 2], at its quantiles
        tensor([[1.1250, 1.3750, 1.6250, 1.8750]])
    """
    if bins.shape[-1] != weights.shape[-1] + 1:
        raise ValueError(f"bins (..., B+1) and weights (..., B) disagree: {tuple(bins.shape)} vs {tuple(weights.shape)}")
    bins = bins.detach()
    w = weights.detach().clamp_min(0.0)
    batch = torch.broadcast_shapes(bins.shape[:-1], w.shape[:-1])
    bins = bins.expand(*batch, bins.shape[-1])
    w = w.expand(*batch, w.shape[-1])
    total = w.sum(dim=-1, keepdim=True)
    empty = total <= 0
    pdf = torch.where(empty, torch.ones_like(w) / w.shape[-1], w / torch.where(empty, torch.ones_like(total), total))
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[..., :1]), cdf[..., :-1], torch.ones_like(cdf[..., :1])], dim=-1)
    if deterministic:
        u = (torch.arange(n_samples, dtype=bins.dtype, device=bins.device) + 0.5) / n_samples
        u = u.expand(*batch, n_samples).contiguous()
    else:
        u = uniform((*batch, n_samples), dtype=bins.dtype, device=bins.device, generator=generator)
        u = torch.sort(u, dim=-1).values
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    n_bins = w.shape[-1]
    upper = idx.clamp(1, n_bins)
    lower = upper - 1
    cdf_lo = torch.gather(cdf, -1, lower)
    cdf_hi = torch.gather(cdf, -1, upper)
    bin_lo = torch.gather(bins, -1, lower)
    bin_hi = torch.gather(bins, -1, upper)
    span = cdf_hi - cdf_lo
    positive = span > 0
    frac = torch.where(positive, (u - cdf_lo) / torch.where(positive, span, torch.ones_like(span)), torch.zeros_like(u))
    samples = bin_lo + frac.clamp(0.0, 1.0) * (bin_hi - bin_lo)
    samples = torch.minimum(torch.maximum(samples, bins[..., :1]), bins[..., -1:])
    # Monotone in u by construction; sort guards rounding ties between bins.
    return torch.sort(samples, dim=-1).values


def blur_weights(weights: Tensor) -> Tensor:
    """mip-NeRF's weight filter: a 2-tap max then a 2-tap mean, ``(..., B) -> (..., B)``.

    Every bin next to a bin with weight gets weight too. Without it, the coarse bin that
    straddles a surface gets no importance samples whenever its midpoint falls outside the
    surface, and that bin's quadrature error is never refined (measured on the analytic sphere:
    plain inverse-CDF sampling then loses to stratified sampling at equal sample counts; with the
    filter it wins at every count, see ``adnerf bench render``).
    """
    padded = torch.nn.functional.pad(weights, (1, 1))
    pair_max = torch.maximum(padded[..., :-1], padded[..., 1:])
    return 0.5 * (pair_max[..., :-1] + pair_max[..., 1:])


@dataclass
class StratifiedSampler:
    """Stratified intervals in per-ray bounds.

    Attributes:
        n_samples: Intervals per ray.
        bounds: Where to sample (a :class:`Bounds`).

    Example:
        >>> from adnerf.cameras import intrinsics_matrix, pixel_rays
        >>> rays = pixel_rays(intrinsics_matrix(8.0, 8.0, 4.0, 4.0), 8, 8)
        >>> samples = StratifiedSampler(16, NearFarBounds(1.0, 3.0))(rays)
        >>> samples.t_starts.shape, samples.positions().shape
        (torch.Size([8, 8, 16]), torch.Size([8, 8, 16, 3]))
    """

    n_samples: int
    bounds: Bounds

    def __call__(self, rays: RayBundle, *, jitter: bool = False, generator: torch.Generator | None = None) -> RaySamples:
        near, far = self.bounds(rays)
        edges = stratified_edges(near, far, self.n_samples, jitter=jitter, generator=generator)
        return RaySamples.from_edges(rays, edges)


@dataclass
class ImportanceSampler:
    """NeRF's fine pass: draw ``n_samples`` by the coarse weights and merge with the coarse edges.

    The result has ``S_coarse + n_samples`` contiguous intervals spanning the same bounds.

    Attributes:
        n_samples: Importance samples per ray.
        blur: Filter the coarse weights with :func:`blur_weights` first (default; see there).
    """

    n_samples: int
    blur: bool = True

    def __call__(self, coarse: RaySamples, weights: Tensor, *, deterministic: bool = True, generator: torch.Generator | None = None) -> RaySamples:
        edges = coarse.edges.detach()
        if self.blur:
            weights = blur_weights(weights.detach())
        fine = sample_pdf(edges, weights, self.n_samples, deterministic=deterministic, generator=generator)
        merged = torch.sort(torch.cat([edges, fine], dim=-1), dim=-1).values
        return RaySamples.from_edges(coarse.rays, merged)
