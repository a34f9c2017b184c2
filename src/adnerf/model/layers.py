"""Radiance layers: a field with its own space, box, samples, occupancy grid and conditions.

A talking-head frame is a stack of layers over a background plate (:mod:`adnerf.model.talking_head`
builds AD-NeRF's two). A :class:`RadianceLayer` owns everything that differs between them:

- its **space**: ``canonical`` (the head's frame: camera rays are moved into it once per frame
  with the frame's head pose, so box, grid and field never see the pose) or camera space;
- its **box** (axis-aligned in its space) and ``(coarse, fine)`` sample counts, fixed, so its
  :class:`~adnerf.renderer.VolumeRenderer` is built once;
- its **occupancy grid** (empty-space skipping, in its space);
- its coarse and fine **fields** (:class:`~adnerf.fields.RadianceField` or anything called as
  ``field(positions, directions, condition)``);
- the **conditions** it reads from a :class:`~adnerf.model.conditions.FrameCondition`, concatenated
  in order into its fields' conditioning vector;
- optionally a **warp**: a signal of the frame (``(9,)``, a row-major ``3 x 3`` map ``H``) that
  turns each camera ray's direction to that of ``H d`` about its origin, the camera centre, before the
  layer's space (the torso's measured motion in the image,
  :func:`~adnerf.model.conditions.torso_rays_map`): the field learns one reference picture of
  what moves, and a frame's rays look where its pixels were in that picture.

Rays given to a layer are camera rays; the ``t`` values it returns (depth) are the camera rays'
because a rigid move keeps distances. Geometry runs in the rays' dtype (float64 in adnerf); the
fields get their parameters' dtype.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor, nn

from ..compositor import Composite
from ..fields import FieldOutput, SampleRows
from ..occupancy import OccupancyGrid
from ..pose import HeadPose, directions_to_canonical
from ..rays import RayBundle
from ..renderer import PerRay, RenderOutput, VolumeRenderer
from ..samplers import AABBBounds
from .conditions import FrameCondition

__all__ = ["RadianceLayer", "SPACES"]

SPACES = ("canonical", "camera")
Box = tuple[tuple[float, float, float], tuple[float, float, float]]


class _CastField:
    """A field called in its parameters' dtype, with the layer's conditioning vector: one frame's
    ``(C,)`` held here, or each ray's (:class:`~adnerf.fields.SampleRows` of the samples
    evaluated), which the renderer passes as ``condition`` for per-ray conditions
    (:class:`~adnerf.renderer.PerRay`)."""

    def __init__(self, field: nn.Module, condition: Tensor | None) -> None:
        self.field, self.condition = field, condition
        self.dtype = next(field.parameters()).dtype

    def __call__(self, positions: Tensor, directions: Tensor, condition: Tensor | SampleRows | None = None) -> FieldOutput:
        return self.field(positions.to(self.dtype), directions.to(self.dtype), self.condition if condition is None else condition)


class RadianceLayer(nn.Module):
    """One layer of a frame (see the module docstring).

    Args:
        name: The layer's name (``"head"``, ``"torso"``, ...).
        coarse: Field of the coarse pass.
        fine: Field of the fine pass (``None``: the coarse field again).
        aabb: ``(min, max)`` corners of its box in its space.
        samples: ``(coarse, fine)`` samples per ray; fine 0 turns the fine pass off.
        space: ``"canonical"`` or ``"camera"``.
        conditions: Signal names of :class:`~adnerf.model.conditions.FrameCondition` its fields read.
        warp: The signal whose value moves its rays (see the module docstring), or ``None``.
        occupancy_resolution: Cells per axis of its occupancy grid; 0: no grid.
        occupancy_threshold: Density (1 / scene unit) below which a cell is empty.
    """

    def __init__(
        self,
        name: str,
        coarse: nn.Module,
        fine: nn.Module | None,
        aabb: Box,
        samples: tuple[int, int],
        *,
        space: str,
        conditions: Sequence[str],
        warp: str | None = None,
        occupancy_resolution: int = 0,
        occupancy_threshold: float = 0.01,
    ) -> None:
        super().__init__()
        if space not in SPACES:
            raise ValueError(f"a layer's space must be one of {SPACES}; got {space!r}")
        self.name = name
        self.space = space
        self.conditions = tuple(conditions)
        self.warp = warp
        self.aabb: Box = (tuple(float(v) for v in aabb[0]), tuple(float(v) for v in aabb[1]))  # type: ignore[assignment]
        self.samples = (int(samples[0]), int(samples[1]))
        self.coarse = coarse
        self.fine = fine
        self.occupancy = OccupancyGrid(*self.aabb, resolution=occupancy_resolution, threshold=occupancy_threshold) if occupancy_resolution > 0 else None
        self._renderers: dict[tuple[torch.dtype, torch.device], VolumeRenderer] = {}

    # ---- space and geometry
    @property
    def canonical(self) -> bool:
        """Whether the layer lives in the head's canonical frame."""
        return self.space == "canonical"

    def warped(self, rays: RayBundle, cond: FrameCondition) -> RayBundle:
        """Camera rays ``(R,)`` moved by the layer's warp of ``cond`` (unchanged without one):
        directions ``H d`` scaled back to the length of ``d``, origins kept.

        Raises:
            KeyError: The frame carries no value of the warp's signal.
        """
        if self.warp is None:
            return rays
        if self.warp not in cond.extra:
            raise KeyError(f"layer {self.name!r} is moved by the {self.warp!r} signal, which this frame does not carry")
        d = rays.directions
        H = cond.extra[self.warp].to(d.dtype).reshape(*cond.extra[self.warp].shape[:-1], 3, 3)
        moved = (H @ d.unsqueeze(-1)).squeeze(-1)
        # Kept at the camera ray's length, so that t stays a distance as it is for unit rays.
        return RayBundle(rays.origins, moved * (torch.linalg.vector_norm(d, dim=-1, keepdim=True) / torch.linalg.vector_norm(moved, dim=-1, keepdim=True)))

    def to_space(self, rays: RayBundle, pose: HeadPose | None) -> RayBundle:
        """Camera rays moved into the layer's space (canonical: by the inverse of ``pose``)."""
        if not self.canonical:
            return rays
        if pose is None:
            raise ValueError(f"layer {self.name!r} lives in canonical space: its rays need the frame's head pose")
        o, d = torch.broadcast_tensors(rays.origins, rays.directions)
        R = pose.R.to(o)
        return RayBundle(pose.to_canonical(o.to(pose.R)).to(o), directions_to_canonical(d, R))

    def renderer(self, like: Tensor) -> VolumeRenderer:
        """The layer's renderer for rays of ``like``'s dtype and device (built once per pair)."""
        key = (like.dtype, like.device)
        if key not in self._renderers:
            lo = torch.tensor(self.aabb[0], dtype=like.dtype, device=like.device)
            hi = torch.tensor(self.aabb[1], dtype=like.dtype, device=like.device)
            self._renderers[key] = VolumeRenderer(AABBBounds(lo, hi), *self.samples)
        return self._renderers[key]

    def crossing(self, rays: RayBundle, pose: HeadPose | None = None) -> tuple[Tensor, Tensor]:
        """``(near, far)`` of camera rays through the layer's box (``far <= near``: a miss)."""
        moved = self.to_space(rays, pose)
        return self.renderer(moved.origins).coarse_sampler.bounds(moved)

    def occupied(self) -> Callable[[Tensor], Tensor] | None:
        """The empty-space predicate on points of the layer's space, ``None`` before its grid is estimated."""
        if self.occupancy is None or not self.occupancy.estimated:
            return None
        return self.occupancy.is_occupied

    # ---- fields
    def _fields(self, cond: FrameCondition) -> tuple[_CastField, _CastField, dict[str, PerRay]]:
        """The coarse and fine fields under ``cond``, and the renderer's conditioning: nothing
        for one frame's condition (the fields hold its vector), the vectors ``(R, C)`` of a
        per-ray one."""
        dtype = next(self.coarse.parameters()).dtype
        vector = cond.vector(self.conditions, dtype)
        per_ray = cond.per_ray and vector is not None
        held = None if per_ray else vector
        fields = _CastField(self.coarse, held), _CastField(self.fine if self.fine is not None else self.coarse, held)
        return fields[0], fields[1], {"condition": PerRay(vector)} if per_ray else {}

    # ---- rendering
    def render(
        self,
        rays: RayBundle,
        cond: FrameCondition,
        *,
        background: Tensor | None = None,
        jitter: bool = False,
        generator: torch.Generator | None = None,
    ) -> RenderOutput:
        """Render camera rays ``(R,)`` through the layer for one frame, or for rays of several
        frames under a per-ray condition (:meth:`FrameCondition.of_rays`), with gradients.

        Args:
            rays: Camera-space rays ``(R,)``.
            cond: The frame's condition, or one per ray.
            background: Colour behind the layer ``(R, 3)``; ``None`` gives premultiplied colour.
            jitter: Random samples (training).
            generator: Random generator of the samples.
        """
        moved = self.to_space(self.warped(rays, cond), cond.pose)
        coarse, fine, per_ray = self._fields(cond)
        return self.renderer(moved.origins).render_rays(moved, coarse, fine, background=background, occupancy=self.occupied(), jitter=jitter, generator=generator, **per_ray)

    def render_hits(self, rays: RayBundle, cond: FrameCondition, chunk: int) -> tuple[Tensor, Composite | None]:
        """Render only the rays ``(R,)`` that cross the box, ``chunk`` at a time (no background).

        Returns:
            ``(hit (R,) bool, their composite or None when none hits)``.
        """
        moved = self.to_space(self.warped(rays, cond), cond.pose)
        renderer = self.renderer(moved.origins)
        near, far = renderer.coarse_sampler.bounds(moved)
        hit = far > near
        if not bool(hit.any()):
            return hit, None
        coarse, fine, per_ray = self._fields(cond)
        per_ray = {k: PerRay(v.value[hit]) for k, v in per_ray.items()}
        return hit, renderer.render_chunked(moved[hit], coarse, fine, chunk=chunk, occupancy=self.occupied(), **per_ray).final

    @torch.no_grad()
    def update_occupancy(self, cond: FrameCondition, *, decay: float = 0.7, dilation: int = 1, generator: torch.Generator | None = None) -> float:
        """Re-estimate the occupancy grid from the coarse and fine fields under one frame's condition.

        Each cell keeps ``max(decay * old, density)``, the density being the larger of the two
        fields' at a random point of the cell, so over many frames the grid holds the union of what
        the conditions (mouth shapes, poses) occupy; the occupied region is then grown by
        ``dilation`` cells, a margin for how the field changes until the next update.

        Returns:
            The occupied fraction of the cells (after dilation).

        Raises:
            ValueError: The layer has no grid.
        """
        if self.occupancy is None:
            raise ValueError(f"layer {self.name!r} has no occupancy grid (occupancy_resolution = 0)")
        if cond.per_ray:
            raise ValueError("the occupancy grid is estimated under one frame's condition; got a per-ray one")
        coarse, fine, _ = self._fields(cond)

        def density(points: Tensor) -> Tensor:
            dirs = torch.zeros_like(points)
            dirs[:, 2] = 1.0  # density does not depend on the view direction; some fields want one
            return torch.maximum(coarse(points, dirs).density, fine(points, dirs).density)

        self.occupancy.update(density, decay=decay, generator=generator)
        self.occupancy.dilate(dilation)
        return self.occupancy.occupied.float().mean().item()

    def extra_repr(self) -> str:
        warp = "" if self.warp is None else f", warp={self.warp!r}"
        return f"name={self.name!r}, space={self.space!r}, conditions={self.conditions}{warp}, samples={self.samples}"
