"""A patch of rays at the mouth and its structural loss (``TrainConfig.lip_patch``).

Stage 1's photometric loss is a mean squared error per ray. Where the audio code leaves the mouth's
state uncertain (a vowel half open, the teeth sometimes shown), the colour that minimises it is
the mean of the states: a soft, half-closed mouth. A loss on a *patch* can ask for what a mean
lacks: the structural similarity (SSIM) of a ``size x size`` grid of rays about the mouth to the
frame's pixels scores the patch's contrast and structure as well as its colours, so a blurred
mouth scores worse than a sharp one of the wrong shape would under the squared error alone.

The patch replaces ``size ** 2`` of a frame's random mouth rays (the mouth's share of the batch is
unchanged): it is the last ``size ** 2`` pixels of the frame's rays, row-major. Its rays are
``stride`` pixels apart, ``stride`` chosen so that the patch spans about ``PATCH_SPAN`` of the side
of the mouth square (``MOUTH_CROP`` scene units, which holds the chin and the cheeks too), and it
lies at a random place inside the square's central ``PATCH_REGION`` (clipped to the image) at
every draw, so over a run it covers the lips at about the frame's own detail.
"""

from __future__ import annotations

import math

import torch
from kornia.metrics import ssim

SSIM_WINDOW = 7
"""Taps of the SSIM window (kornia's Gaussian of sigma 1.5): +-2 sigma."""
MIN_PATCH = SSIM_WINDOW + 1
"""The smallest patch side in rays: the window fits inside with room for one step."""
PATCH_SPAN = 0.25
"""The patch's side as a fraction of the mouth square's (about the lips' width)."""
PATCH_REGION = 0.5
"""The patch lies in the central square of this fraction of the mouth square's side."""


def patch_stride(side_px: float, size: int) -> int:
    """Pixels between the rays of a ``size``-ray patch side that spans about ``PATCH_SPAN`` of a
    mouth square of side ``side_px`` pixels (at least 1)."""
    return max(1, int(round(PATCH_SPAN * side_px / size)))


def patch_pixels(centre: tuple[float, float], side_px: float, size: int, width: int, height: int, generator: torch.Generator, device: torch.device | str = "cpu") -> torch.Tensor:
    """Flat pixel indices ``(size ** 2,)`` int64 of a patch in the square about the mouth.

    Args:
        centre: The mouth's projection ``(u, v)`` in pixels (column, row; pixel centres at +0.5).
        side_px: The mouth square's side in pixels (``MOUTH_CROP`` scene units).
        size: Rays a side of the patch.
        width: Image width in pixels.
        height: Image height in pixels.
        generator: CPU generator of the patch's place (two draws).
        device: Where the indices go.

    Returns:
        Row-major indices ``row * width + col``: entry ``i * size + j`` is the pixel of the
        patch's row ``i`` and column ``j``, ``stride`` (:func:`patch_stride`) pixels apart. The
        patch lies in the image, and in the square's central ``PATCH_REGION`` wherever that
        holds it (else centred on it).
    """
    stride = patch_stride(side_px, size)
    span = (size - 1) * stride + 1
    if span > width or span > height:
        raise ValueError(f"a lip patch of {size} rays {stride} px apart spans {span} px, more than the {width}x{height} image")
    half = 0.5 * PATCH_REGION * side_px
    corners = []
    for c, limit in zip(centre, (width, height)):
        lo = math.ceil(c - half - 0.5)  # first pixel whose centre is in the region
        hi = math.floor(c + half - 0.5) - span + 1  # last corner whose patch ends in it
        lo, hi = min(max(lo, 0), limit - span), min(max(hi, 0), limit - span)
        if hi < lo:  # the region is narrower than the patch: centre the patch on it
            lo = hi = min(max(int(round(c - 0.5 * span)), 0), limit - span)
        corners.append(lo + int(torch.randint(hi - lo + 1, (1,), generator=generator)))
    col0, row0 = corners
    steps = torch.arange(size, device=device) * stride
    return ((row0 + steps)[:, None] * width + (col0 + steps)[None, :]).reshape(-1)


def patch_loss(render: torch.Tensor, target: torch.Tensor, size: int) -> torch.Tensor:
    """Mean of ``1 - SSIM`` over patches of rays.

    Args:
        render: Rendered colours ``(G * size ** 2, 3)`` of ``G`` patches, each row-major
            (:func:`patch_pixels`), in [0, 1].
        target: The frames' colours at the same rays ``(G * size ** 2, 3)``.
        size: Rays a side of each patch.

    Returns:
        A scalar in [0, 2]: 0 where every patch equals its target. Computed in float32 (or the
        inputs' wider float).
    """
    dtype = torch.promote_types(render.dtype, torch.float32)

    def images(x: torch.Tensor) -> torch.Tensor:
        return x.to(dtype).reshape(-1, size, size, 3).permute(0, 3, 1, 2)

    return (1.0 - ssim(images(render), images(target), SSIM_WINDOW, max_val=1.0)).mean()
