"""Volume rendering: from per-sample density and colour to pixels.

Numerics (all in log space, no epsilon inside products):

* optical depth of interval ``i``: ``tau_i = sigma_i * delta_i``;
* opacity of interval ``i``: ``alpha_i = 1 - exp(-tau_i)``, computed as ``-expm1(-tau_i)`` so that
  tiny ``tau`` keeps its digits;
* transmittance up to interval ``i``: ``T_i = exp(-sum_{j<i} tau_j)`` from an *exclusive* prefix sum
  (not a cumulative product of ``1 - alpha`` clamped by an epsilon);
* weight ``w_i = T_i * alpha_i``; residual transmittance ``T_S = exp(-sum_j tau_j)``;
* colours are premultiplied: ``rgb = sum_i w_i c_i + T_S * background``. AD-NeRF's "the last
  sample is the background pixel" is this same residual term.

Densities must be finite and non-negative, interval lengths non-negative. Rays with no samples,
with empty intervals or with zero density are valid: they get zero weights, opacity 0 and the
background colour.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import torch
from torch import Tensor

__all__ = ["Composite", "Layer", "composite", "composite_layers", "over", "render_weights"]


def render_weights(densities: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Volume-rendering weights and residual transmittance.

    Args:
        densities: Non-negative densities ``sigma``, shape ``(..., S)`` (1 / scene unit).
        deltas: Interval lengths, shape ``(..., S)`` (scene units), broadcastable with
            ``densities``.

    Returns:
        ``(weights, residual_transmittance)`` with shapes ``(..., S)`` and ``(...)``. The weights
        sum to ``1 - residual_transmittance`` up to rounding.

    Example:
        >>> import math
        >>> weights, residual = render_weights(torch.ones(1, 3), torch.full((1, 3), math.log(2.0)))
        >>> weights  # each interval stops half of the light that reaches it
        tensor([[0.5000, 0.2500, 0.1250]])
        >>> residual
        tensor([0.1250])
    """
    tau = densities * deltas
    inclusive = torch.cumsum(tau, dim=-1)
    exclusive = torch.cat([torch.zeros_like(tau[..., :1]), inclusive[..., :-1]], dim=-1)
    alpha = -torch.expm1(-tau)
    weights = torch.exp(-exclusive) * alpha
    residual = torch.exp(-tau.sum(dim=-1))
    return weights, residual


@dataclass
class Composite:
    """Result of compositing the samples of a batch of rays.

    Attributes:
        rgb: Colour ``(..., C)``: premultiplied sample colours plus the residual transmittance
            times the background (background black when none was given).
        opacity: Accumulated opacity ``1 - T_S`` in ``[0, 1]``, shape ``(...)``.
        depth: Expected termination distance given that the ray terminates inside the samples,
            ``sum_i w_i t_mid_i / opacity``, shape ``(...)``. Rays with zero opacity report the
            end of their last interval (or 0 when they have no samples).
        weights: Per-sample weights ``(..., S)``.
        residual_transmittance: ``T_S = 1 - opacity``, shape ``(...)``.
    """

    rgb: Tensor
    opacity: Tensor
    depth: Tensor
    weights: Tensor
    residual_transmittance: Tensor


