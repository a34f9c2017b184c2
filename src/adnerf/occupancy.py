"""An occupancy grid that lets rays skip space known to be empty.

The grid covers a box with ``resolution^3`` cells and keeps, per cell, a running estimate of the
largest density seen there. Cells whose estimate is below a threshold are *empty*: the renderer
does not evaluate the field at samples in them (their density counts as zero), so empty space
costs a lookup instead of an MLP evaluation. Points outside the box are empty.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor, nn

from .rng import uniform

__all__ = ["OccupancyGrid"]


class OccupancyGrid(nn.Module):
    """A dense boolean occupancy grid over ``[aabb_min, aabb_max]``.

    Args:
        aabb_min: Box minimum ``(3,)``.
        aabb_max: Box maximum ``(3,)``.
        resolution: Cells per axis.
        threshold: Density below which a cell is empty (1 / scene unit).
    """

    def __init__(self, aabb_min: Tensor | tuple[float, ...], aabb_max: Tensor | tuple[float, ...], resolution: int = 64, threshold: float = 0.01) -> None:
        super().__init__()
        if resolution < 1:
            raise ValueError(f"resolution must be >= 1; got {resolution}")
        self.resolution = resolution
        self.threshold = threshold
        self.register_buffer("aabb_min", torch.as_tensor(aabb_min, dtype=torch.float64).clone())
        self.register_buffer("aabb_max", torch.as_tensor(aabb_max, dtype=torch.float64).clone())
        if not bool((self.aabb_max > self.aabb_min).all()):
            raise ValueError("occupancy grid box must have aabb_max > aabb_min on every axis")
        self.register_buffer("density", torch.full((resolution,) * 3, float("inf")))
        self.register_buffer("occupied", torch.ones((resolution,) * 3, dtype=torch.bool))

    @property
    def estimated(self) -> bool:
        """Whether :meth:`update` has run (before it every cell is occupied, density ``inf``)."""
        return bool(torch.isfinite(self.density).all())

    @property
    def cell_size(self) -> Tensor:
        """Cell edge lengths ``(3,)``."""
        return (self.aabb_max - self.aabb_min) / self.resolution

    def cell_centers(self) -> Tensor:
        """Centres of all cells, shape ``(R, R, R, 3)``, float64, indexed ``[ix, iy, iz]``."""
        idx = torch.arange(self.resolution, dtype=torch.float64, device=self.aabb_min.device) + 0.5
        grid = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), dim=-1)
        return self.aabb_min + grid * self.cell_size

    def cell_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Integer cell indices ``(..., 3)`` of points ``(..., 3)`` and whether each is inside."""
        rel = (points.to(self.aabb_min.dtype) - self.aabb_min) / self.cell_size
        inside = ((rel >= 0) & (rel < self.resolution)).all(dim=-1)
        idx = rel.floor().long().clamp(0, self.resolution - 1)
        return idx, inside

    def is_occupied(self, points: Tensor) -> Tensor:
        """Whether points ``(..., 3)`` lie in occupied cells; shape ``(...)``, bool."""
        idx, inside = self.cell_index(points)
        occ = self.occupied[idx[..., 0], idx[..., 1], idx[..., 2]]
        return occ & inside

    @torch.no_grad()
    def update(
        self,
        density_fn: Callable[[Tensor], Tensor],
        *,
        decay: float = 0.0,
        jitter: bool = True,
        chunk: int = 65536,
        generator: torch.Generator | None = None,
    ) -> float:
        """Re-estimate cell densities and the occupied mask.

        Each cell's density becomes ``max(decay * old, density_fn(point in cell))``: a random
        point per cell when ``jitter`` (repeated updates cover the cell), else the cell centre.
        Use ``decay = 0`` to replace the estimate, e.g. for a known analytic density.

        Args:
            density_fn: Maps points ``(N, 3)`` (float64) to densities ``(N,)``.
            decay: Weight of the previous estimate, in ``[0, 1]``.
            jitter: Sample a random point inside each cell instead of its centre.
            chunk: Points per call of ``density_fn``.
            generator: Optional random generator, on any device (see :mod:`adnerf.rng`).

        Returns:
            The fraction of occupied cells.
        """
        points = self.cell_centers().reshape(-1, 3)
        if jitter:
            noise = uniform(points.shape, dtype=points.dtype, device=points.device, generator=generator) - 0.5
            points = points + noise * self.cell_size
        values = torch.cat([density_fn(points[i : i + chunk]).reshape(-1).to(torch.float32) for i in range(0, points.shape[0], chunk)])
        values = values.reshape(self.density.shape).to(self.density.device)
        old = torch.where(torch.isfinite(self.density), self.density, torch.zeros_like(self.density))
        self.density = torch.maximum(decay * old, values)
        self.occupied = self.density > self.threshold
        return self.occupied.float().mean().item()

    def dilate(self, cells: int = 1) -> None:
        """Grow the occupied region by ``cells`` in every direction (a safety margin)."""
        if cells <= 0:
            return
        occ = self.occupied.float()[None, None]
        grown = torch.nn.functional.max_pool3d(occ, kernel_size=2 * cells + 1, stride=1, padding=cells)
        self.occupied = grown[0, 0] > 0
