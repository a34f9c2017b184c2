"""Input encodings for radiance fields.

* :class:`PositionalEncoding` is NeRF's (and AD-NeRF's) frequency encoding: ``[x, sin(2^k x),
  cos(2^k x)]`` for ``k = 0 .. L-1``; 10 frequencies for positions, 4 for directions.
* :class:`TriPlaneEncoding` is a fast learnable encoding in pure PyTorch: multi-resolution
  feature planes on the xy, xz and yz planes of a box, bilinearly interpolated with
  :func:`torch.nn.functional.grid_sample`. It trades the MLP's depth for memory and makes CPU
  training practical.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["Encoding", "PositionalEncoding", "TriPlaneEncoding", "plane_grid", "sample_planes"]


class Encoding(nn.Module):
    """An encoding maps ``(..., in_dim)`` to ``(..., out_dim)``."""

    in_dim: int
    out_dim: int


class PositionalEncoding(Encoding):
    """NeRF frequency encoding.

    Args:
        in_dim: Input dimension (3 for points and directions).
        n_frequencies: Number of octaves ``L``; frequencies ``2^0 .. 2^(L-1)`` (radians per unit).
        include_input: Prepend the raw input, as NeRF does.

    Example:
        >>> pe = PositionalEncoding(3, 10)  # AD-NeRF's positions: x and sin / cos of 10 octaves
        >>> pe.out_dim
        63
        >>> pe(torch.zeros(2, 3))[0, :6]  # x itself, then sin(x) = 0
        tensor([0., 0., 0., 0., 0., 0.])
    """

    def __init__(self, in_dim: int = 3, n_frequencies: int = 10, include_input: bool = True) -> None:
        super().__init__()
        if n_frequencies < 0:
            raise ValueError(f"n_frequencies must be >= 0; got {n_frequencies}")
        self.in_dim = in_dim
        self.n_frequencies = n_frequencies
        self.include_input = include_input
        self.register_buffer("freqs", 2.0 ** torch.arange(n_frequencies, dtype=torch.float64), persistent=False)
        self.out_dim = in_dim * (int(include_input) + 2 * n_frequencies)

    def forward(self, x: Tensor) -> Tensor:
        """Encode ``x`` of shape ``(..., in_dim)`` to ``(..., out_dim)`` (NeRF's ordering)."""
        parts = [x] if self.include_input else []
        if self.n_frequencies:
            scaled = x[..., None, :] * self.freqs.to(x)[:, None]  # (..., L, D)
            # NeRF ordering: for each frequency, sin then cos of all D components.
            parts.append(torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2).reshape(*x.shape[:-1], -1))
        return torch.cat(parts, dim=-1)