def composite(
    colors: Tensor,
    densities: Tensor,
    t_starts: Tensor,
    t_ends: Tensor,
    background: Tensor | None = None,
) -> Composite:
    """Composite samples along rays into pixels.

    Args:
        colors: Sample colours (or any features), shape ``(..., S, C)``.
        densities: Densities, shape ``(..., S)``.
        t_starts: Interval starts along the ray, shape ``(..., S)``.
        t_ends: Interval ends, shape ``(..., S)``.
        background: Colour behind the samples, shape ``(..., C)`` or ``(C,)``; ``None`` is black
            (the returned colour is then premultiplied and can be layered with :func:`over`).

    Returns:
        A :class:`Composite` in the promoted dtype of the inputs (float64 intervals with
        float32 field outputs composite in float64).

    Example:
        >>> colors = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])  # a red sample, then a green one
        >>> densities = torch.tensor([[1e9, 1e9]])  # the first is opaque
        >>> t0, t1 = torch.tensor([[1.0, 2.0]]), torch.tensor([[2.0, 3.0]])
        >>> out = composite(colors, densities, t0, t1, background=torch.tensor([0.0, 0.0, 1.0]))
        >>> out.rgb, out.opacity, out.depth
        (tensor([[1., 0., 0.]]), tensor([1.]), tensor([1.5000]))
        >>> composite(colors, torch.zeros(1, 2), t0, t1, background=torch.tensor([0.0, 0.0, 1.0])).rgb  # empty ray: the background
        tensor([[0., 0., 1.]])
    """
    if colors.shape[:-1] != densities.shape:
        raise ValueError(f"colors (..., S, C) and densities (..., S) disagree: {tuple(colors.shape)} vs {tuple(densities.shape)}")
    deltas = t_ends - t_starts
    weights, residual = render_weights(densities, deltas)
    total_tau = (densities * deltas).sum(dim=-1)
    opacity = -torch.expm1(-total_tau)
    rgb = torch.einsum("...s,...sc->...c", weights, colors.to(weights.dtype))
    if background is not None:
        rgb = rgb + residual[..., None] * background
    t_mids = 0.5 * (t_starts + t_ends)
    weighted_t = (weights * t_mids).sum(dim=-1)
    hit = opacity > 0
    if t_ends.shape[-1] > 0:
        fallback = t_ends[..., -1].expand_as(opacity)
    else:
        fallback = torch.zeros_like(opacity)
    safe_opacity = torch.where(hit, opacity, torch.ones_like(opacity))
    depth = torch.where(hit, weighted_t / safe_opacity, fallback)
    return Composite(rgb=rgb, opacity=opacity, depth=depth, weights=weights, residual_transmittance=residual)


class _HasLayer(Protocol):
    rgb: Tensor
    opacity: Tensor


@dataclass
class Layer:
    """A premultiplied image layer.

    Attributes:
        rgb: Premultiplied colour ``(..., C)``.
        opacity: Opacity ``(...)`` in ``[0, 1]``.
    """

    rgb: Tensor
    opacity: Tensor

    @staticmethod
    def opaque(rgb: Tensor) -> "Layer":
        """A fully opaque layer, e.g. a background plate ``(..., C)``."""
        return Layer(rgb, torch.ones_like(rgb[..., 0]))


def over(front: _HasLayer, back: _HasLayer) -> Layer:
    """Porter-Duff ``over`` for premultiplied layers.

    ``rgb = rgb_f + (1 - a_f) rgb_b`` and ``a = a_f + (1 - a_f) a_b``. Any objects with ``rgb``
    ``(..., C)`` and ``opacity`` ``(...)`` work, e.g. a background-free :class:`Composite`.

    Example:
        >>> front = Layer(torch.tensor([0.5, 0.0, 0.0]), torch.tensor(0.5))  # half-transparent red, premultiplied
        >>> over(front, Layer.opaque(torch.tensor([0.0, 0.0, 1.0])))
        Layer(rgb=tensor([0.5000, 0.0000, 0.5000]), opacity=tensor(1.))
    """
    keep = 1.0 - front.opacity
    return Layer(front.rgb + keep[..., None] * back.rgb, front.opacity + keep * back.opacity)


def composite_layers(layers: Sequence[_HasLayer], background: Tensor | None = None) -> Layer:
    """Stack premultiplied layers front to back with :func:`over`, then an optional background.

    Args:
        layers: Layers ordered front first (e.g. ``[head, torso]`` or ``[torso, head]``: the
            head/torso order is the caller's choice).
        background: Opaque background colour ``(..., C)``; ``None`` leaves the result's
            opacity as accumulated.

    Returns:
        The composed :class:`Layer`.
    """
    if not layers:
        raise ValueError("composite_layers needs at least one layer")
    out: _HasLayer = layers[0]
    for layer in layers[1:]:
        out = over(out, layer)
    if background is not None:
        out = over(out, Layer.opaque(background.expand_as(out.rgb)))
    return Layer(out.rgb, out.opacity)
