"""Typed containers that flow between cameras, samplers, fields and the compositor.

Conventions (shared by every module of the package):

* Tensors are batch-first; ``...`` in a shape is any number of leading batch dimensions.
* A ray is ``x(t) = origin + t * direction`` with a unit-length direction, so ``t`` is the
  Euclidean distance from the origin (in the units of the scene, not camera-space ``z``).
* Samples along a ray are *intervals* ``[t_start, t_end]``; the field is evaluated at the
  interval's midpoint and the compositor integrates density over the interval's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

__all__ = ["RayBundle", "RaySamples"]


@dataclass
class RayBundle:
    """A batch of rays.

    Attributes:
        origins: Ray origins, shape ``(..., 3)``.
        directions: Unit ray directions, shape ``(..., 3)``.
    """

    origins: Tensor
    directions: Tensor

    def __post_init__(self) -> None:
        if self.origins.shape[-1:] != (3,) or self.directions.shape[-1:] != (3,):
            raise ValueError(
                "RayBundle needs origins and directions of shape (..., 3); got "
                f"{tuple(self.origins.shape)} and {tuple(self.directions.shape)}"
            )

    @property
    def shape(self) -> torch.Size:
        """Batch shape ``(...)`` of the bundle (broadcast of origins and directions)."""
        return torch.broadcast_shapes(self.origins.shape[:-1], self.directions.shape[:-1])

    def __len__(self) -> int:
        return self.shape[0]

    def map(self, fn: Callable[[Tensor], Tensor]) -> "RayBundle":
        """Apply ``fn`` to origins and directions (e.g. ``lambda x: x[mask]``) after broadcasting."""
        o, d = torch.broadcast_tensors(self.origins, self.directions)
        return RayBundle(fn(o), fn(d))

    def flatten(self) -> "RayBundle":
        """Return the bundle reshaped to ``(N, 3)``."""
        return self.map(lambda x: x.reshape(-1, 3))

    def reshape(self, *shape: int) -> "RayBundle":
        """Return the bundle reshaped to ``(*shape, 3)``."""
        return self.map(lambda x: x.reshape(*shape, 3))

    def __getitem__(self, index: object) -> "RayBundle":
        return self.map(lambda x: x[index])

    def at(self, t: Tensor) -> Tensor:
        """Points at distances ``t``.

        Args:
            t: Distances along each ray, shape ``(..., S)``.

        Returns:
            Points of shape ``(..., S, 3)``.

        Example:
            >>> rays = RayBundle(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
            >>> rays.at(torch.tensor([[2.0], [3.0]]))  # one distance (S = 1) along each ray
            tensor([[[0., 0., 2.]],
            <BLANKLINE>
                    [[3., 0., 0.]]])
        """
        return self.origins[..., None, :] + t[..., :, None] * self.directions[..., None, :]


@dataclass
class RaySamples:
    """Intervals along each ray of a :class:`RayBundle`.

    Attributes:
        rays: The rays, batch shape ``(...)``.
        t_starts: Interval starts, shape ``(..., S)``, non-decreasing along the last axis.
        t_ends: Interval ends, shape ``(..., S)``; ``t_ends >= t_starts``.
    """

    rays: RayBundle
    t_starts: Tensor
    t_ends: Tensor

    @property
    def t_mids(self) -> Tensor:
        """Interval midpoints, shape ``(..., S)``."""
        return 0.5 * (self.t_starts + self.t_ends)

    @property
    def deltas(self) -> Tensor:
        """Interval lengths, shape ``(..., S)``."""
        return self.t_ends - self.t_starts

    @property
    def edges(self) -> Tensor:
        """Interval boundaries as bins ``(..., S + 1)`` (assumes contiguous intervals)."""
        return torch.cat([self.t_starts, self.t_ends[..., -1:]], dim=-1)

    def positions(self) -> Tensor:
        """Midpoint positions, shape ``(..., S, 3)``."""
        return self.rays.at(self.t_mids)

    def directions(self) -> Tensor:
        """Ray direction repeated per sample, shape ``(..., S, 3)``."""
        return self.rays.directions[..., None, :].expand(*self.t_starts.shape, 3)

    @staticmethod
    def from_edges(rays: RayBundle, edges: Tensor) -> "RaySamples":
        """Build contiguous intervals from sorted boundaries ``edges`` of shape ``(..., S + 1)``."""
        return RaySamples(rays, edges[..., :-1], edges[..., 1:])
