"""Conditional radiance fields ``F(a, d, x) -> (rgb, density)``.

A :class:`RadianceField` is an encoding of positions (plug-in), an optional encoding of view
directions, an MLP, and a conditioning vector (the audio code, and for the torso the head pose)
concatenated to the encoded position at the input and at the skip layers, as in AD-NeRF. With
``cond_gate`` the field also reads a narrow projection of the condition that each point scales by
a gate of its own position's features (``P c * sigmoid(G e(x) + g)``), so that a condition can act
where the field learns it should (the audio code at the mouth) rather than only as the same shift
of every point's first layer. With ``cond_planes`` a tri-plane field's finest features also depend
on the condition inside a box (the mouth's): ``K`` residual plane sets blended by a linear
projection of the condition, ``e(x) + sum_k (W c)_k D_k(x)``, so that what a condition changes
there (lips parting, teeth showing) is stored at the grid's resolution instead of being drawn
out of the same features by the MLP.

The field knows no space and no pose: a :class:`~adnerf.model.layers.RadianceLayer` places it
(the head layer in the head's canonical space, the torso layer in camera space) and builds its
conditioning vector from the frame's signals. :func:`paper_config` builds the paper-faithful 8x256
MLP with a skip at layer 4 and a view branch, :func:`fast_config` a tri-plane grid with a small MLP.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .encodings import Encoding, PositionalEncoding, TriPlaneEncoding, box_to_unit, plane_grid, sample_planes

__all__ = ["FieldConfig", "FieldOutput", "RadianceField", "SampleRows", "fast_config", "paper_config"]

POSE_CODE_DIM = 9


@dataclass
class FieldOutput:
    """Field values at a batch of samples.

    Attributes:
        rgb: Colours in ``[0, 1]``, shape ``(..., 3)``.
        density: Non-negative densities (1 / scene unit), shape ``(...)``.
    """

    rgb: Tensor
    density: Tensor


@dataclass(frozen=True)
class SampleRows:
    """A condition given per ray and read at samples: ``rows (R, C)``, one per ray, and
    ``ray (...)``, the row of each point of the field call (integer indices into ``rows``).

    :class:`RadianceField` folds each row into its conditioned layers' biases once per ray and
    gathers the result per point, rather than carrying ``C`` values per point through the layer
    (``rows[ray]`` is the plain per-point condition).
    """

    rows: Tensor
    ray: Tensor


@dataclass
class FieldConfig:
    """Everything that defines a :class:`RadianceField`'s architecture.

    Attributes:
        encoding: ``"pe"`` (NeRF positional encoding) or ``"triplane"``.
        pe_frequencies: Octaves of the positional encoding of positions (paper: 10).
        dir_frequencies: Octaves of the direction encoding (paper: 4).
        use_view_dirs: Colour depends on the view direction (paper: yes).
        depth: Hidden layers of the trunk MLP (paper: 8).
        width: Width of the trunk (paper: 256).
        skips: Trunk layers whose input is re-concatenated with the encoded input (paper: (4,)).
        cond_dim: Conditioning width (audio code: 64; 0 for an unconditioned field).
        density_activation: ``"relu"`` (paper) or ``"softplus"`` (smooth, never dead).
        density_bias: Added to the raw density before the activation (a softplus field starts
            transparent with a negative bias).
        aabb_min: Box of the grid encoding (ignored by ``"pe"``).
        aabb_max: Box of the grid encoding.
        grid_levels: Tri-plane levels.
        grid_channels: Features per plane and level.
        grid_base_resolution: Coarsest tri-plane resolution.
        grid_max_resolution: Finest tri-plane resolution.
        cond_gate: Width of the gated condition (0: none): the condition projected to this many
            values once a ray (``P c``), scaled at each point by ``sigmoid(G e(x) + g)`` of the
            point's encoded position ``e(x)``, and read by the first layer (and the skips) beside
            the encoded position and the condition itself.
        cond_planes: Residual plane sets ``K`` of the conditioned features (tri-plane encoding
            only; 0: none): ``K`` sets of three planes ``(grid_channels, R, R)`` over the box
            ``cond_planes_min`` .. ``cond_planes_max``, blended by ``W c`` (``K`` weights, a
            linear map of the condition) and added to the finest level's features of the points
            inside the box, weighted by a box weight that falls from 1 to 0 over the outermost
            cell to each face (zero outside: a plane alone would reach every point of the slab
            its two coordinates span). The planes start at zero, so a new field is the
            unconditioned-features one.
        cond_planes_min: Box of the residual planes (the field's space).
        cond_planes_max: Box of the residual planes.
        cond_planes_resolution: Cells a side ``R`` of each residual plane.
    """

    encoding: Literal["pe", "triplane"] = "pe"
    pe_frequencies: int = 10
    dir_frequencies: int = 4
    use_view_dirs: bool = True
    depth: int = 8
    width: int = 256
    skips: tuple[int, ...] = (4,)
    cond_dim: int = 64
    density_activation: Literal["relu", "softplus"] = "relu"
    density_bias: float = 0.0
    aabb_min: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    aabb_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    grid_levels: int = 4
    grid_channels: int = 8
    grid_base_resolution: int = 16
    grid_max_resolution: int = 128
    cond_gate: int = 0
    cond_planes: int = 0
    cond_planes_min: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    cond_planes_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cond_planes_resolution: int = 128

    def to_dict(self) -> dict:
        """A JSON-serialisable dict (for checkpoints)."""
        d = asdict(self)
        d["skips"] = list(self.skips)
        return d

    @staticmethod
    def from_dict(d: dict) -> "FieldConfig":
        """Inverse of :meth:`to_dict`; unknown keys are an error."""
        check_config_keys(d, FieldConfig, "field config")
        d = dict(d)
        for key in ("skips", "aabb_min", "aabb_max", "cond_planes_min", "cond_planes_max"):
            if key in d:
                d[key] = tuple(d[key])
        return FieldConfig(**d)


def check_config_keys(d: dict, cls: type, what: str) -> None:
    """Raise ``ValueError`` naming the keys of ``d`` that are not fields of the dataclass ``cls``."""
    unknown = set(d) - set(cls.__dataclass_fields__)
    if unknown:
        raise ValueError(f"unknown {what} keys: {sorted(unknown)}")


def paper_config(cond_dim: int = 64) -> FieldConfig:
    """AD-NeRF's field: PE(10) positions, PE(4) directions, 8x256 MLP, skip at layer 4."""
    return FieldConfig(encoding="pe", depth=8, width=256, skips=(4,), cond_dim=cond_dim, use_view_dirs=True)


def fast_config(
    cond_dim: int = 64,
    aabb_min: tuple[float, float, float] = (-1.0, -1.0, -1.0),
    aabb_max: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> FieldConfig:
    """A tri-plane grid with a 2x64 MLP: trains and renders an order of magnitude faster on CPU."""
    return FieldConfig(
        encoding="triplane",
        depth=2,
        width=64,
        skips=(),
        cond_dim=cond_dim,
        use_view_dirs=False,
        density_activation="softplus",
        density_bias=-1.0,
        aabb_min=aabb_min,
        aabb_max=aabb_max,
    )


def _distinct_rows(rows: Tensor) -> tuple[Tensor, Tensor]:
    """Rows ``(R, C)`` as their distinct rows ``(U, C)`` (each the first of its equals, so its
    gradient is the sum over its copies for whatever they were copied from) and each row's
    index among them ``(R,)``. Rows are grouped by a projection and the grouping is checked
    exactly; should two different rows share a projection, every row is its own."""
    r = rows.shape[0]
    key = rows.detach() @ torch.linspace(1.0, 2.0, rows.shape[1], dtype=rows.dtype, device=rows.device)
    _, of_row = torch.unique(key, return_inverse=True)
    first = torch.full((int(of_row.max()) + 1,), r, dtype=of_row.dtype, device=rows.device)
    first = first.scatter_reduce(0, of_row, torch.arange(r, device=rows.device), "amin")
    distinct = rows.index_select(0, first)
    if not torch.equal(distinct.detach().index_select(0, of_row), rows.detach()):
        return rows, torch.arange(r, device=rows.device)
    return distinct, of_row


def _make_encoding(cfg: FieldConfig) -> Encoding:
    if cfg.encoding == "pe":
        return PositionalEncoding(3, cfg.pe_frequencies)
    if cfg.encoding == "triplane":
        return TriPlaneEncoding(
            cfg.aabb_min, cfg.aabb_max, cfg.grid_levels, cfg.grid_channels, cfg.grid_base_resolution, cfg.grid_max_resolution
        )
    raise ValueError(f"unknown encoding {cfg.encoding!r}; choose 'pe' or 'triplane'")


class RadianceField(nn.Module):
    """A conditional radiance field ``F(a, d, x) -> (rgb, density)``.

    Args:
        config: The architecture (see :class:`FieldConfig`).
    """

    def __init__(self, config: FieldConfig) -> None:
        super().__init__()
        if config.depth < 1 or config.width < 1:
            raise ValueError("field depth and width must be >= 1")
        if config.cond_gate < 0 or (config.cond_gate and not config.cond_dim):
            raise ValueError(f"cond_gate is the width of a gated condition (>= 0, and the field must have a condition); got {config.cond_gate} with cond_dim {config.cond_dim}")
        if config.cond_planes < 0 or (config.cond_planes and (not config.cond_dim or config.encoding != "triplane")):
            raise ValueError(f"cond_planes is a number of residual plane sets (>= 0) of a conditioned tri-plane field; got {config.cond_planes} with cond_dim {config.cond_dim} and encoding {config.encoding!r}")
        if config.cond_planes and (config.cond_planes_resolution < 2 or any(not hi > lo for lo, hi in zip(config.cond_planes_min, config.cond_planes_max))):
            raise ValueError(f"the residual planes need a resolution >= 2 and a box with max > min; got {config.cond_planes_resolution}, {config.cond_planes_min} .. {config.cond_planes_max}")
        if any(not 0 < s < config.depth for s in config.skips):
            raise ValueError(f"skip layers must lie in 1..depth-1; got {config.skips} for depth {config.depth}")
        if config.density_activation not in ("relu", "softplus"):
            raise ValueError(f"unknown density activation {config.density_activation!r}")
        self.config = config
        self.position_encoding = _make_encoding(config)
        in_dim = self.position_encoding.out_dim + config.cond_gate + config.cond_dim
        self.gate_code: nn.Linear | None = None
        self.gate: nn.Linear | None = None
        if config.cond_gate:
            self.gate_code = nn.Linear(config.cond_dim, config.cond_gate, bias=False)
            self.gate = nn.Linear(self.position_encoding.out_dim, config.cond_gate)
        self.plane_code: nn.Linear | None = None
        self.cond_residual: nn.Parameter | None = None
        if config.cond_planes:
            r, k = config.cond_planes_resolution, config.cond_planes
            self.plane_code = nn.Linear(config.cond_dim, k, bias=False)
            self.cond_residual = nn.Parameter(torch.zeros(k, 3, config.grid_channels, r, r))
            self.register_buffer("cond_box_min", torch.tensor(config.cond_planes_min, dtype=torch.float32))
            self.register_buffer("cond_box_max", torch.tensor(config.cond_planes_max, dtype=torch.float32))
        layers = []
        for i in range(config.depth):
            fan_in = in_dim if i == 0 else config.width + (in_dim if i in config.skips else 0)
            layers.append(nn.Linear(fan_in, config.width))
        self.trunk = nn.ModuleList(layers)
        self.density_head = nn.Linear(config.width, 1)
        if config.use_view_dirs:
            self.direction_encoding: Encoding | None = PositionalEncoding(3, config.dir_frequencies)
            self.feature = nn.Linear(config.width, config.width)
            self.view_layer = nn.Linear(config.width + self.direction_encoding.out_dim, config.width // 2)
            self.rgb_head = nn.Linear(config.width // 2, 3)
        else:
            self.direction_encoding = None
            self.rgb_head = nn.Linear(config.width, 3)

    def _residual(self, positions: Tensor, condition: Tensor | SampleRows) -> tuple[Tensor, Tensor] | None:
        """The conditioned residual of the finest features (see ``cond_planes``) at the points
        inside the box: ``(idx (M,), values (3 * grid_channels, M))`` into the flattened points,
        ``None`` when no point is inside (the others cost nothing).

        The planes are blended once for each distinct condition when there are fewer of those
        than sets (one frame's condition; a training step's rays, from a frame or two), and each
        blend is sampled at its own points; otherwise every set is sampled at the points and
        blended there."""
        assert self.plane_code is not None and self.cond_residual is not None
        cfg = self.config
        width = 3 * cfg.grid_channels
        dtype = positions.dtype
        p = box_to_unit(positions.reshape(-1, 3), self.cond_box_min, self.cond_box_max)
        n = p.shape[0]
        # Each plane reads a point by two of its coordinates, so a point outside the box along the
        # third would still read it: the box's own weight, 1 inside, falling to 0 over the
        # outermost cell to each face, keeps the residual in the box (and continuous).
        cell = 2.0 / (cfg.cond_planes_resolution - 1)
        box = ((1.0 - p.abs()) / cell).clamp(0.0, 1.0).prod(dim=-1)  # (N,)
        idx = torch.nonzero(box > 0).reshape(-1)  # (M,)
        if idx.numel() == 0:
            return None
        grid = plane_grid(p.index_select(0, idx))
        # The conditions as rows (U, C) and each inside point's row (M,).
        if isinstance(condition, SampleRows):
            rows, of_ray = _distinct_rows(condition.rows.to(dtype))
            which = of_ray.index_select(0, condition.ray.reshape(-1).index_select(0, idx))
        elif condition.dim() == 1:
            rows, which = condition.to(dtype)[None], torch.zeros_like(idx)
        else:
            rows = condition.to(dtype).expand(*positions.shape[:-1], cfg.cond_dim).reshape(n, cfg.cond_dim).index_select(0, idx)
            which = torch.arange(idx.numel(), device=idx.device)
        w = self.plane_code(rows)  # (U, K)
        residual = self.cond_residual.to(dtype)
        if rows.shape[0] < cfg.cond_planes:
            blends = torch.einsum("uk,kpcij->upcij", w, residual)
            if rows.shape[0] == 1:
                feats = sample_planes(blends[0], grid, "zeros").reshape(width, -1)
            else:
                ats = [torch.nonzero(which == u).reshape(-1) for u in range(rows.shape[0])]
                parts = [sample_planes(blends[u], grid.index_select(2, at), "zeros").reshape(width, -1) for u, at in enumerate(ats)]
                # Back into the points' order: the inverse permutation of the groups' concatenation.
                feats = torch.cat(parts, dim=1).index_select(1, torch.argsort(torch.cat(ats)))
        else:
            k, m = cfg.cond_planes, idx.numel()
            stacked = residual.transpose(0, 1).reshape(3, k * cfg.grid_channels, *residual.shape[-2:])
            looked = sample_planes(stacked, grid, "zeros").reshape(3, k, cfg.grid_channels, m)
            feats = torch.einsum("pkcn,nk->pcn", looked, w.index_select(0, which)).reshape(width, m)
        return idx, feats * box.index_select(0, idx)

    def forward(self, positions: Tensor, directions: Tensor | None = None, condition: Tensor | None = None) -> FieldOutput:
        """Evaluate the field.

        Args:
            positions: Points in the field's own space, shape ``(..., 3)``.
            directions: Unit view directions ``(..., 3)``; required when the config uses them.
            condition: Conditioning ``(..., cond_dim)``, a single ``(cond_dim,)`` vector shared
                by all points, or :class:`SampleRows` (one vector per ray, ``ray`` of the
                points' shape ``(...)``); required iff ``cond_dim > 0``.

        Returns:
            :class:`FieldOutput` with ``rgb (..., 3)`` and ``density (...)``, in the dtype of the
            field's parameters.
        """
        cfg = self.config
        batch = positions.shape[:-1]
        if cfg.cond_dim:
            if condition is None:
                raise ValueError(f"this field is conditioned ({cfg.cond_dim}-d) but no condition was given")
            width = condition.rows.shape[-1] if isinstance(condition, SampleRows) else condition.shape[-1]
            if width != cfg.cond_dim:
                raise ValueError(f"condition must have {cfg.cond_dim} features; got {width}")
        if self.cond_residual is not None:  # cond_planes needs cond_dim, so the condition is there
            assert condition is not None
            h_in = self.position_encoding(positions, finest=self._residual(positions, condition))
        else:
            h_in = self.position_encoding(positions)
        # One condition for every point, or one per ray: folded into the layer biases.
        shared: Tensor | SampleRows | None = None
        if cfg.cond_dim:
            assert condition is not None
            if isinstance(condition, SampleRows):
                if condition.ray.shape != batch:
                    raise ValueError(f"the rows' ray index must have the points' shape {tuple(batch)}; got {tuple(condition.ray.shape)}")
                shared = SampleRows(condition.rows.to(h_in), condition.ray)
            elif condition.dim() == 1:
                shared = condition.to(h_in)
            if self.gate_code is not None and self.gate is not None:
                # The projection once a ray (or frame), the gate at each point: [e(x), P c * gate(x)].
                if isinstance(shared, SampleRows):
                    code = self.gate_code(shared.rows).index_select(0, shared.ray.reshape(-1)).reshape(*batch, cfg.cond_gate)
                else:
                    code = self.gate_code(condition.to(h_in))
                h_in = torch.cat([h_in, code * torch.sigmoid(self.gate(h_in))], dim=-1)
            if shared is None:
                h_in = torch.cat([h_in, condition.to(h_in).expand(*batch, cfg.cond_dim)], dim=-1)
        elif condition is not None:
            raise ValueError("this field takes no condition (cond_dim = 0)")
        h = h_in
        for i, layer in enumerate(self.trunk):
            if i in cfg.skips:
                h = torch.cat([h, h_in], dim=-1)
            if shared is None or not (i == 0 or i in cfg.skips):
                h = F.relu(layer(h))
            else:
                # W [x; c] + b == W_x x + (W_c c + b): the same layer without a per-point copy of c
                # (per ray: W_c c + b once a ray, gathered per point).
                k = cfg.cond_dim
                w_x, w_c = layer.weight[:, :-k], layer.weight[:, -k:]
                if isinstance(shared, SampleRows):
                    # index_select, not [ray]: its backward sums the points' gradients into their
                    # rows in a fixed order (indexing's backward adds them atomically across CPU
                    # threads, so a run's gradients would differ in the last bits run to run).
                    per_ray = F.linear(shared.rows, w_c, layer.bias)
                    h = F.relu(F.linear(h, w_x) + per_ray.index_select(0, shared.ray.reshape(-1)).reshape(*shared.ray.shape, -1))
                else:
                    h = F.relu(F.linear(h, w_x, layer.bias + w_c @ shared))
        raw_density = self.density_head(h)[..., 0] + cfg.density_bias
        density = F.relu(raw_density) if cfg.density_activation == "relu" else F.softplus(raw_density)
        if self.direction_encoding is not None:
            if directions is None:
                raise ValueError("this field uses view directions but none were given")
            d = self.direction_encoding(directions.to(h).expand(*batch, 3))
            h = F.relu(self.view_layer(torch.cat([self.feature(h), d], dim=-1)))
        rgb = torch.sigmoid(self.rgb_head(h))
        return FieldOutput(rgb=rgb, density=density)
