"""The volume renderer: sampler + field + compositor, composed; it does not own the field.

A *field* is any callable ``field(positions, directions, **conditioning) -> FieldOutput`` with
positions and directions of shape ``(..., 3)`` (a :class:`~adnerf.fields.RadianceField`, an
analytic scene of :mod:`adnerf.analytic`, or any function). A
:class:`~adnerf.model.layers.RadianceLayer` builds one renderer per layer and moves the rays into
the layer's space before calling it. The conditioning (audio code, head pose, ...) is passed to :meth:`VolumeRenderer.render_rays`
as keyword arguments and forwarded to every field call. A value shared by all rays (per-frame
conditioning, the AD-NeRF setting) is forwarded unchanged and must broadcast against any batch of
points; a value wrapped in :class:`PerRay` differs between rays (rays of several frames rendered in
one call) and each field call gets the rows of the samples it evaluates.

Passes: a coarse pass of stratified intervals; optionally a fine pass that adds importance
samples drawn from the coarse weights (NeRF's hierarchical sampling) and evaluates a fine field
(or the coarse one again) on the merged intervals. With an occupancy predicate, samples in empty
space are not evaluated at all: the field sees only the packed occupied samples.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable, Protocol

import torch
from torch import Tensor

from .compositor import Composite, composite
from .fields import FieldOutput, SampleRows
from .rays import RayBundle, RaySamples
from .samplers import Bounds, ImportanceSampler, StratifiedSampler

__all__ = ["Field", "PerRay", "RenderOutput", "VolumeRenderer"]


class Field(Protocol):
    """What the renderer calls: ``(positions (..., 3), directions (..., 3), **conditioning) -> FieldOutput``."""

    def __call__(self, positions: Tensor, directions: Tensor, **conditioning: Any) -> FieldOutput: ...


Occupancy = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class PerRay:
    """A conditioning value that differs between rays: ``value (..., C)`` over the rays' batch
    shape ``(...)``.

    The renderer hands a field call :class:`~adnerf.fields.SampleRows`: the rays' values ``(R,
    C)`` and the ray of each sample it evaluates, ``(..., S)`` for every sample or ``(M,)`` for
    the ``M`` occupied samples that empty-space skipping packs.
    """

    value: Tensor

    def at_samples(self, shape: torch.Size, mask: Tensor | None) -> SampleRows:
        """The value at samples of shape ``(..., S)`` (the rays' batch shape, then samples per
        ray), or at the samples ``mask (..., S)`` selects."""
        if self.value.shape[:-1] != shape[:-1]:
            raise ValueError(f"a per-ray conditioning value must have the rays' batch shape {tuple(shape[:-1])}; got {tuple(self.value.shape)}")
        rays = shape[:-1].numel()
        ray = torch.arange(rays, device=self.value.device).reshape(*shape[:-1], 1).expand(shape)
        return SampleRows(self.value.reshape(rays, self.value.shape[-1]), ray if mask is None else ray[mask])


def _at_samples(conditioning: dict[str, Any], shape: torch.Size, mask: Tensor | None) -> dict[str, Any]:
    """Conditioning for a field call on samples of shape ``shape`` (``mask``: those evaluated)."""
    return {k: v.at_samples(shape, mask) if isinstance(v, PerRay) else v for k, v in conditioning.items()}


@dataclass
class RenderOutput:
    """Result of rendering a batch of rays.

    Attributes:
        coarse: The coarse pass.
        fine: The fine pass, or ``None`` when the renderer is coarse-only.
        samples_evaluated: Number of field evaluations performed (after occupancy skipping).
    """

    coarse: Composite
    fine: Composite | None
    samples_evaluated: int = 0

    @property
    def final(self) -> Composite:
        """The best available pass (fine if present, else coarse)."""
        return self.fine if self.fine is not None else self.coarse


def evaluate_field(field: Field, samples: RaySamples, occupancy: Occupancy | None, conditioning: dict[str, Any]) -> tuple[Tensor, Tensor, int]:
    """Evaluate ``field`` at the midpoints of ``samples``.

    Returns:
        ``(rgb (..., S, 3), density (..., S), n_evaluated)``. With ``occupancy``, samples in empty
        space and zero-length samples are not evaluated and get density 0 and colour 0. A field
        run under mixed-precision autocast returns half-precision values; they are returned in
        float32, so transmittance and weights are always accumulated in at least float32.
    """
    positions = samples.positions()
    directions = samples.directions()
    shape = samples.t_starts.shape
    if occupancy is None:
        out = field(positions, directions, **_at_samples(conditioning, shape, None))
        return _full(out.rgb), _full(out.density), positions.shape[:-1].numel()
    mask = occupancy(positions) & (samples.deltas > 0)
    n = int(mask.sum())
    if n == 0:
        param_dtype = _field_dtype(field, positions.dtype)
        return (
            torch.zeros(*shape, 3, dtype=param_dtype, device=positions.device),
            torch.zeros(shape, dtype=param_dtype, device=positions.device),
            0,
        )
    out = field(positions[mask], directions[mask], **_at_samples(conditioning, shape, mask))
    out_rgb, out_density = _full(out.rgb), _full(out.density)
    rgb = torch.zeros(*shape, 3, dtype=out_rgb.dtype, device=out_rgb.device).index_put((mask,), out_rgb)
    density = torch.zeros(shape, dtype=out_density.dtype, device=out_density.device).index_put((mask,), out_density)
    return rgb, density, n


def _full(x: Tensor) -> Tensor:
    """Half-precision field outputs (under autocast) go to the compositor in float32."""
    return x.float() if x.dtype in (torch.float16, torch.bfloat16) else x


def _field_dtype(field: Field, default: torch.dtype) -> torch.dtype:
    params = getattr(field, "parameters", None)
    if params is None:
        return default
    first = next(iter(params()), None)
    return first.dtype if first is not None else default


def _cat(parts: list[Composite]) -> Composite:
    return Composite(**{f.name: torch.cat([getattr(p, f.name) for p in parts], dim=0) for f in fields(Composite)})


class VolumeRenderer:
    """Hierarchical volume rendering of radiance fields.

    Args:
        bounds: Per-ray ``[near, far]`` (see :mod:`adnerf.samplers`).
        n_coarse: Stratified intervals per ray (paper: 64).
        n_fine: Importance samples per ray added in the fine pass (paper: 128); 0 disables the
            fine pass.
    """

    def __init__(self, bounds: Bounds, n_coarse: int = 64, n_fine: int = 128) -> None:
        if n_fine < 0:
            raise ValueError(f"n_fine must be >= 0; got {n_fine}")
        self.coarse_sampler = StratifiedSampler(n_coarse, bounds)
        self.fine_sampler = ImportanceSampler(n_fine) if n_fine > 0 else None

    def render_rays(
        self,
        rays: RayBundle,
        field: Field,
        fine_field: Field | None = None,
        *,
        background: Tensor | None = None,
        occupancy: Occupancy | None = None,
        jitter: bool = False,
        generator: torch.Generator | None = None,
        **conditioning: Any,
    ) -> RenderOutput:
        """Render a batch of rays.

        Args:
            rays: Rays of batch shape ``(...)``.
            field: The coarse field (also used for the fine pass when ``fine_field`` is None).
            fine_field: The fine field of the fine pass.
            background: Colour behind the samples, ``(..., 3)`` or ``(3,)``; ``None`` is black
                (premultiplied output, ready for :func:`~adnerf.compositor.over`).
            occupancy: Predicate on sample positions ``(..., 3) -> bool (...)``; samples where it
                is False are skipped.
            jitter: Jitter the stratified intervals and draw random importance samples
                (training); deterministic otherwise.
            generator: Optional random generator.
            **conditioning: Forwarded to every field call (e.g. ``audio=code, pose=pose``);
                :class:`PerRay` values ``(..., C)`` as the rows of the samples evaluated.

        Returns:
            A :class:`RenderOutput`.

        Example:
            >>> from adnerf.analytic import UniformSphere
            >>> from adnerf.cameras import intrinsics_matrix, pixel_rays
            >>> from adnerf.samplers import NearFarBounds
            >>> sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), 1.0, 10.0)
            >>> rays = pixel_rays(intrinsics_matrix(16.0, 16.0, 8.0, 8.0), 16, 16)
            >>> out = VolumeRenderer(NearFarBounds(1.0, 5.0), n_coarse=64, n_fine=64).render_rays(rays, sphere)
            >>> opacity, depth, hit = sphere.truth(rays.origins, rays.directions)  # closed form
            >>> bool((out.final.opacity - opacity).abs().max() < 0.01), bool((out.final.depth - depth)[hit].abs().max() < 0.01)
            (True, True)
        """
        coarse_samples = self.coarse_sampler(rays, jitter=jitter, generator=generator)
        rgb, density, n_eval = evaluate_field(field, coarse_samples, occupancy, conditioning)
        coarse = composite(rgb, density, coarse_samples.t_starts, coarse_samples.t_ends, background)
        if self.fine_sampler is None:
            return RenderOutput(coarse, None, n_eval)
        fine_samples = self.fine_sampler(coarse_samples, coarse.weights, deterministic=not jitter, generator=generator)
        rgb, density, n_fine = evaluate_field(fine_field or field, fine_samples, occupancy, conditioning)
        fine = composite(rgb, density, fine_samples.t_starts, fine_samples.t_ends, background)
        return RenderOutput(coarse, fine, n_eval + n_fine)

    def render_chunked(
        self,
        rays: RayBundle,
        field: Field,
        fine_field: Field | None = None,
        *,
        chunk: int = 8192,
        background: Tensor | None = None,
        occupancy: Occupancy | None = None,
        **conditioning: Any,
    ) -> RenderOutput:
        """Render any number of rays in chunks of ``chunk`` rays (bounded memory, deterministic).

        Rays of batch shape ``(...)`` (e.g. a whole image ``(H, W)``) are flattened, rendered in
        chunks and reshaped back: every output has the batch shape ``(...)`` of ``rays``. A
        per-ray ``background`` ``(..., 3)`` and :class:`PerRay` conditioning are chunked along
        with the rays.
        """
        if chunk < 1:
            raise ValueError(f"chunk must be >= 1; got {chunk}")
        batch = rays.shape
        flat = rays.flatten()
        n = flat.origins.shape[0]
        bg = None
        if background is not None:
            bg = background.expand(*batch, background.shape[-1]).reshape(n, background.shape[-1])
        for key, v in conditioning.items():
            if isinstance(v, PerRay):
                if v.value.shape[:-1] != batch:
                    raise ValueError(f"per-ray conditioning {key!r} must have the rays' batch shape {tuple(batch)}; got {tuple(v.value.shape)}")
                conditioning[key] = PerRay(v.value.reshape(n, v.value.shape[-1]))
        coarse_parts: list[Composite] = []
        fine_parts: list[Composite] = []
        evaluated = 0
        for start in range(0, max(n, 1), chunk):  # one (empty) chunk for zero rays
            sl = slice(start, start + chunk)
            here = {k: PerRay(v.value[sl]) if isinstance(v, PerRay) else v for k, v in conditioning.items()}
            out = self.render_rays(flat[sl], field, fine_field, background=None if bg is None else bg[sl], occupancy=occupancy, **here)
            coarse_parts.append(out.coarse)
            if out.fine is not None:
                fine_parts.append(out.fine)
            evaluated += out.samples_evaluated

        def reshape(c: Composite) -> Composite:
            return Composite(**{f.name: getattr(c, f.name).reshape(*batch, *getattr(c, f.name).shape[1:]) for f in fields(Composite)})

        coarse = reshape(_cat(coarse_parts))
        fine = reshape(_cat(fine_parts)) if fine_parts else None
        return RenderOutput(coarse, fine, evaluated)