def box_to_unit(x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Map points ``(..., 3)`` of the box ``[lo, hi]`` (corners ``(3,)``) to ``[-1, 1]^3``,
    in the points' dtype."""
    lo, hi = lo.to(x), hi.to(x)
    return 2.0 * (x - lo) / (hi - lo) - 1.0


def plane_grid(p: Tensor) -> Tensor:
    """Points ``(N, 3)`` in ``[-1, 1]^3`` as ``grid_sample`` coordinates of the xy, xz and yz
    planes, ``(3, 1, N, 2)`` (``(x, y)`` = (width, height) order)."""
    return torch.stack([p[:, [0, 1]], p[:, [0, 2]], p[:, [1, 2]]], dim=0)[:, None]


def sample_planes(planes: Tensor, grid: Tensor, padding: str) -> Tensor:
    """Bilinear features of three planes ``(3, C, R, R)`` at :func:`plane_grid` coordinates
    ``(3, 1, N, 2)``: ``(3, C, 1, N)``, feature-major. ``padding``: ``"border"`` (points outside
    read the edge) or ``"zeros"`` (they read zero, fading over the outermost cell)."""
    return F.grid_sample(planes, grid, mode="bilinear", padding_mode=padding, align_corners=True)


class TriPlaneEncoding(Encoding):
    """Multi-resolution tri-plane feature encoding.

    Points are mapped from the box ``[aabb_min, aabb_max]`` to ``[-1, 1]^3``; for each level the
    features of the xy, xz and yz planes are sampled bilinearly and concatenated, giving
    ``out_dim = 3 * n_levels * channels``. Points outside the box read the border features.

    Args:
        aabb_min: Box minimum ``(3,)``.
        aabb_max: Box maximum ``(3,)``.
        n_levels: Number of resolutions, geometric from ``base_resolution`` to ``max_resolution``.
        channels: Features per plane and level.
        base_resolution: Coarsest plane resolution.
        max_resolution: Finest plane resolution.
        init_scale: Standard deviation of the initial features.
    """

    def __init__(
        self,
        aabb_min: Tensor | tuple[float, float, float] = (-1.0, -1.0, -1.0),
        aabb_max: Tensor | tuple[float, float, float] = (1.0, 1.0, 1.0),
        n_levels: int = 4,
        channels: int = 8,
        base_resolution: int = 16,
        max_resolution: int = 128,
        init_scale: float = 0.1,
    ) -> None:
        super().__init__()
        if n_levels < 1 or channels < 1 or base_resolution < 2 or max_resolution < base_resolution:
            raise ValueError("TriPlaneEncoding needs n_levels >= 1, channels >= 1 and 2 <= base_resolution <= max_resolution")
        self.in_dim = 3
        self.n_levels = n_levels
        self.channels = channels
        self.register_buffer("aabb_min", torch.as_tensor(aabb_min, dtype=torch.float32).clone())
        self.register_buffer("aabb_max", torch.as_tensor(aabb_max, dtype=torch.float32).clone())
        if n_levels == 1:
            resolutions = [max_resolution]
        else:
            growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))
            resolutions = [int(round(base_resolution * growth**i)) for i in range(n_levels)]
        self.resolutions = resolutions
        self.planes = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(3, channels, r, r)) for r in resolutions]
        )
        self.out_dim = 3 * n_levels * channels

    def normalize(self, x: Tensor) -> Tensor:
        """Map points ``(..., 3)`` from the box to ``[-1, 1]^3``."""
        return box_to_unit(x, self.aabb_min, self.aabb_max)

    def forward(self, x: Tensor, finest: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Encode points ``(..., 3)`` to features ``(..., 3 * n_levels * channels)``.

        ``finest``: ``(idx (M,), values (3 * channels, M))``, added to the finest level's features
        of the points ``idx`` (distinct indices into the flattened points; a field's conditioned
        residual)."""
        batch = x.shape[:-1]
        p = self.normalize(x.reshape(-1, 3))
        grid = plane_grid(p)
        n = grid.shape[2]
        # grid_sample gives (3, C, 1, N) per level: feature-major, so the levels stack along dim 0
        # without a permute, and the (F, N) result is handed on transposed, as a view (the MLP's
        # matrix product reads transposed operands directly). Feature order: level, plane, channel.
        feats = [sample_planes(planes.to(x.dtype), grid, "border").reshape(3 * self.channels, n) for planes in self.planes]
        if finest is not None:
            idx, values = finest
            feats[-1] = feats[-1].index_add(1, idx, values.to(feats[-1].dtype))
        return torch.cat(feats, dim=0).t().reshape(*batch, self.out_dim)

    def total_variation(self) -> Tensor:
        """Mean squared difference of neighbouring plane features (a smoothness regulariser)."""
        tv = torch.zeros((), dtype=self.planes[0].dtype, device=self.planes[0].device)
        for planes in self.planes:
            tv = tv + (planes[..., 1:, :] - planes[..., :-1, :]).pow(2).mean() + (planes[..., :, 1:] - planes[..., :, :-1]).pow(2).mean()
        return tv
