"""Random draws that follow the data's device, whatever device the generator lives on.

PyTorch refuses a generator of one device for a draw on another (a CPU ``torch.Generator`` for
``torch.rand(..., device="cuda")``). Training keeps one CPU generator (its state is checkpointed,
so a resumed run draws exactly what an uninterrupted one would, on any device): every draw that
takes a generator goes through :func:`uniform`, which draws where the generator is and moves the
numbers to where the data is. The same seed then gives the same samples on the CPU and on a GPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Shard", "uniform"]


@dataclass(frozen=True)
class Shard:
    """A generator whose draws are for a batch split over ``count`` processes along its first
    dimension: each process draws the whole batch's numbers and keeps its part ``index``, so the
    generators of all processes stay in step and the parts together are exactly the draw a single
    process makes (multi-process training, :mod:`adnerf.model.train`).

    A batch of several groups (the rays of several frames in one call) is split group by group:
    with ``groups``, the sizes of the whole batch's groups in order, each process keeps part
    ``index`` of every group, and its draw is those parts of the whole draw, in group order.

    Attributes:
        generator: The generator every process holds in the same state.
        index: This process's part (its rank).
        count: The number of parts (the world size).
        groups: The whole batch's group sizes (each divisible by ``count``); empty: one group.
    """

    generator: torch.Generator
    index: int
    count: int
    groups: tuple[int, ...] = ()

    @property
    def device(self) -> torch.device:
        return self.generator.device

    def rows(self, n: int) -> torch.Tensor | slice:
        """This process's rows of the whole batch's draw, for a part of ``n`` rows."""
        if not self.groups:
            return slice(self.index * n, (self.index + 1) * n)
        if sum(self.groups) != n * self.count or any(g % self.count for g in self.groups):
            raise ValueError(f"a part of {n} rows is not 1/{self.count} of each of the groups {self.groups}")
        rows, start = [], 0
        for g in self.groups:
            k = g // self.count
            rows.append(torch.arange(start + self.index * k, start + (self.index + 1) * k))
            start += g
        return torch.cat(rows)


def uniform(shape: tuple[int, ...] | torch.Size, *, dtype: torch.dtype, device: torch.device | str, generator: "torch.Generator | Shard | None" = None) -> torch.Tensor:
    """Uniform numbers in ``[0, 1)`` of ``shape`` and ``dtype`` on ``device``.

    Args:
        shape: Output shape.
        dtype: Output dtype (a floating type).
        device: Where the result lives (the data's device).
        generator: Optional generator (or :class:`Shard`); drawn on its own device, then moved to
            ``device``. Without one, the draw uses ``device``'s default generator.

    Returns:
        A tensor of ``shape`` on ``device``.
    """
    if generator is None:
        return torch.rand(shape, dtype=dtype, device=device)
    if isinstance(generator, Shard):
        n = shape[0]
        whole = torch.rand((n * generator.count, *shape[1:]), dtype=dtype, device=generator.device, generator=generator.generator)
        return whole[generator.rows(n)].to(device)
    return torch.rand(shape, dtype=dtype, device=generator.device, generator=generator).to(device)
