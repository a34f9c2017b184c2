"""Random draws that follow the data's device, whatever device the generator lives on.

PyTorch refuses a generator of one device for a draw on another (a CPU ``torch.Generator`` for
``torch.rand(..., device="cuda")``). Training keeps one CPU generator (its state is checkpointed,
so a resumed run draws exactly what an uninterrupted one would, on any device): every draw that
takes a generator goes through :func:`uniform`, which draws where the generator is and moves the
numbers to where the data is. The same seed then gives the same samples on the CPU and on a GPU.
"""

from __future__ import annotations

import torch

__all__ = ["uniform"]


def uniform(shape: tuple[int, ...] | torch.Size, *, dtype: torch.dtype, device: torch.device | str, generator: torch.Generator | None = None) -> torch.Tensor:
    """Uniform numbers in ``[0, 1)`` of ``shape`` and ``dtype`` on ``device``.

    Args:
        shape: Output shape.
        dtype: Output dtype (a floating type).
        device: Where the result lives (the data's device).
        generator: Optional generator; drawn on its own device, then moved to ``device``. Without
            one, the draw uses ``device``'s default generator.

    Returns:
        A tensor of ``shape`` on ``device``.
    """
    if generator is None:
        return torch.rand(shape, dtype=dtype, device=device)
    return torch.rand(shape, dtype=dtype, device=generator.device, generator=generator).to(device)
