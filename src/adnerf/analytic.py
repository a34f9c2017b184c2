"""Analytic scenes with closed-form volume rendering, for tests and benchmarks.

A homogeneous medium of density ``sigma`` crossed over a chord of length ``L`` starting at
``t0`` has

* opacity ``1 - exp(-sigma L)``;
* expected termination distance, given termination inside the medium,
  ``t0 + 1/sigma - L / expm1(sigma L)`` (``t0 + L/2`` in the thin limit, ``t0`` in the opaque one).

These are the references the quadrature of :mod:`adnerf.compositor` is checked against.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .fields import FieldOutput
from .samplers import ray_aabb, ray_sphere

__all__ = ["UniformBox", "UniformSphere", "homogeneous_depth", "homogeneous_opacity"]


def homogeneous_opacity(sigma: Tensor | float, chord: Tensor) -> Tensor:
    """``1 - exp(-sigma * chord)``, computed with ``expm1``."""
    return -torch.expm1(-sigma * chord)


def homogeneous_depth(sigma: Tensor | float, t0: Tensor, chord: Tensor) -> Tensor:
    """Expected termination distance in a homogeneous chord ``[t0, t0 + chord]``.

    ``t0 + 1/sigma - chord / expm1(sigma chord)``, switching to the series
    ``t0 + chord (1/2 - x/12 + x^3/720)`` with ``x = sigma chord < 1e-2`` (where the closed form
    cancels; the series' truncation error there is below 1e-14 relative). Rays with zero chord
    get ``t0``.
    """
    x = torch.as_tensor(sigma, dtype=chord.dtype, device=chord.device) * chord
    small = x < 1e-2
    safe_x = torch.where(small, torch.ones_like(x), x)
    closed = chord * (1.0 / safe_x - 1.0 / torch.expm1(safe_x))
    series = chord * (0.5 - x / 12.0 + x**3 / 720.0)
    return t0 + torch.where(small, series, closed)


@dataclass
class UniformSphere:
    """A sphere of uniform density ``sigma`` and uniform colour.

    Attributes:
        center: Centre ``(3,)``.
        radius: Radius.
        sigma: Density inside (1 / scene unit).
        color: RGB ``(3,)``.
    """

    center: Tensor
    radius: float
    sigma: float
    color: tuple[float, float, float] = (1.0, 0.5, 0.25)

    def density(self, points: Tensor) -> Tensor:
        """Density at points ``(..., 3)``: ``sigma`` strictly inside, 0 outside."""
        inside = torch.linalg.vector_norm(points - self.center.to(points), dim=-1) < self.radius
        return torch.where(inside, torch.full_like(points[..., 0], self.sigma), torch.zeros_like(points[..., 0]))

    def __call__(self, positions: Tensor, directions: Tensor | None = None, **_: object) -> FieldOutput:
        """Field interface for :class:`~adnerf.renderer.VolumeRenderer`."""
        rgb = torch.tensor(self.color, dtype=positions.dtype, device=positions.device).expand(*positions.shape[:-1], 3)
        return FieldOutput(rgb=rgb, density=self.density(positions))

    def truth(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Closed-form ``(opacity, depth, hit)`` per ray (unit directions); depth is ``t0`` for misses."""
        near, far, hit = ray_sphere(origins, directions, self.center, self.radius)
        chord = far - near
        return homogeneous_opacity(self.sigma, chord), homogeneous_depth(self.sigma, near, chord), hit


@dataclass
class UniformBox:
    """An axis-aligned box (a slab when thin along one axis) of uniform density.

    Attributes:
        aabb_min: Minimum corner ``(3,)``.
        aabb_max: Maximum corner ``(3,)``.
        sigma: Density inside.
    """

    aabb_min: Tensor
    aabb_max: Tensor
    sigma: float

    def density(self, points: Tensor) -> Tensor:
        """Density at points ``(..., 3)``."""
        inside = ((points > self.aabb_min.to(points)) & (points < self.aabb_max.to(points))).all(dim=-1)
        return torch.where(inside, torch.full_like(points[..., 0], self.sigma), torch.zeros_like(points[..., 0]))

    def __call__(self, positions: Tensor, directions: Tensor | None = None, **_: object) -> FieldOutput:
        """Field interface for :class:`~adnerf.renderer.VolumeRenderer` (white medium)."""
        return FieldOutput(rgb=torch.ones_like(positions), density=self.density(positions))

    def truth(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Closed-form ``(opacity, depth, hit)`` per ray."""
        near, far, hit = ray_aabb(origins, directions, self.aabb_min, self.aabb_max)
        chord = far - near
        return homogeneous_opacity(self.sigma, chord), homogeneous_depth(self.sigma, near, chord), hit
