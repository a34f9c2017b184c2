"""Training on several processes (``torchrun``): which process this is, and what they share.

Under ``torchrun --nproc_per_node N adnerf train DATA -o RUN`` every process runs the same
training loop. Each holds the same seeded CPU generator, so all pick the same frame and draw the
same batch of rays; each renders its contiguous ``1/N`` of the batch (:meth:`Ranks.part`) with
the sampler's random numbers drawn for the whole batch and sliced (:class:`adnerf.rng.Shard`),
so the processes' generators stay in step and their parts together are exactly what one process
would draw. A step of several frames is split frame by frame (each process renders its part of
every frame's rays, and the shard keeps those rows of the whole draw). Gradients are averaged over the processes before every optimiser step, which is the
gradient of the whole batch's mean loss: N processes train the same run one process would, up to
the order of floating-point sums. Process 0 writes ``run.json``, the log and the checkpoints.

Backends: ``gloo`` on the CPU, ``nccl`` on CUDA (process ``LOCAL_RANK`` on GPU ``LOCAL_RANK``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rng import Shard

__all__ = ["Ranks", "init_ranks"]


@dataclass(frozen=True)
class Ranks:
    """The processes training together; ``Ranks()`` is a single process.

    Attributes:
        rank: This process's index.
        world: The number of processes.
        backend: ``"gloo"`` or ``"nccl"``; ``None`` for a single process.
        device: Where the tensors of collectives live: the process's GPU under ``nccl``, which
            refuses CPU tensors; the CPU under ``gloo``.
    """

    rank: int = 0
    world: int = 1
    backend: str | None = None
    device: str = "cpu"

    @property
    def main(self) -> bool:
        """Whether this process writes the run's files."""
        return self.rank == 0

    def part(self, batch: Tensor) -> Tensor:
        """This process's contiguous part of a batch whose length the world size divides."""
        n = len(batch) // self.world
        return batch[self.rank * n : (self.rank + 1) * n]

    def shard(self, generator: torch.Generator, groups: tuple[int, ...] = ()) -> "torch.Generator | Shard":
        """``generator`` for draws over a batch split as :meth:`part` splits it, or, for a batch of
        groups of sizes ``groups``, as :meth:`part` splits each group."""
        return generator if self.world == 1 else Shard(generator, self.rank, self.world, groups)

    def barrier(self) -> None:
        if self.world > 1:
            torch.distributed.barrier()

    def mean(self, values: list[float]) -> list[float]:
        """The mean of each value over the processes."""
        if self.world == 1:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(t)
        return (t / self.world).tolist()

    def gather(self, value: object) -> list:
        """Every process's ``value``, in rank order."""
        if self.world == 1:
            return [value]
        out: list = [None] * self.world
        torch.distributed.all_gather_object(out, value)
        return out

    def average_gradients(self, params: list[torch.nn.Parameter]) -> bool:
        """Replace each gradient by its mean over the processes (a process without one counts
        zero; a parameter without a gradient anywhere keeps none, as one process would leave it).
        Returns whether any process had a gradient (else no optimiser step is due)."""
        if self.world == 1:
            return any(p.grad is not None for p in params)
        device = params[0].device
        has = torch.tensor([float(p.grad is not None) for p in params], device=device)
        torch.distributed.all_reduce(has)
        used = [p for p, h in zip(params, has.tolist()) if h > 0]
        if not used:
            return False
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1).float() for p in used])
        torch.distributed.all_reduce(flat)
        flat /= self.world
        offset = 0
        for p in used:
            n = p.numel()
            p.grad = flat[offset : offset + n].view_as(p).to(p.dtype)
            offset += n
        return True


def init_ranks(device: str) -> tuple[Ranks, str]:
    """The processes of this run and this process's device: from ``torchrun``'s environment
    (``WORLD_SIZE`` > 1 starts the process group if nobody has), else a single process.

    Returns:
        ``(ranks, device)``; on CUDA the device becomes ``cuda:LOCAL_RANK``.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Ranks(), device
    cuda = device.startswith("cuda")
    if cuda:  # before the process group: NCCL's communicators and all_gather_object use the current GPU
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if cuda else "gloo")
    backend = torch.distributed.get_backend()
    return Ranks(torch.distributed.get_rank(), torch.distributed.get_world_size(), backend, device if backend == "nccl" else "cpu"), device
